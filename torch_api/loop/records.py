"""What an iteration of Algorithm 1 leaves: its :class:`Choice`, its :class:`IterationRecord`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import torch

__all__ = ["Choice", "IterationRecord", "per_trial_count"]


@dataclass
class Choice:
    """Step 1's outcome for iteration l: the sampling policy chosen, committed before its rewards.

    Attributes:
        chosen: the candidate's index, long ``[*T]`` (0: pi_l itself; always 0 when passive).
        sampling_rule: its ε (or β) ``[*T]``, or None for one of the user's own candidates.
        j_mean: J' ``[*T][K]`` (active), else None; j_all: J ``[*T][Z][K]``, else None.
        reward_free_transitions: reward-free transitions collected for it, per trial ``[*T]``
            (an int without trial dims; runs stored before it was per trial hold the total of
            all trials, :func:`per_trial_count`).
        seconds: wall time of the choice.
        cpu_seconds: CPU time of this process spent on the choice (the reward-free collection
            and J; worker processes' time not included), or None in runs stored before it.
    """

    chosen: torch.Tensor
    sampling_rule: torch.Tensor | None
    j_mean: list | None
    j_all: list | None
    reward_free_transitions: int | list
    seconds: float
    cpu_seconds: float | None = None

    def row(self) -> dict:
        """The choice as the store keeps it (JSON-able)."""
        return {
            f.name: v.tolist() if isinstance(v := getattr(self, f.name), torch.Tensor) else v
            for f in fields(self)
        }

    @classmethod
    def from_row(cls, row: dict) -> Choice:
        """The choice of a stored row (:meth:`row`)."""
        rule = row["sampling_rule"]  # (None: an extra candidate)
        return cls(
            **{
                **row,
                "chosen": torch.tensor(row["chosen"], dtype=torch.long),
                "sampling_rule": None if rule is None else torch.tensor(rule, dtype=torch.float64),
            }
        )


@dataclass
class IterationRecord:
    """What happened in one iteration l (1-based) of Algorithm 1.

    Attributes:
        iteration: l.
        chosen: index of the sampling-policy candidate used (0 = the evaluation policy itself;
            always 0 in passive mode); a list over trials when run with ``num_trials``.
        sampling_rule: ε (or β) of the sampling policy used (per trial with ``num_trials``).
        j_mean: J' of every candidate ``[*T][K]`` (active mode), else None.
        j_all: J of every repeat and candidate ``[*T][Z][K]`` (active mode), else None.
        episodes_bought: rewarded episodes collected in this iteration (per trial).
        rewarded_transitions: rewarded transitions bought so far (cumulative), each trial's
            own ``[*T]`` (episodes may end early; an int without trial dims).
        reward_free_transitions: reward-free transitions collected so far (cumulative), each
            trial's own, as ``rewarded_transitions``.
        performance: what the ``evaluate`` callback returned for pi_{l+1}, or None.
        seconds: wall time of the iteration (evaluation callback excluded).
        selection_cpu_seconds: CPU time of step 1 (reward-free collection and J; 0 when passive).
        theta: θ_l ``[*T][B]``.
        flattening: ν of the fit's flattened weights ``w^ν`` (per trial with ``num_trials``;
            chosen by IWCV with ``flattening="iwcv"``); None in runs stored before it existed.
        effective_sample_size: Kish's ``(Σ w^ν)² / Σ w^{2ν}`` of the fit's weights over all
            rewarded samples so far (per trial), beside ``rewarded_transitions``.
    """

    iteration: int
    chosen: int | list
    sampling_rule: float | list
    j_mean: list | None
    j_all: list | None
    episodes_bought: int
    rewarded_transitions: int | list
    reward_free_transitions: int | list
    performance: dict | None
    seconds: float
    theta: list = field(repr=False)
    flattening: float | list | None = None
    effective_sample_size: float | list | None = None
    selection_cpu_seconds: float | None = None

    @classmethod
    def of(cls, iteration: int, choice: Choice, fitted, **numbers) -> IterationRecord:
        """The record of iteration l from its :class:`Choice`, its fit
        (:class:`~torch_api.core.fit.Fit`) and the loop's counts (``numbers``)."""
        rule = choice.sampling_rule
        return cls(
            iteration=iteration,
            chosen=choice.chosen.tolist(),
            sampling_rule=None if rule is None else rule.tolist(),
            j_mean=choice.j_mean,
            j_all=choice.j_all,
            theta=fitted.theta.cpu().tolist(),
            flattening=fitted.flattening.tolist(),
            effective_sample_size=fitted.ess.tolist(),
            selection_cpu_seconds=choice.cpu_seconds,
            **numbers,
        )

    def summary(self, iterations: int) -> str:
        """One log line: the iteration, its time, the rewards bought, ν and the ESS."""
        nu, ess = (
            "-" if v is None else _brief(torch.tensor(v))
            for v in (self.flattening, self.effective_sample_size)
        )
        bought = _brief(torch.tensor(self.rewarded_transitions))
        return (
            f"iteration {self.iteration}/{iterations} done in {self.seconds:.2f} s: "
            f"{bought} rewarded transitions per trial bought so far, "
            f"flattening ν {nu}, effective sample size {ess}"
        )

    def row(self) -> dict:
        """The iteration's numbers as one flat dict for JSON/CSV (θ and per-repeat J left out)."""
        return {
            "iteration": self.iteration,
            "episodes_bought": self.episodes_bought,
            "rewarded_transitions": self.rewarded_transitions,
            "reward_free_transitions": self.reward_free_transitions,
            "chosen": self.chosen,
            "sampling_rule": self.sampling_rule,
            "j_mean": self.j_mean,
            "flattening": self.flattening,
            "effective_sample_size": self.effective_sample_size,
            "seconds": self.seconds,
            "selection_cpu_seconds": self.selection_cpu_seconds,
            **(self.performance or {}),
        }


def _brief(values: torch.Tensor) -> str:
    """Per-trial numbers as one short string for a log line (the value, or mean and range)."""
    flat = values.reshape(-1).to(torch.float64)
    if flat.numel() == 1:
        return f"{flat.item():.3g}"
    return f"mean {flat.mean().item():.3g} [{flat.min().item():.3g}, {flat.max().item():.3g}]"


def per_trial_count(count: int | list, trial_dims: tuple[int, ...]) -> torch.Tensor:
    """A stored transition count as one count per trial, long ``[*T]``: a list is each trial's
    own; an int with trial dims is the total of all trials that runs stored before the counts
    were per trial hold (read back as its even share, what those runs reported)."""
    if isinstance(count, list) or not trial_dims:
        return torch.tensor(count, dtype=torch.long)
    return torch.full(trial_dims, int(count) // math.prod(trial_dims), dtype=torch.long)
