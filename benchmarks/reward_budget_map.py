"""Where active learning pays: AL − PL against the rewarded and the reward-free budget.

Each cell of the map is a paired experiment (``torch_api.experiment``: AL and PL on the same
trial seeds) on one task with a fixed-length schedule of M rewarded episodes in every
iteration, Z repeats of J and R reward-free episodes per candidate and repeat (R = M: the
paper's), and optionally one lever beyond the paper (``flattening="iwcv"``):

- the chain walk (``envs.chain_walk``, paper section 4.2): the exact expected return of
  pi_{L+1} (``exact_return``), L = 7, N = 10;
- the ball-batting arm (``envs.batting``, paper section 5): Σ carry over 20 test episodes
  (``performance``), L = 7, N = 10;
- CartPole-v1 and Acrobot-v1 (beyond the paper, ``benchmarks/_budget_map_gym.py``): the greedy
  test return of θ_L (``greedy_test_return``), the CartPole showcase's settings (a quadratic
  Q̂ per action, LSTD-Q, γ = 0.95, ν = 0: their cells' ν = 0 is the task's own, not a lever).

Trials are sized from a pilot: a cell first runs ``--pilot`` trials (``--gym-pilot`` on
CartPole and Acrobot); with σ_d the spread of the paired differences there, it is rerun with
n = ⌈((z_0.975 + z_0.8) σ_d / δ)²⌉ trials (between the pilot's and the task's cap), so that a
difference δ would be found with 80 % power by the paired two-tailed t-test at α = 0.05. δ is
``--effect`` times the gap between PL and the optimum (the chain walk: its exact optimum;
CartPole, Acrobot: a solved policy's return) or times PL's score (the batting arm: no optimum
is known). Trial t's seed depends on (the run's seed, t) only, so the n trials hold the
pilot's. Every cell records its trials, AL − PL with its 95 % interval and p, the difference
detectable with 80 % power at its n, and the cost: each method's seconds and reward-free
transitions. Cells are stored as they finish in ``--out-dir`` (a rerun skips them), then the
data file and the figure are written::

    python benchmarks/reward_budget_map.py --tasks all \\
        --out docs/results/data/reward_budget_map.json --figure docs/results/reward_budget_map.png
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.stats
import torch
import tyro

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / d) for d in ("examples", "")]
import chain_walk_api as chain  # noqa: E402  (the chain walk's env, basis and evaluation)
import train_batting as batting  # noqa: E402  (the batting arm's basis and evaluation)

from benchmarks import _budget_map_gym as gym_tasks  # noqa: E402
from benchmarks._budget_map_figure import MEASURE, data_file, plot  # noqa: E402
from benchmarks.summarize import paired_difference, verdict  # noqa: E402
from envs.batting import MAX_STEPS, BattingEnv  # noqa: E402
from envs.chain_walk import CENTERS, TAU  # noqa: E402
from envs.chain_walk.model import GAMMA  # noqa: E402
from torch_api import GaussianActionBasis, RunSpec, SamplingPolicySelector  # noqa: E402
from torch_api import experiment as ex  # noqa: E402
from torch_api.runs.files import write_text_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TASKS = {"both": ["chain", "batting"], "gym": ["cartpole", "acrobot"]}
TASKS["all"] = TASKS["both"] + TASKS["gym"]
OWN_NU = {"cartpole": gym_tasks.NU, "acrobot": gym_tasks.NU}  # a task's own ν (else 1: the paper's)
Z_POWER = float(scipy.stats.norm.ppf(0.975) + scipy.stats.norm.ppf(0.8))  # α = 0.05, 80 % power


@dataclass(frozen=True)
class Cell:
    """One setting of the map: a task, M, R (None: M), Z and the lever."""

    task: str
    episodes: int
    """M, rewarded episodes in each of the L iterations"""
    reward_free: int | None = None
    """R, reward-free episodes per candidate and repeat (None: M, the paper's)"""
    repeats: int = 5
    """Z"""
    flattening: float | str = 1.0
    """ν (1: the paper's) or "iwcv" (beyond the paper)"""
    iterations: int = 7
    """L"""

    @property
    def name(self) -> str:
        r = "M" if self.reward_free is None else str(self.reward_free)
        nu = "" if self.flattening == OWN_NU.get(self.task, 1.0) else f"_nu{self.flattening}"
        return f"{self.task}_M{self.episodes}_R{r}_Z{self.repeats}{nu}_L{self.iterations}"

    @property
    def axis(self) -> str:
        """What the cell varies: the rewarded budget, the reward-free one, or a lever."""
        if self.flattening != OWN_NU.get(self.task, 1.0):
            return "lever"
        return "rewarded" if self.reward_free is None and self.repeats == 5 else "reward_free"


@dataclass(frozen=True)
class RunArgs:
    """What a chunk's run needs: the cell, its trials and the seed (picklable)."""

    cell: Cell
    trials: int
    seed: int


@dataclass
class Args:
    """The reward-budget map: AL − PL against M and the reward-free budget, per task."""

    tasks: Literal["chain", "batting", "cartpole", "acrobot", "both", "gym", "all"] = "both"
    """which tasks' cells to run (both: chain and batting; gym: CartPole and Acrobot)"""
    chain_episodes: tuple[int, ...] = (1, 2, 5, 10)
    """M of the chain walk's rewarded-budget cells"""
    batting_episodes: tuple[int, ...] = (1, 5)
    """M of the batting arm's rewarded-budget cells"""
    chain_reward_free: tuple[tuple[int, int, int], ...] = (
        (2, 1, 5), (2, 10, 5), (2, 2, 1), (1, 5, 5), (1, 1, 1)
    )  # fmt: skip
    """the chain walk's reward-budget cells (M, R, Z); R = M, Z = 5 is a rewarded-budget cell"""
    batting_reward_free: tuple[tuple[int, int, int], ...] = ((5, 1, 5),)
    """the batting arm's reward-budget cells (M, R, Z)"""
    cartpole_episodes: tuple[int, ...] = (1, 4)
    """M of CartPole's rewarded-budget cells"""
    acrobot_episodes: tuple[int, ...] = (2,)
    """M of Acrobot's rewarded-budget cells"""
    cartpole_reward_free: tuple[tuple[int, int, int], ...] = ((4, 1, 1),)
    """CartPole's reward-budget cells (M, R, Z)"""
    acrobot_reward_free: tuple[tuple[int, int, int], ...] = ()
    """Acrobot's reward-budget cells (M, R, Z)"""
    levers: tuple[tuple[str, int], ...] = (("chain", 1), ("batting", 1))
    """(task, M) cells run with flattening="iwcv" (beyond the paper)"""
    iterations: int = 7
    """L, iterations of every cell"""
    pilot: int = 100
    """trials of each cell's pilot"""
    chain_cap: int = 4000
    """most trials of a chain-walk cell"""
    batting_cap: int = 200
    """most trials of a batting cell"""
    gym_pilot: int = 20
    """trials of a CartPole or Acrobot cell's pilot (at most its cap; --pilot: the others')"""
    cartpole_cap: int = 60
    """most trials of a CartPole cell"""
    acrobot_cap: int = 20
    """most trials of an Acrobot cell"""
    effect: float = 0.25
    """δ: this share of the PL-vs-optimum gap (chain walk) or of PL's score (batting)"""
    seed: int = 0
    """the runs' seed (every cell's AL and PL share it: a paired design)"""
    out_dir: str = "results/reward_budget_map"
    """where each cell's runs and result are stored as they go"""
    out: str = ""
    """the data file to write (docs/results/data/reward_budget_map.json), or empty"""
    figure: str = ""
    """the figure to write (docs/results/reward_budget_map.png), or empty"""


def cells(args: Args) -> list[Cell]:
    """Every cell asked for, the rewarded-budget ones first, without repeats."""
    L, made = args.iterations, []
    for task in TASKS.get(args.tasks, [args.tasks]):
        nu = OWN_NU.get(task, 1.0)
        made += [Cell(task, m, flattening=nu, iterations=L) for m in vars(args)[f"{task}_episodes"]]
        for m, r, z in vars(args)[f"{task}_reward_free"]:
            cell = Cell(task, m, reward_free=r, repeats=z, flattening=nu, iterations=L)
            made.append(Cell(task, m, flattening=nu, iterations=L) if r == m and z == 5 else cell)
        made += [Cell(t, m, flattening="iwcv", iterations=L) for t, m in args.levers if t == task]
    return list(dict.fromkeys(made))


# -- one chunk's run of a cell ---------------------------------------------------------------


def spec_of(cell: Cell, trials: int, seed: int) -> RunSpec:
    """The cell's settings (AL's; PL drops the selection), checked when made."""
    common = dict(
        schedule=(cell.episodes,) * cell.iterations,
        num_trials=trials,
        seed=seed,
        num_repeats=cell.repeats,
        reward_free_episodes=cell.reward_free,
        flattening=cell.flattening,
        keep_reward_free=False,
    )
    if cell.task == "chain":
        return RunSpec.of(num_steps=10, gamma=GAMMA, psi_mode="grouped", **common)
    if cell.task in gym_tasks.TASKS:
        return gym_tasks.spec_of(cell.task, common)
    return RunSpec.of(num_steps=MAX_STEPS, gamma=1.0, psi_mode="single", **common)


def run_chunk(chunk: ex.Chunk) -> dict:
    """One chunk's run of the cell's AL or PL (``chunk.args``: a :class:`RunArgs`)."""
    cell, seed, trials = chunk.args.cell, chunk.seed, len(chunk.trials)
    if cell.task in gym_tasks.TASKS:
        return gym_tasks.run_chunk_gym(chunk, spec_of(cell, trials, seed), ex)
    spec = spec_of(cell, trials, seed)
    if cell.task == "chain":
        basis = GaussianActionBasis(
            centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2
        )
        evaluate = chain.make_evaluator(chain.Args(trials=trials), trials)
        selector = SamplingPolicySelector(
            env=chain.env_factory(seed, chain.ROLE_REWARD_FREE, "cpu")
        )
        env = chain.env_factory(seed, chain.ROLE_REWARDED, "cpu")
        api = ex.make_iteration(
            chunk, spec, env=env, selector=selector, basis=basis, evaluate=evaluate
        )
        return ex.run_iterations(chunk, api)

    def env(batch_size: int, seed: int | None = None) -> BattingEnv:
        return BattingEnv(batch_size=batch_size, seed=seed, nthread=1)

    evaluate = batting.make_evaluator(trials, env)
    api = ex.make_iteration(chunk, spec, env=env, basis=batting.make_basis(), evaluate=evaluate)
    return ex.run_iterations(chunk, api)


def run_cell(cell: Cell, trials: int, seed: int, out: Path) -> dict:
    """AL and PL of ``cell`` on ``trials`` paired trials (stored runs resumed), summarised."""
    folder = out / "runs" / f"{cell.name}_T{trials}"
    execution = ex.Execution(out_dir=str(folder), resume=True, backend="local", threads=1)
    experiment = ex.Experiment(
        name="reward_budget_map",
        schedules={"fixed": (cell.episodes,) * cell.iterations},
        run_chunk=run_chunk,
        t_tests=(MEASURE[cell.task],),
        report=lambda results, wall: {"results": results, "wall": wall},
        trials=trials,
        seed=seed,
    )
    done = ex.run_experiment(experiment, execution, RunArgs(cell, trials, seed))
    return summarise(cell, done["results"]["fixed"], done["wall"])


def summarise(cell: Cell, entry: dict, wall: float) -> dict:
    """The cell's numbers at the last iteration: AL, PL, AL − PL, the costs."""
    measure = MEASURE[cell.task]
    last = {m: entry["runs"][m]["iterations"][-1] for m in ex.METHODS}
    al, pl = last["AL"][measure], last["PL"][measure]
    diff = paired_difference(al, pl)

    def per_trial(method: str, key: str) -> float:
        value = last[method].get(key)
        return float(np.mean(value)) if isinstance(value, list) else float(value or 0)

    runs = entry["runs"]
    return {
        "cell": asdict(cell) | {"name": cell.name, "axis": cell.axis},
        "measure": measure,
        "al": stats(al),
        "pl": stats(pl),
        "difference": diff,
        "sd_difference": float(np.std(np.asarray(al) - np.asarray(pl), ddof=1)),
        "detectable_80": Z_POWER * diff["se"] if diff["se"] is not None else None,
        "verdict": verdict(diff["mean"], diff["p"]),
        "rewarded_transitions": {m: per_trial(m, "rewarded_transitions") for m in ex.METHODS},
        "reward_free_transitions": {m: per_trial(m, "reward_free_transitions") for m in ex.METHODS},
        "seconds": {m: runs[m]["seconds"] for m in ex.METHODS},
        "selection_cpu_seconds": sum(
            it.get("selection_cpu_seconds") or 0.0 for it in runs["AL"]["iterations"]
        ),
        "wall_seconds": wall,
    }


def stats(values) -> dict:
    x = np.asarray(values, dtype=np.float64)
    se = float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else None
    return {"mean": float(x.mean()), "se": se, "trials": int(x.size)}


# -- sizing a cell from its pilot ------------------------------------------------------------


def target_effect(cell: Cell, pilot: dict, effect: float) -> float:
    """δ: ``effect`` × (optimum − PL) on the chain walk, × (a solved policy's return − PL) on
    CartPole and Acrobot, ``effect`` × PL's score on the arm."""
    if cell.task == "chain":
        return effect * max(chain.optimal_return(50) - pilot["pl"]["mean"], 0.0)
    if cell.task in gym_tasks.TASKS:
        return effect * max(gym_tasks.TASKS[cell.task].solved - pilot["pl"]["mean"], 0.0)
    return effect * abs(pilot["pl"]["mean"])


def trials_needed(sd: float, delta: float) -> int:
    """n ≈ ((z_0.975 + z_0.8) σ_d / δ)², the paired t-test's trials for 80 % power at 0.05."""
    if delta <= 0:
        return sys.maxsize
    return math.ceil((Z_POWER * sd / delta) ** 2)


def sized_cell(cell: Cell, args: Args, out: Path) -> dict:
    """The cell's pilot, then the cell at the trials its spread asks for (stored on disk)."""
    path = out / "cells" / f"{cell.name}.json"
    if path.is_file():
        return json.loads(path.read_text())
    started, gym = time.perf_counter(), cell.task in gym_tasks.TASKS
    cap = vars(args)[f"{cell.task}_cap"]
    first = min(args.gym_pilot, cap) if gym else args.pilot
    pilot = run_cell(cell, first, args.seed, out)
    delta = target_effect(cell, pilot, args.effect)
    needed = trials_needed(pilot["sd_difference"], delta)
    trials = min(max(needed, first), cap)
    final = pilot if trials == first else run_cell(cell, trials, args.seed, out)
    final |= {
        "pilot": {k: pilot[k] for k in ("al", "pl", "difference", "sd_difference", "seconds")},
        "target_difference": delta,
        "trials_needed": needed if needed < sys.maxsize else None,
        "trials_cap": cap,
        "cell_wall_seconds": time.perf_counter() - started,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(final, indent=1))
    d = final["difference"]
    print(
        f"{cell.name}: {d['trials']} trials, AL − PL {d['mean']:+.4f} "
        f"({d['ci95_low']}, {d['ci95_high']}), p = {d['p']}, "
        f"detectable {final['detectable_80']:.4f}, target {delta:.4f}"
    )
    return final


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    out = Path(args.out_dir)
    try:  # every cell's settings checked before any work
        todo = cells(args)
        for cell in todo:
            spec_of(cell, args.pilot, args.seed)
        if args.pilot < 2 or args.effect <= 0:
            raise ValueError(f"pilot must be >= 2 and effect > 0, got {args.pilot}, {args.effect}")
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    load_start = __import__("os").getloadavg()
    found = [sized_cell(replace(cell), args, out) for cell in todo]
    wall = sum(c["cell_wall_seconds"] for c in found)  # (the cells' own: a rerun reads them)
    payload = data_file(args, found, wall, load_start, chain.optimal_return(50), Z_POWER)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.out), json.dumps(payload, indent=1))
        print(f"wrote {args.out}")
    if args.figure:
        plot(found, Path(args.figure))
        print(f"wrote {args.figure}")
    return payload


if __name__ == "__main__":
    main()
