"""The reward-budget map's data file, rows and figure (``benchmarks/reward_budget_map.py``):
each cell as a row of the results report, the telling rows of the headline, AL − PL against M."""

from __future__ import annotations

import os
import time
from dataclasses import asdict
from pathlib import Path

from torch_api.runs.files import save_figure_atomic

MEASURE = {"chain": "exact_return", "batting": "performance"}
MEASURE |= {"cartpole": "greedy_test_return", "acrobot": "greedy_test_return"}
TITLE = {"chain": "chain walk", "batting": "batting arm", "cartpole": "CartPole-v1"}
TITLE["acrobot"] = "Acrobot-v1"
ROOT = Path(__file__).resolve().parents[1]


def data_file(args, found: list[dict], wall: float, load_start, optimum: float, z: float) -> dict:
    """The map in the format of docs/results/data/ (rows for the headline, every cell);
    ``optimum``: the chain walk's exact optimum, ``z``: z_0.975 + z_0.8."""
    from benchmarks._budget_map_gym import TASKS, TEST_EPISODES, TEST_STEPS
    from benchmarks.summarize import commit_of, machine

    command = f"python benchmarks/reward_budget_map.py --tasks {args.tasks}"
    command += " --out docs/results/data/reward_budget_map.json"
    command += " --figure docs/results/reward_budget_map.png"
    tasks = [TITLE[t] for t in TITLE if any(c["cell"]["task"] == t for c in found)]
    gym = "; ".join(f"{g.env_id}: N = {g.num_steps}, γ = {g.gamma}" for g in TASKS.values())
    return {
        "experiment": "reward_budget_map",
        "title": "Where AL pays: AL − PL against the rewarded and reward-free budgets",
        "task": f"{', '.join(tasks)}: budget map",
        "command": command,
        "commit": commit_of(ROOT),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine(load_start, os.getloadavg(), "before and after"),
        "note": "Each cell runs AL and PL on the same trial seeds with M rewarded episodes in "
        "each of L = 7 iterations, R reward-free episodes per candidate and repeat (M: the "
        "paper's) and Z repeats of J; the chain walk's measure is the exact expected return of "
        "pi_{L+1}, the batting arm's the score of eq. 68, CartPole's and Acrobot's the greedy "
        f"test return of θ_L ({TEST_EPISODES} test episodes of at most {TEST_STEPS} steps per "
        f"trial; {gym}; a quadratic Q̂ per action, LSTD-Q, ν = 0, as the showcase; "
        "gymnasium's SyncVectorEnv through TorchRL's GymWrapper). Trials: a pilot "
        f"({args.pilot} trials; CartPole and Acrobot {args.gym_pilot}), then as many as 80 % "
        "power at α = 0.05 needs against the target δ (a quarter of the PL-to-optimum gap on "
        "the chain walk, of the PL-to-solved gap on CartPole and Acrobot, a quarter of PL's "
        f"score on the batting arm), capped (CartPole at {args.cartpole_cap}, Acrobot at "
        f"{args.acrobot_cap} trials, for the time: where a cap binds, the detectable difference "
        "says what the trials can see); the headline rows are each task's smallest and "
        "largest M, the table below holds every cell.",
        "wall_seconds": wall,
        "wall_note": "the sum of the cells' wall seconds (pilot and sized run), each measured "
        "while other jobs shared the 2 cores",
        "measures": ["exact_return", "performance", "greedy_test_return"],
        "headline_measures": ["exact_return", "performance", "greedy_test_return"],
        "chain_optimum": optimum,
        "solved": {g.env_id: {"return": g.solved, "note": g.solved_note} for g in TASKS.values()},
        "better": "higher",
        "digits": 3,
        "args": asdict(args),
        "power": {
            "alpha": 0.05,
            "power": 0.8,
            "z_sum": z,
            "rule": "n = ceil(((z_0.975 + z_0.8) sd_d / delta)^2) from the pilot, "
            "between the pilot's trials and the task's cap",
            "delta": f"{args.effect} x (optimum - PL) on the chain walk, {args.effect} x "
            f"(solved - PL) on CartPole and Acrobot, {args.effect} x PL on the batting arm",
        },
        "rows": [row_of(c) for c in telling(found)],
        "cells": found,
    }


def row_of(cell: dict) -> dict:
    """A cell as a row of the results report (benchmarks/report.py's headline format)."""
    c = cell["cell"]
    schedule = f"{TITLE[c['task']]}: M = {c['episodes']}, R = {c['reward_free'] or 'M'}, "
    schedule += f"Z = {c['repeats']}"
    if c["flattening"] != 1.0:
        schedule += f", ν = {c['flattening']}"
    return {
        "schedule": schedule,
        "measure": cell["measure"],
        "iteration": c["iterations"],
        "al": cell["al"],
        "pl": cell["pl"],
        "difference": cell["difference"],
        "verdict": cell["verdict"],
        "rewarded_transitions": cell["rewarded_transitions"],
        "reward_free_transitions": cell["reward_free_transitions"],
        "seconds": cell["seconds"],
    }


def telling(found: list[dict]) -> list[dict]:
    """The rows of the headline: per task, the smallest and the largest M of the rewarded
    axis (every cell is in ``cells``)."""
    rows = []
    for task in MEASURE:
        axis = [c for c in found if c["cell"]["task"] == task and c["cell"]["axis"] == "rewarded"]
        axis.sort(key=lambda c: c["cell"]["episodes"])
        rows += axis[:1] + axis[-1:] if len(axis) > 1 else axis
    return rows


def plot(found: list[dict], path: Path) -> None:
    """AL − PL with its 95 % interval against M, one panel per task (every cell of the task:
    the rewarded axis joined by a line, the other cells as labelled points beside it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    tasks = [t for t in MEASURE if any(c["cell"]["task"] == t for c in found)]
    cols = min(len(tasks), 2)
    rows = -(-len(tasks) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4 * rows), squeeze=False)
    for ax in axes.flat[len(tasks) :]:
        ax.set_visible(False)
    for ax, task in zip(axes.flat, tasks, strict=False):
        mine = [c for c in found if c["cell"]["task"] == task]
        for k, c in enumerate(sorted(mine, key=lambda c: (c["cell"]["axis"], c["cell"]["name"]))):
            d, cell = c["difference"], c["cell"]
            low = d["mean"] - (d["ci95_low"] if d["ci95_low"] is not None else d["mean"])
            high = (d["ci95_high"] if d["ci95_high"] is not None else d["mean"]) - d["mean"]
            x = cell["episodes"] * (1.0 if cell["axis"] == "rewarded" else 1.06 + 0.04 * k)
            style = {"rewarded": "o", "reward_free": "s", "lever": "^"}[cell["axis"]]
            label = row_of(c)["schedule"] + f" ({d['trials']} trials)"
            ax.errorbar(x, d["mean"], yerr=[[low], [high]], fmt=style, capsize=3, label=label)
        axis = sorted(
            (c for c in mine if c["cell"]["axis"] == "rewarded"),
            key=lambda c: c["cell"]["episodes"],
        )
        ax.plot(
            [c["cell"]["episodes"] for c in axis], [c["difference"]["mean"] for c in axis], "k-"
        )
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xscale("log")
        ax.set_xticks(sorted({c["cell"]["episodes"] for c in mine}), minor=False)
        ax.set_xticks([], minor=True)
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.set_xlabel("M, rewarded episodes per iteration")
        ax.set_ylabel(f"AL − PL, {MEASURE[task]} at l = L (95 % CI)")
        ax.set_title(TITLE[task])
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure_atomic(fig, path, dpi=110)
    plt.close(fig)
