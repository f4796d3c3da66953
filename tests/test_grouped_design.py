"""torch_api/core/grouped_design.py: the finite-state moments from group sums equal the per-sample
ones (a dense reference: build_design's rows and weights summed sample by sample)."""

import pytest
import torch

from counter_rng import CounterStreams
from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.collection.collect import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.criterion import pooled_moments
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.core.solve import weighted_moment
from torch_api.policies import LinearQPolicy

T, Z, K, M, N = 3, 2, 4, 3, 10


def dense_moments(cand, prev, policy, psi):
    """A_k, C_k, Ũ of eq. 42-45 summed sample by sample over build_design's rows."""
    pool = [cand.reshape(T, Z, K * M, N)]
    if prev is not None:
        pool.append(prev.unsqueeze(1).expand(T, Z, *prev.shape[-2:]).clone())
    design = build_design(torch.cat(pool, -2), policy, psi, min_ess_fraction=0.0)
    split = K * M * N
    x, w, mask = design.x, design.w, design.mask
    own_x = x[..., :split, :].reshape(T, Z, K, M * N, -1)
    own_w = w[..., :split].reshape(T, Z, K, M * N)
    n_own = mask[..., :split].reshape(T, Z, K, M * N).sum(-1).double()
    a_sh = weighted_moment(x[..., split:, :], w[..., split:])
    c_sh = weighted_moment(x[..., split:, :], w[..., split:] ** 2)
    n_sh = mask[..., split:].sum(-1).double()
    n_k = (n_own + n_sh.unsqueeze(-1))[..., None, None]
    n_0 = (n_own.sum(-1) + n_sh)[..., None, None]
    a_own, c_own = weighted_moment(own_x, own_w), weighted_moment(own_x, own_w**2)
    u = (a_own.sum(-3) + a_sh) / n_0
    return (a_own + a_sh.unsqueeze(-3)) / n_k, (c_own + c_sh.unsqueeze(-3)) / n_k**2, u


def episodes(rows, seed, policy, rewarded=False):
    env = ChainWalkEnv(batch_size=T * rows, seed=seed)
    return collect_episodes(env, policy, num_episodes=rows, num_steps=N, rewarded=rewarded)


@pytest.mark.parametrize("earlier", [False, True])
def test_grouped_moments_equal_the_per_sample_sums(earlier):
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="grouped")
    theta = torch.randn(T, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    policy = LinearQPolicy(basis=basis, theta=theta, epsilon=0.3)
    sampler = LinearQPolicy(basis=basis, theta=theta.flip(0), epsilon=0.6)
    cand = episodes(Z * K * M, 1, sampler.with_streams(CounterStreams([1, 2, 3])))
    cand = cand.reshape(T, Z, K, M, N)
    prev = episodes(4, 2, sampler.with_streams(CounterStreams([4, 5, 6]))) if earlier else None
    if earlier:  # padding and an early end in the earlier sets: masked, terminated steps
        prev["mask"][:, 1, 7:] = False
        prev["next", "terminated"][:, 1, 6] = True
        prev["observation"][:, 1, 8:] = float("nan")  # padding may hold anything
    moments = pooled_moments(cand, prev, policy, psi)
    if earlier:
        prev["observation"][:, 1, 8:] = 1.0  # the dense reference needs finite padding
    a, c, u = dense_moments(cand, prev, policy, psi)
    torch.testing.assert_close(moments.a, a, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(moments.c, c, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(moments.u[..., 0, :, :], u, rtol=1e-12, atol=1e-14)
