"""The physics floor of a batting run: bare MuJoCo replaying the run's own physics steps.

A run's environments count their physics steps, and sample some of their rollout calls, into a
:class:`PhysicsAudit` (start state, torques, number of steps; ``envs/batting/audit.py``, a
hook of the env). Replaying the sampled rollouts with nothing around them, and scaling by the
counted steps, estimates how long bare MuJoCo needs for the run's physics. The states matter:
steps in which the arm presses on a joint limit or the bat touches the ball cost more solver
work than a free swing, so a floor timed on other states (e.g. a swing from the initial state)
would be too low or too high.

Two floors are given: ``mujoco.batch.Batch.step`` on ``nthread`` threads (the machine's cores;
the floor the ratios use), and a plain ``mj_step`` loop on one thread.
"""

from __future__ import annotations

import time

import mujoco
import numpy as np
from mujoco.batch import Batch

from envs.batting import BattingSimulator, PhysicsAudit

INTEGRATION_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
MAX_BATCH = 4096  # simulations per replayed Batch (bounds its memory)


def _grouped(audit: PhysicsAudit, kind: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The sampled rollouts of one kind, grouped by their number of steps."""
    groups: dict[int, tuple[list, list]] = {}
    for states, torques, nstep in audit.samples[kind]:
        entry = groups.setdefault(nstep, ([], []))
        entry[0].append(states)
        entry[1].append(torques)
    return {n: (np.concatenate(s), np.concatenate(t)) for n, (s, t) in groups.items()}


def _models() -> dict[str, mujoco.MjModel]:
    sim = BattingSimulator(num_envs=1, nthread=1)
    return {"coarse": sim.coarse_model, "fine": sim.fine_model}


def replay_batch(audit: PhysicsAudit, nthread: int) -> dict[str, float]:
    """Seconds ``Batch.step`` on ``nthread`` threads needs for the audited steps, per kind."""
    seconds = {}
    for kind, model in _models().items():
        sampled = audit.sampled_steps(kind)
        if audit.steps[kind] == 0:
            seconds[kind] = 0.0
            continue
        if sampled == 0:
            raise ValueError(f"the audit counted {kind} steps but sampled none: raise its fraction")
        elapsed = 0.0
        for nstep, (states, torques) in _grouped(audit, kind).items():
            for start in range(0, len(states), MAX_BATCH):
                rows = slice(start, start + MAX_BATCH)
                batch = Batch(model, nsim=len(states[rows]), nthread=nthread)
                batch.state[:] = states[rows]
                batch.ctrl = torques[rows]
                tic = time.perf_counter()
                batch.step(nstep=nstep)
                elapsed += time.perf_counter() - tic
        seconds[kind] = elapsed * audit.steps[kind] / sampled
    return seconds


def replay_loop(audit: PhysicsAudit) -> dict[str, float]:
    """Seconds a one-thread ``mj_step`` loop needs for the audited steps, per kind."""
    seconds = {}
    for kind, model in _models().items():
        sampled = audit.sampled_steps(kind)
        if sampled == 0:
            seconds[kind] = 0.0
            continue
        data = mujoco.MjData(model)
        elapsed = 0.0
        for nstep, (states, torques) in _grouped(audit, kind).items():
            for state, torque in zip(states, torques, strict=True):
                mujoco.mj_setState(model, data, state, INTEGRATION_STATE)
                data.ctrl[:] = torque
                tic = time.perf_counter()
                for _ in range(nstep):
                    mujoco.mj_step(model, data)
                elapsed += time.perf_counter() - tic
        seconds[kind] = elapsed * audit.steps[kind] / sampled
    return seconds
