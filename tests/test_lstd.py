"""LSTD-Q (torch_api/core/lstd.py): θ and J against the dense formulas written out by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.collection import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.lstd import lstd_j_values, phi_rows, weighted_lstd
from torch_api.core.psi import PsiHat
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.policies import LinearQPolicy

LAM = 1e-3


def _basis() -> GaussianActionBasis:
    return GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)


def _episodes(policy, m: int, seed: int):
    env = ChainWalkEnv(batch_size=m, seed=seed)
    policy = policy.with_streams(torch.Generator().manual_seed(seed))
    return collect_episodes(env, policy, num_episodes=m, num_steps=10, rewarded=True)


def _dense_l(phi, x, w, lam):
    """``L = (Φᵀ W X / n + λI)^{-1} Φᵀ W / n``, ``B × n`` (numpy, explicit inverse)."""
    n = len(w)
    a = phi.T @ np.diag(w) @ x / n
    return np.linalg.inv(a + lam * np.eye(a.shape[0])) @ phi.T @ np.diag(w) / n


def test_weighted_lstd_is_the_projected_fixed_point():
    basis = _basis()
    sampler = LinearQPolicy(basis=basis, theta=torch.linspace(-1, 1, 12), epsilon=0.6)
    target = sampler.with_rule(epsilon=0.1)
    episodes = _episodes(sampler, 8, seed=1)
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="single")
    design = build_design(episodes, target, psi, min_ess_fraction=0.0)
    phi = phi_rows(episodes, basis)
    theta = weighted_lstd(
        phi, design.x, design.w, design.reward, LAM, num_samples=design.num_samples
    )
    # by hand: phi(s, a) straight from the basis, per sample
    obs = episodes["observation"].reshape(-1, 1).double()
    hand_phi = basis.phi(obs, episodes["action"].reshape(-1)).numpy()
    np.testing.assert_allclose(phi.numpy(), hand_phi)
    w, x, r = design.w.numpy(), design.x.numpy(), design.reward.numpy()
    expected = _dense_l(hand_phi, x, w, LAM) @ r
    np.testing.assert_allclose(theta.numpy(), expected, rtol=1e-8, atol=1e-10)
    # the fixed point: the weighted residual is orthogonal to the features (up to λθ)
    resid = hand_phi.T @ np.diag(w) @ (x @ theta.numpy() - r) / len(w)
    assert np.abs(resid).max() < 1e-2 * np.abs(hand_phi.T @ (w * r) / len(w)).max()


@pytest.mark.parametrize("nu", [1.0, 0.4])
def test_lstd_j_equals_trace_of_u_l_lt_per_candidate(nu):
    """J_k = tr(Ũ L_k L_kᵀ), Ũ over all candidates' episodes and the earlier set (D̄_0); with
    flattened weights L_k takes w^ν and Ũ keeps w (docs/flattening.md, eq. F3)."""
    basis = _basis()
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="single")
    pi = LinearQPolicy(basis=basis, theta=torch.linspace(1, -1, 12), epsilon=0.15)
    candidates = [pi.with_rule(epsilon=e) for e in (0.15, 0.5, 1.0)]
    cand = torch.stack([_episodes(c, 4, seed=10 + k) for k, c in enumerate(candidates)])
    cand = cand.unsqueeze(0)  # [Z = 1, K, M, N]
    earlier = _episodes(pi.with_rule(epsilon=0.3), 3, seed=5)
    j = lstd_j_values(cand, earlier, pi, psi, LAM, flattening=nu)  # [1, K]

    def rows(episodes):
        d = build_design(episodes, pi, psi, min_ess_fraction=0.0)
        return phi_rows(episodes, basis).numpy(), d.x.numpy(), d.w.numpy()

    prev = rows(earlier)
    own = [rows(cand[0, k]) for k in range(3)]
    every = [*own, prev]
    x0 = np.concatenate([r[1] for r in every])
    w0 = np.concatenate([r[2] for r in every])
    u = x0.T @ np.diag(w0) @ x0 / len(w0)
    for k in range(3):
        phi, x, w = (np.concatenate([own[k][i], prev[i]]) for i in range(3))
        l_k = _dense_l(phi, x, np.where(w > 0, w**nu, 0.0), LAM)
        np.testing.assert_allclose(j[0, k].item(), np.trace(u @ l_k @ l_k.T), rtol=1e-8)


def test_lstd_j_refuses_a_grouped_psi_hat():
    basis = _basis()
    pi = LinearQPolicy(basis=basis, theta=torch.ones(12), epsilon=0.15)
    cand = _episodes(pi, 2, seed=0).unsqueeze(0).unsqueeze(0)
    with pytest.raises(ValueError, match="row-local psi_hat"):
        lstd_j_values(cand, None, pi, PsiHat(basis=basis, gamma=GAMMA, mode="grouped"), LAM)


def test_active_policy_iteration_with_lstd_fits_lstd_theta():
    spec = RunSpec.of(
        schedule=(3, 2),
        num_steps=10,
        gamma=GAMMA,
        num_repeats=2,
        psi_mode="single",
        num_trials=2,
        fit="lstd",
    )
    api = ActivePolicyIteration(
        spec,
        env=lambda e: ChainWalkEnv(batch_size=e, seed=11),
        selector=SamplingPolicySelector(env=lambda e: ChainWalkEnv(batch_size=e, seed=12)),
        basis=_basis(),
    )
    api.step()
    evaluation_policy = api.policy  # pi_2, built from θ_1; refit θ_2 by hand after step 2
    api.step()
    episodes = api.rewarded.episodes()
    design = build_design(episodes, evaluation_policy, api.psi, min_ess_fraction=0.0)
    expected = weighted_lstd(
        phi_rows(episodes, api.basis),
        design.x,
        design.w,
        design.reward,
        LAM,
        num_samples=design.num_samples,
    )
    torch.testing.assert_close(api.theta, expected)
    assert np.asarray(api.history[-1].j_mean).shape == (2, 4)
    with pytest.raises(
        ValueError, match="evaluation.fit='lstd' needs evaluation.psi_mode='single'"
    ):
        RunSpec.of(
            schedule=(1,), num_steps=10, gamma=GAMMA, psi_mode="grouped", fit="lstd", mode="passive"
        )
