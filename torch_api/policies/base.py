"""The base of the library's policies, the one a user extends: :class:`ActionProbsPolicy`.

A policy of this library is pure: it gives action probabilities of observations
(``action_probs``). Drawing an action from them is a function of its own,
:func:`sample_actions`, that takes its random streams as an argument: the library's own
counter-based streams (:class:`counter_rng.CounterStreams`, one per trial), or what a TorchRL
user passes (a ``torch.Generator``, or nothing: torch's global generator). Where the policy must act
as a TorchRL module (``policy(td)`` in ``env.rollout`` or a ``Collector``), it draws from the
streams it was made with (``with_streams`` gives a new policy with others; nothing sets them
afterwards), writes the action in the env's encoding and records the whole distribution
(``sample_probs``), so that importance weights can later be computed against any other
policy. A new policy family subclasses :class:`ActionProbsPolicy` and implements
``_action_probs(obs) -> [..., A]``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type

from counter_rng import CounterStreams
from torch_api._checks import _check_not_meta
from torch_api.data.actions import ActionEncoding

__all__ = ["ActionProbsPolicy", "Streams", "param_dims_of", "sample_actions"]

Streams = CounterStreams | torch.Generator | None
"""Random streams of sampling: counter-based streams (one per equal, consecutive block of rows,
e.g. one per trial; :class:`counter_rng.CounterStreams`), one ``torch.Generator``, or torch's
global generator (None)."""


def _check_streams(streams) -> Streams:
    if streams is None or isinstance(streams, torch.Generator | CounterStreams):
        return streams
    hint = ""
    if isinstance(streams, Sequence) and all(isinstance(g, torch.Generator) for g in streams):
        hint = (
            "; for one stream per block of rows (e.g. per trial) pass "
            "counter_rng.CounterStreams(seeds), one seed per block"
        )
    raise ValueError(
        f"streams must be None, a torch.Generator or a counter_rng.CounterStreams, got "
        f"{type(streams).__name__}{hint}"
    )


def sample_actions(probs: torch.Tensor, streams: Streams = None) -> torch.Tensor:
    """Draw one action index per row: ``probs [..., A] -> [...]`` (long), by the inverse CDF.

    Args:
        probs: action probabilities ``[..., A]``: finite, non-negative, each row summing to 1
            within rounding (else a ``ValueError`` with the sums found: an action drawn from a
            row that sums to 0.6 would take the rest of the mass silently).
        streams: counter-based streams (the leading dims flattened, trial-major, split into
            one equal, consecutive block per stream: block ``b`` is drawn from stream ``b``
            alone, so a batch of T trials draws exactly what T separate draws would, in one
            computation), one ``torch.Generator``, or None (torch's global generator).

    Example:
        >>> probs = torch.tensor([[0.5, 0.5]] * 4, dtype=torch.float64)
        >>> together = sample_actions(probs, CounterStreams([7, 8]))
        >>> alone = [sample_actions(probs[:2], CounterStreams(s)) for s in (7, 8)]
        >>> torch.equal(together, torch.cat(alone))
        True
    """
    streams = _check_streams(streams)
    _check_not_meta("probs", probs)
    cdf = probs.cumsum(-1)
    _check_probs(probs, cdf)
    shape = probs.shape[:-1]
    if isinstance(streams, CounterStreams):
        uniform = streams.uniform(shape if len(shape) else (1,), device=probs.device)
        uniform = uniform.reshape(shape)
    else:
        device = "cpu" if streams is None else streams.device
        uniform = torch.rand(shape, generator=streams, dtype=torch.float64, device=device)
    uniform = uniform.to(probs.device)
    return (cdf < uniform.unsqueeze(-1)).sum(-1).clamp(max=probs.shape[-1] - 1)


PROBS_RTOL = 1e-6  # a row of probabilities may sum to 1 within this (float64; more in float32)


def _check_probs(probs: torch.Tensor, cdf: torch.Tensor) -> None:
    """Refuse rows of ``probs [..., A]`` that are no distribution: an entry negative or not
    finite, or a row whose sum (``cdf[..., -1]``) is off 1 by more than the dtype's rounding
    (:data:`PROBS_RTOL` in float64, ``4·A·eps`` where that is larger). One reduction each and
    one synchronisation; the details are read only for the message."""
    if not probs.numel():
        return
    num_actions = probs.shape[-1]
    eps = torch.finfo(probs.dtype).eps if probs.is_floating_point() else 0.0
    tol = max(PROBS_RTOL, 4 * num_actions * eps)
    total = cdf[..., -1].to(torch.float64)
    off, lowest = torch.stack([(total - 1).abs().max(), probs.min().to(torch.float64)]).tolist()
    if not (math.isfinite(off) and math.isfinite(lowest) and lowest >= 0):
        first = probs[(probs < 0) | ~torch.isfinite(probs)].reshape(-1)[0].item()
        raise ValueError(f"probs must be finite and non-negative, got {first}")
    if off > tol:
        wrong = ((total - 1).abs() > tol).sum().item()
        raise ValueError(
            f"probs rows must sum to 1 (within {tol:.3g}), found sums from "
            f"{total.min().item():.6g} to {total.max().item():.6g} ({wrong} of {total.numel()} "
            "rows off)"
        )


def param_dims_of(policy) -> tuple[int, ...]:
    """The leading parameter dims ``*T`` of a library policy (one θ per trial); ``()`` for any
    other policy (a TorchRL actor holds one set of parameters).

    Example:
        >>> param_dims_of(object())
        ()
    """
    return tuple(policy.param_dims) if isinstance(policy, ActionProbsPolicy) else ()


_GREEDY_EXPLORATION = (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)


class ActionProbsPolicy(TensorDictModuleBase):
    """Base of the library's policies: ``action_probs(obs) -> [..., A]``, ``log_prob(obs, a)``
    (both pure functions of the observations) plus sampling.

    Subclasses implement ``_action_probs``. ``forward`` reads the observation, draws an
    action and writes ``action`` in the env's encoding and ``sample_probs`` (the distribution
    the action was drawn from, ``[..., A]``, float64).

    TorchRL's conventions: under ``set_exploration_type(ExplorationType.RANDOM)`` (a
    ``Collector``'s default) or with no exploration type set, the action is sampled from
    ``pi(·|s)``; under ``DETERMINISTIC``, ``MODE`` (or ``MEAN``) it is the mode of ``pi(·|s)``
    (the greedy action; the lowest index among equal probabilities), and ``sample_probs`` is
    then that one-hot distribution, the one the action was really drawn from. The draw
    (:func:`sample_actions`) uses the streams the policy was made with (``generator=`` or
    ``streams=``, or :meth:`with_streams`), else torch's global generator (so
    ``torch.manual_seed`` governs an unseeded policy, as it does TorchRL's actors). The streams
    are fixed when the policy is made: ``generator``, ``counter_streams`` and ``streams`` are
    read-only.

    A new policy family subclasses it and implements ``_action_probs`` (an extension point):

    Example:
        >>> from tensordict import TensorDict
        >>> class AlwaysRight(ActionProbsPolicy):
        ...     def _action_probs(self, obs):  # [..., d] -> [..., A], float64
        ...         probs = torch.zeros(*obs.shape[:-1], self.num_actions, dtype=torch.float64)
        ...         probs[..., -1] = 1.0
        ...         return probs
        >>> policy = AlwaysRight(num_actions=2, one_hot=False)  # (or action_spec=env.action_spec)
        >>> policy = policy.with_streams(CounterStreams(0))
        >>> td = policy(TensorDict({"observation": torch.zeros(3, 1)}, batch_size=[3]))
        >>> td["action"].tolist(), td["sample_probs"].shape
        ([1, 1, 1], torch.Size([3, 2]))
    """

    def __init__(
        self,
        *,
        num_actions: int,
        one_hot: bool | None = None,
        action_spec=None,
        generator: torch.Generator | None = None,
        streams: Streams = None,
        observation_key="observation",
        action_key="action",
        probs_key="sample_probs",
    ) -> None:
        super().__init__()
        if generator is not None and streams is not None:
            raise ValueError("give the random streams once: generator or streams, not both")
        self.num_actions = int(num_actions)
        # Whether the env's encoding was given (action_spec=, or one_hot= said explicitly):
        # without it, forward refuses to act rather than write an index a one-hot env misreads.
        self.encoding_known = action_spec is not None or one_hot is not None
        one_hot = bool(one_hot)
        self.one_hot = one_hot
        self.action_encoding = _encoding(action_spec, self.num_actions, one_hot)
        self._streams = _check_streams(generator if streams is None else streams)
        self.observation_key = observation_key
        self.action_key = action_key
        self.probs_key = probs_key
        self.in_keys = [observation_key]
        self.out_keys = [action_key, probs_key]

    @property
    def streams(self) -> Streams:
        """The random streams the policy samples from (see :data:`Streams`); read-only."""
        return self._streams

    @property
    def generator(self) -> torch.Generator | None:
        """The ``torch.Generator`` the policy samples from, or None."""
        return self._streams if isinstance(self._streams, torch.Generator) else None

    @property
    def counter_streams(self) -> CounterStreams | None:
        """The counter-based streams the policy samples from (one per block of rows), or None."""
        return self._streams if isinstance(self._streams, CounterStreams) else None

    def with_streams(self, streams: Streams) -> ActionProbsPolicy:
        """The same policy (parameters, rule, encoding) sampling from ``streams`` (counter-based
        streams, one per block of rows, e.g. per trial; or a ``torch.Generator``); the original
        keeps its own."""
        other = self._copy()
        other._streams = _check_streams(streams)
        return other

    def _copy(self) -> ActionProbsPolicy:
        """A shallow copy sharing θ and the basis but not the module's registries (so that
        ``copy.to(...)`` or a new buffer of the copy leaves the original as it is)."""
        other = copy.copy(self)
        for name in ("_parameters", "_buffers", "_modules"):
            other.__dict__[name] = dict(self.__dict__[name])
        return other

    def _io_kwargs(self, trials: slice | None = None) -> dict:
        """The keyword arguments that make a copy of this policy with the same I/O and
        streams (of ``trials`` only, where the streams are one per trial)."""
        streams = self._streams
        if trials is not None and isinstance(streams, CounterStreams) and len(streams) > 1:
            streams = streams.select(trials)
        known = self.encoding_known
        return {
            "one_hot": self.one_hot if known else None,
            "action_spec": self.action_encoding if known else None,
            "streams": streams,
            "observation_key": self.observation_key,
            "action_key": self.action_key,
            "probs_key": self.probs_key,
        }

    @property
    def param_dims(self) -> tuple[int, ...]:
        """Leading dims ``*T`` of the policy's parameters (e.g. ``(T,)`` for one θ per trial)."""
        return ()

    def _action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        """``pi(·|s)``: obs ``[*T, ..., d]`` -> ``[*T, ..., A]`` in float64.

        With per-trial parameters ``[T, ...]``, an environment batch laid out trial-major,
        obs ``[T·R, d]``, is accepted too: row ``e`` belongs to trial ``e // R``.
        """
        lead = self.param_dims
        if not lead or obs.shape[: len(lead)] == lead:
            return self._action_probs(obs)
        trials = math.prod(lead)
        if obs.ndim < 2 or obs.shape[0] % trials:
            raise ValueError(
                f"the policy holds parameters for trials {tuple(lead)}; observations must have "
                f"leading dims {tuple(lead)} or a first dim divisible by {trials}, "
                f"got {tuple(obs.shape)}"
            )
        grid = obs.reshape(*lead, obs.shape[0] // trials, *obs.shape[1:])
        probs = self._action_probs(grid)
        return probs.reshape(*obs.shape[:-1], probs.shape[-1])

    def log_prob(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``log pi(a|s)``: obs ``[..., d]`` and actions as this policy writes them (indices
        ``[...]``, or one-hot ``[..., A]``) -> ``[...]`` float64 (``-inf`` where pi(a|s) = 0).

        Pure: no random stream is touched. E.g. the sampling log-probabilities that per-decision
        importance weights (eq. 21) need, for episodes another process collected.

        Example:
            >>> from torch_api.core.basis import GaussianActionBasis
            >>> from torch_api.policies import LinearQPolicy
            >>> basis = GaussianActionBasis(centers=torch.zeros(1, 1), tau=1.0, num_actions=2)
            >>> theta = torch.tensor([0.0, 0.0, 1.0, 1.0])  # Q(s, right) > Q(s, left)
            >>> pi = LinearQPolicy(basis=basis, theta=theta, epsilon=0.2)
            >>> pi.log_prob(torch.zeros(2, 1), torch.tensor([1, 0])).exp()
            tensor([0.9000, 0.1000], dtype=torch.float64)
        """
        probs = self.action_probs(obs)
        index = self.action_encoding.decode(action, batch_dims=probs.ndim - 1)
        return probs.gather(-1, index.unsqueeze(-1)).squeeze(-1).log()

    def with_action_spec(self, action_spec) -> ActionProbsPolicy:
        """The same policy (same parameters and random streams) writing actions in the encoding
        of ``action_spec`` (a TorchRL spec or an
        :class:`~torch_api.data.actions.ActionEncoding`)."""
        encoding = _encoding(action_spec, self.num_actions, self.one_hot)
        if encoding == self.action_encoding and self.encoding_known:
            return self
        other = self._copy()  # shares θ, the basis and the streams
        other.encoding_known = True
        other.action_encoding = encoding
        other.one_hot = encoding.one_hot
        return other

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self.encoding_known:
            raise ValueError(
                f"{type(self).__name__} was built without action_spec=, so it cannot know whether "
                "the env takes an action index or a one-hot vector (GymEnv's default is one-hot, "
                "and it applies action 0 to an index without an error). Build it with "
                "action_spec=env.action_spec (or call policy.with_action_spec(env.action_spec)); "
                "one_hot=False / True states the encoding by hand. The library's own collection "
                "(collect_episodes, the selector, ActivePolicyIteration) sets it from the env."
            )
        obs = tensordict.get(self.observation_key)
        if obs.ndim == tensordict.batch_dims:  # scalar observations (a state index)
            obs = obs.unsqueeze(-1)
        probs = self.action_probs(obs)
        if exploration_type() in _GREEDY_EXPLORATION:
            index = probs.argmax(-1)
            probs = torch.nn.functional.one_hot(index, probs.shape[-1]).to(probs.dtype)
        else:
            index = sample_actions(probs, self._streams)
        tensordict.set(self.action_key, self.action_encoding.encode(index))
        tensordict.set(self.probs_key, probs)
        return tensordict


def _encoding(action_spec, num_actions: int, one_hot: bool) -> ActionEncoding:
    """The encoding of ``action_spec`` (a spec or an encoding), else of the ``one_hot`` flag."""
    if action_spec is None:  # one-hot actions as TorchRL's OneHot spec writes them by default
        return ActionEncoding(num_actions, one_hot, torch.bool if one_hot else torch.int64)
    if isinstance(action_spec, ActionEncoding):
        encoding = action_spec
    else:
        encoding = ActionEncoding.of_spec(action_spec)
    if encoding.num_actions != num_actions:
        raise ValueError(
            f"action_spec has {encoding.num_actions} actions but the policy {num_actions}"
        )
    return encoding
