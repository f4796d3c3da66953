"""From episodes to a regression design: psi_hat rows, importance weights and rewards.

This joins :mod:`torch_api.psi` (eq. 20) and :mod:`torch_api.weights` (eq. 21) on the episode
format of :mod:`torch_api.data` for one evaluation policy.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from tensordict import TensorDictBase

from torch_api.data import REWARD_KEY
from torch_api.psi import PsiHat
from torch_api.weights import per_decision_weights

__all__ = ["Design", "build_design"]


class Design(NamedTuple):
    """A data set flattened to samples, ready for ``weighted_ridge`` and ``j_criterion``.

    Attributes:
        x: psi_hat rows ``[..., n, B]`` (float64; zero on padding).
        w: per-decision importance weights w.r.t. the evaluation policy ``[..., n]``
            (zero on padding).
        mask: real samples ``[..., n]``.
        reward: rewards ``[..., n]`` (zero on padding), or None for reward-free data.
        num_samples: count of real samples per data set ``[...]`` (the ``n`` of ``1/n``).
    """

    x: torch.Tensor
    w: torch.Tensor
    mask: torch.Tensor
    reward: torch.Tensor | None
    num_samples: torch.Tensor


def taken_probs(probs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Probability of each taken action: ``[..., A]``, ``[...]`` -> ``[...]``."""
    return torch.gather(probs, -1, action.unsqueeze(-1)).squeeze(-1)


def build_design(episodes: TensorDictBase, policy, psi: PsiHat) -> Design:
    """psi_hat (eq. 20) and weights (eq. 21) of a data set under an evaluation policy.

    The data set ``D`` of eq. 20 is everything in ``episodes`` along its last two dims: every
    ``[M, N]`` slice is one data set (leading dims, e.g. ``[Z]`` repeats, are independent).

    Args:
        episodes: TensorDict ``[..., M, N]`` in the format of :mod:`torch_api.data`.
        policy: the evaluation policy pi, with ``action_probs(obs [..., d]) -> [..., A]``; its
            parameters' leading dims (e.g. a trial dimension) must prefix ``[...]``.
        psi: the psi_hat module (basis, γ, grouping mode).

    Returns:
        :class:`Design` with ``n = M N``.
    """
    obs = episodes["observation"]
    action = episodes["action"]
    next_obs = episodes["next", "observation"]
    mask = episodes["mask"]
    terminated = episodes.get(("next", "terminated"), None)
    target = policy.action_probs(obs)
    weights = per_decision_weights(
        taken_probs(target, action),
        taken_probs(episodes["sample_probs"], action).to(torch.float64),
        mask,
    )
    next_probs = policy.action_probs(next_obs)

    def flat(t: torch.Tensor, tail: int) -> torch.Tensor:
        lead = t.shape[: t.ndim - tail]
        return t.reshape(*lead[:-2], lead[-2] * lead[-1], *t.shape[t.ndim - tail :])

    x = psi(
        flat(obs, 1),
        flat(action, 0),
        flat(next_obs, 1),
        flat(next_probs, 1),
        None if terminated is None else flat(terminated, 0),
        flat(mask, 0),
    )
    flat_mask = flat(mask, 0)
    reward = episodes.get(REWARD_KEY, None)
    if reward is not None:
        reward = flat(reward, 0).to(torch.float64) * flat_mask
    return Design(
        x=x,
        w=flat(weights, 0),
        mask=flat_mask,
        reward=reward,
        num_samples=flat_mask.sum(-1),
    )
