"""Independent chunks of trials run one after another in-process, in local worker processes, or
as Ray tasks.

Trials of an experiment are independent: with ``trial_seeds`` (see
:class:`~torch_api.loop.iteration.ActivePolicyIteration`) trial t draws from streams of its own, so
the trials can be split into chunks, each chunk run as one batched computation wherever there is
room, and the results concatenated along the trial axis. For environments with
``set_block_seeds`` the concatenation equals one batched run of all trials, bit for bit.

``backend="processes"`` runs the chunks in a pool of local worker processes: on a machine whose
work alternates between native physics and single-threaded algebra, two or more chunks in flight
keep every core busy. ``backend="ray"`` needs the ``ray`` extra (``pip install torch-api[ray]``).

Workers die with their parent: a reaper process SIGKILLs the local workers (and what they
started) within a fraction of a second of the parent's death, even while they still import
torch (:func:`~torch_api.runs.lifetime.workers_die_with_this_process`, Linux); a local worker
also asks the kernel for SIGKILL when its parent dies (``PR_SET_PDEATHSIG``) and, everywhere, a
watchdog thread ends it once its parent is gone; a Ray task on the parent's host does the same
when the parent process is gone. An interrupted
``run_chunks`` (SIGINT, SIGTERM, an error) terminates its local workers before returning. A
worker killed half-way through a chunk loses at most what its run had not yet committed; with
``ActivePolicyIteration(durable=DurableRun(path))`` the run's lock keeps a resume from racing a
worker that is still finishing.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import socket
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

import torch

from torch_api.runs.lifetime import die_with_parent, workers_die_with_this_process
from torch_api.streams import trial_seeds_of

__all__ = ["BACKENDS", "run_chunks", "split_trials", "threads_per_worker", "trial_seeds"]

BACKENDS = ("local", "processes", "ray")

C = TypeVar("C")
R = TypeVar("R")


def split_trials(num_trials: int, num_chunks: int) -> list[range]:
    """Split trials ``0 … T-1`` into ``num_chunks`` consecutive ranges of near-equal size.

    The first ``T mod num_chunks`` ranges hold one trial more; none is empty.

    Example:
        >>> split_trials(7, 3)
        [range(0, 3), range(3, 5), range(5, 7)]
    """
    if num_trials < 1:
        raise ValueError(f"num_trials must be >= 1, got {num_trials}")
    if not 1 <= num_chunks <= num_trials:
        raise ValueError(f"num_chunks must lie in 1 … num_trials = {num_trials}, got {num_chunks}")
    size, extra = divmod(num_trials, num_chunks)
    bounds = [0]
    for c in range(num_chunks):
        bounds.append(bounds[-1] + size + (c < extra))
    return [range(a, b) for a, b in zip(bounds, bounds[1:], strict=False)]


def trial_seeds(seed: int, trials: Sequence[int]) -> list[int]:
    """Seeds of the given trials of a run seeded ``seed``: ``derive_seed(seed, t, "trial")``.

    These are the seeds :class:`~torch_api.loop.iteration.ActivePolicyIteration` gives its trials by
    default, so a chunk run with ``trial_seeds=trial_seeds(seed, chunk)`` draws exactly what
    those trials draw in one run of all trials with ``seed``. Trial t's seed depends on
    ``(seed, t)`` only, never on the chunking.

    Example:
        >>> trial_seeds(0, range(3))[1:] == trial_seeds(0, [1, 2])
        True
    """
    return trial_seeds_of(seed, trials)


def threads_per_worker(workers: int) -> int:
    """Threads each of ``workers`` local worker processes may use: the CPUs shared out, >= 1."""
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _init_worker(threads: int, parent: int, direct: bool = True) -> None:
    # (a forkserver's worker is the server's child: it watches the caller by its pid)
    die_with_parent(parent, direct=direct)
    # Ctrl-C reaches the whole process group: the parent alone handles it (and ends the
    # workers), so a worker does not print a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a forked worker inherits the parent's handlers: SIGTERM ends it, as a spawned one
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    torch.set_num_threads(threads)


_INHERITED: tuple[Callable, Sequence] | None = None
"""``(fn, chunks)`` of the :func:`run_chunks` call whose forked workers are running: a forked
worker finds them here, so neither needs to be picklable (e.g. a script run under ``python -m
cProfile``, whose functions are not importable as ``__main__``'s)."""


def _run_inherited(i: int):
    fn, chunks = _INHERITED
    return fn(chunks[i])


def _guarded_call(fn, pid: int, host: str, chunk):
    """``fn(chunk)`` as a Ray task that dies with the driver process ``pid`` on ``host``."""
    if socket.gethostname() == host:
        die_with_parent(pid, direct=False)
    return fn(chunk)


def _check_picklable(fn, start_method: str) -> None:
    """A worker started with ``start_method`` (not forked) receives ``fn`` pickled: refuse one
    that is not, here, rather than in the pool's feeder thread once workers are up."""
    try:
        pickle.dumps(fn)
    except (pickle.PicklingError, AttributeError, TypeError) as error:
        raise TypeError(
            f"fn {fn!r} is not picklable ({error}), and workers started with "
            f"start_method={start_method!r} receive it pickled: pass a top-level function, or "
            "start_method='fork' (POSIX) to let the workers inherit it"
        ) from error


def _run_in_pool(fn, chunks, workers: int, start_method: str, done) -> list:
    """The chunks in a pool of local worker processes (``backend="processes"``)."""
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(chunks)),
        mp_context=multiprocessing.get_context(start_method),
        initializer=_init_worker,
        initargs=(threads_per_worker(workers), os.getpid(), start_method != "forkserver"),
    )
    global _INHERITED
    _INHERITED = (fn, chunks)  # before the first worker forks (they start on submit)
    try:
        if start_method == "fork":  # the workers hold fn and the chunks already
            futures = {pool.submit(_run_inherited, i): i for i in range(len(chunks))}
        else:
            futures = {pool.submit(fn, chunk): i for i, chunk in enumerate(chunks)}
        results = [None] * len(chunks)
        for future in as_completed(futures):
            results[futures[future]] = future.result()
            done(futures[future], results[futures[future]])
    except BaseException:  # interrupted or failed: no worker outlives the call
        processes = list((getattr(pool, "_processes", None) or {}).values())
        for process in processes:
            process.terminate()  # SIGTERM: a commit in flight completes (SQLite)
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.join(timeout=10)
        raise
    finally:
        _INHERITED = None
    pool.shutdown()
    return results


def _import_ray():
    try:
        import ray
    except ImportError as error:
        raise ImportError(
            "backend='ray' needs Ray: pip install 'torch-api[ray]' (or pip install ray)"
        ) from error
    return ray


def run_chunks(
    fn: Callable[[C], R],
    chunks: Sequence[C],
    *,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    num_cpus: int | None = None,
    runtime_env: dict[str, Any] | None = None,
    on_result: Callable[[int, R], None] | None = None,
    start_method: str = "spawn",
) -> list[R]:
    """``[fn(chunk) for chunk in chunks]``, in-process or as Ray tasks; results in chunk order.

    Args:
        fn: a top-level (picklable) function of one chunk, e.g. a list of trial indices plus
            the run's settings, returning a picklable result (plain lists and dicts, tensors).
        chunks: the chunks, each independent of the others.
        backend: ``"local"`` runs the chunks here one after another; ``"processes"`` in a pool
            of ``workers`` local processes (started with ``start_method``; each limits torch to
            :func:`threads_per_worker` threads), taking the chunks in the order given;
            ``"ray"`` runs each as a Ray remote task (one CPU each) and gathers the results.
        workers: processes only: the pool size (default: ``os.cpu_count()``).
        address: Ray only: the cluster to join (e.g. ``"ray://head:10001"`` or ``"auto"``);
            ``None`` starts a local Ray instance. Ignored if Ray is initialised already.
        num_cpus: Ray only: CPUs of a local instance started here (default: all).
        runtime_env: Ray only: the ``runtime_env`` of ``ray.init`` (e.g.
            ``{"working_dir": "."}`` to ship this checkout to a cluster whose nodes lack it).
        on_result: called here, in the calling process, as ``on_result(i, result)`` when
            chunk ``i``'s result arrives (in the order they finish), e.g. to move a progress
            bar over the whole experiment.
        start_method: processes only: ``"spawn"`` (the default), ``"forkserver"`` or
            ``"fork"`` (POSIX: the workers start at once with everything the caller has
            imported, instead of importing torch again each; only from a caller that runs no
            other threads holding locks, e.g. a command-line script before its work starts).

    Returns:
        ``[fn(c) for c in chunks]``. A Ray instance started here is shut down afterwards; one
        initialised before the call is left running.

    Example:
        >>> run_chunks(sum, [[1, 2], [3], [4, 5, 6]])
        [3, 3, 15]
        >>> run_chunks(sum, [[1, 2], [3]], backend="ray", num_cpus=2)  # doctest: +SKIP
        [3, 3]
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    done = on_result or (lambda i, result: None)
    if backend == "local":
        results = []
        for i, chunk in enumerate(chunks):
            results.append(fn(chunk))
            done(i, results[-1])
        return results
    if backend == "processes":
        if not chunks:
            return []
        workers = workers or os.cpu_count() or 1
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if start_method != "fork":
            _check_picklable(fn, start_method)
        with workers_die_with_this_process():  # even while they still import torch
            return _run_in_pool(fn, chunks, workers, start_method, done)
    ray = _import_ray()
    started_here = not ray.is_initialized()
    if started_here:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage reports
        options: dict[str, Any] = {"include_dashboard": False, "runtime_env": runtime_env}
        if address is None:
            options["num_cpus"] = num_cpus
        ray.init(address=address, **options)
    try:
        task = ray.remote(num_cpus=1)(_guarded_call)
        driver = (os.getpid(), socket.gethostname())
        pending = {task.remote(fn, *driver, chunk): i for i, chunk in enumerate(chunks)}
        results = [None] * len(chunks)
        waiting = list(pending)
        while waiting:
            ready, waiting = ray.wait(waiting, num_returns=1)
            results[pending[ready[0]]] = ray.get(ready[0])
            done(pending[ready[0]], results[pending[ready[0]]])
        return results
    finally:
        if started_here:
            ray.shutdown()
