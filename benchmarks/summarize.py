"""One experiment's output folder summarized into a small JSON file under docs/results/data/.

Reads the ``<name>.json`` and ``<name>.csv`` that ``torch_api.experiment.results.write_results``
writes (the CSV in long format: schedule, method, seed, iteration, trial, measure, value) and
writes ``docs/results/data/<id>.json``: per schedule and measure, AL and PL at the last iteration
(mean, s.e., trials), their paired difference (mean, s.e., t, p, 95 % interval from the t
quantile), the per-iteration means, the transitions bought, each method's seconds, and a verdict
computed by :func:`verdict` — never typed by hand. The command, the commit of the code that ran
(``git rev-parse HEAD``, ``+dirty`` when tracked files differed) and the machine come with it.

    python -m benchmarks.summarize OUT_DIR --id figure8 --title "…" --task "chain walk" \\
        --measure test_return --command "python examples/chain_walk_api.py --trials 1000"

With ``--run -- ARGV…`` it first runs ARGV itself (in ``--repo``), so that the machine's load
is measured just before and just after the run; otherwise the load is measured when summarizing
and the data file says so. ``python -m benchmarks.report`` turns the data files into the
results pages.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import numpy as np
import scipy.stats

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = ROOT / "docs" / "results" / "data"
ALPHA = 0.05
"""The two-tailed level of every verdict."""
VERDICTS = ("AL better", "no difference found", "PL better")
"""Every verdict :func:`verdict` can give, in the report's order (where AL pays first)."""
TRANSITIONS = ("rewarded_transitions", "reward_free_transitions")


def verdict(difference: float, p: float | None, better: str = "higher") -> str:
    """The fixed rule: AL better if p < 0.05 and AL - PL points the better way, PL better if
    p < 0.05 and it points the other way, else no difference found (also where the test is
    undefined: every pair identical, or a single pair)."""
    if p is None or not p < ALPHA or difference == 0:
        return VERDICTS[1]
    al_ahead = difference > 0 if better == "higher" else difference < 0
    return VERDICTS[0] if al_ahead else VERDICTS[2]


def read_table(path: Path, measures: set[str]) -> dict[tuple, list]:
    """The CSV as ``torch_api.experiment.results.read_results`` reads it, ``{(schedule,
    method, iteration, measure): [value of trial 0, 1, …]}``, but only for ``measures`` (and
    without importing torch)."""
    table: dict[tuple, list] = {}
    with path.open(newline="") as handle:
        for row in csv.DictReader(handle):
            if row["measure"] not in measures:
                continue
            key = (row["schedule"], row["method"], int(row["iteration"]), row["measure"])
            value = row["value"]
            table.setdefault(key, []).append(int(value) if value.isdigit() else float(value))
    return table


def _mean_se(values) -> dict:
    x = np.asarray(values, dtype=np.float64)
    se = float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else None
    return {"mean": float(x.mean()), "se": se, "trials": int(x.size)}


def paired_difference(al, pl) -> dict:
    """AL - PL over paired trials: mean, s.e., the two-tailed paired t-test (scipy) and the
    95 % interval mean ± t_{0.975, n-1} · s.e.; t, p and the interval are None where the test
    is undefined (one pair, or the same difference in every pair)."""
    a, b = np.asarray(al, dtype=np.float64), np.asarray(pl, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"AL has {a.size} trials, PL {b.size}: not paired")
    d = a - b
    out = _mean_se(d)
    out.update(t=None, p=None, ci95_low=None, ci95_high=None)
    if d.size > 1 and not np.all(d == d[0]):
        test = scipy.stats.ttest_rel(a, b)
        half = float(scipy.stats.t.ppf(1 - ALPHA / 2, d.size - 1)) * out["se"]
        out.update(
            t=float(test.statistic),
            p=float(test.pvalue),
            ci95_low=out["mean"] - half,
            ci95_high=out["mean"] + half,
        )
    out["al_better_share"] = float((a > b).mean())
    out["al_worse_share"] = float((a < b).mean())
    return out


def summary_rows(table: dict, run: dict, measures: list[str], better: str) -> list[dict]:
    """One row per (schedule, measure) at the schedule's last iteration."""
    rows = []
    for schedule in sorted({k[0] for k in table}):
        runs = run.get("summary", {}).get(schedule, {}).get("runs", {})
        for measure in measures:
            its = sorted({k[2] for k in table if k[0] == schedule and k[3] == measure})
            if not its:
                continue
            last = its[-1]
            al, pl = table[(schedule, "AL", last, measure)], table[(schedule, "PL", last, measure)]
            diff = paired_difference(al, pl)
            row = {
                "schedule": schedule,
                "measure": measure,
                "iteration": last,
                "al": _mean_se(al),
                "pl": _mean_se(pl),
                "difference": diff,
                "verdict": verdict(diff["mean"], diff["p"], better),
                "per_iteration": {
                    "iterations": its,
                    **{
                        m: [float(np.mean(table[(schedule, m, i, measure)])) for i in its]
                        for m in ("AL", "PL")
                    },
                },
            }
            for name in TRANSITIONS:
                values = {
                    m: table.get((schedule, m, last, name)) for m in ("AL", "PL")
                }  # cumulative: the last iteration's count is the run's
                if all(values.values()):
                    row[name] = {m: float(np.mean(v)) for m, v in values.items()}
            seconds = {m: runs[m]["seconds"] for m in ("AL", "PL") if "seconds" in runs.get(m, {})}
            if seconds:
                row["seconds"] = seconds
            rows.append(row)
    return rows


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(repo), *args], capture_output=True, text=True, check=True
    ).stdout.strip()


def commit_of(repo: Path) -> str:
    """HEAD of ``repo``, with ``+dirty`` where a tracked file differs from it."""
    head = _git(repo, "rev-parse", "HEAD")
    dirty = _git(repo, "status", "--porcelain", "--untracked-files=no")
    return head + ("+dirty" if dirty else "")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def machine(load_start, load_end, measured: str) -> dict:
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "load": {
            "start": [round(x, 2) for x in load_start],
            "end": [round(x, 2) for x in load_end],
        },
        "load_measured": measured,
        "python": platform.python_version(),
        "torch": _version("torch"),
    }


def _results_name(folder: Path, name: str | None) -> str:
    if name:
        return name
    stems = sorted(p.stem for p in folder.glob("*.json") if (folder / f"{p.stem}.csv").exists())
    if len(stems) != 1:
        raise SystemExit(
            f"{folder}: give --name, one of {stems}" if stems else f"{folder}: no results"
        )
    return stems[0]


def summarize(folder: Path, options: argparse.Namespace, machine_record: dict) -> dict:
    """The data file's payload for the experiment in ``folder``."""
    name = _results_name(folder, options.name)
    run = json.loads((folder / f"{name}.json").read_text())
    measures = list(dict.fromkeys(options.measure))
    table = read_table(folder / f"{name}.csv", {*measures, *TRANSITIONS})
    missing = [m for m in measures if not any(k[3] == m for k in table)]
    if missing == measures or (missing and not options.skip_missing):
        raise SystemExit(f"{folder / name}.csv has no measure {missing}")
    measures = [m for m in measures if m not in missing]
    written = datetime.fromtimestamp((folder / f"{name}.json").stat().st_mtime, timezone.utc)
    args = {k: v for k, v in run.get("args", {}).items() if k != "out_dir"}
    payload = {
        "experiment": options.id,
        "title": options.title,
        "task": options.task or options.title,
        "command": options.command,
        "commit": commit_of(options.repo),
        "date": written.replace(microsecond=0).isoformat().replace("+00:00", "Z"),
        "machine": machine_record,
        "wall_seconds": run.get("wall_seconds"),
        "measures": measures,
        "better": options.better,
        "digits": options.digits,
        "args": args,
        "rows": summary_rows(table, run, measures, options.better),
    }
    for key in ("code", "note"):
        if getattr(options, key):
            payload[key] = getattr(options, key)
    if options.executed:  # what ran, and its wall time with start-up, as --run measured it
        payload["executed"] = options.executed
        payload["executed_seconds"] = options.executed_seconds
    return payload


def parse(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    run_argv: list[str] = []
    if "--" in argv:
        at = argv.index("--")
        argv, run_argv = argv[:at], argv[at + 1 :]
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.summarize", description=__doc__.split("\n")[0]
    )
    p.add_argument("folder", type=Path, help="the experiment's --out-dir")
    p.add_argument("--id", required=True, help="short experiment id, the data file's name")
    p.add_argument("--title", required=True, help="the results page's heading")
    p.add_argument("--task", default="", help="the headline table's task column (default: title)")
    p.add_argument("--measure", action="append", required=True, help="first: the headline's")
    p.add_argument("--command", required=True, help="the command that made the folder")
    p.add_argument("--repo", type=Path, default=ROOT, help="the checkout that ran (commit)")
    p.add_argument("--code", default="", help="a note on the code that ran")
    p.add_argument("--note", default="", help="a note printed with the experiment")
    p.add_argument("--name", default="", help="<name>.json/.csv (default: the only pair)")
    p.add_argument("--better", choices=("higher", "lower"), default="higher")
    p.add_argument("--digits", type=int, default=3, help="decimals in the report's tables")
    p.add_argument("--skip-missing", action="store_true", help="drop measures not in the CSV")
    p.add_argument("--data-dir", type=Path, default=DATA_DIR)
    p.add_argument(
        "--run",
        action="store_true",
        help="first run the command after -- in --repo, measuring the load around it",
    )
    options = p.parse_args(argv)
    if options.run != bool(run_argv):
        p.error("--run needs the command to run after --, and that command needs --run")
    options.executed = shlex.join(run_argv) if run_argv else ""
    options.executed_seconds = None
    return options, run_argv


def main(argv: list[str] | None = None) -> int:
    options, run_argv = parse(sys.argv[1:] if argv is None else argv)
    if run_argv:
        load_start = os.getloadavg()
        started = time.perf_counter()
        subprocess.run(run_argv, cwd=options.repo, check=True)
        options.executed_seconds = round(time.perf_counter() - started, 1)
        record = machine(load_start, os.getloadavg(), "just before and just after the run")
    else:
        load = os.getloadavg()
        record = machine(load, load, "when summarized, not during the run")
    payload = summarize(options.folder, options, record)
    options.data_dir.mkdir(parents=True, exist_ok=True)
    out = options.data_dir / f"{options.id}.json"
    out.write_text(json.dumps(payload, indent=1, sort_keys=False) + "\n")
    print(f"wrote {out} ({out.stat().st_size:,} bytes, {len(payload['rows'])} rows)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
