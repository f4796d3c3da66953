"""A small median timer shared by the benchmark scripts, the machine they ran on, their JSON.

Example:
    >>> t = median_time(lambda: sum(range(1000)), budget_s=0.01)
    >>> t.median_ms > 0 and t.repeats >= 3
    True
    >>> both = median_times({"a": lambda: 1, "b": lambda: 2}, budget_s=0.01)
    >>> both["b"].result
    2
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

__all__ = ["Timing", "machine_info", "median_time", "median_times", "write_result"]


@dataclass(frozen=True)
class Timing:
    """Wall-clock times of repeated calls of one function."""

    median_ms: float  # median over the timed repeats (milliseconds)
    min_ms: float  # fastest timed repeat (milliseconds)
    repeats: int  # number of timed repeats (after warm-up)
    result: Any = None  # the value returned by the last call, for correctness checks

    def as_dict(self) -> dict[str, float | int]:
        """The numbers, without the returned value (for JSON)."""
        out = asdict(self)
        del out["result"]
        return out


def median_times(
    fns: dict[str, Callable[[], Any]],
    *,
    budget_s: float = 1.0,
    warmup: int = 1,
    min_repeats: int = 3,
    max_repeats: int = 50,
) -> dict[str, Timing]:
    """Median wall-clock times of several functions, timed side by side.

    Each function gets ``warmup`` untimed calls (0: none, ``min_repeats`` timed rounds only, for a
    smoke run); then the timed calls are interleaved round by
    round (a, b, c, a, b, c, ...) so that load from other processes hits all of them alike.
    The number of rounds fits ``budget_s`` per function (judged from the first warm-up calls),
    clamped to ``[min_repeats, max_repeats]``.
    """
    if warmup < 0 or min_repeats < 1 or max_repeats < min_repeats:
        raise ValueError(
            f"need warmup >= 0 and 1 <= min_repeats <= max_repeats, got warmup={warmup}, "
            f"min_repeats={min_repeats}, max_repeats={max_repeats}"
        )
    first = 0.0
    for fn in fns.values() if warmup else ():
        start = time.perf_counter()
        fn()
        first += time.perf_counter() - start
        for _ in range(warmup - 1):
            fn()
    rounds = min_repeats  # (no warm-up: nothing to judge the budget by; a smoke run)
    if warmup:
        rounds = int(min(max(budget_s * len(fns) / max(first, 1e-9), min_repeats), max_repeats))
    times: dict[str, list[float]] = {name: [] for name in fns}
    results: dict[str, Any] = {}
    for _ in range(rounds):
        for name, fn in fns.items():
            start = time.perf_counter()
            results[name] = fn()
            times[name].append(time.perf_counter() - start)
    return {
        name: Timing(
            median_ms=1e3 * statistics.median(ts),
            min_ms=1e3 * min(ts),
            repeats=rounds,
            result=results[name],
        )
        for name, ts in times.items()
    }


def median_time(fn: Callable[[], Any], **kwargs: Any) -> Timing:
    """Median wall-clock time of ``fn()``; keyword arguments as in :func:`median_times`."""
    return median_times({"fn": fn}, **kwargs)["fn"]


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, str | int | float]:
    """Torch version, thread count and CPU, for the header of a benchmark's output."""
    return {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count() or 0,
        "python": platform.python_version(),
        "load_avg_1min": os.getloadavg()[0],  # other processes competing for the cores
    }


def write_result(path: str | Path, payload: dict) -> dict:
    """Write a benchmark's ``payload`` as JSON to ``path`` (its folder made), say so, return it."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(payload, indent=2))
    print(f"wrote {out}")
    return payload
