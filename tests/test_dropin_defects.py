"""Drop-in defects a TorchRL user hit (issue #46), each refused up front with one line."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import Categorical, MultiCategorical, MultiOneHot, OneHot
from torchrl.envs import GymEnv

from counter_rng import CounterStreams
from torch_api.collection.collect import collect_with_collector
from torch_api.core.basis import GaussianActionBasis
from torch_api.data.actions import ActionEncoding
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.policies import LinearQPolicy, sample_actions

NO_SUCH_GPU = "cuda:99" if torch.cuda.is_available() else "cuda"


# sample_actions


@pytest.mark.parametrize(
    ("probs", "message"),
    [
        ([[0.3, 0.3]], r"probs rows must sum to 1 .* sums from 0.6 to 0.6 \(1 of 1 rows off\)"),
        ([[0.5, 0.5], [0.7, 0.7]], r"sums from 1 to 1.4 \(1 of 2 rows off\)"),
        ([[1.2, -0.2]], r"probs must be finite and non-negative, got -0.2"),
        ([[float("nan"), 1.0]], r"probs must be finite and non-negative, got nan"),
        ([[float("inf"), 0.0]], r"probs must be finite and non-negative, got inf"),
    ],
)
def test_sample_actions_refuses_rows_that_are_not_distributions(probs, message):
    """Before: [0.3, 0.3] drew action 1 in 70 % of the draws, without a word."""
    probs = torch.tensor(probs, dtype=torch.float64)
    for streams in (None, torch.Generator().manual_seed(0), CounterStreams(0)):
        with pytest.raises(ValueError, match=message):
            sample_actions(probs, streams)


def test_sample_actions_accepts_rounded_distributions_and_draws_as_before():
    probs = torch.softmax(torch.randn(1000, 7, dtype=torch.float64), -1)
    probs32 = probs.float()  # float32 rows sum to 1 only within its rounding
    streams = CounterStreams(3)
    assert torch.equal(sample_actions(probs, streams), sample_actions(probs, CounterStreams(3)))
    sample_actions(probs32, CounterStreams(3))
    index = sample_actions(torch.tensor([[0.0, 1.0], [1.0, 0.0]]), CounterStreams(0))
    assert index.tolist() == [1, 0]
    assert sample_actions(torch.empty(0, 3), CounterStreams(0)).shape == (0,)


# the selector's device


def test_a_selector_on_a_missing_gpu_is_refused_when_made():
    """Before: accepted, and torch's AssertionError came from inside select()."""
    with pytest.raises(ValueError, match=f"device '{NO_SUCH_GPU}': torch sees"):
        SamplingPolicySelector(device=NO_SUCH_GPU)
    with pytest.raises(ValueError, match="device must name a torch device, got 'gpu'"):
        SamplingPolicySelector(device="gpu")
    assert SamplingPolicySelector(device="cpu").device == torch.device("cpu")


# a user's Collector without a step cap


def _uncapped_collector(counter: list):
    """CartPole as it comes: episodes last 10-60 steps under a near-uniform policy, no
    StepCounter; ``counter`` receives the number of batches drawn."""

    def make(policy, num_episodes):
        collector = Collector(
            GymEnv("CartPole-v1"),
            policy,
            frames_per_batch=40,
            total_frames=-1,
            auto_register_policy_transforms=False,
        )

        def batches():
            for batch in collector:
                counter.append(1)
                yield batch

        class Counted:
            env = collector.env

            def __iter__(self):
                return batches()

            def shutdown(self):
                collector.shutdown()

        return Counted()

    return make


def test_a_collector_without_a_step_cap_is_refused_at_its_first_batch():
    """Before: the collector ran until its whole (over-long) episodes were in, and only then
    were they refused; in the loop, after they were paid for."""
    torch.manual_seed(0)
    env = GymEnv("CartPole-v1")
    basis = GaussianActionBasis(centers=torch.zeros(1, 4), tau=1.0, num_actions=2)
    policy = LinearQPolicy(
        basis=basis, theta=torch.ones(4), epsilon=1.0, action_spec=env.action_spec
    )
    batches: list = []
    with pytest.raises(
        ValueError, match=r"episode of \d+ steps in its batch 1, more than num_steps = 5"
    ):
        collect_with_collector(
            _uncapped_collector(batches), policy, num_episodes=20, num_steps=5, rewarded=True
        )
    assert len(batches) == 1


# action specs


@pytest.mark.parametrize(
    "spec",
    [MultiCategorical(nvec=[2, 3]), MultiOneHot(nvec=[2, 3])],
    ids=["MultiCategorical", "MultiOneHot"],
)
def test_multi_discrete_action_specs_are_named_unsupported(spec):
    """Before: ``AttributeError: 'BoxList' object has no attribute 'n'``."""
    name = type(spec).__name__
    with pytest.raises(ValueError, match=rf"{name} action specs .* are not supported"):
        ActionEncoding.of_spec(spec)
    with pytest.raises(ValueError, match=rf"{name} action specs .* are not supported"):
        ActionEncoding.from_spec(spec)


def test_single_discrete_action_specs_still_read():
    assert ActionEncoding.of_spec(OneHot(n=3)).num_actions == 3
    assert ActionEncoding.of_spec(Categorical(n=4, shape=(1,))).trailing_dim
