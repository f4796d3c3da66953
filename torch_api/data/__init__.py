"""Layer 1, the episode data: what an episode is, TorchRL data converted, checked and held.

Every episode batch in this library is a TensorDict of batch shape ``[M, N]`` (M episodes of
N steps) holding:

=========================== =============== ==============================================
key                         shape           meaning
=========================== =============== ==============================================
``observation``             ``[M, N, d]``   state s
``action``                  ``[M, N]``      action index a (one-hot actions are converted)
``sample_probs``            ``[M, N, A]``   the sampling policy's pi~(·|s), recorded then,
``sample_log_prob``         ``[M, N]``      or only log pi~(a|s) of the taken action
``("next", "observation")`` ``[M, N, d]``   next state s'
``("next", "terminated")``  ``[M, N]``      the episode terminated at s' (no bootstrap)
``mask``                    ``[M, N]``      True up to and including an episode's last step
``("next", "reward")``      ``[M, N]``      rewarded episodes only
``iteration``, ``policy_id`` ``[M, N]``     tags: when and by which policy it was collected
=========================== =============== ==============================================

Reward-free episodes never carry a reward key: the collector drops whatever the environment
returned before the algorithm can see it.

Per-decision importance weights (eq. 21) need only the sampling policy's probability of the
taken action, so either probability key will do: the library's policies record the whole
distribution (``sample_probs``), TorchRL's ``ProbabilisticActor(..., return_log_prob=True)``
the log-probability of its action (``sample_log_prob`` or ``action_log_prob``, stored here as
``sample_log_prob``).

TorchRL data as TorchRL produces it is converted by :func:`as_episodes` (and accepted as is by
:meth:`EpisodeBuffer.extend`, the selector's earlier episodes and the iteration's
``initial_episodes``): ``env.rollout`` output ``[N]`` or ``[E, N]``; a ``Collector``'s flat
batches with ``("collector", "traj_ids")`` (split into trajectories); its ``split_trajs=True``
or ``trajs_per_batch`` padded batches with ``("collector", "mask")``; trailing ``[..., 1]`` dims
on done/terminated/truncated/reward; one-hot or index actions. Episodes of different lengths
are padded (with copies of their last step) and masked: N is the longest. A trajectory cut at a
collector batch's end is joined with its continuation by :meth:`EpisodeBuffer.extend`, so its
importance weights restart only where the episode really started.

============================== ===================================================
:mod:`torch_api.data.actions`  :class:`ActionEncoding`: an env's action encoding
:mod:`torch_api.data.episodes` the format's keys, :func:`as_episodes`, padding
:mod:`torch_api.data.buffer`   :func:`validate_episodes`, :class:`EpisodeBuffer`
============================== ===================================================

This is the bottom layer: it imports nothing else of the library. Collecting episodes runs
policies in environments and so lies above the policies, in :mod:`torch_api.collection`
(``collect_episodes``, the user's ``Collector``, worker processes).
"""

import importlib
import warnings

from torch_api.data.actions import ActionEncoding
from torch_api.data.buffer import EpisodeBuffer, cat_episodes, validate_episodes
from torch_api.data.episodes import (
    EXTERNAL_POLICY_ID,
    LOG_PROB_KEYS,
    REWARD_KEY,
    SAMPLE_LOG_PROB,
    SAMPLE_PROBS,
    as_episodes,
    joinable,
    pad_steps,
    taken_sample_probs,
    to_log_prob_form,
)

__all__ = [
    "EXTERNAL_POLICY_ID",
    "ActionEncoding",
    "EpisodeBuffer",
    "LOG_PROB_KEYS",
    "REWARD_KEY",
    "SAMPLE_LOG_PROB",
    "SAMPLE_PROBS",
    "as_episodes",
    "cat_episodes",
    "joinable",
    "pad_steps",
    "taken_sample_probs",
    "to_log_prob_form",
    "validate_episodes",
]

# names this module re-exported before the layout of issue #23, now at home elsewhere: kept
# for one release (with a DeprecationWarning naming their home)
_MOVED = {
    "EnvPerBatch": "torch_api.collection",
    "SpecCheckedPolicy": "torch_api.collection",
    "at_most_rows": "torch_api.collection",
    "collect_episodes": "torch_api.collection",
    "collect_with_collector": "torch_api.collection",
    "seed_env": "torch_api.streams",
}


def __getattr__(name: str):
    if name not in _MOVED:
        raise AttributeError(f"module 'torch_api.data' has no attribute {name!r}")
    home = _MOVED[name]
    warnings.warn(
        f"torch_api.data.{name} moved to {home}.{name}; import it from there (or from "
        "torch_api); this alias goes in the next release",
        DeprecationWarning,
        stacklevel=2,
    )
    return getattr(importlib.import_module(home), name)
