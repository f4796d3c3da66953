"""The durable state of a run: what identifies it, and how it is rebuilt from its store.

:class:`~torch_api.loop.iteration.ActivePolicyIteration` commits every selection, every slice of
rewarded episodes and every iteration's record to a :class:`~torch_api.runs.store.RunStore`. Here:
the settings a stored run must agree on (:meth:`DurableState._config`, with
:func:`fingerprint` of the env and the basis), and the rebuilding of the loop's state from a
verified store (:meth:`DurableState._restore`, :meth:`DurableState.load`).
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import torch
from torch import nn

from torch_api._moved import stable_name
from torch_api.data.buffer import EpisodeBuffer, validate_episodes
from torch_api.loop.records import IterationRecord
from torch_api.runs.store import CorruptRunError, RunStore, StoredRun

__all__ = ["DurableState", "fingerprint"]


def _plain(value):
    """A JSON-able, exact description of a setting's value (tensors by digest)."""
    if isinstance(value, torch.Tensor):
        data = value.detach().cpu().contiguous()
        digest = hashlib.sha256(data.view(torch.uint8).numpy().tobytes()).hexdigest()
        return {"dtype": str(data.dtype), "shape": list(data.shape), "sha256": digest}
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, (tuple, list)) and all(
        isinstance(v, (bool, int, float, str)) for v in value
    ):
        return [_plain(v) for v in value]
    return None  # not a plain setting: left out


def _qualified(function) -> str:
    """A function's module and name (how a setting that is a function is told apart)."""
    name = getattr(function, "__qualname__", type(function).__qualname__)
    return f"{stable_name(getattr(function, '__module__', None))}.{name}"


_NOT_IDENTITY = {"batch_size", "seed", "rng", "device", "training", "num_envs", "nthread"}


def fingerprint(obj) -> dict:
    """What identifies an environment or a basis: its class, the tensors of its state and its
    public plain attributes (numbers, strings, tensors), batch size, seeds and device left out.
    """
    out = {"class": f"{stable_name(type(obj).__module__)}.{type(obj).__qualname__}"}
    if isinstance(obj, nn.Module):
        out |= {f"state.{k}": _plain(v) for k, v in obj.state_dict().items()}
    for name, value in sorted(vars(obj).items()):
        if name.startswith("_") or name in _NOT_IDENTITY:
            continue
        plain = _plain(value)
        if plain is not None:
            out[name] = plain
    return out


class DurableState:
    """The durable-state part of :class:`~torch_api.loop.iteration.ActivePolicyIteration` (a mixin:
    its methods read and set the loop's attributes)."""

    def _config(self) -> dict:
        """What gives stored data its meaning: a resume must agree on all of it.

        λ, the device, the worker processes and the evaluation callback are left out: they may
        change on resume (a fit that failed for a bad λ can be redone with a better one).
        """
        last = len(self.schedule) + 1
        trials = math.prod(self.trial_dims)
        selector = self.selector
        config = {
            "schedule": self.schedule,
            "num_steps": self.num_steps,
            "gamma": self.gamma,
            "mode": self.mode,
            "num_repeats": None if selector is None else selector.num_repeats,
            "criterion": None if selector is None else _qualified(selector.criterion),
            "num_trials": self.num_trials,
            "seed": self.seed,
            "trial_seeds": self.trial_seeds,
            "psi_mode": self.psi.mode,
            "knn_k": self.psi.k,
            "improvement": self.improvement,
            "beta": self.beta,
            "tie_break": self.tie_break,
            "candidate_offsets": list(self.candidate_offsets),
            "epsilons": self.family.settings(last),
            "initial_theta": self._initial_theta.tolist(),
            "basis": fingerprint(self.basis),
            "env": fingerprint(self._env_for(trials * self.schedule[0])),
            "keep_reward_free": self.keep_reward_free,
            "rewarded_slice": self.rewarded_slice,
            "initial_episodes": None
            if self._warm is None
            else {str(k): _plain(v) for k, v in self._warm.items(True, True)},
            "fit": self.fit,
        }
        if self.extra_candidates:  # (left out when there are none: older runs stay resumable)
            config["extra_candidates"] = [_qualified(c) for c in self.extra_candidates]
        config |= self.evaluation.settings()  # ν (left out at 1.0: older runs stay resumable)
        return config

    def _open_store(self, *, resume: bool, overwrite: bool) -> None:
        """Open the run's store at ``checkpoint_path`` (if any) and restore a stored run."""
        self.store: RunStore | None = None
        self.resumed = False
        if self.checkpoint_path is None:
            return
        self.store = RunStore(
            self.checkpoint_path, config=self._config(), resume=resume, overwrite=overwrite
        )
        if not self.store.started_fresh:
            try:
                self._restore(self.store.stored)
            except BaseException:
                self._close_store()
                raise
            self.resumed = True

    def _on_commit(self) -> None:
        """Called after every commit to the store: runs the ``on_checkpoint`` hook."""
        if self.on_checkpoint is not None:
            self.on_checkpoint(self)

    def _restore(self, stored: StoredRun, path: Path | None = None) -> None:
        """Rebuild the run's state from a verified store; nothing is changed if it fails.

        Raises:
            CorruptRunError: the stored rows do not form a run of this schedule.
        """
        path = path or self.checkpoint_path
        done = len(stored.records)
        if sorted(stored.records) != list(range(1, done + 1)) or done > len(self.schedule):
            raise CorruptRunError(f"the run {path} holds records {sorted(stored.records)}")
        rewarded = EpisodeBuffer(rewarded=True, capacity=self.rewarded.capacity)
        if self._warm is not None:  # the warm start comes first, as in a fresh run
            rewarded.extend(self._warm)
        reward_free = EpisodeBuffer(rewarded=False, capacity=self.reward_free.capacity)
        free_transitions = 0
        selection, partial = None, {}
        nxt = done + 1
        if nxt <= len(self.schedule) and nxt in stored.selections:
            if stored.episodes.get(nxt) or self.rewarded_slice == "episode":
                selection = dict(stored.selections[nxt])
                partial = dict(stored.episodes.get(nxt, {}))
        try:
            for l_now in range(1, done + 1 + (selection is not None)):
                row = stored.selections.get(l_now)
                if row is None:
                    raise CorruptRunError(
                        f"the run {path} lacks the selection of iteration {l_now}"
                    )
                free_transitions += int(row["reward_free_transitions"])
                if self.keep_reward_free and l_now in stored.free:
                    reward_free.extend(stored.free[l_now])
            for l_now in range(1, done + 1):
                got = stored.episodes.get(l_now, {})
                if sorted(got) != list(range(self.schedule[l_now - 1])):
                    raise CorruptRunError(
                        f"the run {path} holds episodes {sorted(got)} of iteration {l_now}, "
                        f"which bought {self.schedule[l_now - 1]}"
                    )
                rewarded.extend(torch.stack([got[m] for m in sorted(got)], len(self.trial_dims)))
            for m, episode in partial.items():
                if not 0 <= m < self.schedule[nxt - 1]:
                    raise CorruptRunError(f"the run {path} holds episode {m} of iteration {nxt}")
                validate_episodes(episode.unsqueeze(-2), rewarded=True)
            history = [IterationRecord(**r) for _, r in sorted(stored.records.items())]
            theta = self.theta
            if history:
                theta = torch.tensor(history[-1].theta, dtype=torch.float64)
                if theta.shape != self.theta.shape:
                    raise CorruptRunError(f"the run {path} holds θ of shape {tuple(theta.shape)}")
        except (ValueError, TypeError, KeyError, RuntimeError) as error:
            if isinstance(error, CorruptRunError):
                raise
            raise CorruptRunError(f"the run {path} cannot be restored: {error}") from None
        if selection is not None:
            selection["chosen"] = torch.tensor(selection["chosen"], dtype=torch.long)
            if selection["sampling_rule"] is not None:  # (None: an extra candidate)
                selection["sampling_rule"] = torch.tensor(
                    selection["sampling_rule"], dtype=torch.float64
                )
        pending = None
        if selection is not None and len(partial) == self.schedule[nxt - 1]:
            last = [partial[m] for m in sorted(partial)]
            rewarded.extend(torch.stack(last, len(self.trial_dims)))
            pending, selection, partial = selection, None, {}
        # everything checked: now change the object
        self.rewarded, self.reward_free = rewarded, reward_free
        self._reward_free_transitions = free_transitions
        self.history, self.iteration, self.theta = history, done, theta
        self._pending, self._selection, self._partial = pending, selection, partial
        self.policy = self._policy(self.theta, self.iteration + 1)

    def load(self, path: str | os.PathLike) -> None:
        """Take over the state of the run stored at ``path`` (read only; for inspection or a
        copy: to continue a run, build it with ``checkpoint_path=path, resume=True``).

        Raises:
            CorruptRunError: the file fails a check, or was made with other settings; the
                object is then left as it was.
        """
        stored = RunStore.read(path)
        mine = RunStore.normalise(self._config())
        if stored.config != mine:
            differ = sorted(
                k for k in stored.config.keys() | mine.keys() if stored.config.get(k) != mine.get(k)
            )
            raise CorruptRunError(
                f"the run stored in {path} was made with other settings: {differ}"
            )
        self._restore(stored, Path(path))

    def _close_store(self) -> None:
        """Close the run's store (its lock is released); the object keeps its state."""
        if self.store is not None:
            self.store.close()
