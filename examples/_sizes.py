"""What a run's sizes cost in memory, checked before any work starts (light: no torch)."""

from __future__ import annotations

import os

BYTES_PER_TRANSITION = 1024
"""What one stored or collected transition costs in memory, with the designs built from it (a
generous bound, for :func:`memory_error`)."""


def memory_error(transitions: float, flags: str) -> str | None:
    """Why a run that holds ``transitions`` transitions at once would not fit in the memory
    available here (:data:`BYTES_PER_TRANSITION` each), naming the ``flags`` that set it."""
    try:
        with open("/proc/meminfo") as meminfo:
            kib = next(int(line.split()[1]) for line in meminfo if line.startswith("MemAvailable"))
        available = kib * 1024
    except (OSError, StopIteration, ValueError):
        available = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    need = transitions * BYTES_PER_TRANSITION
    if need <= available:
        return None
    return (
        f"a run of these sizes holds about {transitions:.3g} transitions ({need / 2**30:.3g} GiB), "
        f"more than the {available / 2**30:.1f} GiB of memory available: lower {flags}"
    )
