"""Tests of envs/chain_walk/ against independent ground truth.

Reference values come from plain loops / NumPy over the paper's description (section 3.5),
brute force over all 2^10 deterministic policies, and sampling from the TorchRL env; never from
the functions under test themselves.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from envs.chain_walk import (
    CENTERS,
    DEFAULT_REWARD_PROFILE,
    GAMMA,
    N_STATES,
    SUCCESS_PROB,
    TAU,
    ChainWalkEnv,
    actions_to_string,
    chain_walk_model,
    chain_walk_transitions,
    deterministic_policy_probs,
    exact_psi,
    expected_discounted_return,
    expected_reward,
    optimal_policy,
    policy_q_values,
    state_action_occupancy,
    true_generalisation_error,
)

S, A = N_STATES, 2
BASE_POLICIES = ("RRRRRRRRRR", "RLLLLLRRRR", "LLLLLRRRRR")  # docs/chain_walk.md


# ---------------------------------------------------------------------------------------------
# Independent references (plain Python / NumPy)
# ---------------------------------------------------------------------------------------------


def reference_transitions(n: int = S, p: float = SUCCESS_PROB) -> np.ndarray:
    """P[s, a, s'] written out from the paper's description, one entry at a time."""
    P = np.zeros((n, 2, n))
    for s in range(n):
        for a, step in ((0, -1), (1, +1)):
            ok = min(max(s + step, 0), n - 1)
            fail = min(max(s - step, 0), n - 1)
            P[s, a, ok] += p
            P[s, a, fail] += 1 - p
    return P


def reference_policy(pi_letters: str, eps: float) -> np.ndarray:
    pi = np.full((len(pi_letters), 2), eps / 2)
    for s, c in enumerate(pi_letters):
        pi[s, "LR".index(c)] = 1 - eps / 2
    return pi


def gaussian_phi_all() -> np.ndarray:
    """The paper's 12 basis functions (eq. 50) at every (s, a), s = 1 … 10: [S, A, 12]."""
    phi = np.zeros((S, A, 12))
    for s in range(S):
        for a in range(A):
            for i, c in enumerate(CENTERS):
                phi[s, a, 2 * i + a] = math.exp(-((s + 1 - c) ** 2) / (2 * TAU**2))
            phi[s, a, 10 + a] = 1.0
    return phi


def state_values(P: np.ndarray, R: np.ndarray, actions: tuple[int, ...], gamma: float):
    """V^pi of a deterministic policy by a state-value linear solve."""
    idx = np.arange(len(actions))
    P_pi = P[idx, list(actions)]
    r_pi = R[idx, list(actions)]
    return np.linalg.solve(np.eye(len(actions)) - gamma * P_pi, r_pi)


def sample_policy(pi: torch.Tensor, seed: int):
    """A rollout policy drawing a ~ pi(.|s) from its own generator."""
    gen = torch.Generator().manual_seed(seed)

    def policy(td):
        s = td["observation"].squeeze(-1).long() - 1
        u = torch.rand(s.shape, generator=gen)
        td["action"] = (u < pi[s, 1].float()).long()
        return td

    return policy


def threshold_policy(td):
    """Deterministic: 'R' left of state 5, 'L' from it on."""
    td["action"] = (td["observation"].squeeze(-1) < 5).long()
    return td


@pytest.fixture(scope="module")
def model():
    return chain_walk_model()


# ---------------------------------------------------------------------------------------------
# The TorchRL environment
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("max_steps", [None, 4])
@pytest.mark.parametrize("batch_size", [5, (2, 3)])
def test_check_env_specs(batch_size, max_steps):
    env = ChainWalkEnv(batch_size=batch_size, max_steps=max_steps, seed=0)
    check_env_specs(env)


def test_rollout_shapes_and_values():
    E, N = 8, 30
    env = ChainWalkEnv(batch_size=E, seed=1)
    td = env.rollout(N, break_when_any_done=False)
    assert td.batch_size == (E, N)
    assert td["observation"].shape == (E, N, 1) and td["observation"].dtype == torch.float32
    assert td["action"].shape == (E, N) and td["action"].dtype == torch.int64
    assert td["next", "reward"].shape == (E, N, 1) and td["next", "reward"].dtype == torch.float32
    for key in ("done", "terminated", "truncated"):
        assert td["next", key].shape == (E, N, 1) and td["next", key].dtype == torch.bool
        assert not td["next", key].any()
    obs = td["observation"]
    assert ((obs >= 1) & (obs <= S)).all() and torch.equal(obs, obs.round())
    # Consecutive states differ by at most one; the reward is f(s').
    nxt = td["next", "observation"]
    assert torch.equal(td["observation"][:, 1:], nxt[:, :-1])
    assert ((nxt - obs).abs() <= 1).all()
    f = torch.tensor(DEFAULT_REWARD_PROFILE, dtype=torch.float32)
    assert torch.equal(td["next", "reward"].squeeze(-1), f[nxt.squeeze(-1).long() - 1])


def test_max_steps_truncates_and_resets():
    env = ChainWalkEnv(batch_size=3, max_steps=4, seed=2)
    td = env.rollout(12, threshold_policy, break_when_any_done=False)
    done = td["next", "done"].squeeze(-1)
    expected = torch.tensor([False, False, False, True] * 3).expand(3, 12)
    assert torch.equal(done, expected)
    assert torch.equal(td["next", "truncated"].squeeze(-1), expected)
    assert not td["next", "terminated"].any()
    assert torch.equal(td["step_count"].squeeze(-1), torch.tensor([0, 1, 2, 3] * 3).expand(3, 12))


def test_initial_state_is_uniform():
    n = 20_000
    obs = ChainWalkEnv(batch_size=n, seed=3).reset()["observation"].squeeze(-1).long()
    counts = torch.bincount(obs - 1, minlength=S).double()
    assert counts.sum() == n and counts.min() > 0
    sd = math.sqrt(n * 0.1 * 0.9)  # binomial sd of each count
    assert ((counts - n / S).abs() < 5 * sd).all()


@pytest.mark.parametrize("success_prob", [SUCCESS_PROB, 0.3])
def test_empirical_transitions_match_P(success_prob):
    """One batched step from every (s, a), 5000 walkers each, against the reference P."""
    n = 5000
    env = ChainWalkEnv(batch_size=S * A * n, success_prob=success_prob, seed=4)
    s = torch.arange(1, S + 1).repeat_interleave(A * n)
    a = torch.arange(A).repeat_interleave(n).repeat(S)
    td = env.reset()
    td["observation"] = s.float().unsqueeze(-1)
    td["action"] = a
    out = env.step(td)["next"]
    s_next = out["observation"].squeeze(-1).long()
    counts = torch.zeros(S, A, S, dtype=torch.float64)
    counts.index_put_((s - 1, a, s_next - 1), torch.ones(len(s), dtype=torch.float64), True)
    freq = counts / n
    P = reference_transitions(p=success_prob)
    # Impossible transitions never occur; possible ones lie within 5 binomial sd of P.
    assert (freq.numpy()[P == 0] == 0).all()
    sd = np.sqrt(P * (1 - P) / n)
    assert (np.abs(freq.numpy() - P) <= 5 * sd + 1e-12).all()
    f = torch.tensor(DEFAULT_REWARD_PROFILE, dtype=torch.float32)
    assert torch.equal(out["reward"].squeeze(-1), f[s_next - 1])


def test_transition_tensor_matches_reference_and_boundaries():
    for p in (0.0, 0.3, SUCCESS_PROB, 1.0):
        P = chain_walk_transitions(S, p)
        assert P.shape == (S, A, S) and P.dtype == torch.float64
        np.testing.assert_allclose(P.numpy(), reference_transitions(p=p), atol=1e-15)
        torch.testing.assert_close(P.sum(-1), torch.ones(S, A, dtype=torch.float64))
    P = chain_walk_transitions()
    L, R = 0, 1
    # docs/chain_walk.md / paper section 3.5: P(s'=1|s=1,R) = 0.2, P(s'=2|s=1,R) = 0.8.
    assert P[0, R, 0] == pytest.approx(0.2) and P[0, R, 1] == pytest.approx(0.8)
    assert P[0, L, 0] == pytest.approx(0.8) and P[0, L, 1] == pytest.approx(0.2)
    assert P[9, R, 9] == pytest.approx(0.8) and P[9, R, 8] == pytest.approx(0.2)
    assert P[9, L, 9] == pytest.approx(0.2) and P[9, L, 8] == pytest.approx(0.8)
    assert P[4, R, 5] == pytest.approx(0.8) and P[4, R, 3] == pytest.approx(0.2)


def test_expected_reward_matches_loop(model):
    P = reference_transitions()
    f = DEFAULT_REWARD_PROFILE
    ref = np.array([[sum(P[s, a, t] * f[t] for t in range(S)) for a in range(A)] for s in range(S)])
    np.testing.assert_allclose(model.expected_reward.numpy(), ref, atol=1e-15)
    np.testing.assert_allclose(
        expected_reward(model.transitions, torch.tensor(f)).numpy(), ref, atol=1e-15
    )
    assert torch.equal(model.initial, torch.full((S,), 0.1, dtype=torch.float64))
    env_model = ChainWalkEnv(batch_size=1, seed=0).model()
    assert torch.equal(env_model.transitions, model.transitions)
    assert torch.equal(env_model.expected_reward, model.expected_reward)


def test_same_seed_same_trajectory():
    def run(env):
        return env.rollout(25, threshold_policy, break_when_any_done=False)

    a = run(ChainWalkEnv(batch_size=16, seed=123))
    b = run(ChainWalkEnv(batch_size=16, seed=123))
    c = run(ChainWalkEnv(batch_size=16, seed=124))
    assert torch.equal(a["next", "observation"], b["next", "observation"])
    assert torch.equal(a["observation"], b["observation"])
    assert not torch.equal(a["next", "observation"], c["next", "observation"])
    # Re-seeding an env replays the same trajectory.
    env = ChainWalkEnv(batch_size=16, seed=7)
    first = run(env)
    env.set_seed(7)
    assert torch.equal(run(env)["next", "observation"], first["next", "observation"])


def test_seeding_leaves_global_rng_alone():
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    env = ChainWalkEnv(batch_size=4)  # seed=None: fresh entropy, not from the global RNG
    env.rollout(5, threshold_policy, break_when_any_done=False)
    assert torch.equal(torch.rand(3), expected)


def test_partial_reset_keeps_other_rows():
    env = ChainWalkEnv(batch_size=6, max_steps=10, seed=5)
    td = env.reset()
    td["action"] = torch.ones(6, dtype=torch.int64)
    td = env.step(td)["next"].exclude("reward")
    mask = torch.tensor([True, False, True, False, False, True]).unsqueeze(-1)
    before = td["observation"].clone()
    direct = env._reset(td.clone().set("_reset", mask))
    assert torch.equal(direct["observation"][~mask.squeeze(-1)], before[~mask.squeeze(-1)])
    after = env.reset(td.clone().set("_reset", mask))
    keep = ~mask.squeeze(-1)
    assert torch.equal(after["observation"][keep], before[keep])
    assert torch.equal(after["step_count"].squeeze(-1), torch.where(mask.squeeze(-1), 0, 1))
    assert not after["done"].any()


def test_one_hot_and_trailing_one_actions_match_indices():
    actions = torch.tensor([0, 1, 1, 0, 1])
    results = []
    for action in (actions, actions.unsqueeze(-1), torch.nn.functional.one_hot(actions, 2)):
        env = ChainWalkEnv(batch_size=5, seed=9)
        td = env.reset()
        td["action"] = action
        results.append(env.step(td)["next", "observation"])
    assert torch.equal(results[0], results[1]) and torch.equal(results[0], results[2])


def test_bad_step_inputs_raise():
    env = ChainWalkEnv(batch_size=3, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([0, 2, 1])
    with pytest.raises(ValueError, match="action"):
        env.step(td)
    td = env.reset()
    td["action"] = torch.tensor([0, 1, 1])
    td["observation"] = torch.tensor([[0.0], [3.0], [11.0]])
    with pytest.raises(ValueError, match="observation"):
        env.step(td)


def test_runs_on_given_device():
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        env = ChainWalkEnv(batch_size=4, max_steps=3, device=device, seed=0)
        check_env_specs(env)
        td = env.rollout(5, break_when_any_done=False)
        assert td["next", "observation"].device.type == torch.device(device).type
        assert env.model().transitions.device.type == torch.device(device).type


# ---------------------------------------------------------------------------------------------
# The exact model
# ---------------------------------------------------------------------------------------------


def test_deterministic_policy_probs():
    pi = deterministic_policy_probs("RLLLLLRRRR", epsilon=0.1)
    np.testing.assert_allclose(pi.numpy(), reference_policy("RLLLLLRRRR", 0.1), atol=1e-15)
    assert torch.equal(
        deterministic_policy_probs([1, 0], 0.0), torch.tensor([[0.0, 1], [1, 0]]).double()
    )
    torch.testing.assert_close(
        deterministic_policy_probs("RL", 1.0), torch.full((2, 2), 0.5, dtype=torch.float64)
    )
    torch.testing.assert_close(  # eps is capped at 1
        deterministic_policy_probs("RL", 1.7), torch.full((2, 2), 0.5, dtype=torch.float64)
    )
    batched = deterministic_policy_probs("RRL", torch.tensor([0.0, 0.4, 1.0]))
    assert batched.shape == (3, 3, 2)
    torch.testing.assert_close(batched[1], deterministic_policy_probs("RRL", 0.4))
    assert actions_to_string(torch.tensor([1, 0, 0, 1])) == "RLLR"
    assert actions_to_string(deterministic_policy_probs("LRRL").argmax(-1)) == "LRRL"


POLICIES = [(letters, eps) for letters in BASE_POLICIES for eps in (0.0, 0.1, 0.7)]


@pytest.mark.parametrize(("letters", "eps"), POLICIES)
def test_q_values_satisfy_bellman_and_match_iteration(model, letters, eps):
    P, R = model.transitions, model.expected_reward
    pi = deterministic_policy_probs(letters, eps)
    Q = policy_q_values(P, R, pi, GAMMA)
    # Eq. 5, written with explicit expectations.
    V = (pi * Q).sum(-1)
    rhs = R + GAMMA * torch.einsum("sat,t->sa", P, V)
    assert (Q - rhs).abs().max() < 1e-10
    # Independent: iterate the Bellman operator in NumPy from zero (0.9^600 ~ 1e-28).
    Pn, Rn, pin = reference_transitions(), R.numpy(), reference_policy(letters, eps)
    q = np.zeros((S, A))
    for _ in range(600):
        q = Rn + GAMMA * Pn @ (pin * q).sum(-1)
    np.testing.assert_allclose(Q.numpy(), q, atol=1e-10)


def test_q_values_batched_policies(model):
    P, R = model.transitions, model.expected_reward
    pis = deterministic_policy_probs("RLLLLLRRRR", torch.tensor([0.1, 0.5, 0.9]))
    Q = policy_q_values(P, R, pis, GAMMA)
    assert Q.shape == (3, S, A)
    for k in range(3):
        torch.testing.assert_close(Q[k], policy_q_values(P, R, pis[k], GAMMA))


@pytest.mark.parametrize("profile_seed", [None, 0, 1, 2])
def test_optimal_policy_beats_all_deterministic_policies(profile_seed):
    if profile_seed is None:
        f = DEFAULT_REWARD_PROFILE
    else:
        f = tuple(np.random.default_rng(profile_seed).uniform(0, 1, S))
    m = chain_walk_model(f)
    actions, q_star = optimal_policy(m.transitions, m.expected_reward, GAMMA)
    assert actions.shape == (S,) and actions.dtype == torch.int64
    Pn, Rn = reference_transitions(), m.expected_reward.numpy()
    all_values = np.stack(
        [state_values(Pn, Rn, pol, GAMMA) for pol in itertools.product((0, 1), repeat=S)]
    )  # [1024, S]
    best = all_values.max(0)
    np.testing.assert_allclose(q_star.max(-1).values.numpy(), best, atol=1e-10)
    np.testing.assert_allclose(
        state_values(Pn, Rn, tuple(actions.tolist()), GAMMA), best, atol=1e-10
    )


def test_optimal_policy_ties_go_to_lowest_action():
    m = chain_walk_model((0.5,) * S)  # every action is equally good everywhere
    actions, q_star = optimal_policy(m.transitions, m.expected_reward, GAMMA)
    assert actions.tolist() == [0] * S
    torch.testing.assert_close(q_star, torch.full((S, A), 5.0, dtype=torch.float64))


@pytest.mark.parametrize(("letters", "eps"), POLICIES)
def test_occupancy_matches_brute_force_propagation(model, letters, eps):
    n_steps = 10
    d = state_action_occupancy(
        model.transitions, deterministic_policy_probs(letters, eps), model.initial, n_steps
    )
    assert d.sum().item() == pytest.approx(1.0, abs=1e-12)
    Pn, pin = reference_transitions(), reference_policy(letters, eps)
    mu = [1.0 / S] * S
    ref = np.zeros((S, A))
    for _ in range(n_steps):
        nxt = [0.0] * S
        for s in range(S):
            for a in range(A):
                ref[s, a] += mu[s] * pin[s, a] / n_steps
                for t in range(S):
                    nxt[t] += mu[s] * pin[s, a] * Pn[s, a, t]
        mu = nxt
    np.testing.assert_allclose(d.numpy(), ref, atol=1e-14)


def test_exact_psi_matches_loop(model):
    gen = np.random.default_rng(0)
    for phi in (gaussian_phi_all(), gen.normal(size=(S, A, 7))):
        for letters in BASE_POLICIES:
            pin = reference_policy(letters, 0.1)
            psi = exact_psi(model.transitions, torch.tensor(phi), torch.tensor(pin), GAMMA)
            Pn = reference_transitions()
            ref = np.zeros_like(phi)
            for s, a in itertools.product(range(S), range(A)):
                nxt = sum(Pn[s, a, t] * pin[t, b] * phi[t, b] for t in range(S) for b in range(A))
                ref[s, a] = phi[s, a] - GAMMA * nxt
            np.testing.assert_allclose(psi.numpy(), ref, atol=1e-13)
    pis = deterministic_policy_probs("RLLLLLRRRR", torch.tensor([0.2, 0.6]))
    batched = exact_psi(model.transitions, torch.tensor(phi), pis, GAMMA)
    torch.testing.assert_close(
        batched[1], exact_psi(model.transitions, torch.tensor(phi), pis[1], GAMMA)
    )


def test_generalisation_error_is_zero_at_q_pi_with_tabular_basis(model):
    """With a tabular basis, theta = Q^pi solves theta^T psi = R exactly (eq. 5 and 14)."""
    P, R = model.transitions, model.expected_reward
    pi = deterministic_policy_probs("LLLLLRRRRR", 0.1)
    phi = torch.eye(S * A, dtype=torch.float64).reshape(S, A, S * A)
    psi = exact_psi(P, phi, pi, GAMMA)
    d = state_action_occupancy(P, pi, model.initial, 10)
    theta = policy_q_values(P, R, pi, GAMMA).reshape(S * A)
    assert true_generalisation_error(theta, psi, R, d).item() < 1e-20
    assert true_generalisation_error(theta + 0.1, psi, R, d).item() > 1e-4


def test_generalisation_error_matches_loop_and_batches(model):
    P, R = model.transitions, model.expected_reward
    pi = deterministic_policy_probs("RLLLLLRRRR", 0.1)
    psi = exact_psi(P, torch.tensor(gaussian_phi_all()), pi, GAMMA)
    d = state_action_occupancy(P, pi, model.initial, 10)
    thetas = torch.randn(3, 4, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    G = true_generalisation_error(thetas, psi, R, d)
    assert G.shape == (3, 4)
    psin, Rn, dn = psi.numpy(), R.numpy(), d.numpy()
    for i, j in itertools.product(range(3), range(4)):
        th = thetas[i, j].numpy()
        ref = sum(
            dn[s, a] * (float(th @ psin[s, a]) - Rn[s, a]) ** 2 for s in range(S) for a in range(A)
        )
        assert G[i, j].item() == pytest.approx(ref, rel=1e-12)
    # float32 theta is promoted.
    assert true_generalisation_error(thetas[0, 0].float(), psi, R, d).dtype == torch.float64


def test_expected_return_matches_monte_carlo(model):
    """Eq. 61 performance: exact value against 20 000 sampled 50-step episodes."""
    letters, eps, horizon, n = "RLLLLLRRRR", 0.1, 50, 20_000
    pi = deterministic_policy_probs(letters, eps)
    exact = expected_discounted_return(
        model.transitions, model.expected_reward, pi, model.initial, GAMMA, horizon
    )
    assert exact.shape == ()
    env = ChainWalkEnv(batch_size=n, seed=11)
    td = env.rollout(horizon, sample_policy(pi, seed=12), break_when_any_done=False)
    r = td["next", "reward"].squeeze(-1).double()  # [n, horizon]
    returns = (r * GAMMA ** torch.arange(horizon, dtype=torch.float64)).sum(-1)
    se = returns.std().item() / math.sqrt(n)
    assert abs(returns.mean().item() - exact.item()) < 4 * se


def test_expected_return_limits_and_batching(model):
    P, R, mu = model.transitions, model.expected_reward, model.initial
    pis = deterministic_policy_probs("LLLLLRRRRR", torch.tensor([0.0, 0.3, 1.0]))
    # Horizon 1: the expected first reward under the uniform start.
    one = expected_discounted_return(P, R, pis, mu, GAMMA, 1)
    ref = np.array(
        [(reference_policy("LLLLLRRRRR", e) * R.numpy()).sum() / S for e in (0.0, 0.3, 1.0)]
    )
    np.testing.assert_allclose(one.numpy(), ref, atol=1e-15)
    # Long horizon: the infinite-horizon value mu^T V^pi from Q^pi (0.9^1000 ~ 1e-46).
    long = expected_discounted_return(P, R, pis, mu, GAMMA, 1000)
    v0 = (mu * (pis * policy_q_values(P, R, pis, GAMMA)).sum(-1)).sum(-1)
    torch.testing.assert_close(long, v0, atol=1e-10, rtol=0)
    assert long.shape == (3,)


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_errors_naming_the_argument(model):
    P, R, mu = model.transitions, model.expected_reward, model.initial
    pi = deterministic_policy_probs("RRRRRRRRRR", 0.1)
    cases = [
        (lambda: ChainWalkEnv(batch_size=2, reward_profile=(0.0,) * 9), "reward_profile"),
        (lambda: ChainWalkEnv(batch_size=2, success_prob=1.5), "success_prob"),
        (lambda: ChainWalkEnv(batch_size=2, max_steps=0), "max_steps"),
        (lambda: ChainWalkEnv(batch_size=0), "batch_size"),
        (lambda: chain_walk_transitions(10, -0.1), "success_prob"),
        (lambda: chain_walk_transitions(1), "n_states"),
        (lambda: chain_walk_model((0.0,) * 11), "reward_profile"),
        (lambda: expected_reward(P, torch.zeros(9)), "reward_profile"),
        (lambda: policy_q_values(P, R, pi, 1.0), "gamma"),
        (lambda: policy_q_values(P, R, pi * 0.9, GAMMA), "policy_probs"),
        (lambda: policy_q_values(P, R, pi[:9], GAMMA), "policy_probs"),
        (lambda: policy_q_values(P * 2, R, pi, GAMMA), "P"),
        (lambda: state_action_occupancy(P, pi, mu * 2, 10), "initial"),
        (lambda: state_action_occupancy(P, pi, mu, 0), "n_steps"),
        (lambda: exact_psi(P, torch.zeros(9, 2, 12), pi, GAMMA), "phi_all"),
        (lambda: true_generalisation_error(torch.zeros(11), torch.zeros(S, A, 12), R, R), "psi"),
        (lambda: expected_discounted_return(P, R, pi, mu, GAMMA, 0), "horizon"),
        (lambda: deterministic_policy_probs("RLX"), "actions"),
        (lambda: deterministic_policy_probs([0, 2]), "actions"),
        (lambda: deterministic_policy_probs("RL", -0.1), "epsilon"),
    ]
    for make, name in cases:
        with pytest.raises(ValueError, match=name):
            make()


def test_walk_draws_the_numbers_of_a_rollout():
    """``env.walk`` (no TorchRL machinery) gives the states and rewards of ``env.rollout``
    with the same policy and streams, bit for bit."""
    from counter_rng import CounterStreams
    from torch_api.collect import collect_episodes
    from torch_api.policies import TabularPolicy
    from torch_api.policy_base import sample_actions

    trials, m, n = 3, 4, 12
    table = torch.rand(
        trials, 10, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    table = table / table.sum(-1, keepdim=True)
    keys = [11, 12, 13]

    def state_index(obs):
        return obs[..., 0].round().long() - 1

    env = ChainWalkEnv(batch_size=trials * m)
    env.set_block_seeds([21, 22, 23])
    policy = TabularPolicy(table=table, state_index=state_index, streams=CounterStreams(keys))
    episodes = collect_episodes(env, policy, num_episodes=m, num_steps=n, rewarded=True)
    env.set_block_seeds([21, 22, 23])
    rows, streams = table.repeat_interleave(m, 0), CounterStreams(keys)

    def choose(state):
        return sample_actions(rows[torch.arange(len(state)), state - 1], streams)

    states, rewards = env.walk(choose, n)
    assert torch.equal(states[:, :-1].reshape(trials, m, n), episodes["observation"][..., 0].long())
    assert torch.equal(
        rewards.reshape(trials, m, n), episodes["next", "reward"].reshape(trials, m, n)
    )


def test_walk_tabulated_has_the_law_of_a_rollout():
    """``env.walk_tabulated`` (the actions summed out, one uniform a step) gives the states of
    a rollout of the same policy in law: the frequency of each state at every step matches
    the exact distribution ``d_{n+1} = d_n P_pi`` of the model (chi-square over 60,000 walks),
    and so do those of ``env.walk``, which draws the actions."""
    from scipy import stats

    from torch_api.policy_base import sample_actions

    tables, per_table, n = 2, 30_000, 6
    table = torch.rand(tables, 10, 2, generator=torch.Generator().manual_seed(3))
    table = table.to(torch.float64)
    table = table / table.sum(-1, keepdim=True)
    model = chain_walk_model()
    env = ChainWalkEnv(batch_size=tables * per_table, seed=5)
    states, rewards = env.walk_tabulated(table, n)  # time-major
    assert states.shape == (n + 1, tables * per_table) and rewards.shape == (n, tables * per_table)
    assert torch.equal(rewards, model.reward_profile.to(torch.float32)[states[1:] - 1])
    states = states.T
    rows = table.repeat_interleave(per_table, 0)
    drawn, _ = ChainWalkEnv(batch_size=tables * per_table, seed=6).walk(
        lambda s: sample_actions(rows[torch.arange(len(s)), s - 1]), n
    )
    for k in range(tables):
        chain = torch.einsum("sa,sat->st", table[k], model.transitions)  # P_pi [S, S]
        d = torch.full((10,), 0.1, dtype=torch.float64)
        for step in range(n + 1):
            for walks in (states, drawn):
                block = walks[k * per_table : (k + 1) * per_table, step]
                seen = torch.bincount(block - 1, minlength=10).numpy()
                p = stats.chisquare(seen, (d / d.sum() * per_table).numpy()).pvalue
                assert p > 1e-4, (k, step, p)
            d = d @ chain


def test_walk_tabulated_blocks_draw_alone():
    """Rows of one table seeded as a block draw what an env of that block alone draws."""
    table = torch.tensor([[0.3, 0.7]], dtype=torch.float64).expand(3, 10, 2)
    env = ChainWalkEnv(batch_size=3 * 4)
    env.set_block_seeds([7, 8, 9])
    together = env.walk_tabulated(table, 5)
    alone = ChainWalkEnv(batch_size=4, seed=8).walk_tabulated(table[:1], 5)
    assert torch.equal(together[0][:, 4:8], alone[0])
    assert torch.equal(together[1][:, 4:8], alone[1])
    with pytest.raises(ValueError, match="K dividing"):
        env.walk_tabulated(table[:, :, :1], 5)
