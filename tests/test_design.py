"""psi_hat + weights + ridge on chain-walk samples against the exact model (docs/chain_walk.md)."""

import pytest
import torch

from envs.chain_walk import (
    CENTERS,
    GAMMA,
    TAU,
    ChainWalkEnv,
    deterministic_policy_probs,
    exact_psi,
    state_action_occupancy,
)
from torch_api.collection import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.core.solve import weighted_ridge
from torch_api.policies import TabularPolicy

N_STEPS = 10


def _state_index(obs):
    return obs[..., 0].round().long() - 1


def _setup():
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    return basis, PsiHat(basis=basis, gamma=GAMMA, mode="grouped")


def _exact_minimiser(basis, table, model):
    """argmin_θ Σ d(s,a) (θᵀψ(s,a) − R(s,a))² from the model (plain dense normal equations)."""
    states = torch.arange(1, 11, dtype=torch.float64)[:, None]
    psi = exact_psi(model.transitions, basis.phi_all(states), table, GAMMA).reshape(20, -1)
    d = state_action_occupancy(model.transitions, table, model.initial, N_STEPS).reshape(20)
    r = model.expected_reward.reshape(20)
    a = psi.T @ (d[:, None] * psi) + 1e-9 * torch.eye(psi.shape[1], dtype=torch.float64)
    return torch.linalg.solve(a, psi.T @ (d * r)), psi, d


def _fit(sampling_table, eval_table, num_episodes, seed):
    basis, psi = _setup()
    env = ChainWalkEnv(batch_size=num_episodes, seed=seed)
    sampler = TabularPolicy(
        table=sampling_table,
        state_index=_state_index,
        generator=torch.Generator().manual_seed(seed),
    )
    episodes = collect_episodes(
        env, sampler, num_episodes=num_episodes, num_steps=N_STEPS, rewarded=True
    )
    evaluation = TabularPolicy(table=eval_table, state_index=_state_index)
    design = build_design(episodes, evaluation, psi)
    theta = weighted_ridge(design.x, design.w, design.reward, 1e-9)
    return theta, basis, env.model()


def _prediction_error(theta, theta_star, psi, d):
    """d-weighted RMS difference of the fitted values θᵀψ(s, a)."""
    return torch.sqrt((d * (psi @ theta - psi @ theta_star) ** 2).sum()).item()


@pytest.mark.parametrize("sampling_eps", [0.3, 0.8])  # on-policy, then off-policy with weights
def test_sampled_theta_approaches_exact_minimiser(sampling_eps):
    eval_table = deterministic_policy_probs("RLLLLLRRRR", 0.3)
    sampling_table = deterministic_policy_probs("RLLLLLRRRR", sampling_eps)
    errors = []
    for m in (200, 20000):
        theta, basis, model = _fit(sampling_table, eval_table, m, seed=1)
        theta_star, psi, d = _exact_minimiser(basis, eval_table, model)
        errors.append(_prediction_error(theta, theta_star, psi, d))
    assert errors[1] < 0.01  # rewards lie in [0, 1]
    assert errors[1] < errors[0] / 3  # ~1/sqrt(n): 100× more data, ~10× smaller error


def test_on_policy_weights_are_one_and_off_policy_weights_are_ratios():
    eval_table = deterministic_policy_probs("RRRRRRRRRR", 0.2)
    basis, psi = _setup()
    env = ChainWalkEnv(batch_size=50, seed=0)
    sampler = TabularPolicy(table=eval_table, state_index=_state_index)
    episodes = collect_episodes(env, sampler, num_episodes=50, num_steps=N_STEPS, rewarded=True)
    design = build_design(episodes, TabularPolicy(table=eval_table, state_index=_state_index), psi)
    torch.testing.assert_close(design.w, torch.ones_like(design.w))
    other = TabularPolicy(
        table=deterministic_policy_probs("LLLLLLLLLL", 0.2), state_index=_state_index
    )
    design = build_design(episodes, other, psi)
    # each step's ratio is 0.1/0.9 (action disagrees) or 0.9/0.1: per-decision products of them
    ratio = torch.where(episodes["action"] == 1, 0.1 / 0.9, 0.9 / 0.1)
    torch.testing.assert_close(design.w, torch.cumprod(ratio, -1).reshape(-1).double())
