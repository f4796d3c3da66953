"""Algorithm 1 step by step in a user's own TorchRL loop: their Collector, their replay buffer.

``run()`` of :class:`~torch_api.ActivePolicyIteration` does the same steps; given the same
spec, seed and Collector it ends with the same θ (``tests/test_own_loop.py``).

    python examples/own_loop.py
"""

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import GymEnv, StepCounter, TransformedEnv

from torch_api import ActivePolicyIteration, GaussianActionBasis, RunSpec

N, SCHEDULE = 15, (4, 2, 2)  # steps per episode; rewarded episodes M_l of each iteration
SPEC = RunSpec.of(schedule=SCHEDULE, num_steps=N, gamma=0.95, num_repeats=2, reward_free_episodes=2)


def make_parts():
    """The env (CartPole, episodes of at most N steps) and a basis with 16 Gaussian centres."""
    env = TransformedEnv(GymEnv("CartPole-v1"), StepCounter(max_steps=N))
    centers = torch.cartesian_prod(*[torch.tensor([-0.5, 0.5])] * 4)  # [16, 4]
    return env, GaussianActionBasis(centers=centers, tau=1.0, num_actions=2)


def make_collector(env, policy, m: int) -> Collector:
    """The user's Collector: M whole episodes a batch, padded to N steps."""
    return Collector(env, policy, frames_per_batch=m * N, total_frames=-1, trajs_per_batch=m,
                     traj_format="padded", auto_register_policy_transforms=False)  # fmt: skip


def own_loop() -> ActivePolicyIteration:
    env, basis = make_parts()
    api = ActivePolicyIteration(SPEC, env=env, basis=basis)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(sum(SCHEDULE), ndim=1))
    for m in SCHEDULE:
        api.choose()  # 1. the sampling policy, J'-chosen from reward-free episodes
        collector = make_collector(env, api.sampling_policy(), m)
        buffer.extend(next(iter(collector)))  # 2. M_l rewarded episodes, the user's buffer
        collector.shutdown()
        api.fit(buffer[:])  # 3. θ_l on every rewarded episode so far
        api.improve()  # 4. pi_{l+1}
    return api  # θ_L: api.theta; each iteration's record: api.history


if __name__ == "__main__":
    print("θ after", len(SCHEDULE), "iterations:", own_loop().theta)
