"""Argument checks of the chain walk's exact model and env (``ValueError`` naming the value)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

_ATOL_PROBS = 1e-6  # tolerance on probability rows summing to 1


def _as_f64(x: torch.Tensor | Sequence[float], name: str) -> torch.Tensor:
    """Returns ``x`` as a float64 tensor (same device), refusing non-finite values."""
    t = torch.as_tensor(x)
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64, torch.bool)):
        raise ValueError(f"{name} must be a real tensor, got dtype {t.dtype}")
    t = t.to(torch.float64)
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, got {t}")
    return t


def _check_prob(value: float, name: str) -> float:
    value = float(value)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got {value}")
    return value


def _check_gamma(gamma: float, *, allow_one: bool = False) -> float:
    gamma = float(gamma)
    upper_ok = gamma <= 1.0 if allow_one else gamma < 1.0
    if not (gamma >= 0.0 and upper_ok):
        interval = "[0, 1]" if allow_one else "[0, 1)"
        raise ValueError(f"gamma must lie in {interval}, got {gamma}")
    return gamma


def _check_transitions(P: torch.Tensor) -> torch.Tensor:
    P = _as_f64(P, "P")
    if P.ndim != 3 or P.shape[0] != P.shape[2]:
        raise ValueError(f"P must have shape [S, A, S], got {tuple(P.shape)}")
    if (P < 0).any() or not torch.allclose(
        P.sum(-1), torch.ones((), dtype=P.dtype, device=P.device), atol=_ATOL_PROBS
    ):
        raise ValueError("P must hold probability rows P[s, a, :] that are >= 0 and sum to 1")
    return P


def _check_policy(policy_probs: torch.Tensor, S: int, A: int) -> torch.Tensor:
    pi = _as_f64(policy_probs, "policy_probs")
    if pi.ndim < 2 or tuple(pi.shape[-2:]) != (S, A):
        raise ValueError(f"policy_probs must have shape [..., {S}, {A}], got {tuple(pi.shape)}")
    row_sums = pi.sum(-1)
    bad = (pi < 0).any(-1) | ((row_sums - 1.0).abs() > _ATOL_PROBS)
    if bad.any():
        raise ValueError(
            "policy_probs rows must be >= 0 and sum to 1, got row sums "
            f"{row_sums[bad].tolist()[:5]} (first offending rows)"
        )
    return pi


def _check_state_action(x: torch.Tensor, name: str, S: int, A: int) -> torch.Tensor:
    x = _as_f64(x, name)
    if tuple(x.shape[-2:]) != (S, A):
        raise ValueError(f"{name} must have shape [..., {S}, {A}], got {tuple(x.shape)}")
    return x


def _check_model_policy(
    P: torch.Tensor, R: torch.Tensor, policy_probs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``P`` [S, A, S], ``R`` [S, A] and ``policy_probs`` [..., S, A], checked, as float64."""
    P = _check_transitions(P)
    S, A, _ = P.shape
    R = _check_state_action(R, "R", S, A)
    if R.ndim != 2:
        raise ValueError(f"R must have shape [{S}, {A}], got {tuple(R.shape)}")
    return P, R, _check_policy(policy_probs, S, A)


def _check_initial(initial: torch.Tensor, S: int) -> torch.Tensor:
    mu = _as_f64(initial, "initial")
    if mu.shape != (S,) or (mu < 0).any() or abs(float(mu.sum()) - 1.0) > _ATOL_PROBS:
        raise ValueError(
            f"initial must be a probability vector of shape [{S}], got shape {tuple(mu.shape)} "
            f"summing to {float(mu.sum()) if mu.numel() else 0.0}"
        )
    return mu


def _check_reward_profile(
    reward_profile: torch.Tensor | Sequence[float], n_states: int | None = None
) -> torch.Tensor:
    f = _as_f64(reward_profile, "reward_profile")
    if f.ndim != 1 or f.numel() < 2:
        raise ValueError(
            f"reward_profile must be a 1-D sequence with one value per state (at least 2), "
            f"got shape {tuple(f.shape)}"
        )
    if n_states is not None and f.numel() != n_states:
        raise ValueError(
            f"reward_profile must have n_states={n_states} entries, got {f.numel()}: {f.tolist()}"
        )
    return f


# --------------------------------------------------------------------------------------------
# The exact model: pure tensor functions (float64)
# --------------------------------------------------------------------------------------------


def _check_steps(n: int, name: str) -> int:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"{name} must be an int >= 1, got {n!r}")
    return n
