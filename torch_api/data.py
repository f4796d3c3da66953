"""Episodes: collection through TorchRL and storage in TensorDict replay buffers.

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

The code lives in three modules, re-exported here: :mod:`torch_api.episodes` (the format and
:func:`as_episodes`), :mod:`torch_api.collect` (:func:`collect_episodes`, the user's
``Collector``) and :mod:`torch_api.buffer` (:func:`validate_episodes`,
:class:`EpisodeBuffer`).
"""

from torch_api.buffer import EpisodeBuffer, cat_episodes, validate_episodes
from torch_api.collect import (
    EnvPerBatch,
    SpecCheckedPolicy,
    at_most_rows,
    collect_episodes,
    collect_with_collector,
)
from torch_api.episodes import (
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
from torch_api.streams import seed_env

__all__ = [
    "EXTERNAL_POLICY_ID",
    "EnvPerBatch",
    "at_most_rows",
    "EpisodeBuffer",
    "LOG_PROB_KEYS",
    "REWARD_KEY",
    "SAMPLE_LOG_PROB",
    "SAMPLE_PROBS",
    "SpecCheckedPolicy",
    "as_episodes",
    "cat_episodes",
    "collect_episodes",
    "collect_with_collector",
    "joinable",
    "pad_steps",
    "seed_env",
    "taken_sample_probs",
    "to_log_prob_form",
    "validate_episodes",
]
