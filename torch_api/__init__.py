"""Active policy iteration for PyTorch and TorchRL (Akiyama, Hachiya & Sugiyama, 2010).

The pure tensor functions (one concept a module) and the components built on them:

>>> import torch_api
>>> sorted(torch_api.__all__)[:4]
['ActivePolicyIteration', 'EpisodeBuffer', 'GaussianActionBasis', 'IterationRecord']
>>> torch_api.__version__  # the installed distribution's version (pyproject.toml)
'0.1.0'
"""

import logging
from importlib.metadata import PackageNotFoundError, version

from torch_api.basis import GaussianActionBasis
from torch_api.data import EpisodeBuffer, collect_episodes
from torch_api.design import build_design
from torch_api.iteration import ActivePolicyIteration, IterationRecord
from torch_api.policies import LinearQPolicy, TabularPolicy
from torch_api.psi import PsiHat, psi_hat
from torch_api.selector import SamplingPolicySelector, j_values
from torch_api.solve import j_criterion, weighted_ridge
from torch_api.weights import per_decision_weights

try:
    __version__ = version("torch-api")
except PackageNotFoundError:  # a checkout on PYTHONPATH, not installed
    __version__ = "0.1.0"  # keep equal to pyproject.toml (tests/test_package.py checks)

# the library logs on "torch_api" and never prints; the application decides what shows
logging.getLogger("torch_api").addHandler(logging.NullHandler())

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
