"""The files of a run's store around its database (:mod:`torch_api.runs.store`): its atomic creation,
and the commit counter that a shortened write-ahead log cannot hide.

* creation: the schema and the ``meta`` rows are written in one transaction into
  ``PATH.new``, which is synced and renamed onto ``PATH``: an interrupt at any instant leaves
  either no store or a complete empty one, never a database without its tables or ``meta``;
* the commit counter ``PATH.commits`` holds, after every commit, the number of commits and of
  bought episode rows (and a digest of both), synced. The committed rows of a killed writer
  live in ``PATH-wal`` until they are checkpointed, and SQLite ends the log silently at the
  first frame whose checksum fails: a store that holds fewer commits than its counter has lost
  committed rows, and is refused saying how many.
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
from collections.abc import Callable
from pathlib import Path

from torch_api.runs.store_errors import CorruptRunError

__all__ = ["COMPANIONS", "create_atomically", "lost_rows_error", "read_counter", "write_counter"]

COMPANIONS = ("-wal", "-shm", "-journal")
"""SQLite's files beside a database ``PATH`` (``PATH-wal`` ...)."""


def _fsync(path: Path, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    for p in (path, *(Path(f"{path}{s}") for s in COMPANIONS)):
        p.unlink(missing_ok=True)


def create_atomically(path: Path, fill: Callable[[sqlite3.Connection], None]) -> None:
    """Make ``path`` an empty store: ``fill(db)`` (the schema, the ``meta`` rows) runs in one
    transaction on ``PATH.new``, which is then synced and renamed onto ``path``; the store at
    ``path`` (its log and its counter included) is discarded first. The caller holds the lock.
    """
    new = Path(f"{path}.new")
    _remove(new)  # a creation cut short before
    db = sqlite3.connect(new, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.execute("BEGIN IMMEDIATE")
        fill(db)
        db.execute("COMMIT")
    finally:
        db.close()  # checkpoints the log into the file and removes it
    _fsync(new)
    write_counter(path, 0, 0)  # (the store at path, if any, is discarded next)
    _remove(path)
    os.replace(new, path)
    _fsync(path.parent, directory=True)


def _counter_line(commits: int, episodes: int) -> bytes:
    digest = hashlib.sha256(f"{commits} {episodes}".encode()).hexdigest()[:16]
    return f"commits {commits} episodes {episodes} {digest}\n".encode()


def write_counter(path: Path, commits: int, episodes: int) -> None:
    """Record, synced, that the store at ``path`` holds ``commits`` commits and ``episodes``
    bought episode rows (called right after each commit). Written to ``PATH.commits.new`` and
    renamed over the counter: a kill at any instant leaves the old count or the new one (an
    old one is a store one commit ahead: accepted), never an empty or half-written counter."""
    new = Path(f"{path}.commits.new")
    new.unlink(missing_ok=True)
    fd = os.open(new, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        os.write(fd, _counter_line(commits, episodes))
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(new, Path(f"{path}.commits"))


def read_counter(path: Path) -> tuple[int, int] | None:
    """(commits, episode rows) recorded for the store at ``path``; None if no counter is kept.

    Raises:
        CorruptRunError: the counter is damaged.
    """
    counter = Path(f"{path}.commits")
    try:
        text = counter.read_bytes()
    except FileNotFoundError:
        return None
    try:
        _, commits, _, episodes, _ = text.decode().split()
        if _counter_line(int(commits), int(episodes)) == text:
            return int(commits), int(episodes)
    except (ValueError, UnicodeError):
        pass
    raise CorruptRunError(
        f"the commit counter {counter} of the run {path} is damaged ({text[:80]!r}); if the "
        "store itself is intact, remove the counter to accept it as it is"
    )


def lost_rows_error(path: Path, commits: int, episodes: int) -> CorruptRunError | None:
    """The refusal of a store at ``path`` that holds ``commits`` commits and ``episodes``
    episode rows where its counter recorded more commits (rows lost), or None."""
    counter = read_counter(path)
    if counter is None or counter[0] <= commits:
        return None
    return CorruptRunError(
        f"the run {path} lost committed rows: its counter {path}.commits recorded {counter[0]} "
        f"commits holding {counter[1]} bought episode rows, the store holds {commits} commits "
        f"and {episodes} rows ({max(counter[1] - episodes, 0)} episode rows and "
        f"{counter[0] - commits} commits missing; its write-ahead log {path}-wal was cut short "
        "or damaged). Nothing was changed: restore the files from a copy, or discard the run "
        "with --overwrite"
    )
