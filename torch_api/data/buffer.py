"""Checking episode batches and holding them in TensorDict replay buffers.

:func:`validate_episodes` is where data enters the algorithm (missing keys, a reward in
reward-free data, NaN, impossible probabilities); :class:`EpisodeBuffer` keeps rewarded and
reward-free episodes apart, trials aligned.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torch_api._logging import quiet_storage_notices
from torch_api.data.episodes import (
    _PROBABILITY_HELP,
    _REQUIRED,
    REWARD_KEY,
    SAMPLE_LOG_PROB,
    SAMPLE_PROBS,
    _from_torchrl,
    _refuse_meta,
    joinable,
    pad_steps,
    taken_sample_probs,
    to_log_prob_form,
)

__all__ = ["EpisodeBuffer", "cat_episodes", "validate_episodes"]


def validate_episodes(episodes: TensorDictBase, *, rewarded: bool) -> None:
    """Check an episode batch ``[..., M, N]`` before the algorithm uses it.

    Raises:
        ValueError: a missing key, a reward in reward-free data (or none in rewarded data),
            a tensor on the meta device, a mask that is not bool, NaN/inf observations or
            rewards, probability rows that do not sum to 1, or a taken action whose recorded
            sampling probability is 0.
    """
    if episodes.batch_dims < 2:
        raise ValueError(f"episodes must have batch shape [..., M, N], got {tuple(episodes.shape)}")
    _refuse_meta(episodes)
    keys = episodes.keys(include_nested=True)
    for key in _REQUIRED:
        if key not in keys:
            raise ValueError(f"episodes lack the key {key!r}")
    if SAMPLE_PROBS not in keys and SAMPLE_LOG_PROB not in keys:
        raise ValueError(f"episodes lack the sampling probabilities: give {_PROBABILITY_HELP}")
    has_reward = REWARD_KEY in keys
    if rewarded and not has_reward:
        raise ValueError("rewarded episodes lack ('next', 'reward')")
    if not rewarded and has_reward:
        raise ValueError("reward-free episodes must not carry ('next', 'reward')")
    mask = episodes["mask"]
    if mask.dtype != torch.bool:
        raise ValueError(
            f"mask must be a bool tensor (True on the real steps, False on padding), got "
            f"{mask.dtype}"
        )
    for key in ("observation", ("next", "observation")):
        values = episodes[key]
        if not bool(torch.isfinite(values).all()) and _masked_any(~torch.isfinite(values), mask):
            raise ValueError(f"episodes[{key!r}] contains NaN or inf")
    if has_reward:
        reward = episodes[REWARD_KEY]
        if _masked_any(~torch.isfinite(reward), mask):
            bad = reward[mask][~torch.isfinite(reward[mask])][0].item()
            raise ValueError(f"rewards must be finite, got {bad}")
    action = episodes["action"]
    if action.shape != episodes.shape:
        raise ValueError(
            f"action must hold indices of shape {tuple(episodes.shape)}, got "
            f"{tuple(action.shape)} (convert TorchRL data with torch_api.data.as_episodes)"
        )
    if SAMPLE_PROBS in keys:
        probs = episodes[SAMPLE_PROBS]
        if probs.numel():
            off = torch.where(mask, (_last_dim_sum(probs) - 1).abs(), 0.0).max().item()
            bad = (probs < 0) | ~torch.isfinite(probs)
            if not off <= 1e-6 or _masked_any(bad, mask):
                raise ValueError(
                    f"sample_probs rows must be probabilities summing to 1 (one is off by "
                    f"{off:.3g})"
                )
        num_actions = episodes[SAMPLE_PROBS].shape[-1]
        if action.numel() and (action.min() < 0 or action.max() >= num_actions):
            raise ValueError(f"action indices must lie in [0, {num_actions})")
    else:
        log_prob = episodes[SAMPLE_LOG_PROB]
        if _masked_any(torch.isnan(log_prob) | (log_prob > 1e-6), mask):
            raise ValueError("sample_log_prob must hold log-probabilities (<= 0, not NaN)")
        if action.numel() and action.min() < 0:
            raise ValueError(f"action indices must be >= 0, got {int(action.min())}")
    taken = taken_sample_probs(episodes)
    if _masked_any(taken <= 0, mask):
        raise ValueError(
            "a taken action has recorded sampling probability 0: the episode could not have "
            "been collected by the policy it is tagged with"
        )


def _last_dim_sum(values: torch.Tensor) -> torch.Tensor:
    """``values.sum(-1)``, as a few strided additions where the last dim is short (a reduction
    over 2 actions per row is many times slower in torch than one addition)."""
    if values.shape[-1] > 8:
        return values.sum(-1)
    total = values[..., 0].clone()
    for a in range(1, values.shape[-1]):
        total += values[..., a]
    return total


def _masked_any(flags: torch.Tensor, mask: torch.Tensor) -> bool:
    """Whether any flag ``[..., M, N, *rest]`` is set at a step the mask ``[..., M, N]`` keeps
    (a reduction, not a boolean-index copy of the data)."""
    if not flags.numel():
        return False
    flags = flags.reshape(*mask.shape, -1).any(-1) if flags.ndim > mask.ndim else flags
    return bool((flags & mask).any())


def cat_episodes(parts: list[TensorDictBase]) -> TensorDictBase:
    """Concatenate episode batches ``[M_i, N_i]`` along the episode axis (same keys).

    Shorter episodes are padded to the longest N (masked); where some batches carry
    ``sample_probs`` and others ``sample_log_prob``, all are put in the log form.
    """
    parts = [p for p in parts if p is not None and p.shape[0] > 0]
    if not parts:
        raise ValueError("no episodes to concatenate")
    parts = joinable(parts)
    return torch.cat(parts, 0) if len(parts) > 1 else parts[0]


class EpisodeBuffer:
    """Episodes in a ``TensorDictReplayBuffer`` over a ``LazyTensorStorage``, one item an episode.

    Two buffers are kept apart (docs/torchrl_stack.md: one storage silently accepts TensorDicts
    missing a key): ``rewarded=True`` holds bought episodes with their rewards,
    ``rewarded=False`` reward-free ones and refuses any reward.

    Episodes of T trials run side by side are held as ``[T, M, N]``: one storage item is the
    ``[T, N]`` slice of one episode index, so the trials stay aligned.

    Args:
        rewarded: whether the stored episodes carry ``("next", "reward")``.
        capacity: most episodes held (per trial); extending past it is an error (episodes are
            never overwritten: a bought reward must not be lost).
        device: storage device.

    Example:
        >>> from tensordict import TensorDict
        >>> buf = EpisodeBuffer(rewarded=False, capacity=100)
        >>> len(buf)
        0
    """

    def __init__(self, *, rewarded: bool, capacity: int = 100_000, device=None) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.rewarded = rewarded
        self.capacity = int(capacity)
        self.device = device or "cpu"
        self._buffer = self._new_buffer()
        self._steps: int | None = None
        self._trial_dims: tuple[int, ...] | None = None
        self._open: dict[int, int] = {}  # trajectory id -> index of its held, open episode

    def _new_buffer(self) -> TensorDictReplayBuffer:
        return TensorDictReplayBuffer(
            storage=LazyTensorStorage(self.capacity, ndim=1, device=self.device), batch_size=1
        )

    def __len__(self) -> int:
        return len(self._buffer)

    @property
    def steps(self) -> int | None:
        """N, the (padded) length of the held episodes; None while the buffer is empty."""
        return self._steps if len(self) else None

    def longest_episode(self) -> int:
        """Real (unmasked) steps of the longest held episode; 0 while the buffer is empty."""
        return int(self.episodes()["mask"].sum(-1).max()) if len(self) else 0

    @property
    def num_transitions(self) -> int:
        """Real (unmasked) transitions held."""
        return int(self.episodes()["mask"].sum()) if len(self) else 0

    def extend(self, episodes: TensorDictBase, *, validate: bool = True) -> None:
        """Append episodes ``[*T, M, N]`` (validated first; the same T as those held).

        TorchRL data as TorchRL produces it is converted first (:func:`as_episodes`; a
        reward-free buffer drops its reward there). Episodes of another length are padded: N
        becomes the longest held. A trajectory whose end was cut off by the end of a collector
        batch is held open, and the piece of the same trajectory id in a later batch is joined
        to it (one episode, its importance weights running on).

        ``validate=False`` skips :func:`validate_episodes`: the caller checks the episodes
        itself before using them (e.g. episode by episode, to keep the valid ones).
        """
        episodes, traj_ids, going_on = _from_torchrl(episodes, rewarded=self.rewarded)
        if validate:
            validate_episodes(episodes, rewarded=self.rewarded)
        trial_dims = tuple(episodes.shape[:-2])
        if self._trial_dims is not None and trial_dims != self._trial_dims:
            raise ValueError(
                f"this buffer holds episodes of trials {self._trial_dims}, got {trial_dims}"
            )
        if traj_ids is not None and not trial_dims:
            episodes, traj_ids, going_on = self._join_open(episodes, traj_ids, going_on)
            if not episodes.shape[0]:
                return
        num_new, steps = episodes.shape[-2:]
        if len(self) + num_new > self.capacity:
            raise ValueError(
                f"buffer capacity {self.capacity} episodes would be exceeded "
                f"({len(self)} held + {num_new} new)"
            )
        if len(self):
            held = self.episodes()
            held_keys = set(held.keys(include_nested=True, leaves_only=True))
            new_keys = set(episodes.keys(include_nested=True, leaves_only=True))
            if held_keys != new_keys:
                held, episodes = joinable([held, episodes])
                held_keys = set(held.keys(include_nested=True, leaves_only=True))
                new_keys = set(episodes.keys(include_nested=True, leaves_only=True))
                if held_keys != new_keys:
                    raise ValueError(
                        "episode keys differ from those held: "
                        f"{sorted(map(str, held_keys ^ new_keys))}"
                    )
                self._replace(held)
            if steps > self._steps:
                self._replace(pad_steps(self.episodes(), steps))
            episodes = pad_steps(episodes, self._steps)
        first = len(self)
        items = episodes.permute(-2, *range(len(trial_dims)), -1) if trial_dims else episodes
        # (the buffer writes an "index" key into its input; no TorchRL INFO line on first write)
        with quiet_storage_notices():
            self._buffer.extend(items.contiguous())
        self._steps, self._trial_dims = episodes.shape[-1], trial_dims
        if traj_ids is not None and not trial_dims:
            pairs = zip(traj_ids.tolist(), going_on.tolist(), strict=True)
            for row, (traj, more) in enumerate(pairs):
                if more:
                    self._open[traj] = first + row

    def _replace(self, episodes: TensorDictBase) -> None:
        """Hold exactly ``episodes`` (same count), e.g. re-padded or in the log form."""
        trial_dims = tuple(episodes.shape[:-2])
        items = episodes.permute(-2, *range(len(trial_dims)), -1) if trial_dims else episodes
        self._buffer = self._new_buffer()
        with quiet_storage_notices():
            self._buffer.extend(items.contiguous())
        self._steps = episodes.shape[-1]

    def _join_open(self, episodes, traj_ids, going_on):
        """Join the rows continuing a held open trajectory to it; return the other rows."""
        continuing = [row for row, t in enumerate(traj_ids.tolist()) if t in self._open]
        if not continuing:
            return episodes, traj_ids, going_on
        held = self.episodes()
        for row in continuing:
            traj = int(traj_ids[row])
            index = self._open.pop(traj)
            old, new = held[index], episodes[row]
            old, new = joinable([old.unsqueeze(0), new.unsqueeze(0)])
            old_real, new_real = old[0][old[0]["mask"]], new[0][new[0]["mask"]]
            joined = torch.cat([old_real, new_real], 0)
            steps = max(joined.shape[0], held.shape[-1])
            if SAMPLE_PROBS not in old.keys():
                held = to_log_prob_form(held)
            joined = pad_steps(joined.unsqueeze(0), steps)
            joined["iteration"] = old["iteration"][:, :1].expand(joined.shape).clone()
            joined["policy_id"] = old["policy_id"][:, :1].expand(joined.shape).clone()
            held = pad_steps(held, steps)
            held[index] = joined[0]
            if going_on[row]:
                self._open[traj] = index
        self._replace(held)
        keep = torch.tensor([row not in continuing for row in range(episodes.shape[0])])
        return episodes[keep], traj_ids[keep], going_on[keep]

    def episodes(self) -> TensorDictBase:
        """All episodes held, in insertion order, ``[*T, M_total, N]``."""
        if not len(self):
            raise ValueError("the buffer is empty")
        items = self._buffer.storage[: len(self)].exclude("index")
        if self._trial_dims:
            items = items.permute(*range(1, len(self._trial_dims) + 1), 0, -1).contiguous()
        return items

    def state_dict(self) -> dict:
        """Plain tensors and numbers only (loadable with ``torch.load(weights_only=True)``)."""
        if not len(self):
            return {"episodes": None, "batch_size": None}
        episodes = self.episodes()
        return {"episodes": episodes.to_dict(), "batch_size": list(episodes.shape)}

    def load_state_dict(self, state: dict) -> None:
        """Replace the contents with those of :meth:`state_dict` (validated like ``extend``)."""
        self._buffer.empty()
        self._steps = self._trial_dims = None
        self._open = {}
        if state.get("episodes") is not None:
            self.extend(TensorDict.from_dict(state["episodes"], batch_size=state["batch_size"]))

    def whole(self) -> list[int]:
        """Indices of the held episodes that are whole: none awaits its continuation from a
        next collector batch (:meth:`extend` joins a cut trajectory with it)."""
        going_on = set(self._open.values())
        return [i for i in range(len(self)) if i not in going_on]

    @classmethod
    def holding(cls, warm: TensorDictBase | None, *, capacity: int) -> EpisodeBuffer:
        """A rewarded buffer for ``capacity`` more episodes, holding ``warm`` ``[*T, M_0, N]``
        (a warm start, or None) first."""
        buffer = cls(rewarded=True, capacity=capacity + (0 if warm is None else warm.shape[-2]))
        if warm is not None:
            buffer.extend(warm)
        return buffer


def _warm_start(data, trial_dims: tuple[int, ...]) -> TensorDictBase | None:
    """``initial_episodes`` in the library's format ``[*T, M, N]`` (None: no warm start)."""
    if data is None:
        return None
    batches = [data] if isinstance(data, TensorDictBase) else list(data)
    if not batches:
        return None
    joined = EpisodeBuffer(rewarded=True, capacity=sum(b.numel() for b in batches))
    for batch in batches:  # consecutive collector batches: cut trajectories are joined
        joined.extend(batch)
    episodes = joined.episodes()
    return episodes.expand(*trial_dims, *episodes.shape).clone() if trial_dims else episodes
