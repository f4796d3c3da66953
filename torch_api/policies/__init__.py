"""Layer 3, the policies: the base a family extends, the policies of Q̂, candidate families.

====================================== ================================================
:mod:`torch_api.policies.base`         :class:`ActionProbsPolicy`, :func:`sample_actions`
:mod:`torch_api.policies.linear_q`     :class:`LinearQPolicy` (eq. 7-9), :class:`TabularPolicy`
:mod:`torch_api.policies.families`   candidate families: ε-greedy, softmax (eq. 57-59)
====================================== ================================================

The names of the first two are re-exported here (as the one module ``torch_api.policies``
did before this package).
"""

from torch_api.policies.base import ActionProbsPolicy, Streams, param_dims_of, sample_actions
from torch_api.policies.linear_q import (
    TIE_BREAKS,
    TIE_RTOL,
    LinearQPolicy,
    TabularPolicy,
    epsilon_greedy_probs,
    greedy_actions,
    greedy_mask,
    greedy_probs,
    linear_q_values,
    softmax_probs,
)

__all__ = [
    "ActionProbsPolicy",
    "LinearQPolicy",
    "Streams",
    "TabularPolicy",
    "TIE_BREAKS",
    "TIE_RTOL",
    "epsilon_greedy_probs",
    "greedy_actions",
    "greedy_mask",
    "greedy_probs",
    "linear_q_values",
    "param_dims_of",
    "sample_actions",
    "softmax_probs",
]
