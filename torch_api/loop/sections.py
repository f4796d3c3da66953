"""The sections of a run's specification (:class:`~torch_api.loop.spec.RunSpec`), one per
concern, each checking its own fields when it is made (a ``ValueError`` naming the field and
the value)."""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass

import torch

from torch_api._checks import HUGE_LAMBDA, _count
from torch_api._checks import _check_choice as _choice
from torch_api.core.fit import FITS
from torch_api.core.iwcv import DEFAULT_FLATTENING_GRID, DEFAULT_IWCV_FOLDS
from torch_api.core.psi import PSI_MODES
from torch_api.core.solve import DEFAULT_LAMBDA
from torch_api.policies.families import IMPROVEMENTS, PAPER_EPSILON_OFFSETS
from torch_api.policies.linear_q import TIE_BREAKS

__all__ = ["EvaluationSpec", "PolicySpec", "RewardedSpec", "SelectionSpec", "TrialSpec"]

SLICES = ("all", "episode")  # how rewarded episodes are bought
EPSILON_DECAYS = ("inverse", "constant")  # ε_l = ε / l (the paper) or ε
MAX_SEED = 2**63 - 1  # seeds are 64-bit signed integers (torch.Generator, numpy)
MAX_ROWS = 5 * 10**7  # T·ΣM·N rewarded steps a run may hold (at ~256 bytes a step: 12.8 GB)
BYTES_PER_STEP = 256  # an episode step as the buffers hold it (obs, action, probs, mask, ...)


# -- the checks of one value, each naming the field ------------------------------------------


def _check_memory(what: str, factors: tuple[int, ...]) -> None:
    """Refuse a run whose episodes could not be held in memory, before allocating."""
    steps = math.prod(factors)
    if steps > MAX_ROWS:
        raise ValueError(
            f"{what} = {' × '.join(map(str, factors))} = {steps:.3g} episode steps would take "
            f"about {steps * BYTES_PER_STEP / 2**30:.0f} GiB; a run holds at most {MAX_ROWS:.0e}"
        )


def _integer(name: str, value, minimum: int = 1, maximum: int | None = None) -> int:
    value = _count(name, value, minimum)  # an integer (2.5, True, "3" refused) >= minimum
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be <= {maximum}, got {value!r}")
    return value


def _real(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return float(value)


def _reals(name: str, values) -> tuple[float, ...]:
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}")
    return tuple(_real(f"{name}[{i}]", v) for i, v in enumerate(values))


def _set(spec, name: str, value) -> None:
    object.__setattr__(spec, name, value)  # (normalising a frozen dataclass's field)


# -- the sections ----------------------------------------------------------------------------


@dataclass(frozen=True)
class RewardedSpec:
    """The rewards bought (Algorithm 1, step 2)."""

    schedule: tuple[int, ...]
    """M_1, …, M_L: rewarded episodes bought in iteration l (L = its length)."""
    num_steps: int
    """N: steps per episode."""
    rewarded_slice: str = "all"
    """"all": an iteration's M_l episodes in one rollout and one commit (a simulator);
    "episode": one episode at a time, each committed before the next is measured (a robot)."""

    def __post_init__(self) -> None:
        if isinstance(self.schedule, (str, bytes)) or not hasattr(self.schedule, "__iter__"):
            raise ValueError(f"rewarded.schedule must be a sequence, got {self.schedule!r}")
        schedule = tuple(
            _integer(f"rewarded.schedule[{i}]", m) for i, m in enumerate(self.schedule)
        )
        if not schedule:
            raise ValueError("rewarded.schedule must not be empty")
        _set(self, "schedule", schedule)
        _set(self, "num_steps", _integer("rewarded.num_steps", self.num_steps))
        _choice("rewarded.rewarded_slice", self.rewarded_slice, SLICES)
        _check_memory("rewarded.schedule × num_steps", (sum(schedule), self.num_steps))


@dataclass(frozen=True)
class SelectionSpec:
    """Active learning: the sampling policy of each iteration chosen by J' (Algorithm 2)."""

    num_repeats: int = 5
    """Z: J' is the mean of Z values of J, each on its own reward-free episodes."""
    reward_free_episodes: int | None = None
    """Reward-free episodes per candidate and repeat (None: M_l, the paper's); the reward-free
    budget of iteration l is Z·K·(this)·N transitions per trial."""

    def __post_init__(self) -> None:
        _set(self, "num_repeats", _integer("selection.num_repeats", self.num_repeats))
        if self.reward_free_episodes is not None:
            episodes = _integer("selection.reward_free_episodes", self.reward_free_episodes)
            _set(self, "reward_free_episodes", episodes)

    def episodes_for(self, num_episodes: int) -> int:
        """Reward-free episodes per candidate and repeat in an iteration buying M_l."""
        return num_episodes if self.reward_free_episodes is None else self.reward_free_episodes


@dataclass(frozen=True)
class EvaluationSpec:
    """Policy evaluation (Algorithm 1, step 3) and the J that predicts its error."""

    gamma: float
    """γ in (0, 1]: the discount."""
    lam: float = DEFAULT_LAMBDA
    """λ > 0: the ridge of the fit and of J (eq. 22-28, 40-46)."""
    fit: str = "brm"
    """"brm" (the paper: least squares of r on psi_hat) or "lstd" (LSTD-Q, beyond the paper)."""
    psi_mode: str = "single"
    """psi_hat of eq. 20: "grouped" (finite states), "single" (continuous) or "knn"."""
    knn_k: int = 5
    """k of psi_mode="knn"."""
    flattening: float | str = 1.0
    """ν of the flattened weights w^ν: 1.0 (the paper's), a ν in [0, 1], or "iwcv"."""
    flattening_grid: tuple[float, ...] = DEFAULT_FLATTENING_GRID
    """the ν tried by flattening="iwcv"."""
    iwcv_folds: int = DEFAULT_IWCV_FOLDS
    """folds of flattening="iwcv"."""

    def __post_init__(self) -> None:
        gamma = _real("evaluation.gamma", self.gamma)
        if not 0 < gamma <= 1:
            raise ValueError(f"evaluation.gamma must lie in (0, 1], got {self.gamma!r}")
        _set(self, "gamma", gamma)
        lam = _real("evaluation.lam", self.lam)
        if not 1e-10 <= lam:
            raise ValueError(
                f"evaluation.lam must be >= 1e-10 (a smaller ridge is lost in rounding), got "
                f"{self.lam!r}"
            )
        _set(self, "lam", lam)
        if lam > HUGE_LAMBDA:
            warnings.warn(
                f"evaluation.lam = {lam:g} is huge: the ridge penalty dominates every design and "
                "θ shrinks to about 0 whatever the rewards",
                RuntimeWarning,
                stacklevel=3,
            )
        _choice("evaluation.fit", self.fit, FITS)
        _choice("evaluation.psi_mode", self.psi_mode, PSI_MODES)
        if self.fit == "lstd" and self.psi_mode != "single":
            raise ValueError(
                f"evaluation.fit='lstd' needs evaluation.psi_mode='single', got {self.psi_mode!r}"
            )
        _set(self, "knn_k", _integer("evaluation.knn_k", self.knn_k))
        if self.flattening != "iwcv":
            nu = _real("evaluation.flattening", self.flattening)
            if not 0 <= nu <= 1:
                raise ValueError(
                    "evaluation.flattening must be 'iwcv' or lie in [0, 1], got "
                    f"{self.flattening!r}"
                )
            _set(self, "flattening", nu)
        grid = _reals("evaluation.flattening_grid", self.flattening_grid)
        if not grid or not all(0 <= nu <= 1 for nu in grid):
            raise ValueError(
                f"evaluation.flattening_grid must be values in [0, 1], got {list(grid)}"
            )
        _set(self, "flattening_grid", grid)
        _set(self, "iwcv_folds", _integer("evaluation.iwcv_folds", self.iwcv_folds, minimum=2))


@dataclass(frozen=True)
class PolicySpec:
    """Policy improvement (Algorithm 1, step 4) and the candidates of eq. 59."""

    improvement: str = "epsilon_greedy"
    """"epsilon_greedy" (the paper, eq. 57-58) or "softmax" (eq. 7, temperature ``beta``)."""
    epsilon: float = 0.15
    """ε of pi_1; ε_l = ε / l with epsilon_decay="inverse" (the paper), ε with "constant"."""
    epsilon_decay: str = "inverse"
    """how ε_l follows from ε: "inverse" (ε / l) or "constant"."""
    candidate_offsets: tuple[float, ...] = PAPER_EPSILON_OFFSETS
    """the sampling candidates' ε_l + offset (eq. 59); the first is pi_l's own."""
    beta: float | None = None
    """β of improvement="softmax" (its candidates: β × 1, 2, 5, 20)."""
    tie_break: str = "uniform"
    """how ε-greedy shares the greedy mass among tied actions: "uniform" or "lowest"."""
    initial_theta: float | tuple[float, ...] = 1.0
    """θ_0 of pi_1: one value for every entry (1.0: Q̂_0 = Σ_b phi_b, eq. 58, 67) or B values."""

    def __post_init__(self) -> None:
        _choice("policy.improvement", self.improvement, IMPROVEMENTS)
        epsilon = _real("policy.epsilon", self.epsilon)
        if not 0 <= epsilon <= 1:
            raise ValueError(f"policy.epsilon must lie in [0, 1], got {self.epsilon!r}")
        _set(self, "epsilon", epsilon)
        _choice("policy.epsilon_decay", self.epsilon_decay, EPSILON_DECAYS)
        offsets = _reals("policy.candidate_offsets", self.candidate_offsets)
        if not offsets:
            raise ValueError("policy.candidate_offsets must not be empty")
        _set(self, "candidate_offsets", offsets)
        if self.improvement == "softmax":
            beta = None if self.beta is None else _real("policy.beta", self.beta)
            if beta is None or beta <= 0:
                raise ValueError(f"policy.improvement='softmax' needs policy.beta > 0, got {beta}")
            _set(self, "beta", beta)
        elif self.beta is not None:
            raise ValueError(
                f"policy.beta applies to improvement='softmax', got beta={self.beta!r} with "
                f"{self.improvement!r}"
            )
        _choice("policy.tie_break", self.tie_break, TIE_BREAKS)
        if isinstance(self.initial_theta, numbers.Real) and not isinstance(
            self.initial_theta, bool
        ):
            _set(self, "initial_theta", _real("policy.initial_theta", self.initial_theta))
        else:
            _set(self, "initial_theta", _reals("policy.initial_theta", self.initial_theta))

    def epsilon_of(self, iteration: int) -> float:
        """ε_l of pi_l (iteration l, 1-based)."""
        return self.epsilon / iteration if self.epsilon_decay == "inverse" else self.epsilon

    def theta_0(self, width: int) -> torch.Tensor:
        """θ_0 as float64 ``[B]``."""
        if isinstance(self.initial_theta, float):
            return torch.full((width,), self.initial_theta, dtype=torch.float64)
        if len(self.initial_theta) != width:
            raise ValueError(
                f"policy.initial_theta has {len(self.initial_theta)} values; the basis has "
                f"B = {width} features"
            )
        return torch.tensor(self.initial_theta, dtype=torch.float64)


@dataclass(frozen=True)
class TrialSpec:
    """The trials and the run's random streams (docs/random_streams.md)."""

    num_trials: int | None = None
    """T independent trials run as one batch (None: a single run, θ ``[B]``)."""
    seed: int = 0
    """the run's seed: every stream of iteration l comes from (seed, l, role)."""
    trial_seeds: tuple[int, ...] | None = None
    """one seed per trial: T batched trials give the numbers of T runs of one trial each."""

    def __post_init__(self) -> None:
        if self.num_trials is not None:
            _set(self, "num_trials", _integer("trials.num_trials", self.num_trials))
        _set(self, "seed", _integer("trials.seed", self.seed, minimum=0, maximum=MAX_SEED))
        if self.trial_seeds is not None:
            if isinstance(self.trial_seeds, (str, bytes)) or not hasattr(
                self.trial_seeds, "__iter__"
            ):
                raise ValueError(f"trials.trial_seeds must be a sequence, got {self.trial_seeds!r}")
            seeds = tuple(
                _integer(f"trials.trial_seeds[{i}]", s, minimum=0, maximum=MAX_SEED)
                for i, s in enumerate(self.trial_seeds)
            )
            if self.num_trials is None or len(seeds) != self.num_trials:
                raise ValueError(
                    f"trials.trial_seeds needs one seed per trial: {len(seeds)} seeds for "
                    f"num_trials={self.num_trials}"
                )
            _set(self, "trial_seeds", seeds)
