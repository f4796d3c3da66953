"""LSTD-Q: the fixed-point fit of Q̂ and its reward-free error estimate (beyond the paper).

The paper fits θ by weighted least squares of the rewards on the psi_hat rows (eq. 22-28), a
Bellman-residual fit. LSTD-Q instead solves the projected fixed point

    θ = (Â + λI)^{-1} b̂,   Â = (1/n) Σ w_i phi_i x_iᵀ,   b̂ = (1/n) Σ w_i phi_i r_i,

with ``phi_i = phi(s_i, a_i)`` and ``x_i`` the psi_hat row of sample i (``phi - γ E phi'``), so
``θ = L r`` with ``L = (Â + λI)^{-1} (1/n) Φᵀ W``. The generalisation-error estimate of
Algorithm 2 carries over unchanged in form, ``J = tr(Ũ L Lᵀ)``:

    J_k = tr( Ũ (A_k + λI)^{-1} C_k (A_k + λI)^{-T} ),
    A_k = (1/n_k) Σ w phi xᵀ,  C_k = (1/n_k²) Σ w² phi phiᵀ,  Ũ = (1/n_0) Σ w x xᵀ over D̄_0,

where Â is no longer symmetric (an LU solve replaces the Cholesky factorisation).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torch_api._checks import all_finite
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.core.solve import weighted_moment
from torch_api.core.weights import flatten_weights

__all__ = ["lstd_j_from_moments", "lstd_j_values", "phi_rows", "weighted_lstd"]

_KEYS = (
    "observation",
    "action",
    "sample_probs",
    "sample_log_prob",  # (a TorchRL actor's log-probability of its action, torch_api.data)
    ("next", "observation"),
    ("next", "terminated"),
)


def phi_rows(episodes: TensorDictBase, basis) -> torch.Tensor:
    """``phi(s, a)`` of every sample, laid out as the rows of
    :func:`~torch_api.core.design.build_design`.

    episodes ``[..., M, N]`` -> ``[..., M·N, B]`` float64, zero on padding.
    """
    obs = episodes["observation"]
    lead = obs.shape[:-3]
    flat_obs = obs.reshape(*lead, -1, obs.shape[-1]).to(torch.float64)
    action = episodes["action"]
    action = action.reshape(*lead, -1, *action.shape[len(lead) + 2 :])
    mask = episodes["mask"].reshape(*lead, -1)
    return basis.phi(flat_obs, action) * mask.unsqueeze(-1).to(torch.float64)


def _lstd_moment(phi: torch.Tensor, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``Σ_i w_i phi_i x_iᵀ``: ``[..., n, B] × [..., n, B] × [..., n] -> [..., B, B]``."""
    return (phi * w.to(phi.dtype).unsqueeze(-1)).mT @ x.to(phi.dtype)


def _regularised(a: torch.Tensor, lam: float) -> torch.Tensor:
    if not lam > 0:
        raise ValueError(f"lam must be > 0, got {lam}")
    return a + lam * torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)


def weighted_lstd(
    phi: torch.Tensor,
    x: torch.Tensor,
    w: torch.Tensor,
    reward: torch.Tensor,
    lam: float,
    *,
    num_samples: torch.Tensor,
) -> torch.Tensor:
    """θ of LSTD-Q: ``(Â + λI)^{-1} b̂`` (module docstring), batched over leading dims.

    Args:
        phi: ``phi(s, a)`` rows ``[..., n, B]`` (:func:`phi_rows`; zero on padding).
        x: psi_hat rows ``[..., n, B]``; w: importance weights ``[..., n]`` (zero on padding).
        reward: ``[..., n]``.
        lam: λ > 0.
        num_samples: n per data set ``[...]`` (real samples, padding excluded).

    Returns:
        θ ``[..., B]`` in float64.
    """
    if phi.shape != x.shape:
        raise ValueError(f"phi {tuple(phi.shape)} and x {tuple(x.shape)} must have one shape")
    n = num_samples.to(torch.float64).clamp_min(1)[..., None, None]
    a = _lstd_moment(phi.to(torch.float64), x, w) / n
    b = (phi.to(torch.float64) * (w * reward).to(torch.float64).unsqueeze(-1)).sum(-2)
    theta = torch.linalg.solve(_regularised(a, lam), b.unsqueeze(-1) / n)
    return theta.squeeze(-1)


def lstd_j_from_moments(
    a: torch.Tensor, c: torch.Tensor, u: torch.Tensor, lam: float
) -> torch.Tensor:
    """``J = tr(U (A + λI)^{-1} C (A + λI)^{-T})`` for the non-symmetric LSTD ``A``.

    a ``[..., B, B]``, c and u symmetric ``[..., B, B]`` (u broadcast against a) -> ``[...]``.
    """
    m = _regularised(a, lam)
    y = torch.linalg.solve(m, c)  # M^{-1} C
    inner = torch.linalg.solve(m, y.mT)  # M^{-1} C M^{-T}, symmetric
    u = u.to(a.dtype).expand(*a.shape[:-2], *u.shape[-2:]) if u.ndim < a.ndim else u.to(a.dtype)
    return (u * inner).sum((-2, -1))


def lstd_j_values(
    candidate_episodes: TensorDictBase,
    earlier_episodes: TensorDictBase | None,
    policy,
    psi: PsiHat,
    lam: float,
    *,
    flattening: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """J of every candidate for an LSTD-Q learner, like :func:`~torch_api.loop.selector.j_values`.

    Needs a psi_hat whose rows depend on their own transition only (``psi.row_local``: the
    paper's single-sample choice for continuous states).

    Args:
        candidate_episodes: reward-free episodes ``[..., K, M, N]``.
        earlier_episodes: earlier sampling sets ``[*T, M', N]`` (rewards not read) or None.
        policy: the evaluation policy; psi: the psi_hat module; lam: λ > 0.
        flattening: ν of the fit's flattened weights, a number or ``[*T]`` per trial
            (docs/flattening.md, eq. F3): ``A_k`` takes ``w^ν``, ``C_k`` ``w^{2ν}``, Ũ keeps w.

    Returns:
        J ``[..., K]`` (float64).
    """
    if not psi.row_local:
        raise ValueError(
            f"LSTD-Q's J needs a row-local psi_hat (mode 'single'), got mode {psi.mode!r}"
        )
    if candidate_episodes.batch_dims < 3:
        raise ValueError(
            "candidate_episodes must have shape [..., K, M, N], "
            f"got {tuple(candidate_episodes.shape)}"
        )
    keys = [k for k in _KEYS if k in candidate_episodes.keys(include_nested=True)]
    cand = candidate_episodes.select(*keys, "mask")
    lead = cand.shape[:-3]

    def moments(episodes):
        design = build_design(episodes, policy, psi, min_ess_fraction=0.0)
        phi = phi_rows(episodes, psi.basis)
        nu = flattening
        if isinstance(nu, torch.Tensor):  # one ν per trial [*T]: broadcast over the rest
            nu = nu.reshape(*nu.shape, *[1] * (design.w.ndim - nu.ndim))
        w_nu = flatten_weights(design.w, nu)
        return (
            _lstd_moment(phi, design.x, w_nu),  # Σ w^ν phi xᵀ
            weighted_moment(phi, w_nu.pow(2)),  # Σ w^{2ν} phi phiᵀ
            weighted_moment(design.x, design.w),  # Σ w x xᵀ
            design.num_samples.to(torch.float64),
        )

    a_own, c_own, u_own, n_own = moments(cand)  # [..., K, B, B], [..., K]
    a_sh = c_sh = u_sh = a_own.new_zeros(a_own.shape[-2:])
    n_sh = n_own.new_zeros(())
    if earlier_episodes is not None and earlier_episodes.shape[-2] > 0:
        prev_keys = [k for k in _KEYS if k in earlier_episodes.keys(include_nested=True)]
        prev = earlier_episodes.select(*prev_keys, "mask")
        a_sh, c_sh, u_sh, n_sh = moments(prev)  # [*T, B, B], [*T]
        stretch = [1] * (len(lead) - (prev.batch_dims - 2))  # the repeat dims prev lacks
        a_sh, c_sh, u_sh = (
            m.reshape(*m.shape[:-2], *stretch, *m.shape[-2:]) for m in (a_sh, c_sh, u_sh)
        )
        n_sh = n_sh.reshape(*n_sh.shape, *stretch)
    n_k = (n_own + n_sh.unsqueeze(-1))[..., None, None]
    n_0 = (n_own.sum(-1) + n_sh)[..., None, None]
    u_tilde = (u_own.sum(-3) + u_sh) / n_0
    a_k = (a_own + a_sh.unsqueeze(-3)) / n_k
    c_k = (c_own + c_sh.unsqueeze(-3)) / n_k.pow(2)
    if not (all_finite(a_k) and all_finite(c_k)):
        raise ValueError("the LSTD design of the reward-free data contains NaN or inf")
    return lstd_j_from_moments(a_k, c_k, u_tilde.unsqueeze(-3), lam)
