"""Worker processes die with their parent (torch_api/runs/lifetime.py), for real processes."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from _processes import running  # (tests/ is on sys.path)

LIFETIME = Path(__file__).resolve().parents[1] / "torch_api" / "runs" / "lifetime.py"
# the module alone (stdlib only), without importing torch through the package
LOAD = textwrap.dedent(f"""
    import importlib.util, sys, time
    spec = importlib.util.spec_from_file_location("lifetime", {str(LIFETIME)!r})
    lifetime = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(lifetime)
""")


def _gone_within(pid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while running(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not running(pid)


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_worker_dies_with_its_killed_parent():
    """Parent P starts worker W (which calls die_with_parent(P)); SIGKILL P: W ends."""
    worker = LOAD + "lifetime.die_with_parent(int(sys.argv[1]))\nprint('ready', flush=True)\n"
    worker += "time.sleep(120)\n"
    parent = textwrap.dedent(f"""
        import os, subprocess, sys, time
        w = subprocess.Popen([sys.executable, "-c", {worker!r}, str(os.getpid())],
                             stdout=subprocess.PIPE, text=True)
        assert w.stdout.readline().strip() == "ready"
        print(w.pid, flush=True)
        time.sleep(120)
    """)
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True)
    child = int(proc.stdout.readline())
    assert running(child)
    proc.kill()
    proc.wait(timeout=30)
    assert _gone_within(child, 10), "the worker outlived its killed parent"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_task_dies_with_a_driver_that_is_not_its_parent():
    """As a Ray task does: watch a driver process that is not the parent (direct=False)."""
    driver = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    task_code = LOAD + "lifetime.die_with_parent(int(sys.argv[1]), direct=False)\n"
    task_code += "print('ready', flush=True)\ntime.sleep(120)\n"
    task = subprocess.Popen(
        [sys.executable, "-c", task_code, str(driver.pid)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert task.stdout.readline().strip() == "ready"
        driver.kill()
        driver.wait(timeout=30)
        task.wait(timeout=10)  # the watchdog ends it
        assert task.returncode == -signal.SIGKILL
    finally:
        for p in (driver, task):
            if p.poll() is None:
                os.kill(p.pid, signal.SIGKILL)
                p.wait()


def test_a_worker_started_after_its_parent_died_ends_at_once():
    """The pid the parent had is passed in: a worker that starts late sees it is gone."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    late = subprocess.run(
        [sys.executable, "-c", LOAD + f"lifetime.die_with_parent({gone.pid})\nprint('lived')"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert late.returncode == -signal.SIGKILL and "lived" not in late.stdout
