"""The two environments of ``torchrl_pipeline.py``: how each is built, its basis, its user's
own actor (a hand-made ``ProbabilisticActor`` candidate) and its default settings.

Both are Gymnasium's environments as ``GymEnv`` gives them (one-hot actions, the environment's
own time limit), with an ``ObservationNorm`` to unit scale and a ``StepCounter`` (episodes of
at most N steps). What differs:

- ``CartPole-v1`` (+1 a step until the pole falls or the cart leaves the track, at most 500
  steps): observations ``s / (2.4, 2, 0.21, 2)``; a quadratic basis (:class:`QuadraticActionBasis`:
  ``[1, s, upper triangle of s sᵀ]`` per action, B = 30); LSTD-Q, the weights flattened to ν = 0
  (docs/cartpole_remedies.md: with the paper's ν = 1 the per-decision weights over 200 steps
  collapse), γ = 0.95, a first iteration of 120 episodes of pi_1 (uniform), then 4 a iteration
  (docs/cartpole_remedies.md: 85 % of 80 seeds balanced at the end, against 77.5 % with 80 and 5).
- ``MountainCar-v0`` (-1 a step until the flag, at most 200): the observation box mapped to
  [-1, 1], the paper's Gaussian basis on a 5 × 5 grid (τ = 0.4), BRM with the paper's weights,
  γ = 0.99, 6 episodes an iteration: the case the example ran before CartPole.
"""

from __future__ import annotations

from functools import partial

import torch
from torch import nn

from torch_api import GaussianActionBasis

CARTPOLE, MOUNTAIN_CAR = "CartPole-v1", "MountainCar-v0"
ENVS = (CARTPOLE, MOUNTAIN_CAR)
CARTPOLE_SCALE = (2.4, 2.0, 0.21, 2.0)  # (m, m/s, rad, rad/s): the track, ~speeds, the fall angle

DEFAULTS = {
    CARTPOLE: {
        "iterations": 8,
        "first_episodes": 120,
        "episodes": 4,
        "steps": 200,
        "test_steps": 500,
        "test_episodes": 5,
        "gamma": 0.95,
        "basis": "quadratic",
        "fit": "lstd",
        "flattening": "0",
    },
    MOUNTAIN_CAR: {
        "iterations": 5,
        "first_episodes": 6,
        "episodes": 6,
        "steps": 200,
        "test_steps": 200,
        "test_episodes": 10,
        "gamma": 0.99,
        "basis": "grid",
        "fit": "brm",
        "flattening": "1",
    },
}
"""Each environment's settings where a flag is left at its ``0`` / ``"auto"`` default."""


class QuadraticActionBasis(GaussianActionBasis):
    """``phi(s, a) = e_a ⊗ [1, s, s_i s_j (i ≤ j)]``: a quadratic Q̂ per action.

    The block layout (state features times an action indicator) is
    :class:`~torch_api.core.basis.GaussianActionBasis`'s, so its fast paths (``q_values``,
    ``expected_phi``) serve; only the state features differ. For d = 4: 1 + 4 + 10 = 15 a
    block, B = 30 with two actions.

    Example:
        >>> QuadraticActionBasis(obs_dim=4, num_actions=2).num_features
        30
    """

    def __init__(self, *, obs_dim: int, num_actions: int) -> None:
        super().__init__(centers=torch.zeros(1, obs_dim), tau=1.0, num_actions=num_actions)
        self.register_buffer("pairs", torch.triu_indices(obs_dim, obs_dim))
        self.num_kernels = 1 + obs_dim + self.pairs.shape[1]
        self.num_features = self.num_actions * self.num_kernels

    def kernels(self, obs: torch.Tensor) -> torch.Tensor:
        """``[1, s, s_i s_j]``: obs ``[..., d]`` -> ``[..., 1 + d + d(d+1)/2]``."""
        obs = obs if obs.is_floating_point() else obs.to(torch.get_default_dtype())
        if obs.shape[-1] != self.obs_dim:
            raise ValueError(f"obs must end in {self.obs_dim}, got {tuple(obs.shape)}")
        i, j = self.pairs.to(obs.device)
        return torch.cat([torch.ones_like(obs[..., :1]), obs, obs[..., i] * obs[..., j]], -1)


def make_basis(env_id: str, kind: str, grid: int, tau: float) -> GaussianActionBasis:
    """The basis ``kind`` (``"quadratic"`` or ``"grid"``: Gaussians on a grid^d lattice over
    the normalised box, width ``tau``) for ``env_id``'s observations."""
    obs_dim, num_actions = (4, 2) if env_id == CARTPOLE else (2, 3)
    if kind == "quadratic":
        return QuadraticActionBasis(obs_dim=obs_dim, num_actions=num_actions)
    axis = torch.linspace(-1, 1, grid)
    centers = torch.cartesian_prod(*[axis] * obs_dim).reshape(-1, obs_dim)
    return GaussianActionBasis(centers=centers, tau=tau, num_actions=num_actions)


def make_env(env_id: str, max_steps: int):
    """One ``GymEnv(env_id)`` (one-hot actions), observations to unit scale, at most
    ``max_steps`` steps an episode."""
    from torchrl.envs import Compose, GymEnv, ObservationNorm, StepCounter, TransformedEnv

    env = GymEnv(env_id)
    if env_id == CARTPOLE:
        center, scale = torch.zeros(4), torch.tensor(CARTPOLE_SCALE)
    else:
        box = env.observation_spec["observation"].space
        center, scale = (box.high + box.low) / 2, (box.high - box.low) / 2
    norm = ObservationNorm(loc=center, scale=scale, in_keys=["observation"], standard_normal=True)
    return TransformedEnv(env, Compose(norm, StepCounter(max_steps=max_steps)))


class HandMadeRule(nn.Module):
    """Logits of the user's hand-made rule. MountainCar: push the way the car moves (it pumps
    energy into the swing). CartPole: push the way the pole falls (angle plus angular speed)."""

    def __init__(self, env_id: str, sharpness: float = 30.0) -> None:
        super().__init__()
        self.env_id, self.sharpness = env_id, sharpness

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if self.env_id == CARTPOLE:
            lean = observation[..., 2:3] + observation[..., 3:4]  # normalised angle + speed
            return self.sharpness * torch.cat([-lean, lean], -1)
        velocity = observation[..., 1:2]  # normalised, in [-1, 1]
        return self.sharpness * torch.cat([-velocity, torch.zeros_like(velocity), velocity], -1)


def make_actor(env_id: str, action_spec):
    """The user's own candidate: a ``ProbabilisticActor`` over :class:`HandMadeRule`."""
    from tensordict.nn import TensorDictModule
    from torchrl.modules import OneHotCategorical, ProbabilisticActor

    return ProbabilisticActor(
        TensorDictModule(HandMadeRule(env_id), in_keys=["observation"], out_keys=["logits"]),
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
        return_log_prob=True,  # the sampling probability the importance weights need
        spec=action_spec,
    )


def env_rows(args, rows: int, steps: int, seed: int | None = None):
    """``rows`` of :func:`make_env` in one ``SerialEnv``, seeded if ``seed`` is given."""
    from torchrl.envs import SerialEnv

    env = SerialEnv(rows, partial(make_env, args.env, steps))
    if seed is not None:
        env.set_seed(seed)
    return env


def mean_return(policy, env, steps: int, exploration) -> float:
    """Mean return of one ``env.rollout`` of ``policy`` (one episode a row of ``env``)."""
    from torchrl.envs.utils import set_exploration_type

    from torch_api.data.episodes import as_episodes

    with set_exploration_type(exploration):
        rollout = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    done = as_episodes(rollout, rewarded=True)  # steps after each episode's end are masked
    return float((done["next", "reward"] * done["mask"]).sum(-1).mean())


def actor_alone(args, seed: int) -> float:
    """The user's actor alone, sampling: the mean return of its test episodes."""
    env = make_env(args.env, args.test_steps)
    actor = make_actor(args.env, env.action_spec)
    from torchrl.envs.utils import ExplorationType

    from torch_api.streams import derive_seed

    torch.manual_seed(stream := derive_seed(seed, 0, "evaluation"))
    test_env = env_rows(args, args.test_episodes, args.test_steps, stream)
    value = mean_return(actor, test_env, args.test_steps, ExplorationType.RANDOM)
    print(f"seed {seed}: the actor alone (sampling): mean return {value:.1f}")
    return value


ACTOR_NAME = {
    CARTPOLE: "push the way the pole falls (ProbabilisticActor)",
    MOUNTAIN_CAR: "push with velocity (ProbabilisticActor)",
}
