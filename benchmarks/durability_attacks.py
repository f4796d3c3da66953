"""The attacks on a run's store at its edges, counted: tries and outcomes (docs/durable_runs.md).

Every try is a real process (forked from this one, torch loaded as in a run) and real files:

* ``creation``: SIGKILL, or SIGTERM turned into the examples' interrupt, as SQLite starts each
  statement of a store's creation in turn; SIGKILL before each file-system step of it (open,
  write, fsync, rename); a file-size limit (``ulimit -f``) that makes a write of the creation
  fail; then ``resume=True`` must open the run (empty);
* ``wal``: a writer SIGKILLed after 6 commits (its rows in ``run.db-wal``); the log cut at a
  random length or one random bit flipped in it; then ``resume=True`` must give every committed
  row back or refuse saying rows were lost;
* ``signal``: SIGTERM while a commit is open, sent from inside the transaction and at random
  moments from outside into a writer committing in a loop (with a thread that blocks no
  signal, as ``import torch`` starts); every commit that began must stand;
* ``cli`` (``--cli N``): ``examples/chain_walk_api.py`` SIGTERMed the moment its first store
  appears, then ``--resume`` must finish (exit 0).

    python benchmarks/durability_attacks.py --tries 200 --cli 16
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import random
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "examples")]

import torch  # noqa: E402
from _durable import Interrupted, raise_on_signals  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from torch_api.runs import store_files  # noqa: E402
from torch_api.runs.store import CorruptRunError, RunStore, StoreError  # noqa: E402

CONFIG = {"N": 1}


CREATED = 10  # a child's exit status: the creation ended before the statement to stop at


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


def killed_writer(path: Path, commits: int) -> None:
    """A store at ``path`` whose writer put ``commits`` slices and was SIGKILLed: its rows in
    ``PATH-wal``."""

    def body() -> None:
        store = RunStore(path, config=CONFIG)
        for m in range(commits):
            store.put_episodes(1, episodes(m))
        os.kill(os.getpid(), signal.SIGKILL)

    if in_child(body) != -signal.SIGKILL:
        raise RuntimeError(f"the writer of {path} was not killed")


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


def resumes(path: Path) -> str:
    try:
        with RunStore(path, config=CONFIG, resume=True):
            return "resumed"
    except StoreError as error:
        return f"refused: {error}".replace(str(path), "PATH")[:120]


def creation(folder: Path) -> collections.Counter:
    outcomes = collections.Counter()
    for signum in (signal.SIGKILL, signal.SIGTERM):
        for k in range(1, 100):
            path = folder / f"{signum}-{k}" / "run.db"
            if in_child(stop_at_statement(path, k, signum)) == CREATED:
                break
            outcomes[f"{signal.Signals(signum).name} at statement k: {resumes(path)}"] += 1
    for k in range(1, 100):
        path = folder / f"step-{k}" / "run.db"
        if in_child(kill_at_file_step(path, k)) == CREATED:
            break
        outcomes[f"SIGKILL at file step k: {resumes(path)}"] += 1
    for limit in (0, 512, 4096, 8192, 12288, 16384, 32768):
        path = folder / f"fsize-{limit}" / "run.db"

        def body(limit=limit, path=path):
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
            RunStore(path, config=CONFIG).close()

        code = in_child(body)
        outcomes[f"ulimit -f ({'write failed' if code else 'fits'}): {resumes(path)}"] += 1
    return outcomes


def episodes(m: int) -> dict:
    return {m: TensorDict({"reward": torch.full((2, 5), float(m))}, batch_size=[2, 5])}


def wal(folder: Path, tries: int, rng: random.Random) -> collections.Counter:
    commits, path = 6, folder / "killed" / "run.db"
    killed_writer(path, commits)
    log = Path(f"{path}-wal").read_bytes()
    outcomes = collections.Counter()
    for i in range(tries):
        copy = folder / f"try{i}"
        copy.mkdir()
        for f in path.parent.iterdir():
            if not f.name.endswith(".lock"):
                shutil.copy(f, copy / f.name)
        damaged = bytearray(log)
        if i % 2:
            damaged = damaged[: rng.randrange(len(log))]
            kind = "cut"
        else:
            damaged[rng.randrange(len(log))] ^= 1 << rng.randrange(8)
            kind = "bit flip"
        Path(copy / "run.db-wal").write_bytes(bytes(damaged))
        try:
            with RunStore(copy / "run.db", config=CONFIG, resume=True) as store:
                got = 0 if store.stored is None else store.stored.num_episodes
            outcome = "every committed row back" if got == commits else f"SILENTLY {got} rows"
        except CorruptRunError as error:
            outcome = "refused, naming the lost rows" if "lost" in str(error) else str(error)
            outcome = outcome.replace(str(copy / "run.db"), "PATH")[:120]
        outcomes[f"{kind}: {outcome}"] += 1
        shutil.rmtree(copy)
    return outcomes


def signals(folder: Path, tries: int, rng: random.Random) -> collections.Counter:
    outcomes = collections.Counter()
    for i in range(tries):
        path, started = folder / f"direct{i}" / "run.db", folder / f"started{i}"
        signal_inside_a_commit(path)
        kept = RunStore.read(path).records == {1: {"iteration": 1}}
        outcomes[f"inside the transaction: {'committed' if kept else 'ROLLED BACK'}"] += 1
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
        outcomes[f"at a random moment: {'every begun commit stands' if ok else 'LOST ONE'}"] += 1
    return outcomes


def cli(folder: Path, tries: int) -> collections.Counter:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    args = ["--trials", "2", "--iterations", "2", "--steps", "5", "--repeats", "1", "--threads"]
    args += ["1", "--test-episodes", "2", "--test-steps", "5", "--schedule", "decreasing"]
    script = [sys.executable, str(ROOT / "examples" / "chain_walk_api.py"), *args]
    outcomes = collections.Counter()
    for i in range(tries):
        out = folder / f"cli{i}"
        proc = subprocess.Popen(
            [*script, "--out-dir", str(out)],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        store = out / "checkpoints" / "decreasing_AL.db"
        while proc.poll() is None and not store.exists():
            time.sleep(0.001)
        proc.send_signal(signal.SIGTERM)
        proc.communicate()
        again = subprocess.run(
            [*script, "--out-dir", str(out), "--resume"], env=env, capture_output=True, text=True
        )
        last = (again.stderr.strip().splitlines() or [""])[-1][:100] if again.returncode else ""
        last = last.replace(str(out), "OUT")
        outcomes[f"exit {proc.returncode}, then --resume: exit {again.returncode} {last}"] += 1
    return outcomes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tries", type=int, default=200, help="WAL damages (signal tries / 4)")
    parser.add_argument("--cli", type=int, default=0, help="CLI SIGTERMs at store creation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", default="", help="one attack: creation, wal, signal or cli")
    parser.add_argument("--out", default="", help="also write the outcomes as JSON here")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    torch.set_num_threads(1)
    table = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        attacks = {"creation": lambda d: creation(d)}
        attacks["wal"] = lambda d: wal(d, args.tries, rng)
        attacks["signal"] = lambda d: signals(d, max(args.tries // 4, 1), rng)
        if args.cli:
            attacks["cli"] = lambda d: cli(d, args.cli)
        for name, attack in attacks.items():
            if args.only and name != args.only:
                continue
            (folder / name).mkdir()
            started = time.perf_counter()
            outcomes = attack(folder / name)
            print(f"\n{name} ({time.perf_counter() - started:.0f} s)")
            for outcome, count in sorted(outcomes.items()):
                print(f"  {count:4d}  {outcome}")
            table[name] = dict(sorted(outcomes.items()))
    if args.out:
        Path(args.out).write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
