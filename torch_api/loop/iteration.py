"""Active policy iteration and its passive baseline (paper section 4.1, Algorithm 1): the loop.

Small objects own their state: the policies (:class:`~torch_api.loop.policies.LoopPolicies`),
the buyer (steps 1-2, :class:`~torch_api.loop.buying.RewardBuyer`), the evaluation (step 3,
:class:`~torch_api.core.fit.PolicyEvaluation`) and the store it was handed
(:class:`~torch_api.loop.durable.DurableRun`); the loop's own: θ, pi_l, episodes, records."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase
from tqdm import tqdm

from torch_api._checks import _check_device
from torch_api.collection.collect import EnvPerBatch, rollouts_or
from torch_api.core.fit import PolicyEvaluation
from torch_api.core.psi import PsiHat
from torch_api.data.buffer import EpisodeBuffer, _warm_start
from torch_api.loop.buying import RewardBuyer
from torch_api.loop.durable import DurableRun, Restored, RunLayout
from torch_api.loop.identity import run_identity
from torch_api.loop.inputs import checked_parts, name_of, padded_episodes
from torch_api.loop.policies import LoopPolicies
from torch_api.loop.records import Choice, IterationRecord
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.policies.families import make_family
from torch_api.policies.linear_q import LinearQPolicy
from torch_api.streams import TrialStreams, derive_seed

__all__ = ["ActivePolicyIteration", "IterationRecord", "derive_seed"]

_log = logging.getLogger(__name__)


class ActivePolicyIteration:
    """Sample-reuse least-squares policy iteration with active sampling-policy selection.

    Algorithm 1 of Akiyama, Hachiya & Sugiyama (2010). In iteration l = 1 … L:

    1. :meth:`choose`: the sampling policy is the J'-chosen candidate (active learning:
       Algorithm 2, ``spec.selection``) or pi_l itself (passive: ``spec.selection=None``);
    2. :meth:`buy`: ``M_l`` rewarded episodes of N steps are bought with it (or the user buys
       them with :meth:`sampling_policy` in their own collector);
    3. :meth:`fit`: θ_l on ALL rewarded episodes so far (sample reuse, eq. 56), psi_hat on that
       union with pi_l and importance weights towards pi_l;
    4. :meth:`improve`: pi_{l+1} is the ε-greedy or softmax policy of θ_lᵀphi, and the
       iteration's :class:`IterationRecord` is made.

    :meth:`step` runs the four, :meth:`run` every iteration left. Every setting is in the
    :class:`~torch_api.loop.spec.RunSpec`; the other arguments are objects. With T trials it
    runs them as one batch: θ ``[T, B]``, episodes ``[T, M, N]``, J ``[T, Z, K]``.

    Args:
        spec: the run's settings (:class:`~torch_api.loop.spec.RunSpec`).
        env: a TorchRL ``EnvBase`` with discrete actions whose rewards are bought, or a
            callable ``batch_size -> env`` (required with trials: ``T·M_l`` rows).
        basis: the basis module (``phi``, ``phi_all``, ``num_features``, ``num_actions``).
        selector: how active learning collects its reward-free episodes (a
            :class:`~torch_api.loop.selector.SamplingPolicySelector`: its env, workers,
            criterion or collector); default: on the loop's env.
        durable: the run's store (:class:`~torch_api.loop.durable.DurableRun`), where each
            choice, slice of rewarded episodes and record is committed before what depends on
            it; a stored run of the same identity is continued.
        evaluate: optional ``(policy, seed) -> dict`` measuring pi_{l+1} after each iteration.
        device: where psi_hat, J and the solves run (default CPU; the rollouts on the envs').
        initial_episodes: rewarded episodes bought already (a warm start, TorchRL data).
        collector: optional factory ``(policy, num_episodes) -> Collector``: the source of
            episodes (:func:`~torch_api.collection.collect_with_collector`).
        extra_candidates: the user's own sampling policies (e.g. a ``ProbabilisticActor``),
            candidates K, K+1, … (active, without trials).
        on_iteration: optional hook ``(record) -> None`` after each iteration.

    Example:
        >>> from torchrl.envs import GymEnv
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)
        >>> spec = RunSpec.of(schedule=(2, 1), num_steps=5, gamma=0.9, num_repeats=2)
        >>> api = ActivePolicyIteration(spec, env=GymEnv("CartPole-v1"), basis=basis)
        >>> history = api.run()
        >>> len(history), api.mode, api.rewarded_transitions <= 3 * 5
        (2, 'active', True)
    """

    def __init__(
        self,
        spec: RunSpec,
        *,
        env: EnvBase | Callable[[int], EnvBase],
        basis: nn.Module,
        selector: SamplingPolicySelector | None = None,
        durable: DurableRun | None = None,
        evaluate: Callable[[LinearQPolicy, int], dict] | None = None,
        device: torch.device | str | None = None,
        initial_episodes: TensorDictBase | Sequence[TensorDictBase] | None = None,
        collector: Callable | None = None,
        extra_candidates: Sequence[nn.Module] = (),
        on_iteration: Callable[[IterationRecord], None] | None = None,
    ) -> None:
        self.spec = checked_parts(spec, env, selector, collector, extra_candidates)
        rewarded, evaluation, policy = spec.rewarded, spec.evaluation, spec.policy
        self.env, self.envs, self.basis = env, EnvPerBatch(env), basis
        self.device = _check_device(device)
        self.trial_dims = () if spec.trials.num_trials is None else (spec.trials.num_trials,)
        self.family = make_family(
            policy.improvement,
            epsilon_schedule=policy.epsilon_of,
            candidate_offsets=policy.candidate_offsets,
            beta=policy.beta,
        )
        self.evaluation = PolicyEvaluation(  # step 3
            evaluation.fit,
            evaluation.lam,
            evaluation.flattening,
            evaluation.flattening_grid,
            evaluation.iwcv_folds,
        )
        self.evaluate, self.on_iteration = evaluate, on_iteration
        self.streams = TrialStreams.for_trials(
            spec.trials.seed, spec.trials.num_trials, spec.trials.trial_seeds
        )
        self.extra_candidates = tuple(extra_candidates)
        self.psi = PsiHat(
            basis=basis, gamma=evaluation.gamma, mode=evaluation.psi_mode, k=evaluation.knn_k
        )
        self.initial_theta = policy.theta_0(basis.num_features)
        self.theta = self.initial_theta.expand(*self.trial_dims, basis.num_features).clone()
        self.iteration = 0  # iterations completed
        self.initial_episodes = warm = _warm_start(initial_episodes, self.trial_dims)
        schedule = list(rewarded.schedule)
        self.rewarded = EpisodeBuffer.holding(warm, capacity=sum(schedule))  # per trial
        self.policies = LoopPolicies(
            basis=basis, family=self.family, tie_break=policy.tie_break, streams=self.streams
        )
        if isinstance(env, EnvBase):
            self.policies.know_actions(env)
        self.selector = None
        if spec.selection is not None:
            self.selector = (selector or SamplingPolicySelector()).bind(
                env=self.envs,
                psi=self.psi,
                num_steps=rewarded.num_steps,
                num_repeats=spec.selection.num_repeats,
                lam=evaluation.lam,
                fit=evaluation.fit,
                device=self.device,
                collector=collector,
            )
            if self.policies.action_encoding is not None:
                self.selector.know_actions(self.policies.action_encoding)
        k = self.family.num_candidates + len(self.extra_candidates)  # Z·K·M rows a selection
        z = 0 if spec.selection is None else spec.selection.num_repeats
        free_capacity = max(1, z * k * sum(map(self._free_episodes, schedule)))
        self.history: list[IterationRecord] = []
        self._fitted = None  # step 3's fit of the coming iteration, until step 4 records it
        self.policy = self.policies.evaluation(self.theta, 1)
        self.durable = durable if durable is not None else DurableRun(None)
        self.buyer = RewardBuyer(
            envs=self.envs,
            collect=rollouts_or(collector),  # the rewarded episodes' source, chosen once
            streams=self.streams,
            policies=self.policies,
            selector=self.selector,
            durable=self.durable,
            num_steps=rewarded.num_steps,
            trial_dims=self.trial_dims,
            rewarded_slice=rewarded.rewarded_slice,
            keep_reward_free=spec.keep_reward_free,
            reward_free_capacity=free_capacity,
            extra_candidates=self.extra_candidates,
        )
        self.layout = RunLayout(  # what a stored run's rows are read against
            schedule,
            self.trial_dims,
            self.theta.shape,
            rewarded.rewarded_slice,
            spec.keep_reward_free,
            warm,
            (self.rewarded.capacity, free_capacity),
        )
        restored = self.durable.open(self.identity if self.durable.path else {}, self.layout)
        self.resumed = restored is not None
        if self.resumed:
            self._take(restored)

    @property
    def mode(self) -> str:
        """ "active" (the sampling policy chosen by J') or "passive" (pi_l samples)."""
        return self.spec.mode

    @property
    def schedule(self) -> list[int]:
        """M_1 … M_L."""
        return list(self.spec.rewarded.schedule)

    @property
    def num_steps(self) -> int:
        """N."""
        return self.spec.rewarded.num_steps

    @property
    def trial_seeds(self) -> list[int] | None:
        """Each trial's seed (None without trials)."""
        return self.streams.trial_seeds

    def block_seeds(self, iteration: int, stream: str) -> list[int]:
        """Per-trial seeds of one stream of iteration l (``trial_seeds`` runs only)."""
        return self.streams.block_seeds(iteration, stream)

    @property
    def identity(self) -> dict:
        """What a stored run must agree on to be continued by this one
        (:func:`~torch_api.loop.identity.run_identity`)."""
        warm = self.initial_episodes
        return run_identity(
            self.spec,
            env=self.envs(math.prod(self.trial_dims) * self.schedule[0]),
            basis=self.basis,
            criterion=None if self.selector is None else name_of(self.selector.criterion),
            initial_episodes=None if warm is None else dict(warm.items(True, True)),
            extra_candidates=[name_of(c) for c in self.extra_candidates] or None,
        )

    @property
    def reward_free(self) -> EpisodeBuffer:
        """The selector's reward-free episodes kept so far (``spec.keep_reward_free``)."""
        return self.buyer.reward_free

    @property
    def rewarded_transitions(self) -> int:
        """Rewarded transitions bought so far per trial (the mean; records hold each trial's)."""
        trials = math.prod(self.trial_dims)
        return (self.rewarded.num_transitions if len(self.rewarded) else 0) // trials

    def _know_actions(self, num_episodes: int) -> None:  # (from the env of M rows per trial)
        if self.policies.action_encoding is None:  # (once known, no env is built for it)
            self.policies.know_actions(self.envs(math.prod(self.trial_dims) * num_episodes))
            self.policy = self.policy.with_action_spec(self.policies.action_encoding)
            if self.selector is not None:
                self.selector.know_actions(self.policies.action_encoding)

    # -- the steps of Algorithm 1 -------------------------------------------------------------

    def choose(self) -> Choice:
        """Step 1 of the coming iteration l: the sampling policy, chosen by J' from reward-free
        episodes (active) or pi_l itself (passive), committed before any reward is bought; the
        iteration's envs are seeded. Returns the :class:`Choice` (the one under way, if any)."""
        self._check_open()
        if self.buyer.choice is None and self.buyer.pending is None:
            l_now, num_episodes = self.iteration + 1, self.schedule[self.iteration]
            self._know_actions(num_episodes)
            self.buyer.select(
                l_now,
                num_episodes,
                self.policy,
                self.rewarded.episodes() if len(self.rewarded) else None,
                self.evaluation.flattening_for_j(self.history),
                reward_free_episodes=self._free_episodes(num_episodes),
            )
        return self.buyer.choice or self.buyer.pending

    def sampling_policy(self) -> nn.Module:
        """The chosen policy with its streams, for the user's own collector (then :meth:`fit`)."""
        self.choose()
        return self.buyer.sampling_policy(self.iteration + 1, self.policy)

    def buy(self) -> None:
        """Steps 1-2: choose the sampling policy (committed first), then buy and commit its M_l
        rewarded episodes (those not stored yet) into ``api.rewarded``."""
        if self.buyer.pending is not None:
            return
        self.choose()
        l_now, num_episodes = self.iteration + 1, self.schedule[self.iteration]
        self.rewarded.extend(
            self.buyer.buy(l_now, num_episodes, self.policy, kept=len(self.rewarded))
        )

    def fit(self, episodes: TensorDictBase | None = None):
        """Step 3: θ_l on every rewarded episode so far (sample reuse, eq. 56): ``episodes``
        the user bought (TorchRL data: a replay buffer's contents), else ``api.rewarded``
        (:meth:`buy`). Returns the :class:`~torch_api.core.fit.Fit`; θ_l is ``api.theta``."""
        self._check_open()
        if episodes is None:
            if self.buyer.pending is None:
                self.buy()
            episodes = self.rewarded.episodes()
        else:
            self.choose()  # (the choice the user's episodes were bought with)
            episodes = padded_episodes(episodes, self.trial_dims, self.num_steps)
            # the rewarded episodes so far: the next choose()'s J' reuses them, as after buy()
            self.rewarded = EpisodeBuffer.holding(episodes, capacity=sum(self.schedule))
        started = time.perf_counter()
        episodes = episodes.to(self.device)
        fitted = self.evaluation(episodes, self.policy.to_device(self.device), self.psi, self.basis)
        self.theta = fitted.theta.cpu()
        self._fitted = (fitted, episodes["mask"].sum((-2, -1)).tolist(), started)
        return fitted

    def improve(self) -> IterationRecord:
        """Step 4 of iteration l: pi_{l+1} of θ_l (ε-greedy or softmax), measured by
        ``evaluate``; the iteration's record is committed and returned."""
        if self._fitted is None:
            raise RuntimeError("improve() follows fit() (step 3) of the same iteration")
        (fitted, transitions, started), self._fitted = self._fitted, None
        l_now = self.iteration + 1
        self._know_actions(self.schedule[l_now - 1])  # (a resumed run may not have built one)
        self.policy = self.policies.evaluation(self.theta, l_now + 1)
        choice = self.buyer.take_choice()
        performance = None
        if self.evaluate is not None:
            performance = self.evaluate(*self.policies.for_evaluation(self.policy, l_now))
        record = IterationRecord.of(
            l_now,
            choice,
            fitted,
            episodes_bought=self.schedule[l_now - 1],
            rewarded_transitions=transitions,  # each trial's own
            reward_free_transitions=self.buyer.reward_free_transitions.tolist(),
            performance=performance,
            seconds=choice.seconds + time.perf_counter() - started,
        )
        self.durable.put_record(l_now, vars(record).copy())  # (shallow: asdict's deep copy is slow)
        self.iteration = l_now
        self.history.append(record)
        _log.info("%s %s", self.mode, record.summary(len(self.schedule)))
        if self.on_iteration is not None:
            self.on_iteration(record)
        if self.iteration == len(self.schedule):
            self.durable.close()
        return record

    def _free_episodes(self, num_episodes: int) -> int:
        """Reward-free episodes per candidate and repeat of an iteration buying M_l."""
        selection = self.spec.selection
        return selection.episodes_for(num_episodes) if selection is not None else num_episodes

    def step(self) -> IterationRecord:
        """One iteration of Algorithm 1 (:meth:`buy`, :meth:`fit`, :meth:`improve`); its record."""
        if self.iteration >= len(self.schedule):
            raise RuntimeError(f"all {len(self.schedule)} iterations of the schedule are done")
        self.buy()  # steps 1-2 (after a resume, the rewards may be bought already)
        self.fit()
        return self.improve()

    def run(self, *, progress: bool = False) -> list[IterationRecord]:
        """Run the remaining iterations; returns the whole history."""
        remaining = range(self.iteration, len(self.schedule))
        for _ in tqdm(remaining, desc=f"API ({self.mode})", disable=not progress):
            self.step()
        if self.iteration == len(self.schedule):
            self.durable.close()  # (a resumed run that was complete already)
        return self.history

    def candidates(self) -> list[LinearQPolicy]:
        """The K sampling-policy candidates of the coming iteration (eq. 59); the first is pi_l."""
        return self.policies.candidates(self.policy, self.iteration + 1)

    def initial_policy(self) -> LinearQPolicy:
        """pi_1, the policy of θ_0, whatever the run's progress (e.g. after a resume)."""
        return self.policies.evaluation(self.initial_theta.expand_as(self.theta).clone(), 1)

    def _take(self, restored: Restored) -> None:
        """Take over the state of a stored run (checked before anything changes)."""
        self.rewarded = restored.rewarded
        self.history, self.iteration = restored.history, len(restored.history)
        if restored.theta is not None:
            self.theta = restored.theta
        self.buyer.restore(restored)
        self.policy = self.policies.evaluation(self.theta, self.iteration + 1)

    def load(self, path) -> None:
        """Take over the state of the run stored at ``path``, read only (to continue it:
        ``durable=DurableRun(path, resume=True)``); a ``CorruptRunError`` changes nothing."""
        self._take(DurableRun.read(path, self.identity, self.layout))

    def _check_open(self) -> None:
        if self.durable.closed and self.iteration < len(self.schedule):
            raise RuntimeError(f"the run's store {self.durable.path} is closed")

    def close(self) -> None:
        """Close the run's store (its lock) and the envs built from env factories (e.g. the
        workers of ``env=lambda rows: ParallelEnv(rows, make_env)``), not envs given as such;
        the object keeps its state (envs are built again if it goes on, a store is not)."""
        self.durable.close()
        self.envs.close()
        if self.selector is not None:
            self.selector.close()

    def __enter__(self) -> ActivePolicyIteration:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
