"""A stored run's identity: what a resume must agree on, taken by value.

The identity of a run of :class:`~torch_api.loop.iteration.ActivePolicyIteration` is its
:class:`~torch_api.loop.spec.RunSpec` and the parameters its environment and basis declare
(:func:`declared_parameters`), as flat dotted keys, so that a refused resume names the field
that differs (``"evaluation.lam"``, ``"env.end_at_hit"``). Never ``vars()`` of an object nor the
module a class is imported from: a harmless new attribute or a moved module changes nothing.
"""

from __future__ import annotations

import hashlib
import inspect
import math
from typing import Any

import torch
from torch import nn

from torch_api.loop.spec import RunSpec

__all__ = ["declared_parameters", "run_identity"]


def _described(value) -> Any:
    """A JSON-able, exact description of a declared parameter's value (tensors by digest)."""
    if isinstance(value, torch.Tensor):
        data = value.detach().cpu().contiguous()
        digest = hashlib.sha256(data.view(torch.uint8).numpy().tobytes()).hexdigest()
        return {"dtype": str(data.dtype), "shape": list(data.shape), "sha256": digest}
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, (tuple, list)):
        return [_described(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _described(v) for k, v in value.items()}
    raise ValueError(
        f"a declared parameter must be a number, string, tensor or a list/dict of them, got "
        f"{type(value).__name__}"
    )


def declared_parameters(obj) -> dict:
    """What identifies an environment or a basis, by value: its class's name and the parameters
    it declares.

    An object declares its parameters with a method ``identity_parameters() -> dict`` (numbers,
    strings, tensors). Without one: the parameters its ``__init__`` declares, as it holds them
    (:func:`_constructor_parameters`); an ``nn.Module``'s ``state_dict`` (tensors by digest);
    a TorchRL env's ``env_name`` (``GymEnv``), its observation shapes (batch dims left out) and
    its number of actions. Never its other
    attributes, nor the module it is imported from: a harmless new attribute or a moved module
    leaves a stored run resumable.

    >>> from torch_api.core.basis import GaussianActionBasis
    >>> basis = GaussianActionBasis(centers=torch.zeros(1, 2), tau=1.0, num_actions=2)
    >>> sorted(declared_parameters(basis))  # doctest: +ELLIPSIS
    ['class', ...]
    """
    out: dict[str, Any] = {"class": type(obj).__qualname__}
    declared = _own_attribute(obj, "identity_parameters")
    if callable(declared):
        return out | {str(k): _described(v) for k, v in declared().items()}
    out |= _constructor_parameters(obj)
    if isinstance(obj, nn.Module):  # (a TorchRL env is one too: its specs follow)
        out |= {f"state.{k}": _described(v) for k, v in obj.state_dict().items()}
    name = _own_attribute(obj, "env_name")
    if isinstance(name, str):
        out["env_name"] = name
    batch = len(getattr(obj, "batch_size", ()))
    spec = getattr(obj, "observation_spec", None)
    if spec is not None:
        out["observation"] = {
            str(key): list(leaf.shape[batch:]) for key, leaf in spec.items(True, True)
        }
    actions = getattr(getattr(obj, "action_spec", None), "space", None)
    if getattr(actions, "n", None) is not None:
        out["actions"] = int(actions.n)
    return out


# where and how it runs (rows, processes, threads), not what it computes: left out
_WHERE_NOT_WHAT = {
    "batch_size",
    "device",
    "seed",
    "num_workers",
    "num_threads",
    "num_sub_threads",
    "daemon",
    "shutdown_timeout",
    "pin_memory",
}


def _constructor_parameters(obj) -> dict:
    """The parameters the object's class declares in its ``__init__`` that the object holds
    under the same name as a plain value (a number, string, tensor or a list of them), e.g.
    ``ChainWalkEnv(success_prob=0.6)``'s ``success_prob`` or the basis's ``tau``; batch size,
    device, seed and worker settings left out. An attribute the constructor does not declare
    is never read."""
    try:
        parameters = inspect.signature(type(obj).__init__).parameters
    except (TypeError, ValueError):
        return {}
    held = getattr(obj, "__dict__", {})
    out = {}
    for name, parameter in parameters.items():
        if (
            name == "self"
            or name.startswith("_")
            or name in _WHERE_NOT_WHAT
            or name not in held
            or parameter.kind in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD)
        ):
            continue
        try:
            out[name] = _described(held[name])
        except ValueError:  # not a plain value (a function, a module): not compared
            continue
    return out


def _own_attribute(obj, name: str):
    """``obj.name`` where the object or its class defines it, else None: never through a
    ``__getattr__`` (a TorchRL batched env forwards it to its sub-envs, and recurses without
    end before it is started)."""
    if name in getattr(obj, "__dict__", {}) or any(name in vars(c) for c in type(obj).__mro__):
        return getattr(obj, name, None)
    return None


def run_identity(spec: RunSpec, *, env, basis, **extra) -> dict:
    """What a stored run must agree on to be resumed: the specification and the declared
    parameters of the env and the basis, as flat dotted keys (``"evaluation.lam"``,
    ``"env.class"``) so that a refusal names the field; ``extra`` for other settings (the
    criterion's name, the warm start's digest), left out where None."""

    def flatten(prefix: str, value) -> dict:
        if isinstance(value, dict) and value:
            return {
                k: v
                for key, item in value.items()
                for k, v in flatten(f"{prefix}.{key}", item).items()
            }
        return {prefix: value}

    identity = {}
    for key, value in spec.to_dict().items():
        identity |= flatten(key, value)
    identity |= flatten("env", declared_parameters(env))
    identity |= flatten("basis", declared_parameters(basis))
    for key, value in extra.items():
        if value is not None:
            identity |= flatten(key, _described(value))
    return identity
