"""The 10-state chain walk of Akiyama, Hachiya & Sugiyama (2010), sections 3.5 and 4.2.

Two floors in one file:

* :class:`ChainWalkEnv`, a batched TorchRL environment that samples the walk, and
* the exact model as plain float64 tensor functions (transition tensor, expected reward,
  exact ``Q^pi``, the optimal policy, occupancies, the exact ``psi`` of eq. 14, the true
  generalisation error and the exact expected discounted return), so that every quantity the
  experiments estimate from samples can be checked by dynamic programming.

States are numbered 1 … S (the observation holds the state *number*, so a Gaussian basis with
centres 1, 3, 5, 7, 9 applies to it directly); in the model tensors state ``s`` sits at index
``s - 1``. Actions are indices 0 = 'L' (move left) and 1 = 'R' (move right).

This module does not import ``torch_api``: the environment is usable without the algorithm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = [
    "ACTION_NAMES",
    "CENTERS",
    "DEFAULT_REWARD_PROFILE",
    "GAMMA",
    "N_ACTIONS",
    "N_STATES",
    "SUCCESS_PROB",
    "TAU",
    "ChainWalkEnv",
    "ChainWalkModel",
    "actions_to_string",
    "chain_walk_model",
    "chain_walk_transitions",
    "deterministic_policy_probs",
    "exact_psi",
    "expected_discounted_return",
    "expected_reward",
    "optimal_policy",
    "policy_q_values",
    "state_action_occupancy",
    "true_generalisation_error",
]

# f(s') for s' = 1 … 10 (reward units): the project's reading of the paper's Figure 2, a main
# bump at s' = 4 with a secondary rise at the right end (docs/chain_walk.md).
DEFAULT_REWARD_PROFILE = (0.0, 0.1, 0.4, 1.0, 0.6, 0.2, 0.0, 0.1, 0.3, 0.5)
N_STATES = 10  # number of states (states are numbered 1 … N_STATES)
N_ACTIONS = 2  # actions: index 0 = 'L' (move left), index 1 = 'R' (move right)
ACTION_NAMES = ("L", "R")  # letter of each action index, as in the paper's policy strings
SUCCESS_PROB = 0.8  # probability that the intended move succeeds (else: one state the other way)
GAMMA = 0.9  # discount factor of the paper's chain-walk experiments
CENTERS = (1.0, 3.0, 5.0, 7.0, 9.0)  # Gaussian basis centres of eq. 50 (state numbers)
TAU = 1.5  # Gaussian basis width of eq. 50 (state numbers)

_ATOL_PROBS = 1e-6  # tolerance on probability rows summing to 1


# --------------------------------------------------------------------------------------------
# Input validation helpers
# --------------------------------------------------------------------------------------------


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
    P = _check_transitions(P)
    S, A, _ = P.shape
    R = _check_state_action(R, "R", S, A)
    if R.ndim != 2:
        raise ValueError(f"R must have shape [{S}, {A}], got {tuple(R.shape)}")
    pi = _check_policy(policy_probs, S, A)
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


def _check_steps(n: int, name: str) -> int:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"{name} must be an int >= 1, got {n!r}")
    return n


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
        >>> model = chain_walk_model()
        >>> pi = deterministic_policy_probs("RRRRRRRRRR")
        >>> expected_discounted_return(
        ...     model.transitions, model.expected_reward, pi, model.initial, GAMMA, 50
        ... ).shape
        torch.Size([])
    """
    P = _check_transitions(P)
    S, A, _ = P.shape
    R = _check_state_action(R, "R", S, A)
    if R.ndim != 2:
        raise ValueError(f"R must have shape [{S}, {A}], got {tuple(R.shape)}")
    pi = _check_policy(policy_probs, S, A)
    mu0 = _check_initial(initial, S)
    gamma = _check_gamma(gamma, allow_one=True)
    horizon = _check_steps(horizon, "horizon")
    mus = _state_distributions(P, pi, mu0, horizon)  # [..., H, S]
    r_state = (pi * R).sum(-1)  # expected reward in each state under pi: [..., S]
    per_step = (mus * r_state[..., None, :]).sum(-1)  # [..., H]
    discounts = gamma ** torch.arange(horizon, dtype=torch.float64, device=P.device)
    return (per_step * discounts).sum(-1)


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


# --------------------------------------------------------------------------------------------
# The TorchRL environment
# --------------------------------------------------------------------------------------------


class ChainWalkEnv(EnvBase):
    """Batched chain walk (paper section 3.5, Figure 1) as a TorchRL environment.

    States 1 … S, actions 0 = 'L' and 1 = 'R'. The intended move succeeds with probability
    ``success_prob``, otherwise the agent moves one state the other way; a move off either end
    leaves it in place. Reward R(s, a, s') = f(s') (eq. 49); the initial state is uniform. The
    walk never terminates: ``terminated`` is always False, and with ``max_steps`` the episode is
    truncated (``truncated`` = ``done`` = True) on the step that reaches that count.

    The env is stateless in the TorchRL sense: ``_step`` reads the current state from the
    input's ``"observation"`` (the state number as float32 [E, 1]), so stepping a hand-built
    TensorDict from any state is allowed. With ``max_steps`` the step count travels in
    ``"step_count"`` (int64 [E, 1]). All randomness comes from the env's own
    ``torch.Generator`` (``set_seed``); equal seeds give equal trajectories.

    Keys: ``"observation"`` float32 [E, 1]; ``"action"`` int64 [E] (``Categorical(2)``; a
    one-hot [E, 2] action is accepted too); ``"reward"`` float32 [E, 1]; ``"done"``,
    ``"terminated"``, ``"truncated"`` bool [E, 1].

    Args:
        batch_size: number of parallel walks E (an int) or a batch shape.
        reward_profile: f(s') for s' = 1 … S; must have ``n_states`` entries.
        success_prob: probability that the intended move succeeds, in [0, 1].
        max_steps: if given, episodes are truncated after this many steps.
        n_states: number of states S (10 in the paper).
        device: device of the env's tensors (CPU by default). The random numbers are drawn on
            the CPU whatever the device, so a seed gives the same walks on CPU and GPU.
        seed: seed of the env's generator; ``None`` draws a fresh one (not from global state).

    Example:
        >>> env = ChainWalkEnv(batch_size=4, seed=0)
        >>> td = env.rollout(10, break_when_any_done=False)
        >>> td["observation"].shape, td["action"].shape, td["next", "reward"].shape
        (torch.Size([4, 10, 1]), torch.Size([4, 10]), torch.Size([4, 10, 1]))
    """

    def __init__(
        self,
        *,
        batch_size: int | Sequence[int] = 1,
        reward_profile: torch.Tensor | Sequence[float] = DEFAULT_REWARD_PROFILE,
        success_prob: float = SUCCESS_PROB,
        max_steps: int | None = None,
        n_states: int = N_STATES,
        device: torch.device | str | None = None,
        seed: int | None = None,
    ) -> None:
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if any(n < 1 for n in batch_size):
            raise ValueError(f"batch_size must hold positive sizes, got {tuple(batch_size)}")
        if isinstance(n_states, bool) or not isinstance(n_states, int) or n_states < 2:
            raise ValueError(f"n_states must be an int >= 2, got {n_states!r}")
        f = _check_reward_profile(reward_profile, n_states)
        self.success_prob = _check_prob(success_prob, "success_prob")
        if max_steps is not None:
            max_steps = _check_steps(max_steps, "max_steps")
        self.max_steps = max_steps
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise ValueError(f"seed must be an int or None, got {seed!r}")
        super().__init__(
            device=torch.device("cpu") if device is None else device, batch_size=batch_size
        )
        self.n_states = n_states
        self.reward_profile = f.to(self.device)  # float64 [S], for the exact model
        self._f32 = f.to(device=self.device, dtype=torch.float32)
        self._make_spec()
        if seed is None:
            seed = int(torch.Generator().seed())  # fresh entropy, leaves global RNG alone
        self.set_seed(seed)

    # -- specs --------------------------------------------------------------------------------

    def _make_spec(self) -> None:
        shape = self.batch_size
        observation = {
            "observation": Bounded(
                low=1.0,
                high=float(self.n_states),
                shape=(*shape, 1),
                dtype=torch.float32,
                device=self.device,
            )
        }
        if self.max_steps is not None:
            observation["step_count"] = Bounded(
                low=0,
                high=self.max_steps,
                shape=(*shape, 1),
                dtype=torch.int64,
                device=self.device,
            )
        self.observation_spec = Composite(observation, shape=shape, device=self.device)
        self.action_spec = Categorical(
            N_ACTIONS, shape=shape, dtype=torch.int64, device=self.device
        )
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=flag.clone(),
            terminated=flag.clone(),
            truncated=flag.clone(),
            shape=shape,
            device=self.device,
        )

    # -- seeding ------------------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.Generator().seed())
        rng = torch.Generator()  # on the CPU whatever the env's device: see `_draw`
        rng.manual_seed(int(seed))
        self.rng = rng
        self.block_rngs: list[torch.Generator] | None = None

    def set_block_seeds(self, seeds: Sequence[int]) -> None:
        """Give each of ``len(seeds)`` equal, consecutive blocks of rows its own random stream.

        With rows laid out block-major (e.g. one block per independent trial), block ``b``
        then draws exactly what an env of one block seeded with ``seeds[b]`` would: a batched
        run of many trials reproduces one-at-a-time runs. ``set_seed`` returns to one stream.
        """
        rows = self.batch_size.numel()
        if not seeds or rows % len(seeds):
            raise ValueError(
                f"seeds must split the {rows} rows into equal blocks, got {len(seeds)} seeds"
            )
        self.block_rngs = [torch.Generator().manual_seed(int(seed)) for seed in seeds]

    def _draw(self, sampler, shape: torch.Size, *args) -> torch.Tensor:
        """``sampler(*args, shape, generator=...)`` from one stream, or one stream per block.

        The numbers are drawn on the CPU and moved to the env's device, so a seed gives the
        same walks on every device (a CUDA generator would draw other numbers).
        """
        if self.block_rngs is None:
            drawn = sampler(*args, shape, generator=self.rng)
        else:
            rows = shape[0] // len(self.block_rngs)
            drawn = torch.cat(
                [sampler(*args, (rows, *shape[1:]), generator=rng) for rng in self.block_rngs]
            )
        return drawn.to(self.device)

    # -- dynamics -----------------------------------------------------------------------------

    def model(self) -> ChainWalkModel:
        """The exact model of this env (float64 tensors on the env's device)."""
        return chain_walk_model(
            self.reward_profile, self.success_prob, n_states=self.n_states, device=self.device
        )

    def _flags(self, truncated: torch.Tensor) -> dict[str, torch.Tensor]:
        terminated = torch.zeros_like(truncated)
        return {"done": truncated | terminated, "terminated": terminated, "truncated": truncated}

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size
        state = self._draw(torch.randint, torch.Size((*shape, 1)), 1, self.n_states + 1)
        out = {"observation": state.to(torch.float32)}
        if self.max_steps is not None:
            out["step_count"] = torch.zeros((*shape, 1), dtype=torch.int64, device=self.device)
        # Partial reset: rows outside the "_reset" mask keep their state (EnvBase.reset merges
        # the same way; doing it here keeps a direct `_reset` call correct too).
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if mask is not None and not mask.all():
            for key in out:
                old = tensordict.get(key, None)
                if old is not None:
                    out[key] = torch.where(mask.reshape(*shape, 1), out[key], old)
        out.update(self._flags(torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)))
        return TensorDict(out, batch_size=shape, device=self.device)

    def _action_indices(self, action: torch.Tensor) -> torch.Tensor:
        """Action indices [*E] from indices [*E], [*E, 1] or a one-hot [*E, 2]."""
        n_batch = len(self.batch_size)
        if action.ndim == n_batch + 1 and action.shape[-1] == N_ACTIONS:
            return action.long().argmax(-1)  # one-hot (bool or integer)
        if action.ndim == n_batch + 1 and action.shape[-1] == 1:
            action = action.squeeze(-1)
        if action.shape != self.batch_size:
            raise ValueError(
                f"action must have shape {tuple(self.batch_size)} (indices) or "
                f"{(*self.batch_size, N_ACTIONS)} (one-hot), got {tuple(action.shape)}"
            )
        action = action.long()
        if ((action < 0) | (action >= N_ACTIONS)).any():
            raise ValueError(f"action indices must be 0 ('L') or 1 ('R'), got {action.unique()}")
        return action

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = self.batch_size
        state = tensordict["observation"].reshape(shape).round().long()
        if ((state < 1) | (state > self.n_states)).any():
            raise ValueError(
                f"observation must hold state numbers 1 … {self.n_states}, got {state.unique()}"
            )
        action = self._action_indices(tensordict["action"])
        intended = 2 * action - 1  # 'L' -> -1, 'R' -> +1
        success = self._draw(torch.rand, shape) < self.success_prob
        move = torch.where(success, intended, -intended)
        next_state = (state + move).clamp(1, self.n_states)
        out = {
            "observation": next_state.to(torch.float32).unsqueeze(-1),
            "reward": self._f32[next_state - 1].unsqueeze(-1),
        }
        truncated = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        if self.max_steps is not None:
            step_count = tensordict["step_count"] + 1
            out["step_count"] = step_count
            truncated = step_count >= self.max_steps
        out.update(self._flags(truncated))
        return TensorDict(out, batch_size=shape, device=self.device)
