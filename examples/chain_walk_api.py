"""Active vs passive policy iteration on the 10-state chain walk (paper section 4.2, Figure 8).

For each schedule of rewarded episodes — 'decreasing' M = (5, 5, 3, 3, 3, 1, 1) and 'fixed' M =
(3,) * 7, N = 10 steps each — it runs Algorithm 1 twice on the same seeds (paired design): AL (a
``SamplingPolicySelector`` passed in: the sampling policy of every iteration chosen by J', Z = 5
repeats) and PL (no selector: sample with the evaluation policy itself). All trials of a run are
one batched computation (``num_trials``). After every iteration the performance of pi_{l+1} is
measured twice:

* ``test_return``: the paper's estimate (eq. 61), ``(1/50) Σ_m Σ_n γ^(n-1) r`` over 50 test
  episodes of 50 steps of pi_{l+1} (its own ε-greedy rule) on a separately seeded env, so that
  testing never perturbs learning; the episodes are walked with the actions summed out
  (``ChainWalkEnv.walk_tabulated``: the same law of states and rewards, one uniform a step);
* ``exact_return``: the same quantity's exact expectation from the model
  (:func:`~envs.chain_walk.expected_discounted_return`, horizon 50), and ``percent_optimal``,
  that value in % of the optimal deterministic policy's exact value.

Iteration 0 holds pi_1 (θ = 1, shared by AL and PL). At the last iteration AL and PL are
compared by a two-tailed paired t-test on both measures.

Seeds: run seed ``1000·seed + 100·(schedule index)``, the same for AL and PL; trial t of a run
has the seed ``derive_seed(run seed, t, "trial")``. Every random stream of trial t — its
policies' sampling, its rows of the rewarded, reward-free and test environments — is re-seeded
per iteration from ``(trial seed, l)``: AL and PL share every stream they can (a paired design),
the test episodes of a pair meet the same noise, and a trial's numbers do not depend on which
other trials run beside it.

Scale and stored runs (``examples/_harness.py``): ``--chunks C`` splits the trials into C
chunks, each run as one batched computation where ``--backend`` says (``ray``: Ray tasks,
``pip install -e ".[ray]"``, locally or on the cluster at ``--ray-address``), concatenated along
the trial axis: the outputs equal those of one batched run of all trials (tested). Every run
(chunk) is stored as it goes in ``<out-dir>/checkpoints/<schedule>_<AL or
PL>[_chunk<c>of<C>].db``; ``--resume`` continues the runs stored there, buying only what is
missing (the results equal an uninterrupted run's).

    python examples/chain_walk_api.py --trials 1000 --backend ray --chunks 64 --ray-address auto

Outputs in ``--out-dir``: ``chain_walk_api.csv`` (every number, one row per schedule × method ×
iteration × trial × measure: the performance measures, the chosen candidate, its ε, J' of every
candidate, transitions bought; θ and the per-repeat J are left out), ``chain_walk_api.json``
(arguments, t-tests, the runs' seeds and times) and ``fig8_performance.png`` (mean ± standard
error over trials).

    python examples/chain_walk_api.py --trials 1000

By default the runs go to one worker process per core (``--backend processes``): the four runs
(two schedules, AL and PL) side by side, each one batched computation on one thread.

Device: ``--device cuda`` runs the whole experiment on the GPU: the batched chain walks, the
rollouts, psi_hat, J and the solves. The walks' random numbers are drawn on the CPU and moved,
so a seed gives the same episodes on either device.
"""

from __future__ import annotations

from dataclasses import dataclass

from _cli import BACKENDS, ChunkOptions, SelectionOptions, field, parse
from _process import collector_off_for_imports, freeze_imported_objects
from _sizes import memory_error


@dataclass
class Args(SelectionOptions, ChunkOptions):
    """Command-line arguments of the iterated chain-walk experiment."""

    trials: int = field(
        1000,
        low=2,
        why="(a paired t-test needs two)",
        help="independent trials, all run as one batch (the paper: 1000)",
    )
    out_dir: str = field(
        "results/chain_walk_api", help="where the JSON, the CSV, the figure and the stored runs go"
    )
    device: str = field(
        "cpu",
        help=(
            "where the chain walks, the rollouts and the algebra run (cpu, cuda or cuda:N): all "
            "of it"
        ),
    )
    backend: str = field(
        "processes",
        choices=BACKENDS,
        help=(
            "where the chunks of trials run: processes (a pool of local worker processes, one "
            "per core: the 4 runs of a schedule pair side by side; on Linux forked from this "
            "one, so they start at once), local (here, one after another) or ray"
        ),
    )
    tie_break: str = field(
        "uniform",
        choices=("uniform", "lowest"),
        help=(
            "how ε-greedy policies share the greedy mass among tied actions: uniform (equal "
            "parts, so pi_1 of θ_0 = 1 is uniform) or lowest (all to action 0, 'left')"
        ),
    )
    schedule: str = field(
        "both",
        choices=("decreasing", "fixed", "both"),
        help="rewarded-episode schedule: decreasing (5,5,3,3,3,1,1), fixed (3 x 7) or both",
    )
    iterations: int = field(
        7, low=1, high=7, help="L, iterations run (the schedules' first L entries; 7 in the paper)"
    )
    steps: int = field(10, low=1, help="N, steps per rewarded episode")
    test_episodes: int = field(
        50, low=1, help="test episodes per trial for the performance estimate (eq. 61)"
    )
    test_steps: int = field(
        50, low=1, help="steps per test episode (and the horizon of the exact value)"
    )


def size_error(args: Args) -> str | None:
    """Whether the largest chunk's episodes fit in memory (checked before any work starts):
    rewarded, reward-free (Z repeats of 3 candidates) and test transitions at once."""
    trials = -(-args.trials // args.chunks)
    bought = 5 * args.iterations * args.steps  # (at most 5 episodes an iteration)
    free = args.repeats * 3 * bought
    test = args.test_episodes * args.test_steps
    flags = "--trials, --steps, --test-episodes or --test-steps (or raise --chunks)"
    return memory_error(trials * (bought + free + test), flags)


def parse_args(argv=None) -> Args:
    return parse(Args, argv, __doc__, check=size_error)


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below
    collector_off_for_imports()  # examples/_process.py: start-up and exit cost less

from pathlib import Path

import _harness as harness
import torch
from _figures import figure8

from counter_rng import CounterStreams, derive_keys
from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from envs.chain_walk.exact import expected_discounted_return
from envs.chain_walk.model import GAMMA, N_ACTIONS, chain_walk_model, optimal_policy
from torch_api.core.basis import GaussianActionBasis
from torch_api.policies import LinearQPolicy

SCHEDULES = {"decreasing": (5, 5, 3, 3, 3, 1, 1), "fixed": (3, 3, 3, 3, 3, 3, 3)}  # section 4.2
MEASURES = ("test_return", "exact_return", "percent_optimal")
_ROLE_REWARDED, _ROLE_REWARD_FREE, _ROLE_TEST = 1, 2, 3  # environment seed streams


def env_factory(run_seed: int, role: int, device: str = "cpu"):
    """``batch_size -> ChainWalkEnv`` with a seed of its own per role and batch size."""
    return lambda batch: ChainWalkEnv(
        batch_size=batch, seed=harness.derived_seed(run_seed, role, batch), device=device
    )


def optimal_return(horizon: int) -> float:
    """The exact expected discounted return of the optimal deterministic policy."""
    model = chain_walk_model()
    best, _ = optimal_policy(model.transitions, model.expected_reward, GAMMA)
    best_probs = torch.nn.functional.one_hot(best, N_ACTIONS).to(torch.float64)
    return float(
        expected_discounted_return(
            model.transitions, model.expected_reward, best_probs, model.initial, GAMMA, horizon
        )
    )


def make_evaluator(args: Args, trials: int):
    """The ``evaluate`` callback: performance of pi_{l+1} per trial (eq. 61 and exact).

    The library hands pi_{l+1} with one sampling stream per trial, seeded from
    ``api.block_seeds(l, "evaluation")``; the test env's rows of trial t are seeded from the
    same per-trial seed (a stream apart), so trial t's test episodes depend on (its seed, l)
    only: not on the learner's streams, nor on the other trials of the batch.
    """
    m, n = args.test_episodes, args.test_steps
    # re-seeded per trial before every use
    env = ChainWalkEnv(batch_size=trials * m, seed=0, device=args.device)
    model = chain_walk_model()
    P, R = model.transitions, model.expected_reward
    optimum = optimal_return(n)
    states = torch.arange(1, model.n_states + 1, dtype=torch.float64).unsqueeze(-1)

    def evaluate(policy: LinearQPolicy, seed: int | None = None) -> dict:
        env.set_block_seeds(derive_keys(policy.counter_streams.keys, _ROLE_TEST))
        table = policy.action_probs(states.expand(trials, *states.shape))  # [T, S, A]
        # The same policy as a table over the 10 states, on the env's own dynamics without
        # TorchRL's per-step machinery, the actions summed out (env.walk_tabulated: the law of
        # a rollout's states and rewards, tested; one uniform a step instead of two).
        _, reward = env.walk_tabulated(table, n)  # [n, T·m]
        discounted = torch.zeros(trials * m, dtype=torch.float64, device=env.device)
        for step, r in enumerate(reward):  # step by step: each row's sum in one order
            discounted += GAMMA**step * r.to(torch.float64)
        test_return = discounted.reshape(trials, m).mean(-1)  # eq. 61, [T]
        exact = expected_discounted_return(P, R, table, model.initial, GAMMA, n)  # [T]
        return {
            "test_return": test_return.tolist(),
            "exact_return": exact.tolist(),
            "percent_optimal": (100.0 * exact / optimum).tolist(),
        }

    return evaluate


def run_chunk(chunk: harness.Chunk) -> dict:
    """One batched run of Algorithm 1 on a chunk of trials; per-iteration, per-trial records."""
    args, run_seed = chunk.args, chunk.seed
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2)
    evaluate = make_evaluator(args, len(chunk.trials))
    api = harness.make_iteration(
        chunk,
        repeats=args.repeats,
        env=env_factory(run_seed, _ROLE_REWARDED, args.device),
        reward_free_env=env_factory(run_seed, _ROLE_REWARD_FREE, args.device),
        basis=basis,
        schedule=chunk.schedule,
        num_steps=args.steps,
        gamma=GAMMA,
        lam=args.lam,
        psi_mode="grouped",
        tie_break=args.tie_break,
        evaluate=evaluate,
        keep_reward_free=False,  # T·Z·K·ΣM reward-free episodes are not needed afterwards
        device=args.device,
    )
    # pi_1, with streams of its own
    first = api.initial_policy().with_streams(CounterStreams(api.block_seeds(0, "evaluation")))
    return harness.run_iterations(chunk, api, initial=evaluate(first))  # pi_1: iteration 0


def report(args: Args, experiment: harness.Experiment, results: dict, wall: float) -> dict:
    """The tables, the files (JSON, CSV, Figure 8) of a finished experiment."""
    print(f"\nIterated chain walk: {args.trials} trials, mean ± s.e. over trials ({wall:.1f} s)")
    test = f"{args.test_episodes} test episodes of {args.test_steps} steps"
    title = f"performance of pi_{{l+1}}, eq. 61 ({test})"
    harness.print_curves(results, "test_return", title)
    title = "exact expected return of pi_{l+1}, % of the optimal policy"
    harness.print_curves(results, "percent_optimal", title, digits=2)
    harness.print_t_tests(results, args.trials)
    optimum = optimal_return(args.test_steps)
    payload = harness.write_results(args, experiment, results, wall, optimal_exact_return=optimum)
    figure8(results, optimum, Path(args.out_dir) / "fig8_performance.png")
    print(f"wrote {args.out_dir}/chain_walk_api.json, chain_walk_api.csv and fig8_performance.png")
    return payload


def main(argv=None) -> dict:
    args = parse_args(argv)
    names = list(SCHEDULES) if args.schedule == "both" else [args.schedule]
    experiment = harness.Experiment(
        name="chain_walk_api",
        schedules={name: SCHEDULES[name][: args.iterations] for name in names},
        run_chunk=run_chunk,
        t_tests=("test_return", "exact_return"),
        report=lambda results, wall: report(args, experiment, results, wall),
        run_seed=lambda seed, name: 1000 * seed + 100 * list(SCHEDULES).index(name),
        curves=(*MEASURES, "rewarded_transitions"),
        files=("fig8_performance.png",),
    )
    return harness.run_experiment(args, experiment)


if __name__ == "__main__":
    freeze_imported_objects()
    main()
