"""Durable runs of an experiment's output folder: one run writes a folder at a time (its lock
is held from the first check to the last file written); a folder holding runs or another
run's results needs ``resume`` or ``overwrite``; SIGINT/SIGTERM (the commit in flight
completes) and store errors end the script with one line.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from torch_api.runs.run_guard import lock_run
from torch_api.runs.store import RunStore, StoreError

MAY_CHANGE_ON_RESUME = ("execution", "device")
"""Arguments a resumed run may give otherwise than the run whose results are in its folder
(where and how fast it runs, not what it computes: the :class:`Execution` and the device)."""


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


@contextlib.contextmanager
def folder_held(
    out: Path, stores: Sequence[Path], outputs: Sequence[Path], execution, args=None
) -> Iterator[None]:
    """The block writes the output folder ``out`` (its runs at ``stores``, its files
    ``outputs``) holding the folder's lock (``<out>/.folder.lock``): a second script on the
    folder, ``--overwrite`` included, ends with one line (exit 1) before it touches anything.
    Before the block: misplaced paths or a folder that cannot be made (exit 2), then
    :func:`stored_runs_error` (exit 1)."""
    if (why := misplaced_error(stores, outputs)) is not None:
        print(f"error: {why}", file=sys.stderr, flush=True)
        raise SystemExit(2)
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
    except OSError as error:
        print(f"error: out_dir {str(out)!r} cannot be made: {error}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    try:
        fd = lock_run(Path(out) / ".folder", what=f"the folder {out}")
    except StoreError as error:
        exit_store_error(error)
    try:
        if (
            why := stored_runs_error(stores, execution.resume, execution.overwrite, outputs, args)
        ) is not None:
            raise SystemExit(f"error: {why}")
        yield
    finally:
        os.close(fd)


def misplaced_error(stores: Sequence[Path], outputs: Sequence[Path]) -> str | None:
    """Why the script could not write its files: a store's folder or one of its files exists
    as something else (a file where a folder goes, a folder where a file goes); None if not."""
    for folder in dict.fromkeys(Path(p).parent for p in stores):
        if folder.exists() and not folder.is_dir():
            return f"{folder} is in the way: a file where the stored runs' folder goes"
    for path in map(Path, [*stores, *outputs]):
        if path.exists() and not path.is_file():
            return f"{path} is in the way: not a file, where the script writes one"
    return None


def stored_runs_error(
    paths: Sequence[Path], resume: bool, overwrite: bool, outputs: Sequence[Path] = (), args=None
) -> str | None:
    """Why the script must not start, or None if it may: both ``--resume`` and ``--overwrite``;
    or neither, and runs are stored at ``paths`` or beside them, or the results ``outputs`` of
    a run are there; or ``--resume`` of a run of other arguments than the results' (``args``,
    a dataclass, against the arguments in the first output, a JSON file)."""
    if resume and overwrite:
        return "--resume and --overwrite exclude each other"
    if overwrite:
        return None
    if resume:
        return None if args is None or not outputs else _other_results(Path(outputs[0]), args)
    beside = [q for folder in {Path(p).parent for p in paths} for q in sorted(folder.glob("*.db"))]
    held = [p for p in dict.fromkeys([*paths, *beside]) if p.is_file() and p.stat().st_size > 0]
    if held:
        names = ", ".join(str(p) for p in held[:3]) + (" ..." if len(held) > 3 else "")
        return (
            f"runs are stored already ({names}); add --resume to continue them or --overwrite "
            "to discard them"
        )
    if made := [str(p) for p in outputs if Path(p).exists()]:
        return (
            f"the results of a run are in the folder already ({', '.join(made)}); add "
            "--overwrite to replace them, or write into another --out-dir"
        )
    return None


def _other_results(results: Path, args) -> str | None:
    """Why ``--resume`` with ``args`` must not replace the results file ``results``, or None."""
    try:
        theirs = json.loads(results.read_text())["args"]
    except (OSError, ValueError, KeyError, TypeError):
        return None  # no results (or unreadable ones): nothing of another run to keep
    mine = json.loads(json.dumps(_plain(args)))
    differ = [
        f"--{k.replace('_', '-')} {theirs.get(k)!r}, not {mine.get(k)!r}"
        for k in sorted(theirs.keys() | mine.keys())
        if k not in MAY_CHANGE_ON_RESUME and theirs.get(k) != mine.get(k)
    ]
    if not differ:
        return None
    return (
        f"the results in {results} are of a run with other arguments ({'; '.join(differ[:3])}); "
        "resume it with its own, add --overwrite to replace them, or use another --out-dir"
    )


def _plain(args) -> dict:
    """A script's arguments as the results' JSON holds them."""
    return dataclasses.asdict(args) if dataclasses.is_dataclass(args) else dict(vars(args))


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
        config = stored.config  # (a loop's identity: "rewarded.schedule", "trials.num_trials")
        trials = config.get("num_trials", config.get("trials.num_trials")) or 1
        episodes += stored.num_episodes * trials
        schedule = config.get("schedule", config.get("rewarded.schedule", []))
        done, total = len(stored.records), len(schedule)
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
