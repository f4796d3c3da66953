"""Weighted regularised least squares and the J criterion (paper eq. 22-28, 40-46).

Everything here is a pure, batched tensor function over leading dimensions ``[...]`` (for
example trials ``T``, repeats ``Z`` and candidates ``K``). Solves run in float64 by default with
a Cholesky factorisation; no explicit inverse is ever formed.
"""

from __future__ import annotations

import warnings

import torch

from torch_api._checks import _check_not_meta, all_finite
from torch_api.core.weights import flatten_weights

__all__ = [
    "j_criterion",
    "j_from_moments",
    "weighted_moment",
    "weighted_ridge",
]

DEFAULT_LAMBDA = 1e-3  # the paper's regularisation (sections 3.5, 4.2, 5)
_ILL_CONDITIONED = 1e10  # condition number of A + λI above which a solve is reported


def _check_design(x: torch.Tensor, w: torch.Tensor, lam: float) -> None:
    _check_not_meta("x", x)
    _check_not_meta("w", w)
    if x.ndim < 2:
        raise ValueError(f"x must have shape [..., n, B], got {tuple(x.shape)}")
    if w.shape != x.shape[:-1]:
        raise ValueError(
            f"w must have shape {tuple(x.shape[:-1])} (x without its last dim), "
            f"got {tuple(w.shape)}"
        )
    if x.shape[-2] == 0:
        raise ValueError("x holds no samples (n = 0): an empty data set cannot be solved")
    if not lam > 0:
        raise ValueError(f"lam must be > 0, got {lam}")
    # x itself is checked through its moments (_check_moments): a NaN or inf anywhere in x
    # reaches them (inf · 0 is NaN), and reading the small moments is far cheaper than x.
    if not torch.isfinite(w).all() or (w < 0).any():
        raise ValueError("w must be finite and non-negative (importance weights)")


def _check_moments(*moments: torch.Tensor) -> None:
    for moment in moments:
        if not all_finite(moment):
            raise ValueError("x (the psi_hat design) contains NaN or inf")


def _check_u(u: torch.Tensor, *, semidefinite: bool) -> None:
    """Ũ is a second moment ``(1/n) Σ w x xᵀ`` with ``w >= 0``: finite, with a non-negative
    diagonal, and (``semidefinite``) positive semi-definite, so that J = tr(Ũ M C M) >= 0.
    Its off-diagonal entries may be negative. The semi-definite test is a Cholesky factorisation
    of the symmetric part plus ``sqrt(eps) · max diag`` (the rounding a moment formed in u's
    dtype may carry), in float64."""
    _check_not_meta("u", u)
    if not all_finite(u):
        raise ValueError("u (Ũ, a second moment Σ w x xᵀ / n) contains NaN or inf")
    diag = u.diagonal(dim1=-2, dim2=-1)
    if diag.numel() and diag.min() < 0:
        raise ValueError(
            f"u (Ũ, a second moment Σ w x xᵀ / n) must be positive semi-definite, but its "
            f"diagonal holds {diag.min().item():g} (J would come out negative)"
        )
    if not semidefinite or not u.numel():
        return
    sym = (u + u.mT).to(torch.float64) / 2
    eps = torch.finfo(u.dtype).eps if u.is_floating_point() else torch.finfo(torch.float64).eps
    jitter = eps**0.5 * diag.to(torch.float64).amax(-1).clamp_min(torch.finfo(torch.float64).tiny)
    eye = torch.eye(u.shape[-1], dtype=torch.float64, device=u.device)
    _, info = torch.linalg.cholesky_ex(sym + jitter[..., None, None] * eye)
    if (info > 0).any():
        raise ValueError(
            "u (Ũ, a second moment Σ w x xᵀ / n) is not positive semi-definite (it has a "
            "negative eigenvalue beyond rounding): J would not be a squared error"
        )


def _normaliser(num_samples, x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    if num_samples is None:
        return torch.tensor(float(x.shape[-2]), dtype=dtype, device=x.device)
    n = torch.as_tensor(num_samples, dtype=dtype, device=x.device)
    if (n <= 0).any():
        raise ValueError(f"num_samples must be > 0, got {num_samples}")
    return n


def weighted_moment(
    x: torch.Tensor, w: torch.Tensor, *, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Unnormalised weighted moment ``Σ_i w_i x_i x_iᵀ``: ``[..., n, B], [..., n] -> [..., B, B]``.

    Uses ``(x √w)ᵀ (x √w)``, the fastest form measured (docs/torchrl_stack.md); ``w`` must be
    non-negative, as importance weights are.
    """
    xw = x.to(dtype) * w.to(dtype).clamp_min(0).sqrt().unsqueeze(-1)
    return xw.mT @ xw


def _cholesky(matrix: torch.Tensor, lam: float) -> torch.Tensor:
    chol, info = torch.linalg.cholesky_ex(matrix)
    if (info > 0).any():
        raise ValueError(
            f"A + λI is not positive definite (λ = {lam}); the design may contain non-finite "
            "values or λ is too small for the floating-point precision"
        )
    return chol


def _warn_if_ill_conditioned(regularised: torch.Tensor, chol: torch.Tensor, lam: float) -> None:
    """Warn when ``A + λI`` is nearly singular, with its condition number.

    ``(max_i L_ii / min_i L_ii)²`` of the Cholesky factor is a free lower bound of the condition
    number; only when it is already large is the exact value computed (eigenvalues).
    """
    diag = chol.diagonal(dim1=-2, dim2=-1)
    bound = (diag.max(-1).values / diag.min(-1).values.clamp_min(1e-300)).pow(2).max().item()
    if bound <= _ILL_CONDITIONED:
        return
    eig = torch.linalg.eigvalsh(regularised)
    cond = (eig[..., -1] / eig[..., 0].clamp_min(torch.finfo(eig.dtype).tiny)).max().item()
    if cond > _ILL_CONDITIONED:
        warnings.warn(
            f"weighted_ridge: A + λI has condition number {cond:.3g} (λ = {lam}); the design is "
            "close to rank-deficient and θ is determined mostly by the regulariser and rounding. "
            "Collect more varied data or raise λ.",
            RuntimeWarning,
            stacklevel=3,
        )


def weighted_ridge(
    x: torch.Tensor,
    w: torch.Tensor,
    r: torch.Tensor,
    lam: float = DEFAULT_LAMBDA,
    *,
    num_samples: torch.Tensor | int | None = None,
    dtype: torch.dtype = torch.float64,
    check_conditioning: bool = True,
) -> torch.Tensor:
    """Importance-weighted regularised least squares (paper eq. 22-28, Algorithm 1).

    ``Â = (1/n) Σ w_i x_i x_iᵀ``, ``b̂ = (1/n) Σ w_i x_i r_i``, ``θ = (Â + λI)^{-1} b̂``.
    The ``1/n`` normalisation is kept because λ's meaning depends on it (docs/algorithm.md).

    Args:
        x: psi_hat rows ``[..., n, B]``.
        w: importance weights ``[..., n]`` (≥ 0; zero on padding).
        r: rewards ``[..., n]``.
        lam: ridge parameter λ > 0.
        num_samples: the ``n`` of ``1/n``, a number or a ``[...]`` tensor; defaults to the
            length of the sample axis. Pass the count of real samples when rows are padding
            or aggregated (``benchmarks/_aggregate.py``).
        dtype: the dtype of the solve (float64 by default).
        check_conditioning: warn with the condition number when ``Â + λI`` is nearly singular
            (a free bound from the Cholesky factor; eigenvalues only when that bound is high).

    Returns:
        θ ``[..., B]`` in ``dtype``.

    Example:
        >>> x = torch.randn(3, 50, 4, dtype=torch.float64)
        >>> r = x @ torch.ones(4, dtype=torch.float64)
        >>> theta = weighted_ridge(x, torch.ones(3, 50), r, 1e-3)
        >>> theta.shape
        torch.Size([3, 4])
    """
    _check_design(x, w, lam)
    _check_not_meta("r", r)
    if r.shape != w.shape:
        raise ValueError(f"r must have shape {tuple(w.shape)}, got {tuple(r.shape)}")
    if not torch.isfinite(r).all():
        raise ValueError("r (rewards) contains NaN or inf")
    n = _normaliser(num_samples, x, dtype)
    n_mat = n[..., None, None] if n.ndim else n
    a_hat = weighted_moment(x, w, dtype=dtype) / n_mat
    b_hat = (x.to(dtype).mT @ (w.to(dtype) * r.to(dtype)).unsqueeze(-1)) / n_mat
    _check_moments(a_hat, b_hat)
    eye = torch.eye(x.shape[-1], dtype=dtype, device=x.device)
    regularised = a_hat + lam * eye
    chol = _cholesky(regularised, lam)
    if check_conditioning:
        _warn_if_ill_conditioned(regularised, chol, lam)
    return torch.cholesky_solve(b_hat, chol).squeeze(-1)


def j_from_moments(
    a: torch.Tensor, c: torch.Tensor, u: torch.Tensor, lam: float = DEFAULT_LAMBDA
) -> torch.Tensor:
    """``J = tr(U (A + λI)^{-1} C (A + λI)^{-1})`` from normalised moments (eq. 41, 43).

    Args:
        a: ``A = (1/n) Σ w x xᵀ``, ``[..., B, B]``.
        c: ``C = (1/n²) Σ w² x xᵀ``, ``[..., B, B]``.
        u: ``Ũ``, ``[..., B, B]`` (broadcast against ``a``); finite, with a diagonal >= 0.
        lam: λ ≥ 0 (λ = 0 is for analysis only: A must then be positive definite).

    Returns:
        J ``[...]``.
    """
    if not lam >= 0:
        raise ValueError(f"lam must be >= 0, got {lam}")
    _check_not_meta("a", a)
    _check_not_meta("c", c)
    _check_u(u, semidefinite=False)  # (the cheap part: Ũ here is usually the library's own)
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    chol = _cholesky(a + lam * eye, lam)
    u = u.to(a.dtype).expand(*a.shape[:-2], *u.shape[-2:]) if u.ndim < a.ndim else u.to(a.dtype)
    # M = (A + λI)^{-1} is symmetric, so M U M = M (M U)ᵀ: two triangular solve pairs.
    m_u = torch.cholesky_solve(u, chol)
    m_u_m = torch.cholesky_solve(m_u.mT, chol)
    # tr(M U M C) = Σ_ij (M U M)_ij C_ji and C is symmetric.
    return (m_u_m * c).sum((-2, -1))


def j_criterion(
    x: torch.Tensor,
    w: torch.Tensor,
    u: torch.Tensor,
    lam: float = DEFAULT_LAMBDA,
    *,
    num_samples: torch.Tensor | int | None = None,
    sq_weights: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float64,
    flattening: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """The reward-free generalisation-error estimate J of a sampling set (eq. 40-46, Algorithm 2).

    ``A = (1/n) Σ w x xᵀ``, ``C = (1/n²) Σ w² x xᵀ``,
    ``J = tr(Ũ (A + λI)^{-1} C (A + λI)^{-1})``. This equals ``tr(Ũ L Lᵀ)`` with
    ``L = (A + λI)^{-1} X̂ᵀ W / n`` of Algorithm 2 without ever building the ``B × n`` matrix L.

    Args:
        x: psi_hat rows of the candidate's data set ``[..., n, B]`` (e.g. ``[Z, K, n, B]``).
        w: importance weights ``[..., n]`` w.r.t. the evaluation policy.
        u: ``Ũ`` ``[..., B, B]``, broadcast against the leading dims of ``x``
            (e.g. ``[Z, 1, B, B]``): a second moment, positive semi-definite (its
            off-diagonal entries may be negative); anything else is refused, as J would not be
            a squared error (it could come out negative).
        lam: λ > 0.
        num_samples: the ``n`` of the normalisation, as in :func:`weighted_ridge`.
        sq_weights: ``Σ w²`` per row when rows are aggregates of identical rows
            (``benchmarks/_aggregate.py``); defaults to ``w²``.
        dtype: dtype of the computation.
        flattening: ν of the flattened weights ``w^ν`` the fit uses (docs/flattening.md,
            eq. F2): ``A`` takes ``w^ν``, ``C`` takes ``w^{2ν}``; ``u`` is the caller's (it
            keeps the unflattened w). ν = 1 (default) is the paper's J, computed as before.

    Returns:
        J ``[...]`` in ``dtype``.

    Example:
        >>> x = torch.randn(5, 4, 100, 12, dtype=torch.float64)   # [Z, K, n, B]
        >>> u = torch.eye(12, dtype=torch.float64).expand(5, 1, 12, 12)
        >>> j_criterion(x, torch.ones(5, 4, 100), u, 1e-3).shape
        torch.Size([5, 4])
    """
    _check_design(x, w, lam)
    if u.shape[-2:] != (x.shape[-1], x.shape[-1]):
        raise ValueError(
            f"u must have shape [..., {x.shape[-1]}, {x.shape[-1]}], got {tuple(u.shape)}"
        )
    _check_u(u, semidefinite=True)
    if sq_weights is not None and sq_weights.shape != w.shape:
        raise ValueError(
            f"sq_weights must have shape {tuple(w.shape)}, got {tuple(sq_weights.shape)}"
        )
    if sq_weights is not None and not (isinstance(flattening, (int, float)) and flattening == 1.0):
        raise ValueError("sq_weights (aggregated rows) cannot be flattened: use flattening=1.0")
    w = flatten_weights(w, flattening)  # (ν = 1: w itself)
    n = _normaliser(num_samples, x, dtype)
    n_mat = n[..., None, None] if n.ndim else n
    w = w.to(dtype)
    xw = x.to(dtype) * w.clamp_min(0).sqrt().unsqueeze(-1)  # x √w
    a = (xw.mT @ xw) / n_mat
    if sq_weights is None:  # Σ w² x xᵀ = (x w)ᵀ (x w): reuse the buffer, x √w · √w = x w
        xw.mul_(w.clamp_min(0).sqrt().unsqueeze(-1))
    else:
        xw = x.to(dtype) * sq_weights.to(dtype).clamp_min(0).sqrt().unsqueeze(-1)
    c = (xw.mT @ xw) / n_mat.pow(2)
    _check_moments(a, c)
    return j_from_moments(a, c, u, lam)
