"""The library's episode format and its conversion from TorchRL data as TorchRL produces it.

The keys and shapes of an episode batch are listed in :mod:`torch_api.data`. Here:
:func:`as_episodes` (``env.rollout`` output, a ``Collector``'s flat or padded batches, one-hot
or index actions, trailing ``[..., 1]`` dims), padding to a common N (:func:`pad_steps`), the
sampling probabilities of the taken actions (:func:`taken_sample_probs`) and their log form.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from torch_api._checks import _check_not_meta
from torch_api.data.actions import ActionEncoding, check_encoded

__all__ = [
    "EXTERNAL_POLICY_ID",
    "LOG_PROB_KEYS",
    "REWARD_KEY",
    "SAMPLE_LOG_PROB",
    "SAMPLE_PROBS",
    "as_episodes",
    "joinable",
    "pad_steps",
    "taken_sample_probs",
    "to_log_prob_form",
]

REWARD_KEY = ("next", "reward")
SAMPLE_PROBS = "sample_probs"
SAMPLE_LOG_PROB = "sample_log_prob"
LOG_PROB_KEYS = ("sample_log_prob", "action_log_prob")  # TorchRL's names of log pi~(a|s)
EXTERNAL_POLICY_ID = -1  # policy_id of episodes the library did not collect itself
_REQUIRED = ("observation", "action", ("next", "observation"), "mask")
_PROBABILITY_HELP = (
    "'sample_probs' (pi~(·|s), [..., A], written by the library's policies) or "
    "'sample_log_prob' / 'action_log_prob' (log pi~(a|s) of the taken action, written by "
    "TorchRL's ProbabilisticActor(..., return_log_prob=True))"
)


def _as_index(action: torch.Tensor, batch_dims: int) -> torch.Tensor:
    """Action indices ``[E, N]`` from indices ``[E, N]``, ``[E, N, 1]`` or one-hot ``[E, N, A]``."""
    if action.ndim == batch_dims:
        return action.long()
    if action.ndim == batch_dims + 1 and action.shape[-1] == 1:
        return action.squeeze(-1).long()
    return action.long().argmax(-1)


def _refuse_meta(data: TensorDictBase, name: str = "episodes") -> None:
    """Refuse data with a tensor on the ``meta`` device (a shape without values), naming its
    key: one look at each leaf's device, no value read."""
    if data.device is not None and data.device.type != "meta":
        return  # (one device for all, and not meta)
    for key, value in data.items(include_nested=True, leaves_only=True):
        _check_not_meta(f"{name}[{key!r}]", value)


def _probability_entries(data: TensorDictBase, shape: torch.Size) -> dict:
    """The sampling policy's probabilities in the library's keys (see the module docstring)."""
    keys = data.keys(include_nested=True)
    if SAMPLE_PROBS in keys:
        return {SAMPLE_PROBS: data[SAMPLE_PROBS].to(torch.float64)}
    for key in LOG_PROB_KEYS:
        if key in keys:
            value = data[key]
            if value.shape != shape:
                value = value.reshape(shape)  # (a trailing [..., 1])
            return {SAMPLE_LOG_PROB: value.to(torch.float64)}
    raise ValueError(
        "the episodes lack the sampling policy's probabilities, needed for the importance "
        f"weights: give {_PROBABILITY_HELP}"
    )


def _episodes_from_rollout(
    rollout: TensorDictBase,
    *,
    rewarded: bool,
    encoding: ActionEncoding | None = None,
    mask: torch.Tensor | None = None,
) -> TensorDict:
    """Convert a TorchRL rollout ``[E, N]`` into the library's episode format ``[E, N]``.

    ``mask``: steps that exist (a collector's padding excluded); steps after an episode ended
    within its row are masked too.
    """
    obs = rollout["observation"]
    next_obs = rollout["next", "observation"]
    if obs.ndim == rollout.ndim:  # scalar observations: give them a feature dim
        obs, next_obs = obs.unsqueeze(-1), next_obs.unsqueeze(-1)
    shape = rollout.batch_size
    probabilities = _probability_entries(rollout, shape)

    def flag(key):
        value = rollout.get(("next", key), None)
        if value is None:
            return torch.zeros(shape, dtype=torch.bool, device=obs.device)
        return value.reshape(shape).bool()

    done = flag("done") | flag("terminated") | flag("truncated")
    # A step is real if no earlier step of the row ended its episode (rollouts auto-reset).
    ended_before = (torch.cumsum(done.long(), -1) - done.long()) > 0
    real = ~ended_before if mask is None else ~ended_before & mask.reshape(shape).bool()
    action = rollout["action"]
    if encoding is not None:
        check_encoded(encoding, action, real, who="the episodes")
        index = encoding.decode(action, rollout.batch_dims)
    else:
        index = _as_index(action, rollout.batch_dims)
    out = TensorDict(
        {
            "observation": obs,
            "action": index,
            **probabilities,
            ("next", "observation"): next_obs,
            ("next", "terminated"): flag("terminated"),
            "mask": real,
        },
        batch_size=shape,
        device=obs.device,
    )
    if rewarded:
        out[REWARD_KEY] = rollout[REWARD_KEY].reshape(shape)
    return out


def _is_library_format(data: TensorDictBase) -> bool:
    return "mask" in data.keys() and data.batch_dims >= 2


def _split_flat(data: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor, torch.Tensor]:
    """A collector's flat batch ``[F]`` (or ``[E, T]``) -> trajectories ``[U, L]``, their
    trajectory ids ``[U]`` and the mask of existing steps ``[U, L]`` (L: the longest)."""
    flat = data.reshape(-1)
    ids = flat["collector", "traj_ids"].reshape(-1)
    uniq, inverse = torch.unique(ids, return_inverse=True)
    counts = torch.bincount(inverse, minlength=uniq.numel())
    order = torch.argsort(inverse, stable=True)  # steps of each trajectory, in time order
    starts = torch.cumsum(counts, 0) - counts
    position = torch.empty_like(inverse)
    position[order] = torch.arange(inverse.numel(), device=ids.device) - starts[inverse[order]]
    grid = torch.full((uniq.numel(), int(counts.max())), -1, dtype=torch.long, device=ids.device)
    grid[inverse, position] = torch.arange(inverse.numel(), device=ids.device)
    exists = grid >= 0
    # Missing steps repeat the trajectory's last step (then masked): every value stays valid.
    last = (starts + counts - 1)[:, None].expand_as(grid)
    grid = torch.where(exists, grid, order[last])
    return flat[grid], uniq, exists


def _ended(data: TensorDictBase, exists: torch.Tensor) -> torch.Tensor:
    """Whether each row's last existing step ends its episode (done, terminated or truncated)."""
    shape = exists.shape
    done = torch.zeros(shape, dtype=torch.bool, device=exists.device)
    for key in ("done", "terminated", "truncated"):
        value = data.get(("next", key), None)
        if value is not None:
            done |= value.reshape(shape).bool()
    last = (exists.long().sum(-1) - 1).clamp_min(0)
    return done.gather(-1, last[:, None]).squeeze(-1)


def _from_torchrl(
    data: TensorDictBase, *, rewarded: bool, encoding: ActionEncoding | None = None
) -> tuple[TensorDictBase, torch.Tensor | None, torch.Tensor | None]:
    """:func:`as_episodes` plus each episode's trajectory id ``[M]`` and whether the
    trajectory goes on past the data ``[M]`` (both None where the data does not say)."""
    _refuse_meta(data, "the data")
    if _is_library_format(data):
        return data, None, None
    keys = data.keys(include_nested=True)
    for key in ("observation", "action", ("next", "observation")):
        if key not in keys:
            raise ValueError(f"the TorchRL data lack the key {key!r} (keys: {_key_list(data)})")
    traj_ids = exists = None
    if ("collector", "mask") in keys and data.batch_dims >= 2:  # split_trajs / trajs_per_batch
        rows = data.reshape(-1, data.shape[-1])
        exists = rows["collector", "mask"].bool()
        if ("collector", "traj_ids") in keys:
            ids = rows["collector", "traj_ids"]
            traj_ids = torch.where(exists, ids, ids.new_full((), -1)).max(-1).values
    elif ("collector", "traj_ids") in keys:  # a collector's flat batch
        rows, traj_ids, exists = _split_flat(data)
    elif data.batch_dims >= 1:  # env.rollout output [N] or [E, N]: one episode a row
        rows = data.reshape(-1, data.shape[-1])
    else:
        raise ValueError(f"the TorchRL data need a time dim, got batch size {tuple(data.shape)}")
    episodes = _episodes_from_rollout(
        rows,
        rewarded=rewarded and REWARD_KEY in keys,
        encoding=encoding,
        mask=exists,
    )
    if rewarded and REWARD_KEY not in keys:
        raise ValueError("rewarded episodes lack ('next', 'reward')")
    episodes["iteration"] = torch.zeros(episodes.shape, dtype=torch.long)
    episodes["policy_id"] = torch.full(episodes.shape, EXTERNAL_POLICY_ID, dtype=torch.long)
    going_on = None
    if traj_ids is not None:
        going_on = ~_ended(rows, exists)
    return episodes, traj_ids, going_on


def _key_list(data: TensorDictBase) -> list[str]:
    return sorted(map(str, data.keys(include_nested=True, leaves_only=True)))


def as_episodes(
    data: TensorDictBase,
    *,
    rewarded: bool,
    action_spec=None,
    num_steps: int | None = None,
    taken_log_prob: bool = False,
) -> TensorDictBase:
    """TorchRL data as TorchRL produces it -> the library's episode format ``[M, N]``.

    Accepts ``env.rollout`` output (``[N]``, or ``[E, N]`` from a batched env, one episode a
    row; steps after a row's first done are masked), a ``Collector``'s flat batch with
    ``("collector", "traj_ids")`` (split into one row per trajectory), its ``split_trajs=True``
    or ``trajs_per_batch=..., traj_format="padded"`` batches with ``("collector", "mask")``, and
    episodes already in the library's format (returned as they are). Rows are padded to the
    longest and masked. With ``rewarded=False`` the reward is dropped; with ``rewarded=True`` it
    must be there. Converted episodes are tagged ``iteration = 0`` and
    ``policy_id = EXTERNAL_POLICY_ID``. A trajectory cut at the end of a collector batch is one
    row here; :meth:`EpisodeBuffer.extend` joins it with its continuation.

    Args:
        data: the TensorDict.
        rewarded: keep (and require) ``("next", "reward")``.
        action_spec: the env's action spec, to read one-hot actions by their encoding (default:
            a trailing dim of 1 is an index, a longer one a one-hot vector). The actions of
            every real step are checked against it (:func:`~torch_api.data.actions.check_encoded`):
            an index in a one-hot env's data (an action GymEnv applied as 0) is refused.
        num_steps: pad the episodes to this N (e.g. a replay buffer's fixed episode length).
        taken_log_prob: keep only ``sample_log_prob``, the log-probability of the taken action
            (:func:`to_log_prob_form`): the form every sampling policy can give, so episodes of
            the library's policies and of TorchRL actors share one set of keys (one storage).

    Example:
        >>> from torchrl.envs import GymEnv
        >>> env = GymEnv("CartPole-v1")
        >>> from torch_api.policies import LinearQPolicy
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)
        >>> policy = LinearQPolicy(basis=basis, theta=torch.ones(4), epsilon=0.5,
        ...                        action_spec=env.action_spec)
        >>> episodes = as_episodes(env.rollout(5, policy), rewarded=True)
        >>> episodes.shape, episodes["action"].dtype
        (torch.Size([1, 5]), torch.int64)
    """
    encoding = None
    if action_spec is not None:
        encoding = ActionEncoding.of_spec(action_spec)
    episodes, _, _ = _from_torchrl(data, rewarded=rewarded, encoding=encoding)
    if not rewarded:
        episodes = episodes.exclude(REWARD_KEY)
    if num_steps is not None:
        episodes = pad_steps(episodes, num_steps)
    return to_log_prob_form(episodes) if taken_log_prob else episodes


def pad_steps(episodes: TensorDictBase, num_steps: int) -> TensorDictBase:
    """Pad episodes ``[..., M, N]`` to ``num_steps ≥ N`` steps with masked copies of the last."""
    have = episodes.shape[-1]
    if num_steps < have:
        raise ValueError(f"cannot pad episodes of N = {have} steps to {num_steps}")
    if num_steps == have:
        return episodes
    pad = episodes[..., -1:].expand(*episodes.shape[:-1], num_steps - have).clone()
    pad["mask"] = torch.zeros(pad.shape, dtype=torch.bool, device=pad.device)
    return torch.cat([episodes, pad], -1)


def taken_sample_probs(episodes: TensorDictBase) -> torch.Tensor:
    """The sampling policy's probability of each taken action ``[..., M, N]`` (float64), from
    ``sample_probs`` or ``sample_log_prob`` (eq. 21 needs nothing else of pi~)."""
    keys = episodes.keys()
    if SAMPLE_PROBS in keys:
        probs = episodes[SAMPLE_PROBS]
        action = episodes["action"]
        return torch.gather(probs, -1, action.unsqueeze(-1)).squeeze(-1).to(torch.float64)
    if SAMPLE_LOG_PROB in keys:
        return episodes[SAMPLE_LOG_PROB].to(torch.float64).exp()
    raise ValueError(f"the episodes lack the sampling probabilities: give {_PROBABILITY_HELP}")


def to_log_prob_form(episodes: TensorDictBase) -> TensorDictBase:
    """Episodes with ``sample_log_prob`` (log pi~ of the taken action) in place of
    ``sample_probs``: the form episodes of both kinds can be joined in."""
    if SAMPLE_PROBS not in episodes.keys():
        return episodes
    taken = taken_sample_probs(episodes)
    out = episodes.exclude(SAMPLE_PROBS)
    out[SAMPLE_LOG_PROB] = taken.log()
    return out


def joinable(parts: list[TensorDictBase]) -> list[TensorDictBase]:
    """Episode batches made joinable along the episode axis: one probability form (the log
    form where they differ) and one length N (the longest; shorter ones padded, masked)."""
    forms = {SAMPLE_PROBS in p.keys() for p in parts}
    if len(forms) > 1:
        parts = [to_log_prob_form(p) for p in parts]
    steps = max(p.shape[-1] for p in parts)
    return [pad_steps(p, steps) for p in parts]
