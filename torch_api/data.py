"""Episodes: collection through TorchRL and storage in TensorDict replay buffers.

Every episode batch in this library is a TensorDict of batch shape ``[M, N]`` (M episodes of
N steps) holding:

=========================== =============== ==============================================
key                         shape           meaning
=========================== =============== ==============================================
``observation``             ``[M, N, d]``   state s
``action``                  ``[M, N]``      action index a (one-hot actions are converted)
``sample_probs``            ``[M, N, A]``   the sampling policy's pi~(·|s), recorded then
``("next", "observation")`` ``[M, N, d]``   next state s'
``("next", "terminated")``  ``[M, N]``      the episode terminated at s' (no bootstrap)
``mask``                    ``[M, N]``      True up to and including an episode's last step
``("next", "reward")``      ``[M, N]``      rewarded episodes only
``iteration``, ``policy_id`` ``[M, N]``     tags: when and by which policy it was collected
=========================== =============== ==============================================

Reward-free episodes never carry a reward key: the collector drops whatever the environment
returned before the algorithm can see it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase

__all__ = [
    "EnvPerBatch",
    "EpisodeBuffer",
    "REWARD_KEY",
    "cat_episodes",
    "collect_episodes",
    "seed_env",
    "validate_episodes",
]

REWARD_KEY = ("next", "reward")
_REQUIRED = ("observation", "action", "sample_probs", ("next", "observation"), "mask")


class EnvPerBatch:
    """An environment, or a factory ``batch_size -> env`` that builds one env per batch size.

    The algorithm needs batches of different sizes (``T·M_l`` rewarded rows, ``T·Z·K·M_l``
    reward-free rows); a factory lets each size be built once and reused.

    Example:
        >>> from envs.chain_walk import ChainWalkEnv
        >>> envs = EnvPerBatch(lambda rows: ChainWalkEnv(batch_size=rows))
        >>> envs(6) is envs(6), tuple(envs(4).batch_size)
        (True, (4,))
    """

    def __init__(self, env: EnvBase | Callable[[int], EnvBase]) -> None:
        if not (isinstance(env, EnvBase) or callable(env)):
            raise ValueError(f"env must be a TorchRL EnvBase or a callable, got {type(env)}")
        self.env = env
        self._built: dict[int, EnvBase] = {}

    @property
    def is_factory(self) -> bool:
        return not isinstance(self.env, EnvBase)

    def __call__(self, batch: int) -> EnvBase:
        """The env for ``batch`` rows (the fixed env whatever ``batch``, if not a factory)."""
        if not self.is_factory:
            return self.env
        if batch not in self._built:
            self._built[batch] = self.env(batch)
        return self._built[batch]


def seed_env(env: EnvBase, seed: int, block_seeds=None) -> None:
    """Seed ``env``: one stream per block of rows (``set_block_seeds``) where the env has it
    and ``block_seeds`` are given, else ``env.set_seed(seed)``."""
    if block_seeds is not None and hasattr(env, "set_block_seeds"):
        env.set_block_seeds(list(block_seeds))
    else:
        env.set_seed(seed)


def _as_index(action: torch.Tensor, batch_dims: int) -> torch.Tensor:
    """Action indices ``[E, N]`` from indices ``[E, N]``, ``[E, N, 1]`` or one-hot ``[E, N, A]``."""
    if action.ndim == batch_dims:
        return action.long()
    if action.ndim == batch_dims + 1 and action.shape[-1] == 1:
        return action.squeeze(-1).long()
    return action.long().argmax(-1)


def _episodes_from_rollout(rollout: TensorDictBase, *, rewarded: bool) -> TensorDict:
    """Convert a TorchRL rollout ``[E, N]`` into the library's episode format ``[E, N]``."""
    if "sample_probs" not in rollout.keys():
        raise ValueError(
            "the policy did not write 'sample_probs' (its action distribution); use a policy "
            "from torch_api.policies or add the key so importance weights can be computed"
        )
    obs = rollout["observation"]
    next_obs = rollout["next", "observation"]
    if obs.ndim == rollout.ndim:  # scalar observations: give them a feature dim
        obs, next_obs = obs.unsqueeze(-1), next_obs.unsqueeze(-1)
    shape = rollout.batch_size

    def flag(key):
        value = rollout.get(("next", key), None)
        if value is None:
            return torch.zeros(shape, dtype=torch.bool, device=obs.device)
        return value.reshape(shape).bool()

    done = flag("done") | flag("terminated") | flag("truncated")
    # A step is real if no earlier step of the row ended its episode (rollouts auto-reset).
    ended_before = (torch.cumsum(done.long(), -1) - done.long()) > 0
    out = TensorDict(
        {
            "observation": obs,
            "action": _as_index(rollout["action"], rollout.batch_dims),
            "sample_probs": rollout["sample_probs"].to(torch.float64),
            ("next", "observation"): next_obs,
            ("next", "terminated"): flag("terminated"),
            "mask": ~ended_before,
        },
        batch_size=shape,
        device=obs.device,
    )
    if rewarded:
        out[REWARD_KEY] = rollout[REWARD_KEY].reshape(shape)
    return out


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

    Args:
        env: a TorchRL environment with a discrete action space (categorical or one-hot).
        policy: a TensorDict module writing ``action`` and ``sample_probs`` (e.g.
            :class:`~torch_api.policies.LinearQPolicy`).
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
    trial_dims = tuple(getattr(policy, "param_dims", ()))
    rows = math.prod(trial_dims) * num_episodes
    batched = len(env.batch_size) > 0
    if trial_dims and (not batched or env.batch_size[0] != rows):
        raise ValueError(
            f"a policy with per-trial parameters {trial_dims} needs an env of batch size "
            f"[T·M] = [{rows}], got {tuple(env.batch_size)}"
        )
    per_rollout = env.batch_size[0] if batched else 1
    chunks = []
    for _ in range(math.ceil(rows / per_rollout)):
        rollout = env.rollout(
            max_steps=num_steps, policy=policy, break_when_any_done=False, auto_reset=True
        )
        if not batched:
            rollout = rollout.unsqueeze(0)
        if rollout.shape[-1] != num_steps:
            raise RuntimeError(
                f"env.rollout returned {rollout.shape[-1]} steps instead of {num_steps}"
            )
        chunks.append(_episodes_from_rollout(rollout, rewarded=rewarded))
    episodes = torch.cat(chunks, 0)[:rows] if len(chunks) > 1 else chunks[0][:rows]
    episodes = episodes.reshape(*trial_dims, num_episodes, num_steps)
    episodes["iteration"] = torch.full(episodes.shape, iteration, dtype=torch.long)
    ids = torch.as_tensor(policy_id, dtype=torch.long)
    episodes["policy_id"] = ids.reshape(*ids.shape, 1, 1).expand(episodes.shape).clone()
    if validate:
        validate_episodes(episodes, rewarded=rewarded)
    return episodes


def validate_episodes(episodes: TensorDictBase, *, rewarded: bool) -> None:
    """Check an episode batch ``[..., M, N]`` before the algorithm uses it.

    Raises:
        ValueError: a missing key, a reward in reward-free data (or none in rewarded data),
            NaN/inf observations or rewards, probability rows that do not sum to 1, or a taken
            action whose recorded sampling probability is 0.
    """
    if episodes.batch_dims < 2:
        raise ValueError(f"episodes must have batch shape [..., M, N], got {tuple(episodes.shape)}")
    keys = episodes.keys(include_nested=True)
    for key in _REQUIRED:
        if key not in keys:
            raise ValueError(f"episodes lack the key {key!r}")
    has_reward = REWARD_KEY in keys
    if rewarded and not has_reward:
        raise ValueError("rewarded episodes lack ('next', 'reward')")
    if not rewarded and has_reward:
        raise ValueError("reward-free episodes must not carry ('next', 'reward')")
    mask = episodes["mask"]
    for key in ("observation", ("next", "observation")):
        values = episodes[key][mask]
        if not torch.isfinite(values).all():
            raise ValueError(f"episodes[{key!r}] contains NaN or inf")
    if has_reward:
        reward = episodes[REWARD_KEY][mask]
        if not torch.isfinite(reward).all():
            bad = reward[~torch.isfinite(reward)][0].item()
            raise ValueError(f"rewards must be finite, got {bad}")
    probs = episodes["sample_probs"][mask]
    if probs.numel():
        off = (probs.sum(-1) - 1).abs().max().item()
        if not off <= 1e-6 or (probs < 0).any() or not torch.isfinite(probs).all():
            raise ValueError(
                f"sample_probs rows must be probabilities summing to 1 (one is off by {off:.3g})"
            )
    num_actions = episodes["sample_probs"].shape[-1]
    action = episodes["action"]
    if action.numel() and (action.min() < 0 or action.max() >= num_actions):
        raise ValueError(f"action indices must lie in [0, {num_actions})")
    taken = torch.gather(episodes["sample_probs"], -1, action.unsqueeze(-1)).squeeze(-1)
    if (taken[mask] <= 0).any():
        raise ValueError(
            "a taken action has recorded sampling probability 0: the episode could not have "
            "been collected by the policy it is tagged with"
        )


def cat_episodes(parts: list[TensorDictBase]) -> TensorDictBase:
    """Concatenate episode batches ``[M_i, N]`` along the episode axis (same N and keys)."""
    parts = [p for p in parts if p is not None and p.shape[0] > 0]
    if not parts:
        raise ValueError("no episodes to concatenate")
    steps = {p.shape[-1] for p in parts}
    if len(steps) > 1:
        raise ValueError(f"episodes of different lengths N cannot be joined: {sorted(steps)}")
    return torch.cat(parts, 0) if len(parts) > 1 else parts[0]


class EpisodeBuffer:
    """Episodes in a ``TensorDictReplayBuffer`` over a ``LazyTensorStorage``, one item an episode.

    Two buffers are kept apart (TORCHRL-NOTES.md: one storage silently accepts TensorDicts
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
        self._buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(self.capacity, ndim=1, device=device or "cpu"),
            batch_size=1,
        )
        self._steps: int | None = None
        self._trial_dims: tuple[int, ...] | None = None

    def __len__(self) -> int:
        return len(self._buffer)

    @property
    def num_transitions(self) -> int:
        """Real (unmasked) transitions held."""
        return int(self.episodes()["mask"].sum()) if len(self) else 0

    def extend(self, episodes: TensorDictBase) -> None:
        """Append episodes ``[*T, M, N]`` (validated first; same T and N as those held)."""
        validate_episodes(episodes, rewarded=self.rewarded)
        trial_dims, (num_new, steps) = tuple(episodes.shape[:-2]), episodes.shape[-2:]
        if self._steps is not None and steps != self._steps:
            raise ValueError(
                f"this buffer holds episodes of N = {self._steps} steps, got N = {steps}"
            )
        if self._trial_dims is not None and trial_dims != self._trial_dims:
            raise ValueError(
                f"this buffer holds episodes of trials {self._trial_dims}, got {trial_dims}"
            )
        if len(self) + num_new > self.capacity:
            raise ValueError(
                f"buffer capacity {self.capacity} episodes would be exceeded "
                f"({len(self)} held + {num_new} new)"
            )
        if len(self):
            held = set(self.episodes().keys(include_nested=True, leaves_only=True))
            new = set(episodes.keys(include_nested=True, leaves_only=True))
            if held != new:
                raise ValueError(
                    f"episode keys differ from those held: {sorted(map(str, held ^ new))}"
                )
        items = episodes.permute(-2, *range(len(trial_dims)), -1) if trial_dims else episodes
        self._buffer.extend(items.contiguous())  # (the buffer writes an "index" key into its input)
        self._steps, self._trial_dims = steps, trial_dims

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
        if state.get("episodes") is not None:
            self.extend(TensorDict.from_dict(state["episodes"], batch_size=state["batch_size"]))
