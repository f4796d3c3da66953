"""Physics per batting episode with the coarse swing in MuJoCo and in tensors, against the floor.

For each batch size E: E noisy episodes of a uniformly random policy (the env's torques: the
chosen action's plus N(0, 3) noise per joint) stepped by two :class:`BattingSimulator`, one with
``swing="mujoco"`` (the engine of record) and one with ``swing="tensor"``
(:mod:`envs.batting.swing`), on the same torques, interleaved repeat by repeat. Timed: every
``step`` call (the whole physics of a control step: swing, gap prediction, impact window), and
within it the swing alone (between the hook's calls before the swing and after it). The floor,
measured in the same run: bare MuJoCo (``mujoco.batch.Batch.step`` on the same threads)
replaying a sample of the run's own physics steps, coarse and fine
(``benchmarks/_physics_floor.py``). Every speed is printed and stored as a ratio to that floor;
the machine (CPU, cores, load, torch threads) goes into the JSON file.

    python benchmarks/bench_batting_swing.py --out results/bench_batting_swing.json
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from _physics_floor import PhysicsAudit, replay_batch
from _timing import machine_info, write_result

from envs.batting import ACTION_TORQUES, MAX_STEPS, NOISE_VARIANCE, BattingSimulator, PhysicsHook

SWINGS = ("mujoco", "tensor")


@dataclass
class Args:
    """Command-line arguments."""

    sizes: tuple[int, ...] = (64, 640, 2560, 10240)  # batch sizes E (episodes per batch)
    repeats: int = 3  # timed repeats per size and swing (medians reported)
    seed: int = 0  # seed of the actions and the noise
    torch_threads: int = 1  # torch's intra-op threads (the examples' default)
    nthread: int | None = None  # MuJoCo's threads (None: all cores, as the env)
    audit_fraction: float = 0.05  # share of the rollouts replayed for the floor
    out: str = "results/bench_batting_swing.json"  # where the JSON goes


class SwingClock(PhysicsHook):
    """Seconds spent in the coarse swing: from the first coarse rollout of a control step (the
    swing's, announced before it runs) to the start of the impact window's selection."""

    def __init__(self) -> None:
        self.seconds, self._start = 0.0, None

    def on_rollout(self, kind, states, ids, torque, nstep) -> None:
        if kind == "coarse" and self._start is None:
            self._start = time.perf_counter()

    def on_step_start(self, sim, states) -> None:
        self.seconds += time.perf_counter() - self._start

    def on_step_end(self, sim) -> None:
        self._start = None


def episode_torques(size: int, seed: int) -> np.ndarray:
    """Applied torques [E, N, 2] (N m) of a random policy with the env's noise."""
    rng = np.random.default_rng(seed)
    torques = np.asarray(ACTION_TORQUES)[rng.integers(0, 2, (size, MAX_STEPS))]
    return torques + rng.normal(0.0, NOISE_VARIANCE**0.5, torques.shape)


def run_episodes(sim: BattingSimulator, torques: np.ndarray) -> float:
    """Seconds of the ``step`` calls of one batch of episodes."""
    sim.reset()
    start = time.perf_counter()
    for t in range(torques.shape[1]):
        sim.step(torques[:, t])
    return time.perf_counter() - start


def measure(size: int, args: Args) -> dict:
    torques = episode_torques(size, args.seed)
    clocks = {swing: SwingClock() for swing in SWINGS}
    sims = {
        swing: BattingSimulator(num_envs=size, swing=swing, nthread=args.nthread, hook=clock)
        for swing, clock in clocks.items()
    }
    audit = PhysicsAudit(args.audit_fraction, seed=args.seed)
    run_episodes(BattingSimulator(num_envs=size, nthread=args.nthread, hook=audit), torques)
    for sim in sims.values():  # warm-up
        run_episodes(sim, torques)
    times = {swing: {"physics": [], "swing": []} for swing in SWINGS}
    floors = []
    for _ in range(args.repeats):
        for swing, sim in sims.items():  # interleaved, so that load changes hit both alike
            clocks[swing].seconds = 0.0
            times[swing]["physics"].append(run_episodes(sim, torques) / size)
            times[swing]["swing"].append(clocks[swing].seconds / size)
        floor = replay_batch(audit, sims["mujoco"].main.nthread)
        floors.append((floor["coarse"] + floor["fine"]) / size)
    floor = float(np.median(floors))
    row = {
        "E": size,
        "steps_per_episode": float(sims["mujoco"].physics_steps.mean()),
        "fine_steps_per_episode": float(sims["mujoco"].fine_steps.mean()),
        "floor_us_per_episode": 1e6 * floor,
    }
    for swing in SWINGS:
        physics = np.asarray(times[swing]["physics"]) / np.asarray(floors)
        row[f"physics_over_floor_{swing}"] = float(np.median(physics))
        row[f"swing_over_floor_{swing}"] = float(
            np.median(np.asarray(times[swing]["swing"]) / np.asarray(floors))
        )
    ratio = np.asarray(times["tensor"]["physics"]) / np.asarray(times["mujoco"]["physics"])
    row["physics_tensor_over_mujoco"] = float(np.median(ratio))
    swing_ratio = np.asarray(times["tensor"]["swing"]) / np.asarray(times["mujoco"]["swing"])
    row["swing_tensor_over_mujoco"] = float(np.median(swing_ratio))
    return row


def main(args: Args) -> dict:
    torch.set_num_threads(args.torch_threads)
    info = machine_info()
    print(
        f"# {info['cpu']}, {info['cpu_count']} cores, load {info['load_avg_1min']:.2f}, "
        f"torch {info['torch']} on {info['threads']} thread(s), MuJoCo on "
        f"{args.nthread or os.cpu_count()} thread(s)"
    )
    print(
        f"{'E':>6}{'steps/ep':>10}{'fine/ep':>9}{'physics / floor':>18}{'swing / floor':>18}"
        f"{'tensor / mujoco':>18}"
    )
    print(f"{'':>25}{'mujoco  tensor':>18}{'mujoco  tensor':>18}{'physics  swing':>18}")
    rows = []
    for size in args.sizes:
        row = measure(size, args)
        rows.append(row)
        print(
            f"{size:>6}{row['steps_per_episode']:>10.1f}{row['fine_steps_per_episode']:>9.1f}"
            f"{row['physics_over_floor_mujoco']:>10.2f}{row['physics_over_floor_tensor']:>8.2f}"
            f"{row['swing_over_floor_mujoco']:>10.2f}{row['swing_over_floor_tensor']:>8.2f}"
            f"{row['physics_tensor_over_mujoco']:>10.3f}{row['swing_tensor_over_mujoco']:>8.3f}",
            flush=True,
        )
    print(
        "physics: every step call (swing, gap prediction, impact window) per episode; swing: "
        "its coarse swing alone; floor: bare MuJoCo Batch.step replaying a sample of the same "
        "run's coarse and fine steps (medians over repeats of per-repeat ratios)"
    )
    result = {"args": asdict(args), "machine": info, "rows": rows}
    return write_result(args.out, result)


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = Args()
    parser.add_argument("--sizes", type=int, nargs="+", default=list(defaults.sizes))
    parser.add_argument("--repeats", type=int, default=defaults.repeats)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--torch-threads", type=int, default=defaults.torch_threads)
    parser.add_argument("--nthread", type=int, default=defaults.nthread)
    parser.add_argument("--audit-fraction", type=float, default=defaults.audit_fraction)
    parser.add_argument("--out", default=defaults.out)
    ns = parser.parse_args(argv)
    ns.sizes = tuple(ns.sizes)
    return Args(**vars(ns))


if __name__ == "__main__":
    main(parse_args())
