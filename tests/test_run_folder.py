"""One run writes an output folder at a time: two real example processes on one folder, and a
run that would replace another run's files (:mod:`torch_api.experiment.folder`)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
from pathlib import Path

import pytest
from _processes import start_example, wait_for_episodes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import chain_walk_api  # noqa: E402

TINY = ("--trials", "2", "--iterations", "2", "--steps", "5", "--repeats", "1")
TINY += ("--test-episodes", "2", "--test-steps", "5", "--threads", "1")


def _files(folder: Path) -> dict[str, int]:
    """Every file under ``folder`` and its modification time (ns), locks left out (they name
    the process that last asked for them)."""
    files = (p for p in folder.rglob("*") if p.is_file() and p.suffix != ".lock")
    return {str(p): p.stat().st_mtime_ns for p in files}


def _refused(argv, capsys) -> tuple[int, list[str]]:
    """The exit status of ``chain_walk_api.main(argv)`` run here and the lines of its standard
    error (a ``SystemExit("error: ...")`` is printed by the interpreter, exit 1)."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        chain_walk_api.main(list(argv))
    code, err = stop.value.code, capsys.readouterr().err
    if isinstance(code, str):
        code, err = 1, err + code
    assert "Traceback" not in err
    return code, err.strip().splitlines()


def test_overwrite_while_another_run_writes_the_folder_is_refused(tmp_path):
    """Run A (worker processes: the default backend) holds still by SIGSTOP to its process
    group once a PL store holds an episode; B with --overwrite is refused naming the folder,
    and touches nothing: it discarded A's stores and bought them again before (every reward
    bought twice)."""
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


def test_a_flagless_run_with_other_settings_never_replaces_the_folders_results(tmp_path, capsys):
    """A finished run's JSON, CSV and figure; a second run into the folder with another
    ``--schedule`` (its stores have other names) and no flag is refused and changes nothing;
    it replaced the first run's results without a word."""
    args = (*TINY, "--backend", "local", "--out-dir", str(tmp_path))
    chain_walk_api.main([*args, "--schedule", "decreasing"])
    payload = json.loads((tmp_path / "chain_walk_api.json").read_text())
    before = _files(tmp_path)
    code, err = _refused([*args, "--schedule", "fixed"], capsys)
    assert code == 1 and len(err) == 1, err
    assert "runs are stored already" in err[0] and "decreasing_AL.db" in err[0]  # beside its own
    assert _files(tmp_path) == before
    shutil.rmtree(tmp_path / "checkpoints")  # the stores gone, the results still there
    before = _files(tmp_path)
    code, err = _refused([*args, "--schedule", "fixed"], capsys)
    assert code == 1 and len(err) == 1, err
    assert f"results of a run are in the folder already ({tmp_path}/chain_walk_api.json" in err[0]
    assert _files(tmp_path) == before
    assert json.loads((tmp_path / "chain_walk_api.json").read_text()) == payload


def test_misplaced_output_paths_are_one_line_exit_2_before_any_run(tmp_path, capsys):
    """``<out>/checkpoints`` a file, the CSV a folder: they were tracebacks (the second after
    every reward of the experiment was bought)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "checkpoints").write_text("not a folder")
    (tmp_path / "b" / "chain_walk_api.csv").mkdir(parents=True)
    for folder, message in [
        ("a", "checkpoints is in the way: a file where the stored runs' folder goes"),
        ("b", "chain_walk_api.csv is in the way: not a file, where the script writes one"),
    ]:
        argv = [*TINY, "--backend", "local", "--out-dir", str(tmp_path / folder)]
        code, err = _refused(argv, capsys)
        assert code == 2 and err == [f"error: {tmp_path / folder}/{message}"], err
    assert not (tmp_path / "b" / "checkpoints").exists()  # nothing run, nothing stored
