"""Per-decision importance weights (paper eq. 21 and the per-decision form below it)."""

from __future__ import annotations

import torch

__all__ = ["effective_sample_size", "flatten_weights", "per_decision_weights"]


def per_decision_weights(
    target_probs: torch.Tensor,
    sample_probs: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-decision importance weights of episodes (Precup et al., 2000; paper eq. 21).

    ``w[..., m, n] = prod_{n' <= n} pi(a[m, n'] | s[m, n']) / pi~(a[m, n'] | s[m, n'])``,
    computed as the exponential of a cumulative sum of log-ratios.

    Args:
        target_probs: evaluation-policy probability of each taken action, ``[..., M, N]``.
        sample_probs: sampling-policy probability of each taken action, recorded when the
            episode was collected, ``[..., M, N]``.
        mask: optional bool ``[..., M, N]``, False on padding after an episode ended. Masked
            steps get weight 0 and do not enter later products.

    Returns:
        ``[..., M, N]`` weights in the dtype of ``target_probs``.

    Raises:
        ValueError: on mismatched shapes, probabilities outside [0, 1] or not finite, or a taken
            action whose sampling probability is 0 (the episode could not have been collected
            by that policy: a data error).

    Example:
        >>> target = torch.tensor([[0.5, 0.5, 1.0]])
        >>> sample = torch.tensor([[0.5, 0.25, 0.5]])
        >>> per_decision_weights(target, sample)
        tensor([[1., 2., 4.]])
    """
    if target_probs.shape != sample_probs.shape:
        raise ValueError(
            f"target_probs and sample_probs must have the same shape [..., M, N], got "
            f"{tuple(target_probs.shape)} and {tuple(sample_probs.shape)}"
        )
    if target_probs.ndim < 2:
        raise ValueError(
            f"probabilities must have shape [..., M, N], got {tuple(target_probs.shape)}"
        )
    if mask is None:
        mask = torch.ones_like(target_probs, dtype=torch.bool)
    elif mask.shape != target_probs.shape:
        raise ValueError(
            f"mask must have shape {tuple(target_probs.shape)}, got {tuple(mask.shape)}"
        )
    for name, probs in (("target_probs", target_probs), ("sample_probs", sample_probs)):
        bad = mask & ~((probs >= 0) & (probs <= 1 + 1e-6))  # NaN fails both comparisons
        if bad.any():
            raise ValueError(
                f"{name} must be finite probabilities in [0, 1], got {probs[bad][0].item()}"
            )
    zero_taken = mask & (sample_probs <= 0)
    if zero_taken.any():
        where = tuple(int(i) for i in zero_taken.nonzero()[0].tolist())
        raise ValueError(
            f"sample_probs is 0 for a taken action at index {where}: the recorded sampling "
            "policy could not have taken it (wrong probabilities stored with the episode?)"
        )
    one = torch.ones((), dtype=target_probs.dtype, device=target_probs.device)
    log_ratio = torch.log(torch.where(mask, target_probs, one)) - torch.log(
        torch.where(mask, sample_probs.to(target_probs.dtype), one)
    )
    return torch.exp(torch.cumsum(log_ratio, dim=-1)) * mask


def effective_sample_size(weights: torch.Tensor) -> torch.Tensor:
    """Kish's effective sample size ``(Σ w)² / Σ w²`` over the last dimension ``[..., n] -> [...]``.

    Equals n for uniform weights and falls towards 1 as a few weights dominate.
    """
    total = weights.sum(-1)
    return total.pow(2) / weights.pow(2).sum(-1).clamp_min(torch.finfo(weights.dtype).tiny)


def flatten_weights(weights: torch.Tensor, nu: float | torch.Tensor) -> torch.Tensor:
    """Flattened importance weights ``w^ν`` (Hachiya et al. 2009, sample-reuse policy iteration).

    ``ν = 1`` is the unbiased per-decision weight of eq. 21, ``ν = 0`` ignores the weights
    (every sample 1), values in between trade the bias of the plain average for the variance
    of the weighted one (docs/flattening.md, eq. F1). Zero weights (padding, or a step the
    evaluation policy cannot take) stay zero for every ν, ``ν = 0`` included. Where ν = 1 the
    weights are taken as they are (no power is computed), so results are bit-identical to the
    unflattened ones.

    Args:
        weights: importance weights ``[...]`` (≥ 0).
        nu: the flattening exponent ν in [0, 1]: a number, or a tensor broadcast against
            ``weights`` (e.g. ``[T, 1]`` for one ν per trial of ``[T, n]`` weights).

    Returns:
        ``[...]`` weights ``w^ν`` in the dtype of ``weights``.

    Example:
        >>> flatten_weights(torch.tensor([0.0, 0.25, 4.0]), 0.5)
        tensor([0.0000, 0.5000, 2.0000])
    """
    if isinstance(nu, torch.Tensor):
        if ((nu < 0) | (nu > 1) | ~torch.isfinite(nu)).any():
            raise ValueError(f"the flattening exponent ν must lie in [0, 1], got {nu.tolist()}")
        nu = nu.to(weights.dtype)
        powered = torch.where(weights > 0, weights.clamp_min(0).pow(nu), 0.0)
        return torch.where(nu == 1, weights, powered)
    nu = float(nu)
    if not 0.0 <= nu <= 1.0:
        raise ValueError(f"the flattening exponent ν must lie in [0, 1], got {nu}")
    if nu == 1.0:
        return weights
    return torch.where(weights > 0, weights.clamp_min(0).pow(nu), torch.zeros_like(weights))
