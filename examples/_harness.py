"""The paired experiment behind the iterative examples: runs, chunks, statistics and files.

An experiment runs Algorithm 1 twice per schedule of rewarded episodes on the same seeds (a
paired design): AL (``selector=SamplingPolicySelector(...)``, the sampling policy chosen by J')
and PL (``selector=None``: the evaluation policy samples). An example supplies what is its own —
the environment, the basis, the evaluation of pi_{l+1}, as a function of one :class:`Chunk` that
builds its run with :func:`make_iteration` and returns :func:`run_iterations` — and
:func:`run_experiment` does the rest:

1. the trials of every run split into chunks (``--chunks``), each run as one batched
   computation where ``--backend`` says (``torch_api.dispatch.run_chunks``), every chunk stored
   as it goes in ``<out-dir>/checkpoints/`` (``--resume``, ``--overwrite``);
2. SIGINT/SIGTERM: the commit in flight completes, one line, exit 130/143; a store error
   (a run in use, unwritable, corrupted, of other settings): one line, exit 1;
3. the chunks of a run concatenated along the trial axis, the paired two-tailed t-test of AL vs
   PL at the last iteration.

One result layout for every experiment, in memory::

    results[schedule] = {"schedule": [M_1, …, M_L], "t_tests": {measure: {...}},
                         "runs": {"AL": run, "PL": run}}
    run = {"seed": int, "seconds": float, "iterations": [row_l, …], …}
    row_l = {"iteration": l, measure: [T] per trial or one number, "j_mean": [T][K], …}

and on disk (:func:`write_results`): ``<name>.csv`` in long format, one row per (schedule,
method, seed, iteration, trial, measure) with its ``value`` — every per-trial number of the
experiment — and ``<name>.json`` with the arguments, the wall time, the t-tests and every run's
settings and totals.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.stats

from torch_api.dispatch import run_chunks, split_trials, trial_seeds
from torch_api.iteration import ActivePolicyIteration
from torch_api.selector import SamplingPolicySelector
from torch_api.store import RunStore, StoreError

METHODS = {"AL": "active", "PL": "passive"}
"""The two methods of a pair and the loop's mode of each."""
COLUMNS = ("schedule", "method", "seed", "iteration", "trial", "measure", "value")
"""The columns of every experiment's CSV (long format)."""
NOT_IN_CSV = ("iteration", "seconds")
"""Keys of an iteration's row that are not measures (wall times differ between equal runs)."""


def derived_seed(*parts: int, bits: int = 31) -> int:
    """A seed of ``bits`` (31 or 63) bits derived from integers (distinct parts, distinct seeds)."""
    dtype = np.uint32 if bits == 31 else np.uint64
    return int(np.random.SeedSequence(list(parts)).generate_state(1, dtype)[0] >> 1)


# -- one run of a chunk of trials ------------------------------------------------------------


@dataclass
class Chunk:
    """Some trials of one run (a schedule and a method), run as one batch and stored."""

    args: Any
    """the script's arguments (a ``RunOptions``)"""
    schedule_name: str
    schedule: tuple[int, ...]
    method: str
    """AL or PL"""
    seed: int
    """the run's seed, shared by AL and PL; trial t's seed is ``derive_seed(seed, t, "trial")``"""
    trials: list[int]
    """indices t of the run's trials in this chunk"""
    store: Path
    """where the chunk's run is stored"""
    progress: bool = True
    on_checkpoint: Callable | None = None
    """called with the run after every commit (the loop's ``on_checkpoint`` hook)"""

    @property
    def mode(self) -> str:
        return METHODS[self.method]


def make_iteration(
    chunk: Chunk,
    *,
    repeats: int,
    reward_free_env=None,
    reward_free_workers: int = 0,
    **settings,
) -> ActivePolicyIteration:
    """The chunk's run of Algorithm 1: its mode, its trials' seeds, its store; the rest of the
    loop's keyword arguments as given (``seed`` defaults to the run's seed)."""
    settings.setdefault("seed", chunk.seed)
    selector = None  # PL: the evaluation policy samples
    if chunk.mode == "active":  # AL: J'-chosen, reward-free env default the loop's env
        selector = SamplingPolicySelector(
            env=reward_free_env, num_repeats=repeats, num_workers=reward_free_workers
        )
    return ActivePolicyIteration(
        selector=selector,
        num_trials=len(chunk.trials),
        trial_seeds=trial_seeds(chunk.seed, chunk.trials),  # trial t's seed: (run seed, t) only
        checkpoint_path=chunk.store,
        resume=chunk.args.resume,
        overwrite=chunk.args.overwrite,
        on_checkpoint=chunk.on_checkpoint,
        **settings,
    )


def run_iterations(chunk: Chunk, api: ActivePolicyIteration, initial: dict | None = None) -> dict:
    """Run (or resume) ``api`` to its end; the chunk's part of the run.

    ``initial``: the evaluation of pi_1, recorded as iteration 0.
    """
    if api.resumed:
        print(f"resumed {chunk.store} at iteration {api.iteration}/{len(chunk.schedule)}")
    elif chunk.args.resume:
        print(f"nothing stored in {chunk.store}: starting it fresh")
    started = time.perf_counter()
    history = api.run(progress=chunk.progress)
    rows = [rec.row() for rec in history]
    if initial is not None:
        rows.insert(0, {"iteration": 0, "episodes_bought": 0, "rewarded_transitions": 0, **initial})
    return {"seed": chunk.seed, "seconds": time.perf_counter() - started, "iterations": rows}


def concatenate(parts: list[dict]) -> dict:
    """The chunks of one run as one run: per-trial lists concatenated along the trial axis,
    seconds summed, run-level lists concatenated, anything else as the first chunk has it."""

    def join(values: list) -> Any:
        if values[0] is None or isinstance(values[0], str):
            return values[0]
        if isinstance(values[0], list):
            return [x for value in values for x in value]
        return values[0]

    run = {key: join([p[key] for p in parts]) for key in parts[0] if key != "iterations"}
    run["seconds"] = sum(p["seconds"] for p in parts)
    run["iterations"] = []
    for its in zip(*(p["iterations"] for p in parts), strict=True):
        row = {key: join([it[key] for it in its]) for key in its[0]}
        if "seconds" in row:
            row["seconds"] = sum(it["seconds"] for it in its)
        run["iterations"].append(row)
    return run


# -- the experiment --------------------------------------------------------------------------


@dataclass
class Experiment:
    """What an example hands to :func:`run_experiment`."""

    name: str
    """the files' stem (``<name>.json``, ``<name>.csv``) and the logger's experiment"""
    schedules: dict[str, Sequence[int]]
    """the schedules of rewarded episodes to run, by name"""
    run_chunk: Callable[[Chunk], dict]
    """a top-level function (picklable): one chunk's run, :func:`run_iterations`' result"""
    t_tests: tuple[str, ...]
    """the measures compared by the paired t-test at the last iteration"""
    report: Callable[[dict, float], dict]
    """what the example prints and writes from ``(results, wall seconds)``, returning its
    payload; it runs under the same signal guard as the runs (everything is stored by then, so
    a signal while the files are written ends with the same line, and --resume writes them)"""
    run_seed: Callable[[int, str], int] = lambda seed, schedule: seed
    """the seed of the runs of a schedule (AL and PL share it), from ``--seed`` and its name"""
    store_stem: str = "{schedule}_{method}"
    """a run's store name, with ``{schedule}``, ``{method}`` (AL, PL) and ``{mode}``"""
    curves: tuple[str, ...] = ()
    """the measures written by ``--logger`` (means over trials per iteration)"""


def store_path(out: Path, experiment: Experiment, schedule: str, method: str, c: int, n: int):
    """``<out>/checkpoints/<stem>.db``, ``<stem>_chunk<c>of<C>.db`` (c = 1 … C) if C > 1."""
    stem = experiment.store_stem.format(schedule=schedule, method=method, mode=METHODS[method])
    return out / "checkpoints" / (stem + ("" if n == 1 else f"_chunk{c + 1}of{n}") + ".db")


def run_experiment(args, experiment: Experiment, on_checkpoint: Callable | None = None) -> dict:
    """Every run of the experiment, chunked where asked, then ``experiment.report(results,
    wall seconds)``, whose payload it returns.

    Ends the script with one line where the output folder holds runs and neither ``--resume``
    nor ``--overwrite`` was given, on SIGINT/SIGTERM (until the report is written) and on a
    store error (see the module). ``on_checkpoint``: given to every run (local backend only: it
    does not travel).
    """
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # quiet storage-creation notices
    if args.threads > 0:
        import torch

        torch.set_num_threads(args.threads)
    out = Path(args.out_dir)
    backend, chunks = getattr(args, "backend", "local"), getattr(args, "chunks", 1)
    runs = [(name, method) for name in experiment.schedules for method in METHODS]
    pieces = split_trials(args.trials, chunks)
    plan = [
        Chunk(
            args=args,
            schedule_name=name,
            schedule=tuple(experiment.schedules[name]),
            method=method,
            seed=experiment.run_seed(args.seed, name),
            trials=list(trials),
            store=store_path(out, experiment, name, method, c, chunks),
            progress=backend == "local",
            on_checkpoint=on_checkpoint,
        )
        for name, method in runs
        for c, trials in enumerate(pieces)
    ]
    stores = [chunk.store for chunk in plan]
    if (why := stored_runs_error(stores, args.resume, args.overwrite)) is not None:
        raise SystemExit(f"error: {why}")
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    print(f"{len(plan)} chunks of about {args.trials // chunks} trials ({backend})")
    started = time.perf_counter()
    with durable_runs(stores, out / "checkpoints"):
        parts = run_chunks(
            experiment.run_chunk,
            plan,
            backend=backend,
            workers=getattr(args, "workers", 0) or None,
            address=getattr(args, "ray_address", "") or None,
            num_cpus=getattr(args, "ray_cpus", 0) or None,
        )
        results = assemble(experiment, parts, chunks)
        return experiment.report(results, time.perf_counter() - started)


def assemble(experiment: Experiment, parts: list[dict], chunks: int) -> dict:
    """The runs' chunks (in plan order) joined along the trial axis, with the t-tests."""
    runs = [(name, method) for name in experiment.schedules for method in METHODS]
    results: dict = {}
    for j, (name, method) in enumerate(runs):
        entry = results.setdefault(name, {"schedule": list(experiment.schedules[name]), "runs": {}})
        entry["runs"][method] = concatenate(parts[j * chunks : (j + 1) * chunks])
    for entry in results.values():
        al, pl = (entry["runs"][m]["iterations"][-1] for m in METHODS)
        entry["t_tests"] = {
            m: {"iteration": al["iteration"], **paired_test(al[m], pl[m])}
            for m in experiment.t_tests
        }
    return results


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
    test = None
    if len(a) > 1 and not np.all(a - p == (a - p)[0]):
        test = scipy.stats.ttest_rel(a, p)
    return {
        "mean_difference": float((a - p).mean()),
        "t": None if test is None else float(test.statistic),
        "p": None if test is None else float(test.pvalue),
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


def long_rows(results: dict) -> Iterator[tuple]:
    """Every per-trial number of the experiment, one ``COLUMNS`` tuple each.

    A list over trials gives trial t its element; a number of the iteration (the same for
    every trial, e.g. ``rewarded_transitions``) is repeated per trial; a vector per trial
    (``j_mean``, J' of the K candidates) becomes measures ``j_mean_k1`` … ``j_mean_kK``.
    """
    for name, entry in results.items():
        for method, run in entry["runs"].items():
            for it in run["iterations"]:
                trials = max(len(v) for v in it.values() if isinstance(v, list))
                for t in range(trials):
                    head = (name, method, run["seed"], it["iteration"], t)
                    for key, value in it.items():
                        value = value[t] if isinstance(value, list) else value
                        if key in NOT_IN_CSV or value is None:
                            continue
                        if isinstance(value, list):
                            for k, x in enumerate(value):
                                yield (*head, f"{key}_k{k + 1}", x)
                        else:
                            yield (*head, key, value)


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


def write_results(args, experiment: Experiment, results: dict, wall: float, **extra) -> dict:
    """``<name>.csv`` (:func:`long_rows`) and ``<name>.json`` (arguments, wall time, t-tests,
    the runs' settings and totals; ``extra``: more entries) in ``--out-dir``; the learning
    curves with ``--logger``.

    Returns the JSON's payload, with ``results`` (every number, in memory) added.
    """
    out = Path(args.out_dir)
    with (out / f"{experiment.name}.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        writer.writerows(long_rows(results))
    summary = {
        name: {
            "schedule": entry["schedule"],
            "t_tests": entry["t_tests"],
            "runs": {
                method: {k: v for k, v in run.items() if k != "iterations"}
                for method, run in entry["runs"].items()
            },
        }
        for name, entry in results.items()
    }
    payload = {"args": asdict(args), "wall_seconds": wall, **extra}
    (out / f"{experiment.name}.json").write_text(json.dumps({**payload, "summary": summary}))
    log_curves(args.logger, out, experiment, results)
    return {**payload, "summary": summary, "results": results}


def log_curves(kind: str, out: Path, experiment: Experiment, results: dict) -> None:
    """With a TorchRL logger (``--logger``: csv, tensorboard, wandb) under ``<out>/logs``:
    ``<schedule>/<method>/<measure>`` = the mean over trials of each curve, per iteration."""
    if kind == "none":
        return
    from torchrl.record.loggers import get_logger

    logger = get_logger(kind, logger_name=str(out / "logs"), experiment_name=experiment.name)
    for name, entry in results.items():
        for method, run in entry["runs"].items():
            for it in run["iterations"]:
                for measure in experiment.curves:
                    value = it.get(measure)
                    if isinstance(value, list):
                        value = sum(value) / len(value) if value else None
                    if value is not None:
                        logger.log_scalar(
                            f"{name}/{method}/{measure}", float(value), step=it["iteration"]
                        )


# -- durable runs: --resume / --overwrite, signals -------------------------------------------


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived (raised in the main thread by :func:`raise_on_signals`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def raise_on_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise :class:`Interrupted` in the main thread; the
    handlers before it are restored after it.

    The run's store holds both back while it commits, so the exception arrives between
    commits: the write in flight always completes.
    """

    def handler(signum, frame):
        raise Interrupted(signum)

    before = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in before.items():
            signal.signal(sig, old)


@contextlib.contextmanager
def durable_runs(paths: Sequence[Path], where: str | os.PathLike) -> Iterator[None]:
    """The block runs (and stores) the runs at ``paths``; SIGINT/SIGTERM end it with the one
    line of :func:`exit_interrupted` (exit 130/143, the commit in flight completed), a store
    error with the one line of :func:`exit_store_error` (exit 1)."""
    try:
        with raise_on_signals():
            yield
    except Interrupted as interrupt:
        exit_interrupted(interrupt.signum, paths, where)
    except StoreError as error:
        exit_store_error(error)


def stored_runs_error(paths: Sequence[Path], resume: bool, overwrite: bool) -> str | None:
    """Why the script must not start: runs are stored at ``paths`` and neither ``--resume`` nor
    ``--overwrite`` was given (or both were); None if it may."""
    if resume and overwrite:
        return "--resume and --overwrite exclude each other"
    held = [p for p in paths if p.is_file() and p.stat().st_size > 0]
    if held and not (resume or overwrite):
        names = ", ".join(str(p) for p in held[:3]) + (" ..." if len(held) > 3 else "")
        return (
            f"runs are stored already ({names}); add --resume to continue them or --overwrite "
            "to discard them"
        )
    return None


def stored_summary(paths: Sequence[Path]) -> tuple[int, int]:
    """(the iteration in flight, rewarded episodes stored over all trials) of the runs stored
    at ``paths`` (read only; missing or unreadable files count as empty)."""
    in_flight, episodes, last = [], 0, 0
    for path in paths:
        if not Path(path).is_file():
            continue
        try:
            stored = RunStore.read(path)
        except StoreError:
            continue
        trials = stored.config.get("num_trials") or 1
        episodes += stored.num_episodes * trials
        done, total = len(stored.records), len(stored.config.get("schedule", []))
        last = max(last, done)
        if done < total:
            in_flight.append(done + 1)
    return (min(in_flight) if in_flight else last), episodes


def exit_interrupted(signum: int, paths: Sequence[Path], where: str | os.PathLike) -> None:
    """Print the one line of an interrupted run and exit with 128 + the signal (130, 143)."""
    iteration, episodes = stored_summary(paths)
    print(
        f"interrupted at iteration {iteration}; {episodes} rewarded episodes stored in {where}; "
        "continue with --resume",
        file=sys.stderr,
        flush=True,
    )
    raise SystemExit(128 + signum)


def exit_store_error(error: BaseException) -> None:
    """A store error (a run in use, unwritable, corrupted, of other settings) as one line."""
    print(f"error: {error}", file=sys.stderr, flush=True)
    raise SystemExit(1)
