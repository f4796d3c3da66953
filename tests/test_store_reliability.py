"""Reliability of a run's files, the last edges (torch_api/runs/): any one file of a run lost or
damaged is refused with the commits lost, never resumed short in silence; ``RunStore.close``
never closes a descriptor it no longer owns; report files are written atomically and never
through a symbolic link.

The stores are written by real processes (forked from the test), killed by a real SIGKILL.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torch_api.runs.store import CorruptRunError, RunExistsError, RunStore, StoreWriteError
from torch_api.runs.store_files import write_counter

CONFIG = {"N": 1}
COMMITS = 5


def in_child(body) -> int:
    """``body()`` in a forked process; its exit status (negative: the signal that ended it)."""
    pid = os.fork()
    if pid == 0:  # the child: never returns into the caller
        code = 0
        try:
            body()
        except BaseException:  # noqa: BLE001
            code = 3
        os._exit(code)
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def episodes(m: int) -> dict:
    return {m: TensorDict({"reward": torch.full((2, 5), float(m))}, batch_size=[2, 5])}


def killed_writer(path: Path, commits: int) -> None:
    """A store at ``path`` whose writer put ``commits`` slices and was SIGKILLed."""

    def body() -> None:
        store = RunStore(path, config=CONFIG)
        for m in range(commits):
            store.put_episodes(1, episodes(m))
        os.kill(os.getpid(), signal.SIGKILL)

    assert in_child(body) == -signal.SIGKILL


@pytest.fixture(scope="module")
def killed(tmp_path_factory) -> Path:
    """A store whose writer put 5 slices of one episode each and was SIGKILLed."""
    path = tmp_path_factory.mktemp("killed") / "run.db"
    killed_writer(path, COMMITS)
    return path


def _copy(path: Path, to: Path) -> Path:
    to.mkdir(parents=True)
    for f in path.parent.iterdir():
        if f.name.startswith(path.name) and not f.name.endswith(".lock"):
            shutil.copy(f, to / f.name)
    return to / path.name


def _outcome(path: Path) -> str:
    """ "kept" (every committed row back), "refused" (naming the commits), or what went wrong."""
    try:
        with RunStore(path, config=CONFIG, resume=True) as store:
            got = 0 if store.stored is None else store.stored.num_episodes
    except CorruptRunError as error:
        said = str(error)
        return "refused" if str(path) in said and "commits" in said else f"unclear: {said}"
    return "kept" if got == COMMITS else f"silently {got} of {COMMITS} rows"


def _damages(data: bytes) -> dict[str, bytes | None]:
    """Ways to damage one file: removed (None), cut at some lengths, one bit flipped."""
    out: dict[str, bytes | None] = {"removed": None}
    for cut in sorted({0, 1, len(data) // 3, len(data) // 2, max(len(data) - 100, 0)}):
        if cut < len(data):
            out[f"cut at {cut}"] = data[:cut]
    for i, offset in enumerate(range(0, len(data), max(len(data) // 7, 1))):
        flipped = bytearray(data)
        flipped[offset] ^= 1 << (i % 8)
        out[f"bit flipped at {offset}"] = bytes(flipped)
    return out


def test_any_one_file_of_a_run_lost_or_damaged_is_refused_never_resumed_short(killed, tmp_path):
    """Each file a killed writer left (the database, its log or journal if any, the counter)
    removed, cut or flipped in turn: every committed row back, or a refusal naming the
    commits. A lost or damaged counter is refused even where the database is whole: nothing
    else could tell a database cut short (it was accepted as it was)."""
    files = sorted(f.name for f in killed.parent.iterdir() if not f.name.endswith(".lock"))
    assert "run.db.commits" in files
    outcomes = {}
    for name in files:
        for how, data in _damages((killed.parent / name).read_bytes()).items():
            copy = _copy(killed, tmp_path / f"{name}-{how.replace(' ', '-')}")
            if data is None:
                (copy.parent / name).unlink()
            else:
                (copy.parent / name).write_bytes(data)
            outcomes[f"{name} {how}"] = _outcome(copy)
    bad = {k: v for k, v in outcomes.items() if v not in ("kept", "refused")}
    assert bad == {}
    counter = {k: v for k, v in outcomes.items() if k.startswith("run.db.commits")}
    assert set(counter.values()) == {"refused"}, counter


@pytest.mark.parametrize("counter", ["removed", "rewritten with 3 commits"])
def test_a_counter_gone_or_rewritten_beside_a_damaged_log_never_resumes_short(
    killed, tmp_path, counter
):
    """The attack of issue 45: the counter removed, or rewritten with a recomputed digest to
    the commits a cut log still holds, beside a log cut short or flipped. It resumed with 3 of
    5 committed rows (and bought the other 2 again) or restarted from nothing. Now the
    committed rows live in the database file itself: whatever the log, every row is back (or
    the run is refused)."""
    outcomes = {}
    logs = [f for f in killed.parent.iterdir() if f.name.endswith(("-wal", "-journal"))]
    damages = {"no log": None}
    for log in logs:
        data = log.read_bytes()
        damages |= {f"{log.name} cut at {n}": (log.name, data[:n]) for n in (32, len(data) // 2)}
        flipped = bytearray(data)
        flipped[len(data) // 2] ^= 4
        damages[f"{log.name} flipped"] = (log.name, bytes(flipped))
    for i, (how, damage) in enumerate(damages.items()):
        copy = _copy(killed, tmp_path / f"try{i}")
        if damage is not None:
            (copy.parent / damage[0]).write_bytes(damage[1])
        if counter == "removed":
            Path(f"{copy}.commits").unlink()
        else:
            write_counter(copy, 3, 3)
        outcomes[how] = _outcome(copy)
    bad = {k: v for k, v in outcomes.items() if v not in ("kept", "refused")}
    assert bad == {}


def test_a_lost_counter_beside_a_store_with_commits_is_refused_not_taken_as_new(killed, tmp_path):
    """Without its counter the store cannot show it holds every commit: refused, with or
    without --resume; never taken as a new run (nor resumed as it is)."""
    copy = _copy(killed, tmp_path / "run")
    Path(f"{copy}.commits").unlink()
    with pytest.raises(CorruptRunError, match=rf"{COMMITS} commits") as refused:
        RunStore(copy, config=CONFIG, resume=True)
    assert "counter" in str(refused.value) and "remove" not in str(refused.value)
    with pytest.raises((CorruptRunError, RunExistsError)):
        RunStore(copy, config=CONFIG)
    with RunStore(copy, config=CONFIG, overwrite=True) as store:
        assert store.started_fresh


def test_a_damaged_counter_is_refused_without_advising_to_remove_it(killed, tmp_path):
    """The message advised removing the counter "to accept the store as it is": the way to
    resume a run cut short without a word."""
    copy = _copy(killed, tmp_path / "run")
    counter = Path(f"{copy}.commits")
    counter.write_bytes(counter.read_bytes().replace(b"commits 5", b"commits 9"))
    with pytest.raises(CorruptRunError, match="damaged") as refused:
        RunStore(copy, config=CONFIG, resume=True)
    said = str(refused.value)
    assert "remove" not in said and f"{COMMITS} commits" in said and "--overwrite" in said


def test_a_writer_killed_inside_a_commit_leaves_every_earlier_commit(tmp_path):
    """SIGKILL in the middle of a large slice (its pages spilled into the database file before
    the commit): the next open rolls the slice back, every earlier commit stands."""
    path = tmp_path / "run.db"

    def body() -> None:
        store = RunStore(path, config=CONFIG)
        for m in range(COMMITS):
            store.put_episodes(1, episodes(m))
        real, seen = RunStore._put, [0]

        def put(db, table, key, value, free=None):
            real(db, table, key, value, free)
            seen[0] += table == "episode"
            if seen[0] == 30:
                os.kill(os.getpid(), signal.SIGKILL)

        RunStore._put = staticmethod(put)
        big = TensorDict({"reward": torch.randn(64, 1024)}, batch_size=[64, 1024])
        store.put_episodes(2, dict.fromkeys(range(40), big))

    assert in_child(body) == -signal.SIGKILL
    assert Path(f"{path}-journal").stat().st_size > 0  # hot: the slice's pages as they were
    with pytest.raises(CorruptRunError, match="inside a commit by a killed writer"):
        RunStore.read(path)  # a reader never writes, so it cannot roll the slice back
    assert _outcome(path) == "kept"
    assert not Path(f"{path}-journal").exists()
    assert RunStore.read(path).num_episodes == COMMITS


# -- (b) close() never closes a descriptor it no longer owns -----------------------------------


def _locked_elsewhere(lock: Path) -> bool:
    """Whether another process fails to take the flock on ``lock``."""
    code = (
        "import fcntl, os, sys\n"
        f"fd = os.open({str(lock)!r}, os.O_RDWR)\n"
        "try:\n    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\nexcept BlockingIOError:\n"
        "    sys.exit(7)\n"
    )
    return subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 7


def test_close_again_after_a_signal_never_closes_another_stores_lock(tmp_path, monkeypatch):
    """A SIGINT handled right after ``os.close(lock fd)`` left the descriptor set; the next
    store got the same number; a second ``close()`` closed that store's lock, and a second
    process could then write the same run."""
    first = RunStore(tmp_path / "a.db", config=CONFIG)
    real_close, fired, lock = os.close, [], first._lock_fd

    def close_then_interrupt(fd):
        real_close(fd)
        if fd == lock and not fired:
            fired.append(fd)
            raise KeyboardInterrupt  # as a handler of a SIGINT taken right after the call

    monkeypatch.setattr(os, "close", close_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        first.close()
    monkeypatch.setattr(os, "close", real_close)
    second = RunStore(tmp_path / "b.db", config=CONFIG)
    assert second._lock_fd == fired[0]  # the number was reused (what makes the bug bite)
    first.close()  # idempotent: the number is not first's any more
    first.close()
    assert _locked_elsewhere(tmp_path / "b.db.lock")
    second.put_record(1, {"iteration": 1})
    second.close()
    assert not _locked_elsewhere(tmp_path / "b.db.lock")


def test_close_is_idempotent(tmp_path):
    store = RunStore(tmp_path / "run.db", config=CONFIG)
    store.close()
    store.close()
    assert store.closed
    with pytest.raises(StoreWriteError, match="closed"):
        store.put_record(1, {"iteration": 1})


# -- (d) files written atomically, never through a symbolic link -------------------------------


@pytest.mark.parametrize("existing", [False, True])
@pytest.mark.parametrize("where", ["destination", "temporary name"])
def test_a_planted_symlink_is_refused_naming_it_and_its_target_is_untouched(
    tmp_path, existing, where
):
    from torch_api.runs.files import SymlinkRefusedError, temporary_name, write_text_atomic

    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    path = tmp_path / "out" / "results.json"
    path.parent.mkdir()
    if existing:
        path.write_text("old results")
    link = path if where == "destination" else temporary_name(path)
    if link.exists() or link.is_symlink():
        link.unlink()
    link.symlink_to(target)
    with pytest.raises(SymlinkRefusedError, match=str(link)) as refused:
        write_text_atomic(path, "new results")
    assert "\n" not in str(refused.value)
    assert isinstance(refused.value, StoreWriteError)
    assert target.read_text() == "keep me"
    assert link.is_symlink()
    if where != "destination":  # nothing written: the old file as it was, or none
        assert path.read_text() == "old results" if existing else not path.exists()


@pytest.mark.parametrize("existing", [False, True])
def test_atomic_writes_replace_whole_and_leave_nothing_behind(tmp_path, existing):
    from torch_api.runs.files import write_bytes_atomic, write_text_atomic

    path = tmp_path / "table.csv"
    if existing:
        path.write_text("old")
    write_text_atomic(path, "a,b\n1,2\n")
    assert path.read_text() == "a,b\n1,2\n"
    write_bytes_atomic(path, b"\x00\x01")
    assert path.read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    from torch_api.runs import files

    path = tmp_path / "results.json"
    path.write_text("old results")

    def full(fd, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(files.os, "write", full)
    with pytest.raises(OSError, match="No space"):
        files.write_text_atomic(path, "new results")
    assert path.read_text() == "old results"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]


def test_a_figure_is_saved_atomically_and_never_through_a_symlink(tmp_path):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torch_api.runs.files import SymlinkRefusedError, save_figure_atomic

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = tmp_path / "curve.png"
    save_figure_atomic(fig, path)
    assert path.read_bytes().startswith(b"\x89PNG")
    save_figure_atomic(fig, tmp_path / "curve.pdf")
    assert (tmp_path / "curve.pdf").read_bytes().startswith(b"%PDF")
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    (tmp_path / "linked.png").symlink_to(target)
    with pytest.raises(SymlinkRefusedError, match="linked.png"):
        save_figure_atomic(fig, tmp_path / "linked.png")
    plt.close(fig)
    assert target.read_text() == "keep me"
