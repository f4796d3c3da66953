"""Candidate families: the evaluation policy's rule of iteration l and its sampling candidates.

A family says, for iteration l, the rule of the evaluation policy pi_l (ε of an ε-greedy
policy, or β of a softmax one) and the K rules of the sampling-policy candidates (eq. 59), the
first of which is pi_l's. The loop builds its policies with ``policy.with_rule(**{family.key:
rule})`` (:class:`~torch_api.loop.policies.LoopPolicies`). A new family is a new small class
with the same four members, not a new branch of the loop.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from torch_api._checks import _check_finite
from torch_api.core.improvement import EPSILON_ROUNDING

__all__ = [
    "IMPROVEMENTS",
    "PAPER_EPSILON_OFFSETS",
    "SOFTMAX_CANDIDATE_SCALES",
    "EpsilonGreedyFamily",
    "SoftmaxFamily",
    "candidate_epsilons",
    "make_family",
    "paper_epsilon",
]

PAPER_EPSILON_OFFSETS = (0.0, 0.15, 0.5, 0.85)  # eq. 59: candidates ε_l + offset
SOFTMAX_CANDIDATE_SCALES = (1.0, 2.0, 5.0, 20.0)  # softmax candidates: β times these
IMPROVEMENTS = ("epsilon_greedy", "softmax")


def paper_epsilon(iteration: int) -> float:
    """ε of the evaluation policy of iteration l (1-based): ``0.15 / l`` (paper sections 4.2, 5)."""
    return 0.15 / iteration


def candidate_epsilons(epsilon: float, offsets: Sequence[float] = PAPER_EPSILON_OFFSETS) -> list:
    """ε of the sampling-policy candidates of eq. 59: ``[ε + o for o in offsets]``.

    Every ``ε + o`` must lie in [0, 1] (an ε above 1 is no ε-greedy policy; it is refused, not
    clipped); a sum within rounding (1e-12) of 1, such as the paper's ``0.15 + 0.85``, is 1.

    Example:
        >>> candidate_epsilons(0.15)
        [0.15, 0.3, 0.65, 1.0]
    """
    if not 0 <= epsilon <= 1:
        raise ValueError(f"epsilon must lie in [0, 1], got {epsilon}")
    out = []
    for o in offsets:
        value = epsilon + o
        if not -EPSILON_ROUNDING <= value <= 1 + EPSILON_ROUNDING:
            raise ValueError(
                f"epsilon + offset must lie in [0, 1], got {epsilon:g} + {o:g} = {value:g}"
            )
        out.append(min(1.0, max(0.0, value)))
    return out


def _check_offsets(epsilon_schedule: Callable[[int], float], offsets: tuple) -> None:
    """The candidates of iteration 1, ``ε_1 + offset``, must be ε-greedy policies: ε_1 + o in
    [0, 1] for every offset (the paper's ε_l = 0.15 / l is largest at l = 1; a schedule that
    rises later is checked again in each iteration, :meth:`EpsilonGreedyFamily.candidate_rules`)."""
    _check_finite("candidate_offsets", offsets)
    first = epsilon_schedule(1)
    if not 0 <= first <= 1:
        raise ValueError(f"epsilon_schedule(1) = {first} lies outside [0, 1]")
    for o in offsets:
        value = first + o
        if not -EPSILON_ROUNDING <= value <= 1 + EPSILON_ROUNDING:
            raise ValueError(
                f"candidate_offsets {list(offsets)} make a candidate that is no ε-greedy policy: "
                f"ε_1 + {o:g} = {value:g}; every ε_1 + offset must lie in [0, 1] "
                f"(ε_1 = epsilon_schedule(1) = {first:g})"
            )


class EpsilonGreedyFamily:
    """The paper's family: pi_l ε-greedy with ε_l = ``epsilon_schedule(l)``, candidates
    ε_l + offset (eq. 57-59), each in [0, 1]: offsets that push ε_1 + offset outside are
    refused when the family is made.

    Example:
        >>> family = EpsilonGreedyFamily()
        >>> family.evaluation_rule(1), family.candidate_rules(1).tolist()
        ({'epsilon': 0.15}, [0.15, 0.3, 0.65, 1.0])
    """

    key = "epsilon"

    def __init__(
        self,
        *,
        epsilon_schedule: Callable[[int], float] = paper_epsilon,
        offsets: Sequence[float] = PAPER_EPSILON_OFFSETS,
    ) -> None:
        if not offsets:
            raise ValueError("candidate_offsets must not be empty")
        _check_offsets(epsilon_schedule, tuple(offsets))
        self.epsilon_schedule = epsilon_schedule
        self.offsets = tuple(offsets)

    @property
    def num_candidates(self) -> int:
        return len(self.offsets)

    def evaluation_rule(self, iteration: int) -> dict:
        """``{"epsilon": ε_l}`` of pi_l."""
        epsilon = self.epsilon_schedule(iteration)
        if not 0 <= epsilon <= 1:
            raise ValueError(f"epsilon_schedule({iteration}) = {epsilon} lies outside [0, 1]")
        return {"epsilon": epsilon}

    def candidate_rules(self, iteration: int) -> torch.Tensor:
        """ε of the K candidates of iteration l, float64 ``[K]``; the first is pi_l's."""
        eps = self.evaluation_rule(iteration)["epsilon"]
        for o in self.offsets:
            if not -EPSILON_ROUNDING <= eps + o <= 1 + EPSILON_ROUNDING:
                raise ValueError(
                    f"iteration {iteration}: ε_{iteration} + {o:g} = {eps + o:g} lies outside "
                    f"[0, 1] (candidate_offsets {list(self.offsets)}): no ε-greedy candidate"
                )
        return torch.tensor(candidate_epsilons(eps, self.offsets), dtype=torch.float64)

    def settings(self, last: int) -> list | None:
        """What a stored run must agree on: ε_1 … ε_last."""
        return [self.epsilon_schedule(l) for l in range(1, last + 1)]


class SoftmaxFamily:
    """Softmax policies (eq. 7): pi_l with temperature β, candidates β times ``scales``.

    Example:
        >>> SoftmaxFamily(beta=2.0).candidate_rules(1).tolist()
        [2.0, 4.0, 10.0, 40.0]
    """

    key = "beta"

    def __init__(self, *, beta: float, scales: Sequence[float] = SOFTMAX_CANDIDATE_SCALES) -> None:
        if not (beta is not None and beta > 0):
            raise ValueError(f"improvement='softmax' needs beta > 0, got beta={beta}")
        self.beta = beta
        self.scales = tuple(scales)

    @property
    def num_candidates(self) -> int:
        return len(self.scales)

    def evaluation_rule(self, iteration: int) -> dict:
        """``{"beta": β}`` of pi_l (the same in every iteration)."""
        return {"beta": self.beta}

    def candidate_rules(self, iteration: int) -> torch.Tensor:
        """β of the K candidates ``[K]``; the first is pi_l's."""
        return torch.tensor([self.beta * c for c in self.scales])

    def settings(self, last: int) -> list | None:
        return None


def make_family(
    improvement: str,
    *,
    epsilon_schedule: Callable[[int], float] = paper_epsilon,
    candidate_offsets: Sequence[float] = PAPER_EPSILON_OFFSETS,
    beta: float | None = None,
) -> EpsilonGreedyFamily | SoftmaxFamily:
    """The family named by ``improvement`` (``"epsilon_greedy"`` or ``"softmax"``)."""
    if improvement not in IMPROVEMENTS:
        raise ValueError(f"improvement must be one of {IMPROVEMENTS}, got {improvement!r}")
    if improvement == "softmax":
        return SoftmaxFamily(beta=beta)
    return EpsilonGreedyFamily(epsilon_schedule=epsilon_schedule, offsets=candidate_offsets)
