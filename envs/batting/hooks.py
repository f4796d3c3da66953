"""Instrumentation hook of the batting simulator: observe its physics without touching it.

A :class:`PhysicsHook` given to :class:`~envs.batting.BattingSimulator` (or
:class:`~envs.batting.BattingEnv`) is called around every physics rollout of a control step.
The simulator's numbers do not depend on it: a hook only reads. What instruments a run (the
physics audit of ``envs/batting/audit.py``, the per-step arm trace of
``examples/plot_batting_episode.py``) lives with the program that needs it, not in the env.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PhysicsHook"]


class PhysicsHook:
    """Base of the simulator's observers; every method does nothing.

    Attributes:
        wants_qpos: ask the coarse rollouts inside a control step to record ``qpos`` too
            (the fine ones always do), so that :meth:`on_interval` sees the arm at every
            physics step.

    Example:
        >>> from envs.batting import BattingSimulator
        >>> class CountRollouts(PhysicsHook):
        ...     calls = 0
        ...     def on_rollout(self, kind, states, ids, torque, nstep):
        ...         self.calls += 1
        >>> hook = CountRollouts()
        >>> sim = BattingSimulator(num_envs=1, hook=hook)
        >>> _ = sim.reset(); _ = sim.step(np.array([[50.0, -35.0]]))
        >>> hook.calls
        1
    """

    wants_qpos: bool = False

    def on_rollout(
        self, kind: str, states: np.ndarray, ids: np.ndarray, torque: np.ndarray, nstep: int
    ) -> None:
        """Before a rollout of ``nstep`` physics steps of simulations ``ids``.

        ``kind`` is ``"coarse"`` or ``"fine"``; ``states`` [E, nstate] are all simulations'
        integration states before the call, ``torque`` [len(ids), 2] (N m) the torques applied.
        The coarse swing is announced alike whether MuJoCo or the tensor swing computes it.
        """

    def on_step_start(self, sim, states: np.ndarray | None) -> None:
        """After the coarse pass of a control step: ``states`` [E, n_coarse + 1, nstate] are its
        states at the interval boundaries (``None`` in the uniform scheme); with the tensor swing
        a buffer the simulator overwrites in the next control step (copy what is kept)."""

    def on_interval(self, sim, ids: np.ndarray, j: int, out: dict, coarse: bool) -> None:
        """After simulations ``ids`` were re-integrated from coarse interval ``j`` on: ``out``
        is the rollout's record (``qpos`` [len(ids), nstep, nq] where recorded)."""

    def on_step_end(self, sim) -> None:
        """At the end of a control step."""
