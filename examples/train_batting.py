"""Active vs passive policy iteration on the ball-batting robot (paper section 5, Figure 10).

For each schedule of rewarded episodes (``decreasing`` = 10, 10, 7, 7, 7, 4, 4 and ``fixed`` =
7 × 7), an AL run (``mode="active"``: the sampling policy of each iteration is chosen by J',
Algorithm 2) and a PL run (``mode="passive"``: the evaluation policy samples) are made with the
same seed (a paired design), each running all trials as one batched computation. After every
iteration l the performance of pi_{l+1} is measured per trial (eq. 68): the sum of the rewards of
20 test episodes of 10 steps. The script prints mean ± standard error per iteration, the rewards
bought, and a two-tailed paired t-test of AL vs PL at the last iteration; it writes
``train_batting.json`` (every trial's numbers), ``train_batting.csv`` (one row per schedule ×
method × iteration × trial) and ``fig10_performance.png``.

Paper settings: 54 Gaussian centres on {0, π/4} × {-π, 0, π} × {-π/4, 0, π/4} × {-π, 0, π},
τ = 3π/2, 2 actions (B = 110), γ = 1, psi_hat of the single transition, λ = 1e-3, Z = 5,
ε_l = 0.15 / l, candidates ε_l + (0, 0.15, 0.5, 0.85), θ_0 = 1, N = 10 steps.

Defaults (about a minute on 2 CPU cores): 32 trials, the decreasing schedule, all 7 iterations,
AL and PL, one process (MuJoCo steps its batch on every core). Its last lines say what it found:
AL and PL at l = 7 (mean ± standard error over the trials), their paired difference and t-test,
and the share of trials scoring 0. The figure (``fig10_performance.png``) shows the score per
iteration for each method (colour) and schedule (line style) with error bars of one standard
error of the mean over the trials, the reference optimum (the best open-loop action sequence,
examples/batting_reference.py) and the learner's ceiling with the paper's basis
(benchmarks/batting_ceiling.py) as horizontal lines, and, beside it, the paired difference
AL − PL per iteration.

    python examples/train_batting.py

The paper's full experiment (500 trials, both schedules): most of its time is MuJoCo rollouts
(per trial and schedule: 980 reward-free, 49 rewarded and 140 test episodes for AL). Chunks of
about 16 trials in one worker process per core (``--backend processes``) overlap one process's
physics with another's algebra and keep each batch in cache; it took 1085 s (18.1 min) on 2 idle
cores with ``--tie-break lowest`` (``benchmarks/bench_figure10.py`` measures it against its
physics floor); with ties split evenly pi_1 hits the ball in half of its episodes, so more impacts
are resolved finely and it takes longer (README, "The ball-batting robot"):

    python examples/train_batting.py --trials 500 --schedule both --backend processes --chunks 32

Chunks: ``--chunks C`` splits the trials of every run into C chunks, each one batched run;
``--backend processes`` runs them in a pool of ``--workers`` local processes, ``--backend ray``
as Ray tasks (``pip install -e ".[ray]"``; a
local Ray instance, or the cluster at ``--ray-address``); the chunks' results are concatenated
along the trial axis into the same JSON, CSV and figure. Trial t always has the seed
``derive_seed(seed, t, "trial")``, whatever the chunking, and ``BattingEnv.set_block_seeds``
gives every trial's arms noise streams of their own, so the chunked results equal the unchunked
ones (tested). (An environment without ``set_block_seeds`` would draw from one stream per chunk,
seeded from the chunk: an equally valid sample, but not the same numbers.)

    python examples/train_batting.py --trials 500 --schedule both --backend ray --chunks 16

Rewarded episodes are expensive, so every run is stored as it goes
(``<out-dir>/checkpoints/<schedule>_<mode>.db``, with ``_chunk<c>of<C>`` before ``.db`` when
chunked; an SQLite database, see ``torch_api/store.py``): each batch of rewarded episodes is
committed before the next is measured, and every iteration's result after it. A folder that
holds runs already is refused unless ``--resume`` (continue them) or ``--overwrite`` (discard
them) is given. SIGINT/SIGTERM (Ctrl-C) finish the commit in flight and end with one line naming
what is stored (exit 130/143). After an interruption or a kill, the same command with
``--resume`` continues every run from its store without buying its rewarded episodes again;
completed runs are not recomputed. Physics is MuJoCo on the CPU; ``--device cuda`` moves the
algebra (psi_hat, J, the solves) to the GPU.

Testing aid: ``--stop-after-checkpoints K`` ends the process abruptly (``os._exit(3)``, no
cleanup) right after the K-th commit of this invocation, to simulate an interruption (a run
commits its selection, then its rewarded episodes, then the iteration's result: from a fresh
start, K = 2 stops just after the first rewarded episodes were bought).

Ties: θ_0 = 1 gives both actions the same Q̂_0, and so does θ = 0 (a run that has seen no
reward yet). By default (``--tie-break uniform``) tied actions share the greedy mass equally, so
pi_1 is uniformly random (it hits the ball in about half of its episodes). With ``--tie-break
lowest`` the tie goes to action 0 (cock the arm): pi_1 cocks with probability 0.925 per step and
hits the ball in about 0.1 % of episodes, and a PL trial that sees no reward keeps θ = 0 and that
policy for ever.
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
    """Command-line arguments of the batting experiment."""

    trials: int = field(32, low=1)
    """T, independent trials, all run as one batch (the paper: 500)"""
    schedule: str = field("decreasing", choices=("decreasing", "fixed", "both"))
    """rewarded-episode schedule: decreasing (10,10,7,7,7,4,4), fixed (7 x 7) or both"""
    iterations: int = field(7, low=1, high=7)
    """how many of the schedule's L = 7 iterations to run"""
    episodes: int = field(0, low=0)
    """if > 0, M_l of every iteration (replaces the schedule's numbers)"""
    repeats: int = field(5, low=1)
    """Z, J-values averaged into J'"""
    lam: float = field(1e-3, above=0)
    """λ, ridge regularisation"""
    tie_break: str = field("uniform", choices=("uniform", "lowest"))
    """how ε-greedy policies share the greedy mass among tied actions: uniform (equal parts, so
    pi_1 of θ_0 = 1 is uniform) or lowest (all to action 0, 'cock')"""
    seed: int = 0
    """seed of the runs (AL and PL share it: paired rewarded and test environments)"""
    device: str = "cpu"
    """where the algebra runs (cpu, cuda or cuda:N); physics is MuJoCo on the CPU"""
    out_dir: str = "results/train_batting"
    """where the JSON, CSV, figure and checkpoints go"""
    resume: bool = False
    """continue every run stored in out_dir; completed runs are not recomputed (a missing run
    starts fresh)"""
    overwrite: bool = False
    """discard the runs stored in out_dir and start over"""
    stop_after_checkpoints: int = field(0, low=0)
    """testing aid: if > 0, exit abruptly (os._exit(3)) after this many checkpoints"""
    backend: str = field("local", choices=BACKENDS)
    """where the chunks of trials run: local (here, one after another), processes (a pool of
    local worker processes) or ray"""
    chunks: int = field(1, low=1)
    """C, chunks of trials per schedule and mode (each one batched run; results concatenated)"""
    workers: int = field(0, low=0)
    """processes backend: worker processes (0: one per CPU core)"""
    physics_audit: float = field(0.0, low=0.0, high=1.0)
    """fraction of physics rollouts to sample for replay (benchmarks/bench_figure10.py); the
    physics steps are counted either way"""
    ray_address: str = ""
    """Ray cluster to join (e.g. auto); empty starts a local Ray instance"""
    ray_cpus: int = field(0, low=0)
    """CPUs of a local Ray instance (0: all)"""
    logger: str = field("none", choices=LOGGERS)
    """also write the learning curves (means over trials) with a TorchRL logger under
    <out-dir>/logs: csv, tensorboard or wandb (the last two need their package)"""
    basis_widths: str = ""
    """beyond the paper: kernel widths per state dimension w1,w2,w3,w4 (rad, rad/s, rad,
    rad/s) of the paper's 54 centres instead of τ = 3π/2 for all, e.g. 0.785,3.14,0.785,3.14"""
    end_at_hit: bool = False
    """beyond the paper: episodes terminate at the first bat-ball contact (the ball is gone)"""
    fit: str = field("brm", choices=("brm", "lstd"))
    """how θ is fitted: brm (the paper: least squares of r on psi_hat) or lstd (beyond the paper:
    LSTD-Q, with AL's J of the same learner)"""


def parse_widths(text: str) -> list[float] | None:
    """``"w1,w2,w3,w4"`` -> four floats (None for ""); ValueError if not four positive numbers."""
    if not text:
        return None
    try:
        widths = [float(w) for w in text.split(",")]
    except ValueError:
        widths = []
    if len(widths) != 4 or not all(w > 0 for w in widths):
        raise ValueError(f"--basis-widths must be four positive numbers w1,w2,w3,w4, got {text!r}")
    return widths


def check(args: Args) -> str | None:
    if args.resume and args.overwrite:
        return "--resume and --overwrite exclude each other"
    try:
        parse_widths(args.basis_widths)
    except ValueError as error:
        return str(error)
    if args.chunks > args.trials:
        return f"--chunks must lie in 1..{args.trials} (--trials), got {args.chunks}"
    if args.backend != "local" and args.stop_after_checkpoints:
        return "--stop-after-checkpoints is a testing aid of --backend local"
    return None


def parse_args(argv=None) -> Args:
    return parse(
        Args,
        argv,
        description=first_line(__doc__),
        epilog="defaults: 32 trials, decreasing schedule, 7 iterations (about a minute on 2 "
        "cores). The paper's run: --trials 500 --schedule both --backend processes --chunks 32",
        check=check,
    )


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below

import csv  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
import zlib  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
import torch  # noqa: E402
from _physics_audit import PhysicsAudit  # noqa: E402

from envs.batting import (  # noqa: E402
    BASIS_TAU,
    MAX_STEPS,
    N_ACTIONS,
    BattingEnv,
    basis_centers,
)
from torch_api.basis import GaussianActionBasis  # noqa: E402
from torch_api.data import REWARD_KEY, collect_episodes  # noqa: E402
from torch_api.dispatch import (  # noqa: E402
    run_chunks,
    split_trials,
    threads_per_worker,
    trial_seeds,
)
from torch_api.iteration import ActivePolicyIteration, derive_seed  # noqa: E402
from torch_api.policies import LinearQPolicy  # noqa: E402
from torch_api.selector import SamplingPolicySelector  # noqa: E402
from torch_api.store import StoreError  # noqa: E402

SCHEDULES = {"decreasing": (10, 10, 7, 7, 7, 4, 4), "fixed": (7,) * 7}  # M_l, l = 1 … 7
MODES = {"active": "AL", "passive": "PL"}
PER_TRIAL = ("performance", "hit_share", "chosen", "sampling_epsilon", "j_prime")  # [L][T] lists
GAMMA = 1.0  # discount γ
TEST_EPISODES = 20  # test episodes per trial behind one performance value (eq. 68)
# Horizontal lines of the figure (scores of eq. 68, Σ carry over 20 episodes):
REFERENCE_OPTIMUM = 20 * 13.74  # the best open-loop sequence without noise, 13.74 m per episode
# (examples/batting_reference.py); the best LSPI score with the paper's basis on abundant
# random data (benchmarks/batting_ceiling.py; README "The learner's ceiling"):
PAPER_BASIS_CEILING = 199.9


def schedule_of(args: Args, name: str) -> list[int]:
    """M_l of the first ``args.iterations`` iterations of the named schedule."""
    base = SCHEDULES[name][: args.iterations]
    return [args.episodes] * len(base) if args.episodes else list(base)


class ScaledGaussianBasis(GaussianActionBasis):
    """Gaussian kernels with one width per state dimension: ``exp(-Σ_d (s_d - c_d)² / 2w_d²)``.

    The paper's kernel (eq. 64) on coordinates divided by the widths ``w [d]`` (τ = 1 there).
    """

    def __init__(self, *, centers: torch.Tensor, widths, num_actions: int) -> None:
        widths = torch.as_tensor(widths, dtype=torch.float64)
        super().__init__(
            centers=centers / widths.to(centers.dtype), tau=1.0, num_actions=num_actions
        )
        self.register_buffer("widths", widths)

    def kernels(self, obs: torch.Tensor) -> torch.Tensor:
        return super().kernels(obs / self.widths.to(device=obs.device, dtype=obs.dtype))


def make_basis(widths: list[float] | None = None) -> GaussianActionBasis:
    """The paper's 54 Gaussian centres, τ = 3π/2, and a constant, per action (B = 110); with
    ``widths``, the same centres with one kernel width per state dimension (beyond the paper)."""
    if widths is None:
        return GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=N_ACTIONS)
    return ScaledGaussianBasis(centers=basis_centers(), widths=widths, num_actions=N_ACTIONS)


class TestPerformance:
    """Performance of a learned policy (eq. 68): Σ_m Σ_n r over 20 test episodes, per trial.

    The loop hands pi_{l+1} with one sampling stream per trial, seeded from
    ``api.block_seeds(l, "evaluation")``. An environment with ``set_block_seeds`` gets one
    stream per trial too, seeded from the same per-trial seeds (a stream apart): trial t's
    performance then depends on (its seed, l) only. Otherwise the T·20 arms share one stream
    seeded from the ``seed`` the loop passes (derived from the run's seed and l). Either way a
    resumed run measures exactly what an uninterrupted one would.
    """

    def __init__(self, trials: int, make_env=BattingEnv) -> None:
        self.trials = trials
        self.make_env = make_env
        self.env: BattingEnv | None = None

    def __call__(self, policy: LinearQPolicy, seed: int) -> dict:
        if self.env is None:
            self.env = self.make_env(batch_size=self.trials * TEST_EPISODES, seed=seed)
        if hasattr(self.env, "set_block_seeds"):
            self.env.set_block_seeds(
                [derive_seed(g.initial_seed(), 0, "evaluation") for g in policy.block_generators]
            )
        else:
            self.env.set_seed(seed)
        episodes = collect_episodes(
            self.env, policy, num_episodes=TEST_EPISODES, num_steps=MAX_STEPS, rewarded=True
        )  # [T, 20, N]
        reward = episodes[REWARD_KEY] * episodes["mask"]
        hits = (reward > 0).any(-1).double().mean(-1)
        return {"performance": reward.sum((-2, -1)).tolist(), "hit_share": hits.tolist()}


class CheckpointCounter:
    """Counts commits made in this process; with a limit, ends it abruptly (testing aid)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.written = 0

    def saved(self, api: ActivePolicyIteration | None = None) -> None:
        """Count one commit (the run's ``on_checkpoint`` hook)."""
        self.written += 1
        if self.limit and self.written >= self.limit:
            print(f"\n[testing aid] stopping abruptly after {self.written} checkpoints", flush=True)
            os._exit(3)


@dataclass
class Chunk:
    """Some trials of one run (a schedule and a mode), run as one batch and checkpointed."""

    args: Args
    schedule: list[int]
    mode: str
    trials: list[int]
    """indices t of the run's trials in this chunk"""
    checkpoint: Path
    counter: CheckpointCounter
    progress: bool = True
    physics_threads: int | None = None
    """MuJoCo threads of the chunk's environments (None: every core)"""


def checkpoint_name(schedule: str, mode: str, chunk: int, chunks: int) -> str:
    """``<schedule>_<mode>.db``, or ``<schedule>_<mode>_chunk<c>of<C>.db`` (c = 1 … C) if C > 1."""
    suffix = "" if chunks == 1 else f"_chunk{chunk + 1}of{chunks}"
    return f"{schedule}_{mode}{suffix}.db"


def chunk_seed(seed: int, first_trial: int) -> int:
    """A 63-bit seed of the chunk starting at ``first_trial`` (distinct chunks, distinct seeds)."""
    return int(np.random.SeedSequence([seed, first_trial]).generate_state(1, np.uint64)[0] >> 1)


def make_run(chunk: Chunk, audit: PhysicsAudit | None = None) -> ActivePolicyIteration:
    """One ActivePolicyIteration run of the chunk's trials, checkpointed to ``chunk.checkpoint``.

    Trial t's seed is ``derive_seed(seed, t, "trial")`` in every chunking. The run's own seed
    (the environments' single stream where they lack ``set_block_seeds``) is ``--seed`` for the
    chunk holding trial 0 (an unchunked run) and derived from the chunk's first trial for the
    others, so no two chunks replay the same noise. Every environment counts its physics
    into ``audit``.
    """
    args = chunk.args

    def env(batch_size: int, seed: int | None = None) -> BattingEnv:
        # the rewarded and reward-free envs are re-seeded by the loop every iteration
        return BattingEnv(
            batch_size=batch_size,
            seed=seed,
            nthread=chunk.physics_threads,
            hook=audit,
            end_at_hit=args.end_at_hit,
        )

    first = chunk.trials[0]
    seed = args.seed if first == 0 else chunk_seed(args.seed, first)
    return ActivePolicyIteration(
        env=env,
        selector=SamplingPolicySelector(env=env, num_repeats=args.repeats)
        if chunk.mode == "active"
        else None,
        basis=make_basis(parse_widths(args.basis_widths)),
        schedule=chunk.schedule,
        num_steps=MAX_STEPS,
        gamma=GAMMA,
        lam=args.lam,
        psi_mode="single",
        fit=args.fit,
        tie_break=args.tie_break,
        evaluate=TestPerformance(len(chunk.trials), make_env=env),
        num_trials=len(chunk.trials),
        seed=seed,
        trial_seeds=trial_seeds(args.seed, chunk.trials),
        keep_reward_free=False,  # not needed later; keeps checkpoints small
        checkpoint_path=chunk.checkpoint,
        resume=args.resume,
        overwrite=args.overwrite,
        device=args.device,
        on_checkpoint=chunk.counter.saved,  # counts commits (--stop-after-checkpoints)
    )


def run_chunk(chunk: Chunk) -> dict:
    """Run (or resume, with ``--resume``) one chunk; its history as :func:`summarise` lists,
    plus ``"physics"``: the :class:`PhysicsAudit` of this invocation's physics steps."""
    # the audit's sampling stream: its own per chunk (keyed by the checkpoint's name)
    name_key = zlib.crc32(chunk.checkpoint.name.encode())
    audit_seed = int(np.random.SeedSequence([chunk.args.seed, name_key]).generate_state(1)[0])
    audit = PhysicsAudit(chunk.args.physics_audit, seed=audit_seed)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # also in worker processes
    api = make_run(chunk, audit)  # opens (and locks) the run's store, checked writable
    if api.resumed:
        print(f"resumed {chunk.checkpoint} at iteration {api.iteration}/{len(chunk.schedule)}")
    elif chunk.args.resume:
        print(f"nothing stored in {chunk.checkpoint}: starting it fresh")
    api.run(progress=chunk.progress)
    return summarise(api.history, chunk.mode) | {"physics": audit}


def concatenate_chunks(parts: list[dict]) -> dict:
    """The chunks of one run as one run: per-trial lists concatenated, seconds summed, physics
    audits merged."""
    run = dict(parts[0])
    run["physics"] = PhysicsAudit()
    for part in parts:
        run["physics"].merge(part["physics"])
    for key in PER_TRIAL:
        run[key] = [
            None if its[0] is None else [x for part in its for x in part]
            for its in zip(*(p[key] for p in parts), strict=True)
        ]
    run["seconds"] = [sum(s) for s in zip(*(p["seconds"] for p in parts), strict=True)]
    return run


def summarise(history: list, mode: str) -> dict:
    """One run's history as plain lists indexed [iteration][trial]."""
    return {
        "method": MODES[mode],
        "performance": [r.performance["performance"] for r in history],
        "hit_share": [r.performance["hit_share"] for r in history],
        "chosen": [r.chosen for r in history],
        "sampling_epsilon": [r.sampling_rule for r in history],
        "j_prime": [r.j_mean for r in history],
        "episodes_bought": [r.episodes_bought for r in history],
        "rewarded_transitions": [r.rewarded_transitions for r in history],
        "reward_free_transitions": [r.reward_free_transitions for r in history],
        "seconds": [r.seconds for r in history],
    }


def mean_se(values) -> tuple[float, float]:
    """Mean and standard error (nan with a single trial)."""
    x = np.asarray(values, dtype=np.float64)
    se = x.std(ddof=1) / math.sqrt(len(x)) if len(x) > 1 else math.nan
    return float(x.mean()), float(se)


def paired_test(al, pl) -> dict:
    """Two-tailed paired t-test of AL vs PL performance (None when undefined)."""
    al, pl = np.asarray(al, dtype=np.float64), np.asarray(pl, dtype=np.float64)
    if len(al) < 2 or np.all(al - pl == (al - pl)[0]):  # no spread in the differences
        return {"t": None, "p": None}
    res = scipy.stats.ttest_rel(al, pl)
    return {"t": float(res.statistic), "p": float(res.pvalue)}


def print_table(name: str, schedule: list[int], runs: dict, test: dict, trials: int) -> None:
    al, pl = runs["active"], runs["passive"]
    print(f"\nschedule {name} (M_l = {schedule}), {trials} trials, performance (eq. 68) mean ± se")
    print(
        f"{'l':>2} {'M_l':>4} {'AL':>17} {'PL':>17} {'bought/trial':>13} {'bought total':>13} "
        f"{'AL choices (k=1..4)':>20}"
    )
    for i, m in enumerate(schedule):
        a, pa = mean_se(al["performance"][i])
        p, pp = mean_se(pl["performance"][i])
        per_trial = al["rewarded_transitions"][i]
        choices = np.bincount(np.asarray(al["chosen"][i]), minlength=4)
        print(
            f"{i + 1:>2} {m:>4} {a:8.2f} ± {pa:6.2f} {p:8.2f} ± {pp:6.2f} {per_trial:>13} "
            f"{per_trial * trials:>13} {' '.join(str(c) for c in choices):>20}"
        )
    last = f"paired t-test AL vs PL at iteration {len(schedule)}:"
    if test["t"] is None:
        print(f"{last} undefined (fewer than 2 trials or identical results)")
    else:
        print(f"{last} t = {test['t']:.3f}, p = {test['p']:.4f} (two-tailed)")


def print_findings(results: dict, args: Args) -> None:
    """The last lines: what this run found, and how to run the paper-size experiment."""
    print(
        f"\nFound ({args.trials} trials, paired seeds, score of eq. 68 at l = {args.iterations}; "
        f"reference optimum {REFERENCE_OPTIMUM:.0f}, "
        f"paper-basis ceiling {PAPER_BASIS_CEILING:.0f}):"
    )
    for name, res in results.items():
        al, pl = (np.asarray(res["runs"][m]["performance"][-1]) for m in MODES)
        (a, a_se), (p, p_se), (d, d_se) = mean_se(al), mean_se(pl), mean_se(al - pl)
        test = res["paired_t_test_last"]
        if test["p"] is None:
            verdict = "the paired t-test is undefined (no spread in the differences)"
        else:
            verdict = (
                f"{'AL' if d > 0 else 'PL'} better at the 5 % level"
                if test["p"] < 0.05
                else "no difference at the 5 % level"
            )
            verdict += f" (t = {test['t']:.2f}, p = {test['p']:.3g})"
        print(
            f"  {name}: AL {a:.1f} ± {a_se:.1f}, PL {p:.1f} ± {p_se:.1f} (s.e. over trials); "
            f"AL − PL {d:+.1f} ± {d_se:.1f}: {verdict}; trials scoring 0: AL "
            f"{(al == 0).mean():.0%}, PL {(pl == 0).mean():.0%}"
        )
    print("The paper-size experiment (500 trials, both schedules; see README for its wall time):")
    print(
        "  python examples/train_batting.py --trials 500 --schedule both --backend processes "
        "--chunks 32"
    )


def plot(results: dict, path: Path) -> None:
    """Figure 10: performance per iteration (left) and the paired difference AL − PL (right).

    Error bars are the standard error of the mean over the T trials. One colour per method,
    one line style per schedule; the reference optimum and the learner's measured ceiling
    with the paper's basis are horizontal lines.
    """
    fig, (ax, diff_ax) = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = {"active": "tab:red", "passive": "tab:blue"}
    styles = {"decreasing": "-", "fixed": "--"}
    trials = None
    for name, res in results.items():
        runs = res["runs"]
        for mode in MODES:
            perf = np.asarray(runs[mode]["performance"], dtype=np.float64)  # [L, T]
            trials = perf.shape[1]
            stats = np.array([mean_se(row) for row in perf])
            ax.errorbar(
                np.arange(1, len(perf) + 1) + (0.05 if mode == "passive" else 0.0),
                stats[:, 0],
                yerr=np.nan_to_num(stats[:, 1]),
                linestyle=styles[name],
                marker="o",
                markersize=3,
                color=colours[mode],
                capsize=3,
                label=f"{MODES[mode]}, {name}",
            )
        diff = np.asarray(runs["active"]["performance"]) - np.asarray(
            runs["passive"]["performance"]
        )
        stats = np.array([mean_se(row) for row in diff])
        diff_ax.errorbar(
            np.arange(1, len(diff) + 1),
            stats[:, 0],
            yerr=np.nan_to_num(stats[:, 1]),
            linestyle=styles[name],
            marker="o",
            markersize=3,
            color="black",
            capsize=3,
            label=name,
        )
    ax.axhline(REFERENCE_OPTIMUM, color="green", linewidth=1)
    ax.text(
        1,
        REFERENCE_OPTIMUM,
        "reference optimum (best open-loop sequence)",
        va="bottom",
        fontsize=7,
        color="green",
    )
    ax.axhline(PAPER_BASIS_CEILING, color="gray", linewidth=1, linestyle="-.")
    ax.text(
        1,
        PAPER_BASIS_CEILING,
        "ceiling: LSPI, paper's basis, abundant random data",
        va="bottom",
        fontsize=7,
        color="gray",
    )
    ax.set_ylim(bottom=0, top=REFERENCE_OPTIMUM * 1.08)
    ax.set_xlabel("iteration l (performance of pi_{l+1})")
    ax.set_ylabel("Σ carry over 20 test episodes (m), eq. 68")
    ax.set_title(f"Figure 10: mean ± s.e. of the mean over T = {trials} trials", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    diff_ax.axhline(0.0, color="gray", linewidth=1)
    diff_ax.set_xlabel("iteration l")
    diff_ax.set_ylabel("AL − PL, same trial (paired), m")
    diff_ax.set_title(f"paired difference AL − PL: mean ± s.e. over T = {trials}", fontsize=9)
    diff_ax.legend(fontsize=7, title="schedule", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_csv(results: dict, path: Path) -> None:
    """One row per schedule × method × iteration × trial (chosen: candidate k = 1 … 4)."""
    columns = ["schedule", "method", "iteration", "trial", "performance", "hit_share", "chosen"]
    columns += ["sampling_epsilon", "rewarded_transitions", "j1", "j2", "j3", "j4"]
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        for name, res in results.items():
            for run in res["runs"].values():
                for i, perf in enumerate(run["performance"]):
                    for t, value in enumerate(perf):
                        j = run["j_prime"][i][t] if run["j_prime"][i] is not None else []
                        row = dict(zip(columns[9:], j, strict=False))
                        row |= {
                            "schedule": name,
                            "method": run["method"],
                            "iteration": i + 1,
                            "trial": t,
                            "performance": value,
                            "hit_share": run["hit_share"][i][t],
                            "chosen": run["chosen"][i][t] + 1,
                            "sampling_epsilon": run["sampling_epsilon"][i][t],
                            "rewarded_transitions": run["rewarded_transitions"][i],
                        }
                        writer.writerow(row)


def main(argv=None) -> dict:
    args = parse_args(argv)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # quiet storage-creation notices
    out = Path(args.out_dir)
    ckpt_dir = out / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    names = list(SCHEDULES) if args.schedule == "both" else [args.schedule]
    jobs = [(name, mode) for name in names for mode in MODES]
    pieces = split_trials(args.trials, args.chunks)
    stores = [
        ckpt_dir / checkpoint_name(name, mode, c, args.chunks)
        for name, mode in jobs
        for c in range(len(pieces))
    ]
    if (why := stored_runs_error(stores, args.resume, args.overwrite)) is not None:
        raise SystemExit(f"error: {why}")
    try:
        with raise_on_signals():
            return run_all(args, out, ckpt_dir, names, jobs, pieces)
    except Interrupted as interrupt:
        exit_interrupted(interrupt.signum, stores, ckpt_dir)
    except StoreError as error:
        exit_store_error(error)


def run_all(args: Args, out: Path, ckpt_dir: Path, names, jobs, pieces) -> dict:
    """Every run of the experiment (chunks where asked), then the tables, files and figure."""
    counter = CheckpointCounter(args.stop_after_checkpoints)
    started = time.perf_counter()
    # MuJoCo threads per chunk: every core in-process, the cores shared out among processes,
    # one per Ray task (Ray gives each task one CPU)
    physics_threads = {"local": None, "ray": 1}.get(
        args.backend, threads_per_worker(args.workers or os.cpu_count() or 1)
    )
    chunks = [
        Chunk(
            args=args,
            schedule=schedule_of(args, name),
            mode=mode,
            trials=list(trials),
            checkpoint=ckpt_dir / checkpoint_name(name, mode, c, args.chunks),
            counter=counter,
            progress=args.backend == "local",
            physics_threads=physics_threads,
        )
        for name, mode in jobs
        for c, trials in enumerate(pieces)
    ]
    parts = run_chunks(
        run_chunk,
        chunks,
        backend=args.backend,
        workers=args.workers or None,
        address=args.ray_address or None,
        num_cpus=args.ray_cpus or None,
    )
    results = {}
    for j, (name, mode) in enumerate(jobs):
        entry = results.setdefault(name, {"schedule": schedule_of(args, name), "runs": {}})
        entry["runs"][mode] = concatenate_chunks(parts[j * args.chunks : (j + 1) * args.chunks])
    audit = PhysicsAudit()
    for res in results.values():
        runs = res["runs"]
        for run in runs.values():
            physics = run.pop("physics")
            run["physics_steps"] = dict(physics.steps)
            audit.merge(physics)
        test = paired_test(runs["active"]["performance"][-1], runs["passive"]["performance"][-1])
        res["paired_t_test_last"] = test
    wall = time.perf_counter() - started

    for name, res in results.items():
        print_table(name, res["schedule"], res["runs"], res["paired_t_test_last"], args.trials)
    payload = {
        "args": dataclasses.asdict(args),
        "wall_seconds": wall,
        "test_episodes": TEST_EPISODES,
        "physics_steps": dict(audit.steps),
        "results": results,
    }
    (out / "train_batting.json").write_text(json.dumps(payload))
    payload["physics_audit"] = audit  # for benchmarks/bench_figure10.py; not in the JSON
    write_csv(results, out / "train_batting.csv")
    plot(results, out / "fig10_performance.png")
    logger = make_logger(args.logger, out, "train_batting")
    for name, res in results.items():
        for run in res["runs"].values():
            for i, perf in enumerate(run["performance"]):
                curves = {"performance": perf, "hit_share": run["hit_share"][i]}
                curves["rewarded_transitions"] = run["rewarded_transitions"][i]
                log_means(logger, f"{name}/{run['method']}", i + 1, curves)
    steps = audit.steps
    print(f"\nphysics: {steps['coarse']:,} coarse + {steps['fine']:,} fine MuJoCo steps")
    print(f"wall time {wall:.1f} s; wrote {out}/train_batting.json, .csv, fig10_performance.png")
    print_findings(results, args)
    return payload


if __name__ == "__main__":
    main()
