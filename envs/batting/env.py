"""The ball-batting robot (paper section 5, Figure 9) as a batched TorchRL environment.

State s = (phi1, phi1_dot, phi2, phi2_dot) (eq. 62). Action 0 applies the torques (50, -35) N m
to joints 1 and 2 (it cocks the arm), action 1 applies (-50, 10) N m (it swings the bat) (eq.
63); the actual torque is the chosen one plus N(0, 3) noise (variance 3) per joint, drawn once
per control step. Initial state (pi/4, 0, 0, 0) with the ball resting on its pin. Reward: the
carry of the ball, given at the control step in which the bat first touches the ball, 0 at every
other step. Episodes never terminate; they are truncated after ``max_steps`` (10) steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .._common import RandomStreams, check_positive_int, check_seed, done_spec, fresh_seed
from .constants import (
    MAX_STEPS,
    N_ACTIONS,
    NOISE_VARIANCE,
    action_torques,
)
from .simulator import BattingSimulator

__all__ = ["BattingEnv"]


class BattingEnv(EnvBase):
    """Batched ball-batting robot (paper section 5, Figure 9) as a TorchRL environment.

    A stateful env: the MuJoCo states live in a :class:`BattingSimulator` (see
    :mod:`envs.batting.impact` for the integration scheme and the look-ahead carry). Each step
    adds N(0, 3) noise (variance 3, std sqrt(3) N m) to the chosen torques, independently per
    joint and env, drawn from the env's own counter-based streams (``set_seed``); equal seeds give
    equal episodes.

    Keys: ``"observation"`` float32 [E, 4] = (phi1, phi1_dot, phi2, phi2_dot) (rad, rad/s);
    ``"step_count"`` int64 [E, 1]; ``"action"`` int64 [E] (``Categorical(2)``: 0 = (50, -35) N m,
    1 = (-50, 10) N m on joints 1 and 2; a one-hot [E, 2] is accepted too); ``"reward"`` float32
    [E, 1], the carry (m) in the step of the first ball-bat contact, else 0; ``"done"``,
    ``"terminated"`` (False, or with ``end_at_hit`` True from the step of the first contact
    on), ``"truncated"`` bool [E, 1], True at step ``max_steps``.

    Args:
        batch_size: number of parallel arms E (an int or a 1-d shape).
        max_steps: control steps per episode (10 in the paper).
        device: device of the env's tensors (CPU by default) and of the tensor swing; MuJoCo's
            physics (the impact window) runs on the CPU.
        seed: key of the noise stream; ``None`` draws a fresh one (not from global state).
        noise_variance: variance of the torque noise per joint ((N m)^2).
        end_at_hit: end the episode (``terminated``) at the step of the first ball-bat
            contact: the ball is gone, nothing after it can earn a reward. Off by default
            (the paper's episodes run all ``max_steps`` steps).
        **sim_options: keywords of :class:`BattingSimulator`: the fidelity knobs ``scheme``,
            ``coarse_dt``, ``fine_dt``, ``margin``, ``coarse_integrator``, ``swing``
            (``"tensor"``, the default, or ``"mujoco"``, the engine of record), ``nthread``, and
            ``hook``, a :class:`PhysicsHook` observing the env's physics (instrumentation; the
            numbers do not depend on it).

    Example:
        >>> env = BattingEnv(batch_size=4, seed=0)
        >>> td = env.rollout(MAX_STEPS)  # one episode: truncated at the last step
        >>> td["observation"].shape, td["next", "reward"].shape
        (torch.Size([4, 10, 4]), torch.Size([4, 10, 1]))
        >>> bool(td["next", "truncated"][:, -1].all())
        True
    """

    def __init__(
        self,
        *,
        batch_size: int | Sequence[int] = 1,
        max_steps: int = MAX_STEPS,
        device: torch.device | str | None = None,
        seed: int | None = None,
        noise_variance: float = NOISE_VARIANCE,
        end_at_hit: bool = False,
        **sim_options,
    ) -> None:
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(f"batch_size must be one positive size E, got {tuple(batch_size)}")
        check_positive_int(max_steps, "max_steps")
        if not float(noise_variance) >= 0.0:
            raise ValueError(f"noise_variance must be >= 0, got {noise_variance!r}")
        check_seed(seed)
        super().__init__(
            device=torch.device("cpu") if device is None else device,
            batch_size=batch_size,
        )
        self.max_steps = max_steps
        self.end_at_hit = bool(end_at_hit)
        self.noise_std = math.sqrt(float(noise_variance))  # (N m)
        sim_options.setdefault("device", self.device)
        self.sim = BattingSimulator(num_envs=batch_size[0], **sim_options)
        self._steps = np.zeros(batch_size[0], dtype=np.int64)
        self.last_torque = np.zeros((batch_size[0], 2))  # (N m) applied in the last step
        self.streams = RandomStreams(rows=batch_size.numel(), what="arms")
        self._make_spec()
        self.set_seed(fresh_seed() if seed is None else seed)

    # -- specs --------------------------------------------------------------------------------

    def _make_spec(self) -> None:
        shape = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*shape, 4), dtype=torch.float32, device=self.device),
            step_count=Bounded(
                low=0,
                high=self.max_steps,
                shape=(*shape, 1),
                dtype=torch.int64,
                device=self.device,
            ),
            shape=shape,
            device=self.device,
        )
        self.action_spec = Categorical(
            N_ACTIONS, shape=shape, dtype=torch.int64, device=self.device
        )
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=torch.float32, device=self.device)
        self.done_spec = done_spec(shape, self.device)

    # -- seeding and noise --------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        self.streams.seed(seed)

    def set_block_seeds(self, seeds) -> None:
        """Give each of ``len(seeds)`` equal, consecutive blocks of arms its own noise stream.

        With arms laid out block-major (e.g. one block per independent trial), block ``b`` then
        draws exactly the noise an env of one block seeded with ``seeds[b]`` would: a batched
        run of many trials reproduces one-at-a-time runs. ``set_seed`` returns to one stream.
        """
        self.streams.set_block_seeds(seeds)

    def sample_noise(self, num: int) -> torch.Tensor:
        """Torque noise for ``num`` arms, float64 [num, 2] (N m), from the env's stream(s)."""
        if num != self.batch_size.numel():  # not a whole batch: the single stream
            return self.streams.single.normal((num, 2)) * self.noise_std
        return self.streams.normal((num, 2)) * self.noise_std

    # -- dynamics -----------------------------------------------------------------------------

    @property
    def hit(self) -> torch.Tensor:
        """bool [E]: the bat has touched the ball in the current episode."""
        return torch.as_tensor(self.sim.hit.copy(), device=self.device)

    def _output(self, reward: np.ndarray | None) -> TensorDict:
        shape = self.batch_size
        obs = torch.as_tensor(self.sim.observation(), dtype=torch.float32, device=self.device)
        steps = torch.as_tensor(self._steps, device=self.device).unsqueeze(-1)
        truncated = steps >= self.max_steps
        terminated = torch.zeros_like(truncated)
        if self.end_at_hit:
            terminated = torch.as_tensor(self.sim.hit.copy(), device=self.device).unsqueeze(-1)
        out = {
            "observation": obs,
            "step_count": steps.clone(),
            "done": truncated | terminated,
            "terminated": terminated,
            "truncated": truncated & ~terminated,
        }
        if reward is not None:
            out["reward"] = torch.as_tensor(reward, dtype=torch.float32, device=self.device)
            out["reward"] = out["reward"].unsqueeze(-1)
        return TensorDict(out, batch_size=shape, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if mask is None:
            ids = np.arange(self.batch_size[0])
        else:
            ids = np.flatnonzero(mask.reshape(self.batch_size).cpu().numpy())
        self.sim.reset(ids)
        self._steps[ids] = 0
        return self._output(None)

    def _action_indices(self, action: torch.Tensor) -> np.ndarray:
        """Action indices [E] from indices [E], [E, 1] or a one-hot [E, 2]."""
        if action.ndim == 2 and action.shape[-1] == N_ACTIONS:
            action = action.argmax(-1)
        elif action.ndim == 2 and action.shape[-1] == 1:
            action = action.squeeze(-1)
        if action.shape != self.batch_size:
            raise ValueError(
                f"action must have shape {tuple(self.batch_size)} (indices) or "
                f"{(*self.batch_size, N_ACTIONS)} (one-hot), got {tuple(action.shape)}"
            )
        action = action.long().cpu().numpy()
        if ((action < 0) | (action >= N_ACTIONS)).any():
            raise ValueError(f"action indices must be 0 or 1, got {np.unique(action).tolist()}")
        return action

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self._action_indices(tensordict["action"])
        noise = self.sample_noise(self.batch_size[0]).numpy()
        torque = action_torques(action) + noise
        _, carry, first_hit = self.sim.step(torque)
        self.last_torque = torque
        self._steps += 1
        return self._output(np.where(first_hit, carry, 0.0))
