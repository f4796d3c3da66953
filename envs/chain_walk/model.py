"""The exact model of the chain walk (eq. 1, 6, 49): transitions, rewards, Q^pi, the optimum.

Plain float64 tensor functions, so that every quantity the experiments estimate from samples
can be checked by dynamic programming. In the model tensors state ``s`` sits at index ``s - 1``;
actions are indices 0 = 'L' (move left) and 1 = 'R' (move right).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ._checks import (
    _check_gamma,
    _check_model_policy,
    _check_prob,
    _check_reward_profile,
    _check_transitions,
)

__all__ = [
    "ACTION_NAMES",
    "DEFAULT_REWARD_PROFILE",
    "GAMMA",
    "N_ACTIONS",
    "N_STATES",
    "SUCCESS_PROB",
    "ChainWalkModel",
    "actions_to_string",
    "chain_walk_model",
    "chain_walk_transitions",
    "deterministic_policy_probs",
    "expected_reward",
    "optimal_policy",
    "policy_q_values",
]

# f(s') for s' = 1 … 10 (reward units): the project's reading of the paper's Figure 2, a main
# bump at s' = 4 with a secondary rise at the right end (docs/chain_walk.md).
DEFAULT_REWARD_PROFILE = (0.0, 0.1, 0.4, 1.0, 0.6, 0.2, 0.0, 0.1, 0.3, 0.5)
N_STATES = 10  # number of states (states are numbered 1 … N_STATES)
N_ACTIONS = 2  # actions: index 0 = 'L' (move left), index 1 = 'R' (move right)
ACTION_NAMES = ("L", "R")  # letter of each action index, as in the paper's policy strings
SUCCESS_PROB = 0.8  # probability that the intended move succeeds (else: one state the other way)
GAMMA = 0.9  # discount factor of the paper's chain-walk experiments


def chain_walk_transitions(
    n_states: int = N_STATES,
    success_prob: float = SUCCESS_PROB,
    *,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Transition tensor of the chain walk, P_T(s'|s, a) of eq. 1 and Figure 1.

    The intended move (index 0 = left, 1 = right) succeeds with ``success_prob``; otherwise the
    agent moves one state the other way. A move off either end leaves the agent where it is.

    Args:
        n_states: number of states S (>= 2).
        success_prob: probability that the intended move succeeds, in [0, 1].
        device: device of the result.

    Returns:
        P of shape [S, A, S] (A = 2), float64, with ``P[s, a, s']`` for 0-based indices
        (state number minus one). Every row ``P[s, a, :]`` sums to 1.

    Example:
        >>> P = chain_walk_transitions()
        >>> P.shape
        torch.Size([10, 2, 10])
        >>> P[0, 1, :3]  # from state 1, action 'R'
        tensor([0.2000, 0.8000, 0.0000], dtype=torch.float64)
    """
    if isinstance(n_states, bool) or not isinstance(n_states, int) or n_states < 2:
        raise ValueError(f"n_states must be an int >= 2, got {n_states!r}")
    p = _check_prob(success_prob, "success_prob")
    idx = torch.arange(n_states, device=device)
    left = (idx - 1).clamp(min=0)
    right = (idx + 1).clamp(max=n_states - 1)
    P = torch.zeros(n_states, N_ACTIONS, n_states, dtype=torch.float64, device=device)
    success = torch.full((n_states,), p, dtype=torch.float64, device=device)
    # Accumulate: at the ends the failed and the successful move may land in the same state.
    for a, (intended, other) in enumerate(((left, right), (right, left))):
        P_a = P[:, a]  # a view [S, S]
        P_a.index_put_((idx, intended), success, accumulate=True)
        P_a.index_put_((idx, other), 1.0 - success, accumulate=True)
    return P


def expected_reward(P: torch.Tensor, reward_profile: torch.Tensor) -> torch.Tensor:
    """Expected immediate reward R(s, a) = E_{P_T(s'|s,a)}[f(s')] (eq. 6 with eq. 49).

    Args:
        P: transition tensor [S, A, S].
        reward_profile: f [S], the reward f(s') received on arriving in s' (eq. 49).

    Returns:
        R of shape [S, A], float64.

    Example:
        >>> R = expected_reward(chain_walk_transitions(), torch.tensor(DEFAULT_REWARD_PROFILE))
        >>> R.shape
        torch.Size([10, 2])
    """
    P = _check_transitions(P)
    f = _check_reward_profile(reward_profile)
    if f.shape[0] != P.shape[-1]:
        raise ValueError(f"reward_profile must have {P.shape[-1]} entries, got {f.shape[0]}")
    return P @ f


def _policy_transition(P: torch.Tensor, pi: torch.Tensor) -> torch.Tensor:
    """Markov chain of (s, a) pairs: M[..., (s,a), (s',a')] = P(s'|s,a) pi(a'|s')."""
    S, A, _ = P.shape
    M = P[:, :, :, None] * pi[..., None, None, :, :]  # [..., S, A, S, A]
    return M.reshape(*pi.shape[:-2], S * A, S * A)


def policy_q_values(
    P: torch.Tensor, R: torch.Tensor, policy_probs: torch.Tensor, gamma: float
) -> torch.Tensor:
    """Exact Q^pi by solving the Bellman equation (eq. 5) as a linear system.

    ``Q = R + gamma * M Q`` with ``M[(s,a), (s',a')] = P(s'|s,a) pi(a'|s')``, solved as
    ``(I - gamma M) Q = R`` (one dense solve of size S·A).

    Args:
        P: transition tensor [S, A, S].
        R: expected reward [S, A] (eq. 6).
        policy_probs: pi(a|s), [..., S, A]; rows sum to 1. Leading dims are batched.
        gamma: discount factor in [0, 1).

    Returns:
        Q^pi of shape [..., S, A], float64.

    Example:
        >>> model = chain_walk_model()
        >>> pi = deterministic_policy_probs("RRRRRRRRRR", epsilon=0.1)
        >>> policy_q_values(model.transitions, model.expected_reward, pi, GAMMA).shape
        torch.Size([10, 2])
    """
    P, R, pi = _check_model_policy(P, R, policy_probs)
    S, A, _ = P.shape
    gamma = _check_gamma(gamma)
    M = _policy_transition(P, pi)
    eye = torch.eye(S * A, dtype=M.dtype, device=M.device)
    rhs = R.reshape(S * A, 1).expand(*M.shape[:-2], S * A, 1)
    q = torch.linalg.solve(eye - gamma * M, rhs)
    return q.reshape(*pi.shape[:-2], S, A)


def _greedy(Q: torch.Tensor) -> torch.Tensor:
    """Greedy action per state, ties (within a relative 1e-10) to the lowest action index."""
    best = Q.max(-1, keepdim=True).values
    tol = 1e-10 * (1.0 + best.abs())
    return (Q >= best - tol).to(torch.int64).argmax(-1)  # argmax returns the first maximum


def optimal_policy(
    P: torch.Tensor, R: torch.Tensor, gamma: float, *, max_iterations: int = 1000
) -> tuple[torch.Tensor, torch.Tensor]:
    """Optimal deterministic policy (eq. 3) and Q* (eq. 4) by exact policy iteration.

    Starts from 'all action 0', evaluates Q^pi exactly (eq. 5) and improves greedily until the
    policy is stable. Ties in the greedy step (within a relative 1e-10) go to the lowest action
    index, so the result is deterministic.

    Args:
        P: transition tensor [S, A, S].
        R: expected reward [S, A].
        gamma: discount factor in [0, 1).
        max_iterations: safety cap on policy-iteration sweeps (it converges in far fewer).

    Returns:
        ``(actions, q_star)``: actions [S] int64 (the optimal action index per state) and
        Q* [S, A] float64.

    Example:
        >>> model = chain_walk_model()
        >>> actions, q_star = optimal_policy(model.transitions, model.expected_reward, GAMMA)
        >>> actions.shape, q_star.shape
        (torch.Size([10]), torch.Size([10, 2]))
    """
    P = _check_transitions(P)
    S, A, _ = P.shape
    actions = torch.zeros(S, dtype=torch.int64, device=P.device)
    for _ in range(max_iterations):
        q = policy_q_values(P, R, torch.nn.functional.one_hot(actions, A).to(P.dtype), gamma)
        improved = _greedy(q)
        # Keep the current action where it is already (numerically) greedy: no cycling on ties.
        current = q.gather(-1, actions[:, None]).squeeze(-1)
        best = q.max(-1).values
        keep = current >= best - 1e-10 * (1.0 + best.abs())
        new_actions = torch.where(keep, actions, improved)
        if torch.equal(new_actions, actions):
            # Stable: report the lowest-index greedy action of Q* (ties to the lowest index).
            return _greedy(q), q
        actions = new_actions
    raise RuntimeError(f"policy iteration did not converge in {max_iterations} iterations")


def deterministic_policy_probs(
    actions: torch.Tensor | Sequence[int] | str,
    epsilon: float | torch.Tensor = 0.0,
    *,
    n_actions: int = N_ACTIONS,
) -> torch.Tensor:
    """Action probabilities of the epsilon-greedy version of a deterministic base policy.

    The base action gets ``1 - eps + eps/A`` and every other action ``eps/A`` (docs/algorithm.md;
    for A = 2 this is the paper's "intended action with probability 1 - eps/2", section 3.5).
    ``eps`` above 1 is capped at 1 (uniform policy).

    Args:
        actions: the base policy, either action indices [S] (int64) or a string of 'L'/'R'
            letters such as ``'RLLLLLRRRR'`` (the i-th letter is the action in state i).
        epsilon: exploration rate >= 0, a float or a tensor [...] (one policy per entry).
        n_actions: number of actions A (2 for the chain walk; letters need A = 2).

    Returns:
        pi of shape [..., S, A], float64.

    Example:
        >>> deterministic_policy_probs("RL", epsilon=0.2)
        tensor([[0.1000, 0.9000],
                [0.9000, 0.1000]], dtype=torch.float64)
    """
    if isinstance(actions, str):
        letters = actions.upper()
        if n_actions != N_ACTIONS or not letters or set(letters) - set(ACTION_NAMES):
            raise ValueError(
                f"actions must be a non-empty string of 'L'/'R' letters, got {actions!r}"
            )
        actions = [ACTION_NAMES.index(c) for c in letters]
    acts = torch.as_tensor(actions)
    if acts.is_floating_point() or acts.ndim != 1 or acts.numel() == 0:
        raise ValueError(
            f"actions must be a 1-D integer tensor [S], got shape {tuple(acts.shape)} "
            f"and dtype {acts.dtype}"
        )
    if ((acts < 0) | (acts >= n_actions)).any():
        raise ValueError(f"actions must lie in 0 … {n_actions - 1}, got {acts.tolist()}")
    eps = torch.as_tensor(epsilon, dtype=torch.float64, device=acts.device)
    if torch.isnan(eps).any() or (eps < 0).any():
        raise ValueError(f"epsilon must be >= 0, got {epsilon}")
    eps = eps.clamp(max=1.0)[..., None, None]
    base = torch.nn.functional.one_hot(acts.long(), n_actions).to(torch.float64)  # [S, A]
    return (1.0 - eps) * base + eps / n_actions


def actions_to_string(actions: torch.Tensor | Sequence[int]) -> str:
    """Writes a deterministic policy [S] as the paper's letters, e.g. ``'RLLLLLRRRR'``.

    Example:
        >>> actions_to_string(torch.tensor([1, 0, 0]))
        'RLL'
    """
    acts = torch.as_tensor(actions)
    if acts.ndim != 1 or ((acts < 0) | (acts >= N_ACTIONS)).any():
        raise ValueError(f"actions must be a 1-D tensor of 0/1 indices, got {acts.tolist()}")
    return "".join(ACTION_NAMES[int(a)] for a in acts)


@dataclass(frozen=True, eq=False)
class ChainWalkModel:
    """The exact MDP of a chain walk (eq. 1), as float64 tensors.

    Attributes:
        transitions: P_T(s'|s, a), [S, A, S].
        expected_reward: R(s, a) of eq. 6, [S, A].
        reward_profile: f(s') of eq. 49, [S].
        initial: initial state distribution (uniform), [S].

    Example:
        >>> model = chain_walk_model()
        >>> model.transitions.shape, model.expected_reward.shape, model.initial.sum().item()
        (torch.Size([10, 2, 10]), torch.Size([10, 2]), 1.0)
    """

    transitions: torch.Tensor
    expected_reward: torch.Tensor
    reward_profile: torch.Tensor
    initial: torch.Tensor

    @property
    def n_states(self) -> int:
        """Number of states S."""
        return self.transitions.shape[0]

    @property
    def n_actions(self) -> int:
        """Number of actions A."""
        return self.transitions.shape[1]


def chain_walk_model(
    reward_profile: torch.Tensor | Sequence[float] = DEFAULT_REWARD_PROFILE,
    success_prob: float = SUCCESS_PROB,
    *,
    n_states: int = N_STATES,
    device: torch.device | str | None = None,
) -> ChainWalkModel:
    """The exact model of a chain walk (eq. 1, 6, 49; uniform initial state).

    Args:
        reward_profile: f(s') for s' = 1 … S (eq. 49); must have ``n_states`` entries.
        success_prob: probability that the intended move succeeds, in [0, 1].
        n_states: number of states S.
        device: device of the tensors.

    Returns:
        A :class:`ChainWalkModel` (float64 tensors).
    """
    f = _check_reward_profile(reward_profile, n_states).to(device)
    P = chain_walk_transitions(n_states, success_prob, device=f.device)
    initial = torch.full((f.shape[0],), 1.0 / f.shape[0], dtype=torch.float64, device=f.device)
    return ChainWalkModel(
        transitions=P, expected_reward=expected_reward(P, f), reward_profile=f, initial=initial
    )
