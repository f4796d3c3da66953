"""Active policy iteration for PyTorch and TorchRL (Akiyama, Hachiya & Sugiyama, 2010).

The pure tensor functions (one concept a module) and the components built on them:

>>> import torch_api
>>> sorted(torch_api.__all__)[:4]
['ActionEncoding', 'ActionProbsPolicy', 'ActivePolicyIteration', 'BlockSeeded']
>>> torch_api.__version__  # the installed distribution's version (pyproject.toml)
'0.1.0'
"""

import logging
from importlib.metadata import PackageNotFoundError, version

from torch_api.actions import ActionEncoding
from torch_api.basis import GaussianActionBasis
from torch_api.data import EpisodeBuffer, as_episodes, collect_episodes, pad_steps
from torch_api.design import build_design
from torch_api.iteration import ActivePolicyIteration, IterationRecord
from torch_api.policies import (
    ActionProbsPolicy,
    LinearQPolicy,
    TabularPolicy,
    epsilon_greedy_probs,
    greedy_actions,
    softmax_probs,
)
from torch_api.psi import PsiHat, psi_hat, state_action_groups
from torch_api.selector import SamplingPolicySelector, j_values
from torch_api.solve import j_criterion, weighted_moment, weighted_ridge
from torch_api.streams import BlockSeeded, seed_env
from torch_api.weights import per_decision_weights

try:
    __version__ = version("torch-api")
except PackageNotFoundError:  # a checkout on PYTHONPATH, not installed
    __version__ = "0.1.0"  # keep equal to pyproject.toml (tests/test_package.py checks)

# the library logs on "torch_api" and never prints; the application decides what shows
logging.getLogger("torch_api").addHandler(logging.NullHandler())

__all__ = [
    "ActionEncoding",
    "ActionProbsPolicy",
    "ActivePolicyIteration",
    "BlockSeeded",
    "EpisodeBuffer",
    "GaussianActionBasis",
    "IterationRecord",
    "LinearQPolicy",
    "PsiHat",
    "SamplingPolicySelector",
    "TabularPolicy",
    "as_episodes",
    "build_design",
    "collect_episodes",
    "epsilon_greedy_probs",
    "greedy_actions",
    "j_criterion",
    "j_values",
    "pad_steps",
    "per_decision_weights",
    "psi_hat",
    "seed_env",
    "softmax_probs",
    "state_action_groups",
    "weighted_moment",
    "weighted_ridge",
]
