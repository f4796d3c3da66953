"""The loop's policies: pi_l of θ and its K sampling candidates, made by a candidate family.

Policies are pure (:mod:`torch_api.policies.base`): the random streams they sample from are
given per use, derived from (seed, trial, iteration, role) by
:class:`~torch_api.streams.TrialStreams`, so that nothing is to be caught up after a resume or
in a worker process.
"""

from __future__ import annotations

import torch
from torch import nn

from torch_api.data.actions import ActionEncoding
from torch_api.policies.families import EpsilonGreedyFamily, SoftmaxFamily
from torch_api.policies.linear_q import LinearQPolicy
from torch_api.streams import TrialStreams

__all__ = ["LoopPolicies"]


class LoopPolicies:
    """pi_l and its candidates for :class:`~torch_api.loop.iteration.ActivePolicyIteration`.

    Args:
        basis: the basis module of Q̂ = θᵀ phi.
        family: the candidate family (:mod:`torch_api.policies.families`): pi_l's rule (ε or
            β) of iteration l and the K candidates' rules (eq. 59).
        tie_break: how ε-greedy policies share the greedy mass among tied actions.
        streams: the run's random streams.

    Attributes:
        action_encoding: the env's action encoding (one-hot or index) the policies write, once
            known (:meth:`know_actions`), else None.

    Example:
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.zeros(1, 1), tau=1.0, num_actions=2)
        >>> policies = LoopPolicies(basis=basis, family=EpsilonGreedyFamily(),
        ...                         tie_break="uniform", streams=TrialStreams.for_trials(0, None))
        >>> pi_1 = policies.evaluation(torch.ones(4), 1)
        >>> [round(float(c.epsilon), 2) for c in policies.candidates(pi_1, 1)]
        [0.15, 0.3, 0.65, 1.0]
    """

    def __init__(
        self,
        *,
        basis: nn.Module,
        family: EpsilonGreedyFamily | SoftmaxFamily,
        tie_break: str,
        streams: TrialStreams,
    ) -> None:
        self.basis = basis
        self.family = family
        self.tie_break = tie_break
        self.streams = streams
        self.action_encoding: ActionEncoding | None = None

    def know_actions(self, env) -> bool:
        """Read the env's action encoding from its spec, once; True if it was new."""
        if self.action_encoding is not None:
            return False
        self.action_encoding = ActionEncoding.from_spec(env.action_spec, env.batch_size)
        return True

    def evaluation(self, theta: torch.Tensor, iteration: int) -> LinearQPolicy:
        """pi_l of θ ``[*T, B]``: ε-greedy with ε = ε_l (``spec.policy.epsilon_of(l)``,
        eq. 57-58), or softmax (eq. 7)."""
        return LinearQPolicy(
            basis=self.basis,
            theta=theta,
            tie_break=self.tie_break,
            action_spec=self.action_encoding,
            **self.family.evaluation_rule(iteration),
        )

    def candidate_rules(self, iteration: int) -> torch.Tensor:
        """ε (or β) of the K candidates of iteration l ``[K]`` (eq. 59); the first is pi_l's."""
        return self.family.candidate_rules(iteration)

    def with_rule(self, policy: LinearQPolicy, rule: torch.Tensor) -> LinearQPolicy:
        """``policy``'s θ with another ε (or β): a candidate, or the chosen sampling policy."""
        return policy.with_rule(**{self.family.key: rule})

    def candidates(self, policy: LinearQPolicy, iteration: int) -> list[LinearQPolicy]:
        """The K sampling-policy candidates of pi_l = ``policy`` in iteration l (eq. 59)."""
        return [self.with_rule(policy, rule) for rule in self.candidate_rules(iteration)]

    def reward_free_candidates(self, policy: LinearQPolicy, iteration: int) -> list:
        """The candidates drawing from iteration l's reward-free streams (one for all K,
        shared), not from pi_l's (which the rewarded episodes use): the active run's selection
        then leaves the rewarded draws as the passive run's."""
        streams = self.streams.sampling(iteration, "reward_free_policy")
        return [c.with_streams(streams) for c in self.candidates(policy, iteration)]

    def for_evaluation(self, policy: LinearQPolicy, iteration: int) -> tuple[LinearQPolicy, int]:
        """pi_{l+1} = ``policy`` with sampling streams of its own, and the evaluation seed of
        iteration l: both depend on (seed, l) alone, so a resumed run measures what an
        uninterrupted one would."""
        seed = self.streams.run_seed(iteration, "evaluation")
        return policy.with_streams(self.streams.sampling(iteration, "evaluation")), seed
