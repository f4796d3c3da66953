"""The durability attacks on a store, in forked processes (``benchmarks/durability_attacks.py``):
stops during its creation, damaged files of a killed writer, signals inside commits."""

from __future__ import annotations

import collections
import os
import random
import resource
import shutil
import signal
import sqlite3
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from torch_api.experiment.folder import Interrupted, raise_on_signals  # noqa: E402
from torch_api.runs import store_files  # noqa: E402
from torch_api.runs.store import RunStore, StoreError  # noqa: E402

CONFIG = {"N": 1}
COMMITS = 5  # the slices a damaged store's writer committed

CREATED = 10  # a child's exit status: the creation ended before the statement to stop at


class Tally:
    """The outcomes of one attack, with the committed rewards lost or bought twice and the
    silent damages among them."""

    def __init__(self) -> None:
        self.outcomes: collections.Counter = collections.Counter()
        self.tries = self.lost_or_twice = self.silent = 0

    def add(self, outcome: str, lost_or_twice: int = 0, silent: bool = False) -> None:
        self.tries += 1
        self.outcomes[outcome] += 1
        self.lost_or_twice += abs(lost_or_twice)
        self.silent += bool(silent)

    def as_dict(self) -> dict:
        return {
            "tries": self.tries,
            "committed_rewards_lost_or_bought_twice": self.lost_or_twice,
            "silent_damages": self.silent,
            "outcomes": dict(sorted(self.outcomes.items())),
        }


# -- the store, in forked processes ----------------------------------------------------------


def in_child(body) -> int:
    """``body()`` in a forked process; its exit status (negative: the signal that ended it;
    128 + the signal: the examples' interrupt; 1: a store error; 3: another error)."""
    pid = os.fork()
    if pid == 0:  # the child: never returns into the caller
        code = 0
        try:
            body()
        except Interrupted as interrupt:
            code = 128 + interrupt.signum
        except StoreError:
            code = 1
        except BaseException:  # noqa: BLE001
            code = 3
        os._exit(code)
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def stop_at_statement(path: Path, k: int, signum: int):
    """A child's body: create a store at ``path``, sending itself ``signum`` as SQLite starts
    its k-th statement, taken as that statement returns (SIGTERM: the examples' interrupt);
    exits :data:`CREATED` if the creation has fewer statements."""

    def body() -> None:
        real, seen, mask = sqlite3.connect, [0], []

        class Connection(sqlite3.Connection):
            def execute(self, *args):
                try:
                    return super().execute(*args)
                finally:  # the signal sent while SQLite ran, taken as it returns (if unmasked)
                    if mask:
                        signal.pthread_sigmask(signal.SIG_SETMASK, mask.pop())

        def connect(*args, **kwargs):
            db = real(*args, factory=Connection, **kwargs)

            def trace(sql):
                seen[0] += 1
                if seen[0] == k:  # (a handler run here, in the callback, would be swallowed)
                    mask.append(signal.pthread_sigmask(signal.SIG_BLOCK, {signum}))
                    os.kill(os.getpid(), signum)

            db.set_trace_callback(trace)
            return db

        sqlite3.connect = connect
        with raise_on_signals():
            RunStore(path, config=CONFIG).close()
        if seen[0] < k:
            os._exit(CREATED)

    return body


def kill_at_file_step(path: Path, k: int):
    """A child's body: create a store at ``path``, SIGKILLed before the k-th call into ``os``
    of :mod:`torch_api.runs.store_files` (open, write, fsync, rename, ...); exits :data:`CREATED`
    if the creation has fewer."""

    class Steps:
        def __init__(self) -> None:
            self.seen = 0

        def __getattr__(self, name):
            attr = getattr(os, name)
            if not callable(attr):
                return attr

            def step(*args, **kwargs):
                self.seen += 1
                if self.seen == k:
                    os.kill(os.getpid(), signal.SIGKILL)
                return attr(*args, **kwargs)

            return step

    def body() -> None:
        steps = store_files.os = Steps()
        RunStore(path, config=CONFIG).close()
        if steps.seen < k:
            os._exit(CREATED)

    return body


def episodes(m: int) -> dict:
    return {m: TensorDict({"reward": torch.full((2, 5), float(m))}, batch_size=[2, 5])}


def killed_writer(path: Path, inside: bool) -> Path:
    """A store at ``path`` whose writer committed :data:`COMMITS` slices (episode m of
    iteration 1, rewards m) and was SIGKILLed: between commits, or ``inside`` a 6th slice of
    40 large episodes once 30 were written (its pages spilled into the database, its journal
    hot). Its files 2 commits before the end are copied to ``<folder>/older/``."""

    def body() -> None:
        store = RunStore(path, config=CONFIG)
        for m in range(COMMITS):
            store.put_episodes(1, episodes(m))
            if m == COMMITS - 3:
                (path.parent / "older").mkdir()
                for name in (path.name, f"{path.name}.commits"):
                    shutil.copy(path.parent / name, path.parent / "older" / name)
        if not inside:
            os.kill(os.getpid(), signal.SIGKILL)
        real, seen = RunStore._put, [0]

        def put(db, table, key, value, free=None):
            real(db, table, key, value, free)
            seen[0] += table == "episode"
            if seen[0] == 30:
                os.kill(os.getpid(), signal.SIGKILL)

        RunStore._put = staticmethod(put)
        big = TensorDict({"reward": torch.randn(64, 1024)}, batch_size=[64, 1024])
        store.put_episodes(2, dict.fromkeys(range(40), big))

    if in_child(body) != -signal.SIGKILL:
        raise RuntimeError(f"the writer of {path} was not killed")
    if inside and not Path(f"{path}-journal").stat().st_size:
        raise RuntimeError(f"the writer of {path} left no hot journal")
    return path


def _whole(stored) -> bool:
    """Whether a run read back holds exactly the committed slices, value for value."""
    if set(stored.episodes) - {1} or set(stored.episodes.get(1, {})) != set(range(COMMITS)):
        return False
    return all(
        torch.equal(stored.episodes[1][m]["reward"], torch.full((2, 5), float(m)))
        for m in range(COMMITS)
    )


REFUSALS = [  # (words of a store's refusal, what it says in short)
    ("left inside a commit", "left inside a commit"),
    ("lost committed rows", "lost committed rows"),
    ("lost its commit counter", "lost its counter"),
    ("is damaged", "its counter damaged"),
    ("does not match its counter", "does not match its counter"),
    ("checksum mismatch", "a checksum mismatch"),
    ("cannot read the run", "cannot be read"),
    ("not a run database", "not a run database"),
    ("no run is stored", "no run stored"),
]


def _refusal(error: BaseException, path: Path) -> str:
    """A store's refusal, by what it says."""
    said = str(error)
    fallback = said.replace(str(path), "PATH")[:80]
    what = next((what for words, what in REFUSALS if words in said), fallback)
    named = str(path) in said and ("commits" in said or "resume it" in said)
    return f"refused ({what}{'' if named else ', NOT naming the run and its commits'})"


def damaged_outcome(path: Path) -> tuple[str, bool]:
    """(what a reader, then a writer with ``resume=True``, made of the store at ``path``;
    whether either took a damaged run as whole)."""
    said, silent = [], False
    for who in ("read", "resume"):
        try:
            if who == "read":
                stored = RunStore.read(path)
            else:
                with RunStore(path, config=CONFIG, resume=True) as store:
                    stored = store.stored
        except StoreError as error:
            said.append(f"{who}: {_refusal(error, path)}")
            continue
        except Exception as error:  # noqa: BLE001
            said.append(f"{who}: UNEXPECTED {type(error).__name__}")
            continue
        if stored is not None and _whole(stored):
            said.append(f"{who}: every committed slice back")
        else:
            silent = True
            got = 0 if stored is None else stored.num_episodes
            said.append(f"{who}: SILENTLY {got} episode rows, not the {COMMITS} committed")
    return "; ".join(said), silent


def damage(folder: Path, tries: int, rng: random.Random) -> Tally:
    sources = {
        "killed between commits": killed_writer(folder / "between" / "run.db", inside=False),
        "killed inside a commit": killed_writer(folder / "inside" / "run.db", inside=True),
    }
    tally = Tally()
    for i in range(tries):
        state = list(sources)[i % 2]
        source = sources[state]
        names = sorted(
            f.name for f in source.parent.iterdir() if f.is_file() and not f.name.endswith(".lock")
        )
        name = rng.choice(names)
        data = (source.parent / name).read_bytes()
        older = source.parent / "older" / name
        kinds = ["removed", "cut", "bit flip", "bit flip"] + (["older copy"] * older.exists())
        kind = rng.choice(kinds)
        copy = folder / f"try{i}"
        copy.mkdir()
        for f in names:
            shutil.copy(source.parent / f, copy / f)
        target = copy / name
        if kind == "removed":
            target.unlink()
        elif kind == "cut":
            target.write_bytes(data[: rng.randrange(len(data))])
        elif kind == "bit flip":
            flipped = bytearray(data)
            flipped[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            target.write_bytes(bytes(flipped))
        else:
            shutil.copy(older, target)
        outcome, silent = damaged_outcome(copy / source.name)
        part = name.replace(source.name, "database")
        tally.add(f"{state}, {part} {kind}: {outcome}", silent=silent)
        shutil.rmtree(copy)
    return tally


def resumes(path: Path) -> str:
    try:
        with RunStore(path, config=CONFIG, resume=True):
            return "resumed"
    except StoreError as error:
        return f"refused: {error}".replace(str(path), "PATH")[:120]


def creation(folder: Path) -> Tally:
    tally = Tally()
    for signum in (signal.SIGKILL, signal.SIGTERM):
        for k in range(1, 100):
            path = folder / f"{signum}-{k}" / "run.db"
            if in_child(stop_at_statement(path, k, signum)) == CREATED:
                break
            outcome = resumes(path)
            name = signal.Signals(signum).name
            tally.add(f"{name} at statement k: {outcome}", silent=outcome != "resumed")
    for k in range(1, 100):
        path = folder / f"step-{k}" / "run.db"
        if in_child(kill_at_file_step(path, k)) == CREATED:
            break
        outcome = resumes(path)
        tally.add(f"SIGKILL at file step k: {outcome}", silent=outcome != "resumed")
    for limit in (0, 512, 4096, 8192, 12288, 16384, 32768):
        path = folder / f"fsize-{limit}" / "run.db"

        def body(limit=limit, path=path):
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
            RunStore(path, config=CONFIG).close()

        code = in_child(body)
        outcome = resumes(path)
        tally.add(f"ulimit -f ({'write failed' if code else 'fits'}): {outcome}")
    return tally


def signal_inside_a_commit(path: Path) -> int:
    """A child (with a thread that blocks no signal) SIGTERMs itself while its commit of a
    record is open; its exit status (143: interrupted)."""

    def body() -> None:
        threading.Thread(target=time.sleep, args=(30,), daemon=True).start()
        store = RunStore(path, config=CONFIG)
        real = RunStore._put

        def put(db, table, key, value, free=None):
            real(db, table, key, value, free)
            if table == "record":
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)  # the signal is taken while the transaction is open

        RunStore._put = staticmethod(put)
        with raise_on_signals():
            store.put_record(1, {"iteration": 1})
            time.sleep(5)  # (never reached: the interrupt comes right after the commit)

    return in_child(body)


def commit_signals(folder: Path, tries: int, rng: random.Random) -> Tally:
    tally = Tally()
    for i in range(tries):
        path, started = folder / f"direct{i}" / "run.db", folder / f"started{i}"
        signal_inside_a_commit(path)
        kept = RunStore.read(path).records == {1: {"iteration": 1}}
        outcome = f"inside the transaction: {'committed' if kept else 'ROLLED BACK'}"
        tally.add(outcome, lost_or_twice=0 if kept else 1)
        path = folder / f"random{i}" / "run.db"

        def loop(path=path, started=started):
            threading.Thread(target=time.sleep, args=(60,), daemon=True).start()
            store = RunStore(path, config=CONFIG)
            real, log = RunStore._put, open(started, "a", buffering=1)  # noqa: SIM115

            def put(db, table, key, value, free=None):  # inside the open transaction
                if table == "episode":
                    log.write(f"{key[1]}\n")
                real(db, table, key, value, free)

            RunStore._put = staticmethod(put)
            with raise_on_signals():
                for m in range(10_000):
                    store.put_episodes(1, episodes(m))

        pid = os.fork()
        if pid == 0:
            code = 0
            try:
                loop()
            except Interrupted:
                code = 143
            except BaseException:  # noqa: BLE001
                code = 3
            os._exit(code)
        time.sleep(0.3 + rng.random() * 0.5)
        os.kill(pid, signal.SIGTERM)
        code = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
        begun = len(started.read_text().split())
        stored = RunStore.read(path).num_episodes
        ok = code == 143 and stored == begun  # every transaction that reached its row stands
        outcome = f"at a random moment: {'every begun commit stands' if ok else 'LOST ONE'}"
        tally.add(outcome, lost_or_twice=begun - stored)
    return tally
