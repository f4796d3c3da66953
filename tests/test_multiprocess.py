"""Reward-free collection in worker processes (TorchRL's MultiSyncCollector)."""

from __future__ import annotations

import pytest
import torch

from counter_rng import CounterStreams
from envs.batting import BASIS_TAU, BattingEnv, basis_centers
from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.collection.collect import collect_episodes
from torch_api.collection.multiprocess import collect_episodes_in_workers
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.psi import PsiHat
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.policies import LinearQPolicy


def batting_env(rows: int) -> BattingEnv:  # top level: the workers unpickle it by name
    return BattingEnv(batch_size=rows, nthread=1)


def chain_env(rows: int) -> ChainWalkEnv:
    return ChainWalkEnv(batch_size=rows)


def _batting_run(workers: int) -> tuple[list, torch.Tensor]:
    spec = RunSpec.of(
        schedule=(2, 2),
        num_steps=10,
        gamma=1.0,
        num_repeats=2,
        psi_mode="single",
        num_trials=3,
        seed=11,
    )
    api = ActivePolicyIteration(
        spec,
        env=batting_env,
        selector=SamplingPolicySelector(env=batting_env, num_workers=workers),
        basis=GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=2),
    )
    history = api.run()
    return [(r.chosen, r.j_all) for r in history], api.theta


def test_workers_give_the_numbers_of_one_process():
    """Per-trial streams travel with the trials: J, choices and θ are bit-identical."""
    in_workers, theta_workers = _batting_run(workers=2)
    in_process, theta_process = _batting_run(workers=0)
    assert in_workers == in_process
    assert torch.equal(theta_workers, theta_process)


def test_workers_draw_the_streams_they_are_given_and_leave_the_callers_alone():
    """Per-trial streams travel with the trials: the workers' episodes equal one in-process
    rollout's (on the chain walk, whose resets draw the initial states), and the caller's
    generators are not moved on (nothing replays the workers' draws: a caller derives fresh
    streams for every use)."""
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    policy = LinearQPolicy(
        basis=basis, theta=torch.stack([torch.ones(12), torch.linspace(-1, 1, 12)]), epsilon=0.5
    )

    def streams():  # streams already used once: the workers go on from where they are
        used = CounterStreams([5, 6])
        used.uniform((2,))
        return used

    given = streams()
    before = given.calls
    in_workers = collect_episodes_in_workers(
        chain_env,
        policy.with_streams(given),
        num_episodes=3,
        num_steps=4,
        rewarded=True,
        num_workers=2,
        env_block_seeds=[7, 8],
    )
    assert given.calls == before
    env = ChainWalkEnv(batch_size=6)
    env.set_block_seeds([7, 8])
    in_process = collect_episodes(
        env, policy.with_streams(streams()), num_episodes=3, num_steps=4, rewarded=True
    )
    assert in_workers.shape == in_process.shape == (2, 3, 4)
    for key in ("observation", "action", "sample_probs", "mask", ("next", "reward")):
        assert torch.equal(in_workers[key], in_process[key]), key


def test_workers_without_trial_streams_are_reproducible():
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)

    def collect():
        policy = LinearQPolicy(
            basis=basis,
            theta=torch.ones(12),
            epsilon=0.5,
            generator=torch.Generator().manual_seed(4),
        )
        return collect_episodes_in_workers(
            chain_env, policy, num_episodes=6, num_steps=5, rewarded=True, num_workers=2
        )

    first, second = collect(), collect()
    assert first.shape == (6, 5)
    assert torch.equal(first["observation"], second["observation"])
    assert torch.equal(first["action"], second["action"])
    assert "reward" in first["next"].keys()


def test_workers_need_a_factory_and_a_positive_count():
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    policy = LinearQPolicy(basis=basis, theta=torch.ones(12), epsilon=0.5)
    with pytest.raises(ValueError, match="num_workers"):
        collect_episodes_in_workers(
            chain_env, policy, num_episodes=2, num_steps=3, rewarded=False, num_workers=0
        )
    with pytest.raises(ValueError, match="picklable callable"):
        SamplingPolicySelector(
            env=ChainWalkEnv(batch_size=2),
            psi=PsiHat(basis=basis, gamma=0.9),
            num_episodes=2,
            num_steps=3,
            num_workers=2,
        )
