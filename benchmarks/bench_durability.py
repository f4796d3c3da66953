"""What durability costs: committing bought episodes to a run's store, per episode.

Every slice of rewarded episodes is committed (SQLite, WAL, ``synchronous=FULL``: fsynced, one
SHA-256 per episode) before the next is measured. This script times, for episodes shaped like
the chain walk's and the batting arm's (N = 10 steps, T trials side by side):

* ``commit 1``: one slice of one episode index (``rewarded_slice="episode"``, a robot);
* ``commit M``: one slice of M episode indices (``rewarded_slice="all"``, a simulator), per
  episode index;
* ``read``: reading back and verifying the whole run, per episode index;

and a whole chain-walk run (``tests``-sized: T = 3, schedule 3, 2, 2) with and without a store.
Medians over ``--repeats``; the table ends with the machine's load (``os.getloadavg``).

    python benchmarks/bench_durability.py
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv  # noqa: E402
from torch_api.core.basis import GaussianActionBasis  # noqa: E402
from torch_api.loop.iteration import ActivePolicyIteration  # noqa: E402
from torch_api.loop.selector import SamplingPolicySelector  # noqa: E402
from torch_api.runs.store import RunStore  # noqa: E402

STEPS = 10  # N


def episode(trials: int, obs_dim: int) -> TensorDict:
    """One episode index ``[T, N]`` in the library's format (random numbers)."""
    shape = (trials, STEPS)
    return TensorDict(
        {
            "observation": torch.randn(*shape, obs_dim),
            "action": torch.randint(2, shape),
            "sample_probs": torch.full((*shape, 2), 0.5, dtype=torch.float64),
            ("next", "observation"): torch.randn(*shape, obs_dim),
            ("next", "terminated"): torch.zeros(shape, dtype=torch.bool),
            ("next", "reward"): torch.randn(*shape, 1),
            "mask": torch.ones(shape, dtype=torch.bool),
            "iteration": torch.ones(shape, dtype=torch.long),
            "policy_id": torch.zeros(shape, dtype=torch.long),
        },
        batch_size=shape,
    )


def time_store(trials: int, obs_dim: int, slice_size: int, repeats: int) -> dict:
    """Median seconds per episode index: commit in slices of ``slice_size``, then read."""
    commits, reads = [], []
    for r in range(repeats):
        with tempfile.TemporaryDirectory() as folder:
            store = RunStore(Path(folder) / "run.db", config={"bench": r})
            data = episode(trials, obs_dim)
            for it in range(1, 6):
                started = time.perf_counter()
                store.put_episodes(it, {m: data for m in range(slice_size)})
                commits.append((time.perf_counter() - started) / slice_size)
            store.close()
            started = time.perf_counter()
            RunStore.read(Path(folder) / "run.db")
            reads.append((time.perf_counter() - started) / (5 * slice_size))
    return {"commit": statistics.median(commits), "read": statistics.median(reads)}


def chain_walk_run(path: Path | None) -> float:
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    started = time.perf_counter()
    ActivePolicyIteration(
        env=lambda e: ChainWalkEnv(batch_size=e),
        basis=basis,
        schedule=(3, 2, 2),
        num_steps=STEPS,
        gamma=GAMMA,
        selector=SamplingPolicySelector(num_repeats=2),
        psi_mode="grouped",
        num_trials=3,
        seed=7,
        checkpoint_path=path,
    ).run()
    return time.perf_counter() - started


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="repeats behind each median")
    parser.add_argument("--out", default="", help="also write the numbers to this JSON file")
    args = parser.parse_args(argv)
    results: dict = {"rows": {}}
    torch.set_num_threads(1)
    print(
        f"{'episodes like':<28} {'commit 1 (ms)':>14} {'commit M (ms/ep)':>17} {'read (ms/ep)':>13}"
    )
    for name, trials, obs_dim, many in (
        ("chain walk, T = 1", 1, 1, 5),
        ("chain walk, T = 1000", 1000, 1, 5),
        ("batting arm, T = 1", 1, 4, 10),
        ("batting arm, T = 500", 500, 4, 10),
    ):
        one = time_store(trials, obs_dim, 1, args.repeats)
        batch = time_store(trials, obs_dim, many, args.repeats)
        results["rows"][name] = {"commit_1": one["commit"], "commit_m": batch["commit"]}
        results["rows"][name] |= {"read": batch["read"], "m": many}
        print(
            f"{name:<28} {1e3 * one['commit']:>14.2f} {1e3 * batch['commit']:>17.2f} "
            f"{1e3 * batch['read']:>13.3f}"
        )
    plain, durable = [], []
    for _ in range(args.repeats):
        plain.append(chain_walk_run(None))
        with tempfile.TemporaryDirectory() as folder:
            durable.append(chain_walk_run(Path(folder) / "run.db"))
    p, d = statistics.median(plain), statistics.median(durable)
    print(
        f"\nchain-walk run (T = 3, schedule 3, 2, 2, 7 rewarded episode indices): "
        f"{p:.3f} s without a store, {d:.3f} s with ({1e3 * (d - p) / 7:.1f} ms per episode index)"
    )
    load = os.getloadavg()[0]
    print(f"load average {load:.2f} on {os.cpu_count()} CPUs")
    results |= {"run_plain_s": p, "run_durable_s": d, "load": load}
    if args.out:
        Path(args.out).write_text(json.dumps(results))


if __name__ == "__main__":
    main()
