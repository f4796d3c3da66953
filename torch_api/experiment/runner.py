"""The paired experiment behind the iterative examples: runs, chunks, statistics and files.

An experiment runs Algorithm 1 twice per schedule of rewarded episodes on the same seeds (a
paired design): AL (``selector=SamplingPolicySelector(...)``, the sampling policy chosen by J')
and PL (``selector=None``: the evaluation policy samples). An example supplies what is its own —
the environment, the basis, the evaluation of pi_{l+1}, as a function of one :class:`Chunk` that
builds its run with :func:`make_iteration` and returns :func:`run_iterations` — and
:func:`run_experiment` does the rest:

1. the trials of every run split into chunks (``--chunks``), each run as one batched
   computation where ``--backend`` says (``torch_api.runs.dispatch.run_chunks``), every chunk stored
   as it goes in ``<out-dir>/checkpoints/`` (``--resume``, ``--overwrite``);
2. SIGINT/SIGTERM: the commit in flight completes, one line, exit 130/143; a store error
   (a run in use, unwritable, corrupted, of other settings): one line, exit 1 (:mod:`_durable`);
3. the chunks of a run concatenated along the trial axis, the paired two-tailed t-test of AL vs
   PL at the last iteration, then the example's report (its tables and files, :mod:`_results`,
   re-exported here).

One result layout for every experiment, in memory::

    results[schedule] = {"schedule": [M_1, …, M_L], "t_tests": {measure: {...}},
                         "runs": {"AL": run, "PL": run}}
    run = {"seed": int, "seconds": float, "iterations": [row_l, …], …}
    row_l = {"iteration": l, measure: [T] per trial or one number, "j_mean": [T][K], …}

and on disk (:func:`_results.write_results`): ``<name>.csv`` in long format, one row per (schedule,
method, seed, iteration, trial, measure) with its ``value`` — every per-trial number of the
experiment — and ``<name>.json`` with the arguments, the wall time, the t-tests and every run's
settings and totals.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _durable import durable_runs, folder_held, stored_runs_error  # noqa: F401

# the harness is the examples' one entry: the numbers' and the durable runs' parts re-exported
from _process import configure_process
from _results import (  # noqa: F401
    COLUMNS,
    METHODS,
    mean_se,
    paired_test,
    print_curves,
    print_t_tests,
    read_results,
    write_results,
)
from tqdm import tqdm

from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.runs.dispatch import run_chunks, split_trials, trial_seeds


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
    on_iteration: Callable[[], None] | None = None
    """called after every iteration the chunk runs (the experiment's progress bar; local only)"""
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
    files: tuple[str, ...] = ()
    """the files ``report`` writes besides ``<name>.json`` and ``<name>.csv`` (its figures)"""

    def outputs(self, out: Path) -> list[Path]:
        """The files the experiment writes into ``out``, its JSON first."""
        return [out / f"{self.name}.json", out / f"{self.name}.csv", *(out / f for f in self.files)]


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
    configure_process(args)
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
            on_checkpoint=on_checkpoint,
        )
        for name, method in runs
        for c, trials in enumerate(pieces)
    ]
    stores = [chunk.store for chunk in plan]
    with (
        folder_held(out, stores, experiment.outputs(out), args),
        durable_runs(stores, out / "checkpoints"),
    ):
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        print(f"{len(plan)} chunks of about {args.trials // chunks} trials ({backend})")
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
                workers=getattr(args, "workers", 0) or None,
                address=getattr(args, "ray_address", "") or None,
                num_cpus=getattr(args, "ray_cpus", 0) or None,
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
    import torch

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
