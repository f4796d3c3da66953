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

Defaults (about a minute on 2 CPU cores): 8 trials, the decreasing schedule, all 7 iterations.

    python examples/train_batting.py

The paper's full experiment (500 trials, both schedules). Measured at 8, 20 and 40 trials, a
trial of one schedule costs about 5.4 CPU-seconds (most of it MuJoCo rollouts: 980 reward-free,
49 rewarded and 280 test episodes) and about 31 MB of peak memory, so expect about 1.5 hours on
2 uncontended cores and a peak of about 16 GB:

    python examples/train_batting.py --trials 500 --schedule both

Rewarded episodes are expensive, so every run is checkpointed after each batch of rewarded
episodes and after each iteration (``<out-dir>/checkpoints/<schedule>_<mode>.pt``). After an
interruption, the same command with ``--resume`` continues every run from its checkpoint without
buying its rewarded episodes again; completed runs are not recomputed. Physics is MuJoCo on the
CPU; ``--device cuda`` moves the algebra (psi_hat, J, the solves) to the GPU.

Testing aid: ``--stop-after-checkpoints K`` ends the process abruptly (``os._exit(3)``, no
cleanup) right after the K-th checkpoint of this invocation is written, to simulate an
interruption (from a fresh start, odd K stops just after rewarded episodes were bought, even K
after an iteration).

Note: θ_0 = 1 gives both actions the same Q̂_0, the tie goes to action 0 (cock the arm), so pi_1
cocks with probability 0.925 per step and hits the ball in about 0.1 % of episodes (ε = 0.3: about
1.4 %). Many PL trials therefore never see a reward, θ stays 0 and their performance stays 0.
"""

from __future__ import annotations

import argparse
import ast
import csv
import dataclasses
import inspect
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
import torch  # noqa: E402

from envs.batting import MAX_STEPS, N_ACTIONS, BattingEnv  # noqa: E402
from torch_api.basis import GaussianActionBasis  # noqa: E402
from torch_api.data import REWARD_KEY, collect_episodes  # noqa: E402
from torch_api.iteration import ActivePolicyIteration  # noqa: E402
from torch_api.policies import LinearQPolicy  # noqa: E402

SCHEDULES = {"decreasing": (10, 10, 7, 7, 7, 4, 4), "fixed": (7,) * 7}  # M_l, l = 1 … 7
MODES = {"active": "AL", "passive": "PL"}
TAU = 3 * math.pi / 2  # kernel width τ (rad)
GAMMA = 1.0  # discount γ
TEST_EPISODES = 20  # test episodes per trial behind one performance value (eq. 68)
CENTER_GRID = (  # per state dimension: phi1 (rad), phi1_dot (rad/s), phi2 (rad), phi2_dot (rad/s)
    (0.0, math.pi / 4),
    (-math.pi, 0.0, math.pi),
    (-math.pi / 4, 0.0, math.pi / 4),
    (-math.pi, 0.0, math.pi),
)


@dataclass
class Args:
    """Command-line arguments of the batting experiment."""

    trials: int = 8
    """T, independent trials, all run as one batch (the paper: 500)"""
    schedule: str = "decreasing"
    """rewarded-episode schedule: decreasing (10,10,7,7,7,4,4), fixed (7 x 7) or both"""
    iterations: int = 7
    """how many of the schedule's L = 7 iterations to run"""
    episodes: int = 0
    """if > 0, M_l of every iteration (replaces the schedule's numbers)"""
    repeats: int = 5
    """Z, J-values averaged into J'"""
    lam: float = 1e-3
    """λ, ridge regularisation"""
    seed: int = 0
    """seed of the runs (AL and PL share it: paired rewarded and test environments)"""
    device: str = "cpu"
    """where the algebra runs (cpu or cuda); physics is MuJoCo on the CPU"""
    out_dir: str = "results/train_batting"
    """where the JSON, CSV, figure and checkpoints go"""
    resume: bool = False
    """continue every run from its checkpoint in out_dir; completed runs are not recomputed"""
    stop_after_checkpoints: int = 0
    """testing aid: if > 0, exit abruptly (os._exit(3)) after this many checkpoints"""


def field_docs(cls) -> dict[str, str]:
    """The string literal under each field of a dataclass (for --help)."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    return {
        a.target.id: b.value.value
        for a, b in zip(body, body[1:], strict=False)
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr)
    }


def parse_args(argv=None) -> Args:
    docs = field_docs(Args)
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        epilog="defaults: 8 trials, decreasing schedule, 7 iterations (about a minute on 2 "
        "cores). The paper's run: --trials 500 --schedule both",
    )
    for field in dataclasses.fields(Args):
        flag = f"--{field.name.replace('_', '-')}"
        if field.type == "bool":
            parser.add_argument(flag, action="store_true", help=docs.get(field.name))
        else:
            kind = type(field.default)
            parser.add_argument(flag, type=kind, default=field.default, help=docs.get(field.name))
    args = Args(**vars(parser.parse_args(argv)))
    if args.schedule not in (*SCHEDULES, "both"):
        parser.error(f"--schedule must be decreasing, fixed or both, got {args.schedule!r}")
    if not 1 <= args.iterations <= 7:
        parser.error(f"--iterations must lie in 1..7, got {args.iterations}")
    if args.trials < 1 or args.repeats < 1 or args.episodes < 0:
        parser.error("--trials and --repeats must be >= 1 and --episodes >= 0")
    return args


def schedule_of(args: Args, name: str) -> list[int]:
    """M_l of the first ``args.iterations`` iterations of the named schedule."""
    base = SCHEDULES[name][: args.iterations]
    return [args.episodes] * len(base) if args.episodes else list(base)


def make_basis() -> GaussianActionBasis:
    """The paper's 54 Gaussian centres, τ = 3π/2, and a constant, per action (B = 110)."""
    grids = torch.meshgrid(*[torch.tensor(g) for g in CENTER_GRID], indexing="ij")
    centers = torch.stack([g.reshape(-1) for g in grids], dim=-1)  # [54, 4]
    return GaussianActionBasis(centers=centers, tau=TAU, num_actions=N_ACTIONS)


class TestPerformance:
    """Performance of a learned policy (eq. 68): Σ_m Σ_n r over 20 test episodes, per trial.

    The environment (T·20 arms) and the policy's sampling stream are both seeded from the seed
    the iteration loop passes, so a resumed run measures exactly what an uninterrupted one would.
    """

    def __init__(self, trials: int) -> None:
        self.trials = trials
        self.env: BattingEnv | None = None

    def __call__(self, policy: LinearQPolicy, seed: int) -> dict:
        if self.env is None:
            self.env = BattingEnv(batch_size=self.trials * TEST_EPISODES, seed=seed)
        self.env.set_seed(seed)
        tester = LinearQPolicy(
            basis=policy.basis,
            theta=policy.theta,
            epsilon=policy.epsilon,
            generator=torch.Generator().manual_seed(seed),
        )
        episodes = collect_episodes(
            self.env, tester, num_episodes=TEST_EPISODES, num_steps=MAX_STEPS, rewarded=True
        )  # [T, 20, N]
        reward = episodes[REWARD_KEY] * episodes["mask"]
        hits = (reward > 0).any(-1).double().mean(-1)
        return {"performance": reward.sum((-2, -1)).tolist(), "hit_share": hits.tolist()}


class CheckpointCounter:
    """Counts checkpoints written in this process; with a limit, ends it abruptly (testing aid)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.written = 0

    def saved(self) -> None:
        self.written += 1
        if self.limit and self.written >= self.limit:
            print(f"\n[testing aid] stopping abruptly after {self.written} checkpoints", flush=True)
            os._exit(3)


class InterruptibleRun(ActivePolicyIteration):
    """ActivePolicyIteration that reports every checkpoint it writes to a counter."""

    counter: CheckpointCounter | None = None

    def save(self, path) -> None:
        super().save(path)
        if self.counter is not None:
            self.counter.saved()


def make_run(args: Args, schedule: list[int], mode: str, path: Path, counter: CheckpointCounter):
    """One ActivePolicyIteration run of all trials, checkpointed to ``path``."""

    def env(batch: int) -> BattingEnv:
        return BattingEnv(batch_size=batch)  # re-seeded by the loop every iteration

    api = InterruptibleRun(
        env=env,
        reward_free_env=env,
        basis=make_basis(),
        schedule=schedule,
        num_steps=MAX_STEPS,
        gamma=GAMMA,
        mode=mode,
        lam=args.lam,
        num_repeats=args.repeats,
        psi_mode="single",
        evaluate=TestPerformance(args.trials),
        num_trials=args.trials,
        seed=args.seed,
        keep_reward_free=False,  # not needed later; keeps checkpoints small
        checkpoint_path=path,
        device=args.device,
    )
    api.counter = counter
    return api


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
    if len(al) < 2 or np.all(al == pl):
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


def plot(results: dict, path: Path) -> None:
    """Mean performance over iterations with standard-error bars (Figure 10)."""
    fig, ax = plt.subplots(figsize=(5.5, 4))
    colors = {"decreasing": "tab:blue", "fixed": "tab:red"}
    for name, res in results.items():
        for mode, style in (("active", "-"), ("passive", ":")):
            perf = np.asarray(res["runs"][mode]["performance"], dtype=np.float64)  # [L, T]
            stats = np.array([mean_se(row) for row in perf])
            ax.errorbar(
                np.arange(1, len(perf) + 1),
                stats[:, 0],
                yerr=np.nan_to_num(stats[:, 1]),
                linestyle=style,
                marker="o" if mode == "active" else "s",
                color=colors[name],
                capsize=3,
                label=f"{MODES[mode]} ({name})",
            )
    ax.set_xlabel("iteration l")
    ax.set_ylabel("performance: Σ carry over 20 test episodes (m)")
    ax.legend()
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
    counter = CheckpointCounter(args.stop_after_checkpoints)
    started = time.perf_counter()
    results = {}
    for name in names:
        schedule = schedule_of(args, name)
        runs = {}
        for mode in MODES:
            path = ckpt_dir / f"{name}_{mode}.pt"
            api = make_run(args, schedule, mode, path, counter)
            if args.resume and path.exists():
                api.load(path)
                print(f"resumed {path} at iteration {api.iteration}/{len(schedule)}")
            api.run(progress=True)
            runs[mode] = summarise(api.history, mode)
        test = paired_test(runs["active"]["performance"][-1], runs["passive"]["performance"][-1])
        results[name] = {"schedule": schedule, "runs": runs, "paired_t_test_last": test}
    wall = time.perf_counter() - started

    for name, res in results.items():
        print_table(name, res["schedule"], res["runs"], res["paired_t_test_last"], args.trials)
    payload = {
        "args": dataclasses.asdict(args),
        "wall_seconds": wall,
        "test_episodes": TEST_EPISODES,
        "results": results,
    }
    (out / "train_batting.json").write_text(json.dumps(payload))
    write_csv(results, out / "train_batting.csv")
    plot(results, out / "fig10_performance.png")
    print(f"\nwall time {wall:.1f} s; wrote {out}/train_batting.json, .csv, fig10_performance.png")
    return payload


if __name__ == "__main__":
    main()
