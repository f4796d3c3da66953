"""Episode collection, validation and buffers."""

import pytest
import torch
from tensordict import TensorDict

from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.collection import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.data import EpisodeBuffer, cat_episodes, validate_episodes
from torch_api.policies import LinearQPolicy


def _policy(seed=0, one_hot=False):
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    return LinearQPolicy(
        basis=basis,
        theta=torch.ones(12),
        epsilon=0.3,
        one_hot=one_hot,
        generator=torch.Generator().manual_seed(seed),
    )


def test_collect_shapes_tags_and_reward_free_has_no_reward():
    env = ChainWalkEnv(batch_size=4, seed=0)
    eps = collect_episodes(
        env, _policy(), num_episodes=10, num_steps=7, rewarded=True, iteration=3, policy_id=2
    )
    assert eps.shape == (10, 7)
    assert eps["observation"].shape == (10, 7, 1) and eps["sample_probs"].shape == (10, 7, 2)
    assert eps["mask"].all() and (eps["iteration"] == 3).all() and (eps["policy_id"] == 2).all()
    # transitions chain: s'_n = s_{n+1}
    assert torch.equal(eps["next", "observation"][:, :-1], eps["observation"][:, 1:])
    free = collect_episodes(env, _policy(), num_episodes=3, num_steps=7, rewarded=False)
    assert ("next", "reward") not in free.keys(include_nested=True)


def test_one_hot_actions_are_stored_as_indices():
    env = ChainWalkEnv(batch_size=1, seed=0)
    eps = collect_episodes(env, _policy(one_hot=True), num_episodes=3, num_steps=5, rewarded=True)
    assert eps.shape == (3, 5) and eps["action"].dtype == torch.long


def test_reward_free_collection_ignores_nan_rewards():
    class NaNRewardChain(ChainWalkEnv):
        def _step(self, td):
            out = super()._step(td)
            out["reward"] = torch.full_like(out["reward"], float("nan"))
            return out

    free = collect_episodes(
        NaNRewardChain(batch_size=4, seed=0), _policy(), num_episodes=4, num_steps=5, rewarded=False
    )
    assert ("next", "reward") not in free.keys(include_nested=True)
    with pytest.raises(ValueError, match="rewards must be finite, got nan"):
        collect_episodes(
            NaNRewardChain(batch_size=4, seed=0),
            _policy(),
            num_episodes=4,
            num_steps=5,
            rewarded=True,
        )


def _good(m=2, n=3):
    return TensorDict(
        {
            "observation": torch.ones(m, n, 1),
            "action": torch.zeros(m, n, dtype=torch.long),
            "sample_probs": torch.full((m, n, 2), 0.5, dtype=torch.float64),
            ("next", "observation"): torch.ones(m, n, 1),
            ("next", "terminated"): torch.zeros(m, n, dtype=torch.bool),
            ("next", "reward"): torch.zeros(m, n),
            "mask": torch.ones(m, n, dtype=torch.bool),
        },
        batch_size=[m, n],
    )


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda td: td.set("observation", torch.full((2, 3, 1), float("inf"))),
            "observation.*NaN or inf",
        ),
        (
            lambda td: td.set(("next", "reward"), torch.full((2, 3), float("nan"))),
            "rewards must be finite",
        ),
        (
            lambda td: td.set("sample_probs", torch.full((2, 3, 2), 0.4, dtype=torch.float64)),
            "summing to 1",
        ),
        (
            lambda td: td.set(
                "sample_probs",
                torch.tensor([1.0, 0.0], dtype=torch.float64).expand(2, 3, 2).clone(),
            ).set("action", torch.ones(2, 3, dtype=torch.long)),
            "probability 0",
        ),
        (lambda td: td.exclude("mask"), "lack the key 'mask'"),
        (
            lambda td: td.set("action", torch.full((2, 3), 5)),
            r"action indices must lie in \[0, 2\)",
        ),
    ],
)
def test_validation_errors(edit, message):
    with pytest.raises(ValueError, match=message):
        validate_episodes(edit(_good()), rewarded=True)


def test_reward_presence_must_match_the_buffer():
    with pytest.raises(ValueError, match="must not carry"):
        validate_episodes(_good(), rewarded=False)
    with pytest.raises(ValueError, match="lack \\('next', 'reward'\\)"):
        validate_episodes(_good().exclude(("next", "reward")), rewarded=True)


def test_buffer_order_capacity_and_mismatch():
    buf = EpisodeBuffer(rewarded=True, capacity=5)
    with pytest.raises(ValueError, match="empty"):
        buf.episodes()
    a, b = _good(2), _good(2)
    b["observation"] += 1
    buf.extend(a)
    buf.extend(b)
    assert len(buf) == 4 and buf.num_transitions == 12
    assert torch.equal(buf.episodes()["observation"][2:], b["observation"])
    with pytest.raises(ValueError, match="capacity 5 episodes would be exceeded"):
        buf.extend(_good(2))
    buf.extend(_good(1, 4))  # a longer episode: everything held is padded to N = 4, masked
    held = buf.episodes()
    assert held.shape == (5, 4) and buf.num_transitions == 16
    assert not held["mask"][:4, 3].any() and held["mask"][4].all()
    with pytest.raises(ValueError, match="must not carry"):
        EpisodeBuffer(rewarded=False).extend(_good())


def test_cat_episodes():
    assert cat_episodes([_good(2), _good(3)]).shape == (5, 3)
    joined = cat_episodes([_good(2, 3), _good(2, 4)])  # padded to the longest, masked
    assert joined.shape == (4, 4) and int(joined["mask"].sum()) == 14
