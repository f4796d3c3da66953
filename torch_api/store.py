"""A durable store of one run: every bought episode on disk, checksummed, before the next.

Rewarded episodes are expensive (on a robot each reward is a measured hit), so a run keeps
them in an SQLite database (standard library) that survives kills at any moment:

* write-ahead log and ``synchronous=FULL``: a committed transaction is on the disk, a
  transaction cut by a crash is rolled back on the next open, never half-applied;
* one row per bought episode index ``(l, m)`` holding its tensors ``[*T, N]``, one row per
  iteration's selection (the chosen candidates, J', the reward-free episodes) and one per
  completed iteration (its :class:`~torch_api.iteration.IterationRecord`, θ_l included);
* tensors serialised without pickle (a JSON header of keys, dtypes and shapes, then the raw
  bytes); every value (its table, key and bytes) covered by a SHA-256 digest checked when the
  run is read; declared sizes checked against the bytes before any tensor is built;
* one writer, never through a symlink, writes never interrupted half-way by SIGINT/SIGTERM
  (:mod:`torch_api.run_guard`); the errors are in :mod:`torch_api.store_errors`.

The settings that give the stored data its meaning (``config``) are stored with it and must
match when a run is resumed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tensordict import TensorDict, TensorDictBase

from torch_api.codec import decode_tensordict, encode_tensordict
from torch_api.run_guard import lock_run, refuse_symlinks, signals_held
from torch_api.store_errors import (
    CorruptRunError,
    RunExistsError,
    RunInUseError,
    StoreError,
    StoreWriteError,
)

__all__ = [
    "CorruptRunError",
    "RunExistsError",
    "RunInUseError",
    "RunStore",
    "StoreError",
    "StoreWriteError",
    "StoredRun",
    "decode_tensordict",
    "encode_tensordict",
]

FORMAT = 2  # version of the database layout
MAX_JSON_BYTES = 64 << 20  # a JSON value (a record, a selection) is never larger
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value BLOB NOT NULL, digest BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS selection (
    iteration INTEGER PRIMARY KEY, value BLOB NOT NULL, free BLOB, digest BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS episode (
    iteration INTEGER NOT NULL, episode INTEGER NOT NULL, value BLOB NOT NULL,
    digest BLOB NOT NULL, PRIMARY KEY (iteration, episode));
CREATE TABLE IF NOT EXISTS record (
    iteration INTEGER PRIMARY KEY, value BLOB NOT NULL, digest BLOB NOT NULL);
"""
_TABLES = ("meta", "selection", "episode", "record")


# -- the store ------------------------------------------------------------------------------


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

    @property
    def num_episodes(self) -> int:
        """Episode indices stored (rows of the episode table)."""
        return sum(len(e) for e in self.episodes.values())


class RunStore:
    """One run's SQLite database at ``path``, opened for writing by this process alone.

    Args:
        path: the database file (its directory is created if missing).
        config: the settings that give the stored data its meaning (JSON-able dict).
        resume: continue a stored run (its config must equal ``config``); a missing or empty
            run starts fresh (``started_fresh`` tells).
        overwrite: discard a stored run and start over.

    Raises:
        RunExistsError: a run is stored and neither ``resume`` nor ``overwrite`` is set.
        RunInUseError: another process holds the run (its pid and host are named).
        StoreWriteError: the place cannot be written (checked before anything is bought).
        CorruptRunError: with ``resume``, the stored run fails a check.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     store = RunStore(Path(d) / "run.db", config={"N": 10})
        ...     store.put_record(1, {"theta": [1.0]})
        ...     store.close()
        ...     RunStore.read(Path(d) / "run.db").records
        {1: {'theta': [1.0]}}
    """

    def __init__(
        self, path: str | os.PathLike, *, config: dict, resume: bool = False, overwrite=False
    ) -> None:
        if resume and overwrite:
            raise ValueError("resume and overwrite exclude each other")
        self.path = Path(path)
        self.config = self.normalise(config)
        self.stored: StoredRun | None = None  # with resume: the run as read (verified)
        self._lock_fd: int | None = None
        self._db: sqlite3.Connection | None = None
        try:
            self._open(resume=resume, overwrite=overwrite)
        except BaseException:
            self.close()
            raise

    def _open(self, *, resume: bool, overwrite: bool) -> None:
        path = self.path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise StoreWriteError(
                f"cannot create the run's directory {path.parent}: {error.strerror or error}"
            ) from None
        if path.exists() and not path.is_file():
            raise StoreWriteError(f"{path} exists and is not a file")
        refuse_symlinks(path)
        self._lock_fd = lock_run(path)
        self.started_fresh = True
        held = self._has_data()
        if held and not (resume or overwrite):
            raise RunExistsError(
                f"{path} holds a run ({held}); pass resume=True (--resume) to continue it or "
                "overwrite=True (--overwrite) to discard it"
            )
        if held and resume:
            stored = self.read(path)  # verifies every digest and the config
            self._check_config(stored.config)
            self.stored, self.started_fresh = stored, False
        self._connect()
        if overwrite or not held:
            with self._write() as db:
                for table in _TABLES:
                    db.execute(f"DELETE FROM {table}")
                self._put(db, "meta", ("format",), _json(FORMAT))
                self._put(db, "meta", ("config",), _json(self.config))

    def _has_data(self) -> str | None:
        """A short description of what the file at path holds, or None if nothing."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return None
        try:
            db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
            try:
                rows = db.execute("SELECT count(*) FROM episode").fetchone()[0]
                done = db.execute("SELECT count(*) FROM record").fetchone()[0]
            finally:
                db.close()
        except sqlite3.DatabaseError:
            return "a file that is not a readable run"
        if rows == 0 and done == 0:
            return None  # nothing bought yet: nothing to lose
        return f"{rows} bought episode rows, {done} completed iterations"

    @staticmethod
    def normalise(config: dict) -> dict:
        """``config`` as it reads back from JSON (tuples become lists)."""
        return json.loads(json.dumps(config, allow_nan=False))

    @property
    def closed(self) -> bool:
        return self._db is None

    def _connect(self) -> None:
        try:
            db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            self._db = db
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as error:
            raise self._write_error(error) from None
        refuse_symlinks(self.path)

    def _write_error(self, error: Exception) -> StoreError:
        if isinstance(error, sqlite3.DatabaseError) and "not a database" in str(error):
            return CorruptRunError(f"{self.path} is not a run database ({error})")
        return StoreWriteError(f"cannot write the run {self.path}: {error}")

    @contextlib.contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One transaction, committed (fsynced) before the block returns; signals held."""
        if self._db is None:
            raise StoreWriteError(f"the run {self.path} is closed")
        with signals_held():
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    yield self._db
                    self._db.execute("COMMIT")
                except BaseException:
                    # (a signal handler that was pending before the mask may raise after COMMIT:
                    # then there is nothing to roll back, and the interrupt goes on as such)
                    if self._db.in_transaction:
                        self._db.execute("ROLLBACK")
                    raise
            except (sqlite3.DatabaseError, OSError) as error:
                raise self._write_error(error) from None

    @staticmethod
    def _put(db, table: str, key: tuple, value: bytes, free: bytes | None = None) -> None:
        digest = _digest(table, key, value, free) if table == "selection" else None
        digest = digest or _digest(table, key, value)
        if table == "meta":
            db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?, ?)", (*key, value, digest))
        elif table == "selection":
            db.execute(
                "INSERT OR REPLACE INTO selection VALUES (?, ?, ?, ?)", (*key, value, free, digest)
            )
        else:
            slots = ", ".join("?" * (len(key) + 2))
            db.execute(f"INSERT OR REPLACE INTO {table} VALUES ({slots})", (*key, value, digest))

    def _check_config(self, theirs: dict) -> None:
        if theirs != self.config:
            differ = sorted(
                k for k in theirs.keys() | self.config.keys() if theirs.get(k) != self.config.get(k)
            )
            raise CorruptRunError(
                f"the run stored in {self.path} was made with other settings: {differ}"
            )

    # -- writing ----------------------------------------------------------------------------

    def put_selection(self, iteration: int, value: dict, free: TensorDictBase | None) -> None:
        """Store iteration l's selection (JSON-able) and reward-free episodes, replacing any."""
        blob = None if free is None else encode_tensordict(free)
        with self._write() as db:
            db.execute("DELETE FROM episode WHERE iteration = ?", (iteration,))
            self._put(db, "selection", (iteration,), _json(value), blob)

    def put_episodes(self, iteration: int, episodes: dict[int, TensorDictBase]) -> None:
        """Store bought episodes ``{m: [*T, N]}`` of iteration l in one transaction."""
        blobs = {m: encode_tensordict(td) for m, td in episodes.items()}
        with self._write() as db:
            for m, blob in blobs.items():
                self._put(db, "episode", (iteration, m), blob)

    def put_record(self, iteration: int, record: dict) -> None:
        """Store the record of completed iteration l."""
        with self._write() as db:
            self._put(db, "record", (iteration,), _json(record))

    def close(self) -> None:
        """Close the database (checkpointing its log into the file) and release the lock."""
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- reading ----------------------------------------------------------------------------

    @staticmethod
    def read(path: str | os.PathLike) -> StoredRun:
        """Read and verify a stored run (every digest, sizes, the format).

        Raises:
            CorruptRunError: naming the path and what failed.
        """
        path = Path(path)
        if not path.is_file():
            raise CorruptRunError(f"no run is stored at {path}")
        try:
            return RunStore._read(path)
        except CorruptRunError:
            raise
        except (sqlite3.DatabaseError, ValueError, KeyError, TypeError, UnicodeError) as error:
            raise CorruptRunError(
                f"cannot read the run {path}: {type(error).__name__}: {error}"
            ) from None

    @staticmethod
    def _read(path: Path) -> StoredRun:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            check = db.execute("PRAGMA quick_check").fetchall()
            if check != [("ok",)]:
                raise CorruptRunError(f"the run {path} fails SQLite's check: {check[:3]}")

            def rows(sql):
                return db.execute(sql).fetchall()

            meta = {}
            for key, value, digest in rows("SELECT key, value, digest FROM meta"):
                if _digest("meta", (key,), value) != digest:
                    raise CorruptRunError(f"the run {path}: checksum mismatch in meta {key!r}")
                meta[key] = _unjson(value)
            if meta.get("format") != FORMAT:
                raise CorruptRunError(
                    f"the run {path} has format {meta.get('format')!r}, not {FORMAT} "
                    "(written by another version of torch_api?)"
                )
            stored = StoredRun(config=meta["config"])
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
