"""Flattened weights chosen by IWCV (torch_api/core/iwcv.py, torch_api/core/fit.py), in the loop."""

from __future__ import annotations

import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.collection.collect import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.fit import fit_flattened
from torch_api.core.iwcv import check_flattening, choose_flattening
from torch_api.core.psi import PsiHat
from torch_api.core.solve import weighted_ridge
from torch_api.core.weights import effective_sample_size
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.policies import LinearQPolicy

LAM = 1e-3


def _basis() -> GaussianActionBasis:
    return GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)


def _episodes(seed: int, sampling_epsilon: float | None, num_steps: int, num_episodes=10):
    """Chain-walk episodes of a random ε = 0.1 policy pi, sampled by pi itself (None) or by
    its ε = ``sampling_epsilon`` version; returns (episodes, pi)."""
    basis = _basis()
    theta = torch.randn(basis.num_features, generator=torch.Generator().manual_seed(seed))
    pi = LinearQPolicy(basis=basis, theta=theta.double(), epsilon=0.1)
    sampler = pi if sampling_epsilon is None else pi.with_rule(epsilon=sampling_epsilon)
    sampler = sampler.with_streams(torch.Generator().manual_seed(seed))
    env = ChainWalkEnv(batch_size=num_episodes, seed=seed)
    episodes = collect_episodes(
        env, sampler, num_episodes=num_episodes, num_steps=num_steps, rewarded=True
    )
    return episodes, pi, basis


@pytest.mark.parametrize("fit", ["brm", "lstd"])
def test_iwcv_keeps_nu_one_on_policy_and_flattens_where_the_weights_collapse(fit):
    """On-policy data (w = 1: every ν gives the same fit) keeps the unbiased ν = 1; uniform
    sampling for 50 steps against an ε = 0.1 policy collapses the weights and IWCV flattens."""
    for seed in range(3):
        on, pi, basis = _episodes(seed, None, num_steps=50)
        psi = PsiHat(basis=basis, gamma=GAMMA, mode="single")
        chosen = fit_flattened(fit, on, pi, psi, basis, LAM, flattening="iwcv")
        assert chosen.flattening.item() == 1.0
        off, pi, basis = _episodes(seed, 1.0, num_steps=50)
        raw = build_design(off, pi, psi, min_ess_fraction=0.0)
        assert effective_sample_size(raw.w) < 0.1 * raw.num_samples  # the weights collapsed
        chosen = fit_flattened(fit, off, pi, psi, basis, LAM, flattening="iwcv")
        assert chosen.flattening.item() < 1.0
        assert chosen.ess > effective_sample_size(raw.w)
        assert chosen.scores.shape == (5,)


def test_nu_one_fit_is_todays_fit_to_the_bit():
    episodes, pi, basis = _episodes(3, 0.6, num_steps=12)
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="grouped")
    design = build_design(episodes, pi, psi)
    today = weighted_ridge(design.x, design.w, design.reward, LAM, num_samples=design.num_samples)
    assert torch.equal(fit_flattened("brm", episodes, pi, psi, basis, LAM).theta, today)


def test_choice_prefers_the_largest_tied_nu_and_falls_back_without_folds():
    grid = (0.0, 0.5, 1.0)
    scores = torch.tensor([[1.0, 1.0, 1.0], [0.5, 0.2, 0.9], [float("nan")] * 3])
    assert choose_flattening(scores, grid).tolist() == [1.0, 0.5, 1.0]


@pytest.mark.parametrize(
    ("flattening", "grid", "folds", "message"),
    [
        (1.5, (0.0, 1.0), 5, "flattening must lie in"),
        ("cv", (0.0, 1.0), 5, "'iwcv'"),
        ("iwcv", (), 5, "flattening_grid"),
        ("iwcv", (0.0, 2.0), 5, "flattening_grid"),
        ("iwcv", (0.0, 1.0), 1, "iwcv_folds"),
    ],
)
def test_bad_flattening_settings_are_refused(flattening, grid, folds, message):
    with pytest.raises(ValueError, match=message):
        check_flattening(flattening, grid, folds)


def _api(flattening, durable=None, **kwargs):
    spec = RunSpec.of(
        schedule=(3, 3, 2),
        num_steps=10,
        gamma=GAMMA,
        num_repeats=2,
        lam=LAM,
        psi_mode="grouped",
        **({} if flattening is None else {"flattening": flattening}),
        **kwargs,
    )
    return ActivePolicyIteration(
        spec,
        env=lambda e: ChainWalkEnv(batch_size=e, seed=11),
        basis=_basis(),
        selector=SamplingPolicySelector(env=lambda e: ChainWalkEnv(batch_size=e, seed=12)),
        durable=durable,
    )


def test_nu_one_reproduces_the_unflattened_loop_to_the_bit():
    """flattening=1.0 gives the default run's θ and J to the bit; ν = 1 is recorded."""
    default, fixed = _api(None, num_trials=2).run(), _api(1.0, num_trials=2).run()
    for a, b in zip(default, fixed, strict=True):
        assert a.theta == b.theta and a.j_all == b.j_all
        assert a.flattening == [1.0, 1.0]


def test_iwcv_loop_records_nu_and_ess_per_trial_and_stores_the_setting(tmp_path):
    api = _api("iwcv", num_trials=2, durable=DurableRun(tmp_path / "run.db"))
    history = api.run()
    for record in history:
        assert len(record.flattening) == 2 and all(0 <= v <= 1 for v in record.flattening)
        assert len(record.effective_sample_size) == 2
        row = record.row()
        assert row["flattening"] == record.flattening
        pairs = zip(record.effective_sample_size, record.rewarded_transitions, strict=True)
        assert all(0 < e <= n for e, n in pairs)
    with pytest.raises(Exception, match="flattening"):
        _api(0.5, num_trials=2, durable=DurableRun(tmp_path / "run.db", resume=True))
