"""One run writes an output folder at a time: two real example processes on one folder, and a
run that would replace another run's files (``examples/_durable.py``)."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

from _processes import start_example, wait_for_episodes

TINY = ("--trials", "2", "--iterations", "2", "--steps", "5", "--repeats", "1")
TINY += ("--test-episodes", "2", "--test-steps", "5", "--threads", "1")


def _files(folder: Path) -> dict[str, int]:
    """Every file under ``folder`` and its modification time (ns), locks left out (they name
    the process that last asked for them)."""
    files = (p for p in folder.rglob("*") if p.is_file() and p.suffix != ".lock")
    return {str(p): p.stat().st_mtime_ns for p in files}


def test_overwrite_while_another_run_writes_the_folder_is_refused(tmp_path):
    """Run A is on its 2nd store (held still by SIGSTOP to its process group: the parent and
    the worker processes it forked); B with --overwrite
    is refused naming the folder, and touches nothing: it discarded A's finished store and
    bought it again before (every reward bought twice)."""
    args = (*TINY, "--out-dir", str(tmp_path))
    first = start_example("chain_walk_api.py", *args)
    wait_for_episodes(tmp_path / "checkpoints" / "decreasing_PL.db", 1, first)
    os.killpg(first.pid, signal.SIGSTOP)
    try:
        before = _files(tmp_path / "checkpoints")
        second = start_example("chain_walk_api.py", *args, "--overwrite")
        _, err = second.communicate(timeout=240)
        after = _files(tmp_path / "checkpoints")
    finally:
        os.killpg(first.pid, signal.SIGCONT)
    _, first_err = first.communicate(timeout=240)
    assert first.returncode == 0, first_err[-2000:]
    assert second.returncode == 1, err[-2000:]
    assert err.strip().splitlines()[-1].startswith(f"error: the folder {tmp_path} is in use")
    assert after == before


def test_a_flagless_run_with_other_settings_never_replaces_the_folders_results(tmp_path):
    """A finished run's JSON, CSV and figure; a second run into the folder with another
    ``--schedule`` (its stores have other names) and no flag is refused and changes nothing;
    it replaced the first run's results without a word."""
    args = (*TINY, "--out-dir", str(tmp_path))
    first = start_example("chain_walk_api.py", *args, "--schedule", "decreasing")
    _, err = first.communicate(timeout=240)
    assert first.returncode == 0, err[-2000:]
    payload = json.loads((tmp_path / "chain_walk_api.json").read_text())
    before = _files(tmp_path)
    second = start_example("chain_walk_api.py", *args, "--schedule", "fixed")
    _, err = second.communicate(timeout=240)
    assert second.returncode == 1, err[-2000:]
    assert "runs are stored already" in err and "decreasing_AL.db" in err  # beside its own
    assert _files(tmp_path) == before
    shutil.rmtree(tmp_path / "checkpoints")  # the stores gone, the results still there
    before = _files(tmp_path)
    third = start_example("chain_walk_api.py", *args, "--schedule", "fixed")
    _, err = third.communicate(timeout=240)
    assert third.returncode == 1, err[-2000:]
    assert f"results of a run are in the folder already ({tmp_path}/chain_walk_api.json" in err
    assert _files(tmp_path) == before
    assert json.loads((tmp_path / "chain_walk_api.json").read_text()) == payload


def test_misplaced_output_paths_are_one_line_exit_2_before_any_run(tmp_path):
    """``<out>/checkpoints`` a file, the CSV a folder: they were tracebacks (the second after
    every reward of the experiment was bought)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "checkpoints").write_text("not a folder")
    (tmp_path / "b" / "chain_walk_api.csv").mkdir(parents=True)
    for folder, message in [
        ("a", "checkpoints is in the way: a file where the stored runs' folder goes"),
        ("b", "chain_walk_api.csv is in the way: not a file, where the script writes one"),
    ]:
        proc = start_example("chain_walk_api.py", *TINY, "--out-dir", str(tmp_path / folder))
        _, err = proc.communicate(timeout=240)
        assert proc.returncode == 2, err[-2000:]
        assert err.strip().splitlines() == [f"error: {tmp_path / folder}/{message}"]
    assert not (tmp_path / "b" / "checkpoints").exists()  # nothing run, nothing stored
