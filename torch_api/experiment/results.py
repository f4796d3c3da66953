"""The paired experiments' numbers: statistics, printed tables and the result files.

``<name>.csv`` holds every per-trial number in long format, one row per (schedule, method,
seed, iteration, trial, measure) with its ``value`` (:data:`COLUMNS`); ``<name>.json`` holds the
arguments, the wall time, the t-tests and every run's settings and totals. The results in memory
are laid out as :mod:`torch_api.experiment.runner` describes.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterator
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.stats

from torch_api.runs.files import write_text_atomic

if TYPE_CHECKING:
    from torch_api.experiment.runner import Experiment

METHODS = {"AL": "active", "PL": "passive"}
"""The two methods of a pair and the loop's mode of each."""
COLUMNS = ("schedule", "method", "seed", "iteration", "trial", "measure", "value")
"""The columns of every experiment's CSV (long format)."""
NOT_IN_CSV = ("iteration", "seconds", "selection_cpu_seconds")
"""Keys of an iteration's row that are not measures: times differ between equal runs (the
JSON holds them: each run's ``iteration_seconds`` and ``selection_cpu_seconds``)."""


# -- statistics ------------------------------------------------------------------------------


def mean_se(values) -> tuple[float, float]:
    """Mean and standard error of the mean (nan with a single value)."""
    x = np.asarray(values, dtype=np.float64)
    se = x.std(ddof=1) / math.sqrt(x.size) if x.size > 1 else math.nan
    return float(x.mean()), float(se)


def paired_test(al, pl) -> dict:
    """Two-tailed paired t-test of AL vs PL over trials, and the share of trials each wins.

    ``t`` and ``p`` are None where the test is undefined: fewer than two pairs, or no spread in
    the differences (e.g. every pair identical: AL chose pi_l itself in every iteration of
    every trial, so the paired runs bought the same episodes).
    """
    a, p = np.asarray(al, dtype=np.float64), np.asarray(pl, dtype=np.float64)
    d, n = a - p, len(a)
    t = pvalue = None
    if n > 1 and not np.all(d == d[0]):
        test = scipy.stats.ttest_rel(a, p)
        t, pvalue = float(test.statistic), float(test.pvalue)
    return {
        "mean_difference": float(d.mean()),
        "t": t,
        "p": pvalue,
        "al_better_share": float((a > p).mean()),
        "al_worse_share": float((a < p).mean()),
    }


def print_curves(results: dict, measure: str, title: str, digits: int = 4) -> None:
    """A table of ``measure``: one row per schedule and method, mean ± s.e. over trials at
    each iteration."""
    first = next(iter(results.values()))["runs"]["AL"]["iterations"]
    print(f"\n{title}")
    heads = " ".join(f"{'l=' + str(it['iteration']):>15}" for it in first)
    print(f"{'schedule':<11} {'method':<6} {heads}")
    for name, entry in results.items():
        for method, run in entry["runs"].items():
            cells = (mean_se(it[measure]) for it in run["iterations"])
            row = " ".join(f"{f'{m:8.{digits}f}±{se:6.{digits}f}':>15}" for m, se in cells)
            print(f"{name:<11} {method:<6} {row}")


def print_t_tests(results: dict, trials: int) -> None:
    """The paired two-tailed t-tests of AL vs PL at the last iteration, one row per measure."""
    print(f"\nPaired two-tailed t-test, AL vs PL at the last iteration ({trials} pairs)")
    print(
        f"{'schedule':<11} {'measure':<21} {'mean(AL-PL)':>12} {'t':>8} {'p':>10} "
        f"{'AL>PL':>6} {'AL<PL':>6}"
    )
    for name, entry in results.items():
        for measure, t in entry["t_tests"].items():
            stat = "undefined" if t["t"] is None else f"{t['t']:8.3f} {t['p']:10.3g}"
            print(
                f"{name:<11} {measure:<21} {t['mean_difference']:12.5f} {stat:>19} "
                f"{t['al_better_share']:6.2f} {t['al_worse_share']:6.2f}"
            )


# -- files -----------------------------------------------------------------------------------


_NUMBERS = (int, float)  # written by str() as they are (a bool is written by _field)


def _field(value) -> str:
    """``value`` as ``csv.writer`` writes a field of a row (the excel dialect): None empty,
    numbers by ``str``, a text quoted where it holds a comma, a quote or a line break."""
    if value is None:
        return ""
    text = str(value)
    if any(c in text for c in ',"\r\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def csv_lines(results: dict) -> Iterator[str]:
    """Every per-trial number of the experiment, one CSV line (:data:`COLUMNS`, ending in
    ``\r\n``) each, byte for byte what ``csv.writer`` writes of the same rows, header first.

    A list over trials gives trial t its element; a number of the iteration (the same for
    every trial, e.g. ``rewarded_transitions``) is repeated per trial; a vector per trial
    (``j_mean``, J' of the K candidates) becomes measures ``j_mean_k1`` … ``j_mean_kK``.
    (Formatted here rather than by ``csv.writer``: 356,000 rows at 1,000 trials of Figure 8
    took 0.55-0.6 s there, 0.26 s here.)
    """
    yield ",".join(COLUMNS) + "\r\n"
    for name, entry in results.items():
        for method, run in entry["runs"].items():
            for it in run["iterations"]:
                measures = [(k, _field(k), v) for k, v in it.items() if k not in NOT_IN_CSV]
                trials = max(len(v) for v in it.values() if isinstance(v, list))
                head = ",".join(map(_field, (name, method, run["seed"], it["iteration"])))
                for t in range(trials):
                    prefix = f"{head},{t},"
                    for key, field, value in measures:
                        value = value[t] if isinstance(value, list) else value
                        if value is None:
                            continue
                        if isinstance(value, list):
                            for k, x in enumerate(value, 1):
                                x = x if type(x) in _NUMBERS else _field(x)
                                yield f"{prefix}{_field(f'{key}_k{k}')},{x}\r\n"
                        else:
                            value = value if type(value) in _NUMBERS else _field(value)
                            yield f"{prefix}{field},{value}\r\n"


def read_results(path: str | os.PathLike) -> dict[tuple, list]:
    """An experiment's CSV read back: ``{(schedule, method, iteration, measure): [value of
    trial 0, 1, …]}`` (ints where written as ints, else floats)."""
    table: dict[tuple, list] = {}
    with open(path, newline="") as handle:
        for row in csv.DictReader(handle):
            key = (row["schedule"], row["method"], int(row["iteration"]), row["measure"])
            value = row["value"]
            table.setdefault(key, []).append(int(value) if value.isdigit() else float(value))
    return table


def write_results(
    execution, args, experiment: Experiment, results: dict, wall: float, **extra
) -> dict:
    """``<name>.csv`` (:func:`csv_lines`) and ``<name>.json`` (the script's arguments, wall
    time, t-tests, the runs' settings and totals; ``extra``: more entries) in
    ``execution.out_dir``; the learning curves with ``execution.logger``.

    Returns the JSON's payload, with ``results`` (every number, in memory) added.
    """
    out = Path(execution.out_dir)
    write_text_atomic(out / f"{experiment.name}.csv", "".join(csv_lines(results)))
    summary = {
        name: {
            "schedule": entry["schedule"],
            "t_tests": entry["t_tests"],
            "runs": {
                method: {k: v for k, v in run.items() if k != "iterations"}
                | {
                    "iteration_seconds": [it.get("seconds") for it in run["iterations"]],
                    "selection_cpu_seconds": [
                        it.get("selection_cpu_seconds") for it in run["iterations"]
                    ],
                }
                for method, run in entry["runs"].items()
            },
        }
        for name, entry in results.items()
    }
    payload = {"args": _plain(args), "wall_seconds": wall, **extra}
    write_text_atomic(out / f"{experiment.name}.json", json.dumps({**payload, "summary": summary}))
    log_curves(execution.logger, out, experiment, results)
    return {**payload, "summary": summary, "results": results}


def _plain(args) -> dict:
    return asdict(args) if is_dataclass(args) else dict(vars(args))


def log_curves(kind: str, out: Path, experiment: Experiment, results: dict) -> None:
    """With a TorchRL logger (``--logger``: csv, tensorboard, wandb) under ``<out>/logs``:
    ``<schedule>/<method>/<measure>`` = the mean over trials of each curve, per iteration, and
    of the fit's flattening ν and effective sample size (docs/flattening.md)."""
    if kind == "none":
        return
    from torchrl.record.loggers import get_logger

    logger = get_logger(kind, logger_name=str(out / "logs"), experiment_name=experiment.name)
    for name, entry in results.items():
        for method, run in entry["runs"].items():
            for it in run["iterations"]:
                for measure in (*experiment.curves, "flattening", "effective_sample_size"):
                    value = it.get(measure)
                    if isinstance(value, list):
                        value = sum(value) / len(value) if value else None
                    if value is not None:
                        logger.log_scalar(
                            f"{name}/{method}/{measure}", float(value), step=it["iteration"]
                        )
