"""Where the time of an active batting run goes: physics, env Python, TorchRL/collection, algebra.

Runs ``ActivePolicyIteration`` (mode active, the 'decreasing' schedule, Z = 5, K = 4) on T
batched batting trials and splits its wall time, with timers wrapped around:

* physics: MuJoCo's native rollouts inside the env (``BattingSimulator._run``), counted in
  coarse and fine physics steps by a :class:`PhysicsAudit` (a hook of the env);
* env Python: the rest of ``BattingEnv._reset`` / ``_step`` (noise, gap prediction, look-ahead,
  TensorDicts);
* algebra: psi_hat, importance weights, J and the weighted solves (``build_design``,
  ``j_criterion``, ``weighted_ridge``);
* TorchRL / collection: the remainder (``env.rollout``, policies, buffers, checks).

Next to it, in the same invocation, the physics floor of the run: bare MuJoCo replaying a 5 %
sample of the run's own rollouts (same start states, torques and step counts;
``benchmarks/_physics_floor.py``) with ``mujoco.batch.Batch`` on 2 threads, and with a 1-thread
``mj_step`` loop, scaled to the counted steps. For comparison it also times the proxy floor used
before (a free swing from the initial state for the same step counts), which leaves out the
solver work of joint limits and contacts.

    python benchmarks/profile_batting.py --trials 8
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import torch
from _physics_floor import PhysicsAudit, replay_batch, replay_loop
from bench_batting_env import raw_batch_run

import torch_api.core.design
import torch_api.core.fit
import torch_api.core.solve
import torch_api.loop.selector
from envs import batting
from envs.batting import BASIS_TAU, BattingEnv, basis_centers
from torch_api.core.basis import GaussianActionBasis
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec

DECREASING = (10, 10, 7, 7, 7, 4, 4)  # the batting 'decreasing' schedule (section 5)
TIMERS: dict[str, float] = defaultdict(float)
_DEPTH = {"n": 0}  # algebra calls nest (j_values -> build_design): time the outermost only


@contextmanager
def timed(name: str):
    start = time.perf_counter()
    try:
        yield
    finally:
        TIMERS[name] += time.perf_counter() - start


def wrap(owner, attr: str, name: str, *, outermost: bool = False) -> None:
    original = getattr(owner, attr)

    def wrapper(*args, **kwargs):
        if outermost and _DEPTH["n"]:
            return original(*args, **kwargs)
        _DEPTH["n"] += outermost
        try:
            with timed(name):
                return original(*args, **kwargs)
        finally:
            _DEPTH["n"] -= outermost

    setattr(owner, attr, wrapper)


def time_physics() -> None:
    """Time ``BattingSimulator._run``, the env's MuJoCo rollouts."""
    original = batting.BattingSimulator._run

    def run(self, batch, ids, torque, nstep, *args, **kwargs):
        with timed("physics"):
            return original(self, batch, ids, torque, nstep, *args, **kwargs)

    batting.BattingSimulator._run = run


def instrument() -> None:
    time_physics()
    wrap(BattingEnv, "_step", "env")
    wrap(BattingEnv, "_reset", "env")
    for module in (torch_api.core.fit, torch_api.loop.selector):
        for attr in ("build_design", "weighted_ridge", "j_values", "j_criterion"):
            if hasattr(module, attr):
                wrap(module, attr, "algebra", outermost=True)


def basis() -> GaussianActionBasis:
    return GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=2)


def run_arguments(doc: str, *, trials: int, audit: float, out: str) -> argparse.Namespace:
    """The command line of a timed active batting run (this script's, bench_batting_iteration's)."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--trials", type=int, default=trials)
    parser.add_argument("--iterations", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--nthread", type=int, default=2, help="MuJoCo threads of the env")
    parser.add_argument("--audit", type=float, default=audit, help="rollouts sampled for replay")
    parser.add_argument("--out", default=out)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    return args


def active_run(args: argparse.Namespace, make) -> ActivePolicyIteration:
    """The active run timed: 'decreasing', Z = 5, K = 4, the paper's basis; envs from ``make``."""
    spec = RunSpec.of(
        schedule=DECREASING[: args.iterations],
        num_steps=10,
        gamma=1.0,
        num_repeats=5,
        psi_mode="single",
        num_trials=args.trials,
        keep_reward_free=False,
    )
    return ActivePolicyIteration(
        spec, env=make, selector=SamplingPolicySelector(env=make), basis=basis()
    )


def main() -> dict:
    args = run_arguments(__doc__, trials=8, audit=0.05, out="results/profile_batting.json")
    envs: list[BattingEnv] = []
    audit = PhysicsAudit(args.audit, seed=0)

    def make(rows: int) -> BattingEnv:
        envs.append(BattingEnv(batch_size=rows, nthread=args.nthread, hook=audit))
        return envs[-1]

    instrument()
    api = active_run(args, make)
    start = time.perf_counter()
    api.run()
    wall = time.perf_counter() - start
    coarse, fine = audit.steps["coarse"], audit.steps["fine"]
    env_python = TIMERS["env"] - TIMERS["physics"]
    torchrl = wall - TIMERS["env"] - TIMERS["algebra"]
    raw2 = sum(replay_batch(audit, nthread=2).values())
    raw1 = sum(replay_loop(audit).values())
    proxy2 = raw_batch_run(envs[0], coarse, fine, nthread=2)
    rows = {
        "physics (MuJoCo rollouts in the env)": TIMERS["physics"],
        "env Python (noise, gap prediction, look-ahead, TensorDicts)": env_python,
        "TorchRL rollouts, policies, buffers, checks": torchrl,
        "algebra (psi_hat, weights, J, solves)": TIMERS["algebra"],
    }
    print(
        f"\nActive run, {args.trials} trials, schedule {list(api.schedule)}: {wall:.1f} s wall; "
        f"{coarse:,} coarse + {fine:,} fine physics steps\n"
    )
    print("| part | seconds | share |\n|---|---:|---:|")
    for name, seconds in rows.items():
        print(f"| {name} | {seconds:.2f} | {seconds / wall:.0%} |")
    print(f"| **total** | {wall:.2f} | 100% |")
    print(
        f"\nBare MuJoCo replaying the run's physics steps ({args.audit:.0%} sample): {raw2:.2f} s "
        f"(Batch, 2 threads), {raw1:.2f} s (mj_step loop, 1 thread). In-env physics / floor: "
        f"{TIMERS['physics'] / raw2:.2f}×; wall / floor (2 threads): {wall / raw2:.2f}×. "
        f"(Proxy floor of a free swing from the initial state: {proxy2:.2f} s.)"
    )
    payload = {
        "trials": args.trials,
        "wall_s": wall,
        "parts_s": rows,
        "coarse_steps": coarse,
        "fine_steps": fine,
        "raw_batch_2_threads_s": raw2,
        "raw_loop_1_thread_s": raw1,
        "proxy_free_swing_2_threads_s": proxy2,
        "wall_over_floor": wall / raw2,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(payload, indent=1))
    return payload


if __name__ == "__main__":
    main()
