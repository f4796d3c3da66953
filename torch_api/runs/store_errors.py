"""What can go wrong with a run's store (:mod:`torch_api.runs.store`): one exception per cause.

Every message names the run's path. The classes also derive from the built-in exception a
caller would otherwise catch (``ValueError``, ``RuntimeError``, ``FileExistsError``,
``OSError``).
"""

from __future__ import annotations

__all__ = [
    "CorruptRunError",
    "RunExistsError",
    "RunInUseError",
    "StoreError",
    "StoreWriteError",
    "SymlinkRefusedError",
]


class StoreError(Exception):
    """Base of the store's errors; every message names the run's path."""


class CorruptRunError(StoreError, ValueError):
    """The stored run cannot be read back as written (corrupted, truncated, foreign, other
    format or other settings). Nothing was changed in the object that tried to load it."""


class RunInUseError(StoreError, RuntimeError):
    """Another process holds the run open for writing."""


class RunExistsError(StoreError, FileExistsError):
    """A run is stored at the path and neither resume nor overwrite was asked for."""


class StoreWriteError(StoreError, OSError):
    """The run cannot be written (read-only place, disk full, not a directory, ...)."""


class SymlinkRefusedError(StoreWriteError):
    """A file would have been written through a symbolic link (a run's file or a report);
    the message names the link. Nothing was written."""
