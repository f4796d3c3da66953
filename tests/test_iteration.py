"""Algorithm 1 (torch_api/loop/iteration.py): weights, θ, seeding, passive mode, batched trials.

References are written out by hand (NumPy loops over episodes and steps); only psi_hat rows are
taken from the library (they have their own tests in test_psi.py / test_design.py).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec

LAM = 1e-3
N = 10


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Tiny tensors: one intra-op thread is faster, and far faster on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _basis() -> GaussianActionBasis:
    return GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)


def _selector(**kwargs) -> SamplingPolicySelector:
    return SamplingPolicySelector(env=lambda e: ChainWalkEnv(batch_size=e, seed=12), **kwargs)


def _api(
    *,
    mode="active",
    schedule=(3, 2),
    num_trials=None,
    seed=0,
    selector=None,
    durable=None,
    on_iteration=None,
    **settings,
):
    """A chain-walk run; active: Z = 2 and the selector on its own env (``_selector()``) unless
    one is given."""
    spec = RunSpec.of(
        schedule=schedule,
        num_steps=N,
        gamma=GAMMA,
        lam=LAM,
        psi_mode="grouped",
        num_trials=num_trials,
        seed=seed,
        mode=mode,
        **({"num_repeats": 2} if mode == "active" else {}),
        **settings,
    )
    if selector is None and mode == "active":
        selector = _selector()
    return ActivePolicyIteration(
        spec,
        env=lambda e: ChainWalkEnv(batch_size=e, seed=11),
        basis=_basis(),
        selector=selector,
        durable=durable,
        on_iteration=on_iteration,
    )


def _hand_weights(episodes, policy) -> np.ndarray:
    """Per-decision weights ``Π_{n' <= n} pi(a|s) / pi~(a|s)`` by plain loops ``[M, N]``."""
    obs = episodes["observation"]
    target = policy.action_probs(obs).numpy()  # [M, N, A]
    sample = episodes["sample_probs"].numpy()
    action = episodes["action"].numpy()
    mask = episodes["mask"].numpy()
    w = np.zeros(action.shape)
    for m in range(action.shape[0]):
        prod = 1.0
        for n in range(action.shape[1]):
            if not mask[m, n]:
                break
            a = action[m, n]
            prod *= target[m, n, a] / sample[m, n, a]
            w[m, n] = prod
    return w


def _hand_theta(design, lam: float) -> np.ndarray:
    """``(Â + λI)^{-1} b̂`` with ``Â = (1/n) Σ w x xᵀ``, ``b̂ = (1/n) Σ w x r`` (eq. 22-28)."""
    x, w, r = design.x.numpy(), design.w.numpy(), design.reward.numpy()
    n = int(design.mask.sum())
    a_hat = sum(w[i] * np.outer(x[i], x[i]) for i in range(len(w))) / n
    b_hat = sum(w[i] * x[i] * r[i] for i in range(len(w))) / n
    return np.linalg.solve(a_hat + lam * np.eye(x.shape[1]), b_hat)


@pytest.mark.parametrize("mode", ["passive", "active"])
def test_weights_and_theta_follow_algorithm_1(mode):
    """Step 3: θ_l is fitted on ALL rewarded episodes with weights towards pi_l."""
    api = _api(mode=mode, schedule=(3, 3, 2))
    for _ in range(3):
        pi_l = api.policy  # the evaluation policy of the coming iteration
        record = api.step()
    episodes = api.rewarded.episodes()  # [ΣM, N]
    assert episodes.shape == (8, N)
    design = build_design(episodes, pi_l, api.psi)
    w = design.w.reshape(8, N).numpy()
    np.testing.assert_allclose(w, _hand_weights(episodes, pi_l), rtol=1e-12, atol=0)

    mask = episodes["mask"].numpy()
    newest = episodes["iteration"][:, 0].numpy() == 3
    own = newest & (episodes["policy_id"][:, 0].numpy() == 0)  # collected by pi_l itself
    if mode == "passive":
        assert own.sum() == 2
    np.testing.assert_array_equal(w[own][mask[own]], 1.0)
    older = ~newest
    assert not np.allclose(w[older][mask[older]], 1.0)  # earlier sets are reweighted to pi_l
    assert record.chosen == 0 or mode == "active"

    np.testing.assert_allclose(api.theta.numpy(), _hand_theta(design, LAM), rtol=1e-8, atol=1e-10)


def test_same_seed_same_history():
    runs = [_api(num_trials=3, schedule=(3, 2, 1), seed=5) for _ in range(2)]
    histories = [api.run() for api in runs]
    for a, b in zip(*histories, strict=True):
        assert a.theta == b.theta
        assert a.chosen == b.chosen
        assert a.j_mean == b.j_mean
        assert a.j_all == b.j_all
        assert a.sampling_rule == b.sampling_rule
    assert torch.equal(runs[0].theta, runs[1].theta)
    other = _api(num_trials=3, schedule=(3, 2, 1), seed=6).run()
    assert other[-1].theta != histories[0][-1].theta


def test_passive_mode_never_calls_the_selector(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the selector was called in passive mode")

    monkeypatch.setattr(SamplingPolicySelector, "select", refuse)
    monkeypatch.setattr(SamplingPolicySelector, "collect", refuse)
    spec = RunSpec.of(
        schedule=(3, 2), num_steps=N, gamma=GAMMA, psi_mode="grouped", num_trials=2, mode="passive"
    )
    api = ActivePolicyIteration(
        spec, env=lambda e: ChainWalkEnv(batch_size=e, seed=11), basis=_basis(), selector=None
    )
    history = api.run()
    assert len(api.reward_free) == 0
    for record in history:
        assert record.reward_free_transitions == [0, 0]
        assert record.j_mean is None and record.j_all is None
        assert record.chosen == [0, 0]
    assert api.rewarded_transitions == 5 * N
    assert api.mode == "passive"


def test_the_selector_passed_in_is_bound_not_changed():
    """The loop binds the selector it is given to its own settings (psi_hat, N, λ, fit,
    device, streams) in a copy: the object passed keeps its own settings and serves a second
    run exactly as the first."""
    selector = _selector()
    first, second = (_api(selector=selector, num_trials=2) for _ in range(2))
    assert first.mode == "active" and first.selector is not selector
    assert first.selector.psi is first.psi and first.selector.num_steps == N
    assert selector.psi is None and selector.num_steps is None and selector.generator is None
    for a, b in zip(first.run(), second.run(), strict=True):
        assert a.j_all == b.j_all and a.chosen == b.chosen and a.theta == b.theta


def test_a_selector_with_the_loops_settings_is_refused():
    psi = PsiHat(basis=_basis(), gamma=GAMMA, mode="grouped")
    with pytest.raises(ValueError, match=r"selector: \['num_steps', 'psi'\] are the loop's"):
        _api(selector=_selector(psi=psi, num_steps=N))
    with pytest.raises(ValueError, match=r"selector: \['generator', 'num_episodes'\] are"):
        _api(selector=_selector(num_episodes=3, generator=torch.Generator()))
    with pytest.raises(ValueError, match="selector must be a SamplingPolicySelector or None"):
        _api(selector="active")


def test_batched_trials_shapes_and_counts():
    trials, schedule = 3, (3, 2, 1)
    api = _api(num_trials=trials, schedule=schedule)
    history = api.run()
    assert api.theta.shape == (trials, 12)
    assert api.policy.param_dims == (trials,)
    assert api.rewarded.episodes().shape == (trials, sum(schedule), N)
    k = 4  # the paper's candidates ε_l + (0, 0.15, 0.5, 0.85)
    bought = 0
    for record, m in zip(history, schedule, strict=True):
        bought += m * N
        assert record.rewarded_transitions == [bought] * trials  # each trial's own count
        assert record.episodes_bought == m
        assert len(record.chosen) == trials
        assert all(0 <= c < k for c in record.chosen)
        assert np.asarray(record.theta).shape == (trials, 12)
        assert np.asarray(record.j_mean).shape == (trials, k)
        assert np.asarray(record.j_all).shape == (trials, 2, k)
        assert record.chosen == np.asarray(record.j_mean).argmin(-1).tolist()
        free = 2 * k * N * sum(schedule[: record.iteration])
        assert record.reward_free_transitions == [free] * trials
    assert api.rewarded_transitions == sum(schedule) * N
    # the bought episodes of trial t were sampled with its own chosen candidate
    ids = api.rewarded.episodes()["policy_id"][:, :, 0]  # [T, ΣM]
    offsets = np.cumsum((0, *schedule))
    for record in history:
        start = offsets[record.iteration - 1]
        assert ids[:, start].tolist() == record.chosen


def test_batched_trials_equal_one_at_a_time_runs_with_the_same_seeds():
    """Each trial draws from its own streams: T trials in one batch = T separate runs."""
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)

    def run(seeds):
        spec = RunSpec.of(
            schedule=(5, 3, 2),
            num_steps=10,
            gamma=GAMMA,
            psi_mode="grouped",
            num_repeats=3,
            num_trials=len(seeds),
            trial_seeds=seeds,
        )
        api = ActivePolicyIteration(spec, env=lambda e: ChainWalkEnv(batch_size=e), basis=basis)
        api.run()
        return api

    seeds = [11, 22, 33]
    batched = run(seeds)
    for t, seed in enumerate(seeds):
        alone = run([seed])
        assert torch.equal(alone.theta[0], batched.theta[t])
        for r_alone, r_batched in zip(alone.history, batched.history, strict=True):
            assert r_alone.chosen[0] == r_batched.chosen[t]
            assert r_alone.j_mean[0] == r_batched.j_mean[t]


def test_softmax_improvement_runs_with_softmax_candidates():
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    spec = RunSpec.of(
        schedule=(3, 2),
        num_steps=10,
        gamma=GAMMA,
        psi_mode="grouped",
        num_repeats=2,
        num_trials=2,
        improvement="softmax",
        beta=0.5,
    )
    api = ActivePolicyIteration(spec, env=lambda e: ChainWalkEnv(batch_size=e), basis=basis)
    history = api.run()
    assert api.policy.beta == 0.5 and api.policy.epsilon is None
    assert all(rule in (0.5, 1.0, 2.5, 10.0) for r in history for rule in r.sampling_rule)
    assert len(api.reward_free) == 2 * 4 * (3 + 2)  # Z · K · Σ M_l episodes per trial


@pytest.mark.parametrize("tie_break", ["uniform", "lowest"])
def test_passive_run_whose_first_rewards_are_all_zero_still_explores(tie_break):
    """No reward seen: θ_1 = 0, every action ties. Split evenly, pi_2 is uniform and the next
    bought episodes try both actions; to the lowest index, PL would cock (go left) for ever."""
    spec = RunSpec.of(
        schedule=(3, 40),
        num_steps=N,
        gamma=GAMMA,
        psi_mode="grouped",
        num_trials=2,
        tie_break=tie_break,
        mode="passive",
    )
    api = ActivePolicyIteration(
        spec,
        env=lambda e: ChainWalkEnv(batch_size=e, seed=11, reward_profile=[0.0] * 10),
        basis=_basis(),
    )
    api.step()
    assert torch.equal(api.theta, torch.zeros_like(api.theta))
    states = torch.arange(1, 11, dtype=torch.float32)[:, None].expand(2, 10, 1)
    probs = api.policy.action_probs(states)
    api.step()
    right = (api.rewarded.episodes()["action"][:, 3:] == 1).double().mean().item()
    if tie_break == "uniform":
        torch.testing.assert_close(probs, torch.full((2, 10, 2), 0.5, dtype=torch.float64))
        assert 0.4 < right < 0.6  # 800 draws of a fair coin: 5.7 standard errors
    else:
        assert probs[..., 1].eq(0.075 / 2).all()  # ε_2 = 0.075: right only by exploration
        assert right < 0.1


@pytest.mark.parametrize("num_trials", [None, 3])
def test_rewarded_draws_do_not_depend_on_reward_free_collection(num_trials):
    """AL and PL on one seed differ only by the sampling policy: an AL run whose one candidate
    is pi_l itself buys exactly PL's episodes (same actions), although it also collects
    reward-free episodes before every purchase."""
    runs = {
        mode: _api(mode=mode, schedule=(3, 2, 2), num_trials=num_trials, candidate_offsets=(0.0,))
        for mode in ("active", "passive")
    }
    for api in runs.values():
        api.run()
    active, passive = runs["active"], runs["passive"]
    assert np.all(np.asarray(active.history[-1].reward_free_transitions) > 0)
    bought = {mode: api.rewarded.episodes() for mode, api in runs.items()}
    assert torch.equal(bought["active"]["action"], bought["passive"]["action"])
    assert torch.equal(bought["active"]["observation"], bought["passive"]["observation"])
    assert torch.equal(active.theta, passive.theta)


def test_hooks_see_every_commit_and_every_iteration(tmp_path):
    """``on_commit`` after each commit (selection, episodes, record), ``on_iteration`` with
    each record; the numbers are those of a run without hooks."""
    commits, records, hooked = [], [], None
    durable = DurableRun(tmp_path / "run.db", on_commit=lambda: commits.append(hooked.iteration))
    hooked = _api(durable=durable, on_iteration=records.append)
    history = hooked.run()
    plain = _api().run()
    assert records == history
    assert len(commits) == 3 * len(history)  # selection, rewarded episodes, record per l
    for a, b in zip(history, plain, strict=True):
        assert a.theta == b.theta and a.chosen == b.chosen
