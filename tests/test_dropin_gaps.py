"""The drop-in gaps a TorchRL user hit (issue #25, item 5), each on TorchRL's and Gymnasium's
defaults: ``GymEnv("CartPole-v1")`` as it comes (one-hot ``int64`` actions), a real
``Collector``, ``ProbabilisticActor``."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule
from test_torchrl_dropin import _actor, _whole_trajectories
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, SerialEnv
from torchrl.modules import ProbabilisticActor

from envs.chain_walk import ChainWalkEnv
from torch_api import (
    ActivePolicyIteration,
    GaussianActionBasis,
    LinearQPolicy,
    RunSpec,
    SamplingPolicySelector,
    collect_episodes,
)
from torch_api.data.episodes import as_episodes


def _basis() -> GaussianActionBasis:
    return GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)


def _prefers_right(**kwargs) -> LinearQPolicy:
    theta = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=torch.float64)  # Q(s, 1) > Q(s, 0)
    return LinearQPolicy(basis=_basis(), theta=theta, epsilon=0.0, **kwargs)


def test_a_policy_without_action_spec_refuses_to_act_in_the_users_rollout_and_collector():
    """Before: it wrote the index 1 into GymEnv's one-hot env, which applied action 0 at every
    step while the rollout recorded 1."""
    env = GymEnv("CartPole-v1")
    policy = _prefers_right()
    with pytest.raises(ValueError, match="action_spec=env.action_spec"):
        env.rollout(5, policy)
    with pytest.raises(ValueError, match="action_spec=env.action_spec"):
        collector = Collector(
            env, policy, frames_per_batch=5, total_frames=5, auto_register_policy_transforms=False
        )
        next(iter(collector))
    # with the env's spec the action it prefers is the one applied
    rollout = GymEnv("CartPole-v1").rollout(5, _prefers_right(action_spec=env.action_spec))
    assert rollout["action"].argmax(-1).eq(1).all()


def test_a_batched_categorical_spec_is_accepted_as_action_spec():
    env = ChainWalkEnv(batch_size=4, seed=0)  # a Categorical spec of shape [4]
    policy = LinearQPolicy(
        basis=GaussianActionBasis(centers=torch.zeros(1, 1), tau=1.0, num_actions=2),
        theta=torch.ones(4),
        epsilon=0.1,
        action_spec=env.action_spec,
    )
    assert env.rollout(3, policy, break_when_any_done=False)["action"].shape == (4, 3)


def test_as_episodes_checks_the_actions_against_action_spec():
    """An index recorded in a one-hot env's rollout (what GymEnv applied as action 0) is refused;
    the one-hot actions of the same env pass."""
    env = GymEnv("CartPole-v1")
    wrong = env.rollout(5, _prefers_right(one_hot=False))  # the user said index, env is one-hot
    with pytest.raises(ValueError, match="not one-hot vectors"):
        as_episodes(wrong, rewarded=True, action_spec=env.action_spec)
    right = env.rollout(5, _prefers_right(action_spec=env.action_spec))
    assert as_episodes(right, rewarded=True, action_spec=env.action_spec)["action"].eq(1).all()


def test_a_categorical_actor_on_a_multi_row_one_hot_env_names_the_fix():
    env = SerialEnv(3, lambda: GymEnv("CartPole-v1"))
    net = TensorDictModule(torch.nn.Linear(4, 2), in_keys=["observation"], out_keys=["logits"])
    actor = ProbabilisticActor(
        net, in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )  # fmt: skip
    with pytest.raises(ValueError, match="OneHotCategorical"):
        collect_episodes(env, actor, num_episodes=3, num_steps=4, rewarded=True)
    env.close()


def _last_candidate(moments, lam):  # a criterion that always prefers the last candidate
    k = moments.a.shape[-3]
    return -torch.arange(k, dtype=torch.float64).expand(*moments.a.shape[:-3], k)


def test_the_users_actor_is_an_extra_candidate_of_the_loop():
    env = GymEnv("CartPole-v1")
    actor = _actor(env)
    spec = RunSpec.of(
        schedule=(2, 2), num_steps=8, gamma=0.95, num_repeats=1, candidate_offsets=(0.0, 0.5)
    )
    api = ActivePolicyIteration(
        spec,
        env=env,
        basis=_basis(),
        selector=SamplingPolicySelector(criterion=_last_candidate),
        extra_candidates=[actor],
    )
    history = api.run()
    assert [len(r.j_mean) for r in history] == [3, 3]  # K = 2 family candidates + the actor
    assert [r.chosen for r in history] == [2, 2] and history[0].sampling_rule is None
    bought = api.rewarded.episodes()
    assert "sample_log_prob" in bought.keys() and bought.shape == (4, 8)
    with pytest.raises(ValueError, match="extra_candidates"):
        ActivePolicyIteration(
            RunSpec.of(schedule=(1,), num_steps=4, gamma=0.9, mode="passive"),
            env=env,
            basis=_basis(),
            extra_candidates=[actor],
        )


def test_the_loops_collector_also_collects_the_reward_free_episodes():
    """The README's reading: ``collector=`` given to the loop serves the selector too (one
    without an env or collector of its own)."""
    calls = []

    def make_collector(policy, num_episodes):
        calls.append(num_episodes)
        return _whole_trajectories(6)(policy, num_episodes)

    spec = RunSpec.of(
        schedule=(2,), num_steps=6, gamma=0.95, num_repeats=1, candidate_offsets=(0.0, 0.5)
    )
    api = ActivePolicyIteration(
        spec, env=GymEnv("CartPole-v1"), basis=_basis(), collector=make_collector
    )
    api.run()
    assert sorted(calls) == [2, 2, 2]  # K = 2 reward-free calls of Z·M = 2, one rewarded of M


def test_a_factory_capped_by_at_most_rows_never_builds_more_rows():
    """A toy run (Z = 2, K = 4, M = 2) asks a factory for 16 reward-free rows: 16 worker
    processes with ``lambda rows: ParallelEnv(rows, make_env)``. Capped, it gets at most 2."""
    from torch_api import at_most_rows

    asked = []

    def rows_of_cartpole(rows):
        asked.append(rows)
        return SerialEnv(rows, lambda: GymEnv("CartPole-v1"))

    api = ActivePolicyIteration(
        RunSpec.of(schedule=(2, 2), num_steps=5, gamma=0.95, num_repeats=2),
        env=at_most_rows(rows_of_cartpole, 2),
        basis=_basis(),
    )
    api.run()
    api.close()
    assert asked and max(asked) <= 2
    assert api.rewarded.episodes().shape == (4, 5)
    assert api.reward_free.episodes().shape == (2 * 4 * 2 * 2, 5)  # Z·K·M_l per iteration


def _actor_candidate_run(seed: int) -> list:
    """A loop on a batched env factory (a SerialEnv of the rows asked for) with the user's
    actor as an extra candidate: its J values, every repeat and candidate."""
    env = GymEnv("CartPole-v1")
    actor = _actor(env)
    env.close()
    spec = RunSpec.of(
        schedule=(2, 1),
        num_steps=6,
        gamma=0.95,
        num_repeats=2,
        candidate_offsets=(0.0, 0.5),
        seed=seed,
    )
    api = ActivePolicyIteration(
        spec,
        env=lambda rows: SerialEnv(rows, lambda: GymEnv("CartPole-v1")),
        basis=_basis(),
        extra_candidates=[actor],
    )
    try:
        return [r.j_all for r in api.run()]
    finally:
        api.close()


def test_a_run_with_the_users_actor_as_a_candidate_is_reproducible():
    """The reward-free env the candidates are collected on (Z·M rows each, candidate by
    candidate) is the one seeded: before, the loop seeded an env of T·Z·K·M rows, which
    nobody used, and the collecting env kept whatever seed it was made with."""
    assert _actor_candidate_run(5) == _actor_candidate_run(5)
