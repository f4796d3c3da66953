"""Collecting whole episodes: ``env.rollout`` on a batched env against TorchRL's ``Collector``.

The library collects M episodes of N steps by ``env.rollout(N, policy)`` on an env whose batch
holds the M rows (``torch_api.collection.collect_episodes``). The alternative is TorchRL's
collector,
``Collector(env, policy, frames_per_batch=M·N, total_frames=..., reset_at_each_iter=True)``
over the same batched env, which yields the same ``[M, N]`` batches. A third way spreads the rows
over 2 worker processes with TorchRL's ``MultiSyncCollector``
(``torch_api.collection.multiprocess.collect_episodes_in_workers``, start-up of the workers
included, as it
is paid on every call). All are timed side by side on the chain walk and the batting arm, with
the library's ε-greedy linear-Q policy. A last row shows where the workers pay: a slow, CPU-bound
environment (the chain walk plus ``--slow-us`` microseconds of Python work per row and step,
standing in for a simulator that steps its rows one by one), env.rollout against 2 workers.

    python benchmarks/bench_collection.py
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from functools import partial
from pathlib import Path

import torch
from _timing import machine_info, median_times
from torchrl.collectors import Collector

from envs.batting import BASIS_TAU, BattingEnv, basis_centers
from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.collection import collect_episodes
from torch_api.collection.multiprocess import collect_episodes_in_workers
from torch_api.core.basis import GaussianActionBasis
from torch_api.policies import LinearQPolicy

logging.getLogger("torchrl").setLevel(logging.WARNING)
STEPS = 10  # N, steps per episode (both tasks of the paper)


def chain_walk_policy() -> LinearQPolicy:
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    return LinearQPolicy(basis=basis, theta=torch.ones(12), epsilon=0.3)


def batting_policy() -> LinearQPolicy:
    basis = GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=2)
    return LinearQPolicy(basis=basis, theta=torch.ones(110), epsilon=0.3)


def chain_walk_env(rows: int) -> ChainWalkEnv:  # top level: worker processes unpickle it
    return ChainWalkEnv(batch_size=rows, seed=0)


def batting_env(rows: int) -> BattingEnv:
    return BattingEnv(batch_size=rows, seed=0)


class SlowChainWalkEnv(ChainWalkEnv):
    """The chain walk plus ``cost_us`` microseconds of busy Python work per row and step."""

    def __init__(self, *args, cost_us: float, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.cost_us = cost_us

    def _step(self, tensordict):
        until = time.perf_counter() + self.cost_us * 1e-6 * self.batch_size.numel()
        while time.perf_counter() < until:
            pass
        return super()._step(tensordict)


def slow_chain_walk_env(rows: int, cost_us: float) -> SlowChainWalkEnv:
    return SlowChainWalkEnv(batch_size=rows, seed=0, cost_us=cost_us)


def via_workers(make_env, policy, episodes: int):
    return collect_episodes_in_workers(
        make_env, policy, num_episodes=episodes, num_steps=STEPS, rewarded=True, num_workers=2
    )


def via_rollout(env, policy, episodes: int):
    return collect_episodes(env, policy, num_episodes=episodes, num_steps=STEPS, rewarded=True)


def via_collector(env, policy, episodes: int):
    collector = Collector(
        env,
        policy.with_action_spec(env.action_spec),
        frames_per_batch=episodes * STEPS,
        total_frames=episodes * STEPS,
        reset_at_each_iter=True,
        auto_register_policy_transforms=False,
    )
    batch = next(iter(collector))
    collector.shutdown()
    return batch


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[16, 256, 2048])
    parser.add_argument(
        "--tasks",
        nargs="+",
        choices=("chain", "batting"),
        default=["chain", "batting"],
        help="the paper's tasks measured at --sizes: the chain walk, batting (default: both)",
    )
    parser.add_argument("--budget", type=float, default=1.0, help="seconds per method and size")
    parser.add_argument("--repeats", type=int, default=3, help="least timed rounds per size")
    parser.add_argument(
        "--warmup", type=int, default=1, help="untimed calls first (0: a smoke run, no warm-up)"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--slow-us", type=float, default=500.0, help="Python work per row and step, slow env"
    )
    parser.add_argument(
        "--slow-size", type=int, default=2048, help="episodes M of the slow env (0: skip it)"
    )
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    info = machine_info()
    print(f"# bench_collection: torch {info['torch']}, {torch.get_num_threads()} thread(s)")
    rows = []
    tasks = {
        "chain": ("chain walk", chain_walk_env, chain_walk_policy),
        "batting": ("batting", batting_env, batting_policy),
    }
    for task, make_env, make_policy in (tasks[key] for key in tasks if key in args.tasks):
        for episodes in args.sizes:
            env, policy = make_env(episodes), make_policy()
            times = median_times(
                {
                    "rollout": lambda env=env, p=policy, m=episodes: via_rollout(env, p, m),
                    "collector": lambda env=env, p=policy, m=episodes: via_collector(env, p, m),
                    "workers": lambda f=make_env, p=policy, m=episodes: via_workers(f, p, m),
                },
                budget_s=args.budget,
                warmup=args.warmup,
                min_repeats=args.repeats,
            )
            assert tuple(times["collector"].result.shape) == (episodes, STEPS)
            rollout, collector = times["rollout"].median_ms, times["collector"].median_ms
            workers = times["workers"].median_ms
            rows.append(
                {
                    "task": task,
                    "episodes": episodes,
                    "rollout_ms": rollout,
                    "collector_ms": collector,
                    "collector_over_rollout": collector / rollout,
                    "workers_ms": workers,
                    "workers_over_rollout": workers / rollout,
                    "rollout_transitions_per_s": episodes * STEPS / rollout * 1e3,
                }
            )
            print(f"  {task}, M = {episodes}: done", flush=True)
    if args.slow_size > 0:
        episodes, policy = args.slow_size, chain_walk_policy()
        make_env = partial(slow_chain_walk_env, cost_us=args.slow_us)
        env = make_env(episodes)
        times = median_times(  # one timed round: a call takes seconds
            {
                "rollout": lambda: via_rollout(env, policy, episodes),
                "workers": lambda: via_workers(make_env, policy, episodes),
            },
            budget_s=args.budget,
            warmup=args.warmup,
            min_repeats=1,
        )
        rollout, workers = times["rollout"].median_ms, times["workers"].median_ms
        rows.append(
            {
                "task": f"slow chain walk ({args.slow_us:g} µs per row-step)",
                "episodes": episodes,
                "rollout_ms": rollout,
                "collector_ms": None,
                "collector_over_rollout": None,
                "workers_ms": workers,
                "workers_over_rollout": workers / rollout,
                "rollout_transitions_per_s": episodes * STEPS / rollout * 1e3,
            }
        )
        print(f"  slow chain walk, M = {episodes}: done", flush=True)
    print(
        "\n| task | episodes M (N = 10) | env.rollout (ms) | Collector (ms) | Collector / rollout "
        "| 2 workers (ms) | workers / rollout | rollout transitions/s |"
        "\n|---|---:|---:|---:|---:|---:|---:|---:|"
    )
    for r in rows:
        collector = (
            "— | —"
            if r["collector_ms"] is None
            else f"{r['collector_ms']:.1f} | {r['collector_over_rollout']:.2f}×"
        )
        print(
            f"| {r['task']} | {r['episodes']:,} | {r['rollout_ms']:.1f} | {collector} "
            f"| {r['workers_ms']:.0f} "
            f"| {r['workers_over_rollout']:.2f}× | {r['rollout_transitions_per_s']:,.0f} |"
        )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"machine": info, "rows": rows}, indent=1))
    return {"rows": rows}


if __name__ == "__main__":
    main()
