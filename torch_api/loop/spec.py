"""The specification of a run: every setting that gives a run's numbers their meaning, in one place.

A :class:`RunSpec` is frozen and typed, made of one section per concern:

==================  =========================================================================
section             settings
==================  =========================================================================
``rewarded``        the rewards bought: schedule ``(M_1, …, M_L)``, N, how they are sliced
``selection``       active learning (Algorithm 2): Z, the reward-free budget; None: passive
``evaluation``      policy evaluation (step 3): γ, λ, BRM or LSTD-Q, psi_hat, flattening ν
``policy``          policy improvement (step 4): ε-greedy or softmax, ε_l, ties, θ_0, eq. 59
``trials``          T trials, the run's seed, per-trial seeds
==================  =========================================================================

It is checked once, when it is made (a ``ValueError`` naming the field and the value), stored
with a run as JSON (:meth:`RunSpec.to_dict`, :meth:`RunSpec.from_dict`) and is the run's
identity with the env's and basis's parameters (:func:`~torch_api.loop.identity.run_identity`):
a stored run resumes only under the same specification, env parameters and basis. A new
option is a new field of one section (:mod:`torch_api.loop.sections`): its check, its JSON and
its place in the identity follow from the field.

Example:
    >>> spec = RunSpec.of(schedule=(5, 5, 3), num_steps=10, gamma=0.9, num_repeats=5)
    >>> spec.selection.num_repeats, spec.evaluation.lam, spec.mode
    (5, 0.001, 'active')
    >>> RunSpec.from_dict(spec.to_dict()) == spec
    True
    >>> RunSpec.of(schedule=(5,), num_steps=10, gamma=1.5)
    Traceback (most recent call last):
    ...
    ValueError: evaluation.gamma must lie in (0, 1], got 1.5
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field, fields
from typing import Any

from torch_api.loop.sections import (
    EvaluationSpec,
    PolicySpec,
    RewardedSpec,
    SelectionSpec,
    TrialSpec,
    _check_memory,
    _choice,
)

__all__ = [
    "EvaluationSpec",
    "PolicySpec",
    "RewardedSpec",
    "RunSpec",
    "SelectionSpec",
    "TrialSpec",
]

_SECTIONS = {
    "rewarded": RewardedSpec,
    "selection": SelectionSpec,
    "evaluation": EvaluationSpec,
    "policy": PolicySpec,
    "trials": TrialSpec,
}


@dataclass(frozen=True)
class RunSpec:
    """Every setting of a run of active (or passive) policy iteration; see the module.

    Make it section by section, or from flat keywords with :meth:`of` (each field's name is
    unique across sections). ``selection=None`` is the passive baseline (pi_l samples).
    """

    rewarded: RewardedSpec
    evaluation: EvaluationSpec
    selection: SelectionSpec | None = field(default_factory=SelectionSpec)
    policy: PolicySpec = field(default_factory=PolicySpec)
    trials: TrialSpec = field(default_factory=TrialSpec)
    keep_reward_free: bool = True
    """keep the selector's reward-free episodes (``api.reward_free``, the store)."""

    def __post_init__(self) -> None:
        for name, kind in _SECTIONS.items():
            value = getattr(self, name)
            if not (isinstance(value, kind) or (name == "selection" and value is None)):
                raise ValueError(f"{name} must be a {kind.__name__}, got {value!r}")
        if not isinstance(self.keep_reward_free, bool):
            raise ValueError(
                f"keep_reward_free must be True or False, got {self.keep_reward_free!r}"
            )
        trials = self.trials.num_trials or 1
        _check_memory(
            "trials.num_trials × Σ rewarded.schedule × num_steps",
            (trials, sum(self.rewarded.schedule), self.rewarded.num_steps),
        )
        if self.selection is not None:  # one iteration's reward-free episodes, Z·K·M·N a trial
            _check_memory(
                "trials.num_trials × selection.num_repeats × candidates × reward-free episodes "
                "× num_steps",
                (
                    trials,
                    self.selection.num_repeats,
                    len(self.policy.candidate_offsets),
                    max(map(self.selection.episodes_for, self.rewarded.schedule)),
                    self.rewarded.num_steps,
                ),
            )

    @property
    def mode(self) -> str:
        """ "active" (a selection) or "passive"."""
        return "passive" if self.selection is None else "active"

    @property
    def num_iterations(self) -> int:
        """L, the schedule's length."""
        return len(self.rewarded.schedule)

    @classmethod
    def of(cls, *, mode: str = "active", keep_reward_free: bool = True, **settings) -> RunSpec:
        """A specification from flat keywords, each the name of one section's field.

        ``mode="passive"`` leaves out the selection (its fields are then refused).

        >>> RunSpec.of(schedule=(3,), num_steps=5, gamma=1.0, mode="passive").selection is None
        True
        """
        _choice("mode", mode, ("active", "passive"))
        owner = {f.name: name for name, kind in _SECTIONS.items() for f in fields(kind)}
        unknown = sorted(set(settings) - set(owner))
        if unknown:
            raise ValueError(f"unknown settings {unknown}; the settings are {sorted(owner)}")
        parts: dict[str, dict] = {name: {} for name in _SECTIONS}
        for key, value in settings.items():
            parts[owner[key]][key] = value
        if mode == "passive" and parts["selection"]:
            raise ValueError(
                f"{sorted(parts['selection'])} are settings of active learning, given with "
                "mode='passive'"
            )
        made = {
            name: kind(**parts[name]) for name, kind in _SECTIONS.items() if name != "selection"
        }
        selection = None if mode == "passive" else SelectionSpec(**parts["selection"])
        return cls(**made, selection=selection, keep_reward_free=keep_reward_free)

    def replace(self, **settings) -> RunSpec:
        """This specification with some flat settings changed (``mode`` too)."""
        flat = self.flat()
        mode = settings.pop("mode", self.mode)
        if mode == "passive":
            for f in fields(SelectionSpec):
                flat.pop(f.name, None)
        return RunSpec.of(mode=mode, **(flat | settings))

    def flat(self) -> dict[str, Any]:
        """The settings as flat keywords (:meth:`of` makes this specification of them)."""
        out: dict[str, Any] = {"keep_reward_free": self.keep_reward_free}
        for name in _SECTIONS:
            section = getattr(self, name)
            if section is not None:
                out |= {f.name: getattr(section, f.name) for f in fields(section)}
        return out

    def to_dict(self) -> dict:
        """The specification as JSON-able nested dicts (tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self), allow_nan=False))

    @classmethod
    def from_dict(cls, data: dict) -> RunSpec:
        """The specification of :meth:`to_dict`'s dict (checked as when it was made)."""
        if not isinstance(data, dict):
            raise ValueError(f"a run specification is a dict, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_SECTIONS) - {"keep_reward_free"})
        if unknown:
            raise ValueError(f"unknown sections {unknown} in a run specification")

        def section(name: str, kind):
            part = data.get(name)
            if part is None:
                return None
            bad = sorted(set(part) - {f.name for f in fields(kind)})
            if bad:
                raise ValueError(f"unknown settings {bad} in section {name!r}")
            return kind(**{k: tuple(v) if isinstance(v, list) else v for k, v in part.items()})

        made = {name: section(name, kind) for name, kind in _SECTIONS.items()}
        return cls(**made, keep_reward_free=data.get("keep_reward_free", True))
