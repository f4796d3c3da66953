"""Steps 1-2 of Algorithm 1: choose the sampling policy, buy its rewarded episodes, commit.

The rewarded episodes are the expensive part of a run (a robot's trials), so each slice is
committed to the run's store before the next is measured, and a resumed run buys only what is
missing, with the uninterrupted run's random streams (:class:`~torch_api.streams.TrialStreams`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict
from torch import nn

from torch_api.collection.collect import EnvPerBatch
from torch_api.data.buffer import EpisodeBuffer, validate_episodes
from torch_api.data.episodes import to_log_prob_form
from torch_api.loop.durable import DurableRun
from torch_api.loop.policies import LoopPolicies
from torch_api.loop.records import Choice
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.streams import TrialStreams, seed_env

__all__ = ["RewardBuyer"]


class RewardBuyer:
    """Buys the rewarded episodes of each iteration with the sampling policy it chooses.

    It holds the coming iteration's :class:`Choice` and the episodes bought so far by index m
    (:attr:`bought`) until the iteration's M_l are complete; everything else is given.

    Args:
        envs: the rewarded environments, one per batch size.
        collect: the source of episodes, ``collect(env, policy, **kwargs)``
            (:func:`~torch_api.collection.collect.rollouts_or`).
        streams: the run's random streams.
        policies: the loop's policies (the candidates of pi_l, their rules).
        selector: the bound selector (active), or None (passive: pi_l samples).
        durable: the run's store, where each choice and slice is committed; its layout
            (:class:`~torch_api.loop.durable.RunLayout`) gives the trial dims ``()`` or
            ``(T,)``, the slices bought (``rewarded_slice``: ``"all"`` M_l rows in one rollout,
            or ``"episode"`` one at a time) and whether reward-free episodes are kept.
        num_steps: N.
        reward_free: the loop's buffer of reward-free episodes (extended when they are kept).
        extra_candidates: the user's own candidates, K, K+1, … after the family's.

    Attributes:
        reward_free_transitions: reward-free transitions collected so far, per trial ``[*T]``,
            counted with each choice before its commit (a hook that raises after the commit
            leaves them counted, as a resumed run counts them).
    """

    def __init__(
        self,
        *,
        envs: EnvPerBatch,
        collect: Callable,
        streams: TrialStreams,
        policies: LoopPolicies,
        selector: SamplingPolicySelector | None,
        durable: DurableRun,
        num_steps: int,
        trial_dims: tuple[int, ...],
        rewarded_slice: str,
        keep_reward_free: bool,
        reward_free_capacity: int,
        extra_candidates: Sequence[nn.Module] = (),
    ) -> None:
        self.envs, self.collect, self.streams = envs, collect, streams
        self.policies, self.selector, self.durable = policies, selector, durable
        self.num_steps, self.extra_candidates = num_steps, tuple(extra_candidates)
        self.trial_dims = trial_dims
        self.rewarded_slice = rewarded_slice
        self.keep_reward_free = keep_reward_free
        self.reward_free = EpisodeBuffer(rewarded=False, capacity=reward_free_capacity)
        self.reward_free_transitions = torch.zeros(self.trial_dims, dtype=torch.long)
        self.choice: Choice | None = None  # the coming iteration's, once committed
        self.bought: dict[int, TensorDict] = {}  # its episodes bought so far, by index m
        self.pending: Choice | None = None  # the choice whose M_l episodes are all bought
        self._fresh = False  # chosen here, not restored: (with "all") bought in one rollout

    @property
    def _trials(self) -> int:
        return math.prod(self.trial_dims)

    def restore(self, restored) -> None:
        """Continue from a stored run (:class:`~torch_api.loop.durable.Restored`): its
        reward-free episodes and counts, and the iteration under way (its choice, the episodes
        bought of it, or the choice whose episodes are all bought)."""
        self.reward_free = restored.reward_free
        self.reward_free_transitions = restored.reward_free_transitions
        self.choice, self.bought, self._fresh = restored.choice, dict(restored.bought), False
        self.pending = restored.pending

    def take_choice(self) -> Choice:
        """The choice of the iteration whose rewards are bought (or under way, when the user
        bought them), handed over once to its record."""
        choice = self.pending or self.choice
        if choice is None:
            raise RuntimeError("no sampling policy was chosen in this iteration")
        self.pending, self.choice, self.bought = None, None, {}
        return choice

    def sampling_policy(self, l_now: int, policy) -> nn.Module:
        """The chosen sampling policy of iteration l drawing from the iteration's sampling
        streams (what a one-rollout :meth:`buy` collects with)."""
        choice = self.choice or self.pending
        if choice is None:
            raise RuntimeError(f"iteration {l_now}: no sampling policy chosen")
        if choice.sampling_rule is None:
            return self._extra(choice, l_now)
        rule_policy = self.policies.with_rule(policy, choice.sampling_rule)
        return rule_policy.with_streams(self.streams.sampling(l_now, "policy"))

    def _extra(self, choice: Choice, l_now: int) -> nn.Module:
        """The user's own candidate the choice names."""
        return self.extra_candidates[int(choice.chosen) - len(self.policies.candidate_rules(l_now))]

    def select(
        self,
        l_now: int,
        num_episodes: int,
        policy,
        earlier,
        flattening,
        *,
        reward_free_episodes: int | None = None,
    ) -> TensorDict | None:
        """Step 1: seed iteration l, choose the sampling policy (J'), commit the choice.

        Args:
            l_now: l; num_episodes: M_l.
            policy: pi_l; earlier: the rewarded episodes so far ``[*T, M, N]`` (or None).
            flattening: ν of J (:meth:`~torch_api.core.fit.PolicyEvaluation.flattening_for_j`).
            reward_free_episodes: reward-free episodes per candidate and repeat (default M_l).

        Returns:
            The reward-free episodes collected ``[*T, Z·K·M_l, N]``, if kept, else None.
        """
        started, cpu_started = time.perf_counter(), time.process_time()
        rules = self.policies.candidate_rules(l_now)
        candidates = None
        if self.selector is not None:
            candidates = self.policies.reward_free_candidates(policy, l_now)
            candidates += list(self.extra_candidates)
        free_episodes = num_episodes if reward_free_episodes is None else reward_free_episodes
        self._seed_iteration(l_now, num_episodes, candidates, free_episodes)
        chosen = torch.zeros(self.trial_dims, dtype=torch.long)
        j_mean = j_all = free = None
        reward_free_transitions = torch.zeros(self.trial_dims, dtype=torch.long)
        if self.selector is not None:
            selection = self.selector.select(
                policy,
                candidates,
                earlier,
                iteration=l_now,
                num_episodes=free_episodes,
                flattening=flattening,
            )
            chosen = selection.index
            j_mean, j_all = selection.j_mean.tolist(), selection.j_all.tolist()
            # each trial's own count (episodes may end early): [*T, Z·K·M·N] summed
            mask = selection.episodes["mask"].reshape(*self.trial_dims, -1)
            reward_free_transitions = mask.sum(-1)
            if self.keep_reward_free:
                free = selection.episodes.reshape(*self.trial_dims, -1, self.num_steps)
        extra = self.trial_dims == () and int(chosen) >= len(rules)  # the user's own candidate
        choice = Choice(
            chosen=chosen,
            sampling_rule=None if extra else rules[chosen],
            j_mean=j_mean,
            j_all=j_all,
            reward_free_transitions=reward_free_transitions.tolist(),
            seconds=time.perf_counter() - started,
            cpu_seconds=time.process_time() - cpu_started,
        )
        self.choice, self.bought, self._fresh = choice, {}, True
        self.reward_free_transitions += reward_free_transitions
        if free is not None:
            self.reward_free.extend(free)
        self.durable.put_selection(l_now, choice.row(), free)
        return free

    def _seed_iteration(
        self, iteration: int, num_episodes: int, candidates, free_episodes: int
    ) -> None:
        """Re-seed the environments of iteration l (the policies' streams are derived per use):
        the reward-free env is the one the candidates are collected on (``T·Z·K·M_l`` rows for
        the library's policies, ``Z·M_l`` candidate by candidate with the user's own)."""
        rows = self._trials * num_episodes
        seed_env(self.envs(rows), *self.streams.env_seeds(iteration, "rewarded_env"))
        if self.selector is not None:
            batch = self.selector.collection_rows(candidates, free_episodes)
            self.selector.seed_env(batch, *self.streams.env_seeds(iteration, "reward_free_env"))

    def buy(self, l_now: int, num_episodes: int, policy, *, kept: int = 0) -> TensorDict:
        """Step 2: buy and commit the M_l episodes of the choice not bought yet; all M_l
        ``[*T, M_l, N]`` are returned, and the buyer is empty again.

        A choice made in this run (``rewarded_slice="all"``) buys all rows in one rollout
        continuing the iteration's streams; single episodes (a robot, or episodes left to buy
        after a resume or a failure) have streams of their own. ``kept`` (the episodes bought
        before, per trial) goes into the message of a failure.
        """
        if self.choice is None:
            raise RuntimeError(f"iteration {l_now}: no sampling policy chosen to buy with")
        one_slice, self._fresh = self.rewarded_slice == "all" and self._fresh, False
        missing = [m for m in range(num_episodes) if m not in self.bought]
        for episodes in [missing] if one_slice else [[m] for m in missing]:
            self.buy_slice(l_now, episodes, policy, reseed=not one_slice, kept=kept)
        bought = torch.stack([self.bought[m] for m in range(num_episodes)], len(self.trial_dims))
        self.pending, self.choice, self.bought = self.choice, None, {}
        return bought

    def buy_slice(
        self, l_now: int, episodes: list[int], policy, *, reseed: bool, kept: int = 0
    ) -> None:
        """Buy episodes ``episodes`` (indices m) of iteration l with the choice, commit them.

        An episode with a bad reward (NaN, inf) is reported by index; the valid episodes of
        the slice are committed first.
        """
        rows = self._trials * len(episodes)
        if reseed:
            seeds = self.streams.slice_seeds(l_now, episodes[0], "rewarded_env")
            seed_env(self.envs(rows), *seeds)
        streams = (  # the policy's sampling streams, fresh: the iteration's or the slice's
            self.streams.slice_sampling(l_now, episodes[0], "policy")
            if reseed
            else self.streams.sampling(l_now, "policy")
        )
        chosen, rule = self.choice.chosen, self.choice.sampling_rule
        where = f" (stored in {self.durable.path})" if self.durable.path else ""
        try:
            bought = self.collect(
                self.envs(rows),
                self.policies.with_rule(policy, rule).with_streams(streams)
                if rule is not None
                else self._extra(self.choice, l_now),
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
                f"{type(error).__name__}: {error}. The {kept} episodes bought before (per "
                f"trial) are kept in api.rewarded{where}; none of this batch was stored"
            ) from error
        if self.extra_candidates:  # one probability form for the family's and the user's
            bought = to_log_prob_form(bought)
        good, bad = {}, []
        for i, m in enumerate(episodes):
            one = bought[..., i : i + 1, :]
            try:
                validate_episodes(one, rewarded=True)
            except ValueError as error:
                bad.append(f"episode {m}{self._trial_of_bad(one)}: {error}")
            else:
                good[m] = one.squeeze(-2)
        if good:
            self.durable.put_episodes(l_now, good)
        self.bought.update(good)
        if bad:
            raise ValueError(
                f"iteration {l_now}: {'; '.join(bad)}. The {len(good)} valid episodes of this "
                f"slice are kept{where}; a resume buys the others again"
            )

    def _trial_of_bad(self, one: TensorDict) -> str:
        """`` of trial t`` for the first trial whose episode fails the checks (trials only)."""
        for t in range(self._trials) if self.trial_dims else ():
            try:
                validate_episodes(one.reshape(-1, *one.shape[-2:])[t : t + 1], rewarded=True)
            except ValueError:
                return f" of trial {t}"
        return ""
