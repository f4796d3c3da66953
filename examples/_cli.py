"""Command-line parsing shared by the example scripts, light enough to run before torch loads.

Every example reads top to bottom the same way: its docstring, a dataclass ``Args`` (one field
per option, declared with :func:`field`, whose ``help`` is its ``--help`` text: kept in the
field's metadata, so ``--help`` needs no source code and a script runs however it is started,
``python -m cProfile`` or a zipped install), a ``parse_args`` built on :func:`parse`, then::

    if __name__ == "__main__":
        parse_args()  # --help and bad flags answer here, before the heavy imports below

and only then torch, TorchRL, MuJoCo, matplotlib and the library. ``main(argv)`` parses again
(cheap) and runs. This module imports nothing heavy: ``--help`` and a bad flag answer in well
under a second (``tests/test_cli.py`` measures it).

The same flag means the same thing in every script: ``--trials`` (independent trials, >= 1),
``--seed`` (the master seed), ``--out-dir`` (created if needed; checked writable, with room,
before any work starts), ``--device`` (cpu or cuda[:N]), ``--resume`` (continue the runs
stored in ``--out-dir``; ``--overwrite`` discards them; a folder holding runs needs one of them),
``--threads`` (:class:`ThreadOptions`, 1 by default), ``--backend`` (where chunks of trials
run). A script that cannot honour one of them declares it in ``unavailable``: the flag is
refused with the reason, never silently ignored.

The options of the paired experiments are declared once: :class:`RunOptions` (``--trials``,
``--seed``, ``--out-dir``, ``--resume``, ``--overwrite``, ``--threads``, ``--logger``),
:class:`ChunkOptions` (those and ``--device``, ``--backend``, ``--chunks``, ``--workers``,
``--ray-address``, ``--ray-cpus``), :class:`SelectionOptions` (``--repeats``, ``--lam``); a
script's ``Args`` extends those it takes.

Validation is declarative where it can be: ``field(default, low=1)``, ``choices=...``; the
rest goes into a script's ``check(args)`` that returns the first problem as one line. Every
problem ends the script through ``argparse`` (``error: --trials must be >= 1, got -3``, exit
status 2).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

BACKENDS = ("local", "processes", "ray")
"""Where chunks of trials run (``torch_api.runs.dispatch.BACKENDS``; a test keeps them equal)."""

LOGGERS = ("none", "csv", "tensorboard", "wandb")
"""``--logger`` choices: TorchRL's loggers (``torchrl.record.loggers``) for the learning curves."""
_LOGGER_PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb"}

MIN_FREE_MB = 50
"""An output folder needs at least this much free space (MB) before a run starts."""

MAX_THREADS = 1024
"""``--threads`` above this is refused (torch would try to start them all)."""

TINY_LAMBDA = 1e-10
"""The smallest λ (``torch_api._checks.TINY_LAMBDA``; a test keeps them equal)."""

_DEVICE = re.compile(r"^(cpu|cuda(:\d+)?)$")


def field(
    default: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    above: float | None = None,
    choices: Sequence[Any] | None = None,
    why: str = "",
    help: str = "",
) -> Any:
    """A dataclass field with its ``--help`` text and its valid range or its choices.

    ``low <= value <= high`` (either bound optional), ``value > above``, or ``value in
    choices``. ``why`` is appended to the error, e.g. ``"(a paired t-test needs two)"``.
    """
    meta = {"low": low, "high": high, "above": above, "why": why, "help": help}
    meta["choices"] = tuple(choices) if choices else None
    return dataclasses.field(default=default, metadata=meta)


@dataclasses.dataclass
class SelectionOptions:
    """The settings of the sampling-policy selection (Algorithm 2), in every script that selects.
    A script's ``Args`` extends it, declaring a field again where its default differs."""

    repeats: int = field(5, low=1, help="Z, J-values averaged into J'")
    lam: float = field(1e-3, low=TINY_LAMBDA, help="λ, ridge regularisation")


_THREADS = (
    "torch intra-op threads (0: torch's default, one per core). 1 holds up under load: Figure "
    "8 at 200 trials took 20.9 s with 1 and 190.8 s with 2 on 2 loaded cores"
)
_MEMORY = (
    "freed memory: retain (glibc keeps it for the next tensor: examples/_process.py) or return "
    "(glibc's defaults: large blocks go back to the system at once)"
)


@dataclasses.dataclass
class ThreadOptions:
    """torch's threads and freed memory, in every script that computes with torch."""

    threads: int = field(1, low=0, high=MAX_THREADS, help=_THREADS)
    freed_memory: str = field("retain", choices=("retain", "return"), help=_MEMORY)


@dataclasses.dataclass
class RunOptions(ThreadOptions):
    """The options of every paired experiment (AL and PL runs on the same seeds, stored as they
    go). A script's ``Args`` extends it (and :class:`SelectionOptions`: ``class
    Args(SelectionOptions, RunOptions)`` lists the run options first in ``--help``), declaring a
    field again where its default differs."""

    trials: int = field(
        2, low=2, why="(a paired t-test needs two)", help="independent trials, all run as one batch"
    )
    seed: int = field(
        0,
        low=0,
        high=2**63 - 1,
        help="master seed; AL and PL of a schedule share their seeds (a paired design)",
    )
    out_dir: str = field(
        "results", help="where the JSON, the CSV, the figure and the stored runs go"
    )
    resume: bool = field(
        False,
        help=(
            "continue the runs stored in out_dir; completed runs are not recomputed (a missing "
            "run starts fresh)"
        ),
    )
    overwrite: bool = field(False, help="discard the runs stored in out_dir and start over")
    logger: str = field(
        "none",
        choices=LOGGERS,
        help=(
            "also write the learning curves (means over trials) with a TorchRL logger under "
            "<out-dir>/logs: csv, tensorboard or wandb (the last two need their package)"
        ),
    )


@dataclasses.dataclass
class ChunkOptions(RunOptions):
    """:class:`RunOptions` and where the runs go: the device, and chunks of trials on a
    backend (``torch_api.runs.dispatch``)."""

    device: str = field("cpu", help="where the algebra runs (cpu, cuda or cuda:N)")
    backend: str = field(
        "local",
        choices=BACKENDS,
        help=(
            "where the chunks of trials run: local (here, one after another), processes (a pool "
            "of local worker processes) or ray"
        ),
    )
    chunks: int = field(
        1,
        low=1,
        help=(
            "C, chunks of trials per schedule and method (each one batched run; results "
            "concatenated)"
        ),
    )
    workers: int = field(0, low=0, help="processes backend: worker processes (0: one per CPU core)")
    ray_address: str = field(
        "", help="Ray cluster to join (e.g. auto); empty starts a local Ray instance"
    )
    ray_cpus: int = field(0, low=0, help="CPUs of a local Ray instance (0: all)")


def run_options_error(args) -> str | None:
    """The rules between run options: ``--resume`` xor ``--overwrite`` (in any script that
    takes them), ``--chunks`` <= trials."""
    if getattr(args, "resume", False) and getattr(args, "overwrite", False):
        return "--resume and --overwrite exclude each other"
    if not isinstance(args, RunOptions):
        return None
    chunks = getattr(args, "chunks", 1)
    if chunks > args.trials:
        return f"--chunks must lie in 1..{args.trials} (--trials), got {chunks}"
    return None


def field_docs(cls) -> dict[str, str]:
    """The ``help`` of each field of a dataclass (for --help); a field declared again in a
    subclass has the subclass's text."""
    return {f.name: f.metadata.get("help", "") for f in dataclasses.fields(cls)}


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults after every option's help; description and epilog keep their line breaks."""


class _Unavailable(argparse.Action):
    """A flag this script cannot honour: refused with the reason (exit 2)."""

    def __init__(self, *args, reason: str = "", **kwargs) -> None:
        super().__init__(*args, nargs="?", default=argparse.SUPPRESS, **kwargs)
        self.reason = reason

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        parser.error(f"{option_string} is not available in {parser.prog}: {self.reason}")


def dataclass_parser(
    cls,
    description: str,
    epilog: str | None = None,
    unavailable: dict[str, str] | None = None,
) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` with one option per field of the dataclass ``cls``.

    Each field becomes ``--field-name`` with the field's default and docstring; a ``bool``
    field becomes a flag (``store_true``). ``unavailable`` maps flags this script does not
    take (``"device"``) to the reason, listed in the epilog and refused if given.
    """
    docs = field_docs(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    unavailable = {k: v for k, v in (unavailable or {}).items() if k not in fields}
    if unavailable:
        lines = [f"  --{name.replace('_', '-')}: {why}" for name, why in unavailable.items()]
        epilog = "\n\n".join(filter(None, [epilog, "not available here:\n" + "\n".join(lines)]))
    parser = argparse.ArgumentParser(
        description=description, epilog=epilog, formatter_class=_Formatter
    )
    for f in dataclasses.fields(cls):
        flag = f"--{f.name.replace('_', '-')}"
        text = docs.get(f.name, "").replace("%", "%%")
        if f.type in ("bool", bool):
            parser.add_argument(flag, action="store_true", help=text)
            continue
        parser.add_argument(
            flag, type=type(f.default), default=f.default, help=text, metavar=_metavar(f)
        )
    for name, why in unavailable.items():
        parser.add_argument(
            f"--{name.replace('_', '-')}", action=_Unavailable, reason=why, help=argparse.SUPPRESS
        )
    return parser


def _metavar(f: dataclasses.Field) -> str:
    if f.metadata.get("choices"):
        return "{" + ",".join(map(str, f.metadata["choices"])) + "}"
    return {int: "INT", float: "X"}.get(type(f.default), f.name.upper())


def range_error(cls, args) -> str | None:
    """The first field of ``args`` outside its declared range or choices (or a number that is
    not finite), as one line."""
    for f in dataclasses.fields(cls):
        value, meta = getattr(args, f.name), f.metadata
        flag = f"--{f.name.replace('_', '-')}"
        why = f" {meta['why']}" if meta.get("why") else ""
        if isinstance(value, float) and not math.isfinite(value):
            return f"{flag} must be a finite number, got {value}"
        if meta.get("choices") and value not in meta["choices"]:
            options = ", ".join(map(str, meta["choices"]))
            return f"{flag} must be one of {options}{why}, got {value!r}"
        low, high = meta.get("low"), meta.get("high")
        if low is not None and high is not None and not low <= value <= high:
            return f"{flag} must lie in {low}..{high}{why}, got {value}"
        if low is not None and value < low:
            return f"{flag} must be >= {low}{why}, got {value}"
        if high is not None and value > high:
            return f"{flag} must be <= {high}{why}, got {value}"
        if meta.get("above") is not None and not value > meta["above"]:
            return f"{flag} must be > {meta['above']}{why}, got {value}"
    return None


def device_syntax_error(name: str) -> str | None:
    """Why ``--device name`` is not ``cpu``, ``cuda`` or ``cuda:N`` (no torch needed), or None."""
    if _DEVICE.match(name):
        return None
    return f"--device must be cpu or cuda (or cuda:N), got {name!r}"


def device_error(name: str) -> str | None:
    """Why ``--device name`` cannot be used here (an unknown device, or no GPU), or None.

    Imports torch (to ask for CUDA): call it last, after the cheap checks.
    """
    if (why := device_syntax_error(name)) is not None:
        return why
    import torch

    if torch.device(name).type == "cuda" and not torch.cuda.is_available():
        return f"--device {name!r}: torch sees no CUDA GPU here (use --device cpu)"
    return None


def out_dir_error(
    path: str | os.PathLike, flag: str = "--out-dir", need_mb: int = MIN_FREE_MB
) -> str | None:
    """Why results cannot be written into the folder ``path`` (created if missing), or None.

    Creates the folder, writes and removes a probe file, and asks for ``need_mb`` MB free.
    """
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder) as probe:
            probe.write(b"probe")
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as error:
        return f"{flag} {str(folder)!r} is not writable: {error.strerror or error}"
    free_mb = shutil.disk_usage(folder).free / 2**20
    if free_mb < need_mb:
        return (
            f"{flag} {str(folder)!r} has {free_mb:.0f} MB free, a run needs at least {need_mb} MB"
        )
    return None


def logger_error(kind: str) -> str | None:
    """Why ``--logger kind`` cannot be used here (its package is missing), or None."""
    import importlib.util

    package = _LOGGER_PACKAGES.get(kind)
    if package is not None and importlib.util.find_spec(package) is None:
        return f"--logger {kind} needs the {package} package: pip install {package}"
    return None


def parse(
    cls: type[T],
    argv: Sequence[str] | None,
    doc: str | None,
    *,
    epilog: str | None = None,
    check: Callable[[T], str | None] | None = None,
    unavailable: dict[str, str] | None = None,
) -> T:
    """Parse ``argv`` into ``cls`` and validate it; any problem exits through ``argparse``.

    Order: types (argparse), declared ranges and choices, the rules between run options,
    ``check(args)`` (cross-field rules; returns one line or None), ``--device`` syntax, the
    logger's package, then the output (``--out-dir``, or the folder of ``--out FILE``: created,
    probed), then whether a CUDA device is really there (imports torch, so it comes last).

    Args:
        cls: the dataclass of arguments.
        argv: the arguments (``None``: ``sys.argv[1:]``).
        doc: the script's docstring; its first line is the ``--help`` description.
        epilog: for ``--help``.
        check: cross-field validation, returning the first problem as one line, or None.
        unavailable: flags this script cannot honour, mapped to the reason (:func:`not_here`).
    """
    parser = dataclass_parser(cls, first_line(doc), epilog, unavailable)
    args = cls(**vars(parser.parse_args(argv)))
    problem = range_error(cls, args) or run_options_error(args) or (check(args) if check else None)
    device = getattr(args, "device", None)
    if problem is None and device is not None:
        problem = device_syntax_error(device)
    if problem is None and hasattr(args, "logger"):
        problem = logger_error(args.logger)
    if problem is None and hasattr(args, "out_dir"):
        problem = out_dir_error(args.out_dir)
    if problem is None and hasattr(args, "out"):
        problem = out_dir_error(Path(args.out).parent, flag="--out (its folder)")
    if problem is None and device is not None and device != "cpu":
        problem = device_error(device)
    if problem is not None:
        parser.error(problem)
    return args


NOT_HERE = {
    "trials": "one run here, not the independent trials of an experiment",
    "resume": "nothing to resume: a run takes seconds; rerun it",
    "backend": "everything runs in this process",
    "out_dir": "this script writes one file: use --out FILE",
    "logger": "no learning curves: the JSON holds every number",
}
"""Why a script takes no such flag, where the reason is the same for every script."""


def not_here(*flags: str, **reasons: str) -> dict[str, str]:
    """The flags a script cannot honour and why: ``flags`` for the shared reasons of
    :data:`NOT_HERE`, ``reasons`` (flag=reason) for the script's own."""
    return {flag: NOT_HERE[flag] for flag in flags} | reasons


def first_line(doc: str | None) -> str:
    """The first line of a docstring (a script's one-line description)."""
    return (doc or "").strip().split("\n")[0]
