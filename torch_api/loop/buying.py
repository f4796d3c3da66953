"""Steps 1-2 of Algorithm 1: choose the sampling policy, buy its rewarded episodes, commit.

The rewarded episodes are the expensive part of a run (a robot's trials), so each slice is
committed to the run's store before the next is measured, and a resumed run buys only what is
missing, with the uninterrupted run's random streams (:class:`~torch_api.streams.TrialStreams`).
"""

from __future__ import annotations

import math
import time

import torch
from tensordict import TensorDict

from torch_api.data.actions import ActionEncoding
from torch_api.data.buffer import validate_episodes
from torch_api.data.episodes import to_log_prob_form
from torch_api.streams import seed_env

__all__ = ["RewardBuying"]


class RewardBuying:
    """The buying part of :class:`~torch_api.loop.iteration.ActivePolicyIteration` (a mixin: its
    methods read and set the loop's attributes)."""

    def _seed_iteration(self, iteration: int, num_episodes: int) -> None:
        """Re-seed the environments of iteration l (the policies' streams are derived per use)."""
        trials = math.prod(self.trial_dims)
        env = self._env_for(trials * num_episodes)
        if self._action_encoding is None:  # the policies write actions in the env's encoding
            self._action_encoding = ActionEncoding.from_spec(env.action_spec, env.batch_size)
            self.policy = self.policy.with_action_spec(self._action_encoding)
            if self.selector is not None:
                self.selector.action_encoding = self._action_encoding
        seed_env(env, *self.streams.env_seeds(iteration, "rewarded_env"))
        if self.selector is not None:
            z, k = self.selector.num_repeats, len(self._candidate_rules())
            batch = trials * z * k * num_episodes
            self.selector.seed_env(batch, *self.streams.env_seeds(iteration, "reward_free_env"))

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
        if self.selector is not None:
            earlier = self.rewarded.episodes() if len(self.rewarded) else None
            selection = self.selector.select(
                self.policy,
                self._reward_free_candidates() + list(self.extra_candidates),
                earlier,
                iteration=l_now,
                num_episodes=num_episodes,
                flattening=self.evaluation.flattening_for_j(self.history),
            )
            chosen = selection.index
            j_mean, j_all = selection.j_mean.tolist(), selection.j_all.tolist()
            reward_free_transitions = selection.reward_free_transitions
            if self.keep_reward_free:
                free = selection.episodes.reshape(*self.trial_dims, -1, self.num_steps)
        extra = self.trial_dims == () and int(chosen) >= len(rules)  # the user's own candidate
        self._selection = {
            "chosen": chosen,
            "sampling_rule": None if extra else rules[chosen],
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
        """Re-seed the rewarded env for episode m of iteration l."""
        seed_env(self._env_for(rows), *self.streams.slice_seeds(l_now, episode, "rewarded_env"))

    def _buy_slice(self, l_now: int, episodes: list[int], *, reseed: bool) -> None:
        """Buy episodes ``episodes`` (indices m) of iteration l and commit them.

        An episode with a bad reward (NaN, inf) is reported by index; the valid episodes of
        the slice are committed first.
        """
        trials = math.prod(self.trial_dims)
        rows = trials * len(episodes)
        if reseed:
            self._seed_slice(l_now, episodes[0], rows)
        streams = (  # the policy's sampling streams, fresh: the iteration's or the slice's
            self.streams.slice_sampling(l_now, episodes[0], "policy")
            if reseed
            else self.streams.sampling(l_now, "policy")
        )
        selection = self._selection
        chosen = selection["chosen"]
        where = f" (stored in {self.checkpoint_path})" if self.checkpoint_path else ""
        try:
            rule = selection["sampling_rule"]
            bought = self._collect(
                self._env_for(rows),
                self._with_rule(rule).with_streams(streams)
                if rule is not None
                else self.extra_candidates[int(chosen) - len(self._candidate_rules())],
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
