"""Active policy iteration and its passive baseline (paper section 4.1, Algorithm 1)."""

from __future__ import annotations

import hashlib
import logging
import math
import numbers
import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs import EnvBase
from tqdm import tqdm

from torch_api.actions import ActionEncoding
from torch_api.data import (
    EnvPerBatch,
    EpisodeBuffer,
    collect_episodes,
    collect_with_collector,
    seed_env,
    validate_episodes,
)
from torch_api.design import build_design
from torch_api.lstd import phi_rows, weighted_lstd
from torch_api.policies import TIE_BREAKS, LinearQPolicy
from torch_api.psi import PSI_MODES, PsiHat
from torch_api.selector import (
    FITS,
    PAPER_EPSILON_OFFSETS,
    SamplingPolicySelector,
    candidate_epsilons,
)
from torch_api.solve import DEFAULT_LAMBDA, weighted_ridge
from torch_api.store import CorruptRunError, RunStore, StoredRun

__all__ = ["ActivePolicyIteration", "IterationRecord", "derive_seed", "paper_epsilon"]

_log = logging.getLogger(__name__)
_STREAMS = {
    "policy": 0,
    "reward_free_env": 1,
    "rewarded_env": 2,
    "evaluation": 3,
    "trial": 4,
    "reward_free_policy": 5,
}
_SLICE_STREAMS = {"policy": 6, "rewarded_env": 7}  # per-episode slices (rewarded_slice="episode")
SLICES = ("all", "episode")
HUGE_LAMBDA = 1e6  # λ above this shrinks θ towards 0 whatever the data: warned about

MODES = ("active", "passive")
IMPROVEMENTS = ("epsilon_greedy", "softmax")
SOFTMAX_CANDIDATE_SCALES = (1.0, 2.0, 5.0, 20.0)  # softmax candidates: β times these


def paper_epsilon(iteration: int) -> float:
    """ε of the evaluation policy of iteration l (1-based): ``0.15 / l`` (paper sections 4.2, 5)."""
    return 0.15 / iteration


def derive_seed(seed: int, iteration: int, stream: str) -> int:
    """Independent seed of one random stream of one iteration (NumPy ``SeedSequence``).

    Every iteration re-seeds its streams from ``(seed, iteration, stream)``, so an interrupted
    run resumed from a checkpoint draws exactly the numbers an uninterrupted run would have.
    """
    entropy = [int(seed) & 0xFFFFFFFF, int(iteration), _STREAMS[stream]]
    return int(np.random.SeedSequence(entropy).generate_state(1, dtype=np.uint64)[0] >> 1)


def _check_lambda(lam: float) -> None:
    """λ must be a finite number > 0; a huge one (θ shrunk to about 0) is warned about."""
    if not (isinstance(lam, numbers.Real) and lam > 0):
        raise ValueError(f"lam must be > 0, got {lam}")
    if not math.isfinite(lam):
        raise ValueError(f"lam must be finite, got {lam}")
    if lam > HUGE_LAMBDA:
        warnings.warn(
            f"lam = {lam:g} is huge: the ridge penalty dominates every design and θ shrinks to "
            "about 0 whatever the rewards",
            RuntimeWarning,
            stacklevel=3,
        )


def slice_seed(seed: int, iteration: int, episode: int, stream: str) -> int:
    """Seed of one stream of rewarded episode m (0-based) of iteration l, for runs that buy
    one episode at a time (``rewarded_slice="episode"``): a resume continues at any episode."""
    entropy = [int(seed) & 0xFFFFFFFF, int(iteration), _SLICE_STREAMS[stream], int(episode)]
    return int(np.random.SeedSequence(entropy).generate_state(1, dtype=np.uint64)[0] >> 1)


def _count(name: str, value, minimum: int = 1) -> int:
    """``value`` as an int >= minimum; a non-integer (2.5, True, "3") is refused."""
    integral = isinstance(value, numbers.Integral) or (
        isinstance(value, float) and value.is_integer()
    )
    if isinstance(value, bool) or not integral:
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return int(value)


def _plain(value):
    """A JSON-able, exact description of a setting's value (tensors by digest)."""
    if isinstance(value, torch.Tensor):
        data = value.detach().cpu().contiguous()
        digest = hashlib.sha256(data.view(torch.uint8).numpy().tobytes()).hexdigest()
        return {"dtype": str(data.dtype), "shape": list(data.shape), "sha256": digest}
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, (tuple, list)) and all(
        isinstance(v, (bool, int, float, str)) for v in value
    ):
        return [_plain(v) for v in value]
    return None  # not a plain setting: left out


_NOT_IDENTITY = {"batch_size", "seed", "rng", "device", "training", "num_envs", "nthread"}


def fingerprint(obj) -> dict:
    """What identifies an environment or a basis: its class, the tensors of its state and its
    public plain attributes (numbers, strings, tensors), batch size, seeds and device left out.
    """
    out = {"class": f"{type(obj).__module__}.{type(obj).__qualname__}"}
    if isinstance(obj, nn.Module):
        out |= {f"state.{k}": _plain(v) for k, v in obj.state_dict().items()}
    for name, value in sorted(vars(obj).items()):
        if name.startswith("_") or name in _NOT_IDENTITY:
            continue
        plain = _plain(value)
        if plain is not None:
            out[name] = plain
    return out


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
        rewarded_transitions: rewarded transitions bought so far (cumulative, per trial).
        reward_free_transitions: reward-free transitions collected so far (cumulative, per
            trial).
        performance: what the ``evaluate`` callback returned for pi_{l+1}, or None.
        seconds: wall time of the iteration (evaluation callback excluded).
        theta: θ_l ``[*T][B]``.
    """

    iteration: int
    chosen: int | list
    sampling_rule: float | list
    j_mean: list | None
    j_all: list | None
    episodes_bought: int
    rewarded_transitions: int
    reward_free_transitions: int
    performance: dict | None
    seconds: float
    theta: list = field(repr=False)

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
            "seconds": self.seconds,
            **(self.performance or {}),
        }


class ActivePolicyIteration:
    """Sample-reuse least-squares policy iteration with active sampling-policy selection.

    Algorithm 1 of Akiyama, Hachiya & Sugiyama (2010). In iteration l = 1 … L:

    1. the sampling policy is the J'-chosen candidate (``mode="active"``, Algorithm 2, through
       :class:`~torch_api.selector.SamplingPolicySelector`) or pi_l itself (``"passive"``);
    2. ``schedule[l-1]`` rewarded episodes of N steps are bought with it and stored;
    3. θ_l is fitted on ALL rewarded episodes so far (sample reuse, eq. 56), psi_hat on that
       union with pi_l and importance weights towards pi_l;
    4. pi_{l+1} is the ε-greedy (ε = ``epsilon_schedule(l+1)``) or softmax policy of θ_lᵀphi.

    Works with any TorchRL environment with discrete actions (categorical or one-hot) and any
    basis module with ``phi``/``phi_all``/``num_features``/``num_actions``.

    With ``num_trials = T`` it runs T independent trials as one batched computation: θ
    ``[T, B]``, episodes ``[T, M, N]``, J ``[T, Z, K]``, one candidate chosen per trial.

    Args:
        env: the environment whose rewards are bought: a TorchRL ``EnvBase``, or a callable
            ``batch_size -> env`` (required with ``num_trials``: batches of ``T·M_l``).
        basis: the basis module (e.g. :class:`~torch_api.basis.GaussianActionBasis`).
        schedule: episodes bought per iteration ``(M_1, …, M_L)``, each ≥ 1.
        num_steps: N, steps per episode.
        gamma: discount γ in (0, 1].
        mode: ``"active"`` or ``"passive"``.
        lam: λ > 0.
        num_repeats: Z for J'.
        reward_free_env: environment for the selector's reward-free rollouts, or a callable
            ``batch_size -> env`` (give one whose batch is ``Z·K·M_l`` for speed). Default: env.
        psi_mode: ``"grouped"`` (finite states), ``"single"`` (the paper's continuous choice)
            or ``"knn"``; ``knn_k`` its k.
        initial_theta: θ_0 of pi_1 (default all ones: ``Q̂_0 = Σ_b phi_b``, eq. 58, 67).
        epsilon_schedule: ε of pi_l as a function of l (default ``0.15 / l``).
        candidate_offsets: candidates ε_l + offset (eq. 59).
        improvement: ``"epsilon_greedy"`` (the paper) or ``"softmax"`` (eq. 7; pi_l uses
            ``beta`` and the candidates β times ``SOFTMAX_CANDIDATE_SCALES``).
        beta: softmax temperature.
        tie_break: how the ε-greedy policies share the greedy mass among actions whose Q̂ ties
            for the maximum: ``"uniform"`` (equal parts: pi_1 of θ_0 = 1, and any pi_l of
            θ = 0 after rewards that were all zero, is uniform) or ``"lowest"`` (all to the
            lowest action index). See :func:`~torch_api.policies.greedy_probs`.
        evaluate: optional callback ``(policy, seed) -> dict`` measuring pi_{l+1} after every
            iteration. The policy samples from streams seeded from (seed, l) (one per trial with
            ``trial_seeds``); ``seed`` is derived from (seed, l) too, for the callback's own
            environment (with ``set_block_seeds``, ``api.block_seeds(l, "evaluation")`` gives
            per-trial seeds). A resumed run then measures exactly as an uninterrupted one.
        num_trials: T, independent trials run side by side (None: a single run, θ ``[B]``).
        seed: seed of the run. Each iteration re-seeds the policies' stream and the
            environments (``env.set_seed``) from ``(seed, l)`` (:func:`derive_seed`); runs with
            the same seed in active and passive mode share the rewarded environments' streams
            and the sampling streams of the rewarded episodes (a paired design): the reward-free
            rollouts of the active mode draw their actions from streams of their own
            (``"reward_free_policy"``), so the pair differs only by the sampling policy.
        trial_seeds: with ``num_trials``, one seed per trial (default: derived from ``seed``).
            Each trial then draws from streams of its own, seeded from ``(trial_seed, l)``: the
            policies' sampling and, for environments with ``set_block_seeds`` (this project's
            envs), the environments' rows of that trial. A batched run of T trials then gives
            the numbers of T runs with ``num_trials=1, trial_seeds=[s_t]``.
        keep_reward_free: store the selector's reward-free episodes in ``reward_free``.
        checkpoint_path: if set, the run is stored there (:class:`~torch_api.store.RunStore`,
            an SQLite database): each slice of rewarded episodes is committed (fsynced,
            checksummed) before the next is measured, the selection before the rewards it
            buys, every completed iteration's record (θ_l) after it. The place is opened, locked
            against other writers and checked writable here, before anything is bought.
        resume: continue the run stored at ``checkpoint_path`` (built with the same settings:
            everything that gives the stored data its meaning must match, while ``lam``,
            ``device``, ``reward_free_workers`` and ``evaluate`` may change). Only missing
            rewarded episodes are bought, with the uninterrupted run's random streams. A
            missing run starts fresh (``resumed`` is then False).
        overwrite: discard a run stored at ``checkpoint_path``. Without ``resume`` or
            ``overwrite`` an existing run is refused (``RunExistsError``), never replaced.
        rewarded_slice: how rewarded episodes are bought and committed: ``"all"`` (a
            simulator: all M_l rows of an iteration in one rollout, one commit) or
            ``"episode"`` (a robot: one episode index at a time, each committed before the next
            is measured, each with random streams of its own from (seed, l, m)).
        device: where psi_hat, J and the solves run (e.g. ``"cuda"``). The rollouts stay on
            the environments' device (the policies' θ follows the observations) and the
            episode buffers are held on the CPU. Default: CPU.
        reward_free_workers: if > 0, the reward-free episodes are collected in this many worker
            processes by TorchRL's ``MultiSyncCollector``
            (:func:`~torch_api.multiprocess.collect_episodes_in_workers`); ``reward_free_env``
            must then be a picklable callable ``batch_size -> env``.
        fit: ``"brm"`` (the paper: θ by weighted least squares of r on psi_hat, eq. 22-28) or
            ``"lstd"`` (beyond the paper: LSTD-Q, :mod:`torch_api.lstd`, with J of the same
            learner; needs ``psi_mode="single"``).
        initial_episodes: a warm start: rewarded episodes already bought (with any sampling
            policy that recorded its probabilities), stored first in ``api.rewarded`` and used
            by every fit and as earlier sampling sets. TorchRL data as TorchRL produces it (a
            ``Collector``'s batch, or a list of consecutive batches whose cut trajectories are
            joined; ``env.rollout`` output) or the library's format
            (:meth:`~torch_api.data.EpisodeBuffer.extend`). With ``num_trials`` every trial
            starts from the same episodes.
        collector: optional factory ``(policy, num_episodes) -> Collector`` of the user's own
            (a TorchRL ``Collector`` yielding whole trajectories of at most N steps, e.g.
            ``trajs_per_batch=num_episodes, traj_format="padded"`` on an env with
            ``StepCounter(max_steps=N)``): the rewarded and the reward-free episodes are then
            read from it (:func:`~torch_api.data.collect_with_collector`) instead of from
            ``env.rollout`` (the default; faster on batched envs). The collector's env is then
            seeded by the user, not by ``seed``; ``env`` still names the env (its action
            encoding). Not with ``num_trials``.

    Example:
        >>> from envs.chain_walk import ChainWalkEnv, CENTERS, TAU
        >>> from torch_api.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU,
        ...                             num_actions=2)
        >>> api = ActivePolicyIteration(
        ...     env=ChainWalkEnv(batch_size=5, seed=0), basis=basis, schedule=(5, 3),
        ...     num_steps=10, gamma=0.9, psi_mode="grouped",
        ...     reward_free_env=lambda e: ChainWalkEnv(batch_size=e, seed=1))
        >>> history = api.run()
        >>> len(history), api.rewarded_transitions
        (2, 80)
    """

    def __init__(
        self,
        *,
        env: EnvBase | Callable[[int], EnvBase],
        basis: nn.Module,
        schedule: Sequence[int],
        num_steps: int,
        gamma: float,
        mode: str = "active",
        lam: float = DEFAULT_LAMBDA,
        num_repeats: int = 5,
        reward_free_env: EnvBase | Callable[[int], EnvBase] | None = None,
        psi_mode: str = "single",
        knn_k: int = 5,
        initial_theta: torch.Tensor | None = None,
        epsilon_schedule: Callable[[int], float] = paper_epsilon,
        candidate_offsets: Sequence[float] = PAPER_EPSILON_OFFSETS,
        improvement: str = "epsilon_greedy",
        beta: float | None = None,
        tie_break: str = "uniform",
        evaluate: Callable[[LinearQPolicy, int], dict] | None = None,
        num_trials: int | None = None,
        seed: int = 0,
        trial_seeds: Sequence[int] | None = None,
        keep_reward_free: bool = True,
        checkpoint_path: str | os.PathLike | None = None,
        device: torch.device | str | None = None,
        reward_free_workers: int = 0,
        resume: bool = False,
        overwrite: bool = False,
        rewarded_slice: str = "all",
        fit: str = "brm",
        initial_episodes: TensorDictBase | Sequence[TensorDictBase] | None = None,
        collector: Callable | None = None,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if improvement not in IMPROVEMENTS:
            raise ValueError(f"improvement must be one of {IMPROVEMENTS}, got {improvement!r}")
        if tie_break not in TIE_BREAKS:
            raise ValueError(f"tie_break must be one of {TIE_BREAKS}, got {tie_break!r}")
        if improvement == "softmax" and not (beta is not None and beta > 0):
            raise ValueError(f"improvement='softmax' needs beta > 0, got beta={beta}")
        if not schedule or not all(
            isinstance(m, numbers.Integral)
            and not isinstance(m, bool)
            and m >= 1
            or isinstance(m, float)
            and m.is_integer()
            and m >= 1
            for m in schedule
        ):
            raise ValueError(
                "schedule must be a non-empty list of integer episode counts >= 1, "
                f"got {list(schedule)}"
            )
        schedule = [int(m) for m in schedule]
        num_steps = _count("num_steps", num_steps)
        num_repeats = _count("num_repeats", num_repeats)
        knn_k = _count("knn_k", knn_k)
        reward_free_workers = _count("reward_free_workers", reward_free_workers, 0)
        if num_trials is not None:
            num_trials = _count("num_trials", num_trials)
        if not 0 < gamma <= 1:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        _check_lambda(lam)
        if rewarded_slice not in SLICES:
            raise ValueError(f"rewarded_slice must be one of {SLICES}, got {rewarded_slice!r}")
        if (resume or overwrite) and checkpoint_path is None:
            raise ValueError("resume and overwrite need a checkpoint_path")
        if psi_mode not in PSI_MODES:
            raise ValueError(f"psi_mode must be one of {PSI_MODES}, got {psi_mode!r}")
        if not candidate_offsets:
            raise ValueError("candidate_offsets must not be empty")
        if collector is not None and (num_trials is not None or reward_free_workers):
            raise ValueError("collector works without num_trials and reward_free_workers")
        self.collector = collector
        if num_trials is not None and isinstance(env, EnvBase):
            raise ValueError("num_trials needs env as a callable batch_size -> env (T·M_l rows)")
        self.env = env
        self._env_for = EnvPerBatch(env)
        self.num_trials = num_trials
        self.trial_dims = () if num_trials is None else (int(num_trials),)
        self.basis = basis
        self.schedule = schedule
        self.num_steps = int(num_steps)
        self.gamma = float(gamma)
        self.mode = mode
        self.lam = float(lam)
        self.num_repeats = int(num_repeats)
        self.epsilon_schedule = epsilon_schedule
        self.candidate_offsets = tuple(candidate_offsets)
        self.improvement = improvement
        self.beta = beta
        self.tie_break = tie_break
        if fit not in FITS:
            raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
        if fit == "lstd" and psi_mode != "single":
            raise ValueError(f"fit='lstd' needs psi_mode='single', got {psi_mode!r}")
        self.fit = fit
        self.evaluate = evaluate
        self.seed = int(seed)
        if num_trials is None and trial_seeds is not None:
            raise ValueError("trial_seeds needs num_trials")
        if num_trials is not None and trial_seeds is None:
            trial_seeds = [derive_seed(self.seed, t, "trial") for t in range(num_trials)]
        if trial_seeds is not None and len(trial_seeds) != num_trials:
            raise ValueError(
                f"trial_seeds must hold num_trials = {num_trials} seeds, got {len(trial_seeds)}"
            )
        self.trial_seeds = None if trial_seeds is None else [int(t) for t in trial_seeds]
        self.keep_reward_free = keep_reward_free
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.device = torch.device("cpu") if device is None else torch.device(device)
        self.psi = PsiHat(basis=basis, gamma=gamma, mode=psi_mode, k=knn_k)
        self.generator = torch.Generator().manual_seed(self.seed)
        # the reward-free rollouts' own sampling streams (re-seeded every iteration)
        self.reward_free_generator = torch.Generator().manual_seed(self.seed)
        self._reward_free_blocks: list[torch.Generator] | None = None
        theta = torch.ones(basis.num_features, dtype=torch.float64)
        if initial_theta is not None:
            theta = torch.as_tensor(initial_theta, dtype=torch.float64)
            if theta.shape != (basis.num_features,):
                raise ValueError(
                    f"initial_theta must have shape [{basis.num_features}] (the basis width), "
                    f"got {tuple(theta.shape)}"
                )
        self._initial_theta = theta
        self.theta = theta.expand(*self.trial_dims, basis.num_features).clone()
        self.rewarded_slice = rewarded_slice
        self.iteration = 0  # iterations completed
        warm = _warm_start(initial_episodes, self.trial_dims)
        self.rewarded = EpisodeBuffer(  # per trial
            rewarded=True, capacity=sum(schedule) + (0 if warm is None else warm.shape[-2])
        )
        if warm is not None:
            self.rewarded.extend(warm)
        self._warm = warm
        self._action_encoding = None  # the env's action encoding, read from its first instance
        if isinstance(env, EnvBase):
            self._action_encoding = ActionEncoding.from_spec(env.action_spec, env.batch_size)
        num_candidates = len(
            SOFTMAX_CANDIDATE_SCALES if improvement == "softmax" else self.candidate_offsets
        )
        self.reward_free = EpisodeBuffer(
            rewarded=False, capacity=self.num_repeats * num_candidates * sum(schedule)
        )
        self.history: list[IterationRecord] = []
        self._reward_free_transitions = 0
        self._pending: dict | None = None  # an iteration whose rewards are bought, θ not yet fit
        self._selection: dict | None = None  # the coming iteration's chosen sampling policy
        self._partial: dict[int, TensorDict] = {}  # its episodes bought so far, by index m
        self.selector = SamplingPolicySelector(
            env=reward_free_env if reward_free_env is not None else self._env_for,
            psi=self.psi,
            num_episodes=1,  # set per iteration (M_l)
            num_steps=self.num_steps,
            num_repeats=self.num_repeats,
            lam=self.lam,
            generator=self.reward_free_generator,
            device=self.device,
            num_workers=reward_free_workers,
            fit=fit,
            collector=collector,
        )
        self.policy = self._policy(self.theta, 1)
        self.store: RunStore | None = None
        self.resumed = False
        if checkpoint_path is not None:
            self.store = RunStore(
                self.checkpoint_path, config=self._config(), resume=resume, overwrite=overwrite
            )
            if not self.store.started_fresh:
                try:
                    self._restore(self.store.stored)
                except BaseException:
                    self._close_store()
                    raise
                self.resumed = True

    @property
    def rewarded_transitions(self) -> int:
        """Rewarded transitions bought so far (per trial)."""
        trials = math.prod(self.trial_dims)
        return (self.rewarded.num_transitions if len(self.rewarded) else 0) // trials

    def _policy(self, theta: torch.Tensor, iteration: int) -> LinearQPolicy:
        """The evaluation policy pi_l of θ (ε-greedy with ε = epsilon_schedule(l), or softmax)."""
        if self.improvement == "softmax":
            rule = {"beta": self.beta}
        else:
            epsilon = self.epsilon_schedule(iteration)
            if not 0 <= epsilon <= 1:
                raise ValueError(f"epsilon_schedule({iteration}) = {epsilon} lies outside [0, 1]")
            rule = {"epsilon": epsilon}
        return LinearQPolicy(
            basis=self.basis,
            theta=theta,
            generator=self.generator,
            tie_break=self.tie_break,
            action_spec=self._action_encoding,
            **rule,
        )

    def initial_policy(self) -> LinearQPolicy:
        """pi_1, the policy of θ_0, whatever the run's progress (e.g. after a resume)."""
        return self._policy(self._initial_theta.expand_as(self.theta).clone(), 1)

    def _candidate_rules(self) -> torch.Tensor:
        """ε (or β) of the K candidates of the coming iteration (eq. 59); the first is pi_l's."""
        if self.improvement == "softmax":
            return torch.tensor([self.beta * c for c in SOFTMAX_CANDIDATE_SCALES])
        eps = self.epsilon_schedule(self.iteration + 1)
        return torch.tensor(candidate_epsilons(eps, self.candidate_offsets), dtype=torch.float64)

    def _with_rule(self, rule: torch.Tensor) -> LinearQPolicy:
        key = "beta" if self.improvement == "softmax" else "epsilon"
        return self.policy.with_rule(**{key: rule})

    def candidates(self) -> list[LinearQPolicy]:
        """The K sampling-policy candidates of the coming iteration (eq. 59); the first is pi_l."""
        return [self._with_rule(rule) for rule in self._candidate_rules()]

    def _reward_free_candidates(self) -> list[LinearQPolicy]:
        """The candidates drawing from the reward-free streams, not from pi_l's (which the
        rewarded episodes use): AL's selection then leaves the rewarded draws as PL's."""
        candidates = self.candidates()
        for candidate in candidates:
            candidate.generator = self.reward_free_generator
            candidate.block_generators = self._reward_free_blocks
        return candidates

    def block_seeds(self, iteration: int, stream: str) -> list[int]:
        """Per-trial seeds of one stream of iteration l (``trial_seeds`` runs only)."""
        if self.trial_seeds is None:
            raise ValueError("block_seeds needs a run with num_trials")
        return [derive_seed(s, iteration, stream) for s in self.trial_seeds]

    def _evaluation_policy(self, iteration: int) -> tuple[LinearQPolicy, int]:
        """pi_{l+1} with sampling streams of its own, and the evaluation seed of iteration l.

        The streams depend on (seed, l) alone, so a resumed run measures what an
        uninterrupted one would.
        """
        seed = derive_seed(self.seed, iteration, "evaluation")
        policy = self.policy.with_rule(**self.policy._rule())
        policy.generator = torch.Generator().manual_seed(seed)
        if self.trial_seeds is not None:
            policy.block_generators = [
                torch.Generator().manual_seed(s) for s in self.block_seeds(iteration, "evaluation")
            ]
        return policy, seed

    def _env_seeds(self, iteration: int, stream: str) -> tuple[int, list[int] | None]:
        """The seed and, with ``trial_seeds``, the per-trial seeds of an env stream of l."""
        blocks = self.block_seeds(iteration, stream) if self.trial_seeds is not None else None
        return derive_seed(self.seed, iteration, stream), blocks

    def _seed_iteration(self, iteration: int, num_episodes: int) -> None:
        """Re-seed the policies' streams and the environments of iteration l."""
        trials = math.prod(self.trial_dims)
        self.generator.manual_seed(derive_seed(self.seed, iteration, "policy"))
        self.reward_free_generator.manual_seed(
            derive_seed(self.seed, iteration, "reward_free_policy")
        )
        if self.trial_seeds is not None:
            self.policy.block_generators = [
                torch.Generator().manual_seed(s) for s in self.block_seeds(iteration, "policy")
            ]
            self._reward_free_blocks = [
                torch.Generator().manual_seed(s)
                for s in self.block_seeds(iteration, "reward_free_policy")
            ]
        env = self._env_for(trials * num_episodes)
        if self._action_encoding is None:  # the policies write actions in the env's encoding
            self._action_encoding = ActionEncoding.from_spec(env.action_spec, env.batch_size)
            self.policy = self.policy.with_action_spec(self._action_encoding)
            self.selector.action_encoding = self._action_encoding
        seed_env(env, *self._env_seeds(iteration, "rewarded_env"))
        if self.mode == "active":
            batch = trials * self.num_repeats * len(self._candidate_rules()) * num_episodes
            self.selector.seed_env(batch, *self._env_seeds(iteration, "reward_free_env"))

    def _buy(self) -> None:
        """Steps 1-2 of Algorithm 1: choose the sampling policy, buy and store its episodes.

        The selection is committed first, then each slice of rewarded episodes (all M_l rows,
        or one episode index at a time with ``rewarded_slice="episode"``) before the next is
        measured. Episodes already stored (a resumed run) are not bought again.
        """
        l_now = self.iteration + 1
        num_episodes = self.schedule[self.iteration]
        one_slice = self.rewarded_slice == "all" and self._selection is None
        if self._selection is None:
            self._select(l_now, num_episodes)
        missing = [m for m in range(num_episodes) if m not in self._partial]
        # A simulator buys all rows in one rollout continuing the iteration's streams; single
        # episodes (a robot, or episodes left to buy after a resume) have streams of their own.
        slices = [missing] if one_slice else [[m] for m in missing]
        for episodes in slices:
            self._buy_slice(l_now, episodes, reseed=not one_slice)
        bought = [self._partial[m] for m in range(num_episodes)]
        self.rewarded.extend(torch.stack(bought, dim=len(self.trial_dims)))
        self._pending, self._selection, self._partial = self._selection, None, {}

    def _select(self, l_now: int, num_episodes: int) -> None:
        """Step 1: seed iteration l, choose the sampling policy (J'), commit the choice."""
        started = time.perf_counter()
        self._seed_iteration(l_now, num_episodes)
        rules = self._candidate_rules()
        chosen = torch.zeros(self.trial_dims, dtype=torch.long)
        j_mean = j_all = free = None
        reward_free_transitions = 0
        if self.mode == "active":
            self.selector.num_episodes = num_episodes
            earlier = self.rewarded.episodes() if len(self.rewarded) else None
            selection = self.selector.select(
                self.policy, self._reward_free_candidates(), earlier, iteration=l_now
            )
            chosen = selection.index
            j_mean, j_all = selection.j_mean.tolist(), selection.j_all.tolist()
            reward_free_transitions = selection.reward_free_transitions
            if self.keep_reward_free:
                free = selection.episodes.reshape(*self.trial_dims, -1, self.num_steps)
        self._selection = {
            "chosen": chosen,
            "sampling_rule": rules[chosen],
            "j_mean": j_mean,
            "j_all": j_all,
            "reward_free_transitions": reward_free_transitions,
            "seconds": time.perf_counter() - started,
        }
        self._partial = {}
        if self.store is not None:
            self.store.put_selection(l_now, self._selection_row(self._selection), free)
            self._on_commit()
        self._reward_free_transitions += reward_free_transitions
        if free is not None:
            self.reward_free.extend(free)

    @staticmethod
    def _selection_row(selection: dict) -> dict:
        return {k: v.tolist() if isinstance(v, torch.Tensor) else v for k, v in selection.items()}

    def _seed_slice(self, l_now: int, episode: int, rows: int) -> None:
        """Re-seed the policy stream and the rewarded env for episode m of iteration l."""
        self.generator.manual_seed(slice_seed(self.seed, l_now, episode, "policy"))
        if self.trial_seeds is not None:
            self.policy.block_generators = [
                torch.Generator().manual_seed(slice_seed(s, l_now, episode, "policy"))
                for s in self.trial_seeds
            ]
        blocks = None
        if self.trial_seeds is not None:
            blocks = [slice_seed(s, l_now, episode, "rewarded_env") for s in self.trial_seeds]
        seed = slice_seed(self.seed, l_now, episode, "rewarded_env")
        seed_env(self._env_for(rows), seed, blocks)

    def _buy_slice(self, l_now: int, episodes: list[int], *, reseed: bool) -> None:
        """Buy episodes ``episodes`` (indices m) of iteration l and commit them.

        An episode with a bad reward (NaN, inf) is reported by index; the valid episodes of
        the slice are committed first.
        """
        trials = math.prod(self.trial_dims)
        rows = trials * len(episodes)
        if reseed:
            self._seed_slice(l_now, episodes[0], rows)
        selection = self._selection
        chosen = selection["chosen"]
        where = f" (stored in {self.checkpoint_path})" if self.checkpoint_path else ""
        try:
            bought = self._collect(
                self._env_for(rows),
                self._with_rule(selection["sampling_rule"]),  # one candidate per trial
                num_episodes=len(episodes),
                num_steps=self.num_steps,
                rewarded=True,
                iteration=l_now,
                policy_id=chosen,
                validate=False,
            )
        except Exception as error:
            raise RuntimeError(
                f"collecting the rewarded episodes of iteration {l_now} failed: "
                f"{type(error).__name__}: {error}. The {len(self.rewarded)} episodes bought "
                f"before (per trial) are kept in api.rewarded{where}; none of this batch was "
                "stored"
            ) from error
        good, bad = {}, []
        for i, m in enumerate(episodes):
            one = bought[..., i : i + 1, :]
            try:
                validate_episodes(one, rewarded=True)
            except ValueError as error:
                bad.append(f"episode {m}{self._trial_of_bad(one)}: {error}")
            else:
                good[m] = one.squeeze(-2)
        if self.store is not None and good:
            self.store.put_episodes(l_now, good)
            self._on_commit()
        self._partial.update(good)
        if bad:
            raise ValueError(
                f"iteration {l_now}: {'; '.join(bad)}. The {len(good)} valid episodes of this "
                f"slice are kept{where}; a resume buys the others again"
            )

    def _trial_of_bad(self, one: TensorDict) -> str:
        """`` of trial t`` for the first trial whose episode fails the checks (trials only)."""
        for t in range(math.prod(self.trial_dims)) if self.trial_dims else ():
            try:
                validate_episodes(one.reshape(-1, *one.shape[-2:])[t : t + 1], rewarded=True)
            except ValueError:
                return f" of trial {t}"
        return ""

    def _collect(self, env: EnvBase, policy, **kwargs):
        """Episodes from ``env.rollout`` (:func:`collect_episodes`) or the user's collector."""
        if self.collector is None:
            return collect_episodes(env, policy, **kwargs)
        kwargs.pop("validate", None)  # (the collector's episodes are checked as they come)
        return collect_with_collector(self.collector, policy, **kwargs)

    def step(self) -> IterationRecord:
        """Run one iteration of Algorithm 1 and return its record."""
        if self.iteration >= len(self.schedule):
            raise RuntimeError(f"all {len(self.schedule)} iterations of the schedule are done")
        if self._pending is None:  # (after a resume, the rewards may be bought already)
            self._buy()
        elif self.store is not None and self.store.closed:
            raise RuntimeError(f"the run's store {self.checkpoint_path} is closed")
        started = time.perf_counter()
        l_now = self.iteration + 1
        # Policy evaluation on every rewarded episode so far (sample reuse, eq. 56).
        episodes = self.rewarded.episodes().to(self.device)
        design = build_design(episodes, self.policy.to_device(self.device), self.psi)
        if self.fit == "lstd":
            phi = phi_rows(episodes, self.basis)
            self.theta = weighted_lstd(
                phi, design.x, design.w, design.reward, self.lam, num_samples=design.num_samples
            ).cpu()
        else:
            self.theta = weighted_ridge(
                design.x, design.w, design.reward, self.lam, num_samples=design.num_samples
            ).cpu()
        self.policy = self._policy(self.theta, l_now + 1)  # policy improvement
        pending, self._pending = self._pending, None
        seconds = pending["seconds"] + time.perf_counter() - started
        performance = None
        if self.evaluate is not None:
            performance = self.evaluate(*self._evaluation_policy(l_now))
        record = IterationRecord(
            iteration=l_now,
            chosen=pending["chosen"].tolist(),
            sampling_rule=pending["sampling_rule"].tolist(),
            j_mean=pending["j_mean"],
            j_all=pending["j_all"],
            episodes_bought=self.schedule[l_now - 1],
            rewarded_transitions=self.rewarded_transitions,
            reward_free_transitions=self._reward_free_transitions // math.prod(self.trial_dims),
            performance=performance,
            seconds=seconds,
            theta=self.theta.tolist(),
        )
        if self.store is not None:
            self.store.put_record(l_now, asdict(record))
            self._on_commit()
        self.iteration = l_now
        self.history.append(record)
        _log.info(
            "%s iteration %d/%d done in %.2f s: %d rewarded transitions per trial bought so far",
            self.mode,
            l_now,
            len(self.schedule),
            seconds,
            self.rewarded_transitions,
        )
        if self.iteration == len(self.schedule):
            self._close_store()
        return record

    # -- durable state -----------------------------------------------------------------------

    def _config(self) -> dict:
        """What gives stored data its meaning: a resume must agree on all of it.

        λ, the device, the worker processes and the evaluation callback are left out: they may
        change on resume (a fit that failed for a bad λ can be redone with a better one).
        """
        last = len(self.schedule) + 1
        trials = math.prod(self.trial_dims)
        config = {
            "schedule": self.schedule,
            "num_steps": self.num_steps,
            "gamma": self.gamma,
            "mode": self.mode,
            "num_repeats": self.num_repeats,
            "num_trials": self.num_trials,
            "seed": self.seed,
            "trial_seeds": self.trial_seeds,
            "psi_mode": self.psi.mode,
            "knn_k": self.psi.k,
            "improvement": self.improvement,
            "beta": self.beta,
            "tie_break": self.tie_break,
            "candidate_offsets": list(self.candidate_offsets),
            "epsilons": None
            if self.improvement == "softmax"
            else [self.epsilon_schedule(l) for l in range(1, last + 1)],
            "initial_theta": self._initial_theta.tolist(),
            "basis": fingerprint(self.basis),
            "env": fingerprint(self._env_for(trials * self.schedule[0])),
            "keep_reward_free": self.keep_reward_free,
            "rewarded_slice": self.rewarded_slice,
            "initial_episodes": None
            if self._warm is None
            else {str(k): _plain(v) for k, v in self._warm.items(True, True)},
            "fit": self.fit,
        }
        return config

    def _on_commit(self) -> None:
        """Called after every commit to the store (a hook for tests and testing aids)."""

    def _restore(self, stored: StoredRun, path: Path | None = None) -> None:
        """Rebuild the run's state from a verified store; nothing is changed if it fails.

        Raises:
            CorruptRunError: the stored rows do not form a run of this schedule.
        """
        path = path or self.checkpoint_path
        done = len(stored.records)
        if sorted(stored.records) != list(range(1, done + 1)) or done > len(self.schedule):
            raise CorruptRunError(f"the run {path} holds records {sorted(stored.records)}")
        rewarded = EpisodeBuffer(rewarded=True, capacity=self.rewarded.capacity)
        if self._warm is not None:  # the warm start comes first, as in a fresh run
            rewarded.extend(self._warm)
        reward_free = EpisodeBuffer(rewarded=False, capacity=self.reward_free.capacity)
        free_transitions = 0
        selection, partial = None, {}
        nxt = done + 1
        if nxt <= len(self.schedule) and nxt in stored.selections:
            if stored.episodes.get(nxt) or self.rewarded_slice == "episode":
                selection = dict(stored.selections[nxt])
                partial = dict(stored.episodes.get(nxt, {}))
        try:
            for l_now in range(1, done + 1 + (selection is not None)):
                row = stored.selections.get(l_now)
                if row is None:
                    raise CorruptRunError(
                        f"the run {path} lacks the selection of iteration {l_now}"
                    )
                free_transitions += int(row["reward_free_transitions"])
                if self.keep_reward_free and l_now in stored.free:
                    reward_free.extend(stored.free[l_now])
            for l_now in range(1, done + 1):
                got = stored.episodes.get(l_now, {})
                if sorted(got) != list(range(self.schedule[l_now - 1])):
                    raise CorruptRunError(
                        f"the run {path} holds episodes {sorted(got)} of iteration {l_now}, "
                        f"which bought {self.schedule[l_now - 1]}"
                    )
                rewarded.extend(torch.stack([got[m] for m in sorted(got)], len(self.trial_dims)))
            for m, episode in partial.items():
                if not 0 <= m < self.schedule[nxt - 1]:
                    raise CorruptRunError(f"the run {path} holds episode {m} of iteration {nxt}")
                validate_episodes(episode.unsqueeze(-2), rewarded=True)
            history = [IterationRecord(**r) for _, r in sorted(stored.records.items())]
            theta = self.theta
            if history:
                theta = torch.tensor(history[-1].theta, dtype=torch.float64)
                if theta.shape != self.theta.shape:
                    raise CorruptRunError(f"the run {path} holds θ of shape {tuple(theta.shape)}")
        except (ValueError, TypeError, KeyError, RuntimeError) as error:
            if isinstance(error, CorruptRunError):
                raise
            raise CorruptRunError(f"the run {path} cannot be restored: {error}") from None
        if selection is not None:
            selection["chosen"] = torch.tensor(selection["chosen"], dtype=torch.long)
            selection["sampling_rule"] = torch.tensor(
                selection["sampling_rule"], dtype=torch.float64
            )
        pending = None
        if selection is not None and len(partial) == self.schedule[nxt - 1]:
            last = [partial[m] for m in sorted(partial)]
            rewarded.extend(torch.stack(last, len(self.trial_dims)))
            pending, selection, partial = selection, None, {}
        # everything checked: now change the object
        self.rewarded, self.reward_free = rewarded, reward_free
        self._reward_free_transitions = free_transitions
        self.history, self.iteration, self.theta = history, done, theta
        self._pending, self._selection, self._partial = pending, selection, partial
        self.policy = self._policy(self.theta, self.iteration + 1)

    def load(self, path: str | os.PathLike) -> None:
        """Take over the state of the run stored at ``path`` (read only; for inspection or a
        copy: to continue a run, build it with ``checkpoint_path=path, resume=True``).

        Raises:
            CorruptRunError: the file fails a check, or was made with other settings; the
                object is then left as it was.
        """
        stored = RunStore.read(path)
        mine = RunStore.normalise(self._config())
        if stored.config != mine:
            differ = sorted(
                k for k in stored.config.keys() | mine.keys() if stored.config.get(k) != mine.get(k)
            )
            raise CorruptRunError(
                f"the run stored in {path} was made with other settings: {differ}"
            )
        self._restore(stored, Path(path))

    def _close_store(self) -> None:
        """Close the run's store (its lock is released); the object keeps its state."""
        if self.store is not None:
            self.store.close()

    def close(self) -> None:
        """Close the run's store (releasing its lock) and the envs built from env factories
        (rewarded and reward-free), e.g. the worker processes of ``env=lambda rows:
        ParallelEnv(rows, make_env)``; envs given as such are the caller's to close. The
        object keeps its state: envs are built again if it goes on, a store is not."""
        self._close_store()
        self._env_for.close()
        self.selector.close()

    def __enter__(self) -> ActivePolicyIteration:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def run(self, *, progress: bool = False) -> list[IterationRecord]:
        """Run the remaining iterations; returns the whole history."""
        remaining = range(self.iteration, len(self.schedule))
        for _ in tqdm(remaining, desc=f"API ({self.mode})", disable=not progress):
            self.step()
        if self.iteration == len(self.schedule):
            self._close_store()  # (a resumed run that was complete already)
        return self.history


def _warm_start(data, trial_dims: tuple[int, ...]) -> TensorDictBase | None:
    """``initial_episodes`` in the library's format ``[*T, M, N]`` (None: no warm start)."""
    if data is None:
        return None
    batches = [data] if isinstance(data, TensorDictBase) else list(data)
    if not batches:
        return None
    joined = EpisodeBuffer(rewarded=True, capacity=sum(b.numel() for b in batches))
    for batch in batches:  # consecutive collector batches: cut trajectories are joined
        joined.extend(batch)
    episodes = joined.episodes()
    return episodes.expand(*trial_dims, *episodes.shape).clone() if trial_dims else episodes
