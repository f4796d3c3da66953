"""Gaussian state kernels times an action indicator (paper eq. 9-10, 50, 64)."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from torch_api._checks import _count

__all__ = ["GaussianActionBasis", "as_features"]


def as_features(obs: torch.Tensor) -> torch.Tensor:
    """Observations as float features ``[..., d]``: integer observations (FrozenLake's state
    index ``[..., 1]``, a one-hot ``int64`` vector) are cast to the default float dtype.

    (Scalar observations ``[...]`` get their feature dim where the batch dims are known: in
    the policies' ``forward`` and in :mod:`torch_api.data`.)
    """
    if not (obs.is_floating_point() or obs.is_complex()):
        obs = obs.to(torch.get_default_dtype())
    return obs


class GaussianActionBasis(nn.Module):
    """The paper's basis: ``phi(s, a) = e_a ⊗ [k_1(s), ..., k_C(s), 1]`` (eq. 50, 64).

    ``k_c(s) = exp(-||s - c_c||² / (2 τ²))``. Each action owns one block of ``C + 1`` entries,
    so ``B = A (C + 1)``. The paper interleaves the actions; this module lays the blocks out one
    action after another, which changes nothing downstream (docs/algorithm.md).

    Any module with the same two methods (``phi_all`` and ``phi``) and the attributes
    ``num_features`` and ``num_actions`` can stand in for this one; ``q_values`` and
    ``expected_phi`` are optional fast paths the library uses when a basis has them.

    Args:
        centers: Gaussian centres ``[C, d]``.
        tau: kernel width τ > 0.
        num_actions: number of discrete actions A.

    Example:
        >>> basis = GaussianActionBasis(centers=torch.tensor([[1.0], [3.0]]), tau=1.5,
        ...                             num_actions=2)
        >>> basis.num_features
        6
        >>> basis.phi_all(torch.zeros(7, 1)).shape
        torch.Size([7, 2, 6])
        >>> basis.phi(torch.zeros(7, 1), torch.zeros(7, dtype=torch.long)).shape
        torch.Size([7, 6])
    """

    def __init__(self, *, centers: torch.Tensor, tau: float, num_actions: int) -> None:
        super().__init__()
        centers = torch.as_tensor(centers)
        if centers.ndim != 2 or centers.shape[0] == 0:
            raise ValueError(
                f"centers must have shape [C, d] with C >= 1, got {tuple(centers.shape)}"
            )
        if not torch.isfinite(centers).all():
            raise ValueError("centers must be finite")
        if isinstance(tau, bool) or not (isinstance(tau, numbers.Real) and tau > 0):
            raise ValueError(f"tau must be > 0, got {tau!r}")
        if not (math.isfinite(tau) and math.isfinite(2 * tau**2) and 2 * tau**2 > 1e-300):
            raise ValueError(f"tau must be finite with 2·tau² a normal number, got {tau}")
        num_actions = _count("num_actions", num_actions)
        self.register_buffer("centers", centers.to(torch.get_default_dtype()))
        self.tau = float(tau)
        self.num_actions = int(num_actions)
        self.num_kernels = centers.shape[0] + 1
        self.num_features = self.num_actions * self.num_kernels
        self._kernel_memo: dict | None = None  # see reuse_kernels

    @property
    def obs_dim(self) -> int:
        return self.centers.shape[1]

    def kernels(self, obs: torch.Tensor) -> torch.Tensor:
        """State features ``[k_1(s), ..., k_C(s), 1]``: obs ``[..., d]`` -> ``[..., C + 1]``.

        Inside :meth:`reuse_kernels` the result for a given tensor object is computed once.
        Integer observations are cast to float (:func:`as_features`).
        """
        obs = as_features(obs)
        if obs.shape[-1] != self.obs_dim:
            raise ValueError(
                f"obs must have a trailing dimension of {self.obs_dim}, "
                f"got shape {tuple(obs.shape)}"
            )
        if self._kernel_memo is not None:
            hit = self._kernel_memo.get(id(obs))
            if hit is not None and hit[0] is obs:
                return hit[1]
        centers = self.centers.to(device=obs.device, dtype=obs.dtype)
        num_centers = centers.shape[0]
        # ||s - c||² one coordinate at a time on [..., C] (a [..., C, d] intermediate reduced
        # over its short last dim is several times slower); each entry is computed on its own,
        # so the result does not depend on the batch layout.
        sq_dist = obs.new_zeros(*obs.shape[:-1], num_centers)
        for dim in range(self.obs_dim):
            sq_dist.add_((obs[..., dim, None] - centers[:, dim]).square_())
        out = obs.new_empty(*obs.shape[:-1], num_centers + 1)
        torch.exp(sq_dist.mul_(-1.0 / (2.0 * self.tau**2)), out=out[..., :num_centers])
        out[..., num_centers] = 1.0
        if self._kernel_memo is not None:
            self._kernel_memo[id(obs)] = (obs, out)  # holds obs: its id stays unique meanwhile
        return out

    @contextmanager
    def reuse_kernels(self) -> Iterator[None]:
        """Compute the kernels of each observation tensor once inside the block.

        :func:`~torch_api.core.design.build_design` evaluates the kernels of the same observations
        for the evaluation policy's probabilities and for psi_hat; inside this block the second
        call returns the first call's result. Tensors are matched by identity (the block keeps
        them alive, so an identity cannot be reused by another tensor meanwhile); do not modify
        an observation tensor in place inside the block.
        """
        outer = self._kernel_memo
        self._kernel_memo = {} if outer is None else outer
        try:
            yield
        finally:
            self._kernel_memo = outer

    def phi_all(self, obs: torch.Tensor) -> torch.Tensor:
        """Basis for every action: obs ``[..., d]`` -> ``[..., A, B]``."""
        k = self.kernels(obs)
        eye = torch.eye(self.num_actions, dtype=k.dtype, device=k.device)
        # [..., A, 1, A] * [..., 1, C+1, 1] -> block-diagonal rows, flattened per action.
        blocks = eye.unsqueeze(-1) * k.unsqueeze(-2).unsqueeze(-2)
        return blocks.reshape(*k.shape[:-1], self.num_actions, self.num_features)

    def phi(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Basis of the taken action: obs ``[..., d]``, action ``[...]`` (index) -> ``[..., B]``."""
        obs = as_features(obs)
        action = torch.as_tensor(action, device=obs.device)
        if action.shape != obs.shape[:-1]:
            raise ValueError(
                f"action must have shape {tuple(obs.shape[:-1])} (obs without its last dim), "
                f"got {tuple(action.shape)}"
            )
        if action.numel() and (action.min() < 0 or action.max() >= self.num_actions):
            raise ValueError(
                f"action indices must lie in [0, {self.num_actions}), got range "
                f"[{int(action.min())}, {int(action.max())}]"
            )
        k = self.kernels(obs)
        out = k.new_zeros(*k.shape[:-1], self.num_actions, self.num_kernels)
        index = action.long()[..., None, None].expand(*k.shape[:-1], 1, self.num_kernels)
        out.scatter_(-2, index, k.unsqueeze(-2))
        return out.reshape(*k.shape[:-1], self.num_features)

    def q_values(self, obs: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """``θᵀ phi(s, ·)`` without building ``phi_all``.

        obs ``[*T, ..., d]``, θ ``[*T, B]`` -> ``[*T, ..., A]``.

        Uses the block structure: ``Q(s, a) = k(s) · θ_a`` with ``θ_a`` the action's block.
        θ's leading dims ``*T`` must prefix the observation dims.
        """
        lead = theta.shape[:-1]
        k = self.kernels(obs)
        if k.shape[: len(lead)] != lead:
            raise ValueError(
                f"theta's leading dims {tuple(lead)} must prefix the observation dims "
                f"{tuple(obs.shape[:-1])}"
            )
        blocks = theta.to(k.dtype).reshape(*lead, self.num_actions, self.num_kernels)
        flat = k.reshape(*lead, -1, self.num_kernels)  # [*T, R, C+1]
        q = flat @ blocks.mT  # [*T, R, A]
        return q.reshape(*k.shape[:-1], self.num_actions)

    def expected_phi(self, obs: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        """``Σ_a pi(a|s) phi(s, a)`` without ``phi_all``: ``[..., d], [..., A] -> [..., B]``."""
        k = self.kernels(obs)
        if probs.shape != (*k.shape[:-1], self.num_actions):
            raise ValueError(
                f"probs must have shape {(*k.shape[:-1], self.num_actions)}, got "
                f"{tuple(probs.shape)}"
            )
        blocks = probs.to(k.dtype).unsqueeze(-1) * k.unsqueeze(-2)  # [..., A, C+1]
        return blocks.reshape(*k.shape[:-1], self.num_features)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.phi(obs, action)
