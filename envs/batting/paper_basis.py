"""The paper's basis for the batting experiment (eq. 64-65): the algorithm's side, not the env's.

The environment knows nothing of value functions; these are the Gaussian centres and the width
the paper's experiment puts on the arm's state, kept apart from the physics so that another
basis is another grid, not a change to the env. The experiments (``examples/train_batting.py``,
``benchmarks/``) build their :class:`torch_api.core.basis.GaussianActionBasis` from them.
"""

from __future__ import annotations

import math

import torch

__all__ = ["BASIS_CENTER_GRID", "BASIS_TAU", "basis_centers"]

# 54 Gaussian centres on this grid, per state dimension: phi1 (rad), phi1_dot (rad/s),
# phi2 (rad), phi2_dot (rad/s)
BASIS_CENTER_GRID = (
    (0.0, math.pi / 4),
    (-math.pi, 0.0, math.pi),
    (-math.pi / 4, 0.0, math.pi / 4),
    (-math.pi, 0.0, math.pi),
)
BASIS_TAU = 3 * math.pi / 2  # (rad) kernel width τ of eq. 64


def basis_centers() -> torch.Tensor:
    """The 54 Gaussian centres of the paper's batting basis (eq. 65), float64 ``[54, 4]``."""
    grids = torch.meshgrid(
        *[torch.tensor(g, dtype=torch.float64) for g in BASIS_CENTER_GRID], indexing="ij"
    )
    return torch.stack([g.reshape(-1) for g in grids], dim=-1)
