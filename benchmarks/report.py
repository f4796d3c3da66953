"""Every results table in the docs, generated from the data files in docs/results/data/.

    python -m benchmarks.report            # write docs/results/index.md and README.md's block
    python -m benchmarks.report --check    # exit 1, naming the files that would change

docs/results/index.md gets a headline table (each experiment's first measure at the last
iteration, where AL pays first), then one section per experiment: the command, the code's
commit, the date and the machine, every measure's paired test, the transitions and seconds,
and the per-iteration means. README.md's block between ``<!-- results:start -->`` and
``<!-- results:end -->`` gets the headline table (at most :data:`README_ROWS` rows); a README
without both markers is left alone. The output depends on the data files only (sorted, fixed
number formats). The data files are made by ``python -m benchmarks.summarize``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = ROOT / "docs" / "results" / "data"
INDEX = ROOT / "docs" / "results" / "index.md"
README = ROOT / "README.md"
START, END = "<!-- results:start -->", "<!-- results:end -->"
README_ROWS = 8
VERDICTS = ("AL better", "no difference found", "PL better")
"""benchmarks/summarize.py's verdicts, in the tables' order: where AL pays first."""
HEAD = "| task | setting | AL | PL | AL − PL (95 % CI, p) | trials | verdict |"
RULE = "| --- | --- | ---: | ---: | ---: | ---: | --- |"


# -- numbers -------------------------------------------------------------------------------


def num(x, digits: int, sign: bool = False) -> str:
    """``x`` with ``digits`` decimals (``+`` first where ``sign``), ``—`` where None."""
    if x is None:
        return "—"
    return f"{x:+.{digits}f}" if sign else f"{x:.{digits}f}"


def p_text(p) -> str:
    if p is None:
        return "p undefined"
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


def mean_se(stat: dict, digits: int) -> str:
    se = stat.get("se")
    return num(stat["mean"], digits) + ("" if se is None else f" ± {num(se, digits)}")


def difference(d: dict, digits: int) -> str:
    if d.get("ci95_low") is None:
        return f"{num(d['mean'], digits, True)}, {p_text(d.get('p'))}"
    low, high = num(d["ci95_low"], digits, True), num(d["ci95_high"], digits, True)
    return f"{num(d['mean'], digits, True)} ({low}, {high}), {p_text(d['p'])}"


def _count(x: float) -> str:
    return f"{x:,.0f}" if x == int(x) else f"{x:,.1f}"


# -- data ----------------------------------------------------------------------------------


def load(data_dir: Path) -> list[dict]:
    """Every data file, by file name."""
    return [json.loads(p.read_text()) for p in sorted(Path(data_dir).glob("*.json"))]


def headline(experiments: list[dict]) -> list[tuple[dict, dict]]:
    """(experiment, row) of each experiment's first measure: AL better first, then no
    difference, then PL better; within a verdict by experiment id and schedule."""
    pairs = [
        (e, r)
        for e in experiments
        for r in e["rows"]
        if r["measure"] in e.get("headline_measures", e["measures"][:1])
    ]
    return sorted(
        pairs,
        key=lambda er: (VERDICTS.index(er[1]["verdict"]), er[0]["experiment"], er[1]["schedule"]),
    )


def headline_table(pairs: list[tuple[dict, dict]], link: str = "") -> list[str]:
    lines = [HEAD, RULE]
    for e, r in pairs:
        d = e.get("digits", 3)
        task = f"[{e['task']}]({link}#{e['experiment']})" if link else e["task"]
        beside = "".join(  # a learner of the field at the same budget, where one was run
            f"; {b['learner']}: {mean_se(b['return'], d)}"
            for b in e.get("baselines", [])
            if not b["learner"].startswith("library") and b["task"] == r.get("task", b["task"])
        )
        lines.append(
            f"| {task} | {r['schedule']}, `{r['measure']}`{beside} | {mean_se(r['al'], d)} | "
            f"{mean_se(r['pl'], d)} | {difference(r['difference'], d)} | "
            f"{r['difference']['trials']:,} | {r['verdict']} |"
        )
    return lines


# -- the pages -----------------------------------------------------------------------------


def _machine(m: dict) -> str:
    load = m.get("load", {})
    loads = ", ".join(
        f"{k} {' / '.join(f'{x:.2f}' for x in load[k])}" for k in ("start", "end") if k in load
    )
    text = (
        f"{m.get('cpu')}, {m.get('cores')} cores, Python {m.get('python')}, torch {m.get('torch')}"
    )
    if loads:
        text += f"; load average (1, 5, 15 min) {loads}"
        if m.get("load_measured"):
            text += f" ({m['load_measured']})"
    return text


def section(e: dict) -> list[str]:
    d = e.get("digits", 3)
    lines = [f'<a id="{e["experiment"]}"></a>', "", f"## {e['title']}", ""]
    if e.get("note"):
        lines += [e["note"], ""]
    lines += [f"- command: `{e['command']}`", f"- commit: `{e['commit']}`"]
    if e.get("code"):
        lines.append(f"- code: {e['code']}")
    if e.get("executed"):
        lines.append(f"- executed: `{e['executed']}` ({e['executed_seconds']:.1f} s with start-up)")
    lines.append(f"- date: {e['date']}")
    if e.get("wall_seconds") is not None:
        lines.append(f"- wall time (the experiment's own): {e['wall_seconds']:.1f} s")
    lines += [f"- machine: {_machine(e.get('machine', {}))}", f"- data: `{e['experiment']}.json`"]
    better = "higher" if e.get("better", "higher") == "higher" else "lower"
    lines += [
        "",
        f"At the last iteration ({better} is better; AL − PL paired over trials):",
        "",
        "| schedule | measure | AL | PL | AL − PL (95 % CI, p) | t | AL > PL | AL < PL | trials "
        "| verdict |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in e["rows"]:
        diff = r["difference"]
        lines.append(
            f"| {r['schedule']} | `{r['measure']}` | {mean_se(r['al'], d)} | "
            f"{mean_se(r['pl'], d)} | {difference(diff, d)} | {num(diff.get('t'), 2)} | "
            f"{diff['al_better_share']:.1%} | {diff['al_worse_share']:.1%} | "
            f"{diff['trials']:,} | {r['verdict']} |"
        )
    lines += _costs(e) + _curves(e) + _cells(e) + _baselines(e)
    return lines + [""]


def _cells(e: dict) -> list[str]:
    """A map's cells (benchmarks/reward_budget_map.py): one row per setting, with its power."""
    if not e.get("cells"):
        return []
    lines = [
        "",
        "Every cell of the map (AL − PL at l = L, paired; detectable: the difference found with "
        "80 % power at α = 0.05 with this many trials; target: the δ the trials were sized for; "
        "cost: each method's seconds and AL's reward-free transitions per trial):",
        "",
        "| task | M | R | Z | ν | trials | AL − PL (95 % CI, p) | detectable | target | "
        "verdict | seconds AL / PL | reward-free AL |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |",
    ]
    d = e.get("digits", 3)
    for c in e["cells"]:
        cell, diff = c["cell"], c["difference"]
        lines.append(
            f"| {cell['task']} | {cell['episodes']} | {cell['reward_free'] or 'M'} | "
            f"{cell['repeats']} | {cell['flattening']} | {diff['trials']:,} | "
            f"{difference(diff, d)} | {num(c.get('detectable_80'), d)} | "
            f"{num(c.get('target_difference'), d)} | {c['verdict']} | "
            f"{c['seconds']['AL']:.1f} / {c['seconds']['PL']:.1f} | "
            f"{_count(c['reward_free_transitions']['AL'])} |"
        )
    return lines


def _baselines(e: dict) -> list[str]:
    """Other learners beside AL and PL at the same budget (benchmarks/dqn_baseline.py)."""
    if not e.get("baselines"):
        return []
    lines = [
        "",
        "Beside other learners at the same rewarded budget (mean ± s.e. over seeds):",
        "",
        "| task | learner | greedy test return | seeds | rewarded transitions | seconds |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for b in e["baselines"]:
        lines.append(
            f"| {b['task']} | {b['learner']} | {mean_se(b['return'], 1)} | "
            f"{b['return']['trials']} | {_count(b['rewarded_transitions'])} | "
            f"{num(b.get('seconds'), 1)} |"
        )
    return lines


def _costs(e: dict) -> list[str]:
    seen, lines = set(), []
    for r in e["rows"]:
        if r["schedule"] in seen or not any(
            k in r for k in ("rewarded_transitions", "reward_free_transitions", "seconds")
        ):
            continue
        seen.add(r["schedule"])
        for m in ("AL", "PL"):
            cells = [
                _count(r[k][m]) if k in r else "—"
                for k in ("rewarded_transitions", "reward_free_transitions")
            ]
            seconds = f"{r['seconds'][m]:.1f}" if m in r.get("seconds", {}) else "—"
            lines.append(f"| {r['schedule']} | {m} | {cells[0]} | {cells[1]} | {seconds} |")
    if not lines:
        return []
    head = "| schedule | method | rewarded transitions | reward-free transitions | seconds |"
    return ["", "Bought per trial (mean) and each run's seconds:", "", head] + [
        "| --- | --- | ---: | ---: | ---: |",
        *lines,
    ]


def _curves(e: dict) -> list[str]:
    d, lines = e.get("digits", 3), []
    for measure in e["measures"]:
        rows = [r for r in e["rows"] if r["measure"] == measure and r.get("per_iteration")]
        if not rows:
            continue
        its = rows[0]["per_iteration"]["iterations"]
        lines += ["", f"`{measure}`, mean over trials per iteration l:", ""]
        lines += ["| schedule | method | " + " | ".join(f"l={i}" for i in its) + " |"]
        lines += ["| --- | --- |" + " ---: |" * len(its)]
        for r in rows:
            for m in ("AL", "PL"):
                cells = " | ".join(num(x, d) for x in r["per_iteration"][m])
                lines.append(f"| {r['schedule']} | {m} | {cells} |")
    return lines


def index_page(experiments: list[dict]) -> str:
    lines = [
        "# Results",
        "",
        "<!-- generated by `python -m benchmarks.report` from docs/results/data/*.json: "
        "do not edit by hand -->",
        "",
        "Every number here is generated from the data files in `docs/results/data/` "
        "(`python -m benchmarks.summarize` makes one from an experiment's output folder; "
        "`python -m benchmarks.report` writes this page and the README's table). "
        "Means ± standard errors over trials; AL − PL is paired over trials, with the 95 % "
        "interval from the t quantile and the two-tailed paired t-test's p. The verdict is a "
        "fixed rule: *AL better* if p < 0.05 and the difference favours AL, *PL better* if "
        "p < 0.05 and it favours PL, *no difference found* otherwise.",
        "",
        "## Headline",
        "",
        *headline_table(headline(experiments)),
        "",
    ]
    for e in sorted(experiments, key=lambda e: e["experiment"]):
        lines += section(e)
    return "\n".join(lines).rstrip("\n") + "\n"


def readme_block(experiments: list[dict]) -> str:
    pairs = headline([e for e in experiments if e.get("readme", True)])  # (quick runs: left out)
    lines = headline_table(pairs[:README_ROWS], link="docs/results/index.md")
    more = len(pairs) - README_ROWS
    if more > 0:
        lines += ["", f"{more} more rows: [docs/results/index.md](docs/results/index.md)."]
    return "\n".join(lines)


def with_readme_block(text: str, block: str) -> str | None:
    """``text`` with its results block replaced; None where it lacks either marker."""
    start, end = text.find(START), text.find(END)
    if start < 0 or end < start:
        return None
    return text[: start + len(START)] + "\n" + block + "\n" + text[end:]


def generate(data_dir: Path, index: Path, readme: Path | None) -> dict[Path, str]:
    """``{file: its generated text}``; the README only where it has both markers."""
    experiments = load(data_dir)
    pages = {Path(index): index_page(experiments)}
    if readme is not None and Path(readme).exists():
        text = with_readme_block(Path(readme).read_text(), readme_block(experiments))
        if text is not None:
            pages[Path(readme)] = text
    return pages


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.report", description=__doc__.split("\n")[0]
    )
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file differs")
    p.add_argument("--data-dir", type=Path, default=DATA_DIR)
    p.add_argument("--index", type=Path, default=INDEX)
    p.add_argument("--readme", type=Path, default=README, help="'' to leave the README out")
    options = p.parse_args(argv)
    readme = options.readme if str(options.readme) not in ("", ".") else None
    pages = generate(options.data_dir, options.index, readme)
    stale = [path for path, text in pages.items() if not path.exists() or path.read_text() != text]
    if options.check:
        for path in stale:
            print(f"{path} differs from what python -m benchmarks.report generates")
        return 1 if stale else 0
    for path in stale:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(pages[path])
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
