"""The library's logging: one logger, ``torch_api``, and TorchRL's storage notices kept quiet.

The library never prints; it logs through Python's :mod:`logging` on the ``torch_api`` logger
(and its children, e.g. ``torch_api.loop.iteration``), which has a ``NullHandler`` and no level of
its own: nothing shows unless the application configures logging, e.g.

>>> import logging
>>> logging.basicConfig(level=logging.INFO)  # doctest: +SKIP
>>> logging.getLogger("torch_api").setLevel(logging.DEBUG)  # doctest: +SKIP

TorchRL logs ``Initialized LazyTensorStorage with ... shape`` at INFO level, with a handler of
its own writing to stdout (its logger does not propagate), the first time a replay-buffer
storage is written. The library creates such storages for every episode buffer, so the lines
would land in the middle of a user's progress bars. :func:`quiet_storage_notices` drops exactly
these notices, and only while the library's own buffer writes run: it adds a filter to the
``torchrl`` logger for the duration of the call and removes it afterwards. Nothing global
changes: TorchRL's level, handlers and every other message stay as the user set them. Whoever
asks for TorchRL's details (``RL_LOGGING_LEVEL=DEBUG``, or the ``torchrl`` logger at DEBUG)
gets the notices too.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["LOGGER_NAME", "quiet_storage_notices"]

LOGGER_NAME = "torch_api"
_STORAGE_NOTICES = ("Initialized LazyTensorStorage", "Initialized LazyMemmapStorage")


class _DropStorageNotices(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_STORAGE_NOTICES)


_FILTER = _DropStorageNotices()


@contextmanager
def quiet_storage_notices() -> Iterator[None]:
    """Drop TorchRL's storage-initialisation INFO lines while the block runs.

    Left alone when the ``torchrl`` logger is enabled for DEBUG (the user asked for detail).
    """
    torchrl_logger = logging.getLogger("torchrl")
    if torchrl_logger.isEnabledFor(logging.DEBUG) or _FILTER in torchrl_logger.filters:
        yield
        return
    torchrl_logger.addFilter(_FILTER)
    try:
        yield
    finally:
        torchrl_logger.removeFilter(_FILTER)
