"""The figures of the iterative examples, drawn from the harness's results (``_harness.py``).

Every panel shows a measure per iteration with error bars of one standard error of the mean over
the T trials: one colour per method (AL red, PL blue), one line style per schedule.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from _results import mean_se

COLOURS = {"AL": "tab:red", "PL": "tab:blue"}
STYLES = {"decreasing": "-", "fixed": "--"}


def curve(run: dict, measure: str) -> tuple[np.ndarray, np.ndarray]:
    """The iterations of a run and ``[L, 2]`` (mean, s.e.) of ``measure`` at each."""
    its = run["iterations"]
    return np.array([it["iteration"] for it in its]), np.array([mean_se(it[measure]) for it in its])


def figure8(results: dict, optimal_return: float, path: Path) -> None:
    """Figure 8: both performance measures of pi_{l+1} against iterations (chain walk).

    The optimal policy's value is a horizontal line.
    """
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    panels = (
        ("test_return", "eq. 61: discounted return of 50 test episodes"),
        ("percent_optimal", "exact expected return, % of the optimal policy"),
    )
    first_run = next(iter(results.values()))["runs"]["AL"]
    trials = len(first_run["iterations"][0]["test_return"])
    optimum = {"test_return": optimal_return, "percent_optimal": 100.0}
    for ax, (measure, label) in zip(axes, panels, strict=True):
        for name, res in results.items():
            for method, run in res["runs"].items():
                x, stats = curve(run, measure)
                ax.errorbar(
                    x + (0.06 if method == "PL" else 0.0),
                    stats[:, 0],
                    yerr=stats[:, 1],
                    linestyle=STYLES.get(name, "-"),
                    color=COLOURS[method],
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


def figure10(results: dict, reference_optimum: float, ceiling: float | None, path: Path) -> None:
    """Figure 10: performance per iteration (left) and the paired difference AL − PL (right)
    (batting). The reference optimum and the learner's measured ceiling with the paper's basis
    (None: a learner whose ceiling was not measured) are horizontal lines."""
    fig, (ax, diff_ax) = plt.subplots(1, 2, figsize=(11, 4.2))
    trials = None
    for name, res in results.items():
        runs = res["runs"]
        for method, run in runs.items():
            x, stats = curve(run, "performance")
            trials = len(run["iterations"][0]["performance"])
            ax.errorbar(
                x + (0.05 if method == "PL" else 0.0),
                stats[:, 0],
                yerr=np.nan_to_num(stats[:, 1]),
                linestyle=STYLES[name],
                marker="o",
                markersize=3,
                color=COLOURS[method],
                capsize=3,
                label=f"{method}, {name}",
            )
        al, pl = ([it["performance"] for it in runs[m]["iterations"]] for m in ("AL", "PL"))
        diff = np.asarray(al) - np.asarray(pl)
        stats = np.array([mean_se(row) for row in diff])
        diff_ax.errorbar(
            np.arange(1, len(diff) + 1),
            stats[:, 0],
            yerr=np.nan_to_num(stats[:, 1]),
            linestyle=STYLES[name],
            marker="o",
            markersize=3,
            color="black",
            capsize=3,
            label=name,
        )
    for level, colour, style, text in (
        (reference_optimum, "green", "-", "reference optimum (best open-loop sequence)"),
        (ceiling, "gray", "-.", "ceiling: LSPI, paper's basis, abundant random data"),
    ):
        if level is None:
            continue
        ax.axhline(level, color=colour, linewidth=1, linestyle=style)
        ax.text(1, level, text, va="bottom", fontsize=7, color=colour)
    ax.set_ylim(bottom=0, top=reference_optimum * 1.08)
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


def steps_balanced(results: dict, env_id: str, path: Path) -> None:
    """Steps balanced by pi_{l+1} with its ε-greedy rule (left) and greedy (right) (CartPole);
    the lower bars stop at 0."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    runs = next(iter(results.values()))["runs"]
    for ax, key in zip(axes, ("steps_balanced", "steps_balanced_greedy"), strict=True):
        for method, run in runs.items():
            x, stats = curve(run, key)
            ax.errorbar(
                x,
                stats[:, 0],
                yerr=np.stack([np.minimum(stats[:, 1], stats[:, 0]), stats[:, 1]]),  # >= 0
                color=COLOURS[method],
                marker="o",
                capsize=3,
                label=method,
            )
        rule = "greedy" if key.endswith("greedy") else "ε-greedy"
        ax.set_title(f"{env_id}: steps balanced by pi_(l+1) ({rule})", fontsize=9)
        ax.set_xlabel("iteration l (0: the initial policy)")
        ax.set_ylabel("steps balanced")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    trials = len(runs["AL"]["iterations"][0]["steps_balanced"])
    fig.suptitle(f"mean over T = {trials} trials, bars ± 1 standard error of the mean", fontsize=10)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
