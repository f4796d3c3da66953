"""The process settings of the command-line scripts: the garbage collector at start-up and at
exit, and what glibc's malloc does with freed memory.

**The collector.** Importing torch, TensorDict, TorchRL and matplotlib makes millions of objects
that live until the process ends; the cyclic collector walks them again and again while they are
made (its generations fill up as they are allocated), and once more, all of them, at exit.
Measured on 2 idle cores, a process that imports what ``chain_walk_api.py`` imports and exits:
3.92 s; with the collector off during the imports and those objects frozen after them
(``gc.freeze``: never examined again, at exit included) 2.22 s, of which the exit 1.04 s →
0.19 s. So a script calls :func:`collector_off_for_imports` before its heavy imports and
:func:`freeze_imported_objects` after them, both only when it runs as ``__main__`` (a test that
imports the script keeps its own collector). The cost: garbage cycles made while importing are
never freed (they would live to the exit anyway in the common case). Worker processes forked
from the script inherit the frozen objects, and their pages are no longer touched by the
collector's bookkeeping (fewer copy-on-write faults).

**Freed memory.** torch's CPU allocator hands every tensor to ``malloc`` and back to ``free``. glibc
serves a block of more than its mmap threshold (128 KiB at first, raised as such blocks are freed,
at most 32 MiB) with a fresh ``mmap`` and returns it to the system at ``free``, and it trims the
heap's free top; a tensor of the same size a moment later then faults in its pages again, zero-
filled by the kernel. A batched run of many trials makes such tensors all the time (Figure 8 at
1,000 trials: rows of 750,000 reward-free samples), so part of its time went to the kernel: 4.3 s of
system time against 12.5 s of user time, 0.86 M page faults (``/usr/bin/time -v``).

:func:`retain_freed_memory` sets ``M_MMAP_MAX = 0`` (large blocks come from the heap too) and a
trim threshold of 2 GiB (the heap's free top is kept), so freed blocks are reused without a
fault. The cost: memory freed after the peak stays with the process until it ends (the peak
itself is unchanged: measured in ``benchmarks/bench_figure8.py``). A library does not change its
user's allocator, so only the command-line scripts call it; worker processes forked from them
(``--backend processes`` on Linux) inherit it, spawned ones (macOS, CUDA) keep the defaults.
"""

from __future__ import annotations

import ctypes
import gc
import sys

M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's <malloc.h>
_TRIM_BYTES = 2**31 - 1  # mallopt takes an int


def retain_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed memory (see the module); False where there is no glibc
    ``mallopt`` (macOS, Windows, musl) or it refused, and nothing changed."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, _TRIM_BYTES))


def collector_off_for_imports() -> None:
    """Switch the cyclic garbage collector off for the heavy imports that follow (see the
    module); :func:`freeze_imported_objects` switches it on again."""
    gc.disable()


def freeze_imported_objects() -> None:
    """Move every object alive now (the imported modules' objects) out of the collector's
    sight for good, then switch the collector on."""
    gc.freeze()
    gc.enable()


def configure_process(args) -> None:
    """Set torch's intra-op threads from ``args.threads`` (0: leave torch's default) and keep
    freed memory where ``args.freed_memory`` says so (:class:`_cli.ThreadOptions`)."""
    if args.threads > 0:
        __import__("torch").set_num_threads(args.threads)
    if getattr(args, "freed_memory", "return") == "retain":
        retain_freed_memory()
