"""Collecting the K candidates' reward-free episodes ``[*T, Z, K, M, N]`` for Algorithm 2.

How the episodes are collected is chosen once, when a
:class:`~torch_api.loop.selector.SamplingPolicySelector` is built or bound
(:func:`choose_collection`), as one of three small strategies; collecting is then one call:

============================= ===============================================================
:class:`RolloutCollection`    ``env.rollout``: one batched rollout of a :class:`PolicyStack`
                              when the env's batch is ``T·Z·K·M`` (else candidate by candidate)
:class:`WorkerCollection`     worker processes running TorchRL's ``MultiSyncCollector``
:class:`CollectorCollection`  the user's own ``Collector``, candidate by candidate
============================= ===============================================================

Each strategy is called as ``collection(candidates, shape=(Z, M, N), iteration=l,
generator=g, action_encoding=e)`` (``e``: the env's encoding where known, else None) and is
seeded as ``collection.seed(batch, seed, block_seeds)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase

from torch_api.collection.collect import EnvPerBatch, collect_episodes, collect_with_collector
from torch_api.collection.multiprocess import collect_episodes_in_workers
from torch_api.data.episodes import joinable
from torch_api.policies.base import ActionProbsPolicy, param_dims_of
from torch_api.streams import seed_env

__all__ = [
    "CollectorCollection",
    "PolicyStack",
    "RolloutCollection",
    "WorkerCollection",
    "choose_collection",
    "rollout_rows",
]


class PolicyStack(ActionProbsPolicy):
    """K policies side by side over one batched environment, rows laid out as ``[..., K, M]``.

    Row ``e`` of an environment batch of size ``R·K·M`` follows ``policies[(e // M) % K]``.
    Used to collect every candidate's reward-free episodes in a single batched rollout.

    Args:
        policies: K policies with ``action_probs``.
        episodes_per_policy: M, consecutive rows per policy.
        generator: random stream for sampling (or ``streams=``: counter-based streams, one per
            block of rows, e.g. per trial; see :func:`~torch_api.policies.base.sample_actions`).
    """

    def __init__(self, policies: Sequence, *, episodes_per_policy: int, generator=None, **io):
        if not policies:
            raise ValueError("policies must not be empty")
        super().__init__(num_actions=policies[0].num_actions, generator=generator, **io)
        self.policies = list(policies)
        self.episodes_per_policy = int(episodes_per_policy)

    def action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        rows = obs.shape[0]
        block = len(self.policies) * self.episodes_per_policy
        if rows % block:
            raise ValueError(f"a batch of {rows} rows is not a multiple of K·M = {block}")
        grid = obs.reshape(
            rows // block, len(self.policies), self.episodes_per_policy, *obs.shape[1:]
        )
        probs = [p.action_probs(grid[:, k]) for k, p in enumerate(self.policies)]
        return torch.stack(probs, 1).reshape(rows, *probs[0].shape[2:])

    def trial_slice(self, trials: slice) -> PolicyStack:
        """The stack of some trials only (each policy sliced; the per-trial streams too)."""
        return PolicyStack(
            [p.trial_slice(trials) for p in self.policies],
            episodes_per_policy=self.episodes_per_policy,
            **self._io_kwargs(trials),
        )


def _stack(candidates: Sequence, m: int, generator) -> PolicyStack:
    """The candidates as one policy over ``[..., K, M]`` rows, drawing from the first
    candidate's per-trial streams, else from ``generator`` or the first candidate's stream."""
    blocks = candidates[0].counter_streams  # one stream per trial (or one for all)
    streams = blocks if blocks is not None else generator or candidates[0].generator
    return PolicyStack(candidates, episodes_per_policy=m, streams=streams)


def _tag_candidates(episodes: TensorDictBase, shape: tuple, k: int) -> TensorDictBase:
    """``[T·Z·K·M, N]`` rows as ``[*T, Z, K, M, N]`` with ``policy_id`` k of each."""
    episodes = episodes.reshape(*shape)
    ids = torch.arange(k).reshape(k, 1, 1)
    episodes["policy_id"] = ids.expand(episodes.shape).clone()
    return episodes


def _each(source: Callable, candidates: Sequence, shape: tuple, iteration: int):
    """``[Z, K, M, N]`` episodes collected candidate by candidate (Z·M rows each) from
    ``source(rows, policy, **kwargs)``: the way for candidates that are not the library's
    policies (e.g. a TorchRL ``ProbabilisticActor``), which cannot share one batched rollout,
    and for the user's collector."""
    z, m, n = shape
    for cand in candidates:
        if param_dims_of(cand):
            raise ValueError(
                "candidates with per-trial parameters cannot be mixed with other policies"
            )
    parts = [
        source(
            z * m,
            cand,
            num_episodes=z * m,
            num_steps=n,
            rewarded=False,
            iteration=iteration,
            policy_id=i,
        ).reshape(z, m, n)
        for i, cand in enumerate(candidates)
    ]
    return torch.stack(joinable(parts), 1)


def _library_policies(candidates: Sequence) -> bool:
    return all(isinstance(c, ActionProbsPolicy) for c in candidates)


def rollout_rows(candidates: Sequence, shape: tuple) -> int:
    """The batch of the env that :class:`RolloutCollection` collects these candidates with,
    for ``shape = (Z, M, N)``: ``T·Z·K·M`` (one stacked rollout of the library's policies) or
    ``Z·M`` (candidate by candidate). Seed that batch's env before collecting."""
    z, m, _ = shape
    if not _library_policies(candidates):
        return z * m
    return math.prod(param_dims_of(candidates[0])) * z * len(candidates) * m


class RolloutCollection:
    """Reward-free episodes from ``env.rollout`` (the default; fast on batched envs).

    The library's policies share one batched rollout of a :class:`PolicyStack` when the
    environment's batch is ``T·Z·K·M``; on a fixed env of another batch size they are rolled
    out repeat by repeat and candidate by candidate; other policies (a TorchRL actor) candidate
    by candidate on an env of ``Z·M`` rows.

    Args:
        envs: the reward-free environments, one per batch size.
    """

    def __init__(self, envs: EnvPerBatch) -> None:
        self.envs = envs

    def seed(self, batch: int, seed: int, block_seeds: Sequence[int] | None) -> None:
        seed_env(self.envs(batch), seed, block_seeds)

    def _rollout(self, rows: int, policy, **kwargs) -> TensorDictBase:
        return collect_episodes(self.envs(rows), policy, **kwargs)

    def __call__(
        self, candidates: Sequence, *, shape: tuple, iteration: int, generator, action_encoding
    ):
        if not _library_policies(candidates):
            return _each(self._rollout, candidates, shape, iteration)
        z, m, n = shape
        k = len(candidates)
        trial_dims = param_dims_of(candidates[0])
        rows = rollout_rows(candidates, shape)
        env = self.envs(rows)
        if len(env.batch_size) == 1 and env.batch_size[0] == rows:
            episodes = collect_episodes(
                env,
                _stack(candidates, m, generator),
                num_episodes=rows,
                num_steps=n,
                rewarded=False,
                iteration=iteration,
            )
            return _tag_candidates(episodes, (*trial_dims, z, k, m, n), k)
        if trial_dims:
            raise ValueError(
                f"candidates with per-trial parameters {trial_dims} need a reward-free env of "
                f"batch size T·Z·K·M = {rows} (pass a callable batch_size -> env)"
            )
        repeats = [
            torch.stack(
                [
                    collect_episodes(
                        env,
                        cand,
                        num_episodes=m,
                        num_steps=n,
                        rewarded=False,
                        iteration=iteration,
                        policy_id=i,
                    )
                    for i, cand in enumerate(candidates)
                ]
            )
            for _ in range(z)
        ]
        return torch.stack(repeats)

    def close(self) -> None:
        self.envs.close()


class WorkerCollection:
    """Reward-free episodes collected in worker processes by TorchRL's ``MultiSyncCollector``
    (:func:`~torch_api.collection.multiprocess.collect_episodes_in_workers`; for slow environments).

    Args:
        envs: a picklable factory ``batch_size -> env`` (the workers build their own envs).
        num_workers: W ≥ 1 worker processes.
    """

    def __init__(self, envs: EnvPerBatch, num_workers: int) -> None:
        if not envs.is_factory:
            raise ValueError("num_workers needs env as a picklable callable batch_size -> env")
        self.envs = envs
        self.num_workers = int(num_workers)
        self._env_seeds: tuple[int, list[int] | None] = (0, None)

    def seed(self, batch: int, seed: int, block_seeds: Sequence[int] | None) -> None:
        """Seed the workers' environments of the next call."""
        self._env_seeds = (seed, None if block_seeds is None else list(block_seeds))

    def __call__(
        self, candidates: Sequence, *, shape: tuple, iteration: int, generator, action_encoding
    ):
        if not _library_policies(candidates):
            raise ValueError(
                "num_workers needs every candidate to be a torch_api policy; got "
                f"{[type(c).__name__ for c in candidates]}"
            )
        z, m, n = shape
        k = len(candidates)
        trial_dims = param_dims_of(candidates[0])
        trials = math.prod(trial_dims)
        seed, block_seeds = self._env_seeds
        episodes = collect_episodes_in_workers(
            self.envs.env,
            _stack(candidates, m, generator),
            action_spec=action_encoding,
            num_episodes=trials * z * k * m,
            num_steps=n,
            rewarded=False,
            num_workers=self.num_workers,
            blocks=trials,
            env_seed=seed,
            env_block_seeds=block_seeds,
            iteration=iteration,
        )
        return _tag_candidates(episodes, (*trial_dims, z, k, m, n), k)

    def close(self) -> None:
        self.envs.close()


class CollectorCollection:
    """Reward-free episodes read from the user's ``Collector``
    (:func:`~torch_api.collection.collect.collect_with_collector`), candidate by candidate,
    ``Z·M`` each.
    The collector's env is seeded by the user.

    Args:
        collector: a factory ``(policy, num_episodes) -> Collector``.
    """

    def __init__(self, collector: Callable) -> None:
        self.collector = collector

    def seed(self, batch: int, seed: int, block_seeds: Sequence[int] | None) -> None:
        """Nothing to seed: the collector's env is the user's."""

    def _read(self, rows: int, policy, **kwargs) -> TensorDictBase:
        return collect_with_collector(self.collector, policy, **kwargs)

    def __call__(
        self, candidates: Sequence, *, shape: tuple, iteration: int, generator, action_encoding
    ):
        return _each(self._read, candidates, shape, iteration)

    def close(self) -> None:
        """Nothing to close: each collector is shut down after its episodes."""


def choose_collection(
    env: EnvPerBatch, *, num_workers: int = 0, collector: Callable | None = None
) -> RolloutCollection | WorkerCollection | CollectorCollection:
    """The collection strategy of a selector: the user's ``collector`` if given, else worker
    processes if ``num_workers > 0``, else ``env.rollout``."""
    if collector is not None and num_workers:
        raise ValueError("give either collector or num_workers, not both")
    if collector is not None:
        return CollectorCollection(collector)
    if num_workers:
        return WorkerCollection(env, num_workers)
    return RolloutCollection(env)
