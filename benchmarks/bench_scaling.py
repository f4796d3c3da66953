"""How the cost of active policy iteration grows with trials T, samples n and basis size B.

Three tables, each with the fitted order of growth (the slope of log time against log size):

1. wall time of a whole active chain-walk run (schedule 'decreasing', Z = 5, K = 4, N = 10)
   against the number of trials batched together, T = 10, 100, 1000;
2. one J evaluation (``j_criterion``, Z = 5 × K = 4 sets) and one ``weighted_ridge`` solve against
   the samples per set n, at B = 110;
3. the same against the basis size B, at n = 1000.

Run::

    python benchmarks/bench_scaling.py            # about 2-3 minutes on 2 cores
    python benchmarks/bench_scaling.py --quick    # smoke test, seconds
    python benchmarks/bench_scaling.py --out results/bench_scaling.json
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from _timing import machine_info, median_time

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.solve import j_criterion, weighted_ridge
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.spec import RunSpec

DECREASING = (5, 5, 3, 3, 3, 1, 1)  # the chain walk's 'decreasing' schedule (section 4.2)


@dataclass
class Args:
    """Command-line arguments of the scaling benchmark."""

    quick: bool = False
    """tiny sizes, for a smoke test"""
    threads: int = 1
    """torch intra-op threads (1 is fastest for these sizes on a shared 2-core machine)"""
    out: str | None = None
    """write the numbers as JSON to this path"""


def growth_order(sizes: list[float], seconds: list[float]) -> float:
    """Slope of log(time) against log(size): time ~ size^slope."""
    return float(np.polyfit(np.log(sizes), np.log(seconds), 1)[0])


def chain_walk_run(trials: int) -> float:
    """Wall seconds of one active run of ``trials`` batched chain-walk trials."""
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    spec = RunSpec.of(
        schedule=DECREASING,
        num_steps=10,
        gamma=GAMMA,
        psi_mode="grouped",
        num_trials=trials,
        keep_reward_free=False,
    )  # active, Z = 5
    api = ActivePolicyIteration(spec, env=lambda rows: ChainWalkEnv(batch_size=rows), basis=basis)
    start = time.perf_counter()
    api.run()
    return time.perf_counter() - start


def table_trials(sizes: list[int]) -> list[dict]:
    rows = []
    for trials in sizes:
        repeats = 3 if trials <= 100 else 1
        seconds = sorted(chain_walk_run(trials) for _ in range(repeats))[repeats // 2]
        rows.append({"trials": trials, "seconds": seconds, "ms_per_trial": 1e3 * seconds / trials})
        print(f"  T = {trials}: {seconds:.2f} s", flush=True)
    return rows


def algebra_times(n: int, features: int, gen: torch.Generator) -> dict:
    x = torch.randn(5, 4, n, features, generator=gen, dtype=torch.float64)
    w = torch.rand(5, 4, n, generator=gen, dtype=torch.float64) + 0.1
    r = torch.randn(5, 4, n, generator=gen, dtype=torch.float64)
    u = torch.eye(features, dtype=torch.float64).expand(5, 1, features, features)
    j = median_time(lambda: j_criterion(x, w, u), budget_s=0.5)
    ridge = median_time(lambda: weighted_ridge(x[0, 0], w[0, 0], r[0, 0]), budget_s=0.3)
    return {"j_ms": j.median_ms, "ridge_ms": ridge.median_ms}


def table_algebra(key: str, sizes: list[int], fixed: int, gen: torch.Generator) -> list[dict]:
    rows = []
    for size in sizes:
        n, features = (size, fixed) if key == "n" else (fixed, size)
        rows.append({key: size, **algebra_times(n, features, gen)})
        print(f"  {key} = {size}: done", flush=True)
    return rows


def markdown(rows: list[dict], key: str, columns: dict[str, str]) -> str:
    header = f"| {key} | " + " | ".join(columns.values()) + " |"
    lines = [header, "|" + "---:|" * (len(columns) + 1)]
    for row in rows:
        cells = " | ".join(f"{row[c]:.3g}" for c in columns)
        lines.append(f"| {row[key]:,} | {cells} |")
    sizes = [row[key] for row in rows]
    orders = ", ".join(
        f"{label} ~ {key}^{growth_order(sizes, [r[c] for r in rows]):.2f}"
        for c, label in columns.items()
        if not c.startswith("ms_per")
    )
    return "\n".join(lines) + f"\n\nOrder of growth: {orders}."


def main(args: Args) -> dict:
    torch.set_num_threads(args.threads)
    info = machine_info()
    print(
        f"# bench_scaling: torch {info['torch']}, {torch.get_num_threads()} thread(s), "
        f"{info['cpu']}, load average {info['load_avg_1min']:.2f}",
        flush=True,
    )
    gen = torch.Generator().manual_seed(0)
    trials = [2, 5, 10] if args.quick else [10, 100, 1000]
    ns = [100, 300] if args.quick else [100, 300, 1000, 3000, 10000]
    bs = [12, 30] if args.quick else [12, 30, 60, 110, 220]
    print("trials ...", flush=True)
    by_trials = table_trials(trials)
    print("samples n ...", flush=True)
    by_n = table_algebra("n", ns, 110, gen)
    print("basis size B ...", flush=True)
    by_b = table_algebra("B", bs, 300 if args.quick else 1000, gen)

    print("\nActive chain-walk run (decreasing schedule, Z = 5, K = 4), trials batched:\n")
    print(markdown(by_trials, "trials", {"seconds": "wall s", "ms_per_trial": "ms per trial"}))
    print("\nJ for Z·K = 20 sets and one weighted_ridge, against n (B = 110), median ms:\n")
    print(markdown(by_n, "n", {"j_ms": "J (20 sets)", "ridge_ms": "weighted_ridge"}))
    print("\nThe same against B (n = 1000), median ms:\n")
    print(markdown(by_b, "B", {"j_ms": "J (20 sets)", "ridge_ms": "weighted_ridge"}))
    payload = {
        "machine": info,
        "args": asdict(args),
        "trials": by_trials,
        "samples": by_n,
        "basis": by_b,
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(payload, indent=1))
    return payload


def parse_args() -> Args:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None)
    return Args(**vars(parser.parse_args()))


if __name__ == "__main__":
    main(parse_args())
