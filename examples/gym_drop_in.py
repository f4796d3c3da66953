"""Active vs passive policy iteration on Gymnasium's CartPole-v1 through TorchRL (a drop-in demo).

Any TorchRL env with discrete actions works: here E CartPoles in one ``SyncVectorEnv``
(``autoreset_mode=DISABLED``: a terminal step keeps its true next state) wrapped by
``GymWrapper``, observations scaled to about ±1, Gaussian centres ``{-g, g}^4`` ∪ {0}. An
episode ends early when the pole falls: the library masks its later steps (``check_episodes``).
Each pi_{l+1} is tested (mean steps the pole stays up, ε-greedy and greedy); AL and PL run on
the same seeds, with the paired t-test of the last iteration.

    python examples/gym_drop_in.py [--reward-free-workers 2]

Writes ``gym_drop_in.csv`` (every number), ``gym_drop_in.json`` and ``performance.png`` into
``--out-dir``; the runs are stored as they go in ``checkpoints/`` (``--resume`` continues them).
"""

import itertools
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import tyro
from torchrl.envs import GymWrapper, ObservationNorm, TransformedEnv

import torch_api.experiment as ex
from torch_api import GaussianActionBasis, LinearQPolicy, RunSpec, SamplingPolicySelector
from torch_api.collection import collect_episodes
from torch_api.data import REWARD_KEY
from torch_api.streams import CounterStreams, derive_keys


@dataclass
class Args:
    """Command-line arguments of the CartPole drop-in demo."""

    trials: int = 8
    """T, independent trials, all run as one batch (a paired t-test needs two)"""
    seed: int = 0
    """master seed; AL and PL share their seeds (a paired design)"""
    schedule: tuple[int, ...] = (10, 10, 6, 6, 6, 2, 2)
    """M_l, rewarded episodes bought in iteration l (its length is L)"""
    steps: int = 25
    """N, steps per episode (an episode may end earlier when the pole falls)"""
    gamma: float = 0.95
    """discount γ, in (0, 1]"""
    lam: float = 1e-3
    """λ, ridge regularisation"""
    repeats: int = 5
    """Z, J-values averaged into J'"""
    grid: float = 0.5
    """Gaussian centres at ±grid in every normalised coordinate (2^4 = 16) plus the origin"""
    tau: float = 0.75
    """Gaussian kernel width τ in normalised units"""
    test_episodes: int = 20
    """test episodes per trial and iteration"""
    test_steps: int = 200
    """longest test episode (steps)"""
    reward_free_workers: int = 0
    """if > 0, collect the reward-free episodes in this many worker processes"""
    execution: tyro.conf.OmitArgPrefixes[ex.Execution] = ex.Execution("results/gym_drop_in")
    """where the runs go and where the files are written"""


ENV_ID = "CartPole-v1"
OBS_SCALE = (2.4, 2.0, 0.21, 2.0)  # (m, m/s, rad, rad/s): normalised observation = s / scale
X_LIMIT, ANGLE_LIMIT = 2.4, 12 * 2 * math.pi / 360  # CartPole's termination limits (m, rad)
MEASURES = {"steps_balanced": "steps balanced, ε-greedy", "steps_balanced_greedy": "greedy"}


def spec_of(args: Args) -> RunSpec:
    """The runs' settings (a ValueError names a bad one)."""
    least = {"trials": 2, "test_episodes": 1, "test_steps": 1, "reward_free_workers": 0}
    for name, low in least.items():  # (a paired t-test needs two trials)
        if getattr(args, name) < low:
            raise ValueError(f"{name} must be >= {low}, got {getattr(args, name)}")
    args.execution.check_chunks(args.trials)
    make_basis(args)  # (checks grid and tau)
    flat = dict(schedule=args.schedule, num_steps=args.steps, gamma=args.gamma, lam=args.lam)
    return RunSpec.of(
        **flat, psi_mode="single", num_repeats=args.repeats, seed=args.seed, keep_reward_free=False
    )


def make_env(batch: int) -> TransformedEnv:
    """E = ``batch`` CartPoles as one TorchRL env ``[E]`` with normalised observations."""
    vector = gym.vector.SyncVectorEnv(
        [lambda: gym.make(ENV_ID)] * batch, autoreset_mode=gym.vector.AutoresetMode.DISABLED
    )
    env = GymWrapper(vector, categorical_action_encoding=True)
    scale = torch.tensor(OBS_SCALE)
    norm = ObservationNorm(torch.zeros(4), scale, in_keys=["observation"], standard_normal=True)
    return TransformedEnv(env, norm)  # standard_normal: (s - loc) / scale


def make_basis(args: Args) -> GaussianActionBasis:
    corners = torch.tensor(list(itertools.product((-args.grid, args.grid), repeat=4)))
    centers = torch.cat([corners, torch.zeros(1, 4)])  # [17, 4]
    return GaussianActionBasis(centers=centers, tau=args.tau, num_actions=2)


def check_episodes(episodes) -> dict:
    """Check bought episodes ``[T, M, N]``: every mask stops at the episode's first terminal
    step, whose next state lies outside the task's limits (not a reset one); a summary."""
    mask, terminated = episodes["mask"], episodes["next", "terminated"]
    first_end = torch.where(terminated.any(-1), terminated.long().argmax(-1), mask.shape[-1] - 1)
    if not torch.equal(mask, torch.arange(mask.shape[-1]) <= first_end.unsqueeze(-1)):
        raise ValueError("the mask does not end at the first terminal step of every episode")
    raw = episodes["next", "observation"][terminated & mask] * torch.tensor(OBS_SCALE)
    inside = (raw[:, 0].abs() <= X_LIMIT) & (raw[:, 2].abs() <= ANGLE_LIMIT)
    if inside.any():
        raise ValueError(f"{int(inside.sum())} terminal next states lie inside CartPole's limits")
    return {
        "episodes": int(math.prod(mask.shape[:-1])),
        "transitions": int(mask.sum()),
        "share_ended_early": float(terminated.any(-1).double().mean()),
        "mean_length": float(mask.sum(-1).double().mean()),
        "rewards_in_masked_steps": float(episodes[REWARD_KEY][mask].sum()),
    }


def make_evaluator(args: Args):
    """``(policy, seed) -> measures`` of pi_{l+1}: mean steps balanced, ε-greedy and greedy.
    Test row r is seeded ``seed + r`` and the test policies draw from streams derived from
    each trial's, so trial t's numbers do not depend on the trials beside it."""
    m, n = args.test_episodes, args.test_steps
    env = make_env(args.trials * m)

    def balanced(policy: LinearQPolicy, epsilon, role: int) -> list[float]:
        keys = derive_keys(policy.counter_streams.keys, role)
        tester = policy.with_rule(epsilon=epsilon).with_streams(CounterStreams(keys))
        episodes = collect_episodes(env, tester, num_episodes=m, num_steps=n, rewarded=True)
        return (episodes[REWARD_KEY] * episodes["mask"]).sum(-1).double().mean(-1).tolist()

    def evaluate(policy: LinearQPolicy, seed: int | None = None) -> dict:
        if seed is not None:  # the same test noise for AL and PL at iteration l
            env.set_seed(int(seed))
        eps, greedy = balanced(policy, policy.epsilon, 1), balanced(policy, 0.0, 2)  # roles 1, 2
        return {"steps_balanced": eps, "steps_balanced_greedy": greedy}

    return evaluate


def run_chunk(chunk: ex.Chunk) -> dict:
    """One batched run of Algorithm 1 (a chunk of trials), stored as it goes, its data checked."""
    args = chunk.args
    evaluate, workers = make_evaluator(args), args.reward_free_workers
    selector = SamplingPolicySelector(env=make_env, num_workers=workers) if workers else None
    objects = dict(env=make_env, basis=make_basis(args), evaluate=evaluate, selector=selector)
    api = ex.make_iteration(chunk, spec_of(args), **objects)
    first = api.initial_policy().with_streams(CounterStreams(api.block_seeds(0, "evaluation")))
    run = ex.run_iterations(chunk, api, initial=evaluate(first, args.seed + 1))  # pi_1: l = 0
    return run | {"data_check": check_episodes(api.rewarded.episodes())}


def report(args: Args, experiment: ex.Experiment, results: dict, wall: float) -> dict:
    """The tables and the files (CSV, JSON, figure) of the finished experiment."""
    print(f"\n{ENV_ID}: {args.trials} trials, mean ± s.e. over trials ({wall:.1f} s)")
    title = f"steps balanced (of {args.test_steps}) by pi_(l+1), its ε-greedy rule"
    ex.print_curves(results, "steps_balanced", title, digits=1)
    ex.print_curves(results, "steps_balanced_greedy", "the same, greedy", digits=1)
    for method, run in results["custom"]["runs"].items():
        chosen = [np.bincount(it["chosen"], minlength=4).tolist() for it in run["iterations"][1:]]
        print(f"{method}: candidates chosen per iteration (counts of k = 1..4): {chosen}")
        print(f"{method}: bought data {run['data_check']}")
    ex.print_t_tests(results, args.trials)
    payload = ex.write_results(args.execution, args, experiment, results, wall)
    out = Path(args.execution.out_dir)
    ex.plot_paired(results, out / "performance.png", MEASURES, floor=0.0, title=ENV_ID)
    print(f"wrote {out}/gym_drop_in.json, gym_drop_in.csv and performance.png")
    return payload


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    try:
        spec_of(args)
        Path(args.execution.out_dir).mkdir(parents=True, exist_ok=True)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    experiment = ex.Experiment(
        name="gym_drop_in",
        schedules={"custom": args.schedule},
        run_chunk=run_chunk,
        t_tests=("steps_balanced",),
        report=lambda results, wall: report(args, experiment, results, wall),
        store_stem="{mode}",
        curves=tuple(MEASURES),
        files=("performance.png",),
        trials=args.trials,
        seed=args.seed,
    )
    return ex.run_experiment(experiment, args.execution, args)


if __name__ == "__main__":
    main()
