"""Reading a run's store (:mod:`torch_api.runs.store`) back, verified: the layout, the digests of
its rows, the values, and :class:`StoredRun`, what a verified store holds."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import struct
from dataclasses import dataclass, field
from pathlib import Path

from tensordict import TensorDict

from torch_api.runs.codec import decode_tensordict
from torch_api.runs.store_errors import CorruptRunError
from torch_api.runs.store_files import COMPANIONS, at_stake, lost_rows_error, unreadable_error

__all__ = ["FORMAT", "StoredRun", "read_run"]

FORMAT = 2  # version of the database layout
MAX_JSON_BYTES = 64 << 20  # a JSON value (a record, a selection) is never larger
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value BLOB NOT NULL, digest BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS selection (
    iteration INTEGER PRIMARY KEY, value BLOB NOT NULL, free BLOB, digest BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS episode (
    iteration INTEGER NOT NULL, episode INTEGER NOT NULL, value BLOB NOT NULL,
    digest BLOB NOT NULL, PRIMARY KEY (iteration, episode));
CREATE TABLE IF NOT EXISTS record (
    iteration INTEGER PRIMARY KEY, value BLOB NOT NULL, digest BLOB NOT NULL);
"""
TABLES = ("meta", "selection", "episode", "record")
_OBJECTS = {("table", t) for t in TABLES} | {
    ("index", f"sqlite_autoindex_{t}_1") for t in ("meta", "episode")
}  # everything a run's sqlite_master holds


def _digest(table: str, key: tuple, *values: bytes | None) -> bytes:
    h = hashlib.sha256(json.dumps([table, *key]).encode())
    for value in values:
        h.update(b"\x00" if value is None else struct.pack("<Q", len(value)) + value)
    return h.digest()


def _json(value) -> bytes:
    return json.dumps(value, allow_nan=False).encode()


def _unjson(blob: bytes):
    if len(blob) > MAX_JSON_BYTES:
        raise ValueError(f"a JSON value of {len(blob)} bytes exceeds {MAX_JSON_BYTES}")
    return json.loads(blob.decode())


@dataclass
class StoredRun:
    """What a store holds, verified: ``config``, and per iteration l the selection
    (``selections[l]``, reward-free episodes in ``free[l]``), the bought episodes
    (``episodes[l][m]``, each ``[*T, N]``) and the completed iteration's record
    (``records[l]``, a dict)."""

    config: dict
    selections: dict[int, dict] = field(default_factory=dict)
    free: dict[int, TensorDict] = field(default_factory=dict)
    episodes: dict[int, dict[int, TensorDict]] = field(default_factory=dict)
    records: dict[int, dict] = field(default_factory=dict)
    commits: int = 0
    """transactions committed since the store was created"""

    @property
    def num_episodes(self) -> int:
        """Episode indices stored (rows of the episode table)."""
        return sum(len(e) for e in self.episodes.values())


def read_run(path: str | os.PathLike) -> StoredRun:
    """Read and verify a stored run (every digest, sizes, the format).

    Raises:
        CorruptRunError: naming the path and what failed.
    """
    path = Path(path)
    if not path.is_file():
        raise lost_rows_error(path, 0, 0) or CorruptRunError(f"no run is stored at {path}")
    try:
        return _read(path)
    except CorruptRunError as error:
        if "commits" in str(error):  # (the counter's own refusals name them)
            raise
        raise CorruptRunError(f"{error}{at_stake(path)}") from None
    except sqlite3.OperationalError as error:
        journal = Path(f"{path}-journal")
        if "readonly" in str(error) and journal.exists() and journal.stat().st_size:
            raise CorruptRunError(
                f"the run {path} was left inside a commit by a killed writer (its journal "
                f"{journal} is still there): resume it (which opens it for writing and rolls "
                "the commit back) before reading it; a reader never writes"
            ) from None
        raise unreadable_error(path, f"{type(error).__name__}: {error}") from None
    except (
        sqlite3.DatabaseError,
        ValueError,
        KeyError,
        TypeError,
        UnicodeError,
        RecursionError,
    ) as error:
        raise unreadable_error(path, f"{type(error).__name__}: {error}") from None


def _connect_read_only(path: Path) -> sqlite3.Connection:
    """A read-only connection; in a folder this process cannot write (no ``-shm`` can be
    made there) a store with no log or journal left is read as the immutable file it is."""
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        db.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return db
    except sqlite3.OperationalError:
        logs = [Path(f"{path}{suffix}") for suffix in COMPANIONS if suffix != "-shm"]
        if os.access(path.parent, os.W_OK) or any(p.exists() and p.stat().st_size for p in logs):
            raise
        return sqlite3.connect(f"file:{path}?immutable=1", uri=True)


def _read(path: Path) -> StoredRun:
    db = _connect_read_only(path)
    try:
        check = db.execute("PRAGMA quick_check").fetchall()
        if check != [("ok",)]:
            raise unreadable_error(path, f"it fails SQLite's check: {check[:3]}")

        def rows(sql):
            return db.execute(sql).fetchall()

        objects = set(rows("SELECT type, name FROM sqlite_master"))
        tables = {name for kind, name in objects if kind == "table"}
        meta = {}
        if "meta" in tables:
            for key, value, digest in rows("SELECT key, value, digest FROM meta"):
                if _digest("meta", (key,), value) != digest:
                    raise CorruptRunError(f"the run {path}: checksum mismatch in meta {key!r}")
                meta[key] = _unjson(value)
        episodes = rows("SELECT count(*) FROM episode")[0][0] if "episode" in tables else 0
        if (lost := lost_rows_error(path, meta.get("commits", 0), episodes)) is not None:
            raise lost
        if objects - _OBJECTS:
            raise CorruptRunError(
                f"the run {path} holds schema objects a run never has: "
                f"{sorted(objects - _OBJECTS)[:3]}"
            )
        if meta.get("format") != FORMAT:
            raise CorruptRunError(
                f"the run {path} has format {meta.get('format')!r}, not {FORMAT} "
                "(written by another version of torch_api?)"
            )
        stored = StoredRun(config=meta["config"], commits=meta.get("commits", 0))
        for it, value, free, digest in rows(
            "SELECT iteration, value, free, digest FROM selection ORDER BY iteration"
        ):
            if _digest("selection", (it,), value, free) != digest:
                raise CorruptRunError(f"the run {path}: checksum mismatch in selection {it}")
            stored.selections[it] = _unjson(value)
            if free is not None:
                stored.free[it] = decode_tensordict(free)
        for it, m, value, digest in rows(
            "SELECT iteration, episode, value, digest FROM episode ORDER BY iteration, episode"
        ):
            if _digest("episode", (it, m), value) != digest:
                raise CorruptRunError(
                    f"the run {path}: checksum mismatch in episode {m} of iteration {it}"
                )
            stored.episodes.setdefault(it, {})[m] = decode_tensordict(value)
        for it, value, digest in rows(
            "SELECT iteration, value, digest FROM record ORDER BY iteration"
        ):
            if _digest("record", (it,), value) != digest:
                raise CorruptRunError(f"the run {path}: checksum mismatch in record {it}")
            stored.records[it] = _unjson(value)
        return stored
    finally:
        db.close()
