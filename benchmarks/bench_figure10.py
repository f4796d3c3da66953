"""The batting arm's Figure 10 run against its physics floor (issue: wall within 1.5× the floor).

Runs ``examples/train_batting.py`` (both schedules, AL and PL, all 7 iterations) once per
configuration given, then measures the run's physics floor in the same invocation: bare MuJoCo
replaying a sample of the run's own physics rollouts, scaled to the counted steps
(``benchmarks/_physics_floor.py``). Prints one row per configuration: wall time, physics steps,
the floor (``mujoco.batch.Batch`` on all cores, and a 1-thread ``mj_step`` loop) and wall /
floor.

Configurations: ``local`` (one process, trials batched, MuJoCo on every core) and
``processes`` (``--backend processes``: chunks of trials in a pool of ``--workers`` processes,
one core each, so that one process's physics overlaps another's algebra).

    python benchmarks/bench_figure10.py --trials 32 --configs local processes
    python benchmarks/bench_figure10.py --trials 500 --configs processes   # the paper's run
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from _physics_floor import replay_batch, replay_loop

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import train_batting  # noqa: E402

CONFIGS = ("local", "processes")


def run_config(config: str, args: argparse.Namespace) -> dict:
    out_dir = Path(args.out_dir) / config
    argv = [
        "--trials",
        str(args.trials),
        "--schedule",
        "both",
        "--iterations",
        str(args.iterations),
        "--seed",
        str(args.seed),
        "--out-dir",
        str(out_dir),
        "--physics-audit",
        str(args.audit),
        "--overwrite",  # a benchmark times fresh runs, never a resumed one
    ]
    if config == "processes":
        chunks = min(args.trials, args.chunks or args.workers)
        argv += ["--backend", "processes", "--workers", str(args.workers), "--chunks", str(chunks)]
    start = time.perf_counter()
    payload = train_batting.main(argv)
    wall = time.perf_counter() - start
    audit = payload["physics_audit"]
    floor = sum(replay_batch(audit, nthread=os.cpu_count() or 1).values())
    loop = sum(replay_loop(audit).values()) if args.loop_floor else float("nan")
    return {
        "config": config,
        "trials": args.trials,
        "wall_s": wall,
        "coarse_steps": audit.steps["coarse"],
        "fine_steps": audit.steps["fine"],
        "sampled_steps": audit.sampled_steps("coarse") + audit.sampled_steps("fine"),
        "floor_batch_s": floor,
        "floor_loop_1_thread_s": loop,
        "wall_over_floor": wall / floor,
        "last_iteration_mean": {
            f"{name} {method}": sum(last) / len(last)
            for name, res in payload["results"].items()
            for method, run in res["runs"].items()
            for last in [run["iterations"][-1]["performance"]]
        },
    }


def main() -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=32)
    parser.add_argument("--iterations", type=int, default=7)
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=CONFIGS)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--chunks", type=int, default=0, help="0: one chunk per worker")
    parser.add_argument("--audit", type=float, default=0.01, help="rollouts sampled for replay")
    parser.add_argument("--loop-floor", action="store_true", help="also a 1-thread mj_step loop")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", default="results/bench_figure10", help="the runs' outputs")
    parser.add_argument("--out", default="results/bench_figure10/bench_figure10.json")
    args = parser.parse_args()
    rows = [run_config(config, args) for config in args.configs]
    cores = os.cpu_count()
    print(f"\nFigure 10 run ({args.trials} trials × 2 schedules × AL/PL), {cores} cores\n")
    print(
        "| configuration | wall s | coarse + fine steps | floor: Batch, all cores (s) "
        "| floor: mj_step loop, 1 thread (s) | wall / floor |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for row in rows:
        label = row["config"]
        if label == "processes":
            label += f" ({args.workers} workers)"
        print(
            f"| {label} | {row['wall_s']:.1f} | {row['coarse_steps']:,} + {row['fine_steps']:,} "
            f"| {row['floor_batch_s']:.1f} | {row['floor_loop_1_thread_s']:.1f} "
            f"| {row['wall_over_floor']:.2f}× |"
        )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
