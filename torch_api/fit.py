"""Step 3 of Algorithm 1, policy evaluation: θ_l fitted on every rewarded episode so far.

Two learners, named by ``fit``: ``"brm"`` (the paper: θ by weighted least squares of r on the
psi_hat rows, eq. 22-28, :func:`~torch_api.solve.weighted_ridge`) and ``"lstd"`` (beyond the
paper: LSTD-Q, :func:`~torch_api.lstd.weighted_lstd`). The selector's J estimates the error of
the same learner (:mod:`torch_api.criterion`, :func:`~torch_api.lstd.lstd_j_values`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from torch_api.design import build_design
from torch_api.lstd import phi_rows, weighted_lstd
from torch_api.psi import PsiHat
from torch_api.solve import weighted_ridge

__all__ = ["FITS", "fit_theta"]

FITS = ("brm", "lstd")  # the paper's least-squares fit on psi_hat, or LSTD-Q (torch_api.lstd)


def fit_theta(
    fit: str, episodes: TensorDictBase, policy, psi: PsiHat, basis: nn.Module, lam: float
) -> torch.Tensor:
    """θ ``[*T, B]`` of the evaluation policy ``policy`` (pi_l) from rewarded ``episodes``
    ``[*T, M, N]``: psi_hat on their union under pi_l, per-decision weights towards pi_l
    (:func:`~torch_api.design.build_design`), then the ``fit`` learner with ridge ``lam``."""
    design = build_design(episodes, policy, psi)
    if fit == "lstd":
        phi = phi_rows(episodes, basis)
        return weighted_lstd(
            phi, design.x, design.w, design.reward, lam, num_samples=design.num_samples
        )
    if fit == "brm":
        return weighted_ridge(
            design.x, design.w, design.reward, lam, num_samples=design.num_samples
        )
    raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
