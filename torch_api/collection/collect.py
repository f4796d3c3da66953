"""Collecting episodes: TorchRL rollouts (the default) or the user's own ``Collector``.

Both give episode batches in the library's format (:mod:`torch_api.data`), with the sampling
policy's probabilities recorded and, for reward-free episodes, no reward key at all.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torch_api.data.actions import ActionEncoding, check_actions
from torch_api.data.buffer import EpisodeBuffer, validate_episodes
from torch_api.data.episodes import (
    _episodes_from_rollout,
    pad_steps,
)
from torch_api.policies.base import ActionProbsPolicy, param_dims_of

__all__ = [
    "EnvPerBatch",
    "SpecCheckedPolicy",
    "at_most_rows",
    "collect_episodes",
    "collect_with_collector",
    "rollouts_or",
]


class EnvPerBatch:
    """An environment, or a factory ``batch_size -> env`` that builds one env per batch size.

    The algorithm needs batches of different sizes (``T·M_l`` rewarded rows, ``T·Z·K·M_l``
    reward-free rows); a factory lets each size be built once and reused.

    Example:
        >>> from torchrl.envs import GymEnv
        >>> envs = EnvPerBatch(lambda rows: GymEnv("CartPole-v1"))  # a factory, called once a size
        >>> envs(6) is envs(6), envs(6) is envs(4), envs.is_factory
        (True, False, True)
    """

    def __init__(self, env: EnvBase | Callable[[int], EnvBase]) -> None:
        if not (isinstance(env, EnvBase) or callable(env)):
            raise ValueError(f"env must be a TorchRL EnvBase or a callable, got {type(env)}")
        self.env = env
        self._built: dict[int, EnvBase] = {}

    @property
    def is_factory(self) -> bool:
        return not isinstance(self.env, EnvBase)

    @property
    def built(self) -> dict[int, EnvBase]:
        """The envs the factory built so far, by batch size (a copy)."""
        return dict(self._built)

    def __call__(self, batch: int) -> EnvBase:
        """The env for ``batch`` rows (the fixed env whatever ``batch``, if not a factory)."""
        if not self.is_factory:
            return self.env
        if batch not in self._built:
            env = self.env(batch)
            if not isinstance(env, EnvBase):
                raise ValueError(
                    f"env factory returned {'None' if env is None else type(env).__name__}, "
                    f"expected a TorchRL EnvBase (asked for a batch of {batch} rows)"
                )
            self._built[batch] = env
        return self._built[batch]

    def close(self) -> None:
        """Close the envs the factory built (a ``ParallelEnv``'s worker processes end); an env
        given as such is the caller's to close. Later calls build afresh."""
        built, self._built = self._built, {}
        for env in built.values():
            if not getattr(env, "is_closed", False):
                env.close()


def at_most_rows(factory: Callable[[int], EnvBase], max_rows: int) -> Callable[[int], EnvBase]:
    """An env factory that never builds more than ``max_rows`` rows.

    The library asks a factory for the batch it would roll out at once (``T·M_l`` rewarded rows,
    ``T·Z·K·M_l`` reward-free ones: 16 for a toy run of Z = 2, K = 4, M = 2), and
    ``lambda rows: ParallelEnv(rows, make_env)`` starts one worker process per row. Wrapped,
    the factory is asked for ``min(rows, max_rows)``: a smaller env is rolled out as often as
    the episodes need (candidate by candidate in the selector). Runs without ``num_trials``
    only (a trial batch must be rolled out in one piece).

    Example:
        >>> from torchrl.envs import GymEnv, SerialEnv
        >>> make = at_most_rows(lambda rows: SerialEnv(rows, lambda: GymEnv("CartPole-v1")), 2)
        >>> make(16).batch_size, make(1).batch_size
        (torch.Size([2]), torch.Size([1]))
    """
    if isinstance(max_rows, bool) or not isinstance(max_rows, int) or max_rows < 1:
        raise ValueError(f"max_rows must be an integer >= 1, got {max_rows!r}")

    def capped(rows: int) -> EnvBase:
        return factory(min(int(rows), max_rows))

    capped.max_rows = max_rows
    return capped


def collect_episodes(
    env: EnvBase,
    policy,
    *,
    num_episodes: int,
    num_steps: int,
    rewarded: bool,
    iteration: int = 0,
    policy_id: int | torch.Tensor = 0,
    validate: bool = True,
) -> TensorDict:
    """Collect ``num_episodes`` episodes of ``num_steps`` steps with ``policy`` on ``env``.

    Uses ``env.rollout`` on the (batched) environment, so each step advances all of its E
    environments at once; ``ceil(M / E)`` rollouts are run and the first M episodes kept. An
    unbatched environment (``batch_size == []``) is rolled out once per episode. Each row is one
    episode: steps after an episode ends are kept but masked out.

    A policy with per-trial parameters (``policy.param_dims == (T,)``, e.g. θ ``[T, B]``)
    collects M episodes for each trial in one rollout: the environment must then have batch
    size ``[T·M]``, rows laid out trial-major, and the result has shape ``[T, M, N]``.

    Actions are in the env's own encoding: a policy of this library
    (:class:`~torch_api.policies.ActionProbsPolicy`) is given the env's action spec (one-hot or
    index, and its dtype); any policy's actions are checked with ``env.action_spec.is_in``
    before each step is taken, and refused with a ``ValueError`` if they do not fit, so the
    recorded actions are the applied ones. Collection runs under TorchRL's
    ``ExplorationType.RANDOM`` (as a ``Collector`` does by default): the actions are drawn
    from the distributions whose probabilities are recorded for the importance weights.

    Args:
        env: a TorchRL environment with a discrete action space (categorical or one-hot).
        policy: a TensorDict module writing ``action`` and the sampling probabilities: the
            library's policies (e.g. :class:`~torch_api.policies.LinearQPolicy`) write
            ``sample_probs``; TorchRL's ``ProbabilisticActor(..., return_log_prob=True)`` over a
            ``Categorical`` or ``OneHotCategorical`` writes ``sample_log_prob`` or
            ``action_log_prob``, which will do as well.
        num_episodes: M ≥ 1 (per trial).
        num_steps: N ≥ 1.
        rewarded: keep ``("next", "reward")``. With False the reward is dropped on collection
            (reward-free data: nothing downstream can read it).
        iteration, policy_id: tags stored with every step (``policy_id`` may be a ``[*T]``
            tensor: one id per trial).
        validate: check the episodes (:func:`validate_episodes`) before returning them;
            False leaves it to the caller (e.g. to keep the valid episodes of a batch).

    Returns:
        TensorDict ``[*T, M, N]`` in the format of this module's docstring.
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if len(env.batch_size) > 1:
        raise ValueError(f"env must have a batch size [E] or [], got {tuple(env.batch_size)}")
    trial_dims = param_dims_of(policy)
    rows = math.prod(trial_dims) * num_episodes
    batched = len(env.batch_size) > 0
    if trial_dims and (not batched or env.batch_size[0] != rows):
        raise ValueError(
            f"a policy with per-trial parameters {trial_dims} needs an env of batch size "
            f"[T·M] = [{rows}], got {tuple(env.batch_size)}"
        )
    per_rollout = env.batch_size[0] if batched else 1
    encoding = ActionEncoding.from_spec(env.action_spec, tuple(env.batch_size))
    checked = SpecCheckedPolicy(policy, env)
    chunks = []
    for _ in range(math.ceil(rows / per_rollout)):
        with set_exploration_type(ExplorationType.RANDOM):
            rollout = env.rollout(
                max_steps=num_steps, policy=checked, break_when_any_done=False, auto_reset=True
            )
        if not batched:
            rollout = rollout.unsqueeze(0)
        if rollout.shape[-1] != num_steps:
            raise RuntimeError(
                f"env.rollout returned {rollout.shape[-1]} steps instead of {num_steps}"
            )
        chunks.append(_episodes_from_rollout(rollout, rewarded=rewarded, encoding=encoding))
    episodes = torch.cat(chunks, 0)[:rows] if len(chunks) > 1 else chunks[0][:rows]
    episodes = episodes.reshape(*trial_dims, num_episodes, num_steps)
    episodes["iteration"] = torch.full(episodes.shape, iteration, dtype=torch.long)
    ids = torch.as_tensor(policy_id, dtype=torch.long)
    episodes["policy_id"] = ids.reshape(*ids.shape, 1, 1).expand(episodes.shape).clone()
    if validate:
        validate_episodes(episodes, rewarded=rewarded)
    return episodes


def collect_with_collector(
    make_collector: Callable,
    policy,
    *,
    num_episodes: int,
    num_steps: int,
    rewarded: bool,
    iteration: int = 0,
    policy_id: int = 0,
    validate: bool = True,
) -> TensorDict:
    """:func:`collect_episodes` through a TorchRL ``Collector`` of the user's own.

    ``make_collector(policy, num_episodes)`` returns a collector (anything iterable over
    TorchRL batches: ``torchrl.collectors.Collector``, ideally with
    ``trajs_per_batch=num_episodes, traj_format="padded"``) running ``policy`` on an env whose
    episodes last at most ``num_steps`` steps (e.g. a ``StepCounter(max_steps=num_steps)``).
    Its batches are read as :meth:`EpisodeBuffer.extend` reads them (flat or padded;
    trajectories cut at a batch's end joined with their continuation) until the
    ``num_episodes`` episodes that *started* first are whole; those are kept, padded to
    ``num_steps``. A collector numbers trajectories as they start (TorchRL's ``("collector",
    "traj_ids")``, from 0 for a new collector): the kept ones are those numbered below
    ``num_episodes`` (with one row per episode, each row's first). The first to *end* would be
    biased towards short episodes: rows running side by side, a row whose episodes fail early
    ends several before a row whose episode lasts ends one. Batches without trajectory ids
    (rollouts ``[E, N]``, one episode a row) are kept in the order given.
    The collector is shut down afterwards. The collector's env and its exploration type are the
    user's (a ``Collector`` samples, ``ExplorationType.RANDOM``, by default); every batch's
    actions are checked against the collector's ``env.action_spec`` where it has one.
    With ``validate=False`` the episodes are not checked (:func:`validate_episodes`), neither
    batch by batch nor at the end: the caller checks them (e.g. to keep the valid episodes).

    Returns:
        TensorDict ``[M, N]`` in the format of this module's docstring.

    Raises:
        ValueError: an episode longer than ``num_steps`` (at the first batch that holds one,
            before any episode is used), actions outside the spec, or a collector whose
            trajectories are not numbered from its first reset (one used before: make a new
            collector for each call).
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    if isinstance(policy, ActionProbsPolicy):
        policy = copy.copy(policy)  # given the collector env's encoding below
    collector = make_collector(policy, num_episodes)
    env = getattr(collector, "env", None)
    row_spec = getattr(env, "action_spec", None)
    if row_spec is not None and isinstance(policy, ActionProbsPolicy):
        encoding = ActionEncoding.from_spec(row_spec, tuple(env.batch_size))
        policy.action_encoding, policy.one_hot = encoding, encoding.one_hot
    for _ in range(len(getattr(env, "batch_size", ()))):
        row_spec = row_spec[0]  # the spec of one env row
    rows = math.prod(getattr(env, "batch_size", ()) or (1,))
    buffer = EpisodeBuffer(rewarded=rewarded, capacity=16 * num_episodes + 64)
    try:
        for count, batch in enumerate(collector, start=1):
            if row_spec is not None:  # the batch's first step is always a real one
                first = batch["action"].reshape(-1, *row_spec.shape)[0]
                check_actions(row_spec, first, who=f"the collector's policy {_name(policy)}")
            batch = _started_first(batch, num_episodes, max(rows, num_episodes), count == 1)
            if batch is None:
                continue
            buffer.extend(batch, validate=validate)
            _check_step_cap(buffer, num_steps, count)
            if len(buffer.whole()) >= num_episodes:
                break
    finally:
        shutdown = getattr(collector, "shutdown", None)
        if shutdown is not None:
            shutdown()
    closed = buffer.whole()
    if len(closed) < num_episodes:
        raise ValueError(
            f"the collector ended after {len(closed)} whole episodes, {num_episodes} were asked for"
        )
    episodes = buffer.episodes()[torch.tensor(closed[:num_episodes])]
    if episodes.shape[-1] > num_steps:  # (padding only: longer episodes were refused)
        episodes = episodes[..., :num_steps]
    episodes = pad_steps(episodes, num_steps)
    episodes["iteration"] = torch.full(episodes.shape, iteration, dtype=torch.long)
    episodes["policy_id"] = torch.full(episodes.shape, int(policy_id), dtype=torch.long)
    if validate:
        validate_episodes(episodes, rewarded=rewarded)
    return episodes


def _started_first(batch: TensorDictBase, count: int, first_ids: int, first_batch: bool):
    """The steps of ``batch`` (a collector's, flat or padded) in trajectories numbered below
    ``count``, the first ``count`` to start; None if it holds none; the batch as given if it
    carries no trajectory ids. ``first_ids``: the first batch of a new collector holds a
    trajectory numbered below it (its rows' first episodes end before any other)."""
    keys = batch.keys(include_nested=True)
    if ("collector", "traj_ids") not in keys:
        return batch
    if ("collector", "mask") in keys and batch.batch_dims >= 2:  # whole trajectories, padded
        rows = batch.reshape(-1, batch.shape[-1])
        real = rows["collector", "mask"].bool()
        ids = torch.where(real, rows["collector", "traj_ids"], -1).max(-1).values
        kept, lowest = rows[ids < count], ids[ids >= 0].min()
    else:  # steps: every trajectory running in the batch, cut or whole
        flat = batch.reshape(-1)
        ids = flat["collector", "traj_ids"]
        kept, lowest = flat[ids < count], ids.min()
    if first_batch and int(lowest) >= first_ids:
        raise ValueError(
            f"the collector's first trajectories are numbered from {int(lowest)}, not 0: it "
            "was used before (make a new Collector for each purchase: its trajectories are "
            "numbered as they start, and the first to start are kept)"
        )
    return kept if kept.shape[0] else None


def _check_step_cap(buffer: EpisodeBuffer, num_steps: int, batch: int) -> None:
    """Refuse, at the batch that shows it, a collector whose episodes run past ``num_steps``
    (an env without a step cap): before the run reads, or pays for, any of its episodes.
    A trajectory cut at a batch's end counts with the part held so far."""
    if buffer.steps is None or buffer.steps <= num_steps:  # (padded length: no real step more)
        return
    longest = buffer.longest_episode()
    if longest > num_steps:
        raise ValueError(
            f"the collector gave an episode of {longest} steps in its batch {batch}, more than "
            f"num_steps = {num_steps}: its env does not end episodes there (add "
            "StepCounter(max_steps=num_steps) to the env, or give the Collector "
            "max_frames_per_traj=num_steps)"
        )


def rollouts_or(collector: Callable | None) -> Callable:
    """The source of episodes, chosen once: ``source(env, policy, **kwargs)`` is
    :func:`collect_episodes` (``env.rollout``), or with a ``collector`` factory
    :func:`collect_with_collector` (``env`` unused). Both take ``validate``."""
    if collector is None:
        return collect_episodes

    def from_collector(env: EnvBase, policy, **kwargs) -> TensorDict:
        return collect_with_collector(collector, policy, **kwargs)

    return from_collector


class SpecCheckedPolicy:
    """A policy in the env's action encoding whose every action is checked against the spec.

    A policy of this library is given the env's action spec
    (:meth:`~torch_api.policies.ActionProbsPolicy.with_action_spec`); any other policy is
    called as it is, and its first actions are checked with ``env.action_spec.is_in`` right
    after it wrote them, before the env applies them
    (:func:`~torch_api.data.actions.check_actions`).
    (Only the first call is checked: an encoding that fits once fits every step, and a check
    per step would cost a device synchronisation per step on a GPU.)

    Args:
        policy: a TensorDict module (or callable) writing the env's action key.
        env: the TorchRL env it acts in.
    """

    def __init__(self, policy, env: EnvBase) -> None:
        if isinstance(policy, SpecCheckedPolicy):
            policy = policy.policy
        if isinstance(policy, ActionProbsPolicy):
            policy = policy.with_action_spec(
                ActionEncoding.from_spec(env.action_spec, tuple(env.batch_size))
            )
        self.policy = policy
        self.spec = env.action_spec
        self.action_key = env.action_key
        self.checked = False

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.policy(tensordict)
        out = tensordict if out is None else out
        if not self.checked:
            action = out.get(self.action_key)
            check_actions(self.spec, action, who=f"the policy {_name(self.policy)}")
            self.checked = True
        return out


def _name(policy) -> str:
    return type(policy).__name__
