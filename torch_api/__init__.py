"""Active policy iteration for PyTorch and TorchRL (Akiyama, Hachiya & Sugiyama, 2010).

The pure tensor functions (one concept a module) and the components built on them:

>>> import torch_api
>>> sorted(torch_api.__all__)[:4]
['ActivePolicyIteration', 'EpisodeBuffer', 'GaussianActionBasis', 'IterationRecord']
"""

from torch_api.basis import GaussianActionBasis
from torch_api.data import EpisodeBuffer, collect_episodes
from torch_api.design import build_design
from torch_api.iteration import ActivePolicyIteration, IterationRecord
from torch_api.policies import LinearQPolicy, TabularPolicy
from torch_api.psi import PsiHat, psi_hat
from torch_api.selector import SamplingPolicySelector, j_values
from torch_api.solve import j_criterion, weighted_ridge
from torch_api.weights import per_decision_weights

__all__ = [
    "ActivePolicyIteration",
    "EpisodeBuffer",
    "GaussianActionBasis",
    "IterationRecord",
    "LinearQPolicy",
    "PsiHat",
    "SamplingPolicySelector",
    "TabularPolicy",
    "build_design",
    "collect_episodes",
    "j_criterion",
    "j_values",
    "per_decision_weights",
    "psi_hat",
    "weighted_ridge",
]
