"""Random streams of an environment: one seed for all rows, or one stream per block of rows.

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

__all__ = ["BlockSeeded", "has_block_seeds", "seed_env"]


@runtime_checkable
class BlockSeeded(Protocol):
    """An environment whose rows come in equal consecutive blocks, each with its own stream.

    ``set_block_seeds(seeds)`` seeds block ``b`` (rows ``b·R … (b+1)·R - 1`` of a batch of
    ``len(seeds)·R`` rows) from ``seeds[b]``. This project's ``ChainWalkEnv`` and
    ``BattingEnv`` implement it.
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
