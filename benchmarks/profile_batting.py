"""The main job's time beside its physics-and-algebra floor, measured in one run.

Runs what ``examples/train_batting.py`` runs by default, in this process on one core: the AL
and the PL run of the 'decreasing' schedule (Z = 5, K = 4, the paper's basis), T batched
trials, with pi_{l+1} scored on 20 test episodes per trial after each iteration (eq. 68).
Timers are wrapped around the library's own functions:

* swing: the coarse, contact-free swing of every control step (``BattingSimulator._swing``);
  its floor is the batched dynamics alone (``rk4_swing``, timed inside it);
* impact window: MuJoCo's rollouts of the fine window and the coarse intervals around it
  (``BattingSimulator._run``); its floor is bare ``mujoco.batch`` (``Batch.step``, one thread)
  replaying a sample of the run's own window rollouts (``_physics_floor.py``), scaled to the
  counted steps;
* algebra: psi_hat, importance weights, J and the weighted solves (``build_design``,
  ``j_values``, ``weighted_ridge``) and the policies' Q-values in the rollouts
  (``GaussianActionBasis.kernels``), its own floor here (``bench_batting_iteration.py`` splits
  it against matrix-product floors);
* env Python (noise, gap prediction, bookkeeping, TensorDicts) and TorchRL (rollouts,
  policies, buffers): no floor.

The swing's MuJoCo cost is measured beside it: bare ``Batch.step`` replaying a sample of the
run's own swing rollouts (the engine of record's coarse RK4 on the same states). With
``--swing mujoco`` the run itself swings in MuJoCo.

With ``--command``, first the command itself, ``python examples/train_batting.py`` (its default
chunks and worker processes, T trials, output to a temporary folder), from a fresh interpreter:
its wall time from start to exit beside its floor, the dependencies' start-up and exit (a fresh
interpreter importing torch, TensorDict, TorchRL and MuJoCo) plus the work's floor above shared
over the cores its two chunks a run can use (at most two).

    python benchmarks/profile_batting.py --trials 32 [--command]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
from _physics_floor import PhysicsAudit, replay_batch
from _timing import machine_info, write_result

import envs.batting.swing
import torch_api.core.fit
import torch_api.loop.selector
from envs import batting
from envs.batting import BASIS_TAU, MAX_STEPS, BattingEnv, PhysicsHook, basis_centers
from torch_api import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.data import REWARD_KEY
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec

DECREASING = (10, 10, 7, 7, 7, 4, 4)  # the batting 'decreasing' schedule (section 5)
TESTS = 20  # test episodes per trial behind one score (eq. 68)
ROOT = Path(__file__).resolve().parents[1]
DEPENDENCIES = "import torch, tensordict, torchrl.envs, mujoco"  # what any such program imports
TIMERS: dict[str, float] = defaultdict(float)
_DEPTH = {"algebra": 0, "swing": 0}  # nested calls are timed by the outermost only


@contextmanager
def timed(name: str):
    start = time.perf_counter()
    try:
        yield
    finally:
        TIMERS[name] += time.perf_counter() - start


def wrap(owner, attr: str, name: str) -> None:
    """Add the time of ``owner.attr``'s outermost calls to ``TIMERS[name]``."""
    original = getattr(owner, attr)

    def wrapper(*args, **kwargs):
        if _DEPTH.get(name):
            return original(*args, **kwargs)
        _DEPTH[name] = 1
        try:
            with timed(name):
                return original(*args, **kwargs)
        finally:
            _DEPTH[name] = 0

    setattr(owner, attr, wrapper)


class SplitAudit(PhysicsHook):
    """Two :class:`PhysicsAudit`: the swing's rollouts and the impact window's."""

    def __init__(self, fraction: float) -> None:
        self.swing, self.window = PhysicsAudit(fraction, seed=0), PhysicsAudit(fraction, seed=1)

    def on_rollout(self, kind, states, ids, torque, nstep) -> None:
        audit = self.swing if _DEPTH["swing"] else self.window
        audit.on_rollout(kind, states, ids, torque, nstep)


def instrument() -> None:
    """Timers on the swing, its bare dynamics, MuJoCo's rollouts, the env and the algebra."""
    wrap(batting.BattingSimulator, "_swing", "swing")
    wrap(envs.batting.swing, "rk4_swing", "swing dynamics")
    original_run = batting.BattingSimulator._run

    def run(self, *args, **kwargs):  # MuJoCo's rollouts outside the swing: the impact window
        if _DEPTH["swing"]:
            return original_run(self, *args, **kwargs)
        with timed("impact window"):
            return original_run(self, *args, **kwargs)

    batting.BattingSimulator._run = run
    wrap(BattingEnv, "_step", "env")
    wrap(BattingEnv, "_reset", "env")
    for module in (torch_api.core.fit, torch_api.loop.selector):
        for attr in ("build_design", "weighted_ridge", "j_values", "j_criterion"):
            if hasattr(module, attr):
                wrap(module, attr, "algebra")
    wrap(GaussianActionBasis, "kernels", "algebra")  # (also the policies' Q-values in rollouts)


def basis() -> GaussianActionBasis:
    return GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=2)


def run_arguments(
    doc: str, *, trials: int, audit: float, out: str, command: bool = False
) -> argparse.Namespace:
    """The command line of a timed batting run (this script's, bench_batting_iteration's)."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    if command:
        parser.add_argument("--command", action="store_true", help="time the example's command too")
        parser.add_argument("--repeats", type=int, default=3, help="rounds of the command's timing")
    parser.add_argument("--trials", type=int, default=trials)
    parser.add_argument("--iterations", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--nthread", type=int, default=1, help="MuJoCo threads of the env")
    parser.add_argument("--audit", type=float, default=audit, help="rollouts sampled for replay")
    parser.add_argument("--swing", choices=("tensor", "mujoco"), default="tensor")
    parser.add_argument("--out", default=out)
    args = parser.parse_args()
    if command and args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    torch.set_num_threads(args.threads)
    return args


def timed_process(argv: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, its children included) of ``argv`` run from the
    repository's root to its exit; its output is shown only if it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        raise RuntimeError(f"{argv} exited with {done.returncode}:\n{done.stdout}{done.stderr}")
    return wall, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def time_command(args: argparse.Namespace) -> dict:
    """``python examples/train_batting.py`` (T trials, L iterations, its default chunks and
    workers) from start to exit, the example's import alone and the dependencies' alone, in
    ``args.repeats`` interleaved rounds (load from elsewhere hits all three alike): the median
    of each, and every round's numbers (``rounds``)."""
    python, rounds = sys.executable, []
    flags = ["--trials", str(args.trials), "--iterations", str(args.iterations)]
    example = [python, "-c", "import sys; sys.path[:0] = ['examples']; import train_batting"]
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as out:
            wall, cpu = timed_process(
                [python, "examples/train_batting.py", *flags, "--out-dir", out]
            )
            result = json.loads((Path(out) / "train_batting.json").read_text())
        one = dict(wall=wall, cpu=cpu, experiment=result["wall_seconds"])
        one |= dict(example=timed_process(example)[0])
        one |= dict(dependencies=timed_process([python, "-c", DEPENDENCIES])[0])
        rounds.append(one | {"rest": wall - one["experiment"] - one["example"]})
    return {key: statistics.median(r[key] for r in rounds) for key in rounds[0]} | {
        "rounds": rounds
    }


def print_command(command: dict, floor: float) -> dict:
    """The command's parts beside their floors: the dependencies' start-up and exit, and the
    work's floor (``floor``, one core) shared over the cores the default's chunks can use."""
    cores = min(os.cpu_count() or 1, 2)  # two chunks a run, AL's and PL's one after another
    parts = {  # part: (seconds in the command, its floor)
        "start-up and exit: the example's imports": (command["example"], command["dependencies"]),
        f"the experiment ({cores} worker processes)": (command["experiment"], floor / cores),
        "arguments, report, figure, the workers' pool": (command["rest"], 0.0),
    }
    total = sum(f for _, f in parts.values())
    print(
        f"\n`python examples/train_batting.py` from the shell, start to exit (medians of "
        f"{len(command['rounds'])} interleaved rounds): "
        f"{command['wall']:.1f} s wall, {command['cpu']:.1f} CPU-s; its floor: the dependencies' "
        f"start-up and exit ({DEPENDENCIES}) plus the work's floor over {cores} core(s)\n"
    )
    print("| part | in the command (s) | floor (s) |\n|---|---:|---:|")
    for name, (seconds, part_floor) in parts.items():
        print(f"| {name} | {seconds:.2f} | {part_floor:.2f} |")
    print(f"| **the command** | {command['wall']:.2f} | {total:.2f} |")
    return command | {"cores": cores, "floor_s": total, "wall_over_floor": command["wall"] / total}


def active_run(args: argparse.Namespace, make, mode: str = "active", evaluate=None):
    """A run of the main job: 'decreasing', Z = 5, K = 4, the paper's basis; envs from ``make``."""
    active = dict(num_repeats=5, keep_reward_free=False) if mode == "active" else {}
    spec = RunSpec.of(
        schedule=DECREASING[: args.iterations],
        num_steps=MAX_STEPS,
        gamma=1.0,
        psi_mode="single",
        num_trials=args.trials,
        mode=mode,
        **active,
    )
    selector = SamplingPolicySelector(env=make) if mode == "active" else None
    return ActivePolicyIteration(
        spec, env=make, selector=selector, basis=basis(), evaluate=evaluate
    )


def main() -> dict:
    args = run_arguments(
        __doc__, trials=32, audit=0.05, out="results/profile_batting.json", command=True
    )
    command = time_command(args) if args.command else None  # (alone: before the profile)
    audit = SplitAudit(args.audit)

    def make(rows: int, seed: int | None = None) -> BattingEnv:
        return BattingEnv(
            batch_size=rows, seed=seed, nthread=args.nthread, hook=audit, swing=args.swing
        )

    tests = make(args.trials * TESTS, seed=0)

    def evaluate(policy, seed: int) -> dict:  # eq. 68: Σ carry over 20 test episodes
        tests.set_seed(seed)
        td = collect_episodes(tests, policy, num_episodes=TESTS, num_steps=MAX_STEPS, rewarded=True)
        return {"performance": (td[REWARD_KEY] * td["mask"]).sum((-2, -1)).tolist()}

    instrument()
    start = time.perf_counter()
    for mode in ("active", "passive"):
        active_run(args, make, mode, evaluate).run()
    wall = time.perf_counter() - start
    swing_mujoco = sum(replay_batch(audit.swing, nthread=args.nthread).values())
    window_floor = sum(replay_batch(audit.window, nthread=args.nthread).values())
    swing_floor = TIMERS["swing dynamics"] if args.swing == "tensor" else swing_mujoco
    parts = {  # part: (seconds in the run, its floor)
        "swing": (TIMERS["swing"], swing_floor),
        "impact window (MuJoCo)": (TIMERS["impact window"], window_floor),
        "algebra": (TIMERS["algebra"], TIMERS["algebra"]),
        "env Python": (TIMERS["env"] - TIMERS["swing"] - TIMERS["impact window"], 0.0),
        "TorchRL rollouts, policies, buffers": (wall - TIMERS["env"] - TIMERS["algebra"], 0.0),
    }
    floor = sum(f for _, f in parts.values())
    steps = {k: audit.swing.steps[k] + audit.window.steps[k] for k in ("coarse", "fine")}
    print(
        f"\nThe main job ({args.trials} trials, AL and PL, 'decreasing', {args.swing} swing), "
        f"one process, {args.threads} torch / {args.nthread} MuJoCo thread(s): {wall:.1f} s; "
        f"{steps['coarse']:,} coarse + {steps['fine']:,} fine physics steps\n"
    )
    print("| part | in the run (s) | floor (s) | run / floor |\n|---|---:|---:|---:|")
    for name, (seconds, part_floor) in parts.items():
        ratio = f"{seconds / part_floor:.2f}" if part_floor else "-"
        print(f"| {name} | {seconds:.2f} | {part_floor:.2f} | {ratio} |")
    print(f"| **the main job** | {wall:.2f} | {floor:.2f} | {wall / floor:.2f} |")
    swing_ratio = TIMERS["swing dynamics"] / swing_mujoco if args.swing == "tensor" else 1.0
    print(
        f"\nThe swing's physics in MuJoCo (bare Batch.step replaying a {args.audit:.0%} sample "
        f"of its rollouts): {swing_mujoco:.2f} s; in tensors: {swing_floor:.2f} s; "
        f"tensor / MuJoCo {swing_ratio:.2f}. Main job / physics-and-algebra floor: "
        f"{wall / floor:.2f}×."
    )
    payload = {
        "trials": args.trials,
        "swing": args.swing,
        "wall_s": wall,
        "parts_s": {name: {"run": s, "floor": f} for name, (s, f) in parts.items()},
        "floor_s": floor,
        "wall_over_floor": wall / floor,
        "swing_in_mujoco_s": swing_mujoco,
        "swing_tensor_over_mujoco": swing_ratio,
        "physics_steps": steps,
        "machine": machine_info(),
    }
    if command is not None:
        payload["default_command"] = print_command(command, floor)
    return write_result(args.out, payload)


if __name__ == "__main__":
    main()
