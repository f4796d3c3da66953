"""One ball-batting arm as a Gymnasium environment, registered as ``"torch_api/Batting-v0"``.

The registration is in ``envs/__init__.py``; the physics is :class:`BattingSimulator`'s.
"""

from __future__ import annotations

import math

import gymnasium
import numpy as np

from .._common import check_positive_int
from .constants import MAX_STEPS, N_ACTIONS, NOISE_VARIANCE, OBSERVATION_BOUND, action_torques
from .simulator import BattingSimulator

__all__ = ["BattingGymEnv"]


class BattingGymEnv(gymnasium.Env):
    """One ball-batting arm as a Gymnasium environment (``"torch_api/Batting-v0"``).

    Same physics, actions, noise and reward as :class:`BattingEnv`; the noise comes from the
    env's ``np_random`` (seeded by ``reset(seed=...)``). Observation: float32 (4,) =
    (phi1, phi1_dot, phi2, phi2_dot); action: ``Discrete(2)``. ``truncated`` is True at step
    ``max_steps``; ``terminated`` is always False. ``info`` holds ``"hit"`` (the bat has touched
    the ball) and ``"torque"`` (the applied torques, N m).

    Example:
        >>> env = BattingGymEnv()
        >>> obs, info = env.reset(seed=0)
        >>> obs, reward, terminated, truncated, info = env.step(1)
        >>> obs.shape, terminated
        ((4,), False)
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        *,
        max_steps: int = MAX_STEPS,
        noise_variance: float = NOISE_VARIANCE,
        **sim_kwargs,
    ) -> None:
        self.max_steps = check_positive_int(max_steps, "max_steps")
        self.noise_std = math.sqrt(float(noise_variance))  # (N m)
        # one arm stepped alone: MuJoCo's swing (tens of microseconds a control step) beats the
        # tensor swing, whose fixed cost per call pays off only over many arms at once
        sim_kwargs.setdefault("swing", "mujoco")
        self.sim = BattingSimulator(num_envs=1, nthread=1, **sim_kwargs)
        bound = np.array(OBSERVATION_BOUND, dtype=np.float32)
        self.observation_space = gymnasium.spaces.Box(-bound, bound, (4,), np.float32)
        self.action_space = gymnasium.spaces.Discrete(N_ACTIONS)
        self._steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._steps = 0
        obs = self.sim.reset()[0].astype(np.float32)
        return obs, {"hit": False}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0 or 1, got {action!r}")
        torque = action_torques(int(action)) + self.np_random.normal(0.0, self.noise_std, 2)
        obs, carry, first_hit = self.sim.step(torque[None, :])
        self._steps += 1
        reward = float(carry[0]) if first_hit[0] else 0.0
        truncated = self._steps >= self.max_steps
        info = {"hit": bool(self.sim.hit[0]), "torque": torque}
        return obs[0].astype(np.float32), reward, False, truncated, info
