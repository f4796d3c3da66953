"""Active policy iteration and its passive baseline (paper section 4.1, Algorithm 1): the loop.

The loop (:meth:`ActivePolicyIteration.step`, :meth:`~ActivePolicyIteration.run`); the parts
it is made of are listed in :mod:`torch_api.loop`, the candidate families in
:mod:`torch_api.policies.families`, the random streams in :mod:`torch_api.streams`.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs import EnvBase
from tqdm import tqdm

from torch_api._checks import _check_loop_settings, _initial_theta
from torch_api.collection.collect import EnvPerBatch, rollouts_or
from torch_api.core.fit import PolicyEvaluation
from torch_api.core.iwcv import DEFAULT_FLATTENING_GRID, DEFAULT_IWCV_FOLDS
from torch_api.core.psi import PsiHat
from torch_api.core.solve import DEFAULT_LAMBDA
from torch_api.data.actions import ActionEncoding
from torch_api.data.buffer import EpisodeBuffer, _warm_start
from torch_api.loop.buying import RewardBuying
from torch_api.loop.durable import DurableState
from torch_api.loop.records import IterationRecord
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.policies import LinearQPolicy
from torch_api.policies.families import (
    PAPER_EPSILON_OFFSETS,
    CandidatePolicies,
    make_family,
    paper_epsilon,
)
from torch_api.streams import TrialStreams, derive_seed

__all__ = ["ActivePolicyIteration", "IterationRecord", "derive_seed"]

_log = logging.getLogger(__name__)


class ActivePolicyIteration(CandidatePolicies, RewardBuying, DurableState):
    """Sample-reuse least-squares policy iteration with active sampling-policy selection.

    Algorithm 1 of Akiyama, Hachiya & Sugiyama (2010). In iteration l = 1 … L:

    1. the sampling policy is the J'-chosen candidate (active learning: Algorithm 2, by the
       ``selector`` given) or pi_l itself (passive: ``selector=None``);
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
        basis: the basis module (e.g. :class:`~torch_api.core.basis.GaussianActionBasis`).
        schedule: episodes bought per iteration ``(M_1, …, M_L)``, each ≥ 1.
        num_steps: N, steps per episode.
        gamma: discount γ in (0, 1].
        selector: the :class:`~torch_api.loop.selector.SamplingPolicySelector` choosing each
            iteration's sampling policy (active learning), or None (passive: pi_l samples).
            It brings what is its own (its reward-free env or collector, Z = ``num_repeats``,
            worker processes, criterion); the loop binds it to its psi_hat, N, λ, fit and
            device (:meth:`~torch_api.loop.selector.SamplingPolicySelector.bind`; the object passed
            is left as it is) and to ``env`` where it has none, and gives it candidates that
            draw from the loop's reward-free streams. E.g.
            ``selector=SamplingPolicySelector(env=lambda rows: make_env(rows), num_repeats=5)``
            (an env whose batch is ``T·Z·K·M_l`` rolls out once).
        lam: λ > 0.
        psi_mode: ``"grouped"`` (finite states), ``"single"`` (continuous) or ``"knn"`` (k=knn_k).
        initial_theta: θ_0 of pi_1 (default all ones: ``Q̂_0 = Σ_b phi_b``, eq. 58, 67).
        epsilon_schedule: ε of pi_l as a function of l (default ``0.15 / l``).
        candidate_offsets: candidates ε_l + offset (eq. 59).
        improvement: ``"epsilon_greedy"`` (the paper) or ``"softmax"`` (eq. 7; pi_l uses
            ``beta`` and the candidates β times
            :data:`~torch_api.policies.families.SOFTMAX_CANDIDATE_SCALES`).
        beta: softmax temperature.
        tie_break: how the ε-greedy policies share the greedy mass among actions whose Q̂ ties
            for the maximum: ``"uniform"`` (equal parts: pi_1 of θ_0 = 1, and any pi_l of
            θ = 0 after rewards that were all zero, is uniform) or ``"lowest"`` (all to the
            lowest action index). See :func:`~torch_api.policies.greedy_probs`.
        evaluate: optional callback ``(policy, seed) -> dict`` measuring pi_{l+1} after every
            iteration; policy and ``seed`` (for the callback's env; per trial:
            ``api.block_seeds(l, "evaluation")``) come from (seed, l), so a resumed run
            measures exactly as an uninterrupted one.
        num_trials: T, independent trials run side by side (None: a single run, θ ``[B]``).
        seed: seed of the run: the policies' sampling streams (fresh for each use) and the
            envs' seeds (``env.set_seed``) of iteration l are derived from ``(seed, l, role)``
            (:class:`~torch_api.streams.TrialStreams`). Active and passive runs of one seed share
            the rewarded episodes' streams (the reward-free rollouts draw from streams of their
            own): a pair differs only by the sampling policy.
        trial_seeds: with ``num_trials``, one seed per trial (default: derived from ``seed``).
            Each trial then draws from streams of its own, seeded from ``(trial_seed, l)``: the
            policies' sampling and, for environments with ``set_block_seeds`` (this project's
            envs), the environments' rows of that trial. A batched run of T trials then gives
            the numbers of T runs with ``num_trials=1, trial_seeds=[s_t]``.
        keep_reward_free: store the selector's reward-free episodes in ``reward_free``.
        checkpoint_path: if set, the run is stored there (:class:`~torch_api.runs.store.RunStore`,
            an SQLite database): each slice of rewarded episodes is committed (fsynced,
            checksummed) before the next is measured, the selection before the rewards it
            buys, every completed iteration's record (θ_l) after it. The place is opened, locked
            against other writers and checked writable here, before anything is bought.
        resume: continue the run stored at ``checkpoint_path`` (built with the same settings:
            everything that gives the stored data its meaning must match, while ``lam``,
            ``device``, the selector's workers and ``evaluate`` may change). Only missing
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
        fit: ``"brm"`` (the paper: θ by weighted least squares of r on psi_hat, eq. 22-28) or
            ``"lstd"`` (beyond the paper: LSTD-Q, :mod:`torch_api.core.lstd`, with J of the same
            learner; needs ``psi_mode="single"``).
        flattening: ν of the flattened weights ``w^ν`` of the fit and of J (docs/flattening.md):
            1.0 (the paper's, bit for bit), a ν in [0, 1], or ``"iwcv"``: ν of
            ``flattening_grid`` chosen per iteration and trial by IWCV over ``iwcv_folds``
            folds of the rewarded episodes (:mod:`torch_api.core.iwcv`; J of iteration l uses
            ν_{l-1}).
        initial_episodes: a warm start: rewarded episodes already bought (with any sampling
            policy that recorded its probabilities), stored first in ``api.rewarded`` and used
            by every fit and as earlier sampling sets. TorchRL data as TorchRL produces it (a
            ``Collector``'s batch, or a list of consecutive batches whose cut trajectories are
            joined; ``env.rollout`` output) or the library's format
            (:meth:`~torch_api.data.EpisodeBuffer.extend`). With ``num_trials`` every trial
            starts from the same episodes.
        collector: optional factory ``(policy, num_episodes) -> Collector`` of the user's own
            (whole trajectories of at most N steps, e.g. ``trajs_per_batch=num_episodes,
            traj_format="padded"``): the rewarded episodes, and the reward-free ones of a
            selector without an env or collector of its own, are read from it
            (:func:`~torch_api.data.collect_with_collector`) instead of ``env.rollout``. Its env
            is seeded by the user; ``env`` still names the env. Not with ``num_trials``.
        extra_candidates: the user's own sampling policies (e.g. a TorchRL
            ``ProbabilisticActor(..., return_log_prob=True)``), candidates K, K+1, … after the
            family's; rewarded episodes are then stored with ``sample_log_prob``. Active mode,
            without ``num_trials``.
        on_checkpoint: optional hook ``(api) -> None`` called after every commit to the store
            (progress, a testing aid that stops the process at a given commit).
        on_iteration: optional hook ``(record) -> None`` called with each completed
            iteration's :class:`IterationRecord` (logging, early stopping by raising).

    Example:
        >>> from torchrl.envs import GymEnv
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)
        >>> api = ActivePolicyIteration(env=GymEnv("CartPole-v1"), basis=basis, schedule=(2, 1),
        ...                             num_steps=5, gamma=0.9,
        ...                             selector=SamplingPolicySelector(num_repeats=2))
        >>> history = api.run()
        >>> len(history), api.mode, api.rewarded_transitions <= 3 * 5
        (2, 'active', True)
    """

    def __init__(
        self,
        *,
        env: EnvBase | Callable[[int], EnvBase],
        basis: nn.Module,
        schedule: Sequence[int],
        num_steps: int,
        gamma: float,
        selector: SamplingPolicySelector | None = None,
        lam: float = DEFAULT_LAMBDA,
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
        resume: bool = False,
        overwrite: bool = False,
        rewarded_slice: str = "all",
        fit: str = "brm",
        flattening: float | str = 1.0,
        flattening_grid: Sequence[float] = DEFAULT_FLATTENING_GRID,
        iwcv_folds: int = DEFAULT_IWCV_FOLDS,
        initial_episodes: TensorDictBase | Sequence[TensorDictBase] | None = None,
        collector: Callable | None = None,
        extra_candidates: Sequence[nn.Module] = (),
        on_checkpoint: Callable[[ActivePolicyIteration], None] | None = None,
        on_iteration: Callable[[IterationRecord], None] | None = None,
    ) -> None:
        if selector is not None and not isinstance(selector, SamplingPolicySelector):
            raise ValueError(
                "selector must be a SamplingPolicySelector or None (passive), got "
                f"{type(selector).__name__}"
            )
        # the candidate family checks improvement, beta and the offsets
        family = make_family(
            improvement,
            epsilon_schedule=epsilon_schedule,
            candidate_offsets=candidate_offsets,
            beta=beta,
        )
        schedule, num_steps, knn_k, num_trials, seed, device = _check_loop_settings(
            tie_break=tie_break,
            schedule=schedule,
            num_steps=num_steps,
            knn_k=knn_k,
            num_trials=num_trials,
            gamma=gamma,
            lam=lam,
            rewarded_slice=rewarded_slice,
            store=(resume or overwrite, checkpoint_path),
            psi_mode=psi_mode,
            fit=fit,
            collector=collector or getattr(selector, "collector", None),
            extra=(len(extra_candidates), selector is not None),
            env_is_factory=not isinstance(env, EnvBase),
            seed=seed,
            device=device,
            candidate_offsets=candidate_offsets,
        )
        self.extra_candidates = tuple(extra_candidates)
        self._collect = rollouts_or(collector)  # the rewarded episodes' source, chosen once
        self.on_checkpoint = on_checkpoint
        self.on_iteration = on_iteration
        self.env = env
        self._env_for = EnvPerBatch(env)
        self.num_trials = num_trials
        self.trial_dims = () if num_trials is None else (int(num_trials),)
        self.basis = basis
        self.schedule = schedule
        self.num_steps = int(num_steps)
        self.gamma = float(gamma)
        self.lam = float(lam)
        self.epsilon_schedule = epsilon_schedule
        self.candidate_offsets = tuple(candidate_offsets)
        self.improvement = improvement
        self.beta = beta
        self.tie_break = tie_break
        self.fit = fit
        self.evaluation = PolicyEvaluation(  # step 3, checks flattening, its grid and folds
            fit=fit, lam=self.lam, flattening=flattening, grid=flattening_grid, folds=iwcv_folds
        )
        self.evaluate = evaluate
        self.seed = int(seed)
        self.streams = TrialStreams.for_trials(self.seed, num_trials, trial_seeds)
        self.trial_seeds = self.streams.trial_seeds
        self.family = family
        self.keep_reward_free = keep_reward_free
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.device = device
        self.psi = PsiHat(basis=basis, gamma=gamma, mode=psi_mode, k=knn_k)
        self._initial_theta = theta = _initial_theta(initial_theta, basis.num_features)
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
        self.selector = None
        if selector is not None:
            self.selector = selector.bind(
                env=self._env_for,
                psi=self.psi,
                num_steps=self.num_steps,
                lam=self.lam,
                fit=fit,
                device=self.device,
                collector=collector,
            )
        k = self.family.num_candidates + len(self.extra_candidates)
        z = 0 if selector is None else selector.num_repeats
        self.reward_free = EpisodeBuffer(rewarded=False, capacity=max(1, z * k * sum(schedule)))
        self.history: list[IterationRecord] = []
        self._reward_free_transitions = 0
        self._pending: dict | None = None  # an iteration whose rewards are bought, θ not yet fit
        self._selection: dict | None = None  # the coming iteration's chosen sampling policy
        self._partial: dict[int, TensorDict] = {}  # its episodes bought so far, by index m
        self.policy = self._policy(self.theta, 1)
        self._open_store(resume=resume, overwrite=overwrite)

    @property
    def mode(self) -> str:
        """``"active"`` with a selector, ``"passive"`` without."""
        return "passive" if self.selector is None else "active"

    @property
    def rewarded_transitions(self) -> int:
        """Rewarded transitions bought so far (per trial)."""
        trials = math.prod(self.trial_dims)
        return (self.rewarded.num_transitions if len(self.rewarded) else 0) // trials

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
        policy = self.policy.to_device(self.device)
        fitted = self.evaluation(episodes, policy, self.psi, self.basis)
        self.theta = fitted.theta.cpu()
        self.policy = self._policy(self.theta, l_now + 1)  # policy improvement
        pending, self._pending = self._pending, None
        seconds = pending["seconds"] + time.perf_counter() - started
        performance = None
        if self.evaluate is not None:
            performance = self.evaluate(*self._evaluation_policy(l_now))
        record = IterationRecord(
            iteration=l_now,
            chosen=pending["chosen"].tolist(),
            sampling_rule=None if (rule := pending["sampling_rule"]) is None else rule.tolist(),
            j_mean=pending["j_mean"],
            j_all=pending["j_all"],
            episodes_bought=self.schedule[l_now - 1],
            rewarded_transitions=self.rewarded_transitions,
            reward_free_transitions=self._reward_free_transitions // math.prod(self.trial_dims),
            performance=performance,
            seconds=seconds,
            theta=self.theta.tolist(),
            flattening=fitted.flattening.tolist(),
            effective_sample_size=fitted.ess.tolist(),
        )
        if self.store is not None:
            # shallow: the store serialises the lists (asdict's deep copy cost seconds)
            self.store.put_record(l_now, vars(record).copy())
            self._on_commit()
        self.iteration = l_now
        self.history.append(record)
        _log.info("%s %s", self.mode, record.summary(len(self.schedule)))
        if self.on_iteration is not None:
            self.on_iteration(record)
        if self.iteration == len(self.schedule):
            self._close_store()
        return record

    def close(self) -> None:
        """Close the run's store (releasing its lock) and the envs built from env factories
        (rewarded and reward-free), e.g. the worker processes of ``env=lambda rows:
        ParallelEnv(rows, make_env)``; envs given as such are the caller's to close. The
        object keeps its state: envs are built again if it goes on, a store is not."""
        self._close_store()
        self._env_for.close()
        if self.selector is not None:
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
