"""Trials and random streams: one layer from which every generator of a run is derived.

:class:`TrialStreams` derives every seed of a run from (seed, trial, iteration, role); the
functions below say how an environment is seeded with them.

Random streams of an environment: one seed for all rows, or one stream per block of rows.

An environment that runs several independent trials side by side (rows laid out trial-major)
can give each trial's rows a random stream of their own, so that a batched run of T trials
draws exactly the numbers of T separate runs. That capability is declared by a method,
``set_block_seeds(seeds)``, described by the :class:`BlockSeeded` protocol; any other TorchRL
env is seeded with ``env.set_seed(seed)``.

Whether an env has the capability is read with :func:`inspect.getattr_static`, which looks the
method up on the class without calling the env's ``__getattr__``: TorchRL's batched envs
(``SerialEnv``, ``ParallelEnv``) forward unknown attributes to their sub-envs, and before they
are started that lookup recurses without end (a ``RecursionError`` from a plain ``hasattr``).
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch

from counter_rng import CounterStreams, derive_key, derive_keys

__all__ = [
    "BlockSeeded",
    "TrialStreams",
    "derive_seed",
    "has_block_seeds",
    "seed_env",
    "slice_seed",
    "spawn_seed",
    "trial_seeds_of",
]


@runtime_checkable
class BlockSeeded(Protocol):
    """An environment whose rows come in equal consecutive blocks, each with its own stream.

    ``set_block_seeds(seeds)`` seeds block ``b`` (rows ``b·R … (b+1)·R - 1`` of a batch of
    ``len(seeds)·R`` rows) from ``seeds[b]``. This project's ``ChainWalkEnv`` and
    ``BattingEnv`` implement it; any env that does (an extension point) gets per-trial streams
    from :func:`seed_env`, any other is seeded with ``set_seed``.

    Example:
        >>> class Walk:  # a sketch of an env's seeding part
        ...     def set_seed(self, seed): self.seeds = [seed]
        ...     def set_block_seeds(self, seeds): self.seeds = list(seeds)
        >>> env = Walk()
        >>> isinstance(env, BlockSeeded), has_block_seeds(env)
        (True, True)
        >>> seed_env(env, 0, block_seeds=[11, 22]); env.seeds
        [11, 22]
    """

    def set_block_seeds(self, seeds: Sequence[int]) -> None: ...


def has_block_seeds(env) -> bool:
    """Whether ``env`` implements :class:`BlockSeeded` (looked up statically, see the module)."""
    try:
        method = inspect.getattr_static(env, "set_block_seeds")
    except AttributeError:
        return False
    return callable(method) or isinstance(method, staticmethod | classmethod)


def seed_env(env, seed: int, block_seeds: Sequence[int] | None = None) -> None:
    """Seed ``env``: one stream per block of rows where the env is :class:`BlockSeeded` and
    ``block_seeds`` are given, else ``env.set_seed(seed)``."""
    if block_seeds is not None and has_block_seeds(env):
        env.set_block_seeds(list(block_seeds))
    else:
        env.set_seed(seed)


# -- the run's streams: every generator from (seed, trial, iteration, role) -------------------

STREAMS = {  # the roles of one iteration's streams (the numbers enter the seed derivation)
    "policy": 0,
    "reward_free_env": 1,
    "rewarded_env": 2,
    "evaluation": 3,
    "trial": 4,
    "reward_free_policy": 5,
}
SLICE_STREAMS = {"policy": 6, "rewarded_env": 7}  # per-episode slices (rewarded_slice="episode")


def derive_seed(seed: int, iteration: int, stream: str) -> int:
    """Independent seed (a 63-bit key) of one random stream of one iteration.

    ``derive_key(seed, iteration, STREAMS[stream])`` (:func:`counter_rng.derive_key`: the
    first two words of Philox4x32-10 keyed by the seed, counter ``(iteration, role, 0, tag)``).
    Every iteration re-seeds its streams from ``(seed, iteration, stream)``, so an interrupted
    run resumed from a checkpoint draws exactly the numbers an uninterrupted run would have.
    (``derive_seed(seed, t, "trial")`` is trial t's seed.)

    Example:
        >>> a, b = derive_seed(0, 1, "policy"), derive_seed(0, 2, "policy")
        >>> a == derive_seed(0, 1, "policy") and a != b
        True
    """
    return derive_key(seed, iteration, STREAMS[stream])


def slice_seed(seed: int, iteration: int, episode: int, stream: str) -> int:
    """Seed of one stream of rewarded episode m (0-based) of iteration l, for runs that buy
    one episode at a time (``rewarded_slice="episode"``): a resume continues at any episode."""
    return derive_key(seed, iteration, SLICE_STREAMS[stream], episode)


def spawn_seed(stream: torch.Generator | CounterStreams | None) -> int:
    """The seed of a new stream drawn from ``stream`` (one draw; None: torch's global
    generator), e.g. a worker's where the policy has no stream per trial. A counter-based
    stream of one key gives a key derived from its key and position, and moves on.

    Example:
        >>> a, b = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
        >>> spawn_seed(a) == spawn_seed(b) != spawn_seed(a)
        True
    """
    if isinstance(stream, CounterStreams):
        stream.calls += 1
        return derive_key(int(stream.keys[0]), stream.calls - 1, len(stream), _SPAWN)
    return int(torch.randint(2**62, (), generator=stream))


_SPAWN = 0x5350  # the derivation's last word for spawned keys


class TrialStreams:
    """The one place a run's random streams come from: (seed, trial, iteration, role).

    A run has a seed and, with T trials side by side, one seed per trial. Each iteration l
    derives, per role (``STREAMS``: the policy's sampling, the rewarded env, the reward-free
    env, the reward-free sampling, the evaluation), one key for the run (:func:`derive_seed`)
    and one per trial (for per-trial streams: the policies' streams and the envs'
    ``set_block_seeds``), all trials' keys in one vectorised computation. A run that buys one
    episode at a time derives its streams from (seed, trial, iteration, episode, role) instead
    (:func:`slice_seed`).

    Sampling streams are :class:`counter_rng.CounterStreams` made fresh for every use
    (:meth:`sampling`, given to a policy by ``policy.with_streams``): nothing continues a stream
    from one use to the next, so a use in worker processes leaves nothing to catch up in the
    parent, and trial t's numbers do not depend on the other trials of the batch.

    Args:
        seed: the run's seed.
        trial_seeds: one seed per trial, or None (a single run).

    Example:
        >>> streams = TrialStreams(seed=0, trial_seeds=[11, 22])
        >>> seed, blocks = streams.env_seeds(1, "rewarded_env")
        >>> blocks == [derive_seed(11, 1, "rewarded_env"), derive_seed(22, 1, "rewarded_env")]
        True
        >>> len(streams.sampling(1, "policy"))  # one stream per trial
        2
        >>> a, b = streams.sampling(1, "policy"), streams.sampling(1, "policy")
        >>> torch.equal(a.uniform((2, 3)), b.uniform((2, 3)))
        True
    """

    def __init__(self, *, seed: int, trial_seeds: Sequence[int] | None = None) -> None:
        self.seed = int(seed)
        self.trial_seeds = None if trial_seeds is None else [int(s) for s in trial_seeds]
        self._trial_keys = None if trial_seeds is None else torch.tensor(self.trial_seeds)

    @classmethod
    def for_trials(
        cls, seed: int, num_trials: int | None, trial_seeds: Sequence[int] | None = None
    ) -> TrialStreams:
        """The streams of a run of ``num_trials`` trials (None: a single run); without
        ``trial_seeds``, trial t's seed is ``derive_seed(seed, t, "trial")``."""
        if num_trials is None and trial_seeds is not None:
            raise ValueError("trial_seeds needs num_trials")
        if num_trials is not None and trial_seeds is None:
            trial_seeds = trial_seeds_of(seed, range(num_trials))
        if trial_seeds is not None and len(trial_seeds) != num_trials:
            raise ValueError(
                f"trial_seeds must hold num_trials = {num_trials} seeds, got {len(trial_seeds)}"
            )
        return cls(seed=seed, trial_seeds=trial_seeds)

    def run_seed(self, iteration: int, role: str) -> int:
        """The run's seed of ``role`` in iteration l."""
        return derive_seed(self.seed, iteration, role)

    def block_seeds(self, iteration: int, role: str) -> list[int]:
        """Per-trial seeds of ``role`` in iteration l (runs with trials only)."""
        if self._trial_keys is None:
            raise ValueError("block_seeds needs a run with num_trials")
        return derive_keys(self._trial_keys, iteration, STREAMS[role]).tolist()

    def sampling(self, iteration: int, role: str) -> CounterStreams:
        """Fresh sampling streams of ``role`` in iteration l, for ``policy.with_streams``: one
        stream per trial in a run with trials, else one for the run."""
        return _fresh(*self.env_seeds(iteration, role))

    def slice_sampling(self, iteration: int, episode: int, role: str) -> CounterStreams:
        """Fresh sampling streams of ``role`` for rewarded episode m of iteration l."""
        return _fresh(*self.slice_seeds(iteration, episode, role))

    def env_seeds(self, iteration: int, role: str) -> tuple[int, list[int] | None]:
        """The run's seed and, with trials, the per-trial seeds of an env's ``role``."""
        blocks = self.block_seeds(iteration, role) if self.trial_seeds is not None else None
        return self.run_seed(iteration, role), blocks

    def slice_seeds(self, iteration: int, episode: int, role: str) -> tuple[int, list | None]:
        """The run's and the per-trial seeds of ``role`` for rewarded episode m of l."""
        blocks = None
        if self._trial_keys is not None:
            role_id = SLICE_STREAMS[role]
            blocks = derive_keys(self._trial_keys, iteration, role_id, episode).tolist()
        return slice_seed(self.seed, iteration, episode, role), blocks


def trial_seeds_of(seed: int, trials: Sequence[int]) -> list[int]:
    """Trial t's seed ``derive_seed(seed, t, "trial")`` for each t, in one computation.

    Example:
        >>> trial_seeds_of(7, [0, 3]) == [derive_seed(7, 0, "trial"), derive_seed(7, 3, "trial")]
        True
    """
    trials = torch.as_tensor(list(trials), dtype=torch.int64)
    if not len(trials):
        return []
    return derive_keys(
        torch.full_like(trials, int(seed) & _KEY_MASK), trials, STREAMS["trial"]
    ).tolist()


_KEY_MASK = (1 << 63) - 1


def _fresh(seed: int, block_seeds: Sequence[int] | None) -> CounterStreams:
    """New streams: one keyed by ``seed``, or one per block seed."""
    return CounterStreams(seed if block_seeds is None else block_seeds)
