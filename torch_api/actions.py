"""How an environment encodes a discrete action: an index or a one-hot vector, and its dtype.

TorchRL envs declare their action in ``env.action_spec``: a ``Categorical`` spec (an index,
shape ``[*E]`` or ``[*E, 1]``) or a ``OneHot`` spec (shape ``[*E, A]``); Gymnasium envs through
``GymEnv`` are one-hot by default, in ``int64``. A policy that writes an index into a one-hot
env is not refused by every env: ``GymEnv`` reads it as a one-hot vector and applies action 0,
while the index stays in the rollout as if it had been taken. So the library's policies write
actions in the env's own encoding (:class:`ActionEncoding`, read from the spec), and every
collection checks the actions against the spec before the first step
(:func:`check_actions`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ActionEncoding", "check_actions"]


@dataclass(frozen=True)
class ActionEncoding:
    """The encoding of one discrete action.

    Attributes:
        num_actions: A.
        one_hot: a one-hot vector ``[..., A]`` (else an index ``[...]``).
        dtype: the tensor dtype the env expects.
        trailing_dim: an index carries a trailing ``[..., 1]`` (a ``Categorical`` spec whose
            last dim is 1).

    Example:
        >>> from torchrl.data import OneHot
        >>> enc = ActionEncoding.from_spec(OneHot(n=3, dtype=torch.int64))
        >>> enc.encode(torch.tensor([2, 0]))
        tensor([[0, 0, 1],
                [1, 0, 0]])
        >>> enc.decode(enc.encode(torch.tensor([2, 0])), batch_dims=1)
        tensor([2, 0])
    """

    num_actions: int
    one_hot: bool = False
    dtype: torch.dtype = torch.int64
    trailing_dim: bool = False

    @classmethod
    def from_spec(cls, spec, batch_shape: tuple[int, ...] | torch.Size = ()) -> ActionEncoding:
        """The encoding of a TorchRL action spec (``OneHot`` or ``Categorical``).

        Args:
            spec: ``env.action_spec`` (leading dims ``batch_shape``, the env's batch size).
            batch_shape: the env's batch size.

        Raises:
            ValueError: a spec that is not a discrete (one-hot or categorical) action.
        """
        from torchrl.data import Categorical, OneHot  # (imported here: a light module)

        tail = tuple(spec.shape[len(batch_shape) :])
        if isinstance(spec, OneHot):
            return cls(num_actions=int(spec.space.n), one_hot=True, dtype=spec.dtype)
        if isinstance(spec, Categorical):
            if tail not in ((), (1,)):
                raise ValueError(
                    f"a Categorical action spec must hold one action per env row (shape [*E] or "
                    f"[*E, 1]), got shape {tuple(spec.shape)} for batch size {tuple(batch_shape)}"
                )
            return cls(
                num_actions=int(spec.space.n),
                one_hot=False,
                dtype=spec.dtype,
                trailing_dim=tail == (1,),
            )
        raise ValueError(
            f"the env's action spec must be OneHot or Categorical (discrete actions), "
            f"got {type(spec).__name__}"
        )

    def encode(self, index: torch.Tensor) -> torch.Tensor:
        """Action indices ``[...]`` -> the env's action tensor."""
        if self.one_hot:
            return torch.nn.functional.one_hot(index, self.num_actions).to(self.dtype)
        action = index.to(self.dtype)
        return action.unsqueeze(-1) if self.trailing_dim else action

    def decode(self, action: torch.Tensor, batch_dims: int) -> torch.Tensor:
        """The env's action tensor (``batch_dims`` leading dims) -> indices ``[...]`` (long)."""
        if action.ndim == batch_dims:
            return action.long()
        if action.ndim == batch_dims + 1 and action.shape[-1] == 1 and not self.one_hot:
            return action.squeeze(-1).long()
        return action.long().argmax(-1)


def check_actions(spec, action: torch.Tensor, *, who: str = "the policy") -> None:
    """Refuse actions the env's spec does not accept (``spec.is_in``), before they are applied.

    Raises:
        ValueError: naming the spec's shape and dtype and the action's.
    """
    inside = spec.is_in(action)
    if not bool(inside):
        raise ValueError(
            f"{who} wrote actions of shape {tuple(action.shape)} and dtype {action.dtype}, which "
            f"the env's action spec ({type(spec).__name__}, shape {tuple(spec.shape)}, dtype "
            f"{spec.dtype}) does not accept (action_spec.is_in is False). A one-hot env needs "
            "one-hot actions in the spec's dtype, a categorical env indices; the library's "
            "policies follow the spec when given action_spec=env.action_spec"
        )
