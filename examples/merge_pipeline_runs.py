"""Merge the result files of several ``torchrl_pipeline.py`` runs into one table and one plot.

The showcase's seeds are often run as separate processes (``--modes AL`` beside ``--modes PL``,
``--seed 0`` and ``--seed 20``), each writing its own ``torchrl_pipeline.json``. This reads
those files, checks that they ran the same setting (every argument but the seeds, the modes,
the threads and the output folder) and that no (mode, seed) appears twice with different
numbers, then writes what one run over all of their seeds would have: the per-mode summary, the
paired t-test of AL vs PL over the seeds both modes ran, and the plot.

    python examples/merge_pipeline_runs.py --runs runs/al0 runs/pl0 --out-dir results/merged
"""

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from torch_api.experiment.seeds import write_seeds

RESULTS = "torchrl_pipeline.json"
PER_PROCESS = ("seeds", "seed", "modes", "execution", "merged_from")  # may differ between them
GOAL = {"CartPole-v1": 475.0, "Acrobot-v1": -100.0}  # torchrl_pipeline.py's: "learned"


@dataclass
class Args:
    """Command-line arguments of the merge."""

    runs: tuple[str, ...] = ()
    """the runs' --out-dir folders"""
    out_dir: str = "results/merged"
    """where the merged JSON and plot go"""


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
            raise ValueError(f"{p['args']['execution']['out_dir']} ran another setting: {diff}")
        for mode, by_seed in p["runs"].items():
            for seed, run in by_seed.items():
                earlier = runs.setdefault(mode, {}).get(int(seed))
                if earlier is not None and earlier["history"] != run["history"]:
                    raise ValueError(f"{mode} seed {seed} appears twice with different numbers")
                runs[mode][int(seed)] = run
        actor |= {int(s): v for s, v in p.get("actor_alone", {}).items()}
    return payloads[0]["args"], runs, actor, sum(p["wall_seconds"] for p in payloads)


def main(argv: list[str] | None = None) -> dict:
    options = tyro.cli(Args, args=argv, description=__doc__)
    folders = [Path(p) for p in options.runs]
    try:
        if not folders:
            raise ValueError("--runs must name at least one folder of a torchrl_pipeline.py run")
        if missing := [str(d) for d in folders if not (d / RESULTS).is_file()]:
            raise ValueError(f"--runs: no {RESULTS} in {', '.join(missing)}")
        args, runs, actor, wall = merge([json.loads((d / RESULTS).read_text()) for d in folders])
        Path(options.out_dir).mkdir(parents=True, exist_ok=True)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    if set(runs) >= {"AL", "PL"} and runs["AL"] and runs["PL"]:  # pair the seeds both ran
        both = sorted(set(runs["AL"]) & set(runs["PL"]))
        runs = {mode: {s: runs[mode][s] for s in both} for mode in ("AL", "PL")}
    seeds = sorted({s for r in runs.values() for s in r})
    print(f"{len(folders)} files: {len(seeds)} seeds, {seeds[0]} to {seeds[-1]}")
    args |= {"merged_from": [str(d) for d in folders]}
    print("(the wall time is the merged processes' sum)")
    title = f"{args['env']} through TorchRL"
    out = Path(options.out_dir) / RESULTS
    return write_seeds(out, args, runs, actor, goal=GOAL.get(args["env"]), title=title, wall=wall)


if __name__ == "__main__":
    main()
