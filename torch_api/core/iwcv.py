"""Flattened importance weights chosen by importance-weighted cross-validation (beyond the paper).

Sample-reuse policy iteration (Hachiya, Akiyama, Sugiyama & Peters 2009, cited in the paper's
section 4.1) fits θ with flattened weights ``w^ν`` (eq. F1 of docs/flattening.md) and chooses ν
in every iteration by importance-weighted cross-validation (IWCV, Sugiyama et al. 2007) on the
rewarded samples: k folds of whole episodes; for each ν of a grid, θ is fitted on the other
folds with ``w^ν`` and scored on the held-out fold by the fit's own loss weighted by the
*unflattened* weight w (eq. F4), an unbiased estimate of the evaluation policy's expected loss.

Everything is batched over the leading (trial) dims ``[*T]``, the grid ``G`` and the folds
``F`` from per-fold moments, so the held-out fits cost one ``B × B`` solve each:
``A_train(g, f) = A(g) - A(g, f)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torch_api.core.weights import flatten_weights

__all__ = [
    "DEFAULT_FLATTENING_GRID",
    "DEFAULT_IWCV_FOLDS",
    "check_flattening",
    "choose_flattening",
    "flattening_for_j",
    "iwcv_scores",
]

DEFAULT_FLATTENING_GRID = (0.0, 0.25, 0.5, 0.75, 1.0)  # the ν tried by "iwcv"
DEFAULT_IWCV_FOLDS = 5  # k of the k-fold split over episodes
_TIE = 1e-9  # relative: scores this close to the best count as tied (the largest ν wins)


def check_flattening(flattening, grid: Sequence[float], folds: int) -> tuple:
    """Validate ``flattening`` (a ν in [0, 1] or ``"iwcv"``), the grid and the fold count.

    Returns:
        ``(flattening, grid)`` with ν as a float and the grid sorted ascending as a tuple.
    """
    if isinstance(flattening, str):
        if flattening != "iwcv":
            raise ValueError(f"flattening must be a number in [0, 1] or 'iwcv', got {flattening!r}")
    elif isinstance(flattening, bool) or not isinstance(flattening, (int, float)):
        raise ValueError(f"flattening must be a number in [0, 1] or 'iwcv', got {flattening!r}")
    elif not 0.0 <= float(flattening) <= 1.0:
        raise ValueError(f"flattening must lie in [0, 1], got {flattening}")
    else:
        flattening = float(flattening)
    grid = tuple(sorted(float(g) for g in grid))
    if not grid or not all(0.0 <= g <= 1.0 for g in grid):
        raise ValueError(f"flattening_grid must be a non-empty list of ν in [0, 1], got {grid}")
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ValueError(f"iwcv_folds must be an integer >= 2, got {folds!r}")
    return flattening, grid


def _by_fold(t: torch.Tensor, lead: int, num_steps: int, folds: int) -> torch.Tensor:
    """Rows ``[*T, M·N, *]`` -> ``[*T, F, ceil(M/F)·N, *]``: episode m goes to fold m % F
    (padded with zero rows where F does not divide M)."""
    rows = t.shape[lead]
    episodes = rows // num_steps
    per_fold = -(-episodes // folds)
    pad = per_fold * folds * num_steps - rows
    if pad:
        shape = list(t.shape)
        shape[lead] = pad
        t = torch.cat([t, t.new_zeros(shape)], dim=lead)
    tail = t.shape[lead + 1 :]
    t = t.reshape(*t.shape[:lead], per_fold, folds, num_steps, *tail)  # episode = q·F + f
    t = t.movedim(lead + 1, lead)  # [*T, F, per_fold, N, *]
    return t.reshape(*t.shape[:lead], folds, per_fold * num_steps, *tail)


def iwcv_scores(
    x: torch.Tensor,
    w: torch.Tensor,
    reward: torch.Tensor,
    mask: torch.Tensor,
    *,
    num_steps: int,
    lam: float,
    grid: Sequence[float] = DEFAULT_FLATTENING_GRID,
    folds: int = DEFAULT_IWCV_FOLDS,
    phi: torch.Tensor | None = None,
) -> torch.Tensor:
    """IWCV estimate of the held-out loss of the fit with ``w^ν``, for every ν of the grid.

    For fold f (episodes ``m ≡ f mod F``) and ν: θ(ν, f) is fitted on the other folds with
    weights ``w^ν`` (BRM, eq. 22-28: ``(Σ w^ν x xᵀ / n + λI)^{-1} Σ w^ν x r / n``; LSTD-Q when
    ``phi`` is given: ``Σ w^ν phi xᵀ``, ``Σ w^ν phi r``), and scored on fold f by the fit's own
    squared Bellman residual weighted by the unflattened w (eq. F4):
    ``score(ν) = (1/n) Σ_f Σ_{i ∈ f} w_i (x_iᵀ θ(ν, f) - r_i)²``.

    Args:
        x: psi_hat rows ``[*T, M·N, B]`` laid out episode-major
            (:class:`~torch_api.core.design.Design`).
        w: per-decision importance weights ``[*T, M·N]`` (zero on padding).
        reward: ``[*T, M·N]``; mask: real samples ``[*T, M·N]``.
        num_steps: N, the rows of one episode.
        lam: λ > 0.
        grid: the ν tried ``[G]``.
        folds: F (at most M: with fewer episodes, leave-one-episode-out).
        phi: ``phi(s, a)`` rows ``[*T, M·N, B]`` for LSTD-Q, None for BRM.

    Returns:
        scores ``[*T, G]`` (float64); NaN where there are fewer than two episodes.
    """
    lead = x.ndim - 2
    episodes = x.shape[-2] // num_steps
    folds = min(int(folds), episodes)
    if folds < 2:
        return torch.full(
            (*x.shape[:-2], len(grid)), float("nan"), dtype=torch.float64, device=x.device
        )
    x, w = x.to(torch.float64), w.to(torch.float64)
    left = phi.to(torch.float64) if phi is not None else x  # the moments' left factor
    xf, wf, rf = (_by_fold(t, lead, num_steps, folds) for t in (x, w, reward.to(torch.float64)))
    lf = xf if phi is None else _by_fold(left, lead, num_steps, folds)
    nf = _by_fold(mask.to(torch.float64), lead, num_steps, folds).sum(-1)  # [*T, F]
    wg = torch.stack([flatten_weights(wf, g) for g in grid])  # [G, *T, F, n_f]
    a_f = (lf * wg.unsqueeze(-1)).mT @ xf  # [G, *T, F, B, B]
    b_f = ((lf * (wg * rf).unsqueeze(-1)).sum(-2)).unsqueeze(-1)  # [G, *T, F, B, 1]
    n_train = (nf.sum(-1, keepdim=True) - nf).clamp_min(1)[..., None, None]  # [*T, F, 1, 1]
    a_train = (a_f.sum(-3, keepdim=True) - a_f) / n_train
    b_train = (b_f.sum(-3, keepdim=True) - b_f) / n_train
    eye = torch.eye(x.shape[-1], dtype=torch.float64, device=x.device)
    theta = torch.linalg.solve(a_train + lam * eye, b_train)  # [G, *T, F, B, 1]
    residual = (xf @ theta).squeeze(-1) - rf  # [G, *T, F, n_f]
    loss = (wf * residual.pow(2)).sum((-2, -1)) / nf.sum(-1).clamp_min(1)  # [G, *T]
    return loss.movedim(0, -1)


def choose_flattening(scores: torch.Tensor, grid: Sequence[float]) -> torch.Tensor:
    """ν of the best IWCV score per trial: ``[*T, G] -> [*T]`` (float64).

    Scores within a relative ``1e-9`` of the best tie, and the largest tied ν wins (the least
    biased: on on-policy data every ν gives the same fit and ν = 1 is chosen). Where the scores
    are NaN (fewer than two episodes) the largest ν of the grid is taken.
    """
    grid_t = torch.tensor(sorted(grid), dtype=torch.float64, device=scores.device)
    if list(grid) != sorted(grid):
        raise ValueError(f"grid must be sorted ascending, got {list(grid)}")
    finite = torch.isfinite(scores)
    masked = torch.where(finite, scores, torch.full_like(scores, float("inf")))
    best = masked.min(-1, keepdim=True).values
    tied = finite & (masked <= best + _TIE * best.abs())
    index = torch.arange(len(grid), device=scores.device).expand_as(scores)
    pick = torch.where(tied, index, torch.full_like(index, -1)).max(-1).values
    pick = torch.where(finite.any(-1), pick, torch.full_like(pick, len(grid) - 1))
    return grid_t[pick]


def flattening_for_j(flattening, history: Sequence) -> float | torch.Tensor:
    """ν for J of the coming iteration l: the fixed ν, or with ``"iwcv"`` the ν chosen in
    iteration l-1 (per trial ``[*T]``; 1.0 before the first fit, when no ν was chosen yet).

    ``history`` holds the loop's :class:`~torch_api.loop.records.IterationRecord` s.
    """
    if flattening != "iwcv":
        return flattening
    if not history or history[-1].flattening is None:
        return 1.0
    return torch.tensor(history[-1].flattening, dtype=torch.float64)
