"""Algorithm 2: batched J' against a per-candidate dense computation; reward-free invariance."""

import numpy as np
import pytest
import torch

from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.collection import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.data import cat_episodes
from torch_api.loop.selector import SamplingPolicySelector, candidate_epsilons, j_values
from torch_api.policies import LinearQPolicy

LAM = 1e-3


def _setup(seed=0, mode="grouped"):
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    theta = torch.linspace(-1, 1, 12, dtype=torch.float64)
    pi = LinearQPolicy(
        basis=basis, theta=theta, epsilon=0.15, generator=torch.Generator().manual_seed(seed)
    )
    return basis, PsiHat(basis=basis, gamma=0.9, mode=mode), pi


def test_candidate_epsilons_follow_eq_59():
    assert candidate_epsilons(0.15) == [0.15, 0.3, 0.65, 1.0]
    assert candidate_epsilons(0.05) == [0.05, 0.2, 0.55, 0.9]


@pytest.mark.parametrize("with_earlier", [True, False], ids=["earlier-sets", "first-iteration"])
@pytest.mark.parametrize("mode", ["grouped", "single", "knn"])
def test_j_values_match_algorithm_2_written_out(mode, with_earlier):
    """Pooled designs (grouped, k-NN psi_hat) and per-part designs (single) both match.

    Without earlier sets (the first iteration) D̄_0 is still the pool of all K candidates'
    episodes: grouped and k-NN psi_hat average over it, not over each candidate's own.
    """
    _, psi, pi = _setup(mode=mode)
    env = ChainWalkEnv(batch_size=3, seed=0)
    cands = [pi.with_rule(epsilon=e) for e in (0.15, 0.6, 1.0)]
    z, k, m, n = 2, 3, 3, 6
    episodes = torch.stack(
        [
            torch.stack(
                [
                    collect_episodes(env, c, num_episodes=m, num_steps=n, rewarded=False)
                    for c in cands
                ]
            )
            for _ in range(z)
        ]
    )
    earlier = collect_episodes(env, pi, num_episodes=4, num_steps=n, rewarded=True)
    batched = j_values(episodes, earlier if with_earlier else None, pi, psi, LAM)
    assert batched.shape == (z, k)
    plain_earlier = [earlier.exclude(("next", "reward"))] if with_earlier else []
    for zi in range(z):
        d0 = cat_episodes([episodes[zi, ki] for ki in range(k)] + plain_earlier)
        design = build_design(d0, pi, psi)
        x, w = design.x.numpy(), design.w.numpy()
        u = (x.T * w) @ x / x.shape[0]  # Ũ over D̄_0
        for ki in range(k):
            rows = np.r_[ki * m * n : (ki + 1) * m * n, k * m * n : x.shape[0]]  # Π_k
            xk, wk = x[rows], w[rows]
            nk = len(rows)
            a = (xk.T * wk) @ xk / nk
            big_l = np.linalg.solve(a + LAM * np.eye(12), xk.T * wk / nk)  # L, B × n_k
            ref = np.trace(u @ big_l @ big_l.T)
            assert abs(batched[zi, ki].item() - ref) <= 1e-8 * ref


class NaNRewardChain(ChainWalkEnv):
    def _step(self, td):
        out = super()._step(td)
        out["reward"] = torch.full_like(out["reward"], float("nan"))
        return out


def test_choice_is_unchanged_when_reward_free_rewards_are_nan():
    def choose(env_cls):
        _, psi, pi = _setup(seed=5)
        selector = SamplingPolicySelector(
            env=lambda e: env_cls(batch_size=e, seed=11),
            psi=psi,
            num_episodes=4,
            num_steps=10,
            num_repeats=3,
        )
        return selector.select(pi, [pi.with_rule(epsilon=e) for e in candidate_epsilons(0.15)])

    clean, poisoned = choose(ChainWalkEnv), choose(NaNRewardChain)
    assert clean.index == poisoned.index
    assert torch.equal(clean.j_all, poisoned.j_all)
    assert clean.j_all.shape == (3, 4) and torch.isfinite(clean.j_all).all()
    assert ("next", "reward") not in poisoned.episodes.keys(include_nested=True)


def test_batched_and_candidate_by_candidate_collection_agree_in_shape_and_tags():
    _, psi, pi = _setup()
    cands = [pi.with_rule(epsilon=e) for e in (0.15, 1.0)]
    batched = SamplingPolicySelector(
        env=lambda e: ChainWalkEnv(batch_size=e, seed=0),
        psi=psi,
        num_episodes=3,
        num_steps=5,
        num_repeats=2,
    )
    looped = SamplingPolicySelector(
        env=ChainWalkEnv(batch_size=2, seed=0), psi=psi, num_episodes=3, num_steps=5, num_repeats=2
    )
    for sel in (batched, looped):
        eps = sel.collect(cands)
        assert eps.shape == (2, 2, 3, 5)
        assert (eps["policy_id"][:, 1] == 1).all() and (eps["policy_id"][:, 0] == 0).all()
        # the recorded sampling probabilities are those of the tagged candidate
        probs = eps["sample_probs"][:, 1]
        assert torch.allclose(probs, torch.full_like(probs, 0.5))


def test_trial_chunks_give_the_same_j_as_one_batch():
    basis, psi, _ = _setup()
    theta = torch.randn(5, 12, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    pi = LinearQPolicy(basis=basis, theta=theta, epsilon=0.15)
    cands = [pi.with_rule(epsilon=e) for e in (0.15, 0.65)]

    def select(max_bytes):
        selector = SamplingPolicySelector(
            env=lambda e: ChainWalkEnv(batch_size=e, seed=3),
            psi=psi,
            num_episodes=3,
            num_steps=5,
            num_repeats=2,
            max_design_bytes=max_bytes,
        )
        torch.manual_seed(0)  # unseeded policies draw from torch's global generator
        return selector, selector.select(pi, cands)

    one_sel, one = select(2**40)
    chunked_sel, chunked = select(1)  # one trial per chunk
    assert len(chunked_sel._trial_chunks(chunked.episodes, None)) == 5
    assert len(one_sel._trial_chunks(one.episodes, None)) == 1
    assert torch.equal(one.episodes["observation"], chunked.episodes["observation"])
    torch.testing.assert_close(chunked.j_all, one.j_all, rtol=1e-12, atol=0)
    assert torch.equal(chunked.index, one.index) and chunked.j_all.shape == (5, 2, 2)


def test_a_standalone_selector_names_what_it_lacks():
    """Built for a loop (no env, psi or N), used alone it says what to pass; its collection
    strategy is chosen when it is built (or bound), from env, num_workers and collector."""
    _, psi, pi = _setup()
    for_loop = SamplingPolicySelector()
    with pytest.raises(ValueError, match="the selector has no env"):
        for_loop.seed_env(4, 0)
    with pytest.raises(ValueError, match=r"the selector needs \['psi'\]"):
        for_loop.select(pi, [pi])
    no_steps = SamplingPolicySelector(env=ChainWalkEnv(batch_size=2), psi=psi, num_episodes=1)
    with pytest.raises(ValueError, match=r"the selector needs \['num_steps'\]"):
        no_steps.select(pi, [pi])
    loops = {
        "env": lambda e: ChainWalkEnv(batch_size=e, seed=0),
        "psi": psi,
        "num_steps": 5,
        "num_repeats": 2,  # Z: the loop's (spec.selection.num_repeats)
        "lam": LAM,
        "fit": "brm",
        "device": None,
    }
    bound = for_loop.bind(**loops)
    assert type(bound._collection).__name__ == "RolloutCollection"
    assert bound.collect([pi, pi.with_rule(epsilon=1.0)], num_episodes=3).shape == (2, 2, 3, 5)
    assert for_loop.psi is None and for_loop._collection is None  # the original is unchanged
    with pytest.raises(ValueError, match=r"selector: \['num_repeats'\] are the loop's settings"):
        SamplingPolicySelector(num_repeats=2).bind(**loops)  # Z is the loop's spec's


@pytest.mark.parametrize("mode", ["grouped", "single"])
def test_flattened_j_values_match_algorithm_2_written_out(mode):
    """J of the fit with weights w^ν (docs/flattening.md, eq. F2): A and C of Π_k take w^ν
    and w^{2ν}, Ũ keeps w; a per-trial ν tensor equals the number."""
    _, psi, pi = _setup(mode=mode)
    env = ChainWalkEnv(batch_size=3, seed=1)
    cands = [pi.with_rule(epsilon=e) for e in (0.15, 1.0)]
    k, m, n, nu = 2, 3, 8, 0.4
    episodes = torch.stack(
        [collect_episodes(env, c, num_episodes=m, num_steps=n, rewarded=False) for c in cands]
    ).unsqueeze(0)  # [Z=1, K, M, N]
    earlier = collect_episodes(env, cands[1], num_episodes=2, num_steps=n, rewarded=True)
    flat = j_values(episodes, earlier, pi, psi, LAM, flattening=nu)
    per_trial = torch.tensor(nu, dtype=torch.float64)
    torch.testing.assert_close(
        j_values(episodes, earlier, pi, psi, LAM, flattening=per_trial), flat, rtol=1e-12, atol=0
    )
    d0 = cat_episodes([episodes[0, ki] for ki in range(k)] + [earlier.exclude(("next", "reward"))])
    design = build_design(d0, pi, psi, min_ess_fraction=0.0)
    x, w = design.x.numpy(), design.w.numpy()
    u = (x.T * w) @ x / x.shape[0]
    for ki in range(k):
        rows = np.r_[ki * m * n : (ki + 1) * m * n, k * m * n : x.shape[0]]
        xk, wk = x[rows], np.where(w[rows] > 0, w[rows] ** nu, 0.0)
        a = (xk.T * wk) @ xk / len(rows)
        big_l = np.linalg.solve(a + LAM * np.eye(12), xk.T * wk / len(rows))
        ref = np.trace(u @ big_l @ big_l.T)
        assert abs(flat[0, ki].item() - ref) <= 1e-8 * ref
