"""Episodes bought through a user's ``Collector`` are the sampling policy's episodes, not the
shortest of them.

A ``Collector`` yields trajectories as they end, polling its rows ``frames_per_batch`` frames
at a time. The loop kept the first M episodes to *end*: with the README's ``frames_per_batch =
M·N`` every row's first episode has ended by the first yield (the episodes are the policy's),
but polling fewer frames (one step a row, say) a row whose episodes end early ends several
before a row whose episode lasts ends one, and short episodes crowd out the long ones: 86 %
(whole trajectories) and 80 % (flat batches) short here instead of half. The loop now keeps the
M that *started* first (TorchRL numbers trajectories as they start).
"""

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.data import Composite, OneHot, Unbounded
from torchrl.envs import EnvBase, SerialEnv

from torch_api.collection.collect import collect_with_collector

SHORT, LONG = 4, 24  # an episode's length, a fair coin at its reset


class CoinLength(EnvBase):
    """Episodes of SHORT or LONG steps (a coin at reset); the observation is the length."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_spec = Composite(observation=Unbounded(shape=(1,)))
        self.action_spec = OneHot(2)
        self.reward_spec = Unbounded(shape=(1,))
        # (a stream of its own: a Collector restarts a closed SerialEnv, making its rows anew)
        self.generator = torch.Generator().manual_seed(int(torch.randint(2**31, ())))
        self.length = self.t = 0

    def _reset(self, tensordict):
        coin = torch.rand((), generator=self.generator) < 0.5
        self.length, self.t = SHORT if coin else LONG, 0
        return TensorDict({"observation": torch.tensor([float(self.length)])}, [])

    def _step(self, tensordict):
        self.t += 1
        done = torch.tensor([self.t >= self.length])
        observation = torch.tensor([float(self.length)])
        return TensorDict(
            {
                "observation": observation,
                "reward": torch.zeros(1),
                "done": done,
                "terminated": done,
            },
            [],
        )

    def _set_seed(self, seed):
        self.generator.manual_seed(seed)


def push_left(observation: torch.Tensor):
    """Always action 0 (one-hot, the spec's dtype), with its log-probability 0."""
    action = torch.zeros(*observation.shape[:-1], 2, dtype=torch.bool)
    action[..., 0] = True
    return action, torch.zeros(observation.shape[:-1])


@pytest.mark.parametrize("whole", [True, False])  # whole trajectories; flat batches
def test_the_episodes_kept_are_not_the_first_to_end(whole):
    """M = 4 rows, 4 episodes a purchase, the Collector polling one step a row: half of the
    episodes short. (The README's ``frames_per_batch = M·N`` gave the policy's episodes before.)"""
    torch.manual_seed(0)
    rows, policy = (
        SerialEnv(4, CoinLength),
        TensorDictModule(push_left, ["observation"], ["action", "sample_log_prob"]),
    )
    rows.set_seed(1)

    def collector(policy, m: int) -> Collector:
        trajectories = dict(trajs_per_batch=m, traj_format="padded") if whole else {}
        return Collector(rows, policy, frames_per_batch=m, total_frames=-1,
                         auto_register_policy_transforms=False, **trajectories)  # fmt: skip

    lengths = []
    for _ in range(30):
        episodes = collect_with_collector(
            collector, policy, num_episodes=4, num_steps=LONG, rewarded=True, validate=False
        )
        lengths += episodes["mask"].sum(-1).tolist()
    assert set(lengths) <= {SHORT, LONG}
    short = np.mean(np.array(lengths) == SHORT)  # 120 fair coins: 0.5 ± 0.046
    assert 0.35 < short < 0.65, f"{short:.2f} of the kept episodes are short"


def test_a_collector_used_before_is_refused():
    """Its trajectories are numbered from where it stopped: which started first is unknown."""
    rows = SerialEnv(2, CoinLength)
    policy = TensorDictModule(push_left, ["observation"], ["action", "sample_log_prob"])
    used = Collector(rows, policy, frames_per_batch=2 * LONG, total_frames=-1, trajs_per_batch=2,
                     traj_format="padded", auto_register_policy_transforms=False)  # fmt: skip
    for _ in zip(range(3), used, strict=False):  # six trajectories yielded already
        pass
    with pytest.raises(ValueError, match="numbered from [0-9]+, not 0: it was used before"):
        collect_with_collector(lambda p, m: used, policy, num_episodes=2, num_steps=LONG,
                               rewarded=True, validate=False)  # fmt: skip
