"""Active vs passive policy iteration on the ball-batting robot (paper section 5, Figure 10).

Per schedule of rewarded episodes (decreasing: 10, 10, 7, 7, 7, 4, 4; fixed: 7 × 7), an AL run
(its sampling policy chosen by J', Algorithm 2) and a PL run (pi_l samples) on the same seeds,
all trials as one batch; pi_{l+1} scores Σ carry over 20 noisy test episodes (eq. 68). The
paper's learner: 54 Gaussian centres, τ = 3π/2, B = 110, γ = 1, λ = 1e-3, Z = 5, ε_l = 0.15 / l,
θ_0 = 1, N = 10. Writes train_batting.csv, .json and fig10_performance.png into --out-dir.

    python examples/train_batting.py  # 32 trials in two worker processes (chunks of 16)
"""

import functools
import json
import sys
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro
from tyro.conf import FlagCreatePairsOff, OmitArgPrefixes

from counter_rng import derive_keys
from envs.batting import BASIS_TAU, MAX_STEPS, N_ACTIONS, BattingEnv, PhysicsAudit, basis_centers
from torch_api import GaussianActionBasis, RunSpec, collect_episodes
from torch_api import experiment as ex
from torch_api.data import REWARD_KEY
from torch_api.runs.dispatch import threads_per_worker
from torch_api.streams import STREAMS

SCHEDULES = {"decreasing": (10, 10, 7, 7, 7, 4, 4), "fixed": (7,) * 7}  # M_l, l = 1 … 7
TESTS = 20  # test episodes per trial behind one score (eq. 68)
REFERENCE = Path("results/batting_reference.json")  # examples/batting_reference.py writes it
PAPER_SIZE = "--trials 500 --schedule both --backend processes --chunks 8 --out-dir results/paper"
PAPER_RUN = Path("results/paper/train_batting.json")  # what PAPER_SIZE writes, if it was run
SAME = ("trials", "schedule", "execution", "device")  # the paper-size run quoted: this setting


@dataclass(frozen=True)
class Args:
    """The batting experiment: the learner's settings, then where it runs."""

    trials: int = 32
    """T, independent trials, all run as one batch (the paper: 500)"""
    seed: int = 0
    """master seed; AL and PL of a schedule share their trials' seeds (a paired design)"""
    schedule: Literal["decreasing", "fixed", "both"] = "decreasing"
    """rewarded episodes per iteration: decreasing (10,10,7,7,7,4,4), fixed (7 x 7) or both"""
    iterations: int = 7
    """how many of the schedule's L = 7 iterations to run"""
    episodes: int = 0
    """if > 0, M_l of every iteration (replaces the schedule's numbers)"""
    repeats: int = 5
    """Z, J-values averaged into J' (Algorithm 2)"""
    lam: float = 1e-3
    """λ, the ridge of the fit and of J"""
    tie_break: Literal["uniform", "lowest"] = "uniform"
    """ε-greedy's greedy mass among tied actions: uniform (pi_1 of θ_0 = 1 is uniform) or lowest"""
    fit: Literal["brm", "lstd"] = "brm"
    """brm (the paper: least squares of r on psi_hat) or lstd (beyond the paper: LSTD-Q)"""
    flattening: float | Literal["iwcv"] = 1.0
    """ν of the flattened importance weights w^ν (1: the paper's), or iwcv (chosen by IWCV)"""
    basis_widths: tuple[float, float, float, float] | None = None
    """beyond the paper: a kernel width per state dimension (rad, rad/s, rad, rad/s), τ = 1"""
    end_at_hit: bool = False
    """beyond the paper: episodes end at the first bat-ball contact"""
    swing: Literal["tensor", "mujoco"] = "tensor"
    """the contact-free swing: batched tensor dynamics, or MuJoCo's own (the engine of record)"""
    physics_audit: float = 0.0
    """fraction of physics rollouts kept for replay (benchmarks/bench_figure10.py)"""
    device: str = "cpu"
    """where the algebra runs (cpu, cuda or cuda:N); the physics is MuJoCo's, on the CPU"""
    execution: Annotated[ex.Execution, OmitArgPrefixes] = ex.Execution(
        "results/train_batting", backend="processes", chunks=2
    )
    """where the runs go: the output folder, stored runs, chunks of trials and their backend (by
    default two chunks per run in worker processes, one per core: the numbers do not change)"""


def make_spec(args: Args, schedule: list[int], seed: int) -> RunSpec:
    """Every setting of a run of Algorithm 1 (checked: a ValueError names the field)."""
    fixed = dict(num_steps=MAX_STEPS, gamma=1.0, psi_mode="single", keep_reward_free=False)
    learner = dict(lam=args.lam, fit=args.fit, flattening=args.flattening, tie_break=args.tie_break)
    trials = dict(num_trials=args.trials, seed=seed, num_repeats=args.repeats)
    return RunSpec.of(schedule=schedule, **fixed, **learner, **trials)


def make_basis(widths=None) -> GaussianActionBasis:
    """The paper's 54 Gaussian centres, τ = 3π/2, and a constant, per action (B = 110, eq. 64);
    with ``widths``, the same centres with a kernel width per state dimension."""
    centers, tau = basis_centers(), BASIS_TAU if widths is None else 1.0
    return GaussianActionBasis(centers=centers, tau=tau, widths=widths, num_actions=N_ACTIONS)


def make_evaluator(trials: int, make_env):
    """pi_{l+1}'s score per trial, Σ carry over 20 test episodes (eq. 68), and its hit share;
    trial t's test arms draw from a stream of its own: its score depends on (its seed, l) only."""
    env = None

    def evaluate(policy, seed: int) -> dict:
        nonlocal env
        if env is None:  # made once; re-seeded per trial below
            env = make_env(batch_size=trials * TESTS, seed=seed)
        env.set_block_seeds(derive_keys(policy.counter_streams.keys, 0, STREAMS["evaluation"]))
        td = collect_episodes(env, policy, num_episodes=TESTS, num_steps=MAX_STEPS, rewarded=True)
        reward = td[REWARD_KEY] * td["mask"]  # [T, 20, N]
        hits = (reward > 0).any(-1).double().mean(-1)
        return {"performance": reward.sum((-2, -1)).tolist(), "hit_share": hits.tolist()}

    return evaluate


def run_chunk(chunk: ex.Chunk) -> dict:
    """One chunk's run (or its resumption), and the physics steps it took (its audit)."""
    args, first = chunk.args, chunk.trials[0]
    key = zlib.crc32(chunk.store.name.encode())  # the audit's sample: a stream of its own
    audit = PhysicsAudit(args.physics_audit, ex.derived_seed(args.seed, key))
    workers = threads_per_worker(chunk.execution.num_workers)  # MuJoCo's threads per process
    threads = {"local": None, "ray": 1}.get(chunk.execution.backend, workers)

    def env(batch_size: int, seed: int | None = None) -> BattingEnv:  # (re-seeded by the loop)
        kwargs = dict(nthread=threads, hook=audit, end_at_hit=args.end_at_hit, swing=args.swing)
        return BattingEnv(batch_size=batch_size, seed=seed, **kwargs)

    seed = args.seed if first == 0 else ex.derived_seed(args.seed, first, bits=63)
    spec, basis = make_spec(args, list(chunk.schedule), seed), make_basis(args.basis_widths)
    score = make_evaluator(len(chunk.trials), env)
    api = ex.make_iteration(chunk, spec, env=env, basis=basis, evaluate=score, device=args.device)
    with ex.kept_weight_warnings(api, chunk) as caught:
        result = ex.run_iterations(chunk, api)
    return result | {"physics": [audit], "weight_warnings": caught}


def paper_run(args: Args, name: str) -> str:
    """AL − PL at l = L of the stored paper-size run of this setting, or how to make it."""
    stored = json.loads(PAPER_RUN.read_text()) if PAPER_RUN.is_file() else {}
    mine, theirs = json.loads(json.dumps(asdict(args))), stored.get("args", {})
    test = stored.get("summary", {}).get(name, {}).get("t_tests", {}).get("performance", {})
    if test.get("t") is None or any(theirs.get(k) != mine[k] for k in mine if k not in SAME):
        return f"{name}, paper size: python examples/train_batting.py {PAPER_SIZE}"
    d, t, p, trials = test["mean_difference"], test["t"], test["p"], theirs["trials"]
    return f"{name}, {trials} trials ({PAPER_RUN}): AL − PL {d:+.1f}, t = {t:.2f}, p = {p:.2g}"


def report(args: Args, experiment: ex.Experiment, results: dict, wall: float) -> dict:
    """The tables, the files (CSV, JSON, Figure 10) and the paper-size run of this setting."""
    audit, out = PhysicsAudit(), Path(args.execution.out_dir)
    runs = [run for entry in results.values() for run in entry["runs"].values()]
    for run in runs:  # each run's physics steps (the audits of its chunks), and all runs'
        mine = functools.reduce(PhysicsAudit.merge, run.pop("physics"), PhysicsAudit())
        run["physics_steps"] = dict(mine.steps)
        audit.merge(mine)
    ex.print_curves(results, "performance", "score of eq. 68 (m) per iteration l, mean ± s.e.", 1)
    ex.print_t_tests(results, args.trials)
    ex.report_weight_warnings(runs, out / "train_batting.log")
    extra = {"test_episodes": TESTS, "physics_steps": dict(audit.steps)}
    payload = ex.write_results(args.execution, args, experiment, results, wall, **extra)
    payload["physics_audit"] = audit  # (benchmarks/bench_figure10.py; not in the JSON)
    optimum = json.loads(REFERENCE.read_text())["reference_optimum"] if REFERENCE.is_file() else {}
    best = {"reference optimum": optimum.get("best_carry", 0) * TESTS or None}  # (no file: none)
    figure, label = out / "fig10_performance.png", {"performance": "Σ carry, 20 test episodes (m)"}
    ex.plot_paired(results, figure, label, lines={"performance": best}, difference=True, floor=0)
    print(f"\nphysics: {audit.steps['coarse']:,} coarse + {audit.steps['fine']:,} fine steps")
    print(f"wall time {wall:.1f} s; wrote {out}/train_batting.json, .csv, {figure.name}")
    print("\n".join(paper_run(args, name) for name in results))
    return payload


def main(argv: list[str] | None = None, on_commit=None) -> dict:
    """The experiment; ``on_commit()`` is called after every commit (``--backend local``)."""
    args = tyro.cli(Args, args=argv, description=__doc__, config=(FlagCreatePairsOff,))
    names = list(SCHEDULES) if args.schedule == "both" else [args.schedule]
    schedules = {n: [args.episodes or m for m in SCHEDULES[n][: args.iterations]] for n in names}
    try:  # every setting checked before any work: one line naming it, exit 2
        if not 1 <= args.iterations <= 7 or args.episodes < 0:
            raise ValueError(f"iterations must lie in 1..7, got {args.iterations}; episodes >= 0")
        ex.checked_device(args.device)
        make_basis(args.basis_widths), PhysicsAudit(args.physics_audit)  # (each checks its own)
        specs = {name: make_spec(args, schedule, args.seed) for name, schedule in schedules.items()}
        args.execution.check_chunks(args.trials)
        Path(args.execution.out_dir).mkdir(parents=True, exist_ok=True)  # (and writable)
    except (ValueError, RuntimeError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    experiment = ex.Experiment(
        name="train_batting",
        schedules={name: spec.rewarded.schedule for name, spec in specs.items()},
        run_chunk=run_chunk,
        t_tests=("performance",),
        report=lambda results, wall: report(args, experiment, results, wall),
        curves=("performance", "hit_share", "rewarded_transitions"),
        files=("fig10_performance.png",),
        trials=args.trials,
        seed=args.seed,
    )
    return ex.run_experiment(experiment, args.execution, args, on_commit=on_commit)


if __name__ == "__main__":
    main()
