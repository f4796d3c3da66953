"""From episodes to a regression design: psi_hat rows, importance weights and rewards.

This joins :mod:`torch_api.core.psi` (eq. 20) and :mod:`torch_api.core.weights` (eq. 21) on
the episode format of :mod:`torch_api.data` for one evaluation policy.
"""

from __future__ import annotations

import warnings
from contextlib import nullcontext
from typing import NamedTuple

import torch
from tensordict import TensorDictBase

from torch_api.core.psi import PsiHat
from torch_api.core.weights import effective_sample_size, per_decision_weights
from torch_api.data.episodes import REWARD_KEY, taken_sample_probs

__all__ = ["CollapsedWeightsWarning", "Design", "build_design"]


class CollapsedWeightsWarning(RuntimeWarning):
    """Importance weights whose effective sample size fell below a fraction of n.

    Attributes (of the data set with the lowest ESS / n): ``ess``, ``n``; and ``collapsed``
    of ``sets`` data sets collapsed. A program can count these instead of reading the message.
    """

    def __init__(self, message: str, ess: float, n: int, collapsed: int, sets: int) -> None:
        super().__init__(message)
        self.ess, self.n, self.collapsed, self.sets = ess, n, collapsed, sets


DEFAULT_MIN_ESS_FRACTION = 0.01  # warn when a data set's effective sample size falls below this


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


def build_design(
    episodes: TensorDictBase,
    policy,
    psi: PsiHat,
    *,
    min_ess_fraction: float = DEFAULT_MIN_ESS_FRACTION,
) -> Design:
    """psi_hat (eq. 20) and weights (eq. 21) of a data set under an evaluation policy.

    The data set ``D`` of eq. 20 is everything in ``episodes`` along its last two dims: every
    ``[M, N]`` slice is one data set (leading dims, e.g. ``[Z]`` repeats, are independent).

    Args:
        episodes: TensorDict ``[..., M, N]`` in the format of :mod:`torch_api.data`.
        policy: the evaluation policy pi, with ``action_probs(obs [..., d]) -> [..., A]``; its
            parameters' leading dims (e.g. a trial dimension) must prefix ``[...]``.
        psi: the psi_hat module (basis, γ, grouping mode).
        min_ess_fraction: warn (``RuntimeWarning``) when a data set's effective sample size
            ``(Σ w)² / Σ w²`` falls below this fraction of its samples: the importance weights
            are so skewed that a few episodes decide the fit.

    Returns:
        :class:`Design` with ``n = M N``.
    """
    mask = episodes["mask"]
    terminated = episodes.get(("next", "terminated"), None)

    def flat(t: torch.Tensor, tail: int) -> torch.Tensor:  # [..., M, N, *tail] -> [..., M·N, *]
        lead = t.shape[: t.ndim - tail]
        return t.reshape(*lead[:-2], lead[-2] * lead[-1], *t.shape[t.ndim - tail :])

    # The same float64 tensors go to the policy and to psi_hat, so that a basis with
    # ``reuse_kernels`` evaluates the state kernels of each observation once, not twice.
    obs = flat(episodes["observation"], 1).to(torch.float64)
    next_obs = flat(episodes["next", "observation"], 1).to(torch.float64)
    action = flat(episodes["action"], 0)
    reuse = getattr(psi.basis, "reuse_kernels", None)
    with reuse() if reuse is not None else nullcontext():
        target = policy.action_probs(obs).reshape(*mask.shape, -1)
        next_probs = policy.action_probs(next_obs)
        x = psi(
            obs,
            action,
            next_obs,
            next_probs,
            None if terminated is None else flat(terminated, 0),
            flat(mask, 0),
        )
    weights = per_decision_weights(
        taken_probs(target, episodes["action"]), taken_sample_probs(episodes), mask
    )
    flat_mask = flat(mask, 0)
    flat_weights = flat(weights, 0)
    _warn_on_collapsed_weights(flat_weights, flat_mask, min_ess_fraction)
    reward = episodes.get(REWARD_KEY, None)
    if reward is not None:
        reward = flat(reward, 0).to(torch.float64) * flat_mask
    return Design(
        x=x,
        w=flat_weights,
        mask=flat_mask,
        reward=reward,
        num_samples=flat_mask.sum(-1),
    )


def _warn_on_collapsed_weights(w: torch.Tensor, mask: torch.Tensor, fraction: float) -> None:
    ess = effective_sample_size(w)
    n = mask.sum(-1).to(ess.dtype)
    collapsed = ess < fraction * n
    if collapsed.any():
        worst = int(torch.argmin(ess / n.clamp_min(1)).item()) if ess.ndim else 0
        flat_ess, flat_n = ess.reshape(-1), n.reshape(-1)
        ess_w, n_w, count = flat_ess[worst].item(), int(flat_n[worst]), int(collapsed.sum())
        message = (
            f"importance weights collapsed: effective sample size {ess_w:.2f} of "
            f"n = {n_w} samples (below {fraction:.0%}) in {count} of {collapsed.numel()} data "
            "set(s); the sampling policy is far from the evaluation policy, and a few episodes "
            "decide the fit"
        )
        warnings.warn(
            CollapsedWeightsWarning(message, ess_w, n_w, count, collapsed.numel()), stacklevel=3
        )
