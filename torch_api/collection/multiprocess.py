"""Episode collection in worker processes through TorchRL's ``MultiSyncCollector``.

Where an environment is slow and does not batch its rows natively (a Python simulator, a
Gymnasium env stepped row by row), the rows of one collection can be spread over W worker
processes, each stepping an environment of its own share of the rows. The rows are split in
whole blocks (trials): worker w gets trials ``a_w … b_w - 1``, the policy restricted to them
(``trial_slice``) and, where the policy and the environment keep one random stream per trial
(the policy's ``streams``, the env's ``set_block_seeds``), exactly those trials' streams, sent
with the policy. Then the episodes equal those of one in-process ``env.rollout`` bit for bit.
The workers draw from copies: the caller's generators are left as they were, and nothing
replays the workers' draws. A caller therefore derives fresh streams for every collection, as
the loop does (:meth:`~torch_api.streams.TrialStreams.sampling`: one stream per (seed,
trial, iteration, role)).

Without per-trial streams each worker gets a stream keyed from the policy's (one draw per
worker): reproducible, but not the numbers of one process.

The workers die with the calling process: a SIGKILL of it ends them within a fraction of a
second, even while they still import torch (:mod:`torch_api.runs.lifetime`).

Worth it only when collection takes much longer than starting W processes (seconds: each
imports torch, TorchRL and the environment); an environment that already steps its rows in
native threads (the batting arm's ``mujoco.batch``) gains nothing
(``benchmarks/bench_collection.py``).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict
from torchrl.collectors import MultiSyncCollector
from torchrl.data import Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

from counter_rng import CounterStreams
from torch_api.data.actions import ActionEncoding
from torch_api.data.buffer import validate_episodes
from torch_api.data.episodes import _episodes_from_rollout
from torch_api.policies.base import param_dims_of
from torch_api.runs.lifetime import die_with_parent, workers_die_with_this_process
from torch_api.streams import seed_env, spawn_seed

__all__ = ["collect_episodes_in_workers"]


class _WorkerPolicy:
    """Picklable factory of one worker's policy: its trials' slice and random streams."""

    def __init__(self, policy, seed: int | None) -> None:
        self.policy = policy  # pickled with its streams' states (a copy: the caller's stay)
        self.seed = seed  # the worker's own stream where the policy has none per trial

    def __call__(self):
        logging.getLogger("torchrl").setLevel(logging.WARNING)
        torch.set_num_threads(1)
        policy = self.policy
        if self.seed is not None:
            policy = policy.with_streams(CounterStreams(self.seed))
        # Declaring the outputs spares the collector a probing call of the policy at start-up,
        # which would draw from the streams and shift every action by one step.
        encoding = policy.action_encoding  # the env's, set by collect_episodes_in_workers
        if encoding.one_hot:
            action = OneHot(n=policy.num_actions, dtype=encoding.dtype)
        else:
            shape = (1,) if encoding.trailing_dim else ()
            action = Categorical(n=policy.num_actions, shape=shape, dtype=encoding.dtype)
        policy.spec = Composite(
            {
                policy.action_key: action,
                policy.probs_key: Unbounded(shape=(policy.num_actions,), dtype=torch.float64),
            }
        )
        return policy


class _WorkerEnv:
    """Picklable factory of one worker's environment of ``rows`` rows, seeded."""

    def __init__(self, make_env, rows: int, seed: int, block_seeds: Sequence[int] | None):
        self.make_env, self.rows, self.seed, self.block_seeds = make_env, rows, seed, block_seeds
        self.parent = os.getpid()  # (the worker dies with this process)

    def __call__(self) -> EnvBase:
        die_with_parent(self.parent)  # (called in the worker process)
        env = self.make_env(self.rows)
        seed_env(env, self.seed, self.block_seeds)
        return env


def _split(blocks: int, parts: int) -> list[range]:
    size, extra = divmod(blocks, parts)
    bounds = [0]
    for p in range(parts):
        bounds.append(bounds[-1] + size + (p < extra))
    return [range(a, b) for a, b in zip(bounds, bounds[1:], strict=False)]


def collect_episodes_in_workers(
    make_env: Callable[[int], EnvBase],
    policy,
    *,
    num_episodes: int,
    num_steps: int,
    rewarded: bool,
    num_workers: int,
    blocks: int | None = None,
    env_seed: int = 0,
    env_block_seeds: Sequence[int] | None = None,
    iteration: int = 0,
    action_spec=None,
) -> TensorDict:
    """:func:`~torch_api.collection.collect_episodes` with the rows spread over worker processes.

    Args:
        make_env: a picklable callable ``rows -> env`` (a top-level function or class, or a
            ``functools.partial`` of one), called in each worker with its share of the rows.
        policy: as for ``collect_episodes``; it must have ``trial_slice`` when ``blocks > 1``.
            Its streams are read, not moved on (the workers draw from copies of them).
        num_episodes: M per trial (rows in all when the policy has no trial dims).
        num_steps: N.
        rewarded: keep the rewards.
        num_workers: W ≥ 1 worker processes (at most one per block).
        blocks: the rows come in this many equal consecutive blocks that a worker must not
            split, e.g. the trials of a ``PolicyStack`` over ``T·Z·K·M`` rows (default: the
            policy's trials, or one block per row).
        env_seed: seed of the workers' environments (worker w: ``env_seed + w``) where
            ``env_block_seeds`` is not given or the env lacks ``set_block_seeds``.
        env_block_seeds: one seed per block for envs with ``set_block_seeds`` (worker w gets
            its blocks' seeds).
        iteration: tag stored with every step.
        action_spec: the env's action spec or :class:`~torch_api.data.actions.ActionEncoding`; the
            policy writes actions in its encoding (default: read from one env of
            ``make_env(1)``, built here for that).

    Returns:
        TensorDict ``[*T, M, N]`` as ``collect_episodes`` returns.
    """
    if num_workers < 1:
        raise ValueError(f"num_workers must be >= 1, got {num_workers}")
    trial_dims = param_dims_of(policy)
    rows = math.prod(trial_dims) * num_episodes
    if action_spec is None:  # the workers' env encodes actions as one env of its kind does
        probe = make_env(1)
        action_spec = ActionEncoding.from_spec(probe.action_spec, tuple(probe.batch_size))
        if not getattr(probe, "is_closed", False):  # (a batched env not started is closed)
            probe.close()
    policy = policy.with_action_spec(action_spec)
    if blocks is None:
        blocks = math.prod(trial_dims) if trial_dims else rows
    if blocks < 1 or rows % blocks:
        raise ValueError(f"{rows} rows do not split into {blocks} equal blocks")
    if env_block_seeds is not None and len(env_block_seeds) != blocks:
        raise ValueError(f"env_block_seeds must hold {blocks} seeds, got {len(env_block_seeds)}")
    per_block = rows // blocks
    parts = _split(blocks, min(num_workers, blocks))
    streams = policy.counter_streams
    if streams is not None and len(streams) == 1 and blocks > 1:
        streams = None  # one stream for all rows: each worker gets a stream spawned from it
    env_factories, policy_factories = [], []
    for w, part in enumerate(parts):
        piece = policy
        if blocks > 1 and (trial_dims or streams is not None):
            piece = policy.trial_slice(slice(part.start, part.stop))
        # one stream per trial: the worker draws from its trials' streams; else a fresh seed
        seed = (
            None if streams is not None else spawn_seed(policy.counter_streams or policy.generator)
        )
        policy_factories.append(_WorkerPolicy(piece, seed))
        block_seeds = None if env_block_seeds is None else env_block_seeds[part.start : part.stop]
        env_factories.append(_WorkerEnv(make_env, len(part) * per_block, env_seed + w, block_seeds))
    # the workers die with this process, even while they still import torch
    with workers_die_with_this_process():
        collector = MultiSyncCollector(
            env_factories,
            policy_factory=policy_factories,
            frames_per_batch=[len(part) * per_block * num_steps for part in parts],
            total_frames=rows * num_steps,
            # one batch: the collector's first reset is the env's first after seeding, as in
            # env.rollout (a second reset would draw other initial states from the env's
            # streams)
            reset_at_each_iter=False,
            cat_results=0,
            trust_policy=True,
        )
        try:
            batch = next(iter(collector))
        finally:
            collector.shutdown()
    batch = batch.reshape(rows, num_steps)
    episodes = _episodes_from_rollout(batch, rewarded=rewarded)
    episodes = episodes.reshape(*trial_dims, num_episodes, num_steps)
    episodes["iteration"] = torch.full(episodes.shape, iteration, dtype=torch.long)
    episodes["policy_id"] = torch.zeros(episodes.shape, dtype=torch.long)
    validate_episodes(episodes, rewarded=rewarded)
    return episodes
