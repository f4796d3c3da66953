"""Command-line parsing shared by the example scripts, light enough to run before torch loads.

Every example reads top to bottom the same way: its docstring, a dataclass ``Args`` (one field
per option, the string literal under a field is its ``--help`` text), a ``parse_args`` built on
:func:`parse`, then::

    if __name__ == "__main__":
        parse_args()  # --help and bad flags answer here, before the heavy imports below

and only then torch, TorchRL, MuJoCo, matplotlib and the library. ``main(argv)`` parses again
(cheap) and runs. This module imports nothing heavy: ``--help`` and a bad flag answer in well
under a second (``tests/test_cli.py`` measures it).

The same flag means the same thing in every script: ``--trials`` (independent trials, >= 1),
``--seed`` (the master seed), ``--out-dir`` (created if needed; checked writable, with room,
before any work starts), ``--device`` (cpu or cuda[:N]), ``--resume`` (continue the
runs stored in ``--out-dir``; ``--overwrite`` discards them, and without either a folder that
holds runs is refused), ``--backend`` (where chunks of trials run). A script that cannot
honour one of them declares it in ``unavailable``: the flag is refused with the reason, never
silently ignored.

Validation is declarative where it can be: ``field(default, low=1)``, ``choices=...``; the
rest goes into a script's ``check(args)`` that returns the first problem as one line. Every
problem ends the script through ``argparse`` (``error: --trials must be >= 1, got -3``, exit
status 2).
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import inspect
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

BACKENDS = ("local", "processes", "ray")
"""Where chunks of trials run (``torch_api.dispatch.BACKENDS``; a test keeps them equal)."""

LOGGERS = ("none", "csv", "tensorboard", "wandb")
"""``--logger`` choices: TorchRL's loggers (``torchrl.record.loggers``) for the learning curves."""
_LOGGER_PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb"}

MIN_FREE_MB = 50
"""An output folder needs at least this much free space (MB) before a run starts."""

_DEVICE = re.compile(r"^(cpu|cuda(:\d+)?)$")


def field(
    default: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    above: float | None = None,
    choices: Sequence[Any] | None = None,
    why: str = "",
) -> Any:
    """A dataclass field with its valid range or its choices.

    ``low <= value <= high`` (either bound optional), ``value > above``, or ``value in
    choices``. ``why`` is appended to the error, e.g. ``"(a paired t-test needs two)"``.
    """
    meta = {"low": low, "high": high, "above": above, "why": why}
    meta["choices"] = tuple(choices) if choices else None
    return dataclasses.field(default=default, metadata=meta)


def field_docs(cls) -> dict[str, str]:
    """The string literal under each field of a dataclass (for --help)."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    return {
        a.target.id: " ".join(b.value.value.split())
        for a, b in zip(body, body[1:], strict=False)
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr)
    }


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
    """The first field of ``args`` outside its declared range or choices, as one line."""
    for f in dataclasses.fields(cls):
        value, meta = getattr(args, f.name), f.metadata
        flag = f"--{f.name.replace('_', '-')}"
        why = f" {meta['why']}" if meta.get("why") else ""
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


def make_logger(kind: str, out_dir: str | os.PathLike, experiment: str):
    """A TorchRL logger writing under ``<out_dir>/logs/<experiment>``, or None for ``"none"``.

    ``csv`` writes one CSV file per curve (``scalars/<name>.csv``: step, value), ``tensorboard``
    event files for ``tensorboard --logdir <out_dir>/logs``, ``wandb`` a Weights & Biases run
    (log in first; the run is named after the experiment).
    """
    if kind == "none":
        return None
    from torchrl.record.loggers import get_logger

    return get_logger(kind, logger_name=str(Path(out_dir) / "logs"), experiment_name=experiment)


def log_means(logger, prefix: str, step: int, values: dict[str, Any]) -> None:
    """Log ``prefix/name`` = the mean of each per-trial list (or the number) at ``step``."""
    if logger is None:
        return
    for name, value in values.items():
        if value is None:
            continue
        if isinstance(value, list | tuple):
            if not value:
                continue
            value = sum(value) / len(value)
        logger.log_scalar(f"{prefix}/{name}", float(value), step=step)


def parse(
    cls: type[T],
    argv: Sequence[str] | None,
    *,
    description: str,
    epilog: str | None = None,
    check: Callable[[T], str | None] | None = None,
    unavailable: dict[str, str] | None = None,
    out_dir: str | None = "out_dir",
) -> T:
    """Parse ``argv`` into ``cls`` and validate it; any problem exits through ``argparse``.

    Order: types (argparse), declared ranges and choices, ``check(args)`` (cross-field rules;
    returns one line or None), ``--device`` syntax, then the output folder (created, probed),
    then whether a CUDA device is really there (imports torch, so it comes last).

    Args:
        cls: the dataclass of arguments.
        argv: the arguments (``None``: ``sys.argv[1:]``).
        description, epilog: for ``--help``.
        check: cross-field validation, returning the first problem as one line, or None.
        unavailable: flags this script cannot honour, mapped to the reason.
        out_dir: the field naming the output folder (``None``: the script writes none, or
            checks its output itself).
    """
    parser = dataclass_parser(cls, description, epilog, unavailable)
    args = cls(**vars(parser.parse_args(argv)))
    problem = range_error(cls, args) or (check(args) if check else None)
    device = getattr(args, "device", None)
    if problem is None and device is not None:
        problem = device_syntax_error(device)
    if problem is None and hasattr(args, "logger"):
        problem = logger_error(args.logger)
    if problem is None and out_dir is not None and hasattr(args, out_dir):
        problem = out_dir_error(getattr(args, out_dir), f"--{out_dir.replace('_', '-')}")
    if problem is None and device is not None and device != "cpu":
        problem = device_error(device)
    if problem is not None:
        parser.error(problem)
    return args


def first_line(doc: str | None) -> str:
    """The first line of a docstring (a script's one-line description)."""
    return (doc or "").strip().split("\n")[0]


# -- durable runs: --resume / --overwrite, signals ------------------------------------------


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived (raised in the main thread by :func:`raise_on_signals`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def raise_on_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise :class:`Interrupted` in the main thread; the
    handlers before it are restored after it.

    The run's store holds both back while it commits, so the exception arrives between
    commits: the write in flight always completes.
    """
    import signal

    def handler(signum, frame):
        raise Interrupted(signum)

    before = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in before.items():
            signal.signal(sig, old)


def stored_runs_error(paths: Sequence[Path], resume: bool, overwrite: bool) -> str | None:
    """Why the script must not start: runs are stored at ``paths`` and neither ``--resume`` nor
    ``--overwrite`` was given (or both were); None if it may."""
    if resume and overwrite:
        return "--resume and --overwrite exclude each other"
    held = [p for p in paths if p.is_file() and p.stat().st_size > 0]
    if held and not (resume or overwrite):
        names = ", ".join(str(p) for p in held[:3]) + (" ..." if len(held) > 3 else "")
        return (
            f"runs are stored already ({names}); add --resume to continue them or --overwrite "
            "to discard them"
        )
    return None


def stored_summary(paths: Sequence[Path]) -> tuple[int, int]:
    """(the iteration in flight, rewarded episodes stored over all trials) of the runs stored
    at ``paths`` (read only; missing or unreadable files count as empty)."""
    from torch_api.store import RunStore, StoreError

    in_flight, episodes, last = [], 0, 0
    for path in paths:
        if not Path(path).is_file():
            continue
        try:
            stored = RunStore.read(path)
        except StoreError:
            continue
        trials = stored.config.get("num_trials") or 1
        episodes += stored.num_episodes * trials
        done, total = len(stored.records), len(stored.config.get("schedule", []))
        last = max(last, done)
        if done < total:
            in_flight.append(done + 1)
    return (min(in_flight) if in_flight else last), episodes


def exit_interrupted(signum: int, paths: Sequence[Path], where: str | os.PathLike) -> None:
    """Print the one line of an interrupted run and exit with 128 + the signal (130, 143)."""
    import sys

    iteration, episodes = stored_summary(paths)
    print(
        f"interrupted at iteration {iteration}; {episodes} rewarded episodes stored in {where}; "
        "continue with --resume",
        file=sys.stderr,
        flush=True,
    )
    raise SystemExit(128 + signum)


def exit_store_error(error: BaseException) -> None:
    """A store error (a run in use, unwritable, corrupted, of other settings) as one line."""
    import sys

    print(f"error: {error}", file=sys.stderr, flush=True)
    raise SystemExit(1)
