"""What ``torchrl_pipeline.py`` reports: per mode the last greedy returns over the seeds, the
share of seeds at the goal, the reward budget used, the paired t-test of AL vs PL, and the plot
of the greedy return per iteration (mean ± one standard error over the seeds)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from _results import mean_se, paired_test

GOAL = {"CartPole-v1": 475.0}
"""A last greedy return at least this is "learned" (CartPole: balanced ≥ 475 of 500 steps).
MountainCar's goal is the user's actor alone on the same seed."""

COLOURS = {"AL": "tab:red", "PL": "tab:blue"}


def summarise(args, results: dict, baselines: dict, wall: float) -> dict:
    """The JSON payload: every run's history, and per mode what the example prints."""
    summary = {}
    for mode, runs in results.items():
        if not runs:
            continue
        seeds = sorted(runs)
        last = [runs[s]["history"][-1]["greedy_test_return"] for s in seeds]
        goals = [GOAL.get(args.env, baselines[s]) for s in seeds]
        used = [runs[s]["history"][-1]["rewarded_transitions"] for s in seeds]
        reached = [r >= g for r, g in zip(last, goals, strict=True)]
        summary[mode] = {
            "seeds": seeds,
            "last_greedy_return": last,
            "reached_goal": int(sum(reached)),
            "share_reached_goal": float(np.mean(reached)),
            "curve_mean": [
                float(np.mean([runs[s]["history"][i]["greedy_test_return"] for s in seeds]))
                for i in range(len(runs[seeds[0]]["history"]))
            ],
            "rewarded_transitions_mean": float(np.mean(used)),
            "rewarded_transitions_max": int(max(used)),
            "seconds": float(sum(runs[s]["seconds"] for s in seeds)),
        }
        goal = f"≥ {GOAL[args.env]:.0f}" if args.env in GOAL else "≥ the actor alone"
        mean, se = mean_se(last)
        print(
            f"{mode}: last greedy return {mean:.1f} ± {se:.1f} (mean ± s.e. over {len(seeds)} "
            f"seeds); {goal} in {sum(reached)}/{len(seeds)} seeds; reward budget used: "
            f"{np.mean(used):.0f} rewarded transitions a run on average, at most {max(used)}"
        )
    t_test = None
    if summary.keys() == {"AL", "PL"}:
        al, pl = (summary[m]["last_greedy_return"] for m in ("AL", "PL"))
        t_test = paired_test(al, pl)
        t = "undefined" if t_test["t"] is None else f"{t_test['t']:.3f}, p = {t_test['p']:.3g}"
        print(
            f"AL vs PL, paired over {len(al)} seeds (last greedy return): mean difference "
            f"{t_test['mean_difference']:.1f}, t = {t}; AL better in "
            f"{t_test['al_better_share']:.0%}, worse in {t_test['al_worse_share']:.0%}"
        )
    if baselines:
        print(f"the actor alone (sampling): mean return {np.mean(list(baselines.values())):.1f}")
    print(f"{wall:.1f} s wall")
    return {
        "args": dataclasses.asdict(args),
        "wall_seconds": wall,
        "runs": {mode: {str(s): run for s, run in runs.items()} for mode, runs in results.items()},
        "actor_alone": {str(s): v for s, v in baselines.items()},
        "summary": summary,
        "t_test": t_test,
    }


def plot(payload: dict, path: Path) -> None:
    """The greedy return per iteration, mean ± s.e. over the seeds, one line per mode."""
    args = payload["args"]
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for mode, runs in payload["runs"].items():
        if not runs:
            continue
        curves = np.array([[h["greedy_test_return"] for h in r["history"]] for r in runs.values()])
        x = np.arange(1, curves.shape[1] + 1)
        stats = np.array([mean_se(c) for c in curves.T])
        ax.errorbar(x, stats[:, 0], yerr=stats[:, 1], color=COLOURS[mode], marker="o",
                    capsize=3, label=f"{mode} ({len(runs)} seeds)")  # fmt: skip
    if args["env"] in GOAL:
        ax.axhline(GOAL[args["env"]], color="grey", linestyle=":", label="goal")
    elif payload["actor_alone"]:
        actor = np.mean(list(payload["actor_alone"].values()))
        ax.axhline(actor, color="grey", linestyle=":", label="the actor alone")
    ax.set_xlabel("iteration l")
    ax.set_ylabel("greedy test return of pi_(l+1)")
    ax.set_title(f"{args['env']} through TorchRL: greedy return per iteration", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
