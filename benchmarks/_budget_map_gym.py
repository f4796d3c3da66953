"""The reward-budget map's Gymnasium tasks (``benchmarks/reward_budget_map.py``): CartPole-v1
and Acrobot-v1 through :class:`~torch_api.loop.iteration.ActivePolicyIteration`.

As the library's showcase (``examples/torchrl_pipeline.py``) sets them: a Gymnasium env made
by TorchRL, observations normalised to unit scale (``ObservationNorm``; CartPole by its
physical scales, Acrobot by its observation box), a ``StepCounter`` ending an episode after N
steps, a quadratic Q̂ per action (:class:`QuadraticActionBasis`), LSTD-Q, λ = 10⁻³, ν = 0;
γ = 0.95 and N = 200 on CartPole, γ = 0.99 and N = 500 on Acrobot (the showcase's defaults for
``--env Acrobot-v1``). One difference, for cost: the rows are gymnasium's ``SyncVectorEnv``
wrapped by TorchRL's ``GymWrapper`` (one env of ``[rows]``), not ``GymEnv`` rows in a
``SerialEnv``: on this machine a ``SerialEnv`` row-step cost about 2.2 ms, the vector env's
about 75 µs (CartPole, 400 rows). Its rows are seeded per trial (``set_block_seeds``: row j
of trial block b from ``derive_key(seed_b, j)``), so trial t's episodes depend on its own seed
only, as on the chain walk and the batting arm.

The measure is the showcase's: the greedy policy of θ_L (ε = 0), tested on
``TEST_EPISODES`` episodes of at most ``TEST_STEPS`` steps per trial, the mean return. It is
measured after the last iteration only (the map reads l = L; the earlier iterations' tests
would cost more than their learning).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch
from torchrl.envs import Compose, GymWrapper, ObservationNorm, StepCounter, TransformedEnv

from counter_rng import derive_key, derive_keys
from torch_api import RunSpec
from torch_api.collection.collect import collect_episodes
from torch_api.core.quadratic_basis import QuadraticActionBasis
from torch_api.data import REWARD_KEY
from torch_api.streams import STREAMS, derive_seed

TEST_EPISODES = 5  # the showcase's greedy test: 5 episodes …
TEST_STEPS = 500  # … of at most 500 steps (both envs' own time limit)


@dataclass(frozen=True)
class GymTask:
    """A Gymnasium task of the map: its env, episode length N and the return of a solved policy."""

    env_id: str
    num_steps: int
    """N, longest rewarded and reward-free episode"""
    gamma: float
    """γ (the showcase's for the env)"""
    solved: float
    """a solved policy's test return: δ is a share of (solved − PL)"""
    solved_note: str


TASKS = {
    "cartpole": GymTask("CartPole-v1", 200, 0.95, 500.0, "every test step balanced (500)"),
    "acrobot": GymTask("Acrobot-v1", 500, 0.99, -100.0, "gymnasium's reward threshold (-100)"),
}
NU, LAM = 0.0, 1e-3  # the showcase's (examples/torchrl_pipeline.py), as γ and N above
CARTPOLE_SCALE = (2.4, 2.0, 0.21, 2.0)  # m, m/s, rad, rad/s (the showcase's)


class VectorGymEnv(TransformedEnv):
    """``rows`` Gymnasium envs in one ``SyncVectorEnv`` (TorchRL's ``GymWrapper``), observations
    normalised, at most ``max_steps`` steps an episode; per-trial streams (``BlockSeeded``)."""

    def set_block_seeds(self, seeds) -> None:
        """Row j of block b (``rows / len(seeds)`` rows each) from ``derive_key(seeds[b], j)``."""
        seeds = [int(s) for s in seeds]
        rows = self.batch_size[0]
        if rows % len(seeds):
            raise ValueError(f"{rows} rows do not split into {len(seeds)} equal blocks")
        per = rows // len(seeds)
        row_seeds = [derive_key(s, j) for s in seeds for j in range(per)]
        self.base_env._env.reset(seed=row_seeds)  # each row's generator; later resets go on


def make_env(task: str, rows: int, max_steps: int) -> VectorGymEnv:
    """``task``'s env of ``rows`` rows, observations to unit scale, ≤ ``max_steps`` steps."""
    env_id = TASKS[task].env_id
    same_step = gym.vector.AutoresetMode.SAME_STEP  # (the autoreset TorchRL's wrapper accepts)
    vector = gym.vector.SyncVectorEnv([lambda: gym.make(env_id)] * rows, autoreset_mode=same_step)
    base = GymWrapper(vector)
    if task == "cartpole":
        center, scale = torch.zeros(4), torch.tensor(CARTPOLE_SCALE)
    else:  # the observation box to [-1, 1] (Acrobot: cos, sin, angular speeds)
        box = base.observation_spec["observation"].space
        center, scale = (box.high[0] + box.low[0]) / 2, (box.high[0] - box.low[0]) / 2
    norm = ObservationNorm(loc=center, scale=scale, in_keys=["observation"], standard_normal=True)
    return VectorGymEnv(base, Compose(norm, StepCounter(max_steps=max_steps)))


def make_basis(task: str, rows: int = 1) -> QuadraticActionBasis:
    """A quadratic Q̂ per action on ``task``'s observations."""
    env = make_env(task, rows, 1)
    basis = QuadraticActionBasis(
        obs_dim=env.observation_spec["observation"].shape[-1],
        num_actions=env.action_spec.space.n,
    )
    env.close()
    return basis


def spec_of(task: str, common: dict) -> RunSpec:
    """The cell's settings on ``task`` (``common``: schedule, trials, Z, R, ν, …)."""
    g = TASKS[task]
    settings = dict(num_steps=g.num_steps, gamma=g.gamma, lam=LAM, fit="lstd", psi_mode="single")
    return RunSpec.of(**settings, **common)


def make_evaluator(task: str, trials: int, seed: int, iterations: int):
    """``evaluate(policy, seed)``: after iteration L, the greedy policy of θ_L per trial, its
    mean return over ``TEST_EPISODES`` test episodes; nothing after the earlier iterations
    (iteration l is known from its evaluation seed, ``derive_seed(seed, l, "evaluation")``).
    Trial t's test rows are seeded from the policy's stream of trial t, a role apart."""
    env = None
    last = derive_seed(seed, iterations, "evaluation")

    def evaluate(policy, eval_seed: int) -> dict:
        nonlocal env
        if eval_seed != last:
            return {}
        if env is None:
            env = make_env(task, trials * TEST_EPISODES, TEST_STEPS)
        keys = policy.counter_streams.keys
        env.set_block_seeds(derive_keys(keys, 0, STREAMS["evaluation"]).tolist())
        greedy = policy.with_rule(epsilon=0.0).with_streams(policy.counter_streams)
        td = collect_episodes(
            env, greedy, num_episodes=TEST_EPISODES, num_steps=TEST_STEPS, rewarded=True
        )
        returns = (td[REWARD_KEY] * td["mask"]).sum(-1).mean(-1)  # [T]
        return {"greedy_test_return": returns.tolist()}

    return evaluate


def run_chunk_gym(chunk, spec: RunSpec, ex) -> dict:
    """One chunk's run of a Gymnasium cell (``chunk.args``: the map's ``RunArgs``; ``spec``: its
    :func:`spec_of`; ``ex``: ``torch_api.experiment``)."""
    cell, trials = chunk.args.cell, len(chunk.trials)

    def env(rows: int) -> VectorGymEnv:
        return make_env(cell.task, rows, TASKS[cell.task].num_steps)

    evaluate = make_evaluator(cell.task, trials, chunk.seed, cell.iterations)
    basis = make_basis(cell.task)
    api = ex.make_iteration(chunk, spec, env=env, basis=basis, evaluate=evaluate)
    return ex.run_iterations(chunk, api)
