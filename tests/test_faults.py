"""Real SIGKILLs of real runs at many points; every bought reward survives, none is bought twice.

Each run (tests/fault_driver.py, forked from a server process that imported everything once)
counts its reward measurements in a file written by the rewarded environment. Runs are killed
with SIGKILL at random events (inside reward-free collection, inside a rewarded slice, inside a
store transaction between its rows and its commit, right after a commit with the bought rewards
not yet fitted, between iterations) and, a few times, by the test at a random moment; each is
resumed until it completes. The timed kills wait until the run has measured a random share of
what it has left to buy, so they land inside a live run, however fast or loaded the machine is.
Checked after every kill and at the end:

* the rewarded episodes stored never decrease (none lost);
* the measurements of a killed process exceed what it stored by at most one slice (the slice in
  flight), so nothing is measured twice beyond it;
* the completed run equals the uninterrupted one: θ, choices, J', and every bought episode
  tensor by tensor; each bought reward is stored exactly once.
"""

import json
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from torch_api.runs.store import RunStore

DRIVER = Path(__file__).with_name("fault_driver.py")
KILLED = -signal.SIGKILL
KILLS = {"all": 14, "episode": 8}  # event kills per mode (events per run: ~115 / ~160)
EVENTS = {"all": 115, "episode": 160}
TIMED_KILLS = 2  # per mode: SIGKILL from outside at a random moment
MAX_ATTEMPTS = 80  # runs and resumptions per mode (the seeded kills need about 30)
WAIT_FOR_PROGRESS = 120.0  # seconds a timed kill waits for the run to make its progress
AIMED = [  # first kills of each mode: at these points for sure, then at random events
    "inside_a_transaction@4",  # a fresh run: the 1st row of the 1st slice written, no commit
    "after_put_episodes@1",  # rewards of iteration 1 bought and stored, θ_1 not fitted
    "rewarded_step@5",  # in the middle of a rewarded slice
    "after_put_episodes@1",  # (in the resumed run: the next slice stored, not fitted)
]
TRIALS, STEPS, SCHEDULE = 2, 10, (3, 2, 2, 1)  # as in fault_driver.py


class Server:
    """tests/fault_driver.py serve: forks one run per request."""

    def __init__(self, log: Path) -> None:
        self.log = open(log, "w")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [sys.executable, str(DRIVER), "serve"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
        )

    def _answer(self, word: str) -> int:
        for line in self.proc.stdout:  # (skipping anything else a child printed)
            if line.startswith(word + " "):
                return int(line.split()[1])
        raise RuntimeError("the fault server ended: see its log")

    def run(self, *args, kill_when: Callable[[], bool] | None = None) -> int:
        """One run; with ``kill_when``, SIGKILL it from here as soon as that is true."""
        self.proc.stdin.write(" ".join(map(str, args)) + "\n")
        self.proc.stdin.flush()
        pid = self._answer("pid")
        if kill_when is not None:
            deadline = time.monotonic() + WAIT_FOR_PROGRESS
            while not kill_when() and _alive(pid):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"run {pid} made no progress in {WAIT_FOR_PROGRESS} s")
                time.sleep(0.002)
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:  # already done and reaped
                pass
        return self._answer("exit")

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        self.log.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    server = Server(tmp_path_factory.mktemp("server") / "server.log")
    yield server
    server.close()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _count(measured: Path) -> int:
    """Rewarded transitions measured so far (one line per step: the rows it measured)."""
    return sum(int(x) for x in measured.read_text().split()) if measured.exists() else 0


def _stored(path: Path) -> int:
    """Rewarded transitions stored in the run (every trial)."""
    if not path.exists():
        return 0
    stored = RunStore.read(path)
    return sum(len(e) for e in stored.episodes.values()) * TRIALS * STEPS


@pytest.mark.parametrize("slice_mode", ["all", "episode"])
def test_killed_runs_lose_no_reward_and_buy_none_twice(tmp_path, server, slice_mode):
    files = [tmp_path / f"reference.{x}" for x in ("db", "count", "json")]
    assert server.run(*files, -1, slice_mode) == 0
    expected = json.loads(files[2].read_text())
    reference_measured = _count(files[1])
    assert reference_measured == sum(SCHEDULE) * TRIALS * STEPS
    slice_size = TRIALS * STEPS * (max(SCHEDULE) if slice_mode == "all" else 1)
    rng = random.Random(14)
    kills = timed = runs = attempts = 0
    measured_all = wasted_all = 0
    while kills < KILLS[slice_mode] or timed < TIMED_KILLS:
        runs += 1
        path, measured, result = (tmp_path / f"run{runs}.{x}" for x in ("db", "count", "json"))
        wasted = 0
        while True:
            attempts += 1
            assert attempts <= MAX_ATTEMPTS, (
                f"{attempts - 1} runs and resumptions gave {kills} of {KILLS[slice_mode]} event "
                f"kills and {timed} of {TIMED_KILLS} timed kills: kills keep missing the runs"
            )
            stored_before, measured_before = _stored(path), _count(measured)
            kill_at = kill_when = None
            if kills < len(AIMED):
                kill_at = AIMED[kills]
            elif kills < KILLS[slice_mode]:
                kill_at = rng.randint(1, EVENTS[slice_mode])
            elif timed < TIMED_KILLS:  # once a random share of what is left is measured
                share = rng.randint(1, max(1, reference_measured - stored_before - 1))
                kill_when = lambda at=measured_before + share, m=measured: _count(m) >= at  # noqa: E731
            code = server.run(
                path, measured, result, kill_at or -1, slice_mode, kill_when=kill_when
            )
            stored_after, measured_after = _stored(path), _count(measured)
            assert stored_after >= stored_before, "stored rewards were lost"
            lost = (measured_after - measured_before) - (stored_after - stored_before)
            if code == KILLED:
                assert 0 <= lost <= slice_size, f"{lost} transitions measured and not kept"
                wasted += lost
                kills += kill_at is not None
                timed += kill_when is not None
                continue
            assert code == 0, "the run failed: see the server log"
            assert lost == 0
            break
        got = json.loads(result.read_text())
        assert got == expected  # θ, choices, J' and every bought episode, tensor by tensor
        assert _stored(path) == reference_measured  # each bought reward stored exactly once
        assert _count(measured) == reference_measured + wasted
        measured_all, wasted_all = measured_all + _count(measured), wasted_all + wasted
    kinds = set()
    for i in range(1, runs + 1):
        kills_file = tmp_path / f"run{i}.count.kills"
        kinds |= set(kills_file.read_text().split("\n")) if kills_file.exists() else set()
    assert {"rewarded step", "inside a transaction", "after put_episodes"} <= kinds, kinds
    print(
        f"{slice_mode}: {kills} + {timed} SIGKILLs in {runs} runs ({attempts} processes), all "
        "equal to the reference; "
        f"{measured_all} rewarded transitions measured for {runs * reference_measured} kept, "
        f"{wasted_all} in slices cut by a kill"
    )
    print(f"killed at: {sorted(kinds - {''})}")
