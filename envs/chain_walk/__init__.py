"""The 10-state chain walk of Akiyama, Hachiya & Sugiyama (2010), sections 3.5 and 4.2.

* :mod:`~envs.chain_walk.env`: :class:`ChainWalkEnv`, a batched TorchRL environment that
  samples the walk;
* :mod:`~envs.chain_walk.model`: the exact model as plain float64 tensor functions (transition
  tensor, expected reward, exact ``Q^pi``, the optimal policy);
* :mod:`~envs.chain_walk.exact`: expectations by dynamic programming (occupancies, the exact
  ``psi`` of eq. 14, the true generalisation error, the exact expected discounted return), so
  that every quantity the experiments estimate from samples can be checked;
* :mod:`~envs.chain_walk.paper_basis`: the paper's Gaussian basis (eq. 50), for the algorithm.

States are numbered 1 … S (the observation holds the state *number*); in the model tensors
state ``s`` sits at index ``s - 1``. Actions are indices 0 = 'L' (move left) and 1 = 'R' (move
right). Nothing here imports ``torch_api``: the environment is usable without the algorithm.

Example:
    >>> from envs.chain_walk import ChainWalkEnv, chain_walk_model
    >>> ChainWalkEnv(batch_size=3, seed=0).rollout(4)["next", "reward"].shape
    torch.Size([3, 4, 1])
    >>> chain_walk_model().transitions.shape
    torch.Size([10, 2, 10])
"""

from .env import ChainWalkEnv
from .exact import (
    exact_psi,
    expected_discounted_return,
    state_action_occupancy,
    true_generalisation_error,
)
from .model import (
    ACTION_NAMES,
    DEFAULT_REWARD_PROFILE,
    GAMMA,
    N_ACTIONS,
    N_STATES,
    SUCCESS_PROB,
    ChainWalkModel,
    actions_to_string,
    chain_walk_model,
    chain_walk_transitions,
    deterministic_policy_probs,
    expected_reward,
    optimal_policy,
    policy_q_values,
)
from .paper_basis import CENTERS, TAU

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
