"""Active policy iteration for PyTorch and TorchRL (Akiyama, Hachiya & Sugiyama, 2010).

The pure tensor functions (one concept a module) and the components built on them:

>>> import torch_api
>>> sorted(torch_api.__all__)[:4]
['ActionEncoding', 'ActionProbsPolicy', 'ActivePolicyIteration', 'BlockSeeded']

What a user extends, each with a runnable example in its docstring (docs/architecture.md):

* a policy family: subclass :class:`ActionProbsPolicy` (implement ``_action_probs``); it is
  pure, and :func:`sample_actions` draws from the random streams it is given;
* an active-learning criterion: a function with the signature :data:`Criterion`,
  ``(PooledMoments, lam) -> [..., K]`` (the default is :func:`j_eq46`, J of eq. 46);
* an environment with per-trial random streams: the :class:`BlockSeeded` protocol
  (``set_block_seeds``); any TorchRL env with discrete actions works without it.

>>> torch_api.ActionProbsPolicy, torch_api.Criterion, torch_api.BlockSeeded  # doctest: +ELLIPSIS
(<class '...ActionProbsPolicy'>, collections.abc.Callable[...], <class '...BlockSeeded'>)
>>> torch_api.__version__  # the installed distribution's version (pyproject.toml)
'0.1.0'
"""

import logging
from importlib.metadata import PackageNotFoundError, version

from torch_api.collection import at_most_rows, collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.criterion import Criterion, PooledMoments, j_eq46, pooled_moments
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat, psi_hat, state_action_groups
from torch_api.core.solve import j_criterion, weighted_moment, weighted_ridge
from torch_api.core.weights import per_decision_weights
from torch_api.data import EpisodeBuffer, as_episodes, pad_steps
from torch_api.data.actions import ActionEncoding
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration, IterationRecord
from torch_api.loop.selector import SamplingPolicySelector, j_values
from torch_api.loop.spec import (
    EvaluationSpec,
    PolicySpec,
    RewardedSpec,
    RunSpec,
    SelectionSpec,
    TrialSpec,
)
from torch_api.policies import (
    ActionProbsPolicy,
    LinearQPolicy,
    TabularPolicy,
    epsilon_greedy_probs,
    greedy_actions,
    sample_actions,
    softmax_probs,
)
from torch_api.streams import BlockSeeded, TrialStreams, seed_env

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
    "Criterion",
    "DurableRun",
    "EpisodeBuffer",
    "EvaluationSpec",
    "GaussianActionBasis",
    "IterationRecord",
    "LinearQPolicy",
    "PolicySpec",
    "PooledMoments",
    "PsiHat",
    "RewardedSpec",
    "RunSpec",
    "SamplingPolicySelector",
    "SelectionSpec",
    "TabularPolicy",
    "TrialSpec",
    "TrialStreams",
    "as_episodes",
    "build_design",
    "at_most_rows",
    "collect_episodes",
    "epsilon_greedy_probs",
    "greedy_actions",
    "j_criterion",
    "j_eq46",
    "j_values",
    "pad_steps",
    "per_decision_weights",
    "pooled_moments",
    "psi_hat",
    "sample_actions",
    "seed_env",
    "softmax_probs",
    "state_action_groups",
    "weighted_moment",
    "weighted_ridge",
]
