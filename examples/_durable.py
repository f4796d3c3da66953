"""Durable runs of the examples: a folder holding runs needs ``--resume`` or ``--overwrite``;
SIGINT/SIGTERM (the commit in flight completes) and store errors end the script with one line.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from torch_api.store import RunStore, StoreError


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
