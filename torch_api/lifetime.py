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


def die_with_parent(parent: int | None = None) -> None:
    """End this process (SIGKILL) as soon as process ``parent`` (default: the parent) is gone.

    On Linux the kernel sends the signal (``PR_SET_PDEATHSIG``); a daemon thread checks every
    ``WATCH_SECONDS`` as well (other systems, or a parent that is not the direct one).
    """
    direct = parent is None
    parent = os.getppid() if parent is None else parent
    if direct:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # not Linux: the watchdog below does it
            pass

    def watch() -> None:
        while (os.getppid() == parent) if direct else _alive(parent):
            time.sleep(WATCH_SECONDS)
        os.kill(os.getpid(), signal.SIGKILL)

    if (os.getppid() != parent) if direct else not _alive(parent):
        os.kill(os.getpid(), signal.SIGKILL)  # the parent is gone already
    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()
