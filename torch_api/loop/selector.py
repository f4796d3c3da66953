"""Sampling-policy selection by the reward-free J criterion (paper section 3.4, Algorithm 2).

How the reward-free episodes are collected (one batched rollout, worker processes, the user's
``Collector``) is chosen once, when the selector is built or bound:
:mod:`torch_api.collection.candidates`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torch_api._checks import _check_device
from torch_api.collection.candidates import PolicyStack, choose_collection, rollout_rows
from torch_api.collection.collect import EnvPerBatch
from torch_api.core.criterion import Criterion, j_eq46, j_values
from torch_api.core.fit import FITS
from torch_api.core.lstd import lstd_j_values
from torch_api.core.psi import PsiHat
from torch_api.core.solve import DEFAULT_LAMBDA
from torch_api.data.episodes import as_episodes
from torch_api.policies.base import param_dims_of
from torch_api.policies.families import PAPER_EPSILON_OFFSETS, candidate_epsilons

__all__ = [
    "PAPER_EPSILON_OFFSETS",
    "PolicyStack",
    "SamplingPolicySelector",
    "Selection",
    "candidate_epsilons",
    "j_values",
]


@dataclass
class Selection:
    """What :class:`SamplingPolicySelector` decided (``*T``: the policies' trial dims, if any).

    Attributes:
        index: the chosen candidate ``argmin_k J'_k``, long ``[*T]`` (a 0-d tensor without
            trials; ``int(selection.index)`` works then).
        j_mean: J' ``[*T, K]``, the mean over repeats.
        j_all: J ``[*T, Z, K]``, every repeat.
        reward_free_transitions: reward-free transitions collected for the decision (all trials).
        episodes: the reward-free episodes collected ``[*T, Z, K, M, N]``.
    """

    index: torch.Tensor
    j_mean: torch.Tensor
    j_all: torch.Tensor
    reward_free_transitions: int
    episodes: TensorDictBase


class SamplingPolicySelector:
    """Algorithm 2 of the paper as a TorchRL component: choose the sampling policy by J'.

    For Z repeats it collects ``M`` reward-free episodes of ``N`` steps for each of the K
    candidates (one batched rollout when the environment's batch size is ``Z·K·M``), computes
    J for all candidates and repeats in one batched call (:func:`j_values`) and returns the
    candidate with the smallest mean J'. No reward is read: the collected episodes drop it.

    Standalone it needs ``env`` (or ``collector``), ``psi``, ``num_episodes`` and ``num_steps``.
    Passed to :class:`~torch_api.loop.iteration.ActivePolicyIteration` as ``selector=`` it is given
    the loop's settings (:meth:`bind`): leave ``psi``, ``num_episodes``, ``num_steps``,
    ``lam``, ``fit``, ``device`` and ``generator`` unset then (``env`` too, to use the loop's
    env), e.g. ``SamplingPolicySelector(env=reward_free_env, num_workers=2)``.

    Args:
        env: a TorchRL env with discrete actions used for reward-free rollouts, or a callable
            ``batch_size -> env``. An env whose batch size is ``Z·K·M`` is rolled out once;
            any other is rolled out candidate by candidate.
        psi: the psi_hat module (basis, γ, grouping).
        num_episodes: M, reward-free episodes per candidate and repeat (or per call).
        num_steps: N.
        num_repeats: Z (J' is the mean of Z values of J; default 5). A loop gives its own
            (``spec.selection.num_repeats``).
        lam: λ (default :data:`~torch_api.core.solve.DEFAULT_LAMBDA`).
        generator: random stream of the sampling (default: the candidates' own).
        device: where psi_hat and J are computed (default: where the episodes are); rollouts
            stay on the environment's device.
        max_design_bytes: J is computed for as many trials at a time as keep the candidates'
            psi_hat design under about this many bytes (memory, not speed, is the limit at
            hundreds of trials).
        num_workers: if > 0, the reward-free episodes are collected in this many worker
            processes by TorchRL's ``MultiSyncCollector``
            (:func:`~torch_api.collection.multiprocess.collect_episodes_in_workers`; for slow
            environments); ``env`` must then be a picklable callable ``batch_size -> env``,
            seeded through :meth:`seed_env`.
        fit: the learner whose error J estimates: ``"brm"`` (default; the paper's fit on
            psi_hat, :func:`j_values`) or ``"lstd"`` (LSTD-Q, beyond the paper,
            :func:`~torch_api.core.lstd.lstd_j_values`).
        criterion: with ``fit="brm"``, the criterion of the candidates' pooled moments
            (:data:`~torch_api.core.criterion.Criterion`, ``(PooledMoments, lam) -> [..., K]``):
            J of eq. 46 (:func:`~torch_api.core.criterion.j_eq46`) by default; a criterion of one's
            own is a function of the same signature.
        collector: optional factory ``(policy, num_episodes) -> Collector`` of the user's own
            (:func:`~torch_api.collection.collect_with_collector`): each candidate's ``Z·M``
            reward-free episodes are then read from it, candidate by candidate, instead of from
            ``env.rollout`` (the default, faster on batched envs). Without per-trial
            parameters only.

    Example:
        >>> from torchrl.envs import GymEnv
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> from torch_api.policies import LinearQPolicy
        >>> env = GymEnv("CartPole-v1")
        >>> basis = GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)
        >>> psi = PsiHat(basis=basis, gamma=0.9, mode="single")
        >>> pi = LinearQPolicy(basis=basis, theta=torch.ones(basis.num_features), epsilon=0.15,
        ...                    action_spec=env.action_spec)
        >>> selector = SamplingPolicySelector(env=env, psi=psi, num_episodes=2, num_steps=5,
        ...                                   num_repeats=2)
        >>> choice = selector.select(pi, [pi.with_rule(epsilon=e) for e in (0.15, 0.65)])
        >>> choice.j_mean.shape
        torch.Size([2])
    """

    def __init__(
        self,
        *,
        env: EnvBase | Callable[[int], EnvBase] | None = None,
        psi: PsiHat | None = None,
        num_episodes: int | None = None,
        num_steps: int | None = None,
        num_repeats: int | None = None,
        lam: float | None = None,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        max_design_bytes: int = 2**29,
        num_workers: int = 0,
        fit: str | None = None,
        collector: Callable | None = None,
        criterion: Criterion = j_eq46,
    ) -> None:
        for name, value in (
            ("num_episodes", num_episodes),
            ("num_steps", num_steps),
            ("num_repeats", num_repeats),
        ):
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if lam is not None and not lam > 0:
            raise ValueError(f"lam must be > 0, got {lam}")
        if num_workers < 0:
            raise ValueError(f"num_workers must be >= 0, got {num_workers}")
        if fit is not None and fit not in FITS:
            raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
        if fit == "lstd" and criterion is not j_eq46:
            raise ValueError("criterion applies to fit='brm' (LSTD-Q has its own J)")
        # the settings a loop supplies (bind): None where left to it
        self._loop_settings = {
            "psi": psi,
            "num_episodes": num_episodes,
            "num_steps": num_steps,
            "num_repeats": num_repeats,
            "lam": lam,
            "fit": fit,
            "device": device,
            "generator": generator,
        }
        self.env = env
        self.psi = psi
        self.num_episodes = None if num_episodes is None else int(num_episodes)
        self.num_steps = None if num_steps is None else int(num_steps)
        self.num_repeats = 5 if num_repeats is None else int(num_repeats)
        self.lam = DEFAULT_LAMBDA if lam is None else float(lam)
        self.generator = generator
        self.device = None if device is None else _check_device(device)  # a GPU that is there
        self.max_design_bytes = int(max_design_bytes)
        self.num_workers = int(num_workers)
        self.fit = "brm" if fit is None else fit
        self.criterion = criterion
        # the J of the learner, chosen once: LSTD-Q's, or the criterion of the pooled moments
        self._j = (
            lstd_j_values
            if self.fit == "lstd"
            else functools.partial(j_values, criterion=criterion)
        )
        self.collector = collector
        self.action_encoding = None  # the env's action encoding, where known (else probed)
        # how the episodes are collected, chosen once (env.rollout, workers or the collector)
        self._collection = None
        if env is not None or collector is not None:
            envs = None if env is None else EnvPerBatch(env)
            self._collection = choose_collection(
                envs, num_workers=self.num_workers, collector=collector
            )

    def bind(
        self,
        *,
        env: EnvBase | Callable[[int], EnvBase],
        psi: PsiHat,
        num_steps: int,
        num_repeats: int,
        lam: float,
        fit: str,
        device: torch.device | str | None,
        collector: Callable | None = None,
    ) -> SamplingPolicySelector:
        """This selector with a loop's settings: a new selector, this one left as it is.

        :class:`~torch_api.loop.iteration.ActivePolicyIteration` binds the selector it is given to
        its psi_hat (basis, γ), N, Z (``spec.selection.num_repeats``), λ, fit and device;
        ``env`` is used where this selector has none, and the loop's ``collector`` where this
        selector has neither an env nor a collector of its own (the reward-free episodes are
        then read from the user's collector too, with the reward dropped). M (given per call:
        :meth:`select`'s ``num_episodes``) and the sampling streams (its candidates bring its
        reward-free streams) are the loop's too: a selector given any of these settings, or a
        ``generator``, is refused.
        """
        given = sorted(k for k, v in self._loop_settings.items() if v is not None)
        if given:
            raise ValueError(
                f"selector: {given} are the loop's settings (ActivePolicyIteration supplies "
                "them); leave them unset on the selector you pass it"
            )
        loops_collector = (  # the loop's collector, where this selector has no source of its own
            collector is not None
            and self.env is None
            and self.collector is None
            and not self.num_workers
        )
        return SamplingPolicySelector(
            env=None if loops_collector else self.env if self.env is not None else env,
            psi=psi,
            num_steps=num_steps,
            num_repeats=num_repeats,
            lam=lam,
            device=device,
            max_design_bytes=self.max_design_bytes,
            num_workers=self.num_workers,
            fit=fit,
            collector=collector if loops_collector else self.collector,
            criterion=self.criterion,
        )

    def know_actions(self, encoding) -> None:
        """Collect with the env's action encoding (an
        :class:`~torch_api.data.actions.ActionEncoding`), once the loop has read it."""
        self.action_encoding = encoding

    def close(self) -> None:
        """Close the reward-free envs built from an env factory (see ``EnvPerBatch.close``)."""
        if self._collection is not None:
            self._collection.close()

    def _chosen_collection(self):
        if self._collection is None:
            raise ValueError(
                "the selector has no env: pass env= (or collector=), or pass the selector to "
                "ActivePolicyIteration(selector=...), which gives it its env"
            )
        return self._collection

    def seed_env(self, batch: int, seed: int, block_seeds: Sequence[int] | None = None) -> None:
        """Seed the reward-free environment of ``batch`` rows (with ``num_workers``: the
        workers' environments of the next :meth:`collect`), as
        :func:`torch_api.streams.seed_env`. ``batch``: :meth:`collection_rows` of the
        candidates the next :meth:`collect` gets (another batch is another env, unseeded)."""
        self._chosen_collection().seed(batch, seed, block_seeds)

    def collection_rows(self, candidates: Sequence, num_episodes: int | None = None) -> int:
        """The batch of the reward-free env that :meth:`collect` runs these candidates on:
        ``T·Z·K·M`` for the library's policies (one stacked rollout), ``Z·M`` for any other
        (candidate by candidate); the batch to :meth:`seed_env` before collecting."""
        m = self.num_episodes if num_episodes is None else int(num_episodes)
        return rollout_rows(candidates, (self.num_repeats, m, self.num_steps or 0))

    def collect(
        self, candidates: Sequence, iteration: int = 0, num_episodes: int | None = None
    ) -> TensorDictBase:
        """Reward-free episodes of every candidate and repeat, ``[*T, Z, K, M, N]``.

        ``*T`` are the candidates' trial dims (``param_dims``): rows of the environment batch
        are laid out ``(t, z, k, m)``. ``num_episodes`` is M (default: the selector's).
        """
        m = self.num_episodes if num_episodes is None else int(num_episodes)
        self._need(num_episodes=m, num_steps=self.num_steps)
        return self._chosen_collection()(
            candidates,
            shape=(self.num_repeats, m, self.num_steps),
            iteration=iteration,
            generator=self.generator,
            action_encoding=self.action_encoding,
        )

    @staticmethod
    def _need(**settings) -> None:
        missing = [name for name, value in settings.items() if value is None]
        if missing:
            raise ValueError(
                f"the selector needs {missing}: pass them, or pass the selector to "
                "ActivePolicyIteration(selector=...), which supplies them"
            )

    def _trial_chunks(self, episodes: TensorDictBase, earlier: TensorDictBase | None) -> list:
        """Slices of the trial dim such that each chunk's design stays under the byte budget."""
        trials, z, k, m, n = episodes.shape
        earlier_episodes = 0 if earlier is None else earlier.shape[-2]
        per_trial = z * k * (m + earlier_episodes) * n * self.psi.basis.num_features * 8 * 3
        size = max(1, self.max_design_bytes // per_trial)
        return [slice(a, min(a + size, trials)) for a in range(0, trials, size)]

    def _j_chunk(
        self, episodes, earlier, policy, trials: slice | None, flattening=1.0
    ) -> torch.Tensor:
        if trials is not None:
            episodes, policy = episodes[trials], policy.trial_slice(trials)
            earlier = None if earlier is None else earlier[trials]
            if isinstance(flattening, torch.Tensor):
                flattening = flattening[trials]
        if self.device is not None:
            episodes = episodes.to(self.device)
            earlier = None if earlier is None else earlier.to(self.device)
            policy = policy.to_device(self.device)
            if isinstance(flattening, torch.Tensor):
                flattening = flattening.to(self.device)
        j = self._j(episodes, earlier, policy, self.psi, self.lam, flattening=flattening)
        return j.cpu()

    def select(
        self,
        evaluation_policy,
        candidates: Sequence,
        earlier_episodes: TensorDictBase | None = None,
        iteration: int = 0,
        num_episodes: int | None = None,
        flattening: float | torch.Tensor = 1.0,
    ) -> Selection:
        """Run Algorithm 2 and return the chosen candidate with every J value.

        Args:
            evaluation_policy: pi_l (``action_probs``).
            candidates: the K sampling-policy candidates: the library's policies (collected in
                one batched rollout where the env allows) or any TensorDict module writing
                ``action`` and its sampling probability, e.g. TorchRL's
                ``ProbabilisticActor(..., return_log_prob=True)`` (collected candidate by
                candidate, Z·M rows each).
            earlier_episodes: the earlier sampling sets ``[M', N']`` (their rewards are not
                read), in the library's format or as TorchRL produces them (a ``Collector``'s
                batch; :func:`~torch_api.data.as_episodes`).
            iteration: tag stored with the collected episodes.
            num_episodes: M of this call (default: the selector's ``num_episodes``).
            flattening: ν of the flattened weights ``w^ν`` the fit uses (a number, or one per
                trial ``[*T]``): J is then the error of that fit (docs/flattening.md, eq. F2).
        """
        if not candidates:
            raise ValueError("candidates must not be empty")
        self._need(psi=self.psi)
        if earlier_episodes is not None:
            earlier_episodes = as_episodes(earlier_episodes, rewarded=False)
        episodes = self.collect(candidates, iteration, num_episodes)
        j_all = (
            torch.cat(
                [
                    self._j_chunk(episodes, earlier_episodes, evaluation_policy, trials, flattening)
                    for trials in self._trial_chunks(episodes, earlier_episodes)
                ]
            )
            if param_dims_of(evaluation_policy)
            else self._j_chunk(episodes, earlier_episodes, evaluation_policy, None, flattening)
        )
        j_mean = j_all.mean(-2)
        return Selection(
            index=torch.argmin(j_mean, dim=-1),
            j_mean=j_mean,
            j_all=j_all,
            reward_free_transitions=int(episodes["mask"].sum()),
            episodes=episodes,
        )
