"""The physics audit of a batting run: its physics steps counted, a sample kept for replay.

A :class:`~envs.batting.hooks.PhysicsHook` given to the run's environments
(``BattingEnv(hook=PhysicsAudit(...))``): it only reads, so the numbers of a run do not depend
on it. ``examples/train_batting.py`` reports the counts; ``benchmarks/_physics_floor.py``
replays the sample to time bare MuJoCo on the same steps.

Example:
    >>> from envs.batting import BattingEnv, PhysicsAudit
    >>> audit = PhysicsAudit(fraction=0.5, seed=0)
    >>> _ = BattingEnv(batch_size=2, seed=0, hook=audit).rollout(2)
    >>> audit.steps["coarse"] > 0
    True
"""

from __future__ import annotations

import numpy as np

from .hooks import PhysicsHook

__all__ = ["PhysicsAudit"]


class PhysicsAudit(PhysicsHook):
    """Counts the physics steps of one or more simulators and keeps a random sample to replay.

    The physics floor of a run, the time bare MuJoCo needs for the same physics steps, depends
    on the states stepped (joint limits and contacts cost solver work), so it is estimated by
    replaying a uniform sample of the run's rollouts (start state, torque, number of steps)
    with nothing else around them and scaling by the counted steps
    (``benchmarks/_physics_floor.py``). The sampling draws from a stream of its own and never
    touches the environment's.

    Args:
        fraction: probability with which each simulation of each rollout call is sampled
            (0: count only).
        seed: seed of the sampling stream.

    Attributes:
        steps: physics steps counted, ``{"coarse": int, "fine": int}``.
        samples: per kind, a list of ``(states [r, nstate], torques [r, 2], nstep)``.
    """

    KINDS = ("coarse", "fine")

    def __init__(self, fraction: float = 0.0, seed: int = 0) -> None:
        if not 0.0 <= float(fraction) <= 1.0:
            raise ValueError(f"fraction must lie in [0, 1], got {fraction!r}")
        self.fraction = float(fraction)
        self.rng = np.random.default_rng(seed)
        self.steps = dict.fromkeys(self.KINDS, 0)
        self.samples: dict[str, list] = {kind: [] for kind in self.KINDS}

    def on_rollout(
        self, kind: str, states: np.ndarray, ids: np.ndarray, torque: np.ndarray, nstep: int
    ) -> None:
        """Count rollouts of ``nstep`` steps of simulations ``ids`` and sample some of them.

        ``states`` [E, nstate] are all simulations' states before the call, ``torque``
        [len(ids), 2] the torques of the simulations ``ids``.
        """
        self.steps[kind] += len(ids) * nstep
        if self.fraction > 0.0:
            keep = self.rng.random(len(ids)) < self.fraction
            if keep.any():
                self.samples[kind].append((states[ids[keep]], torque[keep].copy(), nstep))

    def merge(self, other: PhysicsAudit) -> PhysicsAudit:
        """Add another audit's counts and samples to this one (returns self)."""
        for kind in self.KINDS:
            self.steps[kind] += other.steps[kind]
            self.samples[kind].extend(other.samples[kind])
        return self

    def sampled_steps(self, kind: str) -> int:
        """Physics steps held in the sample of ``kind``."""
        return sum(len(torque) * nstep for _, torque, nstep in self.samples[kind])
