"""Sampling-policy selection by the reward-free J criterion (paper section 3.4, Algorithm 2)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torch_api.candidates import PAPER_EPSILON_OFFSETS, candidate_epsilons
from torch_api.criterion import Criterion, j_eq46, j_values
from torch_api.data import (
    EnvPerBatch,
    as_episodes,
    collect_episodes,
    collect_with_collector,
    joinable,
    seed_env,
)
from torch_api.lstd import lstd_j_values
from torch_api.multiprocess import collect_episodes_in_workers
from torch_api.policy_base import ActionProbsPolicy, param_dims_of
from torch_api.psi import PsiHat
from torch_api.solve import DEFAULT_LAMBDA

__all__ = [
    "PAPER_EPSILON_OFFSETS",
    "PolicyStack",
    "SamplingPolicySelector",
    "Selection",
    "candidate_epsilons",
    "j_values",
]

FITS = ("brm", "lstd")  # the paper's least-squares fit on psi_hat, or LSTD-Q (torch_api.lstd)


class PolicyStack(ActionProbsPolicy):
    """K policies side by side over one batched environment, rows laid out as ``[..., K, M]``.

    Row ``e`` of an environment batch of size ``R·K·M`` follows ``policies[(e // M) % K]``.
    Used to collect every candidate's reward-free episodes in a single batched rollout.

    Args:
        policies: K policies with ``action_probs``.
        episodes_per_policy: M, consecutive rows per policy.
        generator: random stream for sampling (or ``streams=``: one generator per block of
            rows, e.g. per trial; see :func:`~torch_api.policy_base.sample_actions`).
    """

    def __init__(self, policies: Sequence, *, episodes_per_policy: int, generator=None, **io):
        if not policies:
            raise ValueError("policies must not be empty")
        super().__init__(num_actions=policies[0].num_actions, generator=generator, **io)
        self.policies = list(policies)
        self.episodes_per_policy = int(episodes_per_policy)

    def action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        rows = obs.shape[0]
        block = len(self.policies) * self.episodes_per_policy
        if rows % block:
            raise ValueError(f"a batch of {rows} rows is not a multiple of K·M = {block}")
        grid = obs.reshape(
            rows // block, len(self.policies), self.episodes_per_policy, *obs.shape[1:]
        )
        probs = [p.action_probs(grid[:, k]) for k, p in enumerate(self.policies)]
        return torch.stack(probs, 1).reshape(rows, *probs[0].shape[2:])

    def trial_slice(self, trials: slice) -> PolicyStack:
        """The stack of some trials only (each policy sliced; the per-trial streams too)."""
        return PolicyStack(
            [p.trial_slice(trials) for p in self.policies],
            episodes_per_policy=self.episodes_per_policy,
            **self._io_kwargs(trials),
        )


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

    Args:
        env: a TorchRL env with discrete actions used for reward-free rollouts, or a callable
            ``batch_size -> env``. An env whose batch size is ``Z·K·M`` is rolled out once;
            any other is rolled out candidate by candidate.
        psi: the psi_hat module (basis, γ, grouping).
        num_episodes: M, reward-free episodes per candidate and repeat.
        num_steps: N.
        num_repeats: Z (J' is the mean of Z values of J).
        lam: λ.
        generator: random stream of the sampling (default: the candidates' own).
        device: where psi_hat and J are computed (default: where the episodes are); rollouts
            stay on the environment's device.
        max_design_bytes: J is computed for as many trials at a time as keep the candidates'
            psi_hat design under about this many bytes (memory, not speed, is the limit at
            hundreds of trials).
        num_workers: if > 0, the reward-free episodes are collected in this many worker
            processes by TorchRL's ``MultiSyncCollector``
            (:func:`~torch_api.multiprocess.collect_episodes_in_workers`; for slow
            environments); ``env`` must then be a picklable callable ``batch_size -> env``,
            seeded through :meth:`seed_env`.
        fit: the learner whose error J estimates: ``"brm"`` (the paper's least-squares fit on
            psi_hat, :func:`j_values`) or ``"lstd"`` (LSTD-Q, beyond the paper,
            :func:`~torch_api.lstd.lstd_j_values`).
        criterion: with ``fit="brm"``, the criterion of the candidates' pooled moments
            (:data:`~torch_api.criterion.Criterion`, ``(PooledMoments, lam) -> [..., K]``):
            J of eq. 46 (:func:`~torch_api.criterion.j_eq46`) by default; a criterion of one's
            own is a function of the same signature.
        collector: optional factory ``(policy, num_episodes) -> Collector`` of the user's own
            (:func:`~torch_api.data.collect_with_collector`): each candidate's ``Z·M``
            reward-free episodes are then read from it, candidate by candidate, instead of from
            ``env.rollout`` (the default, faster on batched envs). Without per-trial
            parameters only.

    Example:
        >>> from torchrl.envs import GymEnv
        >>> from torch_api.basis import GaussianActionBasis
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
        env: EnvBase | Callable[[int], EnvBase],
        psi: PsiHat,
        num_episodes: int,
        num_steps: int,
        num_repeats: int = 5,
        lam: float = DEFAULT_LAMBDA,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        max_design_bytes: int = 2**29,
        num_workers: int = 0,
        fit: str = "brm",
        collector: Callable | None = None,
        criterion: Criterion = j_eq46,
    ) -> None:
        for name, value in (
            ("num_episodes", num_episodes),
            ("num_steps", num_steps),
            ("num_repeats", num_repeats),
        ):
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if not lam > 0:
            raise ValueError(f"lam must be > 0, got {lam}")
        self._envs = EnvPerBatch(env)
        self.psi = psi
        self.num_episodes = int(num_episodes)
        self.num_steps = int(num_steps)
        self.num_repeats = int(num_repeats)
        self.lam = float(lam)
        self.generator = generator
        self.device = None if device is None else torch.device(device)
        self.max_design_bytes = int(max_design_bytes)
        if num_workers < 0:
            raise ValueError(f"num_workers must be >= 0, got {num_workers}")
        if num_workers and not self._envs.is_factory:
            raise ValueError("num_workers needs env as a picklable callable batch_size -> env")
        self.num_workers = int(num_workers)
        if fit not in FITS:
            raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
        self.fit = fit
        if fit == "lstd" and criterion is not j_eq46:
            raise ValueError("criterion applies to fit='brm' (LSTD-Q has its own J)")
        self.criterion = criterion
        # the J of the learner, chosen once: LSTD-Q's, or the criterion of the pooled moments
        self._j = (
            lstd_j_values if fit == "lstd" else functools.partial(j_values, criterion=criterion)
        )
        if collector is not None and num_workers:
            raise ValueError("give either collector or num_workers, not both")
        self.collector = collector
        self.action_encoding = None  # the env's action encoding, where known (else probed)
        self._worker_env_seeds: tuple[int, list[int] | None] = (0, None)

    def close(self) -> None:
        """Close the reward-free envs built from an env factory (see ``EnvPerBatch.close``)."""
        self._envs.close()

    def env_for(self, batch: int) -> EnvBase:
        """The reward-free environment for a batch of ``batch`` rows (built once per size)."""
        return self._envs(batch)

    def seed_env(self, batch: int, seed: int, block_seeds: Sequence[int] | None = None) -> None:
        """Seed the reward-free environment of ``batch`` rows (with ``num_workers``: the
        workers' environments of the next :meth:`collect`), as :func:`torch_api.data.seed_env`."""
        if self.num_workers:
            self._worker_env_seeds = (seed, None if block_seeds is None else list(block_seeds))
        else:
            seed_env(self.env_for(batch), seed, block_seeds)

    def collect(self, candidates: Sequence, iteration: int = 0) -> TensorDictBase:
        """Reward-free episodes of every candidate and repeat, ``[*T, Z, K, M, N]``.

        ``*T`` are the candidates' trial dims (``param_dims``): rows of the environment batch
        are laid out ``(t, z, k, m)``.
        """
        if self.collector is not None or not all(
            isinstance(c, ActionProbsPolicy) for c in candidates
        ):
            return self._collect_each(candidates, iteration)
        trial_dims = param_dims_of(candidates[0])
        trials = math.prod(trial_dims)
        z, k, m, n = self.num_repeats, len(candidates), self.num_episodes, self.num_steps
        blocks = candidates[0].block_generators  # one stream per trial, else one for all
        streams = blocks if blocks is not None else self.generator or candidates[0].generator
        ids = torch.arange(k).reshape(k, 1, 1)
        if self.num_workers:
            stack = PolicyStack(candidates, episodes_per_policy=m, streams=streams)
            seed, block_seeds = self._worker_env_seeds
            episodes = collect_episodes_in_workers(
                self._envs.env,
                stack,
                action_spec=self.action_encoding,
                num_episodes=trials * z * k * m,
                num_steps=n,
                rewarded=False,
                num_workers=self.num_workers,
                blocks=trials,
                env_seed=seed,
                env_block_seeds=block_seeds,
                iteration=iteration,
            )
            episodes = episodes.reshape(*trial_dims, z, k, m, n)
            episodes["policy_id"] = ids.expand(episodes.shape).clone()
            return episodes
        env = self.env_for(trials * z * k * m)
        if len(env.batch_size) == 1 and env.batch_size[0] == trials * z * k * m:
            stack = PolicyStack(candidates, episodes_per_policy=m, streams=streams)
            episodes = collect_episodes(
                env,
                stack,
                num_episodes=trials * z * k * m,
                num_steps=n,
                rewarded=False,
                iteration=iteration,
            )
            episodes = episodes.reshape(*trial_dims, z, k, m, n)
            episodes["policy_id"] = ids.expand(episodes.shape).clone()
            return episodes
        if trial_dims:
            raise ValueError(
                f"candidates with per-trial parameters {trial_dims} need a reward-free env of "
                f"batch size T·Z·K·M = {trials * z * k * m} (pass a callable batch_size -> env)"
            )
        repeats = [
            torch.stack(
                [
                    collect_episodes(
                        env,
                        cand,
                        num_episodes=m,
                        num_steps=n,
                        rewarded=False,
                        iteration=iteration,
                        policy_id=i,
                    )
                    for i, cand in enumerate(candidates)
                ]
            )
            for _ in range(z)
        ]
        return torch.stack(repeats)

    def _collect_each(self, candidates: Sequence, iteration: int) -> TensorDictBase:
        """``[Z, K, M, N]`` episodes collected candidate by candidate (Z·M rows each): the way
        for candidates that are not the library's policies (e.g. a TorchRL
        ``ProbabilisticActor``), which cannot share one batched rollout."""
        z, m, n = self.num_repeats, self.num_episodes, self.num_steps
        if self.num_workers:
            raise ValueError(
                "num_workers needs every candidate to be a torch_api policy; got "
                f"{[type(c).__name__ for c in candidates]}"
            )
        for cand in candidates:
            if param_dims_of(cand):
                raise ValueError(
                    "candidates with per-trial parameters cannot be mixed with other policies"
                )
        parts = []
        for i, cand in enumerate(candidates):
            if self.collector is not None:
                episodes = collect_with_collector(
                    self.collector,
                    cand,
                    num_episodes=z * m,
                    num_steps=n,
                    rewarded=False,
                    iteration=iteration,
                    policy_id=i,
                )
            else:
                episodes = collect_episodes(
                    self.env_for(z * m),
                    cand,
                    num_episodes=z * m,
                    num_steps=n,
                    rewarded=False,
                    iteration=iteration,
                    policy_id=i,
                )
            parts.append(episodes.reshape(z, m, n))
        return torch.stack(joinable(parts), 1)

    def _trial_chunks(self, episodes: TensorDictBase, earlier: TensorDictBase | None) -> list:
        """Slices of the trial dim such that each chunk's design stays under the byte budget."""
        trials, z, k, m, n = episodes.shape
        earlier_episodes = 0 if earlier is None else earlier.shape[-2]
        per_trial = z * k * (m + earlier_episodes) * n * self.psi.basis.num_features * 8 * 3
        size = max(1, self.max_design_bytes // per_trial)
        return [slice(a, min(a + size, trials)) for a in range(0, trials, size)]

    def _j_chunk(self, episodes, earlier, policy, trials: slice | None) -> torch.Tensor:
        if trials is not None:
            episodes, policy = episodes[trials], policy.trial_slice(trials)
            earlier = None if earlier is None else earlier[trials]
        if self.device is not None:
            episodes = episodes.to(self.device)
            earlier = None if earlier is None else earlier.to(self.device)
            policy = policy.to_device(self.device)
        return self._j(episodes, earlier, policy, self.psi, self.lam).cpu()

    def select(
        self,
        evaluation_policy,
        candidates: Sequence,
        earlier_episodes: TensorDictBase | None = None,
        iteration: int = 0,
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
        """
        if not candidates:
            raise ValueError("candidates must not be empty")
        if earlier_episodes is not None:
            earlier_episodes = as_episodes(earlier_episodes, rewarded=False)
        episodes = self.collect(candidates, iteration)
        j_all = (
            torch.cat(
                [
                    self._j_chunk(episodes, earlier_episodes, evaluation_policy, trials)
                    for trials in self._trial_chunks(episodes, earlier_episodes)
                ]
            )
            if param_dims_of(evaluation_policy)
            else self._j_chunk(episodes, earlier_episodes, evaluation_policy, None)
        )
        j_mean = j_all.mean(-2)
        return Selection(
            index=torch.argmin(j_mean, dim=-1),
            j_mean=j_mean,
            j_all=j_all,
            reward_free_transitions=int(episodes["mask"].sum()),
            episodes=episodes,
        )
