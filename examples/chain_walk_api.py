"""Active vs passive policy iteration on the 10-state chain walk (paper section 4.2, Figure 8).

For each schedule of rewarded episodes, 'decreasing' M = (5, 5, 3, 3, 3, 1, 1) and 'fixed'
M = (3,) * 7 with N = 10 steps, Algorithm 1 runs twice on the same seeds (a paired design):
AL (the sampling policy chosen by J', Z = 5) and PL (the evaluation policy samples), all trials
of a run in one batch. After every iteration pi_{l+1} is measured by ``test_return`` (eq. 61:
50 test episodes of 50 steps), ``exact_return`` (its exact expectation) and ``percent_optimal``;
iteration 0 is pi_1. A paired t-test compares AL and PL at the last iteration. Trial t's random
streams come from (its seed, iteration, role) alone, so ``--chunks`` and ``--backend`` change
no number. Runs are stored as they go; ``--resume`` buys only what is missing. Writes
chain_walk_api.csv (every number), chain_walk_api.json and fig8_performance.png.

    python examples/chain_walk_api.py --trials 1000 --backend ray --chunks 64 --ray-address auto
"""

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

from counter_rng import derive_keys
from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from envs.chain_walk.exact import expected_discounted_return
from envs.chain_walk.model import GAMMA, N_ACTIONS, chain_walk_model, optimal_policy
from torch_api import GaussianActionBasis, LinearQPolicy, RunSpec, SamplingPolicySelector
from torch_api.experiment import (
    Chunk,
    Execution,
    Experiment,
    checked_device,
    derived_seed,
    make_iteration,
    plot_paired,
    print_curves,
    print_t_tests,
    run_experiment,
    run_iterations,
    write_results,
)

SCHEDULES = {"decreasing": (5, 5, 3, 3, 3, 1, 1), "fixed": (3, 3, 3, 3, 3, 3, 3)}  # section 4.2
ROLE_REWARDED, ROLE_REWARD_FREE, ROLE_TEST = 1, 2, 3  # the environments' seed streams


@dataclass
class Args:
    """Figure 8: active vs passive policy iteration on the chain walk."""

    trials: int = 1000
    """independent trials, all run as one batch (the paper: 1000; a paired t-test needs two)"""
    seed: int = 0
    """master seed; AL and PL of a schedule share their seeds (a paired design)"""
    repeats: int = 5
    """Z, J-values averaged into J'"""
    lam: float = 1e-3
    """λ, ridge regularisation"""
    schedule: Literal["decreasing", "fixed", "both"] = "both"
    """rewarded-episode schedule: decreasing (5,5,3,3,3,1,1), fixed (3 x 7) or both"""
    iterations: int = 7
    """L, iterations run (the schedules' first L entries; 7 in the paper)"""
    steps: int = 10
    """N, steps per rewarded episode"""
    test_episodes: int = 50
    """test episodes per trial for the performance estimate (eq. 61)"""
    test_steps: int = 50
    """steps per test episode (and the horizon of the exact value)"""
    tie_break: Literal["uniform", "lowest"] = "uniform"
    """how ε-greedy shares the greedy mass among tied actions (uniform: pi_1 is uniform)"""
    device: str = "cpu"
    """where the chain walks, the rollouts and the algebra run (cpu, cuda or cuda:N)"""
    execution: Annotated[Execution, tyro.conf.OmitArgPrefixes] = field(
        default_factory=lambda: Execution(out_dir="results/chain_walk_api", backend="processes")
    )
    """where the runs go and where the files are written"""


def run_spec(args: Args, schedule: tuple[int, ...], seed: int) -> RunSpec:
    """The settings of one run (AL; PL leaves out the selection), checked when made."""
    return RunSpec.of(
        schedule=schedule, num_steps=args.steps, gamma=GAMMA, lam=args.lam, psi_mode="grouped",
        num_repeats=args.repeats, tie_break=args.tie_break, seed=seed, keep_reward_free=False,
    )  # fmt: skip


def env_factory(run_seed: int, role: int, device: str):
    """``batch_size -> ChainWalkEnv`` with a seed of its own per role and batch size."""
    return lambda n: ChainWalkEnv(batch_size=n, seed=derived_seed(run_seed, role, n), device=device)


def optimal_return(horizon: int) -> float:
    """The exact expected discounted return of the optimal deterministic policy."""
    model = chain_walk_model()
    best, _ = optimal_policy(model.transitions, model.expected_reward, GAMMA)
    probs = torch.nn.functional.one_hot(best, N_ACTIONS).to(torch.float64)
    terms = model.transitions, model.expected_reward, probs, model.initial, GAMMA, horizon
    return float(expected_discounted_return(*terms))


def make_evaluator(args: Args, trials: int):
    """``evaluate(policy, seed)``: eq. 61 and the exact return of pi_{l+1}, per trial. The test
    env's rows of trial t are seeded from the policy's stream of trial t, a role apart."""
    m, n, model = args.test_episodes, args.test_steps, chain_walk_model()
    env = ChainWalkEnv(batch_size=trials * m, seed=0, device=args.device)  # re-seeded every use
    optimum = optimal_return(n)
    states = torch.arange(1, model.n_states + 1, dtype=torch.float64).unsqueeze(-1)

    def evaluate(policy: LinearQPolicy, seed: int | None = None) -> dict:
        env.set_block_seeds(derive_keys(policy.counter_streams.keys, ROLE_TEST))
        table = policy.action_probs(states.expand(trials, *states.shape))  # [T, S, A]
        _, reward = env.walk_tabulated(table, n)  # [n, T·m]: the law of a rollout's rewards
        discounted = torch.zeros(trials * m, dtype=torch.float64, device=env.device)
        for step, r in enumerate(reward):  # step by step: each row's sum in one order
            discounted += GAMMA**step * r.to(torch.float64)
        terms = model.transitions, model.expected_reward, table, model.initial, GAMMA, n
        exact = expected_discounted_return(*terms)  # [T]
        measures = {"test_return": discounted.reshape(trials, m).mean(-1), "exact_return": exact}
        measures["percent_optimal"] = 100.0 * exact / optimum
        return {key: value.tolist() for key, value in measures.items()}

    return evaluate


def run_chunk(chunk: Chunk) -> dict:
    """One batched run of Algorithm 1 on a chunk of trials: per-iteration, per-trial records."""
    args, seed, device = chunk.args, chunk.seed, chunk.args.device
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2)
    evaluate = make_evaluator(args, len(chunk.trials))
    api = make_iteration(
        chunk,
        run_spec(args, chunk.schedule, seed),
        env=env_factory(seed, ROLE_REWARDED, device),
        selector=SamplingPolicySelector(env=env_factory(seed, ROLE_REWARD_FREE, device)),
        basis=basis,
        evaluate=evaluate,
        device=device,
    )
    first = api.initial_policy().with_streams(api.streams.sampling(0, "evaluation"))
    return run_iterations(chunk, api, initial=evaluate(first))  # pi_1 is iteration 0


def report(args: Args, experiment: Experiment, results: dict, wall: float) -> dict:
    """The tables and the files (JSON, CSV, Figure 8) of a finished experiment."""
    print(f"\nIterated chain walk: {args.trials} trials, mean ± s.e. over trials ({wall:.1f} s)")
    test = f"{args.test_episodes} test episodes of {args.test_steps} steps"
    print_curves(results, "test_return", f"performance of pi_{{l+1}}, eq. 61 ({test})")
    print_curves(results, "percent_optimal", "exact return of pi_{l+1}, % of optimal", digits=2)
    print_t_tests(results, args.trials)
    best, out = optimal_return(args.test_steps), args.execution.out_dir
    extra = {"optimal_exact_return": best}
    payload = write_results(args.execution, args, experiment, results, wall, **extra)
    measures = {"test_return": "eq. 61: discounted return", "percent_optimal": "% of optimal"}
    lines = {"test_return": {"optimal policy": best}, "percent_optimal": {"optimal policy": 100}}
    title = f"Figure 8, chain walk ({test}; iteration 0: pi_1):"
    plot_paired(results, Path(out) / "fig8_performance.png", measures, lines=lines, title=title)
    print(f"wrote {out}/chain_walk_api.json, chain_walk_api.csv and fig8_performance.png")
    return payload


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    names = list(SCHEDULES) if args.schedule == "both" else [args.schedule]
    seeds = {name: 1000 * args.seed + 100 * list(SCHEDULES).index(name) for name in names}
    schedules = {name: SCHEDULES[name][: args.iterations] for name in names}
    limits = {"trials": (2, math.inf), "seed": (0, math.inf), "iterations": (1, 7)}
    limits |= {"test_episodes": (1, math.inf), "test_steps": (1, math.inf)}
    try:  # every setting checked before any work: one line, exit 2
        for name, (low, high) in limits.items():
            if not low <= getattr(args, name) <= high:
                raise ValueError(f"{name} must lie in [{low}, {high}], got {getattr(args, name)}")
        for name in names:
            run_spec(args, schedules[name], seeds[name])  # (RunSpec checks its settings)
        args.execution.check_chunks(args.trials)
        checked_device(args.device)
        Path(args.execution.out_dir).mkdir(parents=True, exist_ok=True)
    except (ValueError, RuntimeError, OSError) as error:  # (a bad device: RuntimeError)
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    experiment = Experiment(
        name="chain_walk_api",
        schedules=schedules,
        run_chunk=run_chunk,
        t_tests=("test_return", "exact_return"),
        report=lambda results, wall: report(args, experiment, results, wall),
        run_seed=lambda seed, name: seeds[name],
        curves=("test_return", "exact_return", "percent_optimal", "rewarded_transitions"),
        files=("fig8_performance.png",),
        trials=args.trials,
        seed=args.seed,
    )
    return run_experiment(experiment, args.execution, args)


if __name__ == "__main__":
    main()
