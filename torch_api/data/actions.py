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

__all__ = ["ActionEncoding", "check_actions", "check_encoded"]


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
            ValueError: a spec that is not a discrete (one-hot or categorical) action, or a
                multi-discrete one (``MultiCategorical``, ``MultiOneHot``: unsupported).
        """
        from torchrl.data import Categorical, OneHot  # (imported here: a light module)

        _refuse_multi_discrete(spec)
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

    @classmethod
    def of_spec(cls, spec) -> ActionEncoding:
        """The encoding of an action spec given without its env's batch size: a ``OneHot``
        spec is ``[*E, A]``, a ``Categorical`` one ``[*E, 1]`` (a trailing 1) or ``[*E]``."""
        _refuse_multi_discrete(spec)
        shape = tuple(spec.shape)
        one_hot = type(spec).__name__ == "OneHot"
        return cls.from_spec(spec, shape[:-1] if one_hot or shape[-1:] == (1,) else shape)

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


_MULTI_DISCRETE = ("MultiCategorical", "MultiOneHot")


def _refuse_multi_discrete(spec) -> None:
    """Several discrete actions per step (TorchRL's ``MultiCategorical`` / ``MultiOneHot``,
    subclasses of ``Categorical`` / ``OneHot``) are not supported: the library's policies and
    basis choose one of A actions."""
    name = type(spec).__name__
    if name in _MULTI_DISCRETE:
        nvec = getattr(spec, "nvec", None)
        nvec = nvec.tolist() if isinstance(nvec, torch.Tensor) else nvec
        sizes = f"nvec = {list(nvec)}: " if isinstance(nvec, list | tuple) else ""
        raise ValueError(
            f"{name} action specs ({sizes}several discrete actions per step) are not supported: "
            "the library's policies choose one of A actions at each step (a OneHot or "
            "Categorical spec); flatten the action space into one Categorical of prod(nvec) "
            "actions"
        )


def check_actions(spec, action: torch.Tensor, *, who: str = "the policy") -> None:
    """Refuse actions the env's spec does not accept (``spec.is_in``), before they are applied.

    Raises:
        ValueError: naming the spec's shape and dtype and the action's.
    """
    one_hot = type(spec).__name__ == "OneHot"
    try:
        inside = spec.is_in(action)
    except RuntimeError as error:  # e.g. an index [E] where a one-hot env wants [E, A]
        hint = (
            "A one-hot env (GymEnv's default) needs one-hot actions: give a ProbabilisticActor "
            "distribution_class=OneHotCategorical (not Categorical), or build the env with "
            "GymEnv(..., categorical_action_encoding=True) to keep Categorical"
            if one_hot
            else "A categorical env needs action indices: give a ProbabilisticActor "
            "distribution_class=Categorical (not OneHotCategorical)"
        )
        raise ValueError(
            f"{who} wrote actions of shape {tuple(action.shape)} and dtype {action.dtype}, which "
            f"the env's action spec ({type(spec).__name__}, shape {tuple(spec.shape)}, dtype "
            f"{spec.dtype}) cannot even compare ({error}). {hint}"
        ) from error
    if not bool(inside):
        raise ValueError(
            f"{who} wrote actions of shape {tuple(action.shape)} and dtype {action.dtype}, which "
            f"the env's action spec ({type(spec).__name__}, shape {tuple(spec.shape)}, dtype "
            f"{spec.dtype}) does not accept (action_spec.is_in is False). A one-hot env needs "
            "one-hot actions in the spec's dtype, a categorical env indices; the library's "
            "policies follow the spec when given action_spec=env.action_spec"
        )


def check_encoded(
    encoding: ActionEncoding, action: torch.Tensor, real: torch.Tensor, *, who: str = "the data"
) -> None:
    """Refuse recorded actions that are not in ``encoding`` on the real steps ``real``.

    Args:
        encoding: the env's encoding (from its action spec).
        action: the recorded actions ``[*E, N]`` (indices) or ``[*E, N, A]`` (one-hot).
        real: bool ``[*E, N]``, the steps that exist (padding is not checked).

    Raises:
        ValueError: an index where the spec is one-hot (the case of a policy that wrote an
            index into ``GymEnv``'s default one-hot env, which applied action 0 instead), a
            one-hot vector where it is an index, or a value outside the A actions.
    """
    kind = f"{'OneHot' if encoding.one_hot else 'Categorical'}, {encoding.num_actions} actions"
    batch_dims = real.ndim
    if encoding.one_hot:
        if action.ndim != batch_dims + 1 or action.shape[-1] != encoding.num_actions:
            raise ValueError(
                f"{who} hold actions of shape {tuple(action.shape)}, not one-hot vectors "
                f"[..., {encoding.num_actions}] as the action_spec ({kind}) says: an index "
                "written into a one-hot env (GymEnv's default) is applied as action 0 without an "
                "error, so these actions were probably not the ones taken. Build the policy with "
                "action_spec=env.action_spec"
            )
        rows = action[real]
        bad = ((rows != 0) & (rows != 1)).any(-1) | (rows.sum(-1) != 1)
    else:
        if action.ndim == batch_dims + 1 and action.shape[-1] == 1:
            action = action.squeeze(-1)
        if action.ndim != batch_dims:
            raise ValueError(
                f"{who} hold actions of shape {tuple(action.shape)}, not indices as the "
                f"action_spec ({kind}) says (a one-hot vector in a categorical env?)"
            )
        rows = action[real]
        bad = (rows < 0) | (rows >= encoding.num_actions) | (rows != rows.long())
    if bad.any():
        first = rows[bad.nonzero()[0, 0]].tolist()
        raise ValueError(
            f"{who} hold {int(bad.sum())} actions outside the action_spec ({kind}), e.g. "
            f"{first}: every real step needs one valid action (one-hot: exactly one 1)"
        )
