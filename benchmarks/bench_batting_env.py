"""Speed of BattingEnv against raw mujoco.mj_step on the same model, in the same run.

For E = 1, 16, 256 parallel arms: episodes of a uniformly random policy through the TorchRL env
(noise, integration scheme, look-ahead, TensorDicts), counting the physics steps it spends
(coarse RK4 and fine Euler separately), and, side by side, a plain Python loop of raw
``mujoco.mj_step`` calls on one MjData doing the same numbers of coarse and fine steps.
Several repeats, medians. Prints physics steps/s of both, their ratio, and episodes/s.

    python benchmarks/bench_batting_env.py --repeats 5
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np
import torch

from envs.batting import MAX_STEPS, BattingEnv


@dataclass
class Args:
    """Command-line arguments."""

    sizes: tuple[int, ...] = (1, 16, 256)  # batch sizes E
    repeats: int = 5  # timed repeats per size (medians reported)
    min_episodes: int = 256  # at least this many episodes per repeat
    seed: int = 0  # seed of the env noise and the random actions
    out: str = "results/bench_batting_env.json"  # where the JSON table goes


def env_run(env: BattingEnv, n_batches: int, gen: torch.Generator) -> tuple[float, int, int]:
    """Seconds, coarse and fine physics steps for ``n_batches`` batches of random episodes."""
    E = env.batch_size[0]
    coarse = fine = 0
    start = time.perf_counter()
    for _ in range(n_batches):
        td = env.reset()
        for _ in range(MAX_STEPS):
            td["action"] = torch.randint(0, 2, (E,), generator=gen)
            td = env.step(td)["next"]
        fine += int(env.sim.fine_steps.sum())
        coarse += int(env.sim.physics_steps.sum() - env.sim.fine_steps.sum())
    return time.perf_counter() - start, coarse, fine


def raw_run(env: BattingEnv, coarse: int, fine: int) -> float:
    """Seconds for ``coarse`` + ``fine`` raw mj_step calls on the env's two models."""
    start = time.perf_counter()
    for model, n, chunk in (
        (env.sim.coarse_model, coarse, env.sim.n_coarse),
        (env.sim.fine_model, fine, env.sim.n_fine),
    ):
        data = mujoco.MjData(model)
        mujoco.mj_setState(model, data, env.sim._initial_state, mujoco.mjtState.mjSTATE_INTEGRATION)
        data.ctrl[:] = (-50.0, 10.0)
        done = 0
        while done < n:
            k = min(chunk, n - done)
            for _ in range(k):
                mujoco.mj_step(model, data)
            done += k
            mujoco.mj_setState(
                model, data, env.sim._initial_state, mujoco.mjtState.mjSTATE_INTEGRATION
            )
    return time.perf_counter() - start


def main(args: Args) -> dict:
    rows = []
    print(
        f"{'E':>5}{'steps/ep':>10}{'fine/ep':>9}{'env steps/s':>13}{'raw steps/s':>13}"
        f"{'ratio':>7}{'env eps/s':>11}{'raw eps/s':>11}"
    )
    for E in args.sizes:
        env = BattingEnv(batch_size=E, seed=args.seed)
        gen = torch.Generator().manual_seed(args.seed)
        n_batches = max(1, args.min_episodes // E)
        env_run(env, 1, gen)  # warm-up
        t_env, t_raw, steps, fines = [], [], [], []
        for _ in range(args.repeats):
            seconds, coarse, fine = env_run(env, n_batches, gen)
            t_env.append(seconds)
            t_raw.append(raw_run(env, coarse, fine))
            steps.append(coarse + fine)
            fines.append(fine)
        episodes = n_batches * E
        env_rate = float(np.median(np.array(steps) / np.array(t_env)))
        raw_rate = float(np.median(np.array(steps) / np.array(t_raw)))
        row = {
            "E": E,
            "episodes_per_repeat": episodes,
            "steps_per_episode": float(np.median(steps)) / episodes,
            "fine_steps_per_episode": float(np.median(fines)) / episodes,
            "env_steps_per_s": env_rate,
            "raw_steps_per_s": raw_rate,
            "ratio": env_rate / raw_rate,
            "env_episodes_per_s": float(np.median(episodes / np.array(t_env))),
            "raw_episodes_per_s": float(np.median(episodes / np.array(t_raw))),
            "nthread": env.sim.main.nthread,
        }
        rows.append(row)
        print(
            f"{E:>5}{row['steps_per_episode']:>10.1f}{row['fine_steps_per_episode']:>9.1f}"
            f"{env_rate:>13.0f}{raw_rate:>13.0f}{row['ratio']:>7.2f}"
            f"{row['env_episodes_per_s']:>11.1f}{row['raw_episodes_per_s']:>11.1f}"
        )
    print(
        "raw: one MjData, one thread, a Python loop of mj_step; "
        "env: MuJoCo batch threads = min(E, cores)"
    )
    result = {"args": asdict(args), "rows": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")
    return result


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = Args()
    parser.add_argument("--sizes", type=int, nargs="+", default=list(defaults.sizes))
    parser.add_argument("--repeats", type=int, default=defaults.repeats)
    parser.add_argument("--min-episodes", type=int, default=defaults.min_episodes)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--out", default=defaults.out)
    ns = parser.parse_args(argv)
    ns.sizes = tuple(ns.sizes)
    return Args(**vars(ns))


if __name__ == "__main__":
    main(parse_args())
