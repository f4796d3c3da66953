"""The figure of a paired experiment: measures per iteration, AL against PL, and AL − PL.

Every panel shows a measure per iteration with error bars of one standard error of the mean over
the T trials: one colour per method (AL red, PL blue), one line style per schedule; a last panel
(optional) shows the paired difference AL − PL of the first measure.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from torch_api.experiment.results import mean_se
from torch_api.runs.files import save_figure_atomic

__all__ = ["plot_paired"]

COLOURS = {"AL": "tab:red", "PL": "tab:blue"}
STYLES = ("-", "--", ":", "-.")


def _curve(run: dict, measure: str) -> tuple[np.ndarray, np.ndarray]:
    """The iterations of a run and ``[L, 2]`` (mean, s.e.) of ``measure`` at each."""
    its = run["iterations"]
    stats = np.array([mean_se(it[measure]) for it in its])
    return np.array([it["iteration"] for it in its]), np.nan_to_num(stats)


def plot_paired(
    results: dict,
    path: str | Path,
    measures: Mapping[str, str],
    *,
    lines: Mapping[str, Mapping[str, float | None]] | None = None,
    difference: bool = False,
    floor: float | None = None,
    title: str = "",
) -> None:
    """Draw ``results`` (:func:`~torch_api.experiment.run_experiment`'s layout) into ``path``.

    Args:
        results: ``{schedule: {"runs": {"AL": run, "PL": run}, ...}}``.
        path: the image file (its suffix gives the format, e.g. ``.png``).
        measures: ``{measure: y-axis label}``, one panel each.
        lines: ``{measure: {label: level}}``: horizontal reference lines (None levels skipped).
        difference: add a panel of AL − PL (paired, per trial) of the first measure.
        floor: the lower y limit of the measures' panels (None: matplotlib's).
        title: the figure's title; the trial count is added.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = len(measures) + bool(difference)
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 4.0), squeeze=False)
    axes = list(axes[0])
    first = next(iter(measures))
    trials = 0
    for ax, (measure, label) in zip(axes, measures.items(), strict=False):
        for style, (name, entry) in zip(STYLES * 4, results.items(), strict=False):
            for method, run in entry["runs"].items():
                x, stats = _curve(run, measure)
                trials = len(np.atleast_1d(run["iterations"][-1][measure]))
                ax.errorbar(
                    x + (0.06 if method == "PL" else 0.0),
                    stats[:, 0],
                    yerr=stats[:, 1],
                    linestyle=style,
                    color=COLOURS.get(method, "black"),
                    marker="o",
                    markersize=3,
                    capsize=3,
                    label=f"{method}, {name}",
                )
        for text, level in ((lines or {}).get(measure) or {}).items():
            if level is not None:
                ax.axhline(level, color="green", linewidth=1)
                ax.text(x[0], level, text, va="bottom", fontsize=7, color="green")
        if floor is not None:
            ax.set_ylim(bottom=floor)
        ax.set_xlabel("iteration l")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    if difference:
        ax = axes[-1]
        for style, (name, entry) in zip(STYLES * 4, results.items(), strict=False):
            al, pl = ([it[first] for it in entry["runs"][m]["iterations"]] for m in ("AL", "PL"))
            stats = np.nan_to_num(np.array([mean_se(row) for row in np.subtract(al, pl)]))
            x = [it["iteration"] for it in entry["runs"]["AL"]["iterations"]]
            ax.errorbar(x, stats[:, 0], yerr=stats[:, 1], linestyle=style, color="black",
                        marker="o", markersize=3, capsize=3, label=name)  # fmt: skip
        ax.axhline(0.0, color="gray", linewidth=1)
        ax.set_xlabel("iteration l")
        ax.set_ylabel(f"AL − PL, same trial (paired): {first}")
        ax.legend(fontsize=7, title="schedule", title_fontsize=7)
    fig.suptitle(f"{title} mean ± s.e. of the mean over T = {trials} trials".strip(), fontsize=10)
    fig.tight_layout()
    try:
        save_figure_atomic(fig, path, dpi=120)
    finally:  # (a refused link leaves no open figure behind)
        plt.close(fig)
