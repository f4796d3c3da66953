"""The files of a run's store around its database (:mod:`torch_api.runs.store`): its journal, its
atomic creation, and the commit counter beside it.

* journal: ``journal_mode=DELETE`` and ``synchronous=EXTRA`` (:func:`use_rollback_journal`).
  A commit is written into the database file itself and synced before it returns; the
  rollback journal ``PATH-journal`` exists only while a transaction is open and holds the
  pages as they were before it. So no committed row lives in a side file (a write-ahead log
  held every commit since the last checkpoint, and SQLite ends a log silently at its first
  damaged frame);
* creation: the schema and the ``meta`` rows are written in one transaction into
  ``PATH.new``, which is synced and renamed onto ``PATH``: an interrupt at any instant leaves
  either no store or a complete empty one, never a database without its tables or ``meta``;
* the count, twice: every commit writes ``meta.commits`` inside its transaction, and right
  after it the counter ``PATH.commits`` (commits, bought episode rows, a digest of both),
  synced. :func:`lost_rows_error` compares the two: a database that holds fewer commits than
  its counter (lost, cut, replaced by an older copy), or other rows at the same count, and a
  counter that is missing or damaged beside a database that holds commits, are refused
  saying how many commits are at stake, never resumed as they are.
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
from collections.abc import Callable
from pathlib import Path

from torch_api.runs.store_errors import CorruptRunError

__all__ = [
    "COMPANIONS",
    "create_atomically",
    "lost_rows_error",
    "at_stake",
    "read_counter",
    "unreadable_error",
    "use_rollback_journal",
    "write_counter",
]

COMPANIONS = ("-wal", "-shm", "-journal")
"""SQLite's files beside a database ``PATH`` (``PATH-wal`` ...); a store made before the
rollback journal kept a write-ahead log, converted on its next open."""
_REMEDY = "Nothing was changed: restore the run's files from a copy, or discard it with --overwrite"


def use_rollback_journal(db: sqlite3.Connection) -> None:
    """Commit into the database file itself, synced: ``journal_mode=DELETE`` (a store that kept
    a write-ahead log has it folded into the file first) and ``synchronous=EXTRA`` (the
    journal's removal, which is what commits, is synced with its folder too).

    Raises:
        sqlite3.OperationalError: the journal mode cannot be changed (another process has the
            database open).
    """
    mode = db.execute("PRAGMA journal_mode=DELETE").fetchone()[0]
    if mode.lower() != "delete":
        raise sqlite3.OperationalError(
            f"its journal mode stays {mode!r} (another process has it open?)"
        )
    db.execute("PRAGMA synchronous=EXTRA")


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
        use_rollback_journal(db)
        db.execute("BEGIN IMMEDIATE")
        fill(db)
        db.execute("COMMIT")
    finally:
        db.close()
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
        ValueError: the counter is damaged (the message quotes its start).
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
    raise ValueError(f"{text[:80]!r}")


def lost_rows_error(path: Path, commits: int, episodes: int) -> CorruptRunError | None:
    """The refusal of a store at ``path`` that holds ``commits`` commits and ``episodes``
    episode rows, or None where its counter vouches for it: the counter recorded these
    commits (and rows), or one commit fewer (a kill between a commit and its count), or none
    is kept and the store holds no commit (a store made by hand).

    Refused: fewer commits than the counter recorded (committed rows lost), the same count
    with other rows, and a counter missing or damaged beside a store that holds commits
    (nothing then tells whether commits were lost after them).
    """
    counter = f"{path}.commits"
    holds = f"the store holds {commits} commits and {episodes} bought episode rows"
    try:
        recorded = read_counter(path)
    except ValueError as damage:
        return CorruptRunError(
            f"the commit counter {counter} of the run {path} is damaged ({damage}): {holds}, "
            f"and nothing tells whether more were committed. {_REMEDY}"
        )
    if recorded is None:
        if commits == 0:
            return None
        return CorruptRunError(
            f"the run {path} lost its commit counter {counter}: {holds}, and nothing tells "
            f"whether more were committed. {_REMEDY}"
        )
    want, rows = recorded
    if want > commits:
        return CorruptRunError(
            f"the run {path} lost committed rows: its counter {counter} recorded {want} "
            f"commits holding {rows} bought episode rows, {holds} "
            f"({max(rows - episodes, 0)} episode rows and {want - commits} commits missing; "
            f"the database file {path} or its journal was damaged, removed or replaced by an "
            f"older copy). {_REMEDY}"
        )
    if want == commits and rows != episodes:
        return CorruptRunError(
            f"the run {path} does not match its counter: {counter} recorded {want} commits "
            f"holding {rows} bought episode rows, {holds} (a commit cut short was not rolled "
            f"back: its journal {path}-journal was damaged or removed?). {_REMEDY}"
        )
    return None


def at_stake(path: Path) -> str:
    """``"; its counter ... recorded N commits holding E bought episode rows. Nothing was
    changed: ..."``, what a refusal of the store at ``path`` adds where its counter recorded
    commits (else ``""``)."""
    try:
        recorded = read_counter(path)
    except ValueError:
        recorded = None
    if recorded is None or recorded[0] == 0:
        return ""
    return (
        f"; its counter {path}.commits recorded {recorded[0]} commits holding {recorded[1]} "
        f"bought episode rows. {_REMEDY}"
    )


def unreadable_error(path: Path, why: str) -> CorruptRunError:
    """The refusal of a store at ``path`` that cannot be read (``why``), naming the commits
    its counter recorded."""
    return CorruptRunError(f"cannot read the run {path}: {why}{at_stake(path)}")
