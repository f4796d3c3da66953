"""Active policy iteration and its passive baseline (paper section 4.1, Algorithm 1): the loop.

The loop holds a few small objects, each with its own state, and passes them what they need:
the candidate policies (:class:`~torch_api.loop.policies.LoopPolicies`), the buyer of rewarded
episodes (:class:`~torch_api.loop.buying.RewardBuyer`, steps 1-2), the policy evaluation
(:class:`~torch_api.core.fit.PolicyEvaluation`, step 3) and the durable run
(:class:`~torch_api.loop.durable.DurableRun`). Its own state is the run's: θ, pi_l, the
episode buffers, the records.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase
from tqdm import tqdm

from torch_api.collection.collect import EnvPerBatch, rollouts_or
from torch_api.core.fit import PolicyEvaluation
from torch_api.core.iwcv import DEFAULT_FLATTENING_GRID, DEFAULT_IWCV_FOLDS
from torch_api.core.psi import PsiHat
from torch_api.core.solve import DEFAULT_LAMBDA
from torch_api.data.buffer import EpisodeBuffer, _warm_start
from torch_api.loop.buying import RewardBuyer
from torch_api.loop.durable import DurableRun, Restored, RunLayout
from torch_api.loop.policies import LoopPolicies
from torch_api.loop.records import Choice, IterationRecord
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.settings import check_initial_theta, check_loop_settings, run_settings
from torch_api.policies.families import PAPER_EPSILON_OFFSETS, make_family, paper_epsilon
from torch_api.policies.linear_q import LinearQPolicy
from torch_api.streams import TrialStreams, derive_seed

__all__ = ["ActivePolicyIteration", "IterationRecord", "derive_seed"]

_log = logging.getLogger(__name__)


class ActivePolicyIteration:
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
        num_steps: N, steps per episode; gamma: discount γ in (0, 1].
        selector: the :class:`~torch_api.loop.selector.SamplingPolicySelector` choosing each
            iteration's sampling policy (active), or None (passive: pi_l samples); the loop
            binds a copy to its psi_hat, N, λ, fit, device and, where it has none, env.
        lam: λ > 0.
        psi_mode: ``"grouped"`` (finite states), ``"single"`` (continuous) or ``"knn"`` (k=knn_k).
        initial_theta: θ_0 of pi_1 (default all ones: ``Q̂_0 = Σ_b phi_b``, eq. 58, 67).
        epsilon_schedule: ε of pi_l as a function of l (default ``0.15 / l``); candidate_offsets:
            candidates ε_l + offset (eq. 59).
        improvement: ``"epsilon_greedy"`` (the paper) or ``"softmax"`` (eq. 7, temperature
            ``beta``; :mod:`torch_api.policies.families`).
        tie_break: how ε-greedy policies share the greedy mass among tied actions:
            ``"uniform"`` (equal parts: pi_1 of θ_0 = 1 is uniform) or ``"lowest"`` (all to the
            lowest index); :func:`~torch_api.policies.greedy_probs`.
        evaluate: optional callback ``(policy, seed) -> dict`` measuring pi_{l+1} after every
            iteration, its streams and ``seed`` from (seed, l) (as a resumed run would).
        num_trials: T, independent trials run side by side (None: a single run, θ ``[B]``).
        seed: every stream of iteration l (sampling, envs' seeds) comes from ``(seed, l,
            role)`` (:class:`~torch_api.streams.TrialStreams`, docs/random_streams.md).
        trial_seeds: with ``num_trials``, one seed per trial: T batched trials then give the
            numbers of T runs with ``num_trials=1, trial_seeds=[s_t]``.
        keep_reward_free: store the selector's reward-free episodes in ``reward_free``.
        checkpoint_path: if set, the run is stored there (SQLite, docs/durable_runs.md): each
            choice, slice of rewarded episodes and record is committed before what depends on
            it (:class:`~torch_api.loop.durable.DurableRun`); opened and locked here.
        resume: continue the run stored there (same settings but ``lam``, ``device``, workers,
            ``evaluate``), buying only what is missing; overwrite: discard a stored run.
        rewarded_slice: ``"all"`` (a simulator: M_l rows in one rollout, one commit) or
            ``"episode"`` (a robot: one episode index at a time, each committed before the next
            is measured, with streams of its own from (seed, l, m)).
        device: where psi_hat, J and the solves run (default CPU; the rollouts on the envs').
        fit: ``"brm"`` (the paper: least squares of r on psi_hat, eq. 22-28) or ``"lstd"``
            (LSTD-Q and its J, :mod:`torch_api.core.lstd`; needs ``psi_mode="single"``).
        flattening: ν of the flattened weights ``w^ν`` of the fit and J (docs/flattening.md):
            1.0 (the paper's), a ν in [0, 1], or ``"iwcv"`` (ν of ``flattening_grid`` by IWCV
            over ``iwcv_folds`` folds, per iteration and trial; :mod:`torch_api.core.iwcv`).
        initial_episodes: a warm start: rewarded episodes already bought (TorchRL data as it
            comes, :meth:`~torch_api.data.EpisodeBuffer.extend`), first in ``api.rewarded``.
        collector: optional factory ``(policy, num_episodes) -> Collector`` of the user's,
            the episodes' source (:func:`~torch_api.collection.collect_with_collector`).
        extra_candidates: the user's own sampling policies (e.g. a TorchRL
            ``ProbabilisticActor``), candidates K, K+1, … (active, without ``num_trials``).
        on_checkpoint: optional hook ``(api) -> None`` called after every commit to the store.
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
        # the candidate family checks improvement, beta and the offsets
        self.family = make_family(
            improvement,
            epsilon_schedule=epsilon_schedule,
            candidate_offsets=candidate_offsets,
            beta=beta,
        )
        schedule, num_steps, knn_k, num_trials, seed, device = check_loop_settings(
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
            selector=selector,
            collector=collector,
            extra=(len(extra_candidates), selector is not None),
            env_is_factory=not isinstance(env, EnvBase),
            seed=seed,
            device=device,
            candidate_offsets=candidate_offsets,
        )
        self.env, self.envs = env, EnvPerBatch(env)
        self.basis, self.schedule, self.num_steps = basis, schedule, int(num_steps)
        self.gamma, self.lam, self.fit, self.device = float(gamma), float(lam), fit, device
        self.num_trials = num_trials
        self.trial_dims = () if num_trials is None else (int(num_trials),)
        self.epsilon_schedule, self.candidate_offsets = epsilon_schedule, tuple(candidate_offsets)
        self.improvement, self.beta, self.tie_break = improvement, beta, tie_break
        self.evaluation = PolicyEvaluation(  # step 3, checks flattening, its grid and folds
            fit=fit, lam=self.lam, flattening=flattening, grid=flattening_grid, folds=iwcv_folds
        )
        self.evaluate, self.on_checkpoint, self.on_iteration = evaluate, on_checkpoint, on_iteration
        self.seed = int(seed)
        self.streams = TrialStreams.for_trials(self.seed, num_trials, trial_seeds)
        self.trial_seeds = self.streams.trial_seeds
        self.keep_reward_free, self.rewarded_slice = keep_reward_free, rewarded_slice
        self.extra_candidates = tuple(extra_candidates)
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.psi = PsiHat(basis=basis, gamma=gamma, mode=psi_mode, k=knn_k)
        self.initial_theta = check_initial_theta(initial_theta, basis.num_features)
        self.theta = self.initial_theta.expand(*self.trial_dims, basis.num_features).clone()
        self.iteration = 0  # iterations completed
        self.initial_episodes = warm = _warm_start(initial_episodes, self.trial_dims)
        self.rewarded = EpisodeBuffer.holding(warm, capacity=sum(schedule))  # per trial
        self.policies = LoopPolicies(
            basis=basis, family=self.family, tie_break=tie_break, streams=self.streams
        )
        if isinstance(env, EnvBase):
            self.policies.know_actions(env)
        self.selector, self.mode = None, "passive" if selector is None else "active"
        if selector is not None:
            self.selector = selector.bind(
                env=self.envs,
                psi=self.psi,
                num_steps=self.num_steps,
                lam=self.lam,
                fit=fit,
                device=self.device,
                collector=collector,
            )
        k = self.family.num_candidates + len(self.extra_candidates)  # Z·K·M_l rows a selection
        z = 0 if selector is None else selector.num_repeats
        self.reward_free = EpisodeBuffer(rewarded=False, capacity=max(1, z * k * sum(schedule)))
        self.history: list[IterationRecord] = []
        self.pending: Choice | None = None  # the coming iteration's, its rewards all bought
        self.policy = self.policies.evaluation(self.theta, 1)
        self.durable = DurableRun(
            self.checkpoint_path,
            settings=lambda: run_settings(self),
            layout=RunLayout(
                schedule=schedule,
                trial_dims=self.trial_dims,
                theta_shape=self.theta.shape,
                rewarded_slice=rewarded_slice,
                keep_reward_free=keep_reward_free,
                warm=warm,
                capacities=(self.rewarded.capacity, self.reward_free.capacity),
            ),
            resume=resume,
            overwrite=overwrite,
            on_commit=lambda: self.on_checkpoint and self.on_checkpoint(self),
        )
        self.buyer = RewardBuyer(
            envs=self.envs,
            collect=rollouts_or(collector),  # the rewarded episodes' source, chosen once
            streams=self.streams,
            policies=self.policies,
            selector=self.selector,
            durable=self.durable,
            num_steps=self.num_steps,
            reward_free=self.reward_free,
            extra_candidates=self.extra_candidates,
        )
        self.store = self.durable.store  # (a RunStore, or None)
        self.resumed = self.durable.restored is not None
        if self.resumed:
            self._take(self.durable.restored)

    @property
    def rewarded_transitions(self) -> int:
        """Rewarded transitions bought so far per trial (the mean; records hold each trial's)."""
        trials = math.prod(self.trial_dims)
        return (self.rewarded.num_transitions if len(self.rewarded) else 0) // trials

    def step(self) -> IterationRecord:
        """Run one iteration of Algorithm 1 and return its record."""
        if self.iteration >= len(self.schedule):
            raise RuntimeError(f"all {len(self.schedule)} iterations of the schedule are done")
        if self.pending is None:  # (after a resume, the rewards may be bought already)
            self.buy()  # steps 1-2
        elif self.durable.closed:
            raise RuntimeError(f"the run's store {self.checkpoint_path} is closed")
        started = time.perf_counter()
        l_now = self.iteration + 1
        # 3. policy evaluation on every rewarded episode so far (sample reuse, eq. 56)
        episodes = self.rewarded.episodes().to(self.device)
        fitted = self.evaluation(episodes, self.policy.to_device(self.device), self.psi, self.basis)
        self.theta = fitted.theta.cpu()
        self.policy = self.policies.evaluation(self.theta, l_now + 1)  # 4. policy improvement
        choice, self.pending = self.pending, None
        performance = None
        if self.evaluate is not None:
            performance = self.evaluate(*self.policies.for_evaluation(self.policy, l_now))
        record = IterationRecord.of(
            l_now,
            choice,
            fitted,
            episodes_bought=self.schedule[l_now - 1],
            rewarded_transitions=episodes["mask"].sum((-2, -1)).tolist(),  # each trial's own
            reward_free_transitions=self.buyer.reward_free_transitions.tolist(),
            performance=performance,
            seconds=choice.seconds + time.perf_counter() - started,
        )
        # shallow: the store serialises the lists (asdict's deep copy cost seconds)
        self.durable.put_record(l_now, vars(record).copy())
        self.iteration = l_now
        self.history.append(record)
        _log.info("%s %s", self.mode, record.summary(len(self.schedule)))
        if self.on_iteration is not None:
            self.on_iteration(record)
        if self.iteration == len(self.schedule):
            self.durable.close()
        return record

    def buy(self) -> None:
        """Steps 1-2 of the coming iteration l: choose the sampling policy (committed first),
        then buy and commit its M_l rewarded episodes (those not stored yet); θ_l is fitted by
        the :meth:`step` that follows. Nothing happens when they are bought already."""
        if self.pending is not None:
            return
        l_now, num_episodes = self.iteration + 1, self.schedule[self.iteration]
        if self.buyer.choice is None:  # 1. (a resumed run may have chosen already)
            if self.policies.know_actions(self.envs(math.prod(self.trial_dims) * num_episodes)):
                self.policy = self.policy.with_action_spec(self.policies.action_encoding)
                if self.selector is not None:
                    self.selector.action_encoding = self.policies.action_encoding
            self.buyer.select(  # (counts and keeps its reward-free episodes)
                l_now,
                num_episodes,
                self.policy,
                self.rewarded.episodes() if len(self.rewarded) else None,
                self.evaluation.flattening_for_j(self.history),
            )
        choice = self.buyer.choice
        self.rewarded.extend(
            self.buyer.buy(l_now, num_episodes, self.policy, kept=len(self.rewarded))
        )
        self.pending = choice  # 2. bought and stored

    def candidates(self) -> list[LinearQPolicy]:
        """The K sampling-policy candidates of the coming iteration (eq. 59); the first is pi_l."""
        return self.policies.candidates(self.policy, self.iteration + 1)

    def initial_policy(self) -> LinearQPolicy:
        """pi_1, the policy of θ_0, whatever the run's progress (e.g. after a resume)."""
        return self.policies.evaluation(self.initial_theta.expand_as(self.theta).clone(), 1)

    def block_seeds(self, iteration: int, stream: str) -> list[int]:
        """Per-trial seeds of one stream of iteration l (``trial_seeds`` runs only)."""
        return self.streams.block_seeds(iteration, stream)

    def _take(self, restored: Restored) -> None:
        """Take over the state of a stored run (checked before anything changes)."""
        self.rewarded, self.reward_free = restored.rewarded, restored.reward_free
        self.buyer.reward_free = self.reward_free
        self.buyer.reward_free_transitions = restored.reward_free_transitions
        self.history, self.iteration = restored.history, len(restored.history)
        if restored.theta is not None:
            self.theta = restored.theta
        self.pending = restored.pending
        self.buyer.resume(restored.choice, restored.bought)
        self.policy = self.policies.evaluation(self.theta, self.iteration + 1)

    def load(self, path: str | os.PathLike) -> None:
        """Take over the state of the run stored at ``path`` (read only; for inspection or a
        copy: to continue a run, build it with ``checkpoint_path=path, resume=True``).

        Raises:
            CorruptRunError: the file fails a check, or was made with other settings; the
                object is then left as it was.
        """
        self._take(self.durable.read(path))

    def close(self) -> None:
        """Close the run's store (releasing its lock) and the envs built from env factories
        (rewarded and reward-free), e.g. the worker processes of ``env=lambda rows:
        ParallelEnv(rows, make_env)``; envs given as such are the caller's to close. The
        object keeps its state: envs are built again if it goes on, a store is not."""
        self.durable.close()
        self.envs.close()
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
            self.durable.close()  # (a resumed run that was complete already)
        return self.history
