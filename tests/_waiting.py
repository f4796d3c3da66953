"""Waiting for a running example's store to reach a point (for tests that kill it there)."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path


def wait_for_episodes(store: Path, rows: int, proc: subprocess.Popen) -> None:
    """Until the run at ``store`` holds at least ``rows`` bought episode rows (committed)."""
    from torch_api.store import RunStore, StoreError

    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if store.exists() and RunStore.read(store).num_episodes >= rows:
                return
        except StoreError:
            pass
        time.sleep(0.05)
    raise AssertionError(f"{store} never held {rows} episode rows")
