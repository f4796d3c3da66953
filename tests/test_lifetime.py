"""Worker processes die with their parent (torch_api/runs/lifetime.py), for real processes."""

import contextlib
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


# -- every worker the library starts ends within 2 s of its parent's SIGKILL ---------------------

ROOT = Path(__file__).resolve().parents[1]
SELECTOR_PARENT = """
import sys
import torch
from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.policies import LinearQPolicy


def chain_env(rows):  # top level: the workers unpickle it by name
    return ChainWalkEnv(batch_size=rows)


if __name__ == "__main__":
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    candidates = [
        LinearQPolicy(basis=basis, theta=torch.randn(2, 12), epsilon=0.5,
                      generator=torch.Generator().manual_seed(k))
        for k in range(3)
    ]
    selector = SamplingPolicySelector(
        env=chain_env, num_episodes=100, num_steps=100, num_repeats=10, num_workers=2
    )
    print("collecting", flush=True)
    while True:
        selector.collect(candidates)
"""
CHUNKS_PARENT = """
import time
from torch_api.runs.dispatch import run_chunks


def busy(chunk):  # top level: the workers unpickle it by name
    end = time.monotonic() + 600
    while time.monotonic() < end:
        pass


if __name__ == "__main__":
    print("collecting", flush=True)
    run_chunks(busy, [0, 1], backend="processes", workers=2)
"""


def _session(sid: int) -> list[int]:
    """The live (not zombie) processes of session ``sid``: a parent started as a session's
    leader and every process it started, whoever their parent is now."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            found.append(int(stat.parent.name))
    return found


def _workers_left_after_killing(tmp_path: Path, code: str, delay: float) -> list[str]:
    """Start ``code`` as the leader of a session of its own; SIGKILL it ``delay`` seconds after
    its second worker process appears; the command lines of its processes still alive 2 s
    later."""
    script = tmp_path / "parent.py"
    script.write_text(code)
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    parent = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert parent.stdout.readline().strip() == "collecting"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            workers = [
                p
                for p in _session(parent.pid)
                if b"multiprocessing" in _cmdline(p) and b"resource_tracker" not in _cmdline(p)
            ]
            if len(workers) >= 2:
                break
            time.sleep(0.01)
        else:
            raise AssertionError("no worker process started")
        time.sleep(delay)
        parent.kill()
        parent.wait(timeout=30)
        time.sleep(2.0)
        return [_cmdline(p).decode(errors="replace")[:120] for p in _session(parent.pid)]
    finally:
        for pid in _session(parent.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
    except OSError:
        return b""


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
@pytest.mark.parametrize("delay", [0.0, 2.0], ids=["starting", "collecting"])
def test_selector_workers_end_within_2s_of_their_parents_sigkill(tmp_path, delay):
    """SamplingPolicySelector(num_workers=2) collecting in TorchRL's MultiSyncCollector,
    its parent SIGKILLed as the workers start (importing torch, before any code of the
    library runs in them) or while they collect: they stayed alive 5-30 s (until their
    imports were done and they looked for their parent)."""
    assert _workers_left_after_killing(tmp_path, SELECTOR_PARENT, delay) == []


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_chunk_workers_end_within_2s_of_their_parents_sigkill(tmp_path):
    """run_chunks(backend="processes"): spawned pool workers, the parent SIGKILLed as they
    start."""
    assert _workers_left_after_killing(tmp_path, CHUNKS_PARENT, 0.0) == []
