"""A durable store of one run: every bought episode on disk, checksummed, before the next.

Rewarded episodes are expensive (on a robot each reward is a measured hit), so a run keeps
them in an SQLite database (standard library) that survives kills at any moment:

* a rollback journal and ``synchronous=EXTRA``: a committed transaction is in the database
  file, synced, before the commit returns; a transaction cut by a crash is rolled back on the
  next open, never half-applied;
* one row per bought episode index ``(l, m)`` holding its tensors ``[*T, N]``, one row per
  iteration's selection (the chosen candidates, J', the reward-free episodes) and one per
  completed iteration (its :class:`~torch_api.loop.iteration.IterationRecord`, θ_l included);
* tensors serialised without pickle (a JSON header of keys, dtypes and shapes, then the raw
  bytes); every value (its table, key and bytes) covered by a SHA-256 digest checked when the
  run is read; declared sizes checked against the bytes before any tensor is built;
* one writer, never through a symlink, writes never interrupted half-way by SIGINT/SIGTERM
  (:mod:`torch_api.runs.run_guard`); the errors are in :mod:`torch_api.runs.store_errors`;
* created atomically (an interrupt at any instant leaves no store or a complete empty one), and
  its count of commits kept twice, inside the database and in a counter file beside it
  (:mod:`torch_api.runs.store_files`): a store that lost committed rows, or a counter lost or
  damaged beside a store that holds commits, is refused, never resumed short or restarted.

The settings that give the stored data its meaning (``config``) are stored with it and must
match when a run is resumed.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
from collections.abc import Iterator
from pathlib import Path

from tensordict import TensorDictBase

from torch_api.runs.codec import decode_tensordict, encode_tensordict
from torch_api.runs.run_guard import lock_run, refuse_symlinks, signals_held
from torch_api.runs.store_errors import (
    CorruptRunError,
    RunExistsError,
    RunInUseError,
    StoreError,
    StoreWriteError,
)
from torch_api.runs.store_files import (
    create_atomically,
    lost_rows_error,
    use_rollback_journal,
    write_counter,
)
from torch_api.runs.store_read import (  # noqa: F401  (_digest: the tests forge rows with it)
    FORMAT,
    SCHEMA,
    StoredRun,
    _digest,
    _json,
    _unjson,
    read_run,
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
        self._commits = 0
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
        held, lost = self._has_data()
        if held and lost and not overwrite:
            self.read(path)  # raises, saying what was lost
        if held and not (resume or overwrite):
            raise RunExistsError(
                f"{path} holds a run ({held}); pass resume=True (--resume) to continue it or "
                "overwrite=True (--overwrite) to discard it"
            )
        if held and resume:
            stored = self.read(path)  # verifies every digest, the counter and the config
            self._check_config(stored.config)
            self.stored, self.started_fresh = stored, False
            self._commits = stored.commits
        if overwrite or not held:
            try:
                with signals_held():  # (an interrupt waits for the creation, as for a commit)
                    create_atomically(path, self._fill)
            except (sqlite3.DatabaseError, OSError) as error:
                raise self._write_error(error) from None
        self._connect()

    def _fill(self, db: sqlite3.Connection) -> None:
        """The tables and ``meta`` rows of a new store (inside its one transaction)."""
        for statement in filter(str.strip, SCHEMA.split(";")):
            db.execute(statement)
        self._put(db, "meta", ("format",), _json(FORMAT))
        self._put(db, "meta", ("config",), _json(self.config))
        self._put(db, "meta", ("commits",), _json(0))

    def _has_data(self) -> tuple[str | None, bool]:
        """A short description of what the store at path holds (None if nothing), and whether
        it lost committed rows or the counter that vouches for them. Opened for writing (the
        lock is held): a hot journal or log left by a killed writer is recovered before the
        store is judged."""
        try:
            commits, episodes = self._count(self.path)
            rows, done = self._count(self.path, "record")
        except (sqlite3.DatabaseError, ValueError, RecursionError):
            return "a file that is not a readable run", False
        lost = lost_rows_error(self.path, commits, episodes) is not None
        if not self.path.exists() or self.path.stat().st_size == 0:
            return ("a store that lost its file", True) if lost else (None, False)
        if lost:
            return "a run that lost committed rows or its counter", True
        if rows == 0 and done == 0:
            return None, False  # nothing bought yet (or a store with no tables): nothing to lose
        return f"{rows} bought episode rows, {done} completed iterations", False

    @staticmethod
    def _count(path: Path, what: str = "commits") -> tuple[int, int]:
        """(commits, episode rows), or with ``what="record"`` (episode rows, records), of the
        store at ``path`` (a missing file or table counts 0), opened for writing."""
        if not path.exists() or path.stat().st_size == 0:
            return 0, 0
        db = sqlite3.connect(path)
        try:
            names = {r[1] for r in db.execute("SELECT type, name FROM sqlite_master")}

            def count(table: str) -> int:
                if table not in names:
                    return 0
                return db.execute(f"SELECT count(*) FROM {table}").fetchone()[0]

            if what == "record":
                return count("episode"), count("record")
            commits = 0
            if "meta" in names:
                row = db.execute("SELECT value FROM meta WHERE key = 'commits'").fetchone()
                commits = 0 if row is None else int(_unjson(row[0]))
            return commits, count("episode")
        finally:
            db.close()

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
            use_rollback_journal(db)  # (a store made with a write-ahead log is converted)
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
            db = self._db
            try:
                db.execute("BEGIN IMMEDIATE")
                try:
                    yield db
                    commits = self._commits + 1
                    self._put(db, "meta", ("commits",), _json(commits))
                    rows = db.execute("SELECT count(*) FROM episode").fetchone()[0]
                    db.execute("COMMIT")
                except BaseException:
                    if db.in_transaction:
                        db.execute("ROLLBACK")
                    raise
                self._commits = commits
                write_counter(self.path, commits, rows)
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
        """Close the database and release the lock; closing again does nothing.

        Each handle is taken from the store before it is closed, with SIGINT/SIGTERM held
        (:func:`~torch_api.runs.run_guard.signals_held`): a signal handled during or right
        after a close never leaves the store holding a descriptor number that the next file
        opened reuses, so a second ``close()`` never closes another store's lock.
        """
        with signals_held():
            db, self._db = self._db, None
            fd, self._lock_fd = self._lock_fd, None
            if db is not None:
                with contextlib.suppress(sqlite3.Error):
                    db.close()
            if fd is not None:
                os.close(fd)  # releases the flock

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- reading ----------------------------------------------------------------------------

    @staticmethod
    def read(path: str | os.PathLike) -> StoredRun:
        """Read and verify a stored run (every digest, sizes, the format, the commit counter).

        Raises:
            CorruptRunError: naming the path and what failed.
        """
        return read_run(path)
