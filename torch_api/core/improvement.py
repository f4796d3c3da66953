"""Policy improvement as pure functions: Q-values ``[..., A]`` to action probabilities.

Linear Q-values ``Q̂(s, a) = θᵀ phi(s, a)`` (eq. 9), the greedy set with its tie rule, ε-greedy
(eq. 57-58) and softmax (eq. 7) probabilities. :class:`~torch_api.policies.LinearQPolicy` is the
TensorDict module built on them.
"""

from __future__ import annotations

import torch

__all__ = [
    "TIE_BREAKS",
    "TIE_RTOL",
    "epsilon_greedy_probs",
    "greedy_actions",
    "greedy_mask",
    "greedy_probs",
    "linear_q_values",
    "softmax_probs",
]

TIE_RTOL = 1e-10  # Q-values this close (relative) to the maximum count as tied with it
TIE_BREAKS = ("uniform", "lowest")
"""How the greedy mass is shared among tied maximal actions: equal parts, or all to the lowest
index."""


def linear_q_values(phi_all: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``Q̂(s, ·) = θᵀ phi(s, ·)`` (eq. 9).

    phi_all ``[*T, ..., A, B]``, θ ``[*T, B]`` -> ``[*T, ..., A]``.

    θ's leading dims ``*T`` (e.g. a trial dimension) must be a prefix of phi_all's.
    """
    if theta.shape[-1] != phi_all.shape[-1]:
        raise ValueError(
            f"theta has {theta.shape[-1]} entries but the basis has {phi_all.shape[-1]} features"
        )
    lead = theta.shape[:-1]
    if phi_all.shape[: len(lead)] != lead:
        raise ValueError(
            f"theta's leading dims {tuple(lead)} must prefix the observation dims "
            f"{tuple(phi_all.shape[:-2])}"
        )
    extra = phi_all.ndim - 1 - theta.ndim
    view = theta.reshape(*lead, *([1] * extra), 1, theta.shape[-1])
    return (phi_all * view.to(phi_all.dtype)).sum(-1)


def greedy_mask(q: torch.Tensor) -> torch.Tensor:
    """Which actions are maximal: ``q[..., a]`` within ``TIE_RTOL`` (relative) of the maximum.

    ``[..., A] -> [..., A]`` bool, at least one True per row.
    """
    best = q.max(-1, keepdim=True).values
    return q >= best - TIE_RTOL * (1.0 + best.abs())


def greedy_actions(q: torch.Tensor) -> torch.Tensor:
    """One greedy action per row: the lowest index among the maximal ones (:func:`greedy_mask`).

    ``[..., A] -> [...]``. A policy that splits ties evenly uses :func:`greedy_probs` instead.
    """
    return greedy_mask(q).to(torch.int8).argmax(-1)  # argmax returns the first maximal index


def _check_tie_break(tie_break: str) -> str:
    if tie_break not in TIE_BREAKS:
        raise ValueError(f"tie_break must be one of {TIE_BREAKS}, got {tie_break!r}")
    return tie_break


def greedy_probs(q: torch.Tensor, tie_break: str = "uniform") -> torch.Tensor:
    """The greedy policy ``I(a = argmax Q̂)`` of eq. 57/66 as probabilities ``[..., A] -> [..., A]``.

    When several actions are maximal (within ``TIE_RTOL``), ``tie_break="uniform"`` gives each
    of them an equal share (the normalised indicator of the argmax set: with all actions tied,
    e.g. θ = 0 or the paper's θ_0 = 1 on a basis with the same features per action, the policy
    is uniform); ``"lowest"`` gives all the mass to the lowest index among them.

    Returns float64.
    """
    _check_tie_break(tie_break)
    if tie_break == "lowest":
        return torch.nn.functional.one_hot(greedy_actions(q), q.shape[-1]).to(torch.float64)
    mask = greedy_mask(q).to(torch.float64)
    return mask / mask.sum(-1, keepdim=True)


EPSILON_ROUNDING = 1e-12  # ε this far above 1 is rounding (ε_l + offset), read as 1


def _check_epsilon(epsilon, *, at_most_one: bool = False) -> torch.Tensor:
    """ε as a float64 tensor: finite and >= 0; with ``at_most_one`` also <= 1 (a policy's ε:
    above 1 there is no ε-greedy policy, and capping it would hide a mistake). Values above 1
    are capped at 1 (the uniform policy), which then only absorbs rounding."""
    eps = torch.as_tensor(epsilon, dtype=torch.float64)
    if at_most_one and (
        not bool(torch.isfinite(eps).all())
        or bool((eps < 0).any())
        or bool((eps > 1 + EPSILON_ROUNDING).any())
    ):
        raise ValueError(f"epsilon must lie in [0, 1], got {_shown(epsilon)}")
    if not torch.isfinite(eps).all() or (eps < 0).any():
        raise ValueError(f"epsilon must be >= 0, got {epsilon}")
    return eps.clamp(max=1.0)  # ε is capped at 1, the uniform policy (docs/algorithm.md)


def _shown(value):
    """A number or a small tensor as a list, for a message."""
    return value.tolist() if isinstance(value, torch.Tensor) else value


def epsilon_greedy_probs(q: torch.Tensor, epsilon, tie_break: str = "uniform") -> torch.Tensor:
    """ε-greedy probabilities (eq. 8): the greedy mass ``1 - ε`` plus ``ε/A`` for every action.

    With a single maximal action it gets ``1 - ε + ε/A`` and the others ``ε/A``; tied maximal
    actions share the greedy mass as :func:`greedy_probs` says (``tie_break``).

    Args:
        q: Q-values ``[..., A]``.
        epsilon: ε ≥ 0, a number or a tensor broadcastable to ``[...]``; values above 1 are
            capped at 1 (uniform).
        tie_break: ``"uniform"`` (tied actions share the greedy mass equally) or ``"lowest"``.

    Returns:
        ``[..., A]`` in float64.
    """
    eps = _check_epsilon(epsilon).to(q.device)
    num_actions = q.shape[-1]
    greedy = greedy_probs(q, tie_break)
    eps = eps.unsqueeze(-1) if eps.ndim else eps
    return (1.0 - eps) * greedy + eps / num_actions


def softmax_probs(q: torch.Tensor, beta) -> torch.Tensor:
    """Softmax probabilities ``pi(a|s) ∝ exp(Q̂(s, a) / β)`` (eq. 7): ``[..., A] -> [..., A]``."""
    beta_t = torch.as_tensor(beta, dtype=torch.float64, device=q.device)
    if not torch.isfinite(beta_t).all() or (beta_t <= 0).any():
        raise ValueError(f"beta must be > 0, got {beta}")
    beta_t = beta_t.unsqueeze(-1) if beta_t.ndim else beta_t
    return torch.softmax(q.to(torch.float64) / beta_t, dim=-1)
