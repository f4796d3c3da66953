"""What the loop is given besides its specification, checked; the user's episodes read in.

:class:`~torch_api.loop.iteration.ActivePolicyIteration` takes a
:class:`~torch_api.loop.spec.RunSpec` (the values) and objects (the env, the selector, a
collector, the user's candidates): :func:`checked_parts` refuses combinations that cannot
work, naming them; :func:`padded_episodes` reads the rewarded episodes a user bought in their
own collector into the library's format.
"""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torch_api.data.buffer import EpisodeBuffer
from torch_api.data.episodes import pad_steps
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec

__all__ = ["checked_parts", "name_of", "padded_episodes"]


def name_of(function) -> str:
    """A function's or a module's name (its class's, for an object): how a setting that is a
    function is told apart, without the module it is imported from."""
    return getattr(function, "__qualname__", type(function).__qualname__)


def padded_episodes(episodes, trial_dims: tuple[int, ...], num_steps: int) -> TensorDictBase:
    """The user's rewarded episodes (TorchRL data as it comes) in the library's format
    ``[*T, M, N]``, padded to N steps as the loop's own are."""
    if trial_dims:
        if not isinstance(episodes, TensorDictBase) or tuple(episodes.shape[:1]) != trial_dims:
            raise ValueError(
                f"with trials, fit(episodes) takes the library's episodes [T, M, N] with T = "
                f"{trial_dims[0]}, got {getattr(episodes, 'shape', type(episodes).__name__)}"
            )
        return episodes
    buffer = EpisodeBuffer(rewarded=True, capacity=episodes.numel() + 1)
    buffer.extend(episodes)
    held = buffer.episodes()
    longest = int(held["mask"].sum(-1).max())
    if longest > num_steps:
        raise ValueError(
            f"fit(episodes) got an episode of {longest} steps, more than num_steps = {num_steps}"
        )
    return pad_steps(held[..., : min(held.shape[-1], num_steps)], num_steps)


def checked_parts(spec, env, selector, collector, extra_candidates) -> RunSpec:
    """The spec, checked against the objects given with it (ValueError naming them)."""
    if not isinstance(spec, RunSpec):
        raise ValueError(f"spec must be a RunSpec (torch_api.RunSpec.of(...)), got {spec!r}")
    if env is None or not (isinstance(env, EnvBase) or callable(env)):
        raise ValueError(
            f"env must be a TorchRL EnvBase or a callable batch_size -> env, got {env!r}"
        )
    if selector is not None and not isinstance(selector, SamplingPolicySelector):
        raise ValueError(
            f"selector must be a SamplingPolicySelector or None, got {type(selector).__name__}"
        )
    if selector is not None and spec.selection is None:
        raise ValueError("a selector was given to a passive run (spec.selection is None)")
    trials = spec.trials.num_trials is not None
    if trials and (collector or getattr(selector, "collector", None)):
        raise ValueError("a collector (the loop's or the selector's) works without num_trials")
    if trials and isinstance(env, EnvBase):
        raise ValueError("num_trials needs env as a callable batch_size -> env (T·M_l rows)")
    if extra_candidates and (trials or spec.selection is None):
        raise ValueError(
            "extra_candidates are offered to the selector: they need active mode "
            "(spec.selection) and work without num_trials (a TorchRL actor holds one set of "
            "parameters)"
        )
    return spec
