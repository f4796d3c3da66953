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

**torch's compiler, not imported.** TensorDict imports ``torch._dynamo`` (torch.compile's
frontend) at import, for four names it applies to its functions there: ``disable``,
``allow_in_graph``, ``assume_constant_result`` (decorators) and ``is_compiling``; TorchRL's
``torch.compiler.disable`` decorators reach the same module, and every ``env.rollout`` asks
whether its policy is a ``torch._dynamo.eval_frame.OptimizedModule`` (a compiled module).
Loading the module costs about 1.2 s of a script's 2.5-3 s start-up (measured on 2 idle AMD
EPYC cores, 2026-12-07), and no script compiles anything. So :func:`collector_off_for_imports`
puts :class:`_CompilerDeferred` in ``sys.modules`` in its place for the rest of the process:
while the real module is not loaded, those names answer as dynamo does in eager execution (the
decorators leave the function as it is; nothing is compiling; no object is a compiled module),
and once it is, from it; any other name loads the real module at once and answers from it (so
``torch.compile`` works, and loads it). The cost: functions decorated during the imports keep
no compiler marks, so a script that compiled TensorDict or TorchRL code would compile through
them (none does). Numbers are unchanged (the decorators do nothing in eager execution; Figure 8's
CSV is the same byte for byte).
"""

from __future__ import annotations

import ctypes
import gc
import importlib
import sys
import types

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


def _loaded_dynamo() -> types.ModuleType | None:
    """The real ``torch._dynamo`` where something has imported it, else None."""
    module = sys.modules.get("torch._dynamo")
    return None if module is None or isinstance(module, _CompilerDeferred) else module


def _real_dynamo() -> types.ModuleType:
    """The real ``torch._dynamo``, imported now if it is not yet, in the stand-in's place."""
    if isinstance(sys.modules.get("torch._dynamo"), _CompilerDeferred):
        del sys.modules["torch._dynamo"]
    torch = sys.modules["torch"]
    if isinstance(vars(torch).get("_dynamo"), _CompilerDeferred):
        delattr(torch, "_dynamo")
    return importlib.import_module("torch._dynamo")


class _NeverCompiled:
    """No object is an instance: nothing has been compiled while the real module is not loaded
    (``torch.compile`` loads it)."""


class _EvalFrameDeferred(types.ModuleType):
    """``torch._dynamo.eval_frame`` of the stand-in: ``OptimizedModule`` (TorchRL's every
    ``rollout`` asks whether its policy is a compiled module) is :class:`_NeverCompiled` until
    the real module is loaded; anything else from the real module."""

    def __getattr__(self, name: str):
        if name == "OptimizedModule" and _loaded_dynamo() is None:
            return _NeverCompiled
        return getattr(_real_dynamo().eval_frame, name)


class _CompilerDeferred(types.ModuleType):
    """``torch._dynamo`` in a script (see the module): the names TensorDict and TorchRL use
    answer as in eager execution while the real module is not loaded (and from it once it is);
    any other name loads the real module and answers from it."""

    eval_frame = _EvalFrameDeferred("torch._dynamo.eval_frame")

    @staticmethod
    def disable(fn=None, recursive=True, *, reason=None, wrapping=True):
        real = _loaded_dynamo()
        if real is not None:
            return real.disable(fn, recursive, reason=reason, wrapping=wrapping)
        return fn if fn is not None else (lambda f: f)

    @staticmethod
    def allow_in_graph(fn):
        real = _loaded_dynamo()
        if real is not None:
            return real.allow_in_graph(fn)
        return list(fn) if isinstance(fn, (list, tuple)) else fn

    @staticmethod
    def assume_constant_result(fn):
        fn._dynamo_marked_constant = True  # what dynamo's own does
        return fn

    @staticmethod
    def is_compiling() -> bool:
        real = _loaded_dynamo()
        return False if real is None else real.is_compiling()

    def __getattr__(self, name: str):
        return getattr(_real_dynamo(), name)


def collector_off_for_imports(*, torch_follows: bool = True) -> None:
    """Switch the cyclic garbage collector off for the heavy imports that follow (see the
    module; :func:`freeze_imported_objects` switches it on again) and, where they include
    torch (``torch_follows``), import it and put the stand-in for its compiler in place for the
    rest of the process (a script that never imports torch passes False and does not load it
    here)."""
    gc.disable()
    if not torch_follows:
        return
    import torch  # noqa: F401  (first: torch's own import must find the real modules)

    if "torch._dynamo" not in sys.modules:
        sys.modules["torch._dynamo"] = _CompilerDeferred("torch._dynamo")


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
