"""Merge the result files of several ``torchrl_pipeline.py`` runs into one table and one plot.

The showcase's seeds are often run as separate processes (``--modes AL`` beside ``--modes PL``,
``--seed 0`` and ``--seed 20``), each writing its own ``torchrl_pipeline.json``. This reads
those files, checks that they ran the same setting (every argument but the seeds, the modes,
the threads and the output folder) and that no (mode, seed) appears twice with different
numbers, then prints and writes what one run over all of their seeds would have: the per-mode
summary, the paired t-test of AL vs PL over the seeds both modes ran, and the plot.

Run::

    python examples/merge_pipeline_runs.py --runs runs/al0,runs/pl0,runs/al20,runs/pl20 \\
        --out-dir results/merged
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from _cli import field, not_here, out_dir_error, parse
from _process import collector_off_for_imports, freeze_imported_objects

RESULTS = "torchrl_pipeline.json"
PER_PROCESS = ("seeds", "seed", "modes", "out_dir", "resume", "overwrite", "threads")
PER_PROCESS += ("merged_from",)
"""Arguments that may differ between the merged processes (which seeds, where, how run)."""


@dataclasses.dataclass
class Args:
    """Command-line arguments of the merge."""

    runs: str = field("", help="the runs' --out-dir folders, comma-separated")
    out_dir: str = field("results/merged", help="where the merged JSON and plot go")


def folders(args: Args) -> list[Path]:
    return [Path(p) for p in args.runs.split(",") if p]


def check(args: Args) -> str | None:
    """The output folder first (as every script's), then the runs to merge."""
    if problem := out_dir_error(args.out_dir):
        return problem
    if not folders(args):
        return "--runs must name at least one folder of a torchrl_pipeline.py run"
    missing = [str(d) for d in folders(args) if not (d / RESULTS).is_file()]
    return f"--runs: no {RESULTS} in {', '.join(missing)}" if missing else None


def parse_args(argv=None) -> Args:
    unavailable = not_here(
        "trials", "resume", "backend",
        seed="the seeds are those of the merged runs",
        device="nothing is computed: the runs' numbers are read",
    )  # fmt: skip
    return parse(Args, argv, __doc__, check=check, unavailable=unavailable)


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before matplotlib loads
    collector_off_for_imports(torch_follows=False)  # examples/_process.py (no torch here)

import _pipeline_report as report  # noqa: E402


def setting(args: dict) -> dict:
    """The arguments that define what was learned (must agree between merged files)."""
    return {k: v for k, v in args.items() if k not in PER_PROCESS}


def merge(payloads: list[dict]) -> tuple[dict, dict, dict, float]:
    """``(args, runs {mode: {seed: run}}, actor_alone {seed: value}, wall seconds summed)``.

    Raises ValueError when two payloads differ in setting, or give one (mode, seed) two
    different histories."""
    first = setting(payloads[0]["args"])
    runs: dict[str, dict[int, dict]] = {}
    actor: dict[int, float] = {}
    for p in payloads:
        theirs = setting(p["args"])
        if theirs != first:
            diff = sorted(k for k in first.keys() | theirs.keys() if first.get(k) != theirs.get(k))
            raise ValueError(f"{p['args']['out_dir']} ran another setting: {diff}")
        for mode, by_seed in p["runs"].items():
            for seed, run in by_seed.items():
                earlier = runs.setdefault(mode, {}).get(int(seed))
                if earlier is not None and earlier["history"] != run["history"]:
                    raise ValueError(f"{mode} seed {seed} appears twice with different numbers")
                runs[mode][int(seed)] = run
        actor |= {int(s): v for s, v in p.get("actor_alone", {}).items()}
    return payloads[0]["args"], runs, actor, sum(p["wall_seconds"] for p in payloads)


def main(argv=None) -> dict:
    options = parse_args(argv)
    payloads = [json.loads((d / RESULTS).read_text()) for d in folders(options)]
    args, runs, actor, wall = merge(payloads)
    if set(runs) == {"AL", "PL"}:  # pair over the seeds both modes ran
        both = sorted(set(runs["AL"]) & set(runs["PL"]))
        runs = {mode: {s: runs[mode][s] for s in both} for mode in ("AL", "PL")}
    seeds = sorted({s for r in runs.values() for s in r})
    print(f"{len(payloads)} files: {len(seeds)} seeds, {seeds[0]} to {seeds[-1]}")
    merged = dataclasses.make_dataclass("MergedArgs", list(args))(**args)  # summarise's args
    payload = report.summarise(merged, runs, actor, wall)
    print("(the wall time is the merged processes' sum)")
    payload["args"] = args | {"merged_from": [str(d) for d in folders(options)]}
    out = Path(options.out_dir)
    (out / RESULTS).write_text(json.dumps(payload, indent=1))
    report.plot(payload, out / "torchrl_pipeline.png")
    print(f"wrote {out / RESULTS} and {out / 'torchrl_pipeline.png'}")
    return payload


if __name__ == "__main__":
    freeze_imported_objects()
    main()
