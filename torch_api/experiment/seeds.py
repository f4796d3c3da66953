"""Runs of a user's pipeline over seeds, AL and PL paired: stored, summarised and written.

Every run (mode, seed) in its own store in one output folder, where an
:class:`~torch_api.experiment.options.Execution` says (:func:`seeds_folder`,
:func:`run_seeds`); the summary and paired t-test of the runs (:func:`summarise_seeds`), their
figure (:func:`plot_seeds`) and JSON (:func:`write_seeds`), each file written atomically
(:mod:`torch_api.runs.files`). Used by ``examples/torchrl_pipeline.py`` and
``examples/merge_pipeline_runs.py``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from torch_api.experiment.folder import durable_runs, folder_held
from torch_api.experiment.options import Execution
from torch_api.experiment.results import mean_se, paired_test
from torch_api.loop.durable import DurableRun
from torch_api.runs.files import save_figure_atomic, write_text_atomic

__all__ = ["plot_seeds", "run_seeds", "seeds_folder", "summarise_seeds", "write_seeds"]


def summarise_seeds(
    results: Mapping[str, Mapping[int, dict]],
    goals: Mapping[int, float],
    goal_text: str,
    measure: str = "greedy_test_return",
) -> tuple[dict, dict | None]:
    """Per mode (AL, PL) the last ``measure`` over the seeds, the seeds at their goal, the
    reward budget used and the curve's mean; the paired t-test of AL vs PL where both ran.

    Args:
        results: ``{mode: {seed: run}}``, each run ``{"history": [row per iteration],
            "seconds": s}`` with ``measure`` and ``rewarded_transitions`` in every row.
        goals: the goal of each seed (a last ``measure`` at least this counts as reached).
        goal_text: how the goal is printed (``"≥ 475"``).

    Returns: ``(summary {mode: {...}}, the t-test or None)``; the lines are printed.
    """
    summary = {}
    for mode, runs in results.items():
        if not runs:
            continue
        seeds = sorted(runs)
        last = [runs[s]["history"][-1][measure] for s in seeds]
        used = [runs[s]["history"][-1]["rewarded_transitions"] for s in seeds]
        reached = [r >= goals[s] for r, s in zip(last, seeds, strict=True)]
        summary[mode] = {
            "seeds": seeds,
            "last_greedy_return": last,
            "reached_goal": int(sum(reached)),
            "share_reached_goal": float(np.mean(reached)),
            "curve_mean": [
                float(np.mean([runs[s]["history"][i][measure] for s in seeds]))
                for i in range(len(runs[seeds[0]]["history"]))
            ],
            "rewarded_transitions_mean": float(np.mean(used)),
            "rewarded_transitions_max": int(max(used)),
            "seconds": float(sum(runs[s]["seconds"] for s in seeds)),
        }
        mean, se = mean_se(last)
        print(
            f"{mode}: last greedy return {mean:.1f} ± {se:.1f} (mean ± s.e. over {len(seeds)} "
            f"seeds); {goal_text} in {sum(reached)}/{len(seeds)} seeds; reward budget used: "
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
    return summary, t_test


def plot_seeds(
    results: Mapping[str, Mapping],
    path: str | Path,
    *,
    title: str,
    line: tuple[float, str] | None = None,
    measure: str = "greedy_test_return",
) -> None:
    """``measure`` per iteration, mean ± s.e. over the seeds, one line per mode (AL red, PL
    blue), and a horizontal ``line = (level, label)``, into the image ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    colours = {"AL": "tab:red", "PL": "tab:blue"}
    for mode, runs in results.items():
        if not runs:
            continue
        curves = np.array([[h[measure] for h in r["history"]] for r in runs.values()])
        stats = np.array([mean_se(c) for c in curves.T])
        ax.errorbar(np.arange(1, curves.shape[1] + 1), stats[:, 0], yerr=stats[:, 1],
                    color=colours.get(mode), marker="o", capsize=3,
                    label=f"{mode} ({len(runs)} seeds)")  # fmt: skip
    if line is not None:
        ax.axhline(line[0], color="grey", linestyle=":", label=line[1])
    ax.set_xlabel("iteration l")
    ax.set_ylabel("greedy test return of pi_(l+1)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure_atomic(fig, path, dpi=120)
    plt.close(fig)


def seeds_folder(execution: Execution) -> Path:
    """``execution.out_dir``, made: where :func:`run_seeds` stores its runs and files. Its runs
    go here, one after another (``--seeds``, ``--modes``; several processes, merged after), so
    a backend, chunks or a logger other than the default is refused with a ValueError."""
    other = ("backend", "chunks", "workers", "ray_address", "ray_cpus", "logger")
    if given := [k for k in other if getattr(execution, k) != getattr(Execution, k)]:
        flags = ", ".join(f"--{k.replace('_', '-')}" for k in given)
        raise ValueError(
            f"{flags}: not for runs over seeds, which run here one after another (split them "
            "over processes with --seed, --seeds and --modes instead)"
        )
    out = Path(execution.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return out


def run_seeds(
    execution: Execution,
    modes: Sequence[str],
    seeds: Sequence[int],
    run: Callable[[str, int, DurableRun], dict],
    *,
    files: Sequence[Path] = (),
    settings: dict | None = None,
) -> dict[str, dict[int, dict]]:
    """``run(mode, seed, durable)`` for each seed of ``seeds`` and each of its ``modes`` (AL,
    PL) in turn, each run's store a :class:`~torch_api.loop.durable.DurableRun` at
    ``<out_dir>/checkpoints/<mode>_seed<seed>.db`` (``execution.resume``, ``overwrite``) for
    the run's :class:`~torch_api.ActivePolicyIteration` (whose identity a resumed store must
    match, and ``settings``: the script's own, e.g. its test's), holding the folder
    ``execution.out_dir`` (one writer at a time; stored runs or
    ``files`` of an earlier run need ``execution.resume`` or ``overwrite``) on
    ``execution.threads`` torch threads (0: torch's default); SIGINT/SIGTERM and store errors
    end the script with one line (:mod:`torch_api.experiment.folder`).

    Returns: ``{"AL": {seed: run}, "PL": {seed: run}}`` (a mode not run stays empty).
    """
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # quiet storage-creation notices
    if execution.threads > 0:
        torch.set_num_threads(execution.threads)
    out, resume, overwrite = Path(execution.out_dir), execution.resume, execution.overwrite
    runs = [(mode, seed) for seed in seeds for mode in modes]
    paths = [out / "checkpoints" / f"{mode}_seed{seed}.db" for mode, seed in runs]
    results: dict[str, dict[int, dict]] = {"AL": {}, "PL": {}}
    with folder_held(out, paths, files, execution), durable_runs(paths, out):
        for (mode, seed), path in zip(runs, paths, strict=True):
            durable = DurableRun(path, resume=resume, overwrite=overwrite, settings=settings)
            results.setdefault(mode, {})[seed] = run(mode, seed, durable)
    return results


def write_seeds(
    path: str | Path,
    args: dict,
    results: Mapping[str, Mapping[int, dict]],
    baselines: Mapping[int, float],
    *,
    goal: float | None,
    title: str,
    wall: float,
) -> dict:
    """Summarise runs over seeds (:func:`summarise_seeds`), write them as JSON to ``path`` and
    their figure beside it (``path`` with ``.png``, :func:`plot_seeds`); returns the payload.

    Args:
        path: the JSON file.
        args: the script's arguments (JSON-able), stored with the results.
        results: ``{mode: {seed: run}}``.
        baselines: each seed's baseline (the user's own policy alone, "the actor alone").
        goal: the level a last greedy return must reach, or None: the seed's baseline.
        title: the figure's title.
        wall: the seconds the runs took.
    """
    path = Path(path)
    goals = {s: b if goal is None else goal for s, b in baselines.items()}
    reach = "≥ the actor alone" if goal is None else f"≥ {goal:.0f}"
    summary, t_test = summarise_seeds(results, goals, reach)
    baseline = float(np.mean(list(baselines.values()))) if baselines else None
    if baseline is not None:
        print(f"the actor alone (sampling): mean return {baseline:.1f}")
    print(f"{wall:.1f} s wall")
    payload = {
        "args": args,
        "wall_seconds": wall,
        "runs": {mode: {str(s): run for s, run in runs.items()} for mode, runs in results.items()},
        "actor_alone": {str(s): v for s, v in baselines.items()},
        "summary": summary,
        "t_test": t_test,
    }
    write_text_atomic(path, json.dumps(payload, indent=1))
    line = (goal, "goal") if goal is not None else None
    if line is None and baseline is not None:
        line = (baseline, "the actor alone")
    plot_seeds(payload["runs"], path.with_suffix(".png"), title=title, line=line)
    print(f"wrote {path} and {path.with_suffix('.png')}")
    return payload
