"""weighted_ridge and j_criterion against dense references of the paper's formulas."""

import numpy as np
import pytest
import scipy.linalg
import torch

from torch_api.core.solve import (
    j_criterion,
    j_from_moments,
    weighted_moment,
    weighted_ridge,
)

LAM = 1e-3


def _data(gen, lead=(), n=60, b=7):
    x = torch.randn(*lead, n, b, generator=gen, dtype=torch.float64)
    w = torch.rand(*lead, n, generator=gen, dtype=torch.float64) * 2
    r = torch.randn(*lead, n, generator=gen, dtype=torch.float64)
    return x, w, r


def _dense_theta(x, w, r, lam):
    x, w, r = x.numpy(), w.numpy(), r.numpy()
    n, b = x.shape
    a = x.T @ np.diag(w) @ x / n + lam * np.eye(b)
    return scipy.linalg.solve(a, x.T @ (w * r) / n, assume_a="pos")


def _dense_j(x, w, u, lam):
    """Algorithm 2 written out: L = (A + λI)^{-1} B with B = (1/n) Xᵀ W (a B × n matrix)."""
    x, w, u = x.numpy(), w.numpy(), u.numpy()
    n, b = x.shape
    a = x.T @ np.diag(w) @ x / n
    big_b = x.T @ np.diag(w) / n
    ell = np.linalg.solve(a + lam * np.eye(b), big_b)
    return np.trace(u @ ell @ ell.T)


def test_weighted_ridge_matches_dense_solve():
    gen = torch.Generator().manual_seed(0)
    x, w, r = _data(gen)
    theta = weighted_ridge(x, w, r, LAM)
    np.testing.assert_allclose(theta.numpy(), _dense_theta(x, w, r, LAM), rtol=1e-8, atol=1e-12)


def test_weighted_ridge_batched_equals_per_item():
    gen = torch.Generator().manual_seed(1)
    x, w, r = _data(gen, lead=(3, 2))
    theta = weighted_ridge(x, w, r, LAM)
    assert theta.shape == (3, 2, 7)
    for i in range(3):
        for j in range(2):
            np.testing.assert_allclose(
                theta[i, j].numpy(), _dense_theta(x[i, j], w[i, j], r[i, j], LAM), rtol=1e-8
            )


def test_j_criterion_matches_algorithm_2_dense_form():
    gen = torch.Generator().manual_seed(2)
    x, w, _ = _data(gen, lead=(5, 4), n=40)
    z = torch.randn(5, 1, 7, 7, generator=gen, dtype=torch.float64)
    u = z @ z.mT / 7  # symmetric PSD, one per repeat, shared by the candidates
    j = j_criterion(x, w, u, LAM)
    assert j.shape == (5, 4)
    for zi in range(5):
        for k in range(4):
            ref = _dense_j(x[zi, k], w[zi, k], u[zi, 0], LAM)
            assert abs(j[zi, k].item() - ref) <= 1e-8 * abs(ref)


def test_moments_and_j_from_moments_agree():
    gen = torch.Generator().manual_seed(4)
    x, w, _ = _data(gen, n=30)
    dense = (x.mT * w) @ x
    torch.testing.assert_close(weighted_moment(x, w), dense)
    u = torch.eye(7, dtype=torch.float64)
    j = j_from_moments(dense / 30, ((x.mT * w**2) @ x) / 900, u, LAM)
    assert abs(j.item() - _dense_j(x, w, u, LAM)) <= 1e-8 * abs(j.item())


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lam": 0.0}, "lam must be > 0"),
        ({"lam": -1.0}, "lam must be > 0"),
        ({"r": torch.tensor([1.0, float("nan"), 0.0])}, "r \\(rewards\\) contains NaN"),
        ({"r": torch.zeros(4)}, "r must have shape"),
        ({"w": torch.zeros(2)}, "w must have shape"),
        ({"w": torch.tensor([1.0, -1.0, 1.0])}, "non-negative"),
        ({"x": torch.zeros(0, 2), "w": torch.zeros(0), "r": torch.zeros(0)}, "n = 0"),
    ],
)
def test_weighted_ridge_rejects_bad_input(kwargs, message):
    args = {"x": torch.ones(3, 2), "w": torch.ones(3), "r": torch.ones(3), "lam": LAM}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        weighted_ridge(args["x"], args["w"], args["r"], args["lam"])


def test_rank_deficient_design_warns_with_condition_number():
    x = torch.ones(20, 4, dtype=torch.float64)  # rank 1
    with pytest.warns(RuntimeWarning, match="condition number"):
        weighted_ridge(x, torch.ones(20), torch.ones(20), 1e-14)


def test_well_conditioned_solve_does_not_warn():
    import warnings

    gen = torch.Generator().manual_seed(5)
    x, w, r = _data(gen)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        weighted_ridge(x, w, r, LAM)


def test_j_criterion_rejects_wrong_u_shape():
    with pytest.raises(ValueError, match="u must have shape"):
        j_criterion(torch.ones(3, 2), torch.ones(3), torch.eye(3), LAM)


def _dense_flattened_j(x, w, u, lam, nu):
    """Eq. F2 written out: L_ν = (A_ν + λI)^{-1} Xᵀ W^ν / n, J = tr(Ũ L_ν L_νᵀ)."""
    return _dense_j(x, torch.where(w > 0, w**nu, 0.0), u, lam)


@pytest.mark.parametrize("nu", [0.0, 0.3, 0.75])
def test_flattened_j_criterion_matches_dense_form(nu):
    gen = torch.Generator().manual_seed(5)
    x, w, _ = _data(gen, lead=(3, 2), n=40)
    w[..., :5] = 0.0  # zero weights stay zero for every ν (padding)
    z = torch.randn(3, 1, 7, 7, generator=gen, dtype=torch.float64)
    u = z @ z.mT / 7
    j = j_criterion(x, w, u, LAM, flattening=nu)
    for zi in range(3):
        for k in range(2):
            ref = _dense_flattened_j(x[zi, k], w[zi, k], u[zi, 0], LAM, nu)
            assert abs(j[zi, k].item() - ref) <= 1e-8 * abs(ref)


def test_flattening_one_is_the_unflattened_j_to_the_bit():
    gen = torch.Generator().manual_seed(6)
    x, w, _ = _data(gen, lead=(2,), n=30)
    u = torch.eye(7, dtype=torch.float64).expand(2, 7, 7)
    assert torch.equal(j_criterion(x, w, u, LAM, flattening=1.0), j_criterion(x, w, u, LAM))
    with pytest.raises(ValueError, match="cannot be flattened"):
        j_criterion(x, w, u, LAM, sq_weights=w**2, flattening=0.5)


@pytest.mark.parametrize(
    ("values", "expected"),
    [
        ([1.0, 2.0, 3.0], True),
        ([1.0, float("nan"), 3.0], False),
        ([1.0, float("inf"), 3.0], False),
        ([float("inf"), float("-inf")], False),  # the sum is NaN
        ([1e308, 1e308], True),  # finite entries whose sum overflows: the entry-wise test decides
        ([1e308, 1e308, float("nan")], False),
    ],
)
def test_all_finite_agrees_with_the_entry_wise_test(values, expected):
    from torch_api._checks import all_finite

    t = torch.tensor(values, dtype=torch.float64)
    assert all_finite(t) is expected
    assert bool(torch.isfinite(t).all()) is expected


def test_a_nan_in_x_reaches_the_moments_check():
    x = torch.ones(3, 2, dtype=torch.float64)
    x[1, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or inf"):
        weighted_ridge(x, torch.ones(3), torch.ones(3), LAM)
