"""Bad input that used to fail late or silently (issue #45): refused where it enters, with one
line naming the value."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import GymEnv

from torch_api.collection.collect import EnvPerBatch
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.psi import PsiHat, psi_hat
from torch_api.core.solve import j_criterion, j_from_moments, weighted_ridge
from torch_api.data import EpisodeBuffer, as_episodes, validate_episodes
from torch_api.policies import LinearQPolicy, TabularPolicy
from torch_api.policies.families import EpsilonGreedyFamily, candidate_epsilons, make_family

NAN, INF = float("nan"), float("inf")


def _basis(**kwargs) -> GaussianActionBasis:
    return GaussianActionBasis(centers=torch.zeros(1, 1), tau=1.0, num_actions=2, **kwargs)


def _episodes(m: int = 2, n: int = 3, **overrides) -> TensorDict:
    entries = {
        "observation": torch.zeros(m, n, 1),
        "action": torch.zeros(m, n, dtype=torch.long),
        ("next", "observation"): torch.zeros(m, n, 1),
        "mask": torch.ones(m, n, dtype=torch.bool),
        "sample_probs": torch.full((m, n, 2), 0.5, dtype=torch.float64),
    } | overrides
    return TensorDict(entries, batch_size=[m, n])


# ε of the ε-greedy policies and of the candidate family


@pytest.mark.parametrize("epsilon", [2, 1.5, torch.tensor([0.5, 1.2])])
def test_an_epsilon_above_one_is_refused_by_the_policy(epsilon):
    """Before: ``LinearQPolicy(epsilon=2)`` was silently the uniform policy."""
    with pytest.raises(ValueError, match=r"epsilon must lie in \[0, 1\], got"):
        LinearQPolicy(basis=_basis(), theta=torch.ones(4), epsilon=epsilon)
    policy = LinearQPolicy(basis=_basis(), theta=torch.ones(4), epsilon=0.5)
    with pytest.raises(ValueError, match=r"epsilon must lie in \[0, 1\], got"):
        policy.with_rule(epsilon=epsilon)


def test_epsilon_one_and_the_paper_candidates_are_accepted():
    policy = LinearQPolicy(basis=_basis(), theta=torch.ones(4), epsilon=1.0)
    probs = policy.action_probs(torch.zeros(3, 1))
    torch.testing.assert_close(probs, torch.full((3, 2), 0.5, dtype=torch.float64))
    for l in (1, 2, 7):  # ε_l + 0.85 <= 1 for the paper's ε_l = 0.15 / l
        rules = EpsilonGreedyFamily().candidate_rules(l)
        assert rules.max() <= 1.0
        policy.with_rule(epsilon=rules)
    assert candidate_epsilons(0.15) == [0.15, 0.3, 0.65, 1.0]


def test_candidate_offsets_that_push_epsilon_above_one_are_refused_up_front():
    """Before: ε_1 + 0.95 = 1.1 was clipped to 1 without a word."""
    with pytest.raises(
        ValueError,
        match=r"candidate_offsets .* ε_1 \+ 0.95 = 1.1; every ε_1 \+ offset must lie in \[0, 1\]",
    ):
        make_family("epsilon_greedy", candidate_offsets=(0.0, 0.15, 0.5, 0.95))
    with pytest.raises(ValueError, match=r"ε_1 \+ -0.2 = -0.05"):
        EpsilonGreedyFamily(offsets=(0.0, -0.2))
    with pytest.raises(ValueError, match=r"epsilon \+ offset must lie in \[0, 1\], got 0.5 \+ 0.6"):
        candidate_epsilons(0.5, (0.0, 0.6))
    rising = EpsilonGreedyFamily(epsilon_schedule=lambda l: 0.05 * l)  # 0.05 + 0.85 is fine
    with pytest.raises(ValueError, match=r"iteration 4: ε_4 \+ 0.85 = 1.05"):
        rising.candidate_rules(4)


# J's Ũ


def test_a_negative_u_is_refused_by_j():
    """Before: J came out negative (an 'error estimate' below 0)."""
    x = torch.randn(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    w = torch.ones(50)
    u = torch.eye(3, dtype=torch.float64)
    assert j_criterion(x, w, u) >= 0
    with pytest.raises(ValueError, match=r"u .* positive semi-definite.* diagonal .* -1"):
        j_criterion(x, w, -u)
    indefinite = torch.tensor([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"u .* not positive semi-definite"):
        j_criterion(x, w, indefinite.double())
    with pytest.raises(ValueError, match=r"u .* NaN or inf"):
        j_criterion(x, w, torch.full((3, 3), NAN, dtype=torch.float64))
    a = x.mT @ x / 50
    with pytest.raises(ValueError, match=r"u .* diagonal .* -1"):
        j_from_moments(a, a, -u)


def test_a_positive_semi_definite_u_with_negative_entries_is_accepted():
    """Ũ is a second moment Σ w x xᵀ / n: its off-diagonal entries may well be negative."""
    x = torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    v = torch.tensor([[1.0, -1.0, 0.0]], dtype=torch.float64)
    u = v.mT @ v  # rank 1, off-diagonal -1
    assert j_criterion(x, torch.ones(40), u) >= 0


# psi_hat of NaN features or observations


def test_psi_hat_refuses_nan_and_inf_features():
    """Before: NaN rows came out of psi_hat."""
    with pytest.raises(ValueError, match=r"phi .* NaN or inf"):
        psi_hat(torch.tensor([[NAN, 1.0]]), torch.zeros(1, 2), 0.9)
    with pytest.raises(ValueError, match=r"next_features .* NaN or inf"):
        psi_hat(torch.zeros(1, 2), torch.tensor([[INF, 1.0]]), 0.9)
    # a masked (padding) row may hold anything: its psi_hat row is zero
    rows = psi_hat(
        torch.tensor([[0.0, 1.0], [NAN, 1.0]]), torch.zeros(2, 2), 0.9, mask=torch.tensor([1, 0])
    )
    assert rows.tolist() == [[0.0, 1.0], [0.0, 0.0]]


@pytest.mark.parametrize("where", ["obs", "next_obs"])
def test_psi_hat_module_refuses_nan_observations(where):
    psi = PsiHat(basis=_basis(), gamma=0.9, mode="single")
    good = torch.zeros(2, 1)
    bad = torch.tensor([[0.0], [NAN]])
    obs, next_obs = (bad, good) if where == "obs" else (good, bad)
    with pytest.raises(ValueError, match=rf"{where} .* NaN or inf"):
        psi(obs, torch.tensor([0, 1]), next_obs, torch.full((2, 2), 0.5))
    mask = torch.tensor([True, False])  # NaN on a padding step: ignored, its row zero
    out = psi(obs, torch.tensor([0, 1]), next_obs, torch.full((2, 2), 0.5), mask=mask)
    assert torch.isfinite(out).all() and not out[1].any()


# the episodes' mask


def test_a_float_mask_is_refused():
    """Before: torch's own RuntimeError from deep inside the checks."""
    with pytest.raises(ValueError, match=r"mask must be a bool tensor .* got torch.float32"):
        validate_episodes(_episodes(mask=torch.ones(2, 3)), rewarded=False)
    with pytest.raises(ValueError, match=r"mask must be a bool tensor .* got torch.float32"):
        EpisodeBuffer(rewarded=False).extend(_episodes(mask=torch.ones(2, 3)))


# meta tensors


def test_meta_tensors_are_refused_where_they_enter():
    """Before: ``Tensor.item() cannot be called on meta tensors`` from some check inside."""
    with pytest.raises(ValueError, match=r"episodes\['observation'\] is on the meta device"):
        validate_episodes(_episodes().to("meta"), rewarded=False)
    with pytest.raises(ValueError, match=r"the data\[.*\] is on the meta device"):
        as_episodes(GymEnv("CartPole-v1").rollout(3).to("meta"), rewarded=False)
    with pytest.raises(ValueError, match=r"theta is on the meta device"):
        LinearQPolicy(basis=_basis(), theta=torch.ones(4, device="meta"), epsilon=0.1)
    with pytest.raises(ValueError, match=r"table is on the meta device"):
        TabularPolicy(table=torch.ones(3, 2, device="meta") / 2, state_index=lambda o: o)
    with pytest.raises(ValueError, match=r"centers is on the meta device"):
        GaussianActionBasis(centers=torch.zeros(1, 1, device="meta"), tau=1.0, num_actions=2)
    psi = PsiHat(basis=_basis(), gamma=0.9)
    meta = torch.zeros(2, 1, device="meta")
    with pytest.raises(ValueError, match=r"obs is on the meta device"):
        psi(meta, torch.tensor([0, 1]), meta, torch.full((2, 2), 0.5))
    with pytest.raises(ValueError, match=r"phi is on the meta device"):
        psi_hat(torch.zeros(1, 2, device="meta"), torch.zeros(1, 2, device="meta"), 0.9)
    x = torch.zeros(5, 2, device="meta")
    with pytest.raises(ValueError, match=r"x is on the meta device"):
        j_criterion(x, torch.ones(5, device="meta"), torch.eye(2, device="meta"))
    with pytest.raises(ValueError, match=r"x is on the meta device"):
        weighted_ridge(x, torch.ones(5, device="meta"), torch.ones(5, device="meta"))


# env factories


def test_an_env_factory_returning_none_is_refused():
    """Before: ``AttributeError: 'NoneType' object has no attribute 'batch_size'`` later."""
    envs = EnvPerBatch(lambda rows: None)
    with pytest.raises(ValueError, match=r"env factory returned None, expected a TorchRL EnvBase"):
        envs(3)
    with pytest.raises(ValueError, match=r"env factory returned int, expected a TorchRL EnvBase"):
        EnvPerBatch(lambda rows: 3)(2)


# kernel widths


@pytest.mark.parametrize(
    ("tau", "message"),
    [
        (INF, r"tau must be finite"),
        (NAN, r"tau must be > 0"),
        (1e-300, r"tau must be .*1/\(2·tau²\).* finite float64 number \(tau >= 1.05e-154\)"),
        (1e-160, r"tau must be .*1/\(2·tau²\).* finite float64 number \(tau >= 1.05e-154\)"),
    ],
)
def test_tau_is_refused_where_the_kernel_cannot_be_computed(tau, message):
    with pytest.raises(ValueError, match=message):
        GaussianActionBasis(centers=torch.zeros(1, 1), tau=tau, num_actions=2)


@pytest.mark.parametrize(
    ("widths", "message"),
    [
        ([INF, 1.0, 1.0, 1.0], r"widths must be finite numbers > 0, got \[inf, 1.0, 1.0, 1.0\]"),
        ([NAN, 1.0, 1.0, 1.0], r"widths must be finite numbers > 0"),
        ([0.0, 1.0, 1.0, 1.0], r"widths must be finite numbers > 0"),
        ([1e-300, 1.0, 1.0, 1.0], r"widths .*1e-300.* 1/\(2·\(tau·width\)²\).* finite float64"),
        ([1.0, 1.0, 1.0], r"widths must hold one width per state dimension \(4\), got 3"),
    ],
)
def test_kernel_widths_are_checked(widths, message):
    """Before: ``--basis-widths inf,1,1,1`` (a dimension silently ignored) and
    ``1e-300,1,1,1`` (kernels 0 or NaN everywhere) ran to the end."""
    centers = torch.tensor([[0.0, -math.pi, 0.0, 0.0], [math.pi / 4, math.pi, 0.5, 1.0]])
    with pytest.raises(ValueError, match=message):
        GaussianActionBasis(centers=centers, tau=1.0, num_actions=2, widths=widths)


def test_centres_that_overflow_the_basis_dtype_are_refused():
    """The batting example's per-dimension widths divide the centres: with a width of 1e-300
    they overflowed float32 (stored as inf) and the kernels were NaN everywhere."""
    huge = torch.tensor([[0.0], [math.pi / 4 / 1e-300]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"centers must be finite in float32"):
        GaussianActionBasis(centers=huge, tau=1.0, num_actions=2)
    with pytest.raises(ValueError, match=r"\|\|c\|\|²/\(2·tau²\) overflows float64"):
        GaussianActionBasis(centers=torch.tensor([[1e30]]), tau=1e-140, num_actions=2)


def test_widths_scale_the_kernel_per_dimension_as_the_scaled_coordinates_do():
    centers = torch.tensor([[0.0, 1.0], [1.0, -1.0]])
    widths = [0.5, 2.0]
    basis = GaussianActionBasis(centers=centers, tau=1.5, num_actions=2, widths=widths)
    plain = GaussianActionBasis(
        centers=centers / torch.tensor(widths), tau=1.5, num_actions=2
    )  # the same kernel on coordinates divided by the widths
    obs = torch.randn(6, 2, generator=torch.Generator().manual_seed(0))
    assert torch.equal(basis.kernels(obs), plain.kernels(obs / torch.tensor(widths)))
    assert torch.equal(_basis(widths=None).kernels(obs[:, :1]), _basis().kernels(obs[:, :1]))
