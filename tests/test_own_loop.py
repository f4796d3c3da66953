"""A user's own loop of Algorithm 1's steps (their Collector, their replay buffer) gives the θ of
``ActivePolicyIteration.run()`` on the same spec, seed and Collector (``examples/own_loop.py``)."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import own_loop  # noqa: E402

from torch_api import ActivePolicyIteration, SamplingPolicySelector  # noqa: E402


def test_the_steps_one_by_one_give_the_theta_of_run():
    mine = own_loop.own_loop()
    env, basis = own_loop.make_parts()
    api = ActivePolicyIteration(
        own_loop.SPEC,
        env=env,
        basis=basis,
        selector=SamplingPolicySelector(env=env),  # reward-free episodes from env, as own_loop's
        collector=lambda policy, m: own_loop.make_collector(env, policy, m),
    )
    api.run()
    assert api.mode == "active" and len(api.history) == len(own_loop.SCHEDULE)
    assert torch.equal(mine.theta, api.theta)  # bit for bit: the same episodes, same order
    # J' of every iteration too: fit(episodes) hands the user's episodes to the next choose()
    assert [r.row()["j_mean"] for r in mine.history] == [r.row()["j_mean"] for r in api.history]
    assert mine.rewarded_transitions == api.rewarded_transitions
