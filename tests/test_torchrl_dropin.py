"""The library dropped into TorchRL pipelines as they come: Gymnasium envs through ``GymEnv``
with its defaults (one-hot actions), batched envs from factories, a real ``Collector``'s
batches, TorchRL's exploration types and a ``ProbabilisticActor``."""

import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, ParallelEnv, SerialEnv, StepCounter, Transform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import OneHotCategorical, ProbabilisticActor

from torch_api import (
    ActivePolicyIteration,
    DurableRun,
    EpisodeBuffer,
    GaussianActionBasis,
    LinearQPolicy,
    PsiHat,
    RunSpec,
    SamplingPolicySelector,
    build_design,
    collect_episodes,
)
from torch_api.policies import greedy_actions
from torch_api.runs.store import RunStore


def cartpole():
    return GymEnv("CartPole-v1")  # TorchRL's defaults: a one-hot action spec, int64


def cartpole_rows(rows: int) -> SerialEnv:
    return SerialEnv(rows, cartpole)


def cartpole_processes(rows: int) -> ParallelEnv:
    return ParallelEnv(rows, cartpole)


def cartpole_basis() -> GaussianActionBasis:
    centers = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.5, 0.1, 0.5], [0.0, -0.5, -0.1, -0.5]])
    return GaussianActionBasis(centers=centers, tau=1.0, num_actions=2)


def applied_share(episodes) -> float:
    """Share of real steps whose recorded action is the push CartPole applied.

    The push (action 1: right, 0: left) of ±10 N dominates the cart's acceleration, so the sign
    of the velocity change over the step tells which action the env applied.
    """
    mask = episodes["mask"]
    change = episodes["next", "observation"][..., 1] - episodes["observation"][..., 1]
    applied = (change > 0).long()
    return (applied[mask] == episodes["action"][mask]).double().mean().item()


def test_one_hot_cartpole_records_the_applied_actions():
    spec = RunSpec.of(
        schedule=(4, 3),
        num_steps=15,
        gamma=0.95,
        num_repeats=1,
        candidate_offsets=(0.0, 0.5),
        psi_mode="single",
        seed=0,
    )
    api = ActivePolicyIteration(spec, env=cartpole(), basis=cartpole_basis())
    api.run()
    assert applied_share(api.rewarded.episodes()) == 1.0
    assert applied_share(api.reward_free.episodes()) == 1.0
    # the learned policy writes the env's own encoding and runs in env.rollout as it is
    env = cartpole()
    rollout = env.rollout(5, api.policy)
    assert env.action_spec.is_in(rollout[0]["action"])


def test_a_policy_whose_actions_do_not_fit_the_spec_is_refused_before_any_step():
    calls = []

    def index_policy(td):  # an index where the env expects a one-hot vector
        calls.append(1)
        td["action"] = torch.tensor(1)
        td["sample_probs"] = torch.tensor([0.5, 0.5], dtype=torch.float64)
        return td

    with pytest.raises(ValueError, match="is_in"):
        collect_episodes(cartpole(), index_policy, num_episodes=1, num_steps=3, rewarded=True)
    assert len(calls) == 1


def test_exploration_types_and_the_global_generator():
    basis = cartpole_basis()
    theta = torch.randn(8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    policy = LinearQPolicy(basis=basis, theta=theta, epsilon=0.6, one_hot=False)
    obs = torch.randn(400, 4, generator=torch.Generator().manual_seed(1))
    greedy = greedy_actions(policy.q_values(obs))
    from tensordict import TensorDict

    def act(mode=None):
        td = TensorDict({"observation": obs}, batch_size=[400])
        if mode is None:
            return policy(td)
        with set_exploration_type(mode):
            return policy(td)

    for mode in (ExplorationType.DETERMINISTIC, ExplorationType.MODE):
        td = act(mode)
        assert torch.equal(td["action"], greedy)
        assert torch.equal(td["sample_probs"].argmax(-1), greedy)  # what was really drawn
        assert (td["sample_probs"].max(-1).values == 1).all()
    assert not torch.equal(act(ExplorationType.RANDOM)["action"], greedy)
    torch.manual_seed(7)
    first = act()["action"]
    torch.manual_seed(7)
    assert torch.equal(act()["action"], first)  # torch.manual_seed governs an unseeded policy
    # one-hot actions in the spec's dtype (GymEnv: int64), accepted by the spec
    spec = cartpole().action_spec
    one_hot = policy.with_action_spec(spec)
    action = one_hot(TensorDict({"observation": obs[0]}, batch_size=[]))["action"]
    assert action.dtype == spec.dtype and spec.is_in(action)


@pytest.mark.parametrize("factory", [cartpole_rows, cartpole_processes], ids=["serial", "parallel"])
def test_batched_env_factories(factory):
    parallel = factory is cartpole_processes
    spec = RunSpec.of(
        schedule=(1,) if parallel else (2,),  # ParallelEnv: T·M = 2 worker processes
        num_steps=8,
        gamma=0.95,
        mode="passive" if parallel else "active",
        **({} if parallel else {"num_repeats": 1}),
        candidate_offsets=(0.0, 0.5),
        num_trials=2,
        seed=0,
    )
    # two trials: the env is built per batch size by the factory
    api = ActivePolicyIteration(spec, env=factory, basis=cartpole_basis())
    try:
        api.run()
        assert applied_share(api.rewarded.episodes()) == 1.0
        assert api.rewarded_transitions > 0 and torch.isfinite(api.theta).all()
    finally:
        built = list(api.envs.built.values())
        api.close()
    assert built and all(env.is_closed for env in built)


def test_frozen_lake_index_observations_with_grouped_psi_hat():
    def frozen_lake():
        return GymEnv("FrozenLake-v1", categorical_action_encoding=True)  # obs: an int index

    centers = torch.tensor([[0.0], [5.0], [10.0], [15.0]])
    basis = GaussianActionBasis(centers=centers, tau=3.0, num_actions=4)
    spec = RunSpec.of(
        schedule=(3, 2),
        num_steps=8,
        gamma=0.9,
        num_repeats=1,
        candidate_offsets=(0.0, 0.5),
        psi_mode="grouped",
        seed=0,
    )
    api = ActivePolicyIteration(spec, env=frozen_lake(), basis=basis)
    api.run()
    assert torch.isfinite(api.theta).all()
    from torch_api import psi_hat, state_action_groups

    episodes = api.rewarded.episodes()
    # the functional pieces on the raw index observations: float64 all the way to Ũ
    obs = episodes["observation"].long().reshape(-1, 1)
    action = episodes["action"].reshape(-1)
    groups = state_action_groups(obs, action)
    phi = basis.phi(obs, action).float()
    rows = psi_hat(phi, phi, 0.9, groups=groups)
    assert rows.dtype == torch.float64
    weights = torch.ones(rows.shape[0], dtype=torch.float64)
    u_tilde = (rows * weights[:, None]).mT @ rows / rows.shape[0]
    assert u_tilde.dtype == torch.float64 and torch.isfinite(u_tilde).all()


def _collector_policy(env, epsilon=0.4):
    theta = torch.randn(8, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    return LinearQPolicy(
        basis=cartpole_basis(), theta=theta, epsilon=epsilon, action_spec=env.action_spec
    )


def _short_cartpole():
    return TransformedEnv(cartpole(), StepCounter(max_steps=6))


def _collector_batches(env, policy, *, frames_per_batch, total_frames, **options):
    """Every batch a real TorchRL ``Collector`` yields (TorchRL's defaults but for ``options``)."""
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        auto_register_policy_transforms=False,
        **options,
    )
    batches = [batch.clone() for batch in collector]
    collector.shutdown()
    return batches


def test_flat_collector_batches_join_a_trajectory_cut_at_the_batch_end():
    env = _short_cartpole()
    env.set_seed(0)
    torch.manual_seed(0)
    batches = _collector_batches(env, _collector_policy(env), frames_per_batch=8, total_frames=16)
    ids = [set(b["collector", "traj_ids"].tolist()) for b in batches]
    assert ids[0] & ids[1], "the test needs a trajectory spanning both batches"
    pieces = EpisodeBuffer(rewarded=True, capacity=10)
    for batch in batches:
        pieces.extend(batch)
    whole = EpisodeBuffer(rewarded=True, capacity=10)
    whole.extend(torch.cat(batches))  # the same steps in one batch: every trajectory whole
    a, b = pieces.episodes(), whole.episodes()
    assert a.shape == b.shape and len(a) == len(ids[0] | ids[1])
    assert torch.equal(a["mask"], b["mask"])
    assert torch.equal(a["observation"][a["mask"]], b["observation"][b["mask"]])
    evaluation = _collector_policy(env, epsilon=0.1)
    psi = PsiHat(basis=cartpole_basis(), gamma=0.95)
    w_pieces = build_design(a, evaluation, psi, min_ess_fraction=0).w
    w_whole = build_design(b, evaluation, psi, min_ess_fraction=0).w
    assert torch.equal(w_pieces, w_whole)
    assert applied_share(a) == 1.0


def test_split_trajs_batch_in_buffer_and_as_earlier_episodes():
    env = _short_cartpole()
    env.set_seed(1)
    (batch,) = _collector_batches(
        env, _collector_policy(env), frames_per_batch=20, total_frames=20, split_trajs=True
    )
    assert batch["next", "terminated"].shape[-1] == 1  # TorchRL's trailing singleton dim
    buffer = EpisodeBuffer(rewarded=True, capacity=10)
    buffer.extend(batch)
    episodes = buffer.episodes()
    assert torch.equal(episodes["mask"], batch["collector", "mask"])
    assert torch.equal(episodes["next", "reward"], batch["next", "reward"].squeeze(-1))
    # padded steps contribute nothing: garbage there leaves the design unchanged
    psi = PsiHat(basis=cartpole_basis(), gamma=0.95)
    evaluation = _collector_policy(env, epsilon=0.1)
    design = build_design(episodes, evaluation, psi)
    noisy = episodes.clone()
    noisy["observation"][~noisy["mask"]] = 50.0
    noisy["next", "reward"][~noisy["mask"]] = 1e6
    other = build_design(noisy, evaluation, psi)
    assert torch.equal(design.x, other.x) and torch.equal(design.reward, other.reward)
    assert torch.equal(design.w, other.w)
    # the selector takes the collector batch itself as the earlier sampling set (N = 6 there,
    # 8 for the candidates)
    selector = SamplingPolicySelector(
        env=lambda rows: cartpole_rows(rows), psi=psi, num_episodes=2, num_steps=8, num_repeats=1
    )
    choice = selector.select(evaluation, [evaluation, evaluation.with_rule(epsilon=0.6)], batch)
    assert choice.j_mean.shape == (2,) and torch.isfinite(choice.j_mean).all()


def _actor(env):
    torch.manual_seed(4)
    net = TensorDictModule(torch.nn.Linear(4, 2), in_keys=["observation"], out_keys=["logits"])
    return ProbabilisticActor(
        net,
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
        return_log_prob=True,
        spec=env.action_spec,
    )


def test_probabilistic_actor_collects_and_is_a_candidate():
    env = cartpole()
    actor = _actor(env)
    episodes = collect_episodes(env, actor, num_episodes=3, num_steps=10, rewarded=True)
    assert applied_share(episodes) == 1.0
    assert "sample_log_prob" in episodes.keys()
    # per-decision weights from the actor's own log-probabilities (eq. 21)
    evaluation = _collector_policy(env, epsilon=0.2)
    psi = PsiHat(basis=cartpole_basis(), gamma=0.95)
    design = build_design(episodes, evaluation, psi, min_ess_fraction=0)
    target = evaluation.action_probs(episodes["observation"].double())
    taken = target.gather(-1, episodes["action"].unsqueeze(-1)).squeeze(-1)
    expected = (taken.log() - episodes["sample_log_prob"]).cumsum(-1).exp() * episodes["mask"]
    torch.testing.assert_close(design.w, expected.reshape(-1), rtol=1e-12, atol=0)
    # a candidate beside the library's own
    selector = SamplingPolicySelector(
        env=lambda rows: cartpole(), psi=psi, num_episodes=2, num_steps=8, num_repeats=2
    )
    choice = selector.select(evaluation, [evaluation, actor], earlier_episodes=episodes)
    assert choice.j_all.shape == (2, 2) and torch.isfinite(choice.j_all).all()
    assert applied_share(choice.episodes) == 1.0


def test_warm_start_from_collector_batches_of_an_actor():
    env = _short_cartpole()
    actor = _actor(env)
    batches = _collector_batches(env, actor, frames_per_batch=8, total_frames=16)
    spec = RunSpec.of(
        schedule=(2,), num_steps=8, gamma=0.95, num_repeats=1, candidate_offsets=(0.0, 0.5), seed=0
    )
    api = ActivePolicyIteration(
        spec, env=cartpole(), basis=cartpole_basis(), initial_episodes=batches
    )
    warm = len(api.rewarded)
    assert warm == len(set(torch.cat(batches)["collector", "traj_ids"].tolist()))
    api.run()
    held = api.rewarded.episodes()
    assert len(held) == warm + 2 and (held["policy_id"][:warm] == -1).all()
    assert torch.isfinite(api.theta).all()


def _whole_trajectories(max_steps, *transforms):
    def make_collector(policy, num_episodes):
        env = TransformedEnv(cartpole(), StepCounter(max_steps=max_steps))
        for transform in transforms:
            env.append_transform(transform())
        return Collector(
            env,
            policy,
            frames_per_batch=num_episodes * max_steps,
            total_frames=-1,
            trajs_per_batch=num_episodes,
            traj_format="padded",
            auto_register_policy_transforms=False,
        )

    return make_collector


def test_iteration_and_selector_read_episodes_from_the_users_collector():
    torch.manual_seed(0)
    spec = RunSpec.of(
        schedule=(3, 2),
        num_steps=10,
        gamma=0.95,
        num_repeats=1,
        candidate_offsets=(0.0, 0.5),
        seed=0,
    )
    api = ActivePolicyIteration(
        spec,
        env=cartpole(),
        basis=cartpole_basis(),
        selector=SamplingPolicySelector(collector=_whole_trajectories(10)),
        collector=_whole_trajectories(10),
    )
    api.run()
    bought = api.rewarded.episodes()
    assert bought.shape == (5, 10) and applied_share(bought) == 1.0
    assert api.reward_free.episodes().shape == (2 * 3 + 2 * 2, 10)  # K·Z·M_l per iteration
    assert applied_share(api.reward_free.episodes()) == 1.0
    # the selector alone, with a candidate that is not the library's
    psi = PsiHat(basis=cartpole_basis(), gamma=0.95)
    selector = SamplingPolicySelector(
        env=cartpole(),
        psi=psi,
        num_episodes=2,
        num_steps=10,
        num_repeats=1,
        collector=_whole_trajectories(10),
    )
    choice = selector.select(api.policy, [api.policy, _actor(cartpole())], bought)
    assert choice.episodes.shape == (1, 2, 2, 10) and torch.isfinite(choice.j_mean).all()


class _NanInSecondEpisode(Transform):
    """Measures a NaN reward on every step of the 2nd episode its env runs (while broken)."""

    broken = True

    def __init__(self):
        super().__init__()
        self.episodes_begun = 0

    def _reset(self, tensordict, tensordict_reset):
        self.episodes_begun += 1
        return tensordict_reset

    def _step(self, tensordict, next_tensordict):
        if self.broken and self.episodes_begun == 2:
            next_tensordict["reward"] = torch.full_like(next_tensordict["reward"], math.nan)
        return next_tensordict


def test_a_bad_reward_from_the_users_collector_keeps_the_valid_episodes(tmp_path):
    """As with ``env.rollout``: the bad episode is named, the slice's others are committed."""
    path = tmp_path / "run.db"

    def api(**kwargs):
        return ActivePolicyIteration(
            RunSpec.of(schedule=(3, 2), num_steps=10, gamma=0.95, seed=0, mode="passive"),
            env=cartpole(),
            basis=cartpole_basis(),
            collector=_whole_trajectories(10, _NanInSecondEpisode),
            durable=DurableRun(path, **kwargs),
        )

    _NanInSecondEpisode.broken = True
    broken = api()
    with pytest.raises(ValueError, match=r"iteration 1: episode 1: rewards must be finite, got n"):
        broken.step()
    broken.close()
    assert sorted(RunStore.read(path).episodes[1]) == [0, 2]
    _NanInSecondEpisode.broken = False
    resumed = api(resume=True)  # a repaired env buys episode 1 again, and only it
    assert sorted(resumed.buyer.bought) == [0, 2]
    resumed.run()
    assert len(resumed.rewarded) == 3 + 2
    assert torch.isfinite(resumed.rewarded.episodes()["next", "reward"]).all()


def test_reward_free_workers_write_the_envs_encoding():
    psi = PsiHat(basis=cartpole_basis(), gamma=0.95)
    policy = LinearQPolicy(basis=cartpole_basis(), theta=torch.ones(8), epsilon=0.3)
    selector = SamplingPolicySelector(
        env=cartpole_rows, psi=psi, num_episodes=2, num_steps=6, num_repeats=1, num_workers=1
    )
    choice = selector.select(policy, [policy, policy.with_rule(epsilon=0.8)])
    assert applied_share(choice.episodes) == 1.0


def test_missing_sampling_probabilities_name_the_keys_that_work():
    def no_probs(td):
        td["action"] = torch.tensor([1, 0])
        return td

    with pytest.raises(ValueError, match="sample_log_prob' / 'action_log_prob"):
        collect_episodes(cartpole(), no_probs, num_episodes=1, num_steps=2, rewarded=True)


def test_lstd_selector_takes_an_actor_candidate():
    env = cartpole()
    psi = PsiHat(basis=cartpole_basis(), gamma=0.95)
    evaluation = _collector_policy(env, epsilon=0.2)
    earlier = collect_episodes(env, evaluation, num_episodes=2, num_steps=6, rewarded=True)
    selector = SamplingPolicySelector(
        env=lambda rows: cartpole(), psi=psi, num_episodes=2, num_steps=8, num_repeats=1, fit="lstd"
    )
    choice = selector.select(evaluation, [evaluation, _actor(env)], earlier_episodes=earlier)
    assert choice.j_mean.shape == (2,) and torch.isfinite(choice.j_mean).all()
