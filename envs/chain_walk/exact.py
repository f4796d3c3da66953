"""Exact expectations under a policy, by dynamic programming over the chain walk's model.

State-action occupancies, the exact ``psi`` of eq. 14, the true generalisation error and the
exact expected discounted return: the ground truth the experiments' estimates are checked
against.
"""

from __future__ import annotations

import torch

from ._checks import (
    _as_f64,
    _check_gamma,
    _check_initial,
    _check_model_policy,
    _check_policy,
    _check_state_action,
    _check_steps,
    _check_transitions,
)

__all__ = [
    "exact_psi",
    "expected_discounted_return",
    "state_action_occupancy",
    "true_generalisation_error",
]


def _state_distributions(
    P: torch.Tensor, pi: torch.Tensor, initial: torch.Tensor, n_steps: int
) -> torch.Tensor:
    """State distributions mu_1 … mu_N under pi: [..., N, S]."""
    P_pi = torch.einsum("...sa,sat->...st", pi, P)  # [..., S, S]
    mu = initial.expand(*pi.shape[:-2], initial.shape[-1])
    out = []
    for _ in range(n_steps):
        out.append(mu)
        mu = (mu[..., None, :] @ P_pi).squeeze(-2)
    return torch.stack(out, dim=-2)


def state_action_occupancy(
    P: torch.Tensor, policy_probs: torch.Tensor, initial: torch.Tensor, n_steps: int
) -> torch.Tensor:
    """Average state-action occupancy d(s, a) over steps 1 … N (the weighting of eq. 32).

    ``d(s, a) = (1/N) sum_{n=1}^{N} mu_n(s) pi(a|s)`` with ``mu_1 = initial`` and
    ``mu_{n+1}(s') = sum_{s,a} mu_n(s) pi(a|s) P(s'|s,a)``.

    Args:
        P: transition tensor [S, A, S].
        policy_probs: pi(a|s), [..., S, A]; leading dims are batched.
        initial: initial state distribution [S].
        n_steps: episode length N (>= 1).

    Returns:
        d of shape [..., S, A], float64, summing to 1 over (S, A).

    Example:
        >>> from envs.chain_walk import GAMMA, chain_walk_model, deterministic_policy_probs
        >>> model = chain_walk_model()
        >>> pi = deterministic_policy_probs("LLLLLRRRRR", epsilon=0.1)
        >>> d = state_action_occupancy(model.transitions, pi, model.initial, 10)
        >>> round(d.sum().item(), 12)
        1.0
    """
    P = _check_transitions(P)
    S, A, _ = P.shape
    pi = _check_policy(policy_probs, S, A)
    mu0 = _check_initial(initial, S)
    n_steps = _check_steps(n_steps, "n_steps")
    mus = _state_distributions(P, pi, mu0, n_steps)  # [..., N, S]
    return mus.mean(-2)[..., None] * pi


def exact_psi(
    P: torch.Tensor, phi_all: torch.Tensor, policy_probs: torch.Tensor, gamma: float
) -> torch.Tensor:
    """Exact psi of eq. 14: ``phi(s,a) - gamma E_{P(s'|s,a)} E_{pi(a'|s')} [phi(s',a')]``.

    Args:
        P: transition tensor [S, A, S].
        phi_all: the basis evaluated at every state-action pair, [S, A, B] (built by the
            caller with its own basis; state index ``i`` is state number ``i + 1``).
        policy_probs: evaluation policy pi(a|s), [..., S, A]; leading dims are batched.
        gamma: discount factor in [0, 1].

    Returns:
        psi of shape [..., S, A, B], float64.

    Example:
        >>> from envs.chain_walk import GAMMA, chain_walk_model, deterministic_policy_probs
        >>> model = chain_walk_model()
        >>> phi_all = torch.eye(20, dtype=torch.float64).reshape(10, 2, 20)  # tabular basis
        >>> pi = deterministic_policy_probs("RRRRRRRRRR", epsilon=0.1)
        >>> exact_psi(model.transitions, phi_all, pi, GAMMA).shape
        torch.Size([10, 2, 20])
    """
    P = _check_transitions(P)
    S, A, _ = P.shape
    phi = _as_f64(phi_all, "phi_all")
    if phi.ndim != 3 or tuple(phi.shape[:2]) != (S, A):
        raise ValueError(f"phi_all must have shape [{S}, {A}, B], got {tuple(phi.shape)}")
    pi = _check_policy(policy_probs, S, A)
    gamma = _check_gamma(gamma, allow_one=True)
    v_phi = torch.einsum("...ta,tab->...tb", pi, phi)  # E_{pi(a'|s')} phi(s', a'): [..., S, B]
    next_phi = torch.einsum("sat,...tb->...sab", P, v_phi)  # [..., S, A, B]
    return phi - gamma * next_phi


def true_generalisation_error(
    theta: torch.Tensor, psi: torch.Tensor, R: torch.Tensor, d: torch.Tensor
) -> torch.Tensor:
    """Exact generalisation error of eq. 32 with the exact psi (docs/chain_walk.md).

    ``G(theta) = sum_{s,a} d(s,a) (theta^T psi(s,a) - R(s,a))^2``.

    Args:
        theta: parameters [..., B]; leading dims are batched (e.g. [trials, K, B]).
        psi: exact psi of eq. 14, [S, A, B] (or [..., S, A, B] broadcasting with theta).
        R: expected reward [S, A] (eq. 6).
        d: state-action occupancy [S, A] (or [..., S, A] broadcasting with theta).

    Returns:
        G of shape [...] (theta's leading dims, broadcast with those of psi and d), float64.

    Example:
        >>> psi = torch.randn(10, 2, 12, dtype=torch.float64)
        >>> R, d = torch.zeros(10, 2), torch.full((10, 2), 0.05)
        >>> true_generalisation_error(torch.zeros(7, 12), psi, R, d).shape
        torch.Size([7])
    """
    theta = _as_f64(theta, "theta")
    psi = _as_f64(psi, "psi")
    if psi.ndim < 3 or psi.shape[-1] != theta.shape[-1]:
        raise ValueError(
            f"psi must have shape [..., S, A, B] with B = theta.shape[-1] = {theta.shape[-1]}, "
            f"got {tuple(psi.shape)}"
        )
    S, A = psi.shape[-3], psi.shape[-2]
    R = _check_state_action(R, "R", S, A)
    d = _check_state_action(d, "d", S, A)
    pred = (psi @ theta[..., None, :, None]).squeeze(-1)  # [..., S, A]
    return (d * (pred - R) ** 2).sum((-2, -1))


def expected_discounted_return(
    P: torch.Tensor,
    R: torch.Tensor,
    policy_probs: torch.Tensor,
    initial: torch.Tensor,
    gamma: float,
    horizon: int,
) -> torch.Tensor:
    """Exact expected value of ``sum_{n=1}^{H} gamma^(n-1) r_n`` for one episode.

    The exact counterpart of the performance of eq. 61 (the paper uses H = 50, gamma = 0.9):
    ``sum_n gamma^(n-1) sum_{s,a} mu_n(s) pi(a|s) R(s,a)`` by propagating the state
    distribution mu_n from ``initial``.

    Args:
        P: transition tensor [S, A, S].
        R: expected reward [S, A] (eq. 6).
        policy_probs: pi(a|s), [..., S, A]; leading dims are batched (e.g. trials).
        initial: initial state distribution [S].
        gamma: discount factor in [0, 1].
        horizon: number of steps H (>= 1).

    Returns:
        The expected discounted return, shape [...] (a scalar for an unbatched policy).

    Example:
        >>> from envs.chain_walk import GAMMA, chain_walk_model, deterministic_policy_probs
        >>> model = chain_walk_model()
        >>> pi = deterministic_policy_probs("RRRRRRRRRR")
        >>> expected_discounted_return(
        ...     model.transitions, model.expected_reward, pi, model.initial, GAMMA, 50
        ... ).shape
        torch.Size([])
    """
    P, R, pi = _check_model_policy(P, R, policy_probs)
    S = P.shape[0]
    mu0 = _check_initial(initial, S)
    gamma = _check_gamma(gamma, allow_one=True)
    horizon = _check_steps(horizon, "horizon")
    mus = _state_distributions(P, pi, mu0, horizon)  # [..., H, S]
    r_state = (pi * R).sum(-1)  # expected reward in each state under pi: [..., S]
    per_step = (mus * r_state[..., None, :]).sum(-1)  # [..., H]
    discounts = gamma ** torch.arange(horizon, dtype=torch.float64, device=P.device)
    return (per_step * discounts).sum(-1)
