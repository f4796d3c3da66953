"""A quadratic Q̂ per action: ``phi(s, a) = e_a ⊗ [1, s, s_i s_j (i ≤ j)]`` (beyond the paper).

CartPole's Q-function is far from a sum of a few Gaussian bumps; a full quadratic form in the
(unit-scaled) state per action fits it with 15 features a block (``examples/torchrl_pipeline.py``,
``benchmarks/cartpole_remedies.py``).
"""

from __future__ import annotations

import torch

from torch_api.core.basis import GaussianActionBasis

__all__ = ["QuadraticActionBasis"]


class QuadraticActionBasis(GaussianActionBasis):
    """``phi(s, a) = e_a ⊗ [1, s, s_i s_j (i ≤ j)]``: a quadratic Q̂ per action.

    The block layout (state features times an action indicator) is
    :class:`~torch_api.core.basis.GaussianActionBasis`'s, so its fast paths (``q_values``,
    ``expected_phi``) serve; only the state features differ: 1 + d + d(d+1)/2 a block.

    Example:
        >>> basis = QuadraticActionBasis(obs_dim=4, num_actions=2)
        >>> basis.num_features, basis.kernels(torch.ones(3, 4)).shape
        (30, torch.Size([3, 15]))
    """

    def __init__(self, *, obs_dim: int, num_actions: int) -> None:
        super().__init__(centers=torch.zeros(1, obs_dim), tau=1.0, num_actions=num_actions)
        self.register_buffer("pairs", torch.triu_indices(obs_dim, obs_dim))
        self.num_kernels = 1 + obs_dim + self.pairs.shape[1]
        self.num_features = self.num_actions * self.num_kernels

    def kernels(self, obs: torch.Tensor) -> torch.Tensor:
        """``[1, s, s_i s_j]``: obs ``[..., d]`` -> ``[..., 1 + d + d(d+1)/2]``."""
        obs = obs if obs.is_floating_point() else obs.to(torch.get_default_dtype())
        if obs.shape[-1] != self.obs_dim:
            raise ValueError(f"obs must end in {self.obs_dim}, got {tuple(obs.shape)}")
        i, j = self.pairs.to(obs.device)
        return torch.cat([torch.ones_like(obs[..., :1]), obs, obs[..., i] * obs[..., j]], -1)
