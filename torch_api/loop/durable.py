"""The durable run: its store, the settings a resume checks, and the rebuilding of a run.

:class:`~torch_api.loop.iteration.ActivePolicyIteration` commits every choice of a sampling
policy, every slice of rewarded episodes and every iteration's record through a
:class:`DurableRun` (a :class:`~torch_api.runs.store.RunStore`, or nothing). Here also: the
loop's state rebuilt from a verified store (:func:`restore`, a :class:`Restored`), checked
before anything is changed.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import NoneType
from typing import NamedTuple

import torch
from tensordict import TensorDict

from torch_api.data.buffer import EpisodeBuffer, validate_episodes
from torch_api.loop.records import Choice, IterationRecord, per_trial_count
from torch_api.runs.store import CorruptRunError, RunStore, StoredRun

__all__ = ["DurableRun", "Restored", "RunLayout", "restore"]


class DurableRun:
    """A run's store at ``path`` (or none), through which the loop commits what it buys.

    Made by the caller and handed to the loop
    (``ActivePolicyIteration(spec, ..., durable=DurableRun(path, resume=True))``), which opens it
    with the run's identity and layout (:meth:`open`): the store is created, or a stored run of
    the same identity is read back and verified for the loop to continue. Each commit calls
    ``on_commit()`` after it. Without a path every ``put_*`` does nothing.

    Args:
        path: the store's SQLite file, or None (a run in memory only).
        resume: continue the run stored there (the same specification, env and basis); a
            missing or empty store starts fresh.
        overwrite: discard a stored run.
        on_commit: called after every commit (e.g. to count commits, or stop a test run).
        settings: the caller's own settings its results depend on beyond the run's identity
            (say, the episodes and length of its test), ``{name: number, string, bool or
            None}``: stored with the run and checked on resume beside its identity (a refusal
            names ``settings.<name>``).

    Attributes:
        store: the :class:`~torch_api.runs.store.RunStore` once opened, or None.
    """

    def __init__(
        self,
        path: str | os.PathLike | None,
        *,
        resume: bool = False,
        overwrite: bool = False,
        on_commit: Callable[[], None] | None = None,
        settings: dict | None = None,
    ) -> None:
        if path is None and (resume or overwrite):
            raise ValueError("resume and overwrite need the path of a store")
        self.settings = dict(settings or {})
        for name, value in self.settings.items():
            if not isinstance(name, str) or not isinstance(
                value, (bool, int, float, str, NoneType)
            ):
                raise ValueError(
                    f"settings must map names to numbers, strings, bools or None, got "
                    f"{name!r}: {value!r}"
                )
        self.path = None if path is None else Path(path)
        self.resume, self.overwrite = bool(resume), bool(overwrite)
        self.on_commit = on_commit or (lambda: None)
        self.store: RunStore | None = None
        self.layout: RunLayout | None = None

    def open(self, identity: dict, layout: RunLayout) -> Restored | None:
        """Open (and lock) the store for a run of ``identity``; returns the state of the stored
        run to continue (verified), or None (a fresh start, or no store).

        Raises:
            StoreError: the run is in use, unwritable, damaged, or stored with another
                identity (the differing fields named).
        """
        if self.store is not None:
            raise RuntimeError(f"the store {self.path} is open already")
        self.layout = layout
        if self.path is None:
            return None
        identity = identity | {f"settings.{name}": v for name, v in self.settings.items()}
        self.store = RunStore(
            self.path, config=identity, resume=self.resume, overwrite=self.overwrite
        )
        if self.store.started_fresh:
            return None
        try:
            return restore(self.store.stored, self.path, layout)
        except BaseException:
            self.store.close()
            raise

    @staticmethod
    def read(path: str | os.PathLike, identity: dict, layout: RunLayout) -> Restored:
        """The state of the run stored at ``path`` (read only), made with ``identity``.

        Raises:
            CorruptRunError: the file fails a check, or was made with another identity.
        """
        stored = RunStore.read(path)
        mine = RunStore.normalise(identity)
        if stored.config != mine:
            differ = sorted(
                k for k in stored.config.keys() | mine.keys() if stored.config.get(k) != mine.get(k)
            )
            raise CorruptRunError(
                f"the run stored in {path} was made with other settings: {differ}"
            )
        return restore(stored, Path(path), layout)

    @property
    def closed(self) -> bool:
        """The store is closed (a run without one is never closed)."""
        return self.store is not None and self.store.closed

    def put_selection(self, iteration: int, row: dict, free: TensorDict | None) -> None:
        """Commit iteration l's choice (and its reward-free episodes, if kept)."""
        if self.store is not None:
            self.store.put_selection(iteration, row, free)
            self.on_commit()

    def put_episodes(self, iteration: int, episodes: dict[int, TensorDict]) -> None:
        """Commit rewarded episodes of iteration l, by index m."""
        if self.store is not None:
            self.store.put_episodes(iteration, episodes)
            self.on_commit()

    def put_record(self, iteration: int, record: dict) -> None:
        """Commit iteration l's record (θ_l)."""
        if self.store is not None:
            self.store.put_record(iteration, record)
            self.on_commit()

    def close(self) -> None:
        """Close the store (its lock is released)."""
        if self.store is not None:
            self.store.close()


@dataclass
class Restored:
    """The loop's state rebuilt from a stored run (:func:`restore`).

    Attributes:
        rewarded, reward_free: the buffers, the warm start first.
        reward_free_transitions: collected so far, per trial ``[*T]`` (long).
        history: the records of the iterations done; theta: θ of the last (None: none done).
        pending: the choice of the coming iteration when all its rewards are bought, else None.
        choice, bought: the coming iteration's choice and the episodes bought of it by index,
            when it is under way (else None and ``{}``).
    """

    rewarded: EpisodeBuffer
    reward_free: EpisodeBuffer
    reward_free_transitions: torch.Tensor
    history: list[IterationRecord]
    theta: torch.Tensor | None
    pending: Choice | None
    choice: Choice | None
    bought: dict[int, TensorDict]


class RunLayout(NamedTuple):
    """What a stored run's rows are read against: the loop's schedule and shapes.

    Attributes:
        schedule: M_1 … M_L; trial_dims: ``()`` or ``(T,)``; theta_shape: θ's ``[*T, B]``.
        rewarded_slice, keep_reward_free: as the loop's.
        warm: the warm start's episodes ``[*T, M_0, N]`` (or None), first in the buffer.
        capacities: those of the rewarded and the reward-free buffers.
    """

    schedule: list[int]
    trial_dims: tuple[int, ...]
    theta_shape: torch.Size
    rewarded_slice: str
    keep_reward_free: bool
    warm: TensorDict | None
    capacities: tuple[int, int]


def restore(stored: StoredRun, path, layout: RunLayout) -> Restored:
    """Rebuild the loop's state from a verified store; pure (nothing is changed if it fails).

    Raises:
        CorruptRunError: the stored rows do not form a run of this schedule.
    """
    schedule, trial_dims, theta_shape, rewarded_slice, keep_reward_free, warm, capacities = layout
    done = len(stored.records)
    if sorted(stored.records) != list(range(1, done + 1)) or done > len(schedule):
        raise CorruptRunError(f"the run {path} holds records {sorted(stored.records)}")
    rewarded = EpisodeBuffer(rewarded=True, capacity=capacities[0])
    if warm is not None:  # the warm start comes first, as in a fresh run
        rewarded.extend(warm)
    reward_free = EpisodeBuffer(rewarded=False, capacity=capacities[1])
    free_transitions = torch.zeros(trial_dims, dtype=torch.long)
    choice, bought = None, {}
    nxt = done + 1
    if nxt <= len(schedule) and nxt in stored.selections:
        if stored.episodes.get(nxt) or rewarded_slice == "episode":
            choice = dict(stored.selections[nxt])
            bought = dict(stored.episodes.get(nxt, {}))
    try:
        for l_now in range(1, done + 1 + (choice is not None)):
            row = stored.selections.get(l_now)
            if row is None:
                raise CorruptRunError(f"the run {path} lacks the selection of iteration {l_now}")
            free_transitions = free_transitions + per_trial_count(
                row["reward_free_transitions"], trial_dims
            )
            if keep_reward_free and l_now in stored.free:
                reward_free.extend(stored.free[l_now])
        for l_now in range(1, done + 1):
            got = stored.episodes.get(l_now, {})
            if sorted(got) != list(range(schedule[l_now - 1])):
                raise CorruptRunError(
                    f"the run {path} holds episodes {sorted(got)} of iteration {l_now}, "
                    f"which bought {schedule[l_now - 1]}"
                )
            rewarded.extend(torch.stack([got[m] for m in sorted(got)], len(trial_dims)))
        for m, episode in bought.items():
            if not 0 <= m < schedule[nxt - 1]:
                raise CorruptRunError(f"the run {path} holds episode {m} of iteration {nxt}")
            validate_episodes(episode.unsqueeze(-2), rewarded=True)
        history = [IterationRecord(**r) for _, r in sorted(stored.records.items())]
        theta = None
        if history:
            theta = torch.tensor(history[-1].theta, dtype=torch.float64)
            if theta.shape != theta_shape:
                raise CorruptRunError(f"the run {path} holds θ of shape {tuple(theta.shape)}")
    except (ValueError, TypeError, KeyError, RuntimeError) as error:
        if isinstance(error, CorruptRunError):
            raise
        raise CorruptRunError(f"the run {path} cannot be restored: {error}") from None
    if choice is not None:
        choice = Choice.from_row(choice)
    pending = None
    if choice is not None and len(bought) == schedule[nxt - 1]:
        last = [bought[m] for m in sorted(bought)]
        rewarded.extend(torch.stack(last, len(trial_dims)))
        pending, choice, bought = choice, None, {}
    return Restored(
        rewarded=rewarded,
        reward_free=reward_free,
        reward_free_transitions=free_transitions,
        history=history,
        theta=theta,
        pending=pending,
        choice=choice,
        bought=bought,
    )
