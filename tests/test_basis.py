"""The Gaussian-times-action-indicator basis of eq. 50 / 64."""

import math

import pytest
import torch

from torch_api.core.basis import GaussianActionBasis


def _chain_basis():
    centers = torch.tensor([[1.0], [3.0], [5.0], [7.0], [9.0]])
    return GaussianActionBasis(centers=centers, tau=1.5, num_actions=2)


def test_chain_walk_basis_values_match_eq_50():
    basis = _chain_basis()
    assert basis.num_features == 12
    s = 4.0
    phi = basis.phi(torch.tensor([[s]]), torch.tensor([1]))[0]
    kernels = [math.exp(-((s - c) ** 2) / (2 * 1.5**2)) for c in (1, 3, 5, 7, 9)] + [1.0]
    # action 1's block holds the kernels, action 0's block is zero
    assert phi[:6].abs().sum().item() == 0.0
    assert phi[6:].tolist() == pytest.approx(kernels, rel=1e-6)


def test_phi_all_rows_are_phi_of_each_action():
    basis = _chain_basis()
    obs = torch.arange(1, 11, dtype=torch.float32).reshape(2, 5, 1)
    phi_all = basis.phi_all(obs)
    assert phi_all.shape == (2, 5, 2, 12)
    for a in range(2):
        action = torch.full((2, 5), a)
        torch.testing.assert_close(phi_all[..., a, :], basis.phi(obs, action))


def test_batting_basis_width_is_110():
    grid = torch.cartesian_prod(
        torch.tensor([0.0, math.pi / 4]),
        torch.tensor([-math.pi, 0.0, math.pi]),
        torch.tensor([-math.pi / 4, 0.0, math.pi / 4]),
        torch.tensor([-math.pi, 0.0, math.pi]),
    )
    basis = GaussianActionBasis(centers=grid, tau=3 * math.pi / 2, num_actions=2)
    assert basis.num_features == 110
    from envs.batting import BASIS_TAU, basis_centers

    assert torch.equal(basis_centers().float(), grid) and BASIS_TAU == 3 * math.pi / 2
    assert basis.phi_all(torch.zeros(3, 4)).shape == (3, 2, 110)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"centers": torch.ones(3)}, "centers must have shape"),
        ({"tau": 0.0}, "tau must be > 0"),
        ({"num_actions": 0}, "num_actions must be >= 1"),
    ],
)
def test_bad_construction(kwargs, message):
    args = {"centers": torch.ones(2, 1), "tau": 1.0, "num_actions": 2} | kwargs
    with pytest.raises(ValueError, match=message):
        GaussianActionBasis(**args)


def test_bad_calls():
    basis = _chain_basis()
    with pytest.raises(ValueError, match="trailing dimension of 1"):
        basis.phi_all(torch.zeros(3, 2))
    with pytest.raises(ValueError, match="action indices must lie in"):
        basis.phi(torch.zeros(3, 1), torch.tensor([0, 1, 2]))
    with pytest.raises(ValueError, match="action must have shape"):
        basis.phi(torch.zeros(3, 1), torch.tensor([0, 1]))


def test_fast_paths_equal_the_generic_forms():
    basis = _chain_basis()
    obs = torch.rand(3, 7, 1, dtype=torch.float64) * 10
    theta = torch.randn(3, 12, dtype=torch.float64)
    generic_q = (basis.phi_all(obs) * theta[:, None, None, :]).sum(-1)
    torch.testing.assert_close(basis.q_values(obs, theta), generic_q)
    probs = torch.softmax(torch.randn(3, 7, 2, dtype=torch.float64), -1)
    generic = (probs.unsqueeze(-1) * basis.phi_all(obs)).sum(-2)
    torch.testing.assert_close(basis.expected_phi(obs, probs), generic)
