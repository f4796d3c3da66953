"""Guards of a run's files: one writer at a time, never through a symlink, never a write cut
half-way by SIGINT/SIGTERM.

* one writer: an exclusive ``flock`` on ``PATH.lock``, which records the holder's pid and host,
  held for as long as the store is open and released by the kernel when the process dies;
* never through a symlink: the database, its ``-wal``/``-shm``/``-journal`` files and the lock
  must not be symbolic links;
* signals held: SIGINT and SIGTERM are held back while a transaction commits (in every thread:
  the main thread blocks them and their handlers only note them) and delivered right after.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

from torch_api.runs.store_errors import RunInUseError, StoreWriteError, SymlinkRefusedError

__all__ = ["lock_run", "refuse_symlinks", "signals_held"]


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT/SIGTERM back until the block is done, then deliver them.

    Two guards, both needed: the main thread blocks both signals (so no system call of the
    block is cut), and their Python handlers are replaced by one that only notes the signal.
    A signal sent to the process is taken by any thread that does not block it (``import
    torch`` starts such threads) and its Python handler then runs in the main thread at the
    next bytecode, inside the block: the noted signals are raised again after it, so the
    handlers run once the block is done. Outside the main thread it does nothing (Python runs
    signal handlers in the main thread only, so they never interrupt another thread's block).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held, noted = (signal.SIGINT, signal.SIGTERM), []
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    before = {sig: signal.signal(sig, lambda signum, frame: noted.append(signum)) for sig in held}
    try:
        yield
    finally:
        raised = _restore_handlers(before)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # whatever a handler raised
        if raised is not None:
            raise raised
        for signum in dict.fromkeys(noted):
            signal.raise_signal(signum)


def _restore_handlers(before: dict) -> BaseException | None:
    """Put every handler back; what a pending handler raised meanwhile is returned, not
    raised. (``signal.signal`` runs pending handlers before it changes one: SIGINT's own raises
    KeyboardInterrupt there, and the change is then not made, so it is made again.)"""
    raised = None
    for sig, handler in before.items():
        while True:
            try:
                signal.signal(sig, signal.SIG_DFL if handler is None else handler)
                break
            except BaseException as error:  # (re-raised by the caller)
                raised = raised or error
    return raised


def refuse_symlinks(path: Path) -> None:
    """Raise :class:`SymlinkRefusedError` (a :class:`StoreWriteError`) if the run's database or
    one of its files is a symlink."""
    suffixes = ("-wal", "-shm", "-journal", ".lock", ".commits", ".commits.new", ".new")
    for p in (path, *(Path(f"{path}{s}") for s in suffixes)):
        if p.is_symlink():
            raise SymlinkRefusedError(f"{p} is a symbolic link; a run is never written through one")


def lock_run(path: Path, what: str | None = None) -> int:
    """Take the run's writer lock (``flock`` on ``PATH.lock``) and return its file descriptor;
    closing the descriptor (or the process ending) releases it. ``what``: how the messages
    name what is locked (default: ``path``).

    Raises:
        RunInUseError: another process holds it (its pid and host are named).
        StoreWriteError: the lock file cannot be opened.
    """
    lock = Path(f"{path}.lock")
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as error:
        raise StoreWriteError(
            f"cannot write the run {path}: {lock}: {error.strerror or error}"
        ) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise RunInUseError(
            f"{what or path} is in use by another process ({holder}); wait for it to end or "
            "stop it before resuming"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()} on host {socket.gethostname()}\n".encode(), 0)
    return fd
