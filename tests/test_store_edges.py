"""The durable store at its edges, on real processes and real files: a kill or a signal while a
store is being created, a killed writer's database cut short or flipped, a signal that lands
while a commit is open.

Each child is a real process forked from the test (it has torch loaded already, as a run has),
killed by a real SIGKILL or stopped by a real SIGTERM; the attacks are those that
``benchmarks/durability_attacks.py`` counts.
"""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from torch_api.runs.store import CorruptRunError, RunStore

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from durability_attacks import (  # noqa: E402  (the attacks, counted there)
    COMMITS,
    CONFIG,
    CREATED,
    episodes,
    in_child,
    kill_at_file_step,
    killed_writer,
    signal_inside_a_commit,
    stop_at_statement,
)


@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM])
def test_a_stop_at_any_statement_of_store_creation_leaves_a_run_resume_takes(tmp_path, signum):
    """Killed (SIGKILL) or interrupted (SIGTERM) before each SQL statement of the creation in
    turn: ``resume`` then opens the run, empty (it was refused as "no such table: meta", "a
    readonly database" or "format None")."""
    refused = []
    for k in range(1, 60):
        path = tmp_path / f"k{k}" / "run.db"
        code = in_child(stop_at_statement(path, k, signum))
        if code == CREATED:
            break
        assert code in (-signal.SIGKILL, 128 + signal.SIGTERM), code
        try:
            with RunStore(path, config=CONFIG, resume=True) as store:
                assert store.started_fresh
            assert RunStore.read(path).config == CONFIG
        except Exception as error:  # noqa: BLE001
            refused.append(f"stopped at statement {k}: {type(error).__name__}: {error}")
    else:
        raise AssertionError("the creation never ended")
    assert k > 3, "the trace saw too few statements to test anything"
    assert refused == []


def test_a_kill_at_any_file_step_of_store_creation_leaves_a_run_resume_takes(tmp_path):
    """SIGKILL before each call into ``os`` of the creation (open, write, fsync, rename) in
    turn. A kill between the counter's creation and its first write left it empty: the run was
    refused as "the commit counter ... is damaged" (seen once in 16 SIGTERMs of the CLI)."""
    refused = []
    for k in range(1, 60):
        path = tmp_path / f"k{k}" / "run.db"
        code = in_child(kill_at_file_step(path, k))
        if code == CREATED:
            break
        assert code == -signal.SIGKILL, code
        try:
            with RunStore(path, config=CONFIG, resume=True) as store:
                assert store.started_fresh
        except Exception as error:  # noqa: BLE001
            refused.append(f"killed at step {k}: {type(error).__name__}: {error}")
    assert k > 3 and refused == []


def _copy(path: Path, to: Path) -> Path:
    to.mkdir()
    for f in path.parent.iterdir():
        if f.name.startswith(path.name) and not f.name.endswith(".lock"):
            shutil.copy(f, to / f.name)
    return to / path.name


def _outcome(path: Path, commits: int) -> str:
    """ "kept" (every committed row back), "refused" (naming the loss) or what went wrong."""
    try:
        with RunStore(path, config=CONFIG, resume=True) as store:
            got = 0 if store.stored is None else store.stored.num_episodes
    except CorruptRunError as error:
        said = str(error)
        return "refused" if "commits" in said and str(path) in said else said
    return "kept" if got == commits else f"silently {got} of {commits} rows"


def test_a_killed_writers_database_cut_or_flipped_is_refused_never_silently(tmp_path):
    """The rows of a killed writer lived in ``run.db-wal``, which SQLite ends at its first frame
    that fails a checksum: cut or flipped, the run lost rows without a word. They now live in
    ``run.db`` itself (a rollback journal; no log is left after a kill between commits). Cut
    or flipped anywhere: every row back, or a refusal that names the commits."""
    commits, path = COMMITS, tmp_path / "killed" / "run.db"
    killed_writer(path, inside=False)
    assert not Path(f"{path}-wal").exists() and not Path(f"{path}-journal").exists()
    data = path.read_bytes()
    outcomes = {}
    cuts = [0, 100, len(data) // 3, len(data) - 4096, len(data) - 100]
    for i, cut in enumerate(cuts):
        copy = _copy(path, tmp_path / f"cut{i}")
        copy.write_bytes(data[:cut])
        outcomes[f"cut at {cut}"] = _outcome(copy, commits)
    for i, offset in enumerate(range(40, len(data), len(data) // 9)):
        copy = _copy(path, tmp_path / f"flip{i}")
        damaged = bytearray(data)
        damaged[offset] ^= 1 << (i % 8)
        copy.write_bytes(bytes(damaged))
        outcomes[f"flip at {offset}"] = _outcome(copy, commits)
    bad = {k: v for k, v in outcomes.items() if v not in ("kept", "refused")}
    assert bad == {}
    assert "refused" in outcomes.values()


def test_a_signal_that_lands_while_a_commit_is_open_waits_for_the_commit(tmp_path):
    """torch starts threads that block no signal, so a SIGTERM to the process is taken by one
    of them and its Python handler runs in the main thread at the next bytecode: inside the
    open transaction, which it rolled back (the slice was bought again)."""
    path = tmp_path / "run.db"
    assert signal_inside_a_commit(path) == 128 + signal.SIGTERM
    assert RunStore.read(path).records == {1: {"iteration": 1}}


def _stored(folder: Path) -> Path:
    path = folder / "run.db"
    with RunStore(path, config=CONFIG) as store:
        store.put_episodes(1, episodes(0))
        store.put_record(1, {"iteration": 1})
    return path


def test_a_store_with_a_trigger_is_refused_before_it_eats_rows(tmp_path):
    """A trigger a run never has (here: one that deletes every bought row) makes the store
    foreign: refused, not resumed to swallow each row the resume buys."""
    path = _stored(tmp_path)
    db = sqlite3.connect(path)
    db.execute("CREATE TRIGGER eat AFTER INSERT ON episode BEGIN DELETE FROM episode; END")
    db.commit()
    db.close()
    with pytest.raises(CorruptRunError, match="schema objects a run never has"):
        RunStore(path, config=CONFIG, resume=True)


def test_a_config_nested_deeper_than_python_recurses_is_corrupt_not_a_traceback(tmp_path):
    from torch_api.runs.store import _digest

    path = _stored(tmp_path)
    deep = b"[" * 100_000 + b"]" * 100_000
    db = sqlite3.connect(path)
    db.execute(
        "UPDATE meta SET value = ?, digest = ? WHERE key = 'config'",
        (deep, _digest("meta", ("config",), deep)),
    )
    db.commit()
    db.close()
    with pytest.raises(CorruptRunError, match="RecursionError"):
        RunStore.read(path)


def test_an_intact_run_in_a_read_only_folder_reads_back(tmp_path):
    """chmod 0o500 for an ordinary user; for root a read-only bind mount (``unshare -m``). It
    was "cannot read the run ...: unable to open database file" (SQLite makes a ``-shm``)."""
    path = _stored(tmp_path / "ro")
    os.chmod(path.parent, 0o500)
    script = (
        f"from torch_api.runs.store import RunStore; print(RunStore.read({str(path)!r}).records)"
    )
    command = [sys.executable, "-c", script]
    if os.access(path.parent, os.W_OK):  # root
        if shutil.which("unshare") is None:
            pytest.skip("root without unshare: no way to make a folder read-only here")
        ro = path.parent
        mount = f'mount --bind -o ro {ro} {ro} && exec {sys.executable} -c "$0"'
        command = ["unshare", "-m", "sh", "-c", mount, script]
    out = subprocess.run(command, capture_output=True, text=True, timeout=120)
    os.chmod(path.parent, 0o700)
    assert out.stdout.strip() == "{1: {'iteration': 1}}", out.stderr[-800:]
