"""Invariants of the weights, psi_hat, the solver and J under random input (hypothesis)."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_api.core.basis import GaussianActionBasis
from torch_api.core.psi import PsiHat
from torch_api.core.solve import j_criterion, j_from_moments, weighted_moment, weighted_ridge
from torch_api.core.weights import per_decision_weights

# database=None: no .hypothesis/ folder written into the checkout
SETTINGS = settings(max_examples=40, deadline=None, database=None)
seeds = st.integers(0, 2**31 - 1)


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _design(seed, lead=(), n=30, b=5):
    gen = _gen(seed)
    x = torch.randn(*lead, n, b, generator=gen, dtype=torch.float64)
    w = torch.rand(*lead, n, generator=gen, dtype=torch.float64) * 3 + 0.01
    r = torch.randn(*lead, n, generator=gen, dtype=torch.float64)
    return x, w, r


@SETTINGS
@given(seed=seeds, m=st.integers(1, 5), n=st.integers(1, 12))
def test_weights_of_a_policy_against_itself_are_one(seed, m, n):
    probs = torch.rand(m, n, generator=_gen(seed), dtype=torch.float64) * 0.99 + 0.01
    torch.testing.assert_close(per_decision_weights(probs, probs), torch.ones_like(probs))


@SETTINGS
@given(seed=seeds, lam=st.floats(1e-6, 1.0))
def test_solve_satisfies_its_normal_equations(seed, lam):
    x, w, r = _design(seed)
    theta = weighted_ridge(x, w, r, lam)
    n = x.shape[0]
    lhs = (x.T * w) @ x / n @ theta + lam * theta
    rhs = x.T @ (w * r) / n
    torch.testing.assert_close(lhs, rhs, rtol=1e-9, atol=1e-11)


@SETTINGS
@given(seed=seeds, lam=st.floats(1e-5, 1.0))
def test_batched_results_equal_per_item_results(seed, lam):
    x, w, r = _design(seed, lead=(3,))
    u = torch.eye(5, dtype=torch.float64)
    theta, j = weighted_ridge(x, w, r, lam), j_criterion(x, w, u, lam)
    for i in range(3):
        torch.testing.assert_close(theta[i], weighted_ridge(x[i], w[i], r[i], lam))
        torch.testing.assert_close(j[i], j_criterion(x[i], w[i], u, lam))


@SETTINGS
@given(seed=seeds, lam=st.floats(1e-5, 1.0))
def test_j_is_invariant_to_permuting_samples(seed, lam):
    x, w, _ = _design(seed)
    u = torch.eye(5, dtype=torch.float64) + 0.1
    perm = torch.randperm(x.shape[0], generator=_gen(seed + 1))
    torch.testing.assert_close(j_criterion(x[perm], w[perm], u, lam), j_criterion(x, w, u, lam))


@SETTINGS
@given(seed=seeds, scale=st.floats(0.01, 100.0))
def test_with_lambda_zero_j_is_invariant_to_scaling_the_weights(seed, scale):
    x, w, _ = _design(seed, n=40)
    u = torch.eye(5, dtype=torch.float64)

    def j(weights):
        n = x.shape[0]
        a = weighted_moment(x, weights) / n
        c = weighted_moment(x, weights**2) / n**2
        return j_from_moments(a, c, u, 0.0)

    torch.testing.assert_close(j(w * scale), j(w), rtol=1e-8, atol=0)


@SETTINGS
@given(seed=seeds)
def test_grouped_psi_hat_is_equivariant_to_permuting_samples(seed):
    gen = _gen(seed)
    basis = GaussianActionBasis(centers=torch.tensor([[1.0], [4.0]]), tau=1.5, num_actions=2)
    psi = PsiHat(basis=basis, gamma=0.9, mode="grouped")
    obs = torch.randint(1, 5, (25, 1), generator=gen).double()
    nxt = torch.randint(1, 5, (25, 1), generator=gen).double()
    action = torch.randint(0, 2, (25,), generator=gen)
    probs = torch.softmax(torch.randn(25, 2, generator=gen, dtype=torch.float64), -1)
    perm = torch.randperm(25, generator=gen)
    out = psi(obs, action, nxt, probs)
    torch.testing.assert_close(psi(obs[perm], action[perm], nxt[perm], probs[perm]), out[perm])
