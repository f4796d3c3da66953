"""The reward-budget map's rows and figure (``benchmarks/reward_budget_map.py``): each cell as
a row of the results report, the telling rows of the headline, AL − PL against M."""

from __future__ import annotations

from pathlib import Path

from torch_api.runs.files import save_figure_atomic

MEASURE = {"chain": "exact_return", "batting": "performance"}
TITLE = {"chain": "chain walk", "batting": "batting arm"}


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
    for task in ("chain", "batting"):
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

    tasks = [t for t in ("chain", "batting") if any(c["cell"]["task"] == t for c in found)]
    fig, axes = plt.subplots(1, len(tasks), figsize=(6 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
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
