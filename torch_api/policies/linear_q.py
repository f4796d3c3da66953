"""Policies derived from a linear Q-function ``Q̂(s, a) = θᵀ phi(s, a)`` (paper eq. 7-9, 57-59).

The pure functions that turn Q-values ``[..., A]`` into action probabilities live in
:mod:`torch_api.core.improvement`, the base class :class:`ActionProbsPolicy` (the one to
subclass for a new policy family) and the sampling function :func:`sample_actions` (which takes
its random streams as an argument) in :mod:`torch_api.policies.base`; all are re-exported
here. Here:
:class:`LinearQPolicy`, a TensorDict module that samples an action from the streams it was made
with and records the whole distribution (``sample_probs``) so that importance weights can be
computed later against any other policy, and :class:`TabularPolicy`.
"""

from __future__ import annotations

import torch
from torch import nn

from torch_api._checks import _check_not_meta
from torch_api.core.basis import as_features
from torch_api.core.improvement import (
    TIE_BREAKS,
    TIE_RTOL,
    _check_epsilon,
    _check_tie_break,
    epsilon_greedy_probs,
    greedy_actions,
    greedy_mask,
    greedy_probs,
    linear_q_values,
    softmax_probs,
)
from torch_api.policies.base import ActionProbsPolicy, Streams, sample_actions

__all__ = [
    "ActionProbsPolicy",
    "LinearQPolicy",
    "TabularPolicy",
    "TIE_BREAKS",
    "TIE_RTOL",
    "epsilon_greedy_probs",
    "greedy_actions",
    "greedy_mask",
    "greedy_probs",
    "linear_q_values",
    "sample_actions",
    "softmax_probs",
]


class TabularPolicy(ActionProbsPolicy):
    """A policy given as a probability table over a finite state space.

    Args:
        table: ``[*T, S, A]`` probabilities, rows summing to 1 (``*T``: e.g. one table per
            environment of a batch, prefixing the observation dims).
        state_index: maps an observation ``[..., d]`` to its row index ``[...]`` (long).
        one_hot, generator, streams, observation_key, action_key, probs_key: as in
            :class:`ActionProbsPolicy`.

    Example:
        >>> table = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=torch.float64)
        >>> policy = TabularPolicy(table=table, state_index=lambda obs: obs[..., 0].long())
        >>> policy.action_probs(torch.tensor([[1.0], [0.0]]))
        tensor([[0.2000, 0.8000],
                [0.9000, 0.1000]], dtype=torch.float64)
    """

    def __init__(self, *, table: torch.Tensor, state_index, **io) -> None:
        _check_not_meta("table", table)
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
        return TabularPolicy(
            table=self.table[trials], state_index=self.state_index, **self._io_kwargs(trials)
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
    uses the random streams the policy was made with, if any (see :class:`ActionProbsPolicy`).

    Args:
        basis: module with ``phi_all(obs [..., d]) -> [..., A, B]`` and ``num_features``.
        theta: ``[B]`` or ``[*T, B]`` (a leading trial dimension prefixing the observation dims).
        epsilon: ε in [0, 1] of the ε-greedy rule (0 is greedy, 1 uniform), a number or a
            ``[*T]`` tensor (one per trial); a value outside [0, 1] is refused. Exclusive with
            ``beta``.
        beta: temperature of the softmax rule (eq. 7), a number or ``[*T]``. Exclusive with
            ``epsilon``.
        tie_break: how the ε-greedy rule shares the greedy mass among actions whose Q̂ ties for
            the maximum: ``"uniform"`` (equal parts; with θ = 0, or θ = 1 on a basis with the
            same features per action, the policy is uniform) or ``"lowest"`` (all to the lowest
            index). See :func:`greedy_probs`.
        one_hot: where no ``action_spec`` is given, the encoding stated by hand: True writes
            one-hot actions (``bool``, TorchRL's ``OneHot`` default), False indices. Given
            neither, the policy refuses to act as a module (``policy(td)``, ``env.rollout``,
            a ``Collector``) with an error naming the fix: an index written into a one-hot env
            (``GymEnv``'s default) would be applied as action 0. Its pure functions
            (``action_probs``, ``log_prob``) need no encoding.
        action_spec: the env's action spec (``env.action_spec``): actions are written in its
            encoding (one-hot or index) and dtype. :func:`~torch_api.collection.collect_episodes`
            sets it from the env it collects on.
        generator: random stream for sampling (default: torch's global generator).
        streams: instead of ``generator``, one generator per trial (``[*T]`` flattened) or
            per equal block of rows (see :func:`sample_actions`).
        observation_key, action_key, probs_key: tensordict keys.

    Example:
        >>> from tensordict import TensorDict
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.tensor([[1.0], [9.0]]), tau=1.5,
        ...                             num_actions=2)
        >>> policy = LinearQPolicy(basis=basis, theta=torch.ones(6), epsilon=0.15, one_hot=False)
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
        one_hot: bool | None = None,
        action_spec=None,
        generator: torch.Generator | None = None,
        streams: Streams = None,
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
        _check_not_meta("theta", theta)
        theta = torch.as_tensor(theta, dtype=torch.float64)
        if theta.ndim == 0 or theta.shape[-1] != basis.num_features:
            raise ValueError(
                f"theta must have shape [..., {basis.num_features}] (the basis width), "
                f"got {tuple(theta.shape)}"
            )
        if not torch.isfinite(theta).all():
            raise ValueError("theta contains NaN or inf")
        if epsilon is not None:
            epsilon = _check_epsilon(epsilon, at_most_one=True)
        if beta is not None:
            beta = torch.as_tensor(beta, dtype=torch.float64)
            if not torch.isfinite(beta).all() or (beta <= 0).any():
                raise ValueError(f"beta must be > 0, got {beta}")
        super().__init__(
            num_actions=basis.num_actions,
            one_hot=one_hot,
            action_spec=action_spec,
            generator=generator,
            streams=streams,
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
        return LinearQPolicy(
            basis=self.basis,
            theta=self.theta[trials],
            **rule,
            tie_break=self.tie_break,
            **self._io_kwargs(trials),
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
        return LinearQPolicy(
            basis=self.basis,
            theta=self.theta.to(device),
            **rule,
            tie_break=self.tie_break,
            **self._io_kwargs(),
        )

    def with_rule(
        self,
        *,
        epsilon: float | torch.Tensor | None = None,
        beta: float | torch.Tensor | None = None,
    ) -> LinearQPolicy:
        """The same θ and basis under another rule (e.g. the candidates of eq. 59)."""
        return LinearQPolicy(
            basis=self.basis,
            theta=self.theta,
            epsilon=epsilon,
            beta=beta,
            tie_break=self.tie_break,
            **self._io_kwargs(),
        )
