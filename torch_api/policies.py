"""Policies derived from a linear Q-function ``Q̂(s, a) = θᵀ phi(s, a)`` (paper eq. 7-9, 57-59).

Pure functions turn Q-values ``[..., A]`` into action probabilities; :class:`LinearQPolicy` is a
TensorDict module that samples an action and records the whole distribution (``sample_probs``)
so that importance weights can be computed later against any other policy.
"""

from __future__ import annotations

import copy
import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type

from torch_api.actions import ActionEncoding
from torch_api.basis import as_features

__all__ = [
    "ActionProbsPolicy",
    "LinearQPolicy",
    "TabularPolicy",
    "TIE_BREAKS",
    "epsilon_greedy_probs",
    "greedy_actions",
    "greedy_mask",
    "greedy_probs",
    "linear_q_values",
    "softmax_probs",
]

TIE_RTOL = 1e-10  # Q-values this close (relative) to the maximum count as tied with it
TIE_BREAKS = ("uniform", "lowest")
"""How the greedy mass is shared among tied maximal actions: equal parts, or all to the lowest
index."""


def linear_q_values(phi_all: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``Q̂(s, ·) = θᵀ phi(s, ·)`` (eq. 9).

    phi_all ``[*T, ..., A, B]``, θ ``[*T, B]`` -> ``[*T, ..., A]``.

    θ's leading dims ``*T`` (e.g. a trial dimension) must be a prefix of phi_all's.
    """
    if theta.shape[-1] != phi_all.shape[-1]:
        raise ValueError(
            f"theta has {theta.shape[-1]} entries but the basis has {phi_all.shape[-1]} features"
        )
    lead = theta.shape[:-1]
    if phi_all.shape[: len(lead)] != lead:
        raise ValueError(
            f"theta's leading dims {tuple(lead)} must prefix the observation dims "
            f"{tuple(phi_all.shape[:-2])}"
        )
    extra = phi_all.ndim - 1 - theta.ndim
    view = theta.reshape(*lead, *([1] * extra), 1, theta.shape[-1])
    return (phi_all * view.to(phi_all.dtype)).sum(-1)


def greedy_mask(q: torch.Tensor) -> torch.Tensor:
    """Which actions are maximal: ``q[..., a]`` within ``TIE_RTOL`` (relative) of the maximum.

    ``[..., A] -> [..., A]`` bool, at least one True per row.
    """
    best = q.max(-1, keepdim=True).values
    return q >= best - TIE_RTOL * (1.0 + best.abs())


def greedy_actions(q: torch.Tensor) -> torch.Tensor:
    """One greedy action per row: the lowest index among the maximal ones (:func:`greedy_mask`).

    ``[..., A] -> [...]``. A policy that splits ties evenly uses :func:`greedy_probs` instead.
    """
    return greedy_mask(q).to(torch.int8).argmax(-1)  # argmax returns the first maximal index


def _check_tie_break(tie_break: str) -> str:
    if tie_break not in TIE_BREAKS:
        raise ValueError(f"tie_break must be one of {TIE_BREAKS}, got {tie_break!r}")
    return tie_break


def greedy_probs(q: torch.Tensor, tie_break: str = "uniform") -> torch.Tensor:
    """The greedy policy ``I(a = argmax Q̂)`` of eq. 57/66 as probabilities ``[..., A] -> [..., A]``.

    When several actions are maximal (within ``TIE_RTOL``), ``tie_break="uniform"`` gives each
    of them an equal share (the normalised indicator of the argmax set: with all actions tied,
    e.g. θ = 0 or the paper's θ_0 = 1 on a basis with the same features per action, the policy
    is uniform); ``"lowest"`` gives all the mass to the lowest index among them.

    Returns float64.
    """
    _check_tie_break(tie_break)
    if tie_break == "lowest":
        return torch.nn.functional.one_hot(greedy_actions(q), q.shape[-1]).to(torch.float64)
    mask = greedy_mask(q).to(torch.float64)
    return mask / mask.sum(-1, keepdim=True)


def _check_epsilon(epsilon) -> torch.Tensor:
    eps = torch.as_tensor(epsilon, dtype=torch.float64)
    if not torch.isfinite(eps).all() or (eps < 0).any():
        raise ValueError(f"epsilon must be >= 0, got {epsilon}")
    return eps.clamp(max=1.0)  # ε is capped at 1, the uniform policy (docs/algorithm.md)


def epsilon_greedy_probs(q: torch.Tensor, epsilon, tie_break: str = "uniform") -> torch.Tensor:
    """ε-greedy probabilities (eq. 8): the greedy mass ``1 - ε`` plus ``ε/A`` for every action.

    With a single maximal action it gets ``1 - ε + ε/A`` and the others ``ε/A``; tied maximal
    actions share the greedy mass as :func:`greedy_probs` says (``tie_break``).

    Args:
        q: Q-values ``[..., A]``.
        epsilon: ε ≥ 0, a number or a tensor broadcastable to ``[...]``; values above 1 are
            capped at 1 (uniform).
        tie_break: ``"uniform"`` (tied actions share the greedy mass equally) or ``"lowest"``.

    Returns:
        ``[..., A]`` in float64.
    """
    eps = _check_epsilon(epsilon).to(q.device)
    num_actions = q.shape[-1]
    greedy = greedy_probs(q, tie_break)
    eps = eps.unsqueeze(-1) if eps.ndim else eps
    return (1.0 - eps) * greedy + eps / num_actions


def softmax_probs(q: torch.Tensor, beta) -> torch.Tensor:
    """Softmax probabilities ``pi(a|s) ∝ exp(Q̂(s, a) / β)`` (eq. 7): ``[..., A] -> [..., A]``."""
    beta_t = torch.as_tensor(beta, dtype=torch.float64, device=q.device)
    if not torch.isfinite(beta_t).all() or (beta_t <= 0).any():
        raise ValueError(f"beta must be > 0, got {beta}")
    beta_t = beta_t.unsqueeze(-1) if beta_t.ndim else beta_t
    return torch.softmax(q.to(torch.float64) / beta_t, dim=-1)


_GREEDY_EXPLORATION = (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)


class ActionProbsPolicy(TensorDictModuleBase):
    """Base of the library's policies: ``action_probs(obs) -> [..., A]`` plus sampling.

    Subclasses implement :meth:`action_probs`. ``forward`` reads the observation, draws an
    action and writes ``action`` in the env's encoding and ``sample_probs`` (the distribution
    the action was drawn from, ``[..., A]``, float64).

    TorchRL's conventions: under ``set_exploration_type(ExplorationType.RANDOM)`` (a
    ``Collector``'s default) or with no exploration type set, the action is sampled from
    ``pi(·|s)``; under ``DETERMINISTIC``, ``MODE`` (or ``MEAN``) it is the mode of ``pi(·|s)``
    (the greedy action; the lowest index among equal probabilities), and ``sample_probs`` is
    then that one-hot distribution, the one the action was really drawn from. The draw uses the
    policy's ``generator`` if it has one, else torch's global generator (so ``torch.manual_seed``
    governs an unseeded policy, as it does TorchRL's actors).
    """

    def __init__(
        self,
        *,
        num_actions: int,
        one_hot: bool = False,
        action_spec=None,
        generator: torch.Generator | None = None,
        observation_key="observation",
        action_key="action",
        probs_key="sample_probs",
    ) -> None:
        super().__init__()
        self.num_actions = int(num_actions)
        self.one_hot = one_hot
        self.action_encoding = _encoding(action_spec, self.num_actions, one_hot)
        self.generator = generator
        self.observation_key = observation_key
        self.action_key = action_key
        self.probs_key = probs_key
        self.in_keys = [observation_key]
        self.out_keys = [action_key, probs_key]

    def _copy_streams(self, other: ActionProbsPolicy, trials: slice | None = None):
        blocks = self.block_generators
        other.block_generators = blocks if blocks is None or trials is None else blocks[trials]
        return other

    def _io_kwargs(self) -> dict:
        return {
            "one_hot": self.one_hot,
            "action_spec": self.action_encoding,
            "generator": self.generator,
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

    block_generators: list[torch.Generator] | None = None
    """One random stream per equal, consecutive block of rows (e.g. per trial), or None."""

    def sample(self, probs: torch.Tensor) -> torch.Tensor:
        """Draw action indices ``[...]`` from ``probs [..., A]`` with the policy's generator.

        With ``block_generators`` set, the rows (flattened leading dims, trial-major) are split
        into equal blocks, each drawn from its own generator.
        """
        shape = probs.shape[:-1]
        if self.block_generators is None:
            device = "cpu" if self.generator is None else self.generator.device
            uniform = torch.rand(
                shape, generator=self.generator, dtype=torch.float64, device=device
            )
        else:
            rows, blocks = shape.numel(), len(self.block_generators)
            if rows % blocks:
                raise ValueError(f"{rows} rows do not split into {blocks} equal blocks")
            uniform = torch.cat(
                [
                    torch.rand(rows // blocks, generator=g, dtype=torch.float64, device=g.device)
                    for g in self.block_generators
                ]
            ).reshape(shape)
        uniform = uniform.to(probs.device)
        cdf = probs.cumsum(-1)
        return (cdf < uniform.unsqueeze(-1)).sum(-1).clamp(max=probs.shape[-1] - 1)

    def with_action_spec(self, action_spec) -> ActionProbsPolicy:
        """The same policy (same parameters and random streams) writing actions in the encoding
        of ``action_spec`` (a TorchRL spec or an :class:`~torch_api.actions.ActionEncoding`)."""
        encoding = _encoding(action_spec, self.num_actions, self.one_hot)
        if encoding == self.action_encoding:
            return self
        other = copy.copy(self)  # shares θ, the basis and the generators
        other.action_encoding = encoding
        other.one_hot = encoding.one_hot
        return other

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.observation_key)
        if obs.ndim == tensordict.batch_dims:  # scalar observations (a state index)
            obs = obs.unsqueeze(-1)
        probs = self.action_probs(obs)
        if exploration_type() in _GREEDY_EXPLORATION:
            index = probs.argmax(-1)
            probs = torch.nn.functional.one_hot(index, probs.shape[-1]).to(probs.dtype)
        else:
            index = self.sample(probs)
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
        batch = tuple(action_spec.shape[:-1])
        encoding = ActionEncoding.from_spec(action_spec, batch)
    if encoding.num_actions != num_actions:
        raise ValueError(
            f"action_spec has {encoding.num_actions} actions but the policy {num_actions}"
        )
    return encoding


class TabularPolicy(ActionProbsPolicy):
    """A policy given as a probability table over a finite state space.

    Args:
        table: ``[*T, S, A]`` probabilities, rows summing to 1 (``*T``: e.g. one table per
            environment of a batch, prefixing the observation dims).
        state_index: maps an observation ``[..., d]`` to its row index ``[...]`` (long).
        one_hot, generator, observation_key, action_key, probs_key: as in
            :class:`ActionProbsPolicy`.

    Example:
        >>> table = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=torch.float64)
        >>> policy = TabularPolicy(table=table, state_index=lambda obs: obs[..., 0].long())
        >>> policy.action_probs(torch.tensor([[1.0], [0.0]]))
        tensor([[0.2000, 0.8000],
                [0.9000, 0.1000]], dtype=torch.float64)
    """

    def __init__(self, *, table: torch.Tensor, state_index, **io) -> None:
        table = torch.as_tensor(table, dtype=torch.float64)
        if table.ndim < 2:
            raise ValueError(f"table must have shape [..., S, A], got {tuple(table.shape)}")
        _check_distribution(table, "table")
        super().__init__(num_actions=table.shape[-1], **io)
        self.register_buffer("table", table)
        self.state_index = state_index

    @property
    def param_dims(self) -> tuple[int, ...]:
        return tuple(self.table.shape[:-2])

    def trial_slice(self, trials: slice) -> TabularPolicy:
        """The policy of some trials only (the first parameter dim sliced)."""
        return self._copy_streams(
            TabularPolicy(
                table=self.table[trials], state_index=self.state_index, **self._io_kwargs()
            ),
            trials,
        )

    def _action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        index = self.state_index(obs).long()
        lead = self.table.shape[:-2]
        if index.shape[: len(lead)] != lead:
            raise ValueError(
                f"the table's leading dims {tuple(lead)} must prefix the observation dims "
                f"{tuple(index.shape)}"
            )
        num_states = self.table.shape[-2]
        if index.numel() and (index.min() < 0 or index.max() >= num_states):
            raise ValueError(
                f"state_index gave rows outside [0, {num_states}): "
                f"[{int(index.min())}, {int(index.max())}]"
            )
        extra = index.ndim - len(lead)
        table = self.table.to(index.device).reshape(*lead, *([1] * extra), *self.table.shape[-2:])
        table = table.expand(*index.shape, *self.table.shape[-2:])
        return torch.gather(
            table, -2, index[..., None, None].expand(*index.shape, 1, self.num_actions)
        ).squeeze(-2)


def _check_distribution(probs: torch.Tensor, name: str) -> None:
    if not torch.isfinite(probs).all() or (probs < 0).any():
        raise ValueError(f"{name} must hold finite, non-negative probabilities")
    total = probs.sum(-1)
    worst = (total - 1).abs().max().item() if total.numel() else 0.0
    if worst > 1e-6:
        raise ValueError(
            f"{name} rows must sum to 1, one sums to {1 + worst:.6g} (off by {worst:.3g})"
        )


class LinearQPolicy(ActionProbsPolicy):
    """ε-greedy, greedy or softmax policy over ``Q̂ = θᵀ phi`` as a TensorDict module.

    Reads ``observation`` and writes ``action`` (in the encoding of ``action_spec``: an index,
    or one-hot) and ``sample_probs`` (the full distribution ``[..., A]``, float64) so that the
    episode can be importance-weighted later. Sampling follows TorchRL's exploration type and
    uses the policy's own ``torch.Generator`` if given (see :class:`ActionProbsPolicy`).

    Args:
        basis: module with ``phi_all(obs [..., d]) -> [..., A, B]`` and ``num_features``.
        theta: ``[B]`` or ``[*T, B]`` (a leading trial dimension prefixing the observation dims).
        epsilon: ε of the ε-greedy rule (0 is greedy), a number or a ``[*T]`` tensor (one per
            trial). Exclusive with ``beta``.
        beta: temperature of the softmax rule (eq. 7), a number or ``[*T]``. Exclusive with
            ``epsilon``.
        tie_break: how the ε-greedy rule shares the greedy mass among actions whose Q̂ ties for
            the maximum: ``"uniform"`` (equal parts; with θ = 0, or θ = 1 on a basis with the
            same features per action, the policy is uniform) or ``"lowest"`` (all to the lowest
            index). See :func:`greedy_probs`.
        one_hot: write one-hot actions (``bool``, TorchRL's ``OneHot`` default) where no
            ``action_spec`` is given.
        action_spec: the env's action spec (``env.action_spec``): actions are written in its
            encoding (one-hot or index) and dtype. :func:`~torch_api.data.collect_episodes`
            sets it from the env it collects on.
        generator: random stream for sampling (default: torch's global generator).
        observation_key, action_key, probs_key: tensordict keys.

    Example:
        >>> from tensordict import TensorDict
        >>> from torch_api.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.tensor([[1.0], [9.0]]), tau=1.5,
        ...                             num_actions=2)
        >>> policy = LinearQPolicy(basis=basis, theta=torch.ones(6), epsilon=0.15)
        >>> td = policy(TensorDict({"observation": torch.ones(4, 1)}, batch_size=[4]))
        >>> td["action"].shape, td["sample_probs"].shape
        (torch.Size([4]), torch.Size([4, 2]))
    """

    def __init__(
        self,
        *,
        basis: nn.Module,
        theta: torch.Tensor,
        epsilon: float | torch.Tensor | None = None,
        beta: float | torch.Tensor | None = None,
        tie_break: str = "uniform",
        one_hot: bool = False,
        action_spec=None,
        generator: torch.Generator | None = None,
        observation_key="observation",
        action_key="action",
        probs_key="sample_probs",
    ) -> None:
        _check_tie_break(tie_break)
        if (epsilon is None) == (beta is None):
            raise ValueError(
                f"give exactly one of epsilon (ε-greedy) or beta (softmax), got epsilon={epsilon}, "
                f"beta={beta}"
            )
        theta = torch.as_tensor(theta, dtype=torch.float64)
        if theta.ndim == 0 or theta.shape[-1] != basis.num_features:
            raise ValueError(
                f"theta must have shape [..., {basis.num_features}] (the basis width), "
                f"got {tuple(theta.shape)}"
            )
        if not torch.isfinite(theta).all():
            raise ValueError("theta contains NaN or inf")
        if epsilon is not None:
            epsilon = _check_epsilon(epsilon)
        if beta is not None:
            beta = torch.as_tensor(beta, dtype=torch.float64)
            if not torch.isfinite(beta).all() or (beta <= 0).any():
                raise ValueError(f"beta must be > 0, got {beta}")
        super().__init__(
            num_actions=basis.num_actions,
            one_hot=one_hot,
            action_spec=action_spec,
            generator=generator,
            observation_key=observation_key,
            action_key=action_key,
            probs_key=probs_key,
        )
        self.basis = basis
        self.register_buffer("theta", theta)
        self.epsilon = epsilon
        self.beta = beta
        self.tie_break = tie_break

    def q_values(self, obs: torch.Tensor) -> torch.Tensor:
        """``Q̂(s, ·)``: obs ``[*T, ..., d]`` -> ``[*T, ..., A]`` in float64."""
        obs = as_features(obs).to(torch.float64)
        theta = self.theta.to(obs.device)  # θ follows the observations (env on CPU or GPU)
        if hasattr(self.basis, "q_values"):  # block-structured fast path
            return self.basis.q_values(obs, theta)
        return linear_q_values(self.basis.phi_all(obs), theta)

    @property
    def param_dims(self) -> tuple[int, ...]:
        return tuple(self.theta.shape[:-1])

    def _rule(self) -> dict:
        return {"beta": self.beta} if self.beta is not None else {"epsilon": self.epsilon}

    def trial_slice(self, trials: slice) -> LinearQPolicy:
        """The policy of some trials only (θ's first dim, and a per-trial ε or β, sliced)."""
        rule = {k: v[trials] if v.ndim else v for k, v in self._rule().items()}
        return self._copy_streams(
            LinearQPolicy(
                basis=self.basis,
                theta=self.theta[trials],
                **rule,
                tie_break=self.tie_break,
                **self._io_kwargs(),
            ),
            trials,
        )

    def _action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        q = self.q_values(obs)
        rule = self.beta if self.beta is not None else self.epsilon
        if rule.ndim:  # per-trial ε or β [*T]: align with the observation dims
            rule = rule.reshape(*rule.shape, *([1] * (q.ndim - 1 - rule.ndim)))
        if self.beta is not None:
            return softmax_probs(q, rule)
        return epsilon_greedy_probs(q, rule, self.tie_break)

    def to_device(self, device) -> LinearQPolicy:
        """A copy whose θ lives on ``device`` (the sampling generator stays where it is)."""
        rule = self._rule()
        return self._copy_streams(
            LinearQPolicy(
                basis=self.basis,
                theta=self.theta.to(device),
                **rule,
                tie_break=self.tie_break,
                **self._io_kwargs(),
            )
        )

    def with_rule(
        self,
        *,
        epsilon: float | torch.Tensor | None = None,
        beta: float | torch.Tensor | None = None,
    ) -> LinearQPolicy:
        """The same θ and basis under another rule (e.g. the candidates of eq. 59)."""
        return self._copy_streams(
            LinearQPolicy(
                basis=self.basis,
                theta=self.theta,
                epsilon=epsilon,
                beta=beta,
                tie_break=self.tie_break,
                **self._io_kwargs(),
            )
        )
