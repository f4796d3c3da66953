"""Example scripts run as real processes by the tests: starting one, waiting for its store to
reach a point (to kill it there), and watching processes through ``/proc``."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def start_example(script: str, *args: str) -> subprocess.Popen:
    """``examples/<script> args`` in a process of its own (one thread; pipes for its output),
    the leader of a process group of its own: ``os.killpg(proc.pid, ...)`` reaches the worker
    processes it forks as well."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env["OMP_NUM_THREADS"] = "1"
    return subprocess.Popen(
        [sys.executable, str(ROOT / "examples" / script), *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def run_example(script: str, *args: str, timeout: float = 300) -> str:
    """``examples/<script> args`` run to its end (as :func:`start_example`); its stdout. A
    non-zero exit fails the test with the end of the script's output."""
    proc = start_example(script, *args)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        proc.kill()
    assert proc.returncode == 0, f"{script} failed:\n{out[-3000:]}\n{err[-3000:]}"
    return out


def wait_for_episodes(store: Path, rows: int, proc: subprocess.Popen) -> None:
    """Until the run at ``store`` holds at least ``rows`` bought episode rows (committed)."""
    from torch_api.runs.store import RunStore, StoreError

    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if store.exists() and RunStore.read(store).num_episodes >= rows:
                return
        except StoreError:
            pass
        time.sleep(0.05)
    raise AssertionError(f"{store} never held {rows} episode rows")


def running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def children(pid: int) -> list[int]:
    """The pids of the processes whose parent is ``pid``."""
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids
