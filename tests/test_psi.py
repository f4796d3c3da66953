"""psi_hat (eq. 20) against hand computations."""

import pytest
import torch

from torch_api.core.basis import GaussianActionBasis
from torch_api.core.psi import PsiHat, knn_mean, psi_hat, state_action_groups


def _basis():
    return GaussianActionBasis(centers=torch.tensor([[1.0], [4.0]]), tau=1.5, num_actions=2)


def test_grouped_mean_by_hand():
    # transitions: (s, a, s') = (1, R, 2), (1, R, 1), (2, L, 1), (1, L, 2)
    obs = torch.tensor([[1.0], [1.0], [2.0], [1.0]])
    action = torch.tensor([1, 1, 0, 0])
    nxt = torch.tensor([[2.0], [1.0], [1.0], [2.0]])
    probs = torch.tensor([[0.3, 0.7]] * 4, dtype=torch.float64)
    basis = _basis()
    out = PsiHat(basis=basis, gamma=0.9, mode="grouped")(obs, action, nxt, probs)

    def v(s):  # Σ_a' π(a'|s') φ(s', a')
        phi_all = basis.phi_all(torch.tensor([[s]], dtype=torch.float64))[0]
        return 0.3 * phi_all[0] + 0.7 * phi_all[1]

    phi = basis.phi(obs.double(), action)
    shared = (v(2.0) + v(1.0)) / 2  # both (1, R) transitions share the mean over {2, 1}
    torch.testing.assert_close(out[0], phi[0] - 0.9 * shared)
    torch.testing.assert_close(out[1], phi[1] - 0.9 * shared)
    torch.testing.assert_close(out[2], phi[2] - 0.9 * v(1.0))
    torch.testing.assert_close(out[3], phi[3] - 0.9 * v(2.0))


def test_groups_do_not_cross_batch_items_or_masks():
    obs = torch.ones(2, 3, 1)
    action = torch.zeros(2, 3, dtype=torch.long)
    groups = state_action_groups(obs, action)
    assert groups[0].unique().numel() == 1 and groups[1].unique().numel() == 1
    assert groups[0, 0] != groups[1, 0]
    mask = torch.tensor([[True, True, False], [True, True, True]])
    groups = state_action_groups(obs, action, mask)
    assert groups[0, 2] != groups[0, 0]


def test_single_sample_and_termination():
    basis = _basis()
    obs = torch.tensor([[1.0], [1.0]])
    action = torch.tensor([0, 0])
    nxt = torch.tensor([[2.0], [3.0]])
    probs = torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    terminated = torch.tensor([False, True])
    out = PsiHat(basis=basis, gamma=0.5, mode="single")(obs, action, nxt, probs, terminated)
    phi = basis.phi(obs.double(), action)
    next_phi = basis.phi(nxt.double(), action)
    torch.testing.assert_close(out[0], phi[0] - 0.5 * next_phi[0])
    torch.testing.assert_close(out[1], phi[1])  # no bootstrap after termination


def test_knn_brute_force_and_k1_is_single():
    gen = torch.Generator().manual_seed(0)
    obs = torch.randn(12, 2, generator=gen, dtype=torch.float64)
    action = torch.randint(0, 2, (12,), generator=gen)
    values = torch.randn(12, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(knn_mean(obs, action, values, 1), values)
    out = knn_mean(obs, action, values, 3)
    for i in range(12):
        same = [j for j in range(12) if action[j] == action[i]]
        same.sort(key=lambda j: (j != i, (obs[j] - obs[i]).norm().item()))
        ref = values[same[:3]].mean(0)
        torch.testing.assert_close(out[i], ref)


def test_psi_hat_rejects_bad_gamma_and_shapes():
    with pytest.raises(ValueError, match="gamma must lie in"):
        psi_hat(torch.ones(2, 3), torch.ones(2, 3), 1.5)
    with pytest.raises(ValueError, match="next_features must have shape"):
        psi_hat(torch.ones(2, 3), torch.ones(2, 4), 0.9)
    with pytest.raises(ValueError, match="mode must be one of"):
        PsiHat(basis=_basis(), gamma=0.9, mode="nearest")
