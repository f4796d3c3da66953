"""Episodes: collection through TorchRL and storage in TensorDict replay buffers.

Every episode batch in this library is a TensorDict of batch shape ``[M, N]`` (M episodes of
N steps) holding:

=========================== =============== ==============================================
key                         shape           meaning
=========================== =============== ==============================================
``observation``             ``[M, N, d]``   state s
``action``                  ``[M, N]``      action index a (one-hot actions are converted)
``sample_probs``            ``[M, N, A]``   the sampling policy's pi~(·|s), recorded then,
``sample_log_prob``         ``[M, N]``      or only log pi~(a|s) of the taken action
``("next", "observation")`` ``[M, N, d]``   next state s'
``("next", "terminated")``  ``[M, N]``      the episode terminated at s' (no bootstrap)
``mask``                    ``[M, N]``      True up to and including an episode's last step
``("next", "reward")``      ``[M, N]``      rewarded episodes only
``iteration``, ``policy_id`` ``[M, N]``     tags: when and by which policy it was collected
=========================== =============== ==============================================

Reward-free episodes never carry a reward key: the collector drops whatever the environment
returned before the algorithm can see it.

Per-decision importance weights (eq. 21) need only the sampling policy's probability of the
taken action, so either probability key will do: the library's policies record the whole
distribution (``sample_probs``), TorchRL's ``ProbabilisticActor(..., return_log_prob=True)``
the log-probability of its action (``sample_log_prob`` or ``action_log_prob``, stored here as
``sample_log_prob``).

TorchRL data as TorchRL produces it is converted by :func:`as_episodes` (and accepted as is by
:meth:`EpisodeBuffer.extend`, the selector's earlier episodes and the iteration's
``initial_episodes``): ``env.rollout`` output ``[N]`` or ``[E, N]``; a ``Collector``'s flat
batches with ``("collector", "traj_ids")`` (split into trajectories); its ``split_trajs=True``
or ``trajs_per_batch`` padded batches with ``("collector", "mask")``; trailing ``[..., 1]`` dims
on done/terminated/truncated/reward; one-hot or index actions. Episodes of different lengths
are padded (with copies of their last step) and masked: N is the longest. A trajectory cut at a
collector batch's end is joined with its continuation by :meth:`EpisodeBuffer.extend`, so its
importance weights restart only where the episode really started.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torch_api._logging import quiet_storage_notices
from torch_api.actions import ActionEncoding, check_actions
from torch_api.policies import ActionProbsPolicy
from torch_api.streams import seed_env

__all__ = [
    "EnvPerBatch",
    "EpisodeBuffer",
    "REWARD_KEY",
    "SpecCheckedPolicy",
    "as_episodes",
    "cat_episodes",
    "collect_episodes",
    "collect_with_collector",
    "joinable",
    "pad_steps",
    "seed_env",
    "taken_sample_probs",
    "to_log_prob_form",
    "validate_episodes",
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

    def close(self) -> None:
        """Close the envs the factory built (a ``ParallelEnv``'s worker processes end); an env
        given as such is the caller's to close. Later calls build afresh."""
        built, self._built = self._built, {}
        for env in built.values():
            if not getattr(env, "is_closed", False):
                env.close()


def _as_index(action: torch.Tensor, batch_dims: int) -> torch.Tensor:
    """Action indices ``[E, N]`` from indices ``[E, N]``, ``[E, N, 1]`` or one-hot ``[E, N, A]``."""
    if action.ndim == batch_dims:
        return action.long()
    if action.ndim == batch_dims + 1 and action.shape[-1] == 1:
        return action.squeeze(-1).long()
    return action.long().argmax(-1)


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
            a trailing dim of 1 is an index, a longer one a one-hot vector).
        num_steps: pad the episodes to this N (e.g. a replay buffer's fixed episode length).
        taken_log_prob: keep only ``sample_log_prob``, the log-probability of the taken action
            (:func:`to_log_prob_form`): the form every sampling policy can give, so episodes of
            the library's policies and of TorchRL actors share one set of keys (one storage).

    Example:
        >>> from torchrl.envs import GymEnv
        >>> env = GymEnv("CartPole-v1")
        >>> from torch_api.policies import LinearQPolicy
        >>> from torch_api.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)
        >>> policy = LinearQPolicy(basis=basis, theta=torch.ones(4), epsilon=0.5,
        ...                        action_spec=env.action_spec)
        >>> episodes = as_episodes(env.rollout(5, policy), rewarded=True)
        >>> episodes.shape, episodes["action"].dtype
        (torch.Size([1, 5]), torch.int64)
    """
    encoding = None
    if action_spec is not None:
        encoding = ActionEncoding.from_spec(action_spec, tuple(action_spec.shape[:-1]))
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
    trial_dims = tuple(getattr(policy, "param_dims", ()))
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
) -> TensorDict:
    """:func:`collect_episodes` through a TorchRL ``Collector`` of the user's own.

    ``make_collector(policy, num_episodes)`` returns a collector (anything iterable over
    TorchRL batches: ``torchrl.collectors.Collector``, ideally with
    ``trajs_per_batch=num_episodes, traj_format="padded"``) running ``policy`` on an env whose
    episodes last at most ``num_steps`` steps (e.g. a ``StepCounter(max_steps=num_steps)``).
    Its batches are read as :meth:`EpisodeBuffer.extend` reads them (flat or padded;
    trajectories cut at a batch's end joined with their continuation) until ``num_episodes``
    whole episodes are in; the first ``num_episodes`` are kept, padded to ``num_steps``.
    The collector is shut down afterwards. The collector's env and its exploration type are the
    user's (a ``Collector`` samples, ``ExplorationType.RANDOM``, by default); every batch's
    actions are checked against the collector's ``env.action_spec`` where it has one.

    Returns:
        TensorDict ``[M, N]`` in the format of this module's docstring.

    Raises:
        ValueError: an episode longer than ``num_steps``, or actions outside the spec.
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
    buffer = EpisodeBuffer(rewarded=rewarded, capacity=16 * num_episodes + 64)
    try:
        for batch in collector:
            if row_spec is not None:  # the batch's first step is always a real one
                first = batch["action"].reshape(-1, *row_spec.shape)[0]
                check_actions(row_spec, first, who=f"the collector's policy {_name(policy)}")
            buffer.extend(batch)
            if len(buffer) - len(buffer._open) >= num_episodes:
                break
    finally:
        shutdown = getattr(collector, "shutdown", None)
        if shutdown is not None:
            shutdown()
    if len(buffer) - len(buffer._open) < num_episodes:
        raise ValueError(
            f"the collector ended after {len(buffer) - len(buffer._open)} whole episodes, "
            f"{num_episodes} were asked for"
        )
    closed = [i for i in range(len(buffer)) if i not in set(buffer._open.values())]
    episodes = buffer.episodes()[torch.tensor(closed[:num_episodes])]
    if episodes.shape[-1] > num_steps:
        longest = int(episodes["mask"].sum(-1).max())
        if longest > num_steps:
            raise ValueError(
                f"the collector gave an episode of {longest} steps, more than num_steps = "
                f"{num_steps} (end its env's episodes there, e.g. StepCounter(max_steps=...))"
            )
        episodes = episodes[..., :num_steps]
    episodes = pad_steps(episodes, num_steps)
    episodes["iteration"] = torch.full(episodes.shape, iteration, dtype=torch.long)
    episodes["policy_id"] = torch.full(episodes.shape, int(policy_id), dtype=torch.long)
    validate_episodes(episodes, rewarded=rewarded)
    return episodes


class SpecCheckedPolicy:
    """A policy in the env's action encoding whose every action is checked against the spec.

    A policy of this library is given the env's action spec
    (:meth:`~torch_api.policies.ActionProbsPolicy.with_action_spec`); any other policy is
    called as it is, and its first actions are checked with ``env.action_spec.is_in`` right
    after it wrote them, before the env applies them (:func:`~torch_api.actions.check_actions`).
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
    if SAMPLE_PROBS not in keys and SAMPLE_LOG_PROB not in keys:
        raise ValueError(f"episodes lack the sampling probabilities: give {_PROBABILITY_HELP}")
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
    action = episodes["action"]
    if action.shape != episodes.shape:
        raise ValueError(
            f"action must hold indices of shape {tuple(episodes.shape)}, got "
            f"{tuple(action.shape)} (convert TorchRL data with torch_api.data.as_episodes)"
        )
    if SAMPLE_PROBS in keys:
        probs = episodes[SAMPLE_PROBS][mask]
        if probs.numel():
            off = (probs.sum(-1) - 1).abs().max().item()
            if not off <= 1e-6 or (probs < 0).any() or not torch.isfinite(probs).all():
                raise ValueError(
                    f"sample_probs rows must be probabilities summing to 1 (one is off by "
                    f"{off:.3g})"
                )
        num_actions = episodes[SAMPLE_PROBS].shape[-1]
        if action.numel() and (action.min() < 0 or action.max() >= num_actions):
            raise ValueError(f"action indices must lie in [0, {num_actions})")
    else:
        log_prob = episodes[SAMPLE_LOG_PROB][mask]
        if torch.isnan(log_prob).any() or (log_prob > 1e-6).any():
            raise ValueError("sample_log_prob must hold log-probabilities (<= 0, not NaN)")
        if action.numel() and action.min() < 0:
            raise ValueError(f"action indices must be >= 0, got {int(action.min())}")
    taken = taken_sample_probs(episodes)
    if (taken[mask] <= 0).any():
        raise ValueError(
            "a taken action has recorded sampling probability 0: the episode could not have "
            "been collected by the policy it is tagged with"
        )


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
    def num_transitions(self) -> int:
        """Real (unmasked) transitions held."""
        return int(self.episodes()["mask"].sum()) if len(self) else 0

    def extend(self, episodes: TensorDictBase) -> None:
        """Append episodes ``[*T, M, N]`` (validated first; the same T as those held).

        TorchRL data as TorchRL produces it is converted first (:func:`as_episodes`; a
        reward-free buffer drops its reward there). Episodes of another length are padded: N
        becomes the longest held. A trajectory whose end was cut off by the end of a collector
        batch is held open, and the piece of the same trajectory id in a later batch is joined
        to it (one episode, its importance weights running on).
        """
        episodes, traj_ids, going_on = _from_torchrl(episodes, rewarded=self.rewarded)
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
