"""The paired experiment: AL and PL runs on the same seeds, chunked, stored, tested, written.

An experiment runs Algorithm 1 twice per schedule of rewarded episodes on the same seeds (a
paired design): AL (the sampling policy chosen by J', ``spec.selection``) and PL (the
evaluation policy samples, ``selection=None``). A script supplies what is its own — the
environment, the basis, the evaluation of pi_{l+1}, as a function of one :class:`Chunk` that
builds its run with :func:`make_iteration` and returns :func:`run_iterations` — and
:func:`run_experiment` does the rest:

1. the trials of every run split into chunks (``Execution.chunks``), each run as one batched
   computation where ``Execution.backend`` says (:func:`torch_api.runs.dispatch.run_chunks`),
   every chunk stored as it goes in ``<out_dir>/checkpoints/`` (``resume``, ``overwrite``);
2. SIGINT/SIGTERM: the commit in flight completes, one line, exit 130/143; a store error
   (a run in use, unwritable, corrupted, of another specification): one line, exit 1
   (:mod:`torch_api.experiment.folder`);
3. the chunks of a run concatenated along the trial axis, the paired two-tailed t-test of AL vs
   PL at the last iteration, then the script's report (its tables and files,
   :mod:`torch_api.experiment.results`).

One result layout for every experiment, in memory::

    results[schedule] = {"schedule": [M_1, …, M_L], "t_tests": {measure: {...}},
                         "runs": {"AL": run, "PL": run}}
    run = {"seed": int, "seconds": float, "iterations": [row_l, …], …}
    row_l = {"iteration": l, measure: [T] per trial or one number, "j_mean": [T][K], …}

and on disk (:func:`~torch_api.experiment.results.write_results`): ``<name>.csv`` in long
format, one row per (schedule, method, seed, iteration, trial, measure) with its ``value``
— every per-trial number of the experiment — and ``<name>.json`` with the arguments, the wall
time, the t-tests and every run's settings and totals.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from torch_api.experiment.folder import durable_runs, folder_held
from torch_api.experiment.options import Execution
from torch_api.experiment.results import METHODS, paired_test
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.spec import RunSpec
from torch_api.runs.dispatch import run_chunks, split_trials, trial_seeds

__all__ = [
    "Chunk",
    "Experiment",
    "derived_seed",
    "make_iteration",
    "run_experiment",
    "run_iterations",
]


def derived_seed(*parts: int, bits: int = 31) -> int:
    """A seed of ``bits`` (31 or 63) bits derived from integers (distinct parts, distinct seeds)."""
    dtype = np.uint32 if bits == 31 else np.uint64
    return int(np.random.SeedSequence(list(parts)).generate_state(1, dtype)[0] >> 1)


# -- one run of a chunk of trials ------------------------------------------------------------


@dataclass
class Chunk:
    """Some trials of one run (a schedule and a method), run as one batch and stored."""

    args: Any
    """the script's own arguments (a picklable dataclass)"""
    execution: Execution
    """where it runs (``resume``, ``overwrite``)"""
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
    on_iteration: Callable[[], None] | None = None
    """called after every iteration the chunk runs (the experiment's progress bar; local only)"""
    on_commit: Callable[[], None] | None = None
    """called after every commit of the chunk's run (local backend only: it does not travel)"""
    spec: RunSpec | None = None
    """the experiment's specification, if it has one (:attr:`Experiment.spec`)"""

    @property
    def mode(self) -> str:
        return METHODS[self.method]


def make_iteration(chunk: Chunk, spec: RunSpec, **objects) -> ActivePolicyIteration:
    """The chunk's run of Algorithm 1: ``spec`` with the chunk's mode (AL: its selection; PL:
    none), its trials and their seeds (trial t's seed from (run seed, t) only, so any chunking
    gives the same numbers), stored in ``chunk.store``; ``objects``: the loop's other arguments
    (env, basis, evaluate, selector, device, ...)."""
    selection = spec.selection if chunk.mode == "active" else None
    if chunk.mode == "active" and selection is None:
        raise ValueError("an AL chunk needs spec.selection (the settings of Algorithm 2)")
    if chunk.mode == "passive":
        objects.pop("selector", None)  # (PL: the evaluation policy samples)
    trials = dataclasses.replace(
        spec.trials,
        num_trials=len(chunk.trials),
        trial_seeds=tuple(trial_seeds(chunk.seed, chunk.trials)),
    )
    execution = chunk.execution
    return ActivePolicyIteration(
        dataclasses.replace(spec, selection=selection, trials=trials),
        durable=DurableRun(
            chunk.store,
            resume=execution.resume,
            overwrite=execution.overwrite,
            on_commit=chunk.on_commit,
        ),
        **objects,
    )


def run_iterations(chunk: Chunk, api: ActivePolicyIteration, initial: dict | None = None) -> dict:
    """Run (or resume) ``api`` to its end; the chunk's part of the run.

    ``initial``: the evaluation of pi_1, recorded as iteration 0.
    """
    if api.resumed:
        print(f"resumed {chunk.store} at iteration {api.iteration}/{len(chunk.schedule)}")
    elif chunk.execution.resume:
        print(f"nothing stored in {chunk.store}: starting it fresh")
    started = time.perf_counter()
    for _ in range(api.iteration, len(api.schedule)):
        api.step()
        if chunk.on_iteration is not None:
            chunk.on_iteration()
    history = api.run()  # nothing left to run: closes the store, returns the whole history
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
        for key in ("seconds", "selection_cpu_seconds"):  # (the chunks' times add up)
            if row.get(key) is not None:
                row[key] = sum(it[key] for it in its)
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
    files: tuple[str, ...] = ()
    """the files ``report`` writes besides ``<name>.json`` and ``<name>.csv`` (its figures)"""
    trials: int = 2
    """T, the trials of every run (a paired t-test needs two)"""
    seed: int = 0
    """the master seed (``run_seed`` derives each schedule's from it)"""
    spec: RunSpec | None = None
    """the runs' specification (AL's; PL's drops the selection), checked for all the trials
    before anything starts (a run too large for memory is refused at once); each
    :class:`Chunk` carries it"""

    def outputs(self, out: Path) -> list[Path]:
        """The files the experiment writes into ``out``, its JSON first."""
        return [out / f"{self.name}.json", out / f"{self.name}.csv", *(out / f for f in self.files)]


def store_path(out: Path, experiment: Experiment, schedule: str, method: str, c: int, n: int):
    """``<out>/checkpoints/<stem>.db``, ``<stem>_chunk<c>of<C>.db`` (c = 1 … C) if C > 1."""
    stem = experiment.store_stem.format(schedule=schedule, method=method, mode=METHODS[method])
    return out / "checkpoints" / (stem + ("" if n == 1 else f"_chunk{c + 1}of{n}") + ".db")


def run_experiment(
    experiment: Experiment,
    execution: Execution,
    args: Any,
    on_commit: Callable[[], None] | None = None,
) -> dict:
    """Every run of the experiment, chunked where ``execution`` says, then
    ``experiment.report(results, wall seconds)``, whose payload it returns.

    ``args``: the script's own arguments (a dataclass), handed to every :class:`Chunk` and
    written into the results' JSON. Ends the script with one line where the output folder
    holds runs and neither ``resume`` nor ``overwrite`` was given, on SIGINT/SIGTERM (until the
    report is written) and on a store error (see the module). ``on_commit``: called after
    every commit of every run (local backend only: it does not travel).
    """
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # quiet storage-creation notices
    if execution.threads > 0:
        torch.set_num_threads(execution.threads)
    for schedule in experiment.schedules.values() if experiment.spec is not None else ():
        # every run's specification, checked before any list of trials is made
        experiment.spec.replace(
            schedule=tuple(schedule), num_trials=experiment.trials, trial_seeds=None
        )
    execution.check_chunks(experiment.trials)
    out = Path(execution.out_dir)
    backend, chunks = execution.backend, execution.chunks
    runs = [(name, method) for name in experiment.schedules for method in METHODS]
    pieces = split_trials(experiment.trials, chunks)
    plan = [
        Chunk(
            args=args,
            execution=execution,
            schedule_name=name,
            schedule=tuple(experiment.schedules[name]),
            method=method,
            seed=experiment.run_seed(experiment.seed, name),
            trials=list(trials),
            store=store_path(out, experiment, name, method, c, chunks),
            on_commit=on_commit if backend == "local" else None,
            spec=experiment.spec,
        )
        for name, method in runs
        for c, trials in enumerate(pieces)
    ]
    stores = [chunk.store for chunk in plan]
    with (
        folder_held(out, stores, experiment.outputs(out), execution, args),
        durable_runs(stores, out / "checkpoints"),
    ):
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        print(f"{len(plan)} chunks of about {experiment.trials // chunks} trials ({backend})")
        # one bar for the whole experiment: every iteration of every chunk, with its ETA
        total = [len(chunk.schedule) for chunk in plan]
        bar = tqdm(
            total=sum(total), desc=f"{experiment.name}, {len(plan)} chunks", unit="iteration"
        )
        if backend == "local":
            for chunk in plan:
                chunk.on_iteration = bar.update

        def chunk_done(i: int, result: dict) -> None:
            # a worker's chunk moves the bar when it returns; a local one has moved it already
            # (by its iterations; a resumed chunk's stored ones are added here)
            bar.update(sum(total[: i + 1]) - bar.n if backend == "local" else total[i])

        started = time.perf_counter()
        try:
            parts = run_chunks(
                experiment.run_chunk,
                plan,
                backend=backend,
                workers=execution.workers or None,
                address=execution.ray_address or None,
                num_cpus=execution.ray_cpus or None,
                on_result=chunk_done,
                start_method=_start_method(),
            )
        finally:  # before a signal's or an error's last line
            bar.close()
        results = assemble(experiment, parts, chunks)
        return experiment.report(results, time.perf_counter() - started)


def _start_method() -> str:
    """Linux: local workers forked from this process start at once, with torch imported (no
    thread of this process holds a lock then); elsewhere, or once CUDA is initialised here
    (which a fork does not survive), fresh interpreters."""
    return "fork" if sys.platform == "linux" and not torch.cuda.is_initialized() else "spawn"


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
