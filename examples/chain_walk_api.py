"""Active vs passive policy iteration on the 10-state chain walk (paper section 4.2, Figure 8).

For each schedule of rewarded episodes — 'decreasing' M = (5, 5, 3, 3, 3, 1, 1) and 'fixed'
M = (3,) * 7, N = 10 steps each — it runs Algorithm 1 twice on the same seeds (paired design):
AL (``mode="active"``: the sampling policy of every iteration chosen by J', Z = 5 repeats) and
PL (``mode="passive"``: sample with the evaluation policy itself). All trials of a run are one
batched computation (``num_trials``). After every iteration the performance of pi_{l+1} is
measured twice:

* ``test_return``: the paper's estimate (eq. 61), ``(1/50) Σ_m Σ_n γ^(n-1) r`` over 50 test
  episodes of 50 steps collected with pi_{l+1} (its own ε-greedy rule) on a separately seeded
  env, with a sampling stream of its own so that testing never perturbs learning;
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

Scale: ``--chunks C`` splits the trials into C chunks, each run as one batched computation;
``--backend ray`` runs the chunks as Ray tasks (``pip install -e ".[ray]"``; a local Ray
instance, or the cluster at ``--ray-address``). The chunks' results are concatenated along the
trial axis, so the outputs equal those of one batched run of all trials (tested):

    python examples/chain_walk_api.py --trials 1000 --backend ray --chunks 8
    python examples/chain_walk_api.py --trials 1000 --backend ray --chunks 64 --ray-address auto

Outputs in ``--out-dir``: ``chain_walk_api.json`` (every number per trial and iteration:
performance, chosen candidate, its ε, J' of every candidate, transitions bought; θ and the
per-repeat J are left out), ``chain_walk_api.csv`` (one row per schedule × method × iteration ×
trial) and ``fig8_performance.png`` (mean ± standard error over trials).

    python examples/chain_walk_api.py --trials 1000

Durable runs: every run (chunk) is stored as it goes in ``<out-dir>/checkpoints/<schedule>_<AL
or PL>[_chunk<c>of<C>].db`` (an SQLite database, ``torch_api/store.py``): the rewarded
episodes of an iteration are committed before the next are measured. A folder holding runs is
refused unless ``--resume`` (continue them, buying only what is missing; the results equal an
uninterrupted run's) or ``--overwrite`` (discard them) is given. SIGINT/SIGTERM finish the
commit in flight and end with one line (exit 130/143).

Device: ``--device cuda`` runs the whole experiment on the GPU: the batched chain walks, the
rollouts, psi_hat, J and the solves. The walks' random numbers are drawn on the CPU and moved,
so a seed gives the same episodes on either device.
"""

from __future__ import annotations

from dataclasses import dataclass

from _cli import (
    BACKENDS,
    LOGGERS,
    Interrupted,
    exit_interrupted,
    exit_store_error,
    field,
    first_line,
    log_means,
    make_logger,
    parse,
    raise_on_signals,
    stored_runs_error,
)


@dataclass
class Args:
    """Command-line arguments of the iterated chain-walk experiment."""

    trials: int = field(1000, low=2, why="(a paired t-test needs two)")
    """independent trials, all run as one batch (the paper: 1000)"""
    seed: int = 0
    """master seed; AL and PL of a schedule share their seeds"""
    out_dir: str = "results/chain_walk_api"
    """where the JSON, the CSV, the figure and the stored runs go"""
    resume: bool = False
    """continue the runs stored in out_dir (a missing run starts fresh)"""
    overwrite: bool = False
    """discard the runs stored in out_dir and start over"""
    repeats: int = field(5, low=1)
    """Z, J-values averaged into J'"""
    lam: float = field(1e-3, above=0)
    """λ, ridge regularisation"""
    tie_break: str = field("uniform", choices=("uniform", "lowest"))
    """how ε-greedy policies share the greedy mass among tied actions: uniform (equal parts, so
    pi_1 of θ_0 = 1 is uniform) or lowest (all to action 0, 'left')"""
    schedule: str = field("both", choices=("decreasing", "fixed", "both"))
    """rewarded-episode schedule: decreasing (5,5,3,3,3,1,1), fixed (3 x 7) or both"""
    iterations: int = field(7, low=1, high=7)
    """L, iterations run (the schedules' first L entries; 7 in the paper)"""
    steps: int = field(10, low=1)
    """N, steps per rewarded episode"""
    test_episodes: int = field(50, low=1)
    """test episodes per trial for the performance estimate (eq. 61)"""
    test_steps: int = field(50, low=1)
    """steps per test episode (and the horizon of the exact value)"""
    threads: int = field(0, low=0)
    """torch intra-op threads (0: torch's default; 1 is much faster on a busy machine)"""
    backend: str = field("local", choices=BACKENDS)
    """where the chunks of trials run: local (here, one after another), processes (a pool
    of local worker processes) or ray"""
    chunks: int = field(1, low=1)
    """C, chunks of trials per schedule and method (each one batched run; results concatenated)"""
    workers: int = field(0, low=0)
    """processes backend: worker processes (0: one per CPU core)"""
    ray_address: str = ""
    """Ray cluster to join (e.g. auto); empty starts a local Ray instance"""
    ray_cpus: int = field(0, low=0)
    """CPUs of a local Ray instance (0: all)"""
    device: str = "cpu"
    """where the chain walks, the rollouts and the algebra run (cpu, cuda or cuda:N): all of it"""
    logger: str = field("none", choices=LOGGERS)
    """also write the learning curves (means over trials) with a TorchRL logger under
    <out-dir>/logs: csv, tensorboard or wandb (the last two need their package)"""


def check(args: Args) -> str | None:
    if args.resume and args.overwrite:
        return "--resume and --overwrite exclude each other"
    if args.chunks > args.trials:
        return f"--chunks must lie in 1..{args.trials} (--trials), got {args.chunks}"
    return None


def parse_args(argv=None) -> Args:
    return parse(
        Args,
        argv,
        description=first_line(__doc__),
        check=check,
    )


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below

import csv  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
import torch  # noqa: E402

from envs.chain_walk import (  # noqa: E402
    CENTERS,
    GAMMA,
    N_ACTIONS,
    TAU,
    ChainWalkEnv,
    chain_walk_model,
    expected_discounted_return,
    optimal_policy,
)
from torch_api.basis import GaussianActionBasis  # noqa: E402
from torch_api.data import REWARD_KEY, collect_episodes  # noqa: E402
from torch_api.dispatch import run_chunks, split_trials, trial_seeds  # noqa: E402
from torch_api.iteration import ActivePolicyIteration  # noqa: E402
from torch_api.policies import LinearQPolicy  # noqa: E402
from torch_api.store import StoreError  # noqa: E402

SCHEDULES = {"decreasing": (5, 5, 3, 3, 3, 1, 1), "fixed": (3, 3, 3, 3, 3, 3, 3)}  # section 4.2
METHODS = {"AL": "active", "PL": "passive"}
MEASURES = ("test_return", "exact_return", "percent_optimal")
PER_TRIAL = (*MEASURES, "chosen", "sampling_rule", "j_mean")  # per-iteration lists over trials
_ROLE_REWARDED, _ROLE_REWARD_FREE, _ROLE_TEST = 1, 2, 3  # environment seed streams


def derived_seed(*parts: int) -> int:
    """A 31-bit seed derived deterministically from integers (distinct parts, distinct seeds)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0] >> 1)


def env_factory(run_seed: int, role: int, device: str = "cpu"):
    """``batch_size -> ChainWalkEnv`` with a seed of its own per role and batch size."""
    return lambda batch: ChainWalkEnv(
        batch_size=batch, seed=derived_seed(run_seed, role, batch), device=device
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
    best, _ = optimal_policy(P, R, GAMMA)
    best_probs = torch.nn.functional.one_hot(best, N_ACTIONS).to(torch.float64)
    optimum = expected_discounted_return(P, R, best_probs, model.initial, GAMMA, n)
    states = torch.arange(1, model.n_states + 1, dtype=torch.float64).unsqueeze(-1)
    discounts = GAMMA ** torch.arange(n, dtype=torch.float64, device=env.device)

    def evaluate(policy: LinearQPolicy, seed: int | None = None) -> dict:
        env.set_block_seeds(
            [derived_seed(g.initial_seed(), _ROLE_TEST) for g in policy.block_generators]
        )
        episodes = collect_episodes(env, policy, num_episodes=m, num_steps=n, rewarded=True)
        reward = episodes[REWARD_KEY].to(torch.float64) * episodes["mask"]  # [T, m, n]
        test_return = (reward * discounts).sum(-1).mean(-1)  # eq. 61, [T]
        table = policy.action_probs(states.expand(trials, *states.shape))  # [T, S, A]
        exact = expected_discounted_return(P, R, table, model.initial, GAMMA, n)  # [T]
        return {
            "test_return": test_return.tolist(),
            "exact_return": exact.tolist(),
            "percent_optimal": (100.0 * exact / optimum).tolist(),
        }

    return evaluate, float(optimum)


@dataclass
class Chunk:
    """Some trials of one run (a schedule and a method), to be run as one batch."""

    args: Args
    schedule: tuple[int, ...]
    mode: str
    run_seed: int
    trials: list[int]
    """indices t of the run's trials in this chunk"""
    store: Path
    """where the chunk's run is stored"""
    progress: bool = True


def store_name(schedule: str, method: str, chunk: int, chunks: int) -> str:
    """``<schedule>_<method>.db``, or ``..._chunk<c>of<C>.db`` (c = 1 … C) if C > 1."""
    suffix = "" if chunks == 1 else f"_chunk{chunk + 1}of{chunks}"
    return f"{schedule}_{method}{suffix}.db"


def run_chunk(chunk: Chunk) -> dict:
    """One batched run of Algorithm 1 on a chunk of trials; per-iteration, per-trial records."""
    args, run_seed = chunk.args, chunk.run_seed
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2)
    evaluate, optimum = make_evaluator(args, len(chunk.trials))
    api = ActivePolicyIteration(
        env=env_factory(run_seed, _ROLE_REWARDED, args.device),
        reward_free_env=env_factory(run_seed, _ROLE_REWARD_FREE, args.device),
        basis=basis,
        schedule=chunk.schedule,
        num_steps=args.steps,
        gamma=GAMMA,
        mode=chunk.mode,
        lam=args.lam,
        num_repeats=args.repeats,
        psi_mode="grouped",
        tie_break=args.tie_break,
        evaluate=evaluate,
        num_trials=len(chunk.trials),
        seed=run_seed,
        trial_seeds=trial_seeds(run_seed, chunk.trials),  # trial t's seed: (run seed, t) only
        keep_reward_free=False,  # T·Z·K·ΣM reward-free episodes are not needed afterwards
        device=args.device,
        checkpoint_path=chunk.store,
        resume=args.resume,
        overwrite=args.overwrite,
    )
    if api.resumed:
        print(f"resumed {chunk.store} at iteration {api.iteration}/{len(chunk.schedule)}")
    elif args.resume:
        print(f"nothing stored in {chunk.store}: starting it fresh")
    first = api.initial_policy().with_streams(  # pi_1, with streams of its own
        [torch.Generator().manual_seed(s) for s in api.block_seeds(0, "evaluation")]
    )
    initial = evaluate(first)  # pi_1, iteration 0
    started = time.perf_counter()
    history = api.run(progress=chunk.progress)
    seconds = time.perf_counter() - started
    return {
        "mode": chunk.mode,
        "seed": run_seed,
        "seconds": seconds,
        "optimal_exact_return": optimum,
        "iterations": [{"iteration": 0, "episodes_bought": 0, "rewarded_transitions": 0, **initial}]
        + [rec.row() for rec in history],
    }


def concatenate_chunks(parts: list[dict]) -> dict:
    """The chunks of one run as one run: per-trial lists concatenated, seconds summed."""
    run = {**parts[0], "seconds": sum(p["seconds"] for p in parts), "iterations": []}
    for its in zip(*(p["iterations"] for p in parts), strict=True):
        it = dict(its[0])
        for key in PER_TRIAL:
            if it.get(key) is not None:
                it[key] = [x for part in its for x in part[key]]
        if "seconds" in it:
            it["seconds"] = sum(part["seconds"] for part in its)
        run["iterations"].append(it)
    return run


def mean_se(values) -> tuple[float, float]:
    """Mean and standard error of the mean."""
    x = np.asarray(values, dtype=np.float64)
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size))


def paired_tests(runs: dict) -> dict:
    """Two-tailed paired t-test of AL vs PL at the last iteration, on each measure.

    ``t`` and ``p`` are None where the test is undefined: every pair identical (AL chose pi_l
    itself in every iteration of every trial, so the paired runs bought the same episodes).
    """
    al, pl = runs["AL"]["iterations"][-1], runs["PL"]["iterations"][-1]
    out = {}
    for measure in ("test_return", "exact_return"):
        a, p = np.asarray(al[measure]), np.asarray(pl[measure])
        test = None if np.all(a - p == (a - p)[0]) else scipy.stats.ttest_rel(a, p)
        out[measure] = {
            "iteration": al["iteration"],
            "mean_difference": float((a - p).mean()),
            "t": None if test is None else float(test.statistic),
            "p": None if test is None else float(test.pvalue),
            "al_better_share": float((a > p).mean()),
            "al_worse_share": float((a < p).mean()),
        }
    return out


def write_csv(results: dict, path: Path) -> None:
    """One row per schedule × method × iteration × trial."""
    num_candidates = None
    rows = []
    for name, res in results.items():
        for method, run in res["runs"].items():
            for it in run["iterations"]:
                for t in range(len(it["test_return"])):
                    j_mean = it.get("j_mean")
                    if j_mean is not None:
                        num_candidates = len(j_mean[t])
                    rows.append(
                        {
                            "schedule": name,
                            "method": method,
                            "iteration": it["iteration"],
                            "trial": t,
                            "episodes_bought": it["episodes_bought"],
                            "rewarded_transitions": it["rewarded_transitions"],
                            "chosen": it["chosen"][t] if "chosen" in it else "",
                            "sampling_rule": (
                                it["sampling_rule"][t] if "sampling_rule" in it else ""
                            ),
                            **{m: it[m][t] for m in MEASURES},
                            "j_mean": j_mean[t] if j_mean is not None else None,
                        }
                    )
    j_cols = [f"j_mean_k{k + 1}" for k in range(num_candidates or 0)]
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        header = [c for c in rows[0] if c != "j_mean"] + j_cols
        writer.writerow(header)
        for row in rows:
            j_mean = row.pop("j_mean")
            writer.writerow(
                [*row.values(), *(j_mean if j_mean is not None else [""] * len(j_cols))]
            )


def plot(results: dict, path: Path) -> None:
    """Figure 8: both performance measures of pi_{l+1} against iterations.

    Error bars are the standard error of the mean over the T trials; one colour per method,
    one line style per schedule; the optimal policy's value is a horizontal line.
    """
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    panels = (
        ("test_return", "eq. 61: discounted return of 50 test episodes"),
        ("percent_optimal", "exact expected return, % of the optimal policy"),
    )
    styles = {"decreasing": "-", "fixed": "--"}
    colours = {"AL": "tab:red", "PL": "tab:blue"}
    first_run = next(iter(results.values()))["runs"]["AL"]
    trials = len(first_run["iterations"][0]["test_return"])
    optimum = {"test_return": first_run["optimal_exact_return"], "percent_optimal": 100.0}
    for ax, (measure, label) in zip(axes, panels, strict=True):
        for name, res in results.items():
            for method, run in res["runs"].items():
                its = run["iterations"]
                stats = np.array([mean_se(it[measure]) for it in its])
                x = np.array([it["iteration"] for it in its]) + (0.06 if method == "PL" else 0.0)
                ax.errorbar(
                    x,
                    stats[:, 0],
                    yerr=stats[:, 1],
                    linestyle=styles.get(name, "-"),
                    color=colours[method],
                    marker="o",
                    markersize=3,
                    capsize=3,
                    label=f"{method}, {name}",
                )
        ax.axhline(optimum[measure], color="green", linewidth=1)
        ax.text(0, optimum[measure], "optimal policy", va="top", fontsize=7, color="green")
        ax.set_xticks(sorted({it["iteration"] for it in first_run["iterations"]}))
        ax.set_xlabel("iteration l (0: the initial policy pi_1)")
        ax.set_ylabel(label)
        ax.set_title(f"mean ± s.e. of the mean over T = {trials} trials", fontsize=9)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_table(results: dict, args: Args, wall: float) -> None:
    trials = args.trials
    print(f"\nIterated chain walk: {trials} trials, mean ± s.e. over trials ({wall:.1f} s wall)")
    for measure, title in (
        ("test_return", "performance of pi_{l+1}, eq. 61 (50 test episodes of 50 steps)"),
        ("percent_optimal", "exact expected return of pi_{l+1}, % of the optimal policy"),
    ):
        print(f"\n{title}")
        iters = [it["iteration"] for it in next(iter(results.values()))["runs"]["AL"]["iterations"]]
        print(f"{'schedule':<11} {'method':<6} " + " ".join(f"{'l=' + str(i):>15}" for i in iters))
        for name, res in results.items():
            for method, run in res["runs"].items():
                cells = []
                for it in run["iterations"]:
                    m, se = mean_se(it[measure])
                    cells.append(
                        f"{m:8.4f}±{se:6.4f}"
                        if measure != "percent_optimal"
                        else f"{m:8.2f}±{se:6.2f}"
                    )
                print(f"{name:<11} {method:<6} " + " ".join(f"{c:>15}" for c in cells))
    print(f"\nPaired two-tailed t-test, AL vs PL at iteration {args.iterations} ({trials} pairs)")
    print(
        f"{'schedule':<11} {'measure':<13} {'mean(AL-PL)':>12} {'t':>8} {'p':>10} "
        f"{'AL>PL':>6} {'AL<PL':>6}"
    )
    for name, res in results.items():
        for measure, t in res["t_tests"].items():
            stat = "undefined" if t["t"] is None else f"{t['t']:8.3f} {t['p']:10.3g}"
            print(
                f"{name:<11} {measure:<13} {t['mean_difference']:12.5f} {stat:>19} "
                f"{t['al_better_share']:6.2f} {t['al_worse_share']:6.2f}"
            )


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = list(SCHEDULES) if args.schedule == "both" else [args.schedule]
    jobs = [(name, method) for name in names for method in METHODS]
    stores = [
        out / "checkpoints" / store_name(name, method, c, args.chunks)
        for name, method in jobs
        for c in range(args.chunks)
    ]
    if (why := stored_runs_error(stores, args.resume, args.overwrite)) is not None:
        raise SystemExit(f"error: {why}")
    try:
        with raise_on_signals():
            return run_all(args, out, names, jobs)
    except Interrupted as interrupt:
        exit_interrupted(interrupt.signum, stores, out / "checkpoints")
    except StoreError as error:
        exit_store_error(error)


def run_all(args: Args, out: Path, names: list[str], jobs: list[tuple[str, str]]) -> dict:
    """Every run (chunks where asked), then the table, the files and the figure."""
    started = time.perf_counter()
    chunks = [
        Chunk(
            args=args,
            schedule=SCHEDULES[name][: args.iterations],
            mode=METHODS[method],
            run_seed=1000 * args.seed + 100 * list(SCHEDULES).index(name),  # AL, PL: paired
            trials=list(trials),
            store=out / "checkpoints" / store_name(name, method, c, args.chunks),
            progress=args.backend == "local",
        )
        for name, method in jobs
        for c, trials in enumerate(split_trials(args.trials, args.chunks))
    ]
    print(f"{len(chunks)} chunks of about {args.trials // args.chunks} trials ({args.backend})")
    parts = run_chunks(
        run_chunk,
        chunks,
        backend=args.backend,
        workers=args.workers or None,
        address=args.ray_address or None,
        num_cpus=args.ray_cpus or None,
    )
    results = {}
    for j, (name, method) in enumerate(jobs):
        entry = results.setdefault(
            name, {"schedule": list(SCHEDULES[name][: args.iterations]), "runs": {}}
        )
        entry["runs"][method] = concatenate_chunks(parts[j * args.chunks : (j + 1) * args.chunks])
    for res in results.values():
        res["t_tests"] = paired_tests(res["runs"])
    wall = time.perf_counter() - started

    print_table(results, args, wall)
    payload = {"args": dataclasses.asdict(args), "wall_seconds": wall, "results": results}
    (out / "chain_walk_api.json").write_text(json.dumps(payload))
    write_csv(results, out / "chain_walk_api.csv")
    plot(results, out / "fig8_performance.png")
    logger = make_logger(args.logger, out, "chain_walk_api")
    for name, res in results.items():
        for method, run in res["runs"].items():
            for it in run["iterations"]:
                curves = {k: it[k] for k in (*MEASURES, "rewarded_transitions")}
                log_means(logger, f"{name}/{method}", it["iteration"], curves)
    print(f"wrote {out}/chain_walk_api.json, chain_walk_api.csv and fig8_performance.png")
    return payload


if __name__ == "__main__":
    main()
