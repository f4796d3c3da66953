"""Gaussian state kernels times an action indicator (paper eq. 9-10, 50, 64)."""

from __future__ import annotations

import math
import numbers
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from torch import nn

from torch_api._checks import _check_not_meta, _count

__all__ = ["TAU_MIN", "GaussianActionBasis", "as_features"]


def as_features(obs: torch.Tensor) -> torch.Tensor:
    """Observations as float features ``[..., d]``: integer observations (FrozenLake's state
    index ``[..., 1]``, a one-hot ``int64`` vector) are cast to the default float dtype.

    (Scalar observations ``[...]`` get their feature dim where the batch dims are known: in
    the policies' ``forward`` and in :mod:`torch_api.data`.)
    """
    if not (obs.is_floating_point() or obs.is_complex()):
        obs = obs.to(torch.get_default_dtype())
    return obs


TAU_MIN = math.sqrt(sys.float_info.min / 2)  # 2τ² a normal float64: 1/(2τ²) finite (1.05e-154)


def _kernel_scale_is_finite(width: float) -> bool:
    """Whether ``2·width²`` is a normal float64 number, so that the kernel's scale
    ``1/(2·width²)`` is finite."""
    return math.isfinite(2 * width**2) and 2 * width**2 >= sys.float_info.min


def _check_widths(widths, dims: int, tau: float) -> torch.Tensor:
    """Per-dimension kernel widths ``[d]`` as float64: finite, > 0, and ``τ·w_d`` large enough
    for a finite kernel scale (an infinite width would silently drop its dimension; a tiny one
    makes every kernel 0, or NaN, away from its centre)."""
    _check_not_meta("widths", widths)
    widths = torch.as_tensor(widths, dtype=torch.float64).cpu()
    if widths.ndim != 1 or widths.shape[0] != dims:
        raise ValueError(
            f"widths must hold one width per state dimension ({dims}), got "
            f"{widths.shape[0] if widths.ndim == 1 else tuple(widths.shape)}"
        )
    if not (torch.isfinite(widths).all() and (widths > 0).all()):
        raise ValueError(f"widths must be finite numbers > 0, got {widths.tolist()}")
    if not all(_kernel_scale_is_finite(tau * w) for w in widths.tolist()):
        raise ValueError(
            f"widths {widths.tolist()} with tau = {tau:g}: each kernel scale "
            f"1/(2·(tau·width)²) must be a finite float64 number (tau·width >= {TAU_MIN:.3g})"
        )
    return widths


def _check_kernel_range(given: torch.Tensor, centers: torch.Tensor, tau: float) -> None:
    """The stored centres must be finite in their dtype, and ``||c||²/(2τ²)`` finite in float64:
    else ``||s - c||²/(2τ²)`` overflows for observations of ordinary size and every kernel
    is ``exp(-inf) = 0`` (or NaN)."""
    if not torch.isfinite(centers).all():
        raise ValueError(
            f"centers must be finite in {str(centers.dtype).removeprefix('torch.')} (the dtype "
            f"they are stored in), got a coordinate of {given.abs().max().item():.3g} (centres "
            "divided by tiny widths overflow it)"
        )
    scaled = (centers.to(torch.float64) / tau).square().sum(-1) / 2
    if not torch.isfinite(scaled).all():
        largest = (centers.to(torch.float64).abs().amax() / tau).item()
        raise ValueError(
            f"||c||²/(2·tau²) overflows float64 for the centres (a coordinate over tau up to "
            f"{largest:.3g}): ||s - c||²/(2·tau²) is inf for observations of ordinary size, "
            "and every kernel exp(-inf) = 0"
        )


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
        tau: kernel width τ > 0, at least :data:`TAU_MIN` (the kernel's scale ``1/(2τ²)``
            must be a finite float64 number).
        num_actions: number of discrete actions A.
        widths: optional widths ``w [d]`` per state dimension (beyond the paper): the kernel
            becomes ``exp(-Σ_d (s_d - c_d)² / (2 τ² w_d²))``, computed as the paper's kernel on
            coordinates divided by the widths. Finite and > 0, with ``τ·w_d >= TAU_MIN``.

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

    def __init__(
        self,
        *,
        centers: torch.Tensor,
        tau: float,
        num_actions: int,
        widths: Sequence[float] | torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        _check_not_meta("centers", centers)
        centers = torch.as_tensor(centers)
        if centers.ndim != 2 or centers.shape[0] == 0:
            raise ValueError(
                f"centers must have shape [C, d] with C >= 1, got {tuple(centers.shape)}"
            )
        if not torch.isfinite(centers).all():
            raise ValueError("centers must be finite")
        if isinstance(tau, bool) or not (isinstance(tau, numbers.Real) and tau > 0):
            raise ValueError(f"tau must be > 0, got {tau!r}")
        if not (math.isfinite(tau) and _kernel_scale_is_finite(tau)):
            raise ValueError(
                f"tau must be finite with 2·tau² a normal number, got {tau}: the kernel's scale "
                f"1/(2·tau²) must be a finite float64 number (tau >= {TAU_MIN:.3g})"
            )
        num_actions = _count("num_actions", num_actions)
        if widths is not None:
            widths = _check_widths(widths, centers.shape[1], float(tau))
            centers = centers / widths.to(centers.dtype)  # the kernel on coordinates / widths
        self.register_buffer("kernel_widths", widths)
        stored = centers.to(torch.get_default_dtype())
        _check_kernel_range(centers, stored, float(tau))
        self.register_buffer("centers", stored)
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
        given = obs
        if self.kernel_widths is not None:  # (the centres were divided when the basis was made)
            obs = obs / self.kernel_widths.to(device=obs.device, dtype=obs.dtype)
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
            self._kernel_memo[id(given)] = (given, out)  # holds it: its id stays unique meanwhile
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
