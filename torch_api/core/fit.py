"""Step 3 of Algorithm 1, policy evaluation: θ_l fitted on every rewarded episode so far.

Two learners, named by ``fit``: ``"brm"`` (the paper: θ by weighted least squares of r on the
psi_hat rows, eq. 22-28, :func:`~torch_api.core.solve.weighted_ridge`) and ``"lstd"`` (beyond the
paper: LSTD-Q, :func:`~torch_api.core.lstd.weighted_lstd`). The selector's J estimates the error of
the same learner (:mod:`torch_api.core.criterion`, :func:`~torch_api.core.lstd.lstd_j_values`).

Either learner takes flattened weights ``w^ν`` (docs/flattening.md): a fixed ν, or ν chosen
by importance-weighted cross-validation (``"iwcv"``, :mod:`torch_api.core.iwcv`). ν = 1 is the
paper's fit, computed exactly as without flattening.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from torch import nn

from torch_api.core.design import DEFAULT_MIN_ESS_FRACTION, _warn_on_collapsed_weights, build_design
from torch_api.core.iwcv import (
    DEFAULT_FLATTENING_GRID,
    DEFAULT_IWCV_FOLDS,
    check_flattening,
    choose_flattening,
    flattening_for_j,
    iwcv_scores,
)
from torch_api.core.lstd import phi_rows, weighted_lstd
from torch_api.core.psi import PsiHat
from torch_api.core.solve import weighted_ridge
from torch_api.core.weights import effective_sample_size, flatten_weights

__all__ = ["FITS", "Fit", "PolicyEvaluation", "fit_flattened", "fit_theta"]

FITS = ("brm", "lstd")  # the paper's least-squares fit on psi_hat, or LSTD-Q (torch_api.core.lstd)


class Fit(NamedTuple):
    """θ_l and how its weights were flattened.

    Attributes:
        theta: θ ``[*T, B]`` (float64).
        flattening: the ν used ``[*T]`` (float64).
        ess: Kish's effective sample size of the weights used, ``(Σ w^ν)² / Σ w^{2ν}``, ``[*T]``.
        num_samples: the rewarded samples n ``[*T]``.
        scores: the IWCV scores ``[*T, G]`` of the grid (``flattening="iwcv"``), else None.
    """

    theta: torch.Tensor
    flattening: torch.Tensor
    ess: torch.Tensor
    num_samples: torch.Tensor
    scores: torch.Tensor | None


def fit_theta(
    fit: str, episodes: TensorDictBase, policy, psi: PsiHat, basis: nn.Module, lam: float
) -> torch.Tensor:
    """θ ``[*T, B]`` of the evaluation policy ``policy`` (pi_l) from rewarded ``episodes``
    ``[*T, M, N]``: psi_hat on their union under pi_l, per-decision weights towards pi_l
    (:func:`~torch_api.core.design.build_design`), then the ``fit`` learner with ridge ``lam``."""
    return fit_flattened(fit, episodes, policy, psi, basis, lam).theta


def fit_flattened(
    fit: str,
    episodes: TensorDictBase,
    policy,
    psi: PsiHat,
    basis: nn.Module,
    lam: float,
    *,
    flattening: float | str = 1.0,
    grid: Sequence[float] = DEFAULT_FLATTENING_GRID,
    folds: int = DEFAULT_IWCV_FOLDS,
) -> Fit:
    """θ as :func:`fit_theta`, with importance weights flattened to ``w^ν`` (eq. F1).

    Args:
        fit: ``"brm"`` or ``"lstd"``.
        episodes: rewarded episodes ``[*T, M, N]``.
        policy: the evaluation policy pi_l; psi: the psi_hat module; basis: its basis.
        lam: λ > 0.
        flattening: ν in [0, 1] (1: the paper's weights, bit for bit), or ``"iwcv"``: ν of
            ``grid`` chosen per trial by IWCV over ``folds`` folds of whole episodes
            (:func:`~torch_api.core.iwcv.iwcv_scores`).
        grid: the ν tried by ``"iwcv"``, ascending.
        folds: k of the k-fold split (at most M).

    Returns:
        :class:`Fit`.
    """
    if fit not in FITS:
        raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
    plain = flattening == 1.0
    design = build_design(
        episodes, policy, psi, min_ess_fraction=DEFAULT_MIN_ESS_FRACTION if plain else 0.0
    )
    phi = phi_rows(episodes, basis) if fit == "lstd" else None
    lead = design.w.shape[:-1]
    scores = None
    if flattening == "iwcv":
        scores = iwcv_scores(
            design.x,
            design.w,
            design.reward,
            design.mask,
            num_steps=episodes.shape[-1],
            lam=lam,
            grid=grid,
            folds=folds,
            phi=phi,
        )
        nu = choose_flattening(scores, grid)  # [*T]
        w = flatten_weights(design.w, nu.reshape(*nu.shape, 1))
    else:
        nu = torch.full(lead, float(flattening), dtype=torch.float64)
        w = flatten_weights(design.w, float(flattening))
    if not plain:
        _warn_on_collapsed_weights(w, design.mask, DEFAULT_MIN_ESS_FRACTION)
    if fit == "lstd":
        theta = weighted_lstd(phi, design.x, w, design.reward, lam, num_samples=design.num_samples)
    else:
        theta = weighted_ridge(design.x, w, design.reward, lam, num_samples=design.num_samples)
    return Fit(
        theta=theta,
        flattening=nu,
        ess=effective_sample_size(w.to(torch.float64)),
        num_samples=design.num_samples,
        scores=scores,
    )


@dataclass(frozen=True)
class PolicyEvaluation:
    """Step 3 of Algorithm 1 as the loop holds it: the learner, λ and the weights' flattening.

    Example:
        >>> PolicyEvaluation(fit="brm", lam=1e-3, flattening="iwcv").grid
        (0.0, 0.25, 0.5, 0.75, 1.0)
    """

    fit: str = "brm"
    lam: float = 1e-3
    flattening: float | str = 1.0
    grid: Sequence[float] = DEFAULT_FLATTENING_GRID
    folds: int = DEFAULT_IWCV_FOLDS

    def __post_init__(self) -> None:
        flattening, grid = check_flattening(self.flattening, self.grid, self.folds)
        object.__setattr__(self, "flattening", flattening)
        object.__setattr__(self, "grid", grid)

    def __call__(self, episodes: TensorDictBase, policy, psi: PsiHat, basis: nn.Module) -> Fit:
        """θ_l of ``policy`` (pi_l) on every rewarded episode ``[*T, M, N]`` (eq. 56)."""
        return fit_flattened(
            self.fit,
            episodes,
            policy,
            psi,
            basis,
            self.lam,
            flattening=self.flattening,
            grid=self.grid,
            folds=self.folds,
        )

    def flattening_for_j(self, history: Sequence) -> float | torch.Tensor:
        """ν for J of the coming iteration (:func:`~torch_api.core.iwcv.flattening_for_j`)."""
        return flattening_for_j(self.flattening, history)

    def settings(self) -> dict:
        """What a stored run must agree on (nothing while ν = 1, as before flattening)."""
        if self.flattening == 1.0:
            return {}
        return {
            "flattening": self.flattening,
            "flattening_grid": list(self.grid),
            "iwcv_folds": self.folds,
        }
