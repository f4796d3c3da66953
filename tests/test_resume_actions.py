"""A run resumed between buying an iteration's episodes and improving its policy.

Seen from outside: ``examples/torchrl_pipeline.py --resume`` of a run stopped after it had
committed iteration 3's rewarded episodes raised "LinearQPolicy was built without
action_spec=" in its greedy test: the resumed loop's first step was ``improve()``, before any
env had told the policies the action encoding (``GymEnv`` takes one-hot actions).
"""

from torchrl.envs import GymEnv, SerialEnv, StepCounter, TransformedEnv

from torch_api import RunSpec
from torch_api.core.quadratic_basis import QuadraticActionBasis
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration

STEPS = 20


def cartpole() -> TransformedEnv:
    return TransformedEnv(GymEnv("CartPole-v1"), StepCounter(max_steps=STEPS))


def rows(count: int) -> SerialEnv:
    return SerialEnv(count, cartpole)


def greedy_return(policy, seed: int) -> dict:
    """The user's test: the policy on a fresh one-hot GymEnv of its own."""
    env = cartpole()
    env.set_seed(seed)
    return {"test_return": env.rollout(STEPS, policy)["next", "reward"].sum().item()}


def test_a_run_resumed_before_its_improve_step_knows_the_actions(tmp_path):
    spec = RunSpec.of(schedule=(2, 2), num_steps=STEPS, gamma=0.95, mode="passive", seed=4)
    basis, path = QuadraticActionBasis(obs_dim=4, num_actions=2), tmp_path / "run.db"
    kwargs = dict(env=rows, basis=basis, evaluate=greedy_return)
    with ActivePolicyIteration(spec, durable=DurableRun(path), **kwargs) as api:
        api.buy()  # iteration 1's episodes committed; stopped before fit() and improve()
    with ActivePolicyIteration(spec, durable=DurableRun(path, resume=True), **kwargs) as api:
        assert api.iteration == 0
        api.run()
        assert [r.iteration for r in api.history] == [1, 2]
    with ActivePolicyIteration(spec, durable=DurableRun(tmp_path / "whole.db"), **kwargs) as api:
        api.run()  # the same run uninterrupted: the same numbers
        whole = [r.performance for r in api.history]
    with ActivePolicyIteration(spec, durable=DurableRun(path, resume=True), **kwargs) as api:
        assert [r.performance for r in api.history] == whole
