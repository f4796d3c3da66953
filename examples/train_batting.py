"""Active vs passive policy iteration on the ball-batting robot (paper section 5, Figure 10).

For each schedule of rewarded episodes (``decreasing`` = 10, 10, 7, 7, 7, 4, 4 and ``fixed`` = 7
× 7), an AL run (the sampling policy chosen by J', Algorithm 2) and a PL run (the evaluation
policy samples) are made with the same seed (a paired design), all trials as one batch. After
every iteration l, pi_{l+1} is measured per trial (eq. 68: the rewards of 20 test episodes of 10
steps). It prints mean ± s.e. per iteration, the rewards bought and a paired t-test of AL vs PL
at the last iteration, and writes ``train_batting.csv`` (one row per schedule × method ×
iteration × trial × measure), ``train_batting.json`` (arguments, t-tests, physics steps, times)
and ``fig10_performance.png``.

Paper settings: 54 Gaussian centres on {0, π/4} × {-π, 0, π} × {-π/4, 0, π/4} × {-π, 0, π},
τ = 3π/2, 2 actions (B = 110), γ = 1, psi_hat of the single transition, λ = 1e-3, Z = 5,
ε_l = 0.15 / l, candidates ε_l + (0, 0.15, 0.5, 0.85), θ_0 = 1, N = 10 steps.

Defaults (about a minute on 2 CPU cores): 32 trials, the decreasing schedule, all 7 iterations,
AL and PL, one process (MuJoCo steps its batch on every core). Its last lines say what it found:
AL and PL at l = 7 (mean ± s.e. over trials), their paired difference, t-test and the share of
trials scoring 0. The figure shows the score per iteration, method (colour) and schedule (line
style) with s.e. bars, the reference optimum (examples/batting_reference.py) and the learner's
ceiling with the paper's basis (benchmarks/batting_ceiling.py), and beside it AL − PL.

    python examples/train_batting.py

The paper's full experiment (500 trials, both schedules) is mostly MuJoCo rollouts. Chunks of
about 16 trials in one worker process per core overlap one process's physics with another's
algebra; it took 1085 s (18.1 min) on 2 idle cores with ``--tie-break lowest``
(``benchmarks/bench_figure10.py``; README, "The ball-batting robot"):

    python examples/train_batting.py --trials 500 --schedule both --backend processes --chunks 32

Chunks and stored runs (``examples/_harness.py``): ``--chunks C`` splits every run's trials into
C batched chunks, run where ``--backend`` says (``processes``: ``--workers`` local processes;
``ray``: Ray tasks, at ``--ray-address``); trial t's seed and arm noise streams are its own, so
the chunked results equal the unchunked ones (tested). Every run is stored as it goes
(``<out-dir>/checkpoints/<schedule>_<mode>[_chunk<c>of<C>].db``), each batch of rewarded
episodes committed before the next is measured; ``--resume`` continues from the stores without
buying rewards again, and SIGINT/SIGTERM finish the commit in flight (exit 130/143). Physics is
MuJoCo on the CPU; ``--device cuda`` moves the algebra (psi_hat, J, the solves) to the GPU.

    python examples/train_batting.py --trials 500 --schedule both --backend ray --chunks 16

Ties: θ_0 = 1 (and θ = 0, before any reward) gives both actions the same Q̂: by default pi_1 is
uniform (it hits the ball in half of its episodes); with ``--tie-break lowest`` it cocks the arm
(hits in 0.1 %), and a PL trial that sees no reward keeps θ = 0 and that policy for ever.
"""

from __future__ import annotations

from dataclasses import dataclass

from _batting_options import BeyondPaperOptions, check, paper_learner, parse_widths
from _cli import ChunkOptions, SelectionOptions, field, parse
from _flattening import parse_flattening
from _process import collector_off_for_imports, freeze_imported_objects


@dataclass
class Args(BeyondPaperOptions, SelectionOptions, ChunkOptions):
    """Command-line arguments of the batting experiment."""

    trials: int = field(
        32, low=1, help="T, independent trials, all run as one batch (the paper: 500)"
    )
    out_dir: str = field(
        "results/train_batting", help="where the JSON, CSV, figure and checkpoints go"
    )
    device: str = field(
        "cpu", help="where the algebra runs (cpu, cuda or cuda:N); physics is MuJoCo on the CPU"
    )
    schedule: str = field(
        "decreasing",
        choices=("decreasing", "fixed", "both"),
        help="rewarded-episode schedule: decreasing (10,10,7,7,7,4,4), fixed (7 x 7) or both",
    )
    iterations: int = field(
        7, low=1, high=7, help="how many of the schedule's L = 7 iterations to run"
    )
    episodes: int = field(
        0, low=0, help="if > 0, M_l of every iteration (replaces the schedule's numbers)"
    )
    tie_break: str = field(
        "uniform",
        choices=("uniform", "lowest"),
        help=(
            "how ε-greedy policies share the greedy mass among tied actions: uniform (equal "
            "parts, so pi_1 of θ_0 = 1 is uniform) or lowest (all to action 0, 'cock')"
        ),
    )
    physics_audit: float = field(
        0.0,
        low=0.0,
        high=1.0,
        help=(
            "fraction of physics rollouts to sample for replay (benchmarks/bench_figure10.py); "
            "the physics steps are counted either way"
        ),
    )


EPILOG = (
    "defaults: 32 trials, decreasing schedule, 7 iterations (about a minute on 2 cores). The "
    "paper's run: --trials 500 --schedule both --backend processes --chunks 32"
)


def parse_args(argv=None) -> Args:
    return parse(Args, argv, __doc__, epilog=EPILOG, check=check)


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below
    collector_off_for_imports()  # examples/_process.py: start-up and exit cost less

import os
import zlib
from pathlib import Path

import _harness as harness
import numpy as np
import scipy.special
from _batting_basis import make_basis
from _figures import figure10
from _physics_audit import PhysicsAudit
from _weight_warnings import kept_weight_warnings, report_weight_warnings

from counter_rng import derive_keys
from envs.batting import MAX_STEPS, BattingEnv
from torch_api.collection import collect_episodes
from torch_api.data import REWARD_KEY
from torch_api.policies import LinearQPolicy
from torch_api.runs.dispatch import threads_per_worker
from torch_api.streams import STREAMS

SCHEDULES = {"decreasing": (10, 10, 7, 7, 7, 4, 4), "fixed": (7,) * 7}  # M_l, l = 1 … 7
GAMMA = 1.0  # discount γ
TEST_EPISODES = 20  # test episodes per trial behind one performance value (eq. 68)
# Horizontal lines of the figure (scores of eq. 68, Σ carry over 20 episodes): the best
# open-loop sequence without noise, 13.74 m per episode (examples/batting_reference.py); the
# best LSPI score with the paper's basis on abundant random data (benchmarks/batting_ceiling.py)
REFERENCE_OPTIMUM, PAPER_BASIS_CEILING = 20 * 13.74, 199.9
# What the paper-size run of the default setting found (README, the Figure 10 table: 500 trials,
# seed 0, ties split evenly, the paper's learner): AL − PL at l = 7, its s.e. and the paired
# t-test's p, per schedule. Rerun with the README's table; a run of another setting has none.
PAPER_SIZE_RUN = {"decreasing": (4.1, 4.2, 0.33), "fixed": (-7.4, 4.4, 0.09)}


def schedule_of(args: Args, name: str) -> list[int]:
    """M_l of the first ``args.iterations`` iterations of the named schedule."""
    base = SCHEDULES[name][: args.iterations]
    return [args.episodes] * len(base) if args.episodes else list(base)


def make_evaluator(trials: int, make_env):
    """The ``evaluate`` callback: performance of pi_{l+1} (eq. 68), Σ_m Σ_n r over 20 test
    episodes, and the share of them that hit the ball, per trial.

    The loop hands pi_{l+1} with one sampling stream per trial, seeded from
    ``api.block_seeds(l, "evaluation")``; the 20 test arms of trial t get one stream of their own
    seeded from the same per-trial seed (a stream apart), so trial t's performance depends on
    (its seed, l) only, and a resumed run measures exactly what an uninterrupted one would.
    """
    env = None

    def evaluate(policy: LinearQPolicy, seed: int) -> dict:
        nonlocal env
        if env is None:
            env = make_env(batch_size=trials * TEST_EPISODES, seed=seed)
        keys = policy.counter_streams.keys  # one stream per trial
        env.set_block_seeds(derive_keys(keys, 0, STREAMS["evaluation"]))
        episodes = collect_episodes(
            env, policy, num_episodes=TEST_EPISODES, num_steps=MAX_STEPS, rewarded=True
        )  # [T, 20, N]
        reward = episodes[REWARD_KEY] * episodes["mask"]
        hits = (reward > 0).any(-1).double().mean(-1)
        return {"performance": reward.sum((-2, -1)).tolist(), "hit_share": hits.tolist()}

    return evaluate


def run_chunk(chunk: harness.Chunk) -> dict:
    """Run (or resume, with ``--resume``) one chunk, checkpointed to ``chunk.store``; plus
    ``"physics"``: the :class:`PhysicsAudit` of this invocation's physics steps.

    Trial t's seed is ``derive_seed(seed, t, "trial")`` in every chunking; the run's own seed is
    ``--seed`` for the chunk of trial 0, else derived from the chunk's first trial.
    """
    args, first = chunk.args, chunk.trials[0]
    # the audit's sampling stream: its own per chunk (keyed by the store's name)
    name_key = zlib.crc32(chunk.store.name.encode())
    audit_seed = int(np.random.SeedSequence([args.seed, name_key]).generate_state(1)[0])
    audit = PhysicsAudit(args.physics_audit, seed=audit_seed)
    # MuJoCo threads: every core in-process, the cores shared out among processes, one per
    # Ray task (Ray gives each task one CPU)
    threads = {"local": None, "ray": 1}.get(
        args.backend, threads_per_worker(args.workers or os.cpu_count() or 1)
    )

    def env(batch_size: int, seed: int | None = None) -> BattingEnv:
        # the rewarded and reward-free envs are re-seeded by the loop every iteration
        return BattingEnv(
            batch_size=batch_size,
            seed=seed,
            nthread=threads,
            hook=audit,
            end_at_hit=args.end_at_hit,
        )

    api = harness.make_iteration(
        chunk,
        repeats=args.repeats,
        env=env,
        reward_free_env=env,
        basis=make_basis(parse_widths(args.basis_widths)),
        schedule=chunk.schedule,
        num_steps=MAX_STEPS,
        gamma=GAMMA,
        lam=args.lam,
        psi_mode="single",
        fit=args.fit,
        flattening=parse_flattening(args.flattening),
        tie_break=args.tie_break,
        evaluate=make_evaluator(len(chunk.trials), env),
        seed=args.seed if first == 0 else harness.derived_seed(args.seed, first, bits=63),
        keep_reward_free=False,  # not needed later; keeps checkpoints small
        device=args.device,
    )
    with kept_weight_warnings(api, chunk) as caught:
        result = harness.run_iterations(chunk, api)
    return result | {"physics": [audit], "weight_warnings": caught}


def print_table(name: str, entry: dict, trials: int) -> None:
    schedule, test = entry["schedule"], entry["t_tests"]["performance"]
    al, pl = (entry["runs"][m]["iterations"] for m in ("AL", "PL"))
    print(f"\nschedule {name} (M_l = {schedule}), {trials} trials, performance (eq. 68) mean ± se")
    print(
        f"{'l':>2} {'M_l':>4} {'AL':>17} {'PL':>17} {'bought/trial':>13} {'bought total':>13} "
        f"{'AL choices (k=1..4)':>20}"
    )
    for i, m in enumerate(schedule):
        a, pa = harness.mean_se(al[i]["performance"])
        p, pp = harness.mean_se(pl[i]["performance"])
        bought = np.asarray(al[i]["rewarded_transitions"])  # each trial's own (early ends)
        per_trial, total = round(float(bought.mean())), int(bought.sum())
        choices = np.bincount(np.asarray(al[i]["chosen"]), minlength=4)
        print(
            f"{i + 1:>2} {m:>4} {a:8.2f} ± {pa:6.2f} {p:8.2f} ± {pp:6.2f} {per_trial:>13} "
            f"{total:>13} {' '.join(str(c) for c in choices):>20}"
        )
    last = f"paired t-test AL vs PL at iteration {len(schedule)}:"
    if test["t"] is None:
        print(f"{last} undefined (fewer than 2 trials or identical results)")
    else:
        print(f"{last} t = {test['t']:.3f}, p = {test['p']:.4f} (two-tailed)")


def learner_ceiling(args: Args) -> float | None:
    """The measured ceiling of this run's learner: the paper's basis and fit only (None else)."""
    return PAPER_BASIS_CEILING if paper_learner(args) else None


def default_setting(args: Args) -> bool:
    """Whether the run has the setting of the README's paper-size table (any trial count)."""
    defaults = Args()
    same = ("seed", "repeats", "lam", "iterations", "episodes", "tie_break", "end_at_hit")
    return learner_ceiling(args) is not None and all(
        getattr(args, key) == getattr(defaults, key) for key in same
    )


def print_findings(results: dict, args: Args) -> None:
    """The last lines: what this run found, and how to run the paper-size experiment."""
    ceiling = learner_ceiling(args)
    print(
        f"\nFound ({args.trials} trials, paired seeds, score of eq. 68 at l = {args.iterations}; "
        f"reference optimum {REFERENCE_OPTIMUM:.0f}, "
        + (
            f"paper-basis ceiling {ceiling:.0f}):"
            if ceiling is not None
            else "no measured ceiling for this basis and learner):"
        )
    )
    for name, entry in results.items():
        al, pl = (
            np.asarray(entry["runs"][m]["iterations"][-1]["performance"]) for m in ("AL", "PL")
        )
        (a, a_se), (p, p_se), (d, d_se) = map(harness.mean_se, (al, pl, al - pl))
        test = entry["t_tests"]["performance"]
        if test["p"] is None:
            tested = "the paired t-test is undefined (no spread in the differences)"
        else:
            half = scipy.special.stdtrit(len(al) - 1, 0.975) * d_se  # t quantile
            tested = (
                f"95 % CI [{d - half:+.1f}, {d + half:+.1f}] (paired t-test over {len(al)} "
                f"trials: t = {test['t']:.2f}, p = {test['p']:.3g})"
            )
        print(
            f"  {name}: AL {a:.1f} ± {a_se:.1f}, PL {p:.1f} ± {p_se:.1f} (s.e. over trials); "
            f"AL − PL {d:+.1f} ± {d_se:.1f}, {tested}; trials scoring 0: AL "
            f"{(al == 0).mean():.0%}, PL {(pl == 0).mean():.0%}"
        )
        paper_size = PAPER_SIZE_RUN.get(name) if default_setting(args) else None
        if paper_size is not None and args.trials < 500:
            print(
                f"    the paper-size run of this setting (README, Figure 10 table, 500 trials): "
                f"AL − PL {paper_size[0]:+.1f} ± {paper_size[1]:.1f}, p = {paper_size[2]:.2f}"
            )
    print("The paper-size experiment (500 trials, both schedules; see README for its wall time):")
    print(
        "  python examples/train_batting.py --trials 500 --schedule both --backend processes "
        "--chunks 32"
    )


def report(args: Args, experiment: harness.Experiment, results: dict, wall: float) -> dict:
    """The tables, the files (JSON, CSV, Figure 10) and the findings of a finished experiment."""
    audit = PhysicsAudit()
    for entry in results.values():
        for run in entry["runs"].values():
            physics = PhysicsAudit()
            for part in run.pop("physics"):
                physics.merge(part)
            run["physics_steps"] = dict(physics.steps)
            audit.merge(physics)
    for name, entry in results.items():
        print_table(name, entry, args.trials)
    runs = [run for entry in results.values() for run in entry["runs"].values()]
    report_weight_warnings(runs, Path(args.out_dir) / "train_batting.log")
    steps = dict(audit.steps)
    payload = harness.write_results(
        args, experiment, results, wall, test_episodes=TEST_EPISODES, physics_steps=steps
    )
    payload["physics_audit"] = audit  # for benchmarks/bench_figure10.py; not in the JSON
    out = Path(args.out_dir)
    figure10(results, REFERENCE_OPTIMUM, learner_ceiling(args), out / "fig10_performance.png")
    print(f"\nphysics: {steps['coarse']:,} coarse + {steps['fine']:,} fine MuJoCo steps")
    print(f"wall time {wall:.1f} s; wrote {out}/train_batting.json, .csv, fig10_performance.png")
    print_findings(results, args)
    return payload


def main(argv=None, on_checkpoint=None) -> dict:
    """The experiment; ``on_checkpoint(api)`` is called after every commit of every run
    (``--backend local`` only)."""
    args = parse_args(argv)
    names = list(SCHEDULES) if args.schedule == "both" else [args.schedule]
    experiment = harness.Experiment(
        name="train_batting",
        schedules={name: schedule_of(args, name) for name in names},
        run_chunk=run_chunk,
        t_tests=("performance",),
        report=lambda results, wall: report(args, experiment, results, wall),
        store_stem="{schedule}_{mode}",
        curves=("performance", "hit_share", "rewarded_transitions"),
        files=("fig10_performance.png",),
    )
    return harness.run_experiment(args, experiment, on_checkpoint=on_checkpoint)


if __name__ == "__main__":
    freeze_imported_objects()
    main()
