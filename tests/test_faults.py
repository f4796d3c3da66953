"""Kill runs at random points; every resume must finish with the uninterrupted run's numbers.

Each run has about 90 kill-able events (environment steps during reward-free and rewarded
collection, checkpoint writes, iteration boundaries; see fault_driver.py). The test kills runs
at random events until MIN_KILLS kills have happened, resuming each time from the checkpoint;
a run that completes is compared with the uninterrupted reference and a fresh one is started.
"""

import json
import random
import subprocess
import sys
from pathlib import Path

DRIVER = Path(__file__).with_name("fault_driver.py")
KILLED = 137
MIN_KILLS = 20


def _run(checkpoint: Path, result: Path, kill_at: int) -> int:
    return subprocess.run(
        [sys.executable, str(DRIVER), str(checkpoint), str(result), str(kill_at)],
        capture_output=True,
        text=True,
        timeout=300,
    ).returncode


def _numbers(result: Path) -> dict:
    got = json.loads(result.read_text())
    got.pop("events")  # a resumed run replays fewer events
    return got


def test_killed_runs_resume_to_the_same_result(tmp_path):
    reference = tmp_path / "reference.json"
    assert _run(tmp_path / "reference.pt", reference, -1) == 0
    expected = _numbers(reference)
    assert expected["episodes_per_trial"] == 3 + 2 + 2 + 1
    assert expected["iteration_tags"][0] == [1, 1, 1, 2, 2, 3, 3, 4]

    rng = random.Random(0)
    checkpoint, result = tmp_path / "run.pt", tmp_path / "run.json"
    kills = completed = 0
    while kills < MIN_KILLS or not result.exists():
        code = _run(checkpoint, result, rng.randint(1, 30) if kills < MIN_KILLS else -1)
        if code == KILLED:
            kills += 1
            continue
        assert code == 0
        # same θ, choices and J', the very same bought episodes: none twice, none lost
        assert _numbers(result) == expected
        completed += 1
        if kills < MIN_KILLS:  # start a fresh run to kill
            checkpoint.unlink()
            result.unlink()
    assert kills == MIN_KILLS and completed >= 1
    print(f"{kills} kills, {completed} completed runs, all equal to the uninterrupted run")
