"""Worker processes that die with their parent (local pools, collectors, Ray tasks).

A worker left running after its parent was killed would go on measuring rewards nobody
stores, and could race a resumed run; :func:`die_with_parent` ends it instead.
"""

from __future__ import annotations

import ctypes
import os
import signal
import threading
import time

__all__ = ["WATCH_SECONDS", "die_with_parent"]

_PR_SET_PDEATHSIG = 1  # prctl option: the signal a process gets when its parent dies
WATCH_SECONDS = 0.5  # how often a worker's watchdog looks for its parent


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
