"""Linear-Q policies: probabilities, tie-breaking, sampling, TensorDict I/O."""

import pytest
import torch
from tensordict import TensorDict

from counter_rng import CounterStreams
from torch_api.core.basis import GaussianActionBasis
from torch_api.policies import (
    LinearQPolicy,
    TabularPolicy,
    epsilon_greedy_probs,
    greedy_actions,
    greedy_probs,
    sample_actions,
    softmax_probs,
)


def _basis():
    return GaussianActionBasis(centers=torch.tensor([[1.0], [5.0], [9.0]]), tau=1.5, num_actions=2)


def test_epsilon_greedy_probabilities():
    q = torch.tensor([[0.0, 1.0, 0.5]])
    probs = epsilon_greedy_probs(q, 0.3)
    torch.testing.assert_close(probs, torch.tensor([[0.1, 0.8, 0.1]], dtype=torch.float64))
    # ε is capped at 1: uniform
    torch.testing.assert_close(
        epsilon_greedy_probs(q, 1.7), torch.full((1, 3), 1 / 3, dtype=torch.float64)
    )
    with pytest.raises(ValueError, match="epsilon must be >= 0"):
        epsilon_greedy_probs(q, -0.1)


def test_greedy_actions_take_the_lowest_maximal_index():
    q = torch.tensor([[1.0, 1.0], [0.0, 2.0], [3.0, 3.0 + 1e-14]])
    assert greedy_actions(q).tolist() == [0, 1, 0]


def test_ties_split_the_greedy_mass_evenly():
    """Every action within the tolerance of the maximum gets an equal share of 1 - ε."""
    q = torch.tensor([[1.0, 1.0, 0.0], [0.0, 2.0, 2.0 + 1e-14], [5.0, 5.0, 5.0], [0.0, 1.0, 0.5]])
    expected_greedy = torch.tensor(
        [[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.0, 1.0, 0.0]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(greedy_probs(q), expected_greedy)
    eps = 0.3
    torch.testing.assert_close(epsilon_greedy_probs(q, eps), (1 - eps) * expected_greedy + eps / 3)
    # a gap above the tolerance is no tie
    assert greedy_probs(torch.tensor([1.0, 1.0 + 1e-6])).tolist() == [0.0, 1.0]


def test_lowest_index_rule_stays_available():
    q = torch.tensor([[1.0, 1.0, 0.0], [0.0, 2.0, 2.0], [0.0, 1.0, 0.5]])
    torch.testing.assert_close(
        epsilon_greedy_probs(q, 0.3, tie_break="lowest"),
        torch.tensor([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.8, 0.1]], dtype=torch.float64),
    )
    with pytest.raises(ValueError, match="tie_break must be one of"):
        epsilon_greedy_probs(q, 0.3, tie_break="random")
    with pytest.raises(ValueError, match="tie_break must be one of"):
        LinearQPolicy(basis=_basis(), theta=torch.ones(8), epsilon=0.1, tie_break="first")


@pytest.mark.parametrize("theta_value", [0.0, 1.0])
def test_theta_zero_or_one_gives_a_uniform_policy(theta_value):
    """θ = 0 (no reward seen) or θ_0 = 1 (pi_1, eq. 58/67): Q̂ ties for every action."""
    obs = torch.arange(1, 11, dtype=torch.float32).unsqueeze(-1)
    policy = LinearQPolicy(basis=_basis(), theta=torch.full((8,), theta_value), epsilon=0.15)
    uniform = torch.full((10, 2), 0.5, dtype=torch.float64)
    torch.testing.assert_close(policy.action_probs(obs), uniform)
    # the tie rule survives the copies the library makes of a policy
    for copy in (policy.with_rule(epsilon=0.0), policy.trial_slice(slice(None)).to_device("cpu")):
        torch.testing.assert_close(copy.action_probs(obs), uniform)


def test_initial_policy_with_lowest_index_ties_is_all_left():
    """With ``tie_break="lowest"`` θ = 1 sends the tie to action 0: pi_1 is 1 - ε/2 left."""
    policy = LinearQPolicy(
        basis=_basis(), theta=torch.ones(8), epsilon=0.15, tie_break="lowest"
    ).with_rule(epsilon=0.15)
    probs = policy.action_probs(torch.arange(1, 11, dtype=torch.float32).unsqueeze(-1))
    torch.testing.assert_close(probs[:, 0], torch.full((10,), 1 - 0.15 / 2, dtype=torch.float64))


def test_softmax():
    probs = softmax_probs(torch.tensor([0.0, 1.0]), beta=0.5)
    ratio = probs[1] / probs[0]
    assert ratio.item() == pytest.approx(torch.exp(torch.tensor(2.0)).item())
    with pytest.raises(ValueError, match="beta must be > 0"):
        softmax_probs(torch.tensor([0.0, 1.0]), beta=0.0)


def test_module_writes_action_and_probs_and_samples_them():
    policy = LinearQPolicy(
        basis=_basis(),
        theta=torch.linspace(-1, 1, 8),
        epsilon=0.4,
        one_hot=False,
        generator=torch.Generator().manual_seed(3),
    )
    obs = torch.full((20000, 1), 5.0)
    td = policy(TensorDict({"observation": obs}, batch_size=[20000]))
    probs = td["sample_probs"][0]
    freq = torch.bincount(td["action"], minlength=2).double() / 20000
    assert (freq - probs).abs().max().item() < 0.02  # 5 standard errors of a proportion


def test_same_generator_seed_same_actions_and_one_hot():
    def run(seed):
        policy = LinearQPolicy(
            basis=_basis(),
            theta=torch.zeros(8),
            epsilon=1.0,
            one_hot=True,
            generator=torch.Generator().manual_seed(seed),
        )
        return policy(TensorDict({"observation": torch.ones(50, 1)}, batch_size=[50]))["action"]

    assert torch.equal(run(1), run(1))
    assert not torch.equal(run(1), run(2))
    assert run(1).shape == (50, 2)


def test_trial_dimension_theta():
    theta = torch.stack(
        [torch.tensor([1.0, 0, 0, 0, -1, 0, 0, 0]), torch.tensor([-1.0, 0, 0, 0, 1, 0, 0, 0])]
    )
    policy = LinearQPolicy(basis=_basis(), theta=theta, epsilon=0.0)
    probs = policy.action_probs(torch.ones(2, 7, 1))  # [T, M, d]
    assert probs[0, :, 0].eq(1).all() and probs[1, :, 1].eq(1).all()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"theta": torch.ones(7)}, "theta must have shape"),
        ({"epsilon": None}, "give exactly one of epsilon"),
        ({"beta": 1.0}, "give exactly one of epsilon"),
        ({"theta": torch.full((8,), float("nan"))}, "NaN"),
    ],
)
def test_bad_construction(kwargs, message):
    args = {"basis": _basis(), "theta": torch.ones(8), "epsilon": 0.1} | kwargs
    with pytest.raises(ValueError, match=message):
        LinearQPolicy(**args)


def test_tabular_policy_and_trial_major_rows():
    table = torch.tensor([[[0.9, 0.1], [0.2, 0.8]], [[0.5, 0.5], [1.0, 0.0]]], dtype=torch.float64)
    policy = TabularPolicy(table=table, state_index=lambda obs: obs[..., 0].long())
    obs = torch.tensor([[0.0], [1.0], [1.0], [0.0]])  # rows of trial 0, then of trial 1
    expected = torch.tensor([[0.9, 0.1], [0.2, 0.8], [1.0, 0.0], [0.5, 0.5]], dtype=torch.float64)
    torch.testing.assert_close(policy.action_probs(obs), expected)
    with pytest.raises(ValueError, match="divisible by 2"):
        policy.action_probs(torch.zeros(3, 1))
    with pytest.raises(ValueError, match="rows must sum to 1"):
        TabularPolicy(table=torch.tensor([[0.5, 0.6]]), state_index=lambda obs: obs[..., 0].long())


def test_sample_actions_draws_from_the_streams_it_is_given():
    """One generator: the inverse CDF of its uniforms; counter-based streams, one per block of
    rows: block b's rows drawn from stream b alone, as if each block were sampled by itself,
    the inverse CDF of the documented uniforms."""
    probs = torch.tensor([[0.2, 0.8], [0.5, 0.5], [0.9, 0.1]] * 2, dtype=torch.float64)
    u = torch.rand(6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    expected = (u > probs[:, 0]).long()
    assert torch.equal(sample_actions(probs, torch.Generator().manual_seed(0)), expected)
    blocks = sample_actions(probs, CounterStreams([1, 2, 3]))
    alone = [
        sample_actions(probs[2 * b : 2 * b + 2], CounterStreams(s)) for b, s in enumerate((1, 2, 3))
    ]
    assert torch.equal(blocks, torch.cat(alone))
    u = CounterStreams([1, 2, 3]).uniform((6,))
    assert torch.equal(blocks, (u > probs[:, 0]).long())
    with pytest.raises(ValueError, match="6 rows do not split into 4 equal blocks"):
        sample_actions(probs, CounterStreams([1, 2, 3, 4]))
    with pytest.raises(ValueError, match="streams must be"):
        sample_actions(probs, 3)
    with pytest.raises(ValueError, match="pass counter_rng.CounterStreams"):
        sample_actions(probs, [torch.Generator() for _ in range(3)])


def test_streams_are_fixed_when_a_policy_is_made():
    """Nobody sets a policy's random streams from outside: ``with_streams`` gives a new policy
    (the original keeps its own), and the library's copies carry the streams along."""
    from envs.chain_walk import ChainWalkEnv

    theta = torch.stack([torch.linspace(-1, 1, 8), torch.linspace(1, -1, 8)])  # two trials
    policy = LinearQPolicy(basis=_basis(), theta=theta, epsilon=0.5, one_hot=False)
    with pytest.raises(AttributeError):
        policy.counter_streams = CounterStreams([1, 2])
    with pytest.raises(AttributeError):
        policy.generator = torch.Generator()
    streams = CounterStreams([1, 2])
    seeded = policy.with_streams(streams)
    assert policy.streams is None and seeded.counter_streams is streams
    seeded.to(torch.float32)  # a copy's registries are its own: the original keeps float64 θ
    assert policy.theta.dtype == torch.float64 and seeded.theta.dtype == torch.float32
    assert seeded.trial_slice(slice(1, 2)).counter_streams.keys.tolist() == [2]
    assert seeded.with_rule(epsilon=0.2).streams == seeded.to_device("cpu").streams
    with pytest.raises(ValueError, match="streams must be"):
        policy.with_streams([1, 2])

    def rollout(policy):  # as a TorchRL module in env.rollout
        env = ChainWalkEnv(batch_size=4, seed=0)
        return env.rollout(5, policy=policy, break_when_any_done=False)

    first = rollout(policy.with_streams(CounterStreams([1, 2])))
    again = rollout(policy.with_streams(CounterStreams([1, 2])))
    assert torch.equal(first["action"], again["action"])


@pytest.mark.parametrize(
    "spec",
    ["one-hot", "categorical [..., 1]", "index"],
)
def test_log_prob_of_the_actions_a_rollout_wrote(spec):
    """log pi(a|s) of the actions as the env holds them (GymEnv's one-hot int64, a Categorical
    spec with a trailing dim, a plain index) is the log of the probability they were drawn with."""
    from torchrl.data import Categorical, OneHot

    rows = 64
    action_spec = {
        "one-hot": OneHot(n=2, shape=(rows, 2), dtype=torch.int64),
        "categorical [..., 1]": Categorical(n=2, shape=(rows, 1)),
        "index": None,
    }[spec]
    policy = LinearQPolicy(
        basis=_basis(),
        theta=torch.linspace(-1, 1, 8),
        epsilon=0.3,
        action_spec=action_spec,
        one_hot=False if action_spec is None else None,
        generator=torch.Generator().manual_seed(5),
    )
    obs = torch.linspace(0, 10, rows).unsqueeze(-1)
    td = policy(TensorDict({"observation": obs}, batch_size=[rows]))
    if action_spec is not None:
        assert action_spec.is_in(td["action"])
    index = td["action"].argmax(-1) if spec == "one-hot" else td["action"].reshape(rows)
    drawn = td["sample_probs"].gather(-1, index.unsqueeze(-1)).squeeze(-1)
    log_prob = policy.log_prob(obs, td["action"])
    assert log_prob.shape == (rows,) and log_prob.dtype == torch.float64
    assert torch.equal(log_prob, drawn.log())
    assert len(set(index.tolist())) == 2  # both actions occur: the check covers both
