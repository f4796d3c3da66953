"""The basis of the batting experiment: the paper's Gaussian kernels, or one width per dimension.

``make_basis()`` is the paper's (eq. 64): 54 Gaussian centres on {0, π/4} × {-π, 0, π} ×
{-π/4, 0, π/4} × {-π, 0, π}, τ = 3π/2, and a constant, per action (B = 110).
``make_basis(widths)`` keeps the centres and gives every state dimension a kernel width of its
own (beyond the paper; ``examples/train_batting.py --basis-widths``).
"""

from __future__ import annotations

import torch

from envs.batting import BASIS_TAU, N_ACTIONS, basis_centers
from torch_api.core.basis import GaussianActionBasis


class ScaledGaussianBasis(GaussianActionBasis):
    """Gaussian kernels with one width per state dimension: ``exp(-Σ_d (s_d - c_d)² / 2w_d²)``.

    The paper's kernel (eq. 64) on coordinates divided by the widths ``w [d]`` (τ = 1 there).
    """

    def __init__(self, *, centers: torch.Tensor, widths, num_actions: int) -> None:
        widths = torch.as_tensor(widths, dtype=torch.float64)
        super().__init__(
            centers=centers / widths.to(centers.dtype), tau=1.0, num_actions=num_actions
        )
        self.register_buffer("widths", widths)

    def kernels(self, obs: torch.Tensor) -> torch.Tensor:
        return super().kernels(obs / self.widths.to(device=obs.device, dtype=obs.dtype))


def make_basis(widths: list[float] | None = None) -> GaussianActionBasis:
    """The paper's 54 Gaussian centres, τ = 3π/2, and a constant, per action (B = 110); with
    ``widths``, the same centres with one kernel width per state dimension (beyond the paper)."""
    if widths is None:
        return GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=N_ACTIONS)
    return ScaledGaussianBasis(centers=basis_centers(), widths=widths, num_actions=N_ACTIONS)
