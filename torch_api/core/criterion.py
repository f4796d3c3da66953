"""The active-learning criterion: the pooled moments of each candidate, and J of them.

Three J functions, from the most raw to the most assembled; a user calls:

* :func:`j_values` with reward-free *episodes* of K candidates (what
  :class:`~torch_api.loop.selector.SamplingPolicySelector` does): psi_hat, importance weights,
  pooling with the earlier sets (:func:`pooled_moments`), then a criterion;
* :func:`~torch_api.core.solve.j_from_moments` with normalised *moments* ``A``, ``C``, ``Ũ`` already
  at hand (the criterion of eq. 46 itself, :func:`j_eq46`, calls it);
* :func:`~torch_api.core.solve.j_criterion` with one sampling set's *design rows* ``x``, ``w``
  (``[..., n, B]``): the textbook form of eq. 40-46, for analysis and tests.

A criterion is any function ``(moments: PooledMoments, lam: float) -> Tensor [..., K]``
(smaller is better): the paper's J (eq. 46) is :func:`j_eq46`, the default; another criterion
(e.g. one of the paper's "future work" variants) is a new function of the same signature,
passed as ``criterion=`` to :func:`j_values` or to the selector.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from tensordict import TensorDictBase

from torch_api._checks import all_finite
from torch_api.core.design import build_design
from torch_api.core.grouped_design import group_sums, grouped_design
from torch_api.core.psi import PsiHat
from torch_api.core.solve import DEFAULT_LAMBDA, j_from_moments, weighted_moment
from torch_api.core.weights import flatten_weights
from torch_api.data.episodes import as_episodes, joinable

__all__ = ["Criterion", "PooledMoments", "j_eq46", "j_values", "pooled_moments"]

_STATE_ACTION_KEYS = (
    "observation",
    "action",
    "sample_probs",
    "sample_log_prob",
    ("next", "observation"),
    ("next", "terminated"),
    "mask",
)


class PooledMoments(NamedTuple):
    """What every criterion sees: each candidate's pooled, normalised moments (eq. 42-45).

    Attributes:
        a: ``A_k = (1/n_k) Σ_{Π_k} w x xᵀ``, ``[..., K, B, B]``.
        c: ``C_k = (1/n_k²) Σ_{Π_k} w² x xᵀ``, ``[..., K, B, B]``.
        u: ``Ũ = (1/n_0) Σ_{D̄_0} w x xᵀ`` over all candidates' and earlier rows,
            ``[..., 1, B, B]`` (broadcasts against ``a``).
        n: ``n_k``, the rows of ``Π_k``, ``[..., K]``.
    """

    a: torch.Tensor
    c: torch.Tensor
    u: torch.Tensor
    n: torch.Tensor


Criterion = Callable[[PooledMoments, float], torch.Tensor]
"""The signature of a criterion: ``(moments, lam) -> [..., K]``, smaller is better."""


def j_eq46(moments: PooledMoments, lam: float = DEFAULT_LAMBDA) -> torch.Tensor:
    """The paper's criterion: ``J_k = tr(Ũ (A_k + λI)^{-1} C_k (A_k + λI)^{-1})`` (eq. 46).

    Example (a criterion of one's own has this signature):
        >>> eye = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
        >>> moments = PooledMoments(a=eye, c=eye / 10, u=eye[:1], n=torch.tensor([10.0, 10.0]))
        >>> j_eq46(moments, lam=0.0).tolist()
        [0.30000000000000004, 0.30000000000000004]
        >>> def trace_of_c(moments, lam):  # another criterion: a new function, same signature
        ...     return moments.c.diagonal(dim1=-2, dim2=-1).sum(-1)
        >>> trace_of_c(moments, 0.0).tolist()
        [0.30000000000000004, 0.30000000000000004]
    """
    return j_from_moments(moments.a, moments.c, moments.u, lam)


def j_values(
    candidate_episodes: TensorDictBase,
    earlier_episodes: TensorDictBase | None,
    policy,
    psi: PsiHat,
    lam: float = DEFAULT_LAMBDA,
    *,
    criterion: Criterion = j_eq46,
    flattening: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """J of every candidate from reward-free episodes (eq. 42-46, Algorithm 2 steps 2-4).

    The call a user makes with episodes in hand: :func:`pooled_moments`, then ``criterion``
    (J of eq. 46 by default), all K candidates and all leading indices in one batched call.

    Args:
        candidate_episodes: reward-free episodes ``[..., K, M, N]``.
        earlier_episodes: earlier sampling sets ``[M', N']`` or None (see
            :func:`pooled_moments`).
        policy: the evaluation policy (``action_probs``); parameters' leading dims prefix
            ``[...]``.
        psi: the psi_hat module.
        lam: λ.
        criterion: ``(PooledMoments, lam) -> [..., K]`` (:data:`Criterion`).
        flattening: ν of the fit's flattened weights (see :func:`pooled_moments`).

    Returns:
        J ``[..., K]`` (float64).
    """
    moments = pooled_moments(
        candidate_episodes, earlier_episodes, policy, psi, flattening=flattening
    )
    return criterion(moments, lam)


def _per_trial(nu, w: torch.Tensor):
    """ν (a number, or ``[*T]`` per trial) shaped to broadcast against weights ``[*T, ..., n]``."""
    if not isinstance(nu, torch.Tensor):
        return nu
    return nu.reshape(*nu.shape, *[1] * (w.ndim - nu.ndim))


def _flat_moments(x, w, nu):
    """``Σ w^ν x xᵀ``, ``Σ w^{2ν} x xᵀ`` and the unflattened ``Σ w x xᵀ`` of Ũ (eq. F2)."""
    w_nu = flatten_weights(w, _per_trial(nu, w))
    a = weighted_moment(x, w_nu)
    u = a if w_nu is w else weighted_moment(x, w)
    return a, weighted_moment(x, w_nu.pow(2)), u


def pooled_moments(
    candidate_episodes: TensorDictBase,
    earlier_episodes: TensorDictBase | None,
    policy,
    psi: PsiHat,
    *,
    flattening: float | torch.Tensor = 1.0,
) -> PooledMoments:
    """The pooled moments of every candidate from reward-free episodes (eq. 42-45).

    For each leading index (a repeat z, a trial, ...): ``D̄_0`` = all candidates' episodes plus
    the earlier sampling sets; psi_hat is computed on ``D̄_0`` under the evaluation policy;
    ``Ũ = (1/n_0) Σ_{D̄_0} w x xᵀ``; candidate k's set ``Π_k`` = its own episodes plus the
    earlier sets, with ``A_k = (1/n_k) Σ_{Π_k} w x xᵀ`` and ``C_k = (1/n_k²) Σ_{Π_k} w² x xᵀ``.

    Args:
        candidate_episodes: reward-free episodes ``[..., K, M, N]``.
        earlier_episodes: earlier sampling sets ``[M', N']`` (rewards, if any, are ignored) or
            None in the first iteration; TorchRL data as TorchRL produces it (a ``Collector``'s
            batch, ``env.rollout`` output) is converted (:func:`~torch_api.data.as_episodes`).
            Episodes of another length than the candidates' are padded (masked).
        policy: the evaluation policy (``action_probs``); parameters' leading dims prefix
            ``[...]``.
        psi: the psi_hat module.
        flattening: ν of the flattened weights the fit will use (docs/flattening.md, eq. F2),
            a number or one per trial ``[*T]`` (the leading dims of the policy's parameters):
            ``A_k`` takes ``w^ν``, ``C_k`` takes ``w^{2ν}``, while ``Ũ`` keeps w (it measures
            the error under the evaluation policy). ν = 1: the paper's moments, as before.

    Returns:
        :class:`PooledMoments` with ``a``, ``c`` ``[..., K, B, B]``, ``u`` ``[..., 1, B, B]``
        and ``n`` ``[..., K]``.
    """
    if candidate_episodes.batch_dims < 3:
        raise ValueError(
            "candidate_episodes must have shape [..., K, M, N], "
            f"got {tuple(candidate_episodes.shape)}"
        )
    cand = candidate_episodes.select(*_STATE_ACTION_KEYS, strict=False)
    prev = None
    if earlier_episodes is not None:
        earlier_episodes = as_episodes(earlier_episodes, rewarded=False)
    if earlier_episodes is not None and earlier_episodes.shape[0] > 0:
        prev = earlier_episodes.select(*_STATE_ACTION_KEYS, strict=False)
        cand, prev = joinable([cand, prev])
    *lead, num_candidates, num_episodes, num_steps = cand.shape
    # Far candidates (ε up to 1) have skewed weights by design, and J measures exactly that:
    # the collapse warning is for fits on rewarded data, not for this reward-free pool.
    if psi.row_local:
        # Each row's psi_hat depends on the row alone: the earlier sets, which every Π_k and
        # every repeat shares, get their design once, not once per repeat.
        own = build_design(cand, policy, psi, min_ess_fraction=0.0)  # [..., K, M·N, B]
        own_x, own_w, n_own = own.x, own.w, own.num_samples.to(torch.float64)
        shared = None if prev is None else build_design(prev, policy, psi, min_ess_fraction=0.0)
    else:
        # Grouped or k-NN psi_hat averages over the data set D̄_0 of each repeat (all K
        # candidates' episodes, plus the earlier sets when there are any): pool first.
        pieces = [cand.reshape(*lead, num_candidates * num_episodes, num_steps)]
        if prev is not None:
            own_lead = prev.batch_dims - 2  # earlier sets [*T, M', N]: broadcast over repeats
            prev = prev.reshape(
                *prev.shape[:own_lead], *[1] * (len(lead) - own_lead), *prev.shape[-2:]
            )
            pieces.append(prev.expand(*lead, *prev.shape[-2:]).clone())
        split = num_candidates * num_episodes * num_steps
        if psi.mode == "grouped":  # one psi_hat row per (s, a): the moments are group sums
            pool = torch.cat(pieces, dim=-2)
            return _grouped_moments(pool, policy, psi, split, num_candidates, flattening)
        design = build_design(torch.cat(pieces, dim=-2), policy, psi, min_ess_fraction=0.0)

        def own_rows(t: torch.Tensor) -> torch.Tensor:  # [..., K, M·N, *]
            return t.narrow(len(lead), 0, split).reshape(
                *lead, num_candidates, num_episodes * num_steps, *t.shape[len(lead) + 1 :]
            )

        own_x, own_w = own_rows(design.x), own_rows(design.w)
        n_own = own_rows(design.mask).sum(-1).to(torch.float64)
        shared = None
        if prev is not None:
            shared = design._replace(
                x=design.x.narrow(len(lead), split, design.x.shape[len(lead)] - split),
                w=design.w.narrow(len(lead), split, design.w.shape[len(lead)] - split),
                num_samples=design.num_samples - n_own.sum(-1),
            )
    return _normalised(*_moments(own_x, own_w, n_own, shared, len(lead), flattening))


def _moments(own_x, own_w, n_own, shared, lead_dims: int, flattening):
    """Unnormalised moments of each candidate's own rows and of the shared earlier rows: A's
    (``w^ν``), C's (``w^{2ν}``) and Ũ's (w) sums (eq. F2)."""
    a_own, c_own, u_own = _flat_moments(own_x, own_w, flattening)  # [..., K, B, B]
    a_shared = c_shared = u_shared = own_x.new_zeros(own_x.shape[-1], own_x.shape[-1])
    n_shared = n_own.new_zeros(())
    if shared is not None:
        stretch = [1] * (lead_dims + 2 - shared.x.ndim)  # dims (repeats) the shared rows lack
        a_shared, c_shared, u_shared = (
            m.reshape(*m.shape[:-2], *stretch, *m.shape[-2:])
            for m in _flat_moments(shared.x, shared.w, flattening)
        )
        n_shared = shared.num_samples.to(torch.float64)
        n_shared = n_shared.reshape(*n_shared.shape, *stretch)
    return a_own, c_own, u_own, n_own, a_shared, c_shared, u_shared, n_shared


def _grouped_moments(pool, policy, psi: PsiHat, split: int, num_candidates: int, flattening):
    """The pooled moments of grouped psi_hat from group sums (:mod:`torch_api.core.grouped_design`):
    ``Σ_i w_i x_i x_iᵀ = Σ_g (Σ_{i∈g} w_i) x_g x_gᵀ``; the first ``split`` samples of each
    pool ``[..., K·M + M', N]`` are the K candidates' (equal shares), the rest the earlier sets."""
    design = grouped_design(pool, policy, psi)
    x, width = design.x, design.x.shape[-2]
    lead = x.shape[:-2]

    def moments(weights: torch.Tensor, group: torch.Tensor) -> tuple[torch.Tensor, ...]:
        rows = x.unsqueeze(-3) if weights.ndim > x.ndim - 1 else x  # [..., (1,) G, B]
        w_nu = flatten_weights(weights, _per_trial(flattening, weights))

        def summed(w: torch.Tensor) -> torch.Tensor:  # Σ_g (Σ_{i∈g} w_i) x_g x_gᵀ
            return (rows * group_sums(w, group, width).unsqueeze(-1)).mT @ rows

        # A's, C's and Ũ's weights: w^ν, w^2ν, w (eq. F2); at ν = 1 Ũ's sum is A's
        a = summed(w_nu)
        return a, summed(w_nu.pow(2)), a if w_nu is weights else summed(weights)

    own = (*lead, num_candidates, split // num_candidates)
    own_w, own_group = design.w[..., :split].reshape(own), design.group[..., :split].reshape(own)
    n_own = design.mask[..., :split].reshape(own).sum(-1).to(torch.float64)
    shared = moments(design.w[..., split:], design.group[..., split:])
    n_shared = design.mask[..., split:].sum(-1).to(torch.float64)
    return _normalised(*moments(own_w, own_group), n_own, *shared, n_shared)


def _normalised(a_own, c_own, u_own, n_own, a_shared, c_shared, u_shared, n_shared):
    """A_k, C_k of each candidate's Π_k and Ũ of D̄_0 (all candidates' rows and the shared
    ones, with no pass of its own) from the unnormalised moments: :class:`PooledMoments`."""
    n_k = (n_own + n_shared.unsqueeze(-1))[..., None, None]
    n_0 = (n_own.sum(-1) + n_shared)[..., None, None]
    u_tilde = (u_own.sum(-3) + u_shared) / n_0  # eq. 42 over D̄_0
    a_k = (a_own + a_shared.unsqueeze(-3)) / n_k  # A of Π_k
    c_k = (c_own + c_shared.unsqueeze(-3)) / n_k.pow(2)  # C of Π_k
    if not (all_finite(a_k) and all_finite(c_k)):
        raise ValueError("the psi_hat design of the reward-free data contains NaN or inf")
    return PooledMoments(a=a_k, c=c_k, u=u_tilde.unsqueeze(-3), n=n_k[..., 0, 0])
