"""Worker processes that die with their parent (local pools, collectors, Ray tasks).

A worker left running after its parent was killed would go on measuring rewards nobody
stores, and could race a resumed run. Two guards end it instead:

* :func:`die_with_parent`, called in the worker: the kernel's ``PR_SET_PDEATHSIG`` and a
  watchdog thread. It runs only once the worker runs code of the library, and a spawned
  worker first imports torch (seconds; tens of seconds on a loaded host);
* :func:`workers_die_with_this_process`, around the code in the parent that starts workers:
  a small reaper process (the standard library only, started in milliseconds) that, when the
  parent dies, SIGKILLs every process started in the block, whatever it is doing, and every
  process those started (spawned workers, TorchRL's, their own children). It finds them by a
  mark in the environment they inherit (``TORCH_API_DIE_WITH``, read back from
  ``/proc/<pid>/environ``), so it needs no pid from the parent and misses none started
  while the parent dies.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing.resource_tracker
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

__all__ = ["MARK", "WATCH_SECONDS", "die_with_parent", "workers_die_with_this_process"]

_PR_SET_PDEATHSIG = 1  # prctl option: the signal a process gets when its parent dies
WATCH_SECONDS = 0.5  # how often a worker's watchdog looks for its parent
REAP_WATCH_SECONDS = 0.05  # how often the reaper looks for its parent
MARK = "TORCH_API_DIE_WITH"
"""The environment variable marking the processes started in
:func:`workers_die_with_this_process` (``:``-separated marks, one per enclosing block)."""

_REAPER = r"""
import os, select, signal, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)  # (Ctrl-C and the examples' SIGTERM reach the
signal.signal(signal.SIGTERM, signal.SIG_IGN)  # process group: the reaper outlives them)
mark, parent, name, every = sys.argv[1].encode(), int(sys.argv[2]), sys.argv[3], sys.argv[4]
key = (name + "=").encode()
while os.getppid() == parent:
    if select.select([0], [], [], float(every))[0]:
        said = os.read(0, 16)
        if said.startswith(b"done"):
            sys.exit(0)
        if not said:
            break
def marked(pid):
    try:
        with open("/proc/%d/environ" % pid, "rb") as f:
            env = f.read()
    except OSError:
        return False
    for var in env.split(b"\0"):
        if var.startswith(key):
            return mark in var[len(key):].split(b":")
    return False
me = os.getpid()
for _ in range(100):  # until none is left (one may have started another meanwhile)
    found = [int(p) for p in os.listdir("/proc") if p.isdigit() and int(p) != me]
    found = [p for p in found if marked(p)]
    for p in found:
        try:
            os.kill(p, signal.SIGKILL)
        except OSError:
            pass
    if not found:
        break
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def die_with_parent(parent: int | None = None, *, direct: bool = True) -> None:
    """End this process (SIGKILL) as soon as process ``parent`` is gone.

    Args:
        parent: the pid to outlive not (default: the current parent). Give the pid the parent
            had when it started this process: if it died before this call, this process is
            ended at once.
        direct: ``parent`` is this process's parent. On Linux the kernel then sends SIGKILL
            when it dies (``PR_SET_PDEATHSIG``); a daemon thread also checks ``os.getppid()``
            every ``WATCH_SECONDS``. With ``direct=False`` (a Ray task and the driver) the
            thread checks that ``parent`` is alive.
    """
    parent = os.getppid() if parent is None else int(parent)
    if direct:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # not Linux: the watchdog below does it
            pass

    def there() -> bool:
        return os.getppid() == parent if direct else _alive(parent)

    if not there():
        os.kill(os.getpid(), signal.SIGKILL)  # the parent is gone already

    def watch() -> None:
        while there():
            time.sleep(WATCH_SECONDS)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


@contextlib.contextmanager
def workers_die_with_this_process() -> Iterator[None]:
    """Every process started in the block (and every process it starts) is SIGKILLed within
    about 0.1 s of this process's death, even one still importing its modules.

    Leave the block only once its workers have ended (the block shuts them down). Processes
    that other threads start meanwhile are marked too, and die with this process as well.
    Works where ``/proc`` shows environments (Linux); elsewhere the block does nothing (the
    workers' own :func:`die_with_parent` remains).

    Example:
        >>> with workers_die_with_this_process():
        ...     subprocess.run([sys.executable, "-c", "pass"], check=True).returncode
        0
    """
    if not Path(f"/proc/{os.getpid()}/environ").exists():
        yield
        return
    # The resource tracker is shared by every later process: started here, before the mark,
    # so that it is never killed (it cleans up after the workers once they are gone).
    multiprocessing.resource_tracker.ensure_running()
    mark = f"{os.getpid()}.{secrets.token_hex(6)}"
    reaper = subprocess.Popen(
        [sys.executable, "-I", "-S", "-c", _REAPER, mark, str(os.getpid()), MARK]
        + [str(REAP_WATCH_SECONDS)],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
    )
    before = os.environ.get(MARK)
    os.environ[MARK] = mark if not before else f"{before}:{mark}"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(MARK, None)
        else:
            os.environ[MARK] = before
        with contextlib.suppress(OSError):
            reaper.stdin.write(b"done")
            reaper.stdin.close()
        try:
            reaper.wait(timeout=10)
        except subprocess.TimeoutExpired:
            reaper.kill()
            reaper.wait()
