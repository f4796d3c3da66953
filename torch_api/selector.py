"""Sampling-policy selection by the reward-free J criterion (paper section 3.4, Algorithm 2)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torch_api.data import (
    EnvPerBatch,
    as_episodes,
    collect_episodes,
    collect_with_collector,
    joinable,
    seed_env,
)
from torch_api.design import build_design
from torch_api.lstd import lstd_j_values
from torch_api.multiprocess import collect_episodes_in_workers
from torch_api.policies import ActionProbsPolicy
from torch_api.psi import PsiHat
from torch_api.solve import DEFAULT_LAMBDA, j_from_moments, weighted_moment

__all__ = [
    "PolicyStack",
    "SamplingPolicySelector",
    "Selection",
    "candidate_epsilons",
    "j_values",
]

PAPER_EPSILON_OFFSETS = (0.0, 0.15, 0.5, 0.85)  # eq. 59: candidates ε_l + offset
FITS = ("brm", "lstd")  # the paper's least-squares fit on psi_hat, or LSTD-Q (torch_api.lstd)
_STATE_ACTION_KEYS = (
    "observation",
    "action",
    "sample_probs",
    "sample_log_prob",
    ("next", "observation"),
    ("next", "terminated"),
    "mask",
)


def candidate_epsilons(epsilon: float, offsets: Sequence[float] = PAPER_EPSILON_OFFSETS) -> list:
    """ε of the sampling-policy candidates of eq. 59: ``[ε + o for o in offsets]`` capped at 1."""
    if not 0 <= epsilon <= 1:
        raise ValueError(f"epsilon must lie in [0, 1], got {epsilon}")
    return [min(1.0, epsilon + o) for o in offsets]


def j_values(
    candidate_episodes: TensorDictBase,
    earlier_episodes: TensorDictBase | None,
    policy,
    psi: PsiHat,
    lam: float = DEFAULT_LAMBDA,
) -> torch.Tensor:
    """J of every candidate from reward-free episodes (eq. 42-46, Algorithm 2 steps 2-4).

    For each leading index (a repeat z, a trial, ...): ``D̄_0`` = all candidates' episodes plus
    the earlier sampling sets; psi_hat is computed on ``D̄_0`` under the evaluation policy;
    ``Ũ = (1/n_0) Σ_{D̄_0} w x xᵀ``; candidate k's set ``Π_k`` = its own episodes plus the
    earlier sets, and ``J_k = tr(Ũ (A_k + λI)^{-1} C_k (A_k + λI)^{-1})``, all K in one
    batched call.

    Args:
        candidate_episodes: reward-free episodes ``[..., K, M, N]``.
        earlier_episodes: earlier sampling sets ``[M', N']`` (rewards, if any, are ignored) or
            None in the first iteration; TorchRL data as TorchRL produces it (a ``Collector``'s
            batch, ``env.rollout`` output) is converted (:func:`~torch_api.data.as_episodes`).
            Episodes of another length than the candidates' are padded (masked).
        policy: the evaluation policy (``action_probs``); parameters' leading dims prefix
            ``[...]``.
        psi: the psi_hat module.
        lam: λ.

    Returns:
        J ``[..., K]`` (float64).
    """
    if candidate_episodes.batch_dims < 3:
        raise ValueError(
            "candidate_episodes must have shape [..., K, M, N], "
            f"got {tuple(candidate_episodes.shape)}"
        )
    cand = candidate_episodes.select(*_STATE_ACTION_KEYS, strict=False)
    prev = None
    if earlier_episodes is not None:
        earlier_episodes = as_episodes(earlier_episodes, rewarded=False)
    if earlier_episodes is not None and earlier_episodes.shape[0] > 0:
        prev = earlier_episodes.select(*_STATE_ACTION_KEYS, strict=False)
        cand, prev = joinable([cand, prev])
    *lead, num_candidates, num_episodes, num_steps = cand.shape
    # Far candidates (ε up to 1) have skewed weights by design, and J measures exactly that:
    # the collapse warning is for fits on rewarded data, not for this reward-free pool.
    if psi.row_local:
        # Each row's psi_hat depends on the row alone: the earlier sets, which every Π_k and
        # every repeat shares, get their design once, not once per repeat.
        own = build_design(cand, policy, psi, min_ess_fraction=0.0)  # [..., K, M·N, B]
        own_x, own_w, n_own = own.x, own.w, own.num_samples.to(torch.float64)
        shared = None if prev is None else build_design(prev, policy, psi, min_ess_fraction=0.0)
    else:
        # Grouped or k-NN psi_hat averages over the data set D̄_0 of each repeat (all K
        # candidates' episodes, plus the earlier sets when there are any): pool first.
        pieces = [cand.reshape(*lead, num_candidates * num_episodes, num_steps)]
        if prev is not None:
            own_lead = prev.batch_dims - 2  # earlier sets [*T, M', N]: broadcast over repeats
            prev = prev.reshape(
                *prev.shape[:own_lead], *[1] * (len(lead) - own_lead), *prev.shape[-2:]
            )
            pieces.append(prev.expand(*lead, *prev.shape[-2:]).clone())
        design = build_design(torch.cat(pieces, dim=-2), policy, psi, min_ess_fraction=0.0)
        split = num_candidates * num_episodes * num_steps

        def own_rows(t: torch.Tensor) -> torch.Tensor:  # [..., K, M·N, *]
            return t.narrow(len(lead), 0, split).reshape(
                *lead, num_candidates, num_episodes * num_steps, *t.shape[len(lead) + 1 :]
            )

        own_x, own_w = own_rows(design.x), own_rows(design.w)
        n_own = own_rows(design.mask).sum(-1).to(torch.float64)
        shared = None
        if prev is not None:
            shared = design._replace(
                x=design.x.narrow(len(lead), split, design.x.shape[len(lead)] - split),
                w=design.w.narrow(len(lead), split, design.w.shape[len(lead)] - split),
                num_samples=design.num_samples - n_own.sum(-1),
            )
    # Unnormalised moments of each candidate's own rows and of the shared earlier rows; Ũ over
    # D̄_0 is their sum, with no pass of its own.
    a_own = weighted_moment(own_x, own_w)  # [..., K, B, B]
    c_own = weighted_moment(own_x, own_w.pow(2))
    a_shared = c_shared = own_x.new_zeros(own_x.shape[-1], own_x.shape[-1])
    n_shared = n_own.new_zeros(())
    if shared is not None:
        stretch = [1] * (len(lead) + 2 - shared.x.ndim)  # dims (repeats) the shared rows lack
        a_shared = weighted_moment(shared.x, shared.w)
        a_shared = a_shared.reshape(*a_shared.shape[:-2], *stretch, *a_shared.shape[-2:])
        c_shared = weighted_moment(shared.x, shared.w.pow(2)).reshape(a_shared.shape)
        n_shared = shared.num_samples.to(torch.float64)
        n_shared = n_shared.reshape(*n_shared.shape, *stretch)
    n_k = (n_own + n_shared.unsqueeze(-1))[..., None, None]
    n_0 = (n_own.sum(-1) + n_shared)[..., None, None]
    u_tilde = (a_own.sum(-3) + a_shared) / n_0  # eq. 42 over D̄_0
    a_k = (a_own + a_shared.unsqueeze(-3)) / n_k  # A of Π_k
    c_k = (c_own + c_shared.unsqueeze(-3)) / n_k.pow(2)  # C of Π_k
    if not (torch.isfinite(a_k).all() and torch.isfinite(c_k).all()):
        raise ValueError("the psi_hat design of the reward-free data contains NaN or inf")
    return j_from_moments(a_k, c_k, u_tilde.unsqueeze(-3), lam)


class PolicyStack(ActionProbsPolicy):
    """K policies side by side over one batched environment, rows laid out as ``[..., K, M]``.

    Row ``e`` of an environment batch of size ``R·K·M`` follows ``policies[(e // M) % K]``.
    Used to collect every candidate's reward-free episodes in a single batched rollout.

    Args:
        policies: K policies with ``action_probs``.
        episodes_per_policy: M, consecutive rows per policy.
        generator: random stream for sampling.
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
        return self._copy_streams(
            PolicyStack(
                [p.trial_slice(trials) for p in self.policies],
                episodes_per_policy=self.episodes_per_policy,
                **self._io_kwargs(),
            ),
            trials,
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
        collector: optional factory ``(policy, num_episodes) -> Collector`` of the user's own
            (:func:`~torch_api.data.collect_with_collector`): each candidate's ``Z·M``
            reward-free episodes are then read from it, candidate by candidate, instead of from
            ``env.rollout`` (the default, faster on batched envs). Without per-trial
            parameters only.

    Example:
        >>> from envs.chain_walk import ChainWalkEnv, CENTERS, TAU
        >>> from torch_api.basis import GaussianActionBasis
        >>> from torch_api.policies import LinearQPolicy
        >>> basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU,
        ...                             num_actions=2)
        >>> psi = PsiHat(basis=basis, gamma=0.9, mode="grouped")
        >>> pi = LinearQPolicy(basis=basis, theta=torch.ones(12), epsilon=0.15)
        >>> selector = SamplingPolicySelector(env=lambda e: ChainWalkEnv(batch_size=e, seed=0),
        ...                                   psi=psi, num_episodes=3, num_steps=10)
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
        trial_dims = tuple(getattr(candidates[0], "param_dims", ()))
        trials = math.prod(trial_dims)
        z, k, m, n = self.num_repeats, len(candidates), self.num_episodes, self.num_steps
        generator = self.generator or candidates[0].generator
        ids = torch.arange(k).reshape(k, 1, 1)
        if self.num_workers:
            stack = PolicyStack(candidates, episodes_per_policy=m, generator=generator)
            stack.block_generators = getattr(candidates[0], "block_generators", None)
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
            stack = PolicyStack(candidates, episodes_per_policy=m, generator=generator)
            stack.block_generators = getattr(candidates[0], "block_generators", None)
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
            if tuple(getattr(cand, "param_dims", ())):
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
        j = lstd_j_values if self.fit == "lstd" else j_values
        return j(episodes, earlier, policy, self.psi, self.lam).cpu()

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
            if tuple(getattr(evaluation_policy, "param_dims", ()))
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
