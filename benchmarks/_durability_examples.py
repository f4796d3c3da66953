"""The durability attacks on the examples, as processes (``benchmarks/durability_attacks.py``):
SIGKILL, SIGINT/SIGTERM and damaged stores of a running ``examples/chain_walk_api.py``."""

from __future__ import annotations

import os
import random
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from _durability_store import REFUSALS, Tally  # noqa: E402

# -- the examples, as processes --------------------------------------------------------------

EXAMPLE = ["--trials", "2", "--schedule", "decreasing", "--iterations", "4", "--repeats", "1"]
EXAMPLE += ["--test-episodes", "2", "--test-steps", "5", "--backend", "local", "--threads", "1"]
SCHEDULE = (5, 5, 3, 3)  # the decreasing schedule's first 4 iterations
TOTAL = 2 * sum(SCHEDULE)  # rewarded episode rows of AL and PL

DRIVER = """
import sys
sys.path[:0] = [{root!r}, {examples!r}]
import torch_api.loop.iteration as iteration
log, real = open({log!r}, "a", buffering=1), iteration.rollouts_or
def counting(collector):
    collect = real(collector)
    def counted(*args, **kwargs):
        episodes = collect(*args, **kwargs)
        log.write(f"{{kwargs['num_episodes']}}\\n")  # bought (committed next, or not)
        return episodes
    return counted
iteration.rollouts_or = counting
import chain_walk_api
chain_walk_api.main(sys.argv[1:])
"""


def start(out: Path, log: Path, *extra: str) -> subprocess.Popen:
    """``examples/chain_walk_api.py`` on :data:`EXAMPLE` into ``out``, every rewarded
    collection it makes counted in ``log`` (the rows bought, one line per collection)."""
    code = DRIVER.format(root=str(ROOT), examples=str(ROOT / "examples"), log=str(log))
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    return subprocess.Popen(
        [sys.executable, "-c", code, *EXAMPLE, "--out-dir", str(out), *extra],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def bought(log: Path) -> int:
    return sum(map(int, log.read_text().split())) if log.exists() else 0


def committed(checkpoints: Path, scratch: Path) -> int:
    """The rewarded episode rows committed in the stores of ``checkpoints``: counted on a copy,
    where SQLite rolls back a commit in flight (its hot journal) as the next writer would."""
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    rows = 0
    for db in sorted(checkpoints.glob("*.db")) if checkpoints.is_dir() else ():
        for f in (db, Path(f"{db}-journal")):
            if f.exists():
                shutil.copy(f, scratch / f.name)
        copy = sqlite3.connect(scratch / db.name)
        try:
            names = {r[0] for r in copy.execute("SELECT name FROM sqlite_master")}
            if "episode" in names:
                rows += copy.execute("SELECT count(*) FROM episode").fetchone()[0]
        finally:
            copy.close()
    return rows


def _csv(out: Path) -> str | None:
    path = out / "chain_walk_api.csv"
    return path.read_text() if path.is_file() else None


def _last_line(err: str, folder: Path) -> str:
    lines = err.strip().splitlines()
    return (lines[-1] if lines else "").replace(str(folder), "OUT")


def damage_a_store(checkpoints: Path, rng: random.Random) -> str:
    """One file of the stores of a killed example damaged: removed, cut or a bit flipped."""
    files = sorted(
        f
        for f in checkpoints.glob("*.db*")
        if f.is_file() and not f.name.endswith((".lock", ".new"))
    ) if checkpoints.is_dir() else []  # fmt: skip
    if not files:
        return "no store to damage"
    target = rng.choice(files)
    data = target.read_bytes()
    kind = rng.choice(["removed", "cut", "bit flip", "bit flip"] if data else ["removed"])
    if kind == "removed":
        target.unlink()
    elif kind == "cut":
        target.write_bytes(data[: rng.randrange(len(data))])
    else:
        flipped = bytearray(data)
        flipped[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        target.write_bytes(bytes(flipped))
    part = "journal" if target.name.endswith("-journal") else "database"
    part = "counter" if target.name.endswith(".commits") else part
    return f"its {part} {kind}"


def example(folder: Path, kind: str, tries: int, rng: random.Random, reference) -> Tally:
    """``kind``: kill, signal or damage (a kill, then one file of a store damaged)."""
    csv, duration = reference
    tally = Tally()
    for i in range(tries):
        out, logs = folder / f"run{i}", (folder / f"bought{i}.first", folder / f"bought{i}.again")
        signum = signal.SIGKILL if kind != "signal" else (signal.SIGINT, signal.SIGTERM)[i % 2]
        proc = start(out, logs[0])
        first = out / "checkpoints" / "decreasing_AL.db"
        while proc.poll() is None and not (out / "checkpoints").is_dir():
            time.sleep(0.005)  # (made with the signal handlers in place)
        if i % 4 == 0:
            when = "as its first store appears"
            while proc.poll() is None and not first.exists():
                time.sleep(0.001)
        else:  # (before its last result is written, as the reference run wrote it)
            when = "at a random moment"
            time.sleep(rng.random() * duration)
        late = proc.poll() is not None
        if not late:
            os.killpg(proc.pid, signum)
        _, err = proc.communicate()
        code, line = proc.returncode, _last_line(err, out)
        written = (out / "fig8_performance.png").is_file() and _csv(out) == csv
        kept = committed(out / "checkpoints", folder / "scratch")
        damaged = damage_a_store(out / "checkpoints", rng) if kind == "damage" else ""
        again = start(out, logs[1], "--resume")
        _, err_again = again.communicate()
        name = signal.Signals(signum).name
        if late:
            first_part = "it ended before the signal"
        elif written:  # the experiment's work was done: the signal came as the process ended
            first_part = f"exit {code} after its results were written"
        elif kind == "signal":
            one = line.startswith("interrupted at iteration ") and "Traceback" not in err
            first_part = f"exit {code}, {'its one line' if one else 'NOT its one line: ' + line}"
        else:
            first_part = f"exit {code}"
        same = _csv(out) == csv
        if again.returncode == 0:
            twice = kept + bought(logs[1]) - TOTAL  # committed rows lost, or bought again
            result = "the uninterrupted numbers" if same else "OTHER NUMBERS"
            second = f"--resume: exit 0, {result}"
        else:
            twice = bought(logs[1])  # refused: its files left as they were, nothing bought
            said = _last_line(err_again, out)
            if said.startswith("error: ") and "Traceback" not in err_again:
                what = next((w for k, w in REFUSALS if k in said), said[7:60])
                second = f"--resume: exit {again.returncode}, refused in one line ({what})"
            else:
                second = f"--resume: exit {again.returncode} {said[:100]}"
        silent = again.returncode == 0 and not same
        parts = [f"{name} {when}: {first_part}", damaged, second]
        tally.add(", ".join(p for p in parts if p), lost_or_twice=twice, silent=silent)
        shutil.rmtree(out)
    return tally


def reference_run(folder: Path) -> tuple[str, float]:
    """An uninterrupted run: its CSV and the seconds from its checkpoints folder to its last
    result written (the median of 3 runs: the first one starts cold)."""
    seconds = []
    for i in range(3):
        out, log = folder / f"reference{i}", folder / f"reference{i}.bought"
        proc = start(out, log)
        while proc.poll() is None and not (out / "checkpoints").is_dir():
            time.sleep(0.005)
        started = time.perf_counter()
        while proc.poll() is None and not (out / "fig8_performance.png").is_file():
            time.sleep(0.005)
        seconds.append(time.perf_counter() - started)
        _, err = proc.communicate()
        if proc.returncode != 0 or bought(log) != TOTAL:
            raise RuntimeError(f"the reference run failed (bought {bought(log)}):\n{err[-3000:]}")
    return (out / "chain_walk_api.csv").read_text(), sorted(seconds)[1]
