"""Collecting whole episodes: ``env.rollout`` on a batched env against TorchRL's ``Collector``.

The library collects M episodes of N steps by ``env.rollout(N, policy)`` on an env whose batch
holds the M rows (``torch_api.data.collect_episodes``). The alternative is TorchRL's collector,
``Collector(env, policy, frames_per_batch=M·N, total_frames=..., reset_at_each_iter=True)``
over the same batched env, which yields the same ``[M, N]`` batches. Both are timed side by side
on the chain walk and the batting arm, with the library's ε-greedy linear-Q policy.

    python benchmarks/bench_collection.py
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import torch
from _timing import machine_info, median_times
from torchrl.collectors import Collector

from envs.batting import BASIS_TAU, BattingEnv, basis_centers
from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.basis import GaussianActionBasis
from torch_api.data import collect_episodes
from torch_api.policies import LinearQPolicy

logging.getLogger("torchrl").setLevel(logging.WARNING)
STEPS = 10  # N, steps per episode (both tasks of the paper)


def chain_walk_policy() -> LinearQPolicy:
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    return LinearQPolicy(basis=basis, theta=torch.ones(12), epsilon=0.3)


def batting_policy() -> LinearQPolicy:
    basis = GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=2)
    return LinearQPolicy(basis=basis, theta=torch.ones(110), epsilon=0.3)


def via_rollout(env, policy, episodes: int):
    return collect_episodes(env, policy, num_episodes=episodes, num_steps=STEPS, rewarded=True)


def via_collector(env, policy, episodes: int):
    collector = Collector(
        env,
        policy,
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
    parser.add_argument("--budget", type=float, default=1.0, help="seconds per method and size")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    info = machine_info()
    print(f"# bench_collection: torch {info['torch']}, {torch.get_num_threads()} thread(s)")
    rows = []
    for task, make_env, make_policy in (
        ("chain walk", lambda e: ChainWalkEnv(batch_size=e, seed=0), chain_walk_policy),
        ("batting", lambda e: BattingEnv(batch_size=e, seed=0), batting_policy),
    ):
        for episodes in args.sizes:
            env, policy = make_env(episodes), make_policy()
            times = median_times(
                {
                    "rollout": lambda env=env, p=policy, m=episodes: via_rollout(env, p, m),
                    "collector": lambda env=env, p=policy, m=episodes: via_collector(env, p, m),
                },
                budget_s=args.budget,
            )
            assert tuple(times["collector"].result.shape) == (episodes, STEPS)
            rollout, collector = times["rollout"].median_ms, times["collector"].median_ms
            rows.append(
                {
                    "task": task,
                    "episodes": episodes,
                    "rollout_ms": rollout,
                    "collector_ms": collector,
                    "collector_over_rollout": collector / rollout,
                    "rollout_transitions_per_s": episodes * STEPS / rollout * 1e3,
                }
            )
            print(f"  {task}, M = {episodes}: done", flush=True)
    print(
        "\n| task | episodes M (N = 10) | env.rollout (ms) | Collector (ms) | Collector / rollout "
        "| rollout transitions/s |\n|---|---:|---:|---:|---:|---:|"
    )
    for r in rows:
        print(
            f"| {r['task']} | {r['episodes']:,} | {r['rollout_ms']:.1f} | {r['collector_ms']:.1f} "
            f"| {r['collector_over_rollout']:.2f}× | {r['rollout_transitions_per_s']:,.0f} |"
        )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"machine": info, "rows": rows}, indent=1))
    return {"rows": rows}


if __name__ == "__main__":
    main()
