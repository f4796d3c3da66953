"""What durability costs: committing bought episodes to a run's store, per episode.

Every slice of rewarded episodes is committed (SQLite, WAL, ``synchronous=FULL``: fsynced, one
SHA-256 per episode) before the next is measured. This script times, for episodes shaped like
the chain walk's and the batting arm's (N = 10 steps, T trials side by side):

* ``commit 1``: one slice of one episode index (``rewarded_slice="episode"``, a robot);
* ``commit M``: one slice of M episode indices (``rewarded_slice="all"``, a simulator), per
  episode index;
* ``read``: reading back and verifying the whole run, per episode index;

and a whole chain-walk run (``tests``-sized: T = 3, schedule 3, 2, 2) with and without a store.

The cost per commit of the store's journal, before and after the committed rows moved out of
the write-ahead log (issue 45): one slice of one episode committed with ``journal_mode=WAL``,
``synchronous=FULL`` (before) and with the rollback journal, ``synchronous=EXTRA`` (after),
each as a ratio to a floor measured in the same run: the episode's bytes written to a new
file and fsynced (what any durable write of them costs on this disk).

Medians over ``--repeats``; the table ends with the machine's load (``os.getloadavg``); the
JSON (``--out``) and CSV (``--csv``) record the machine.

    python benchmarks/bench_durability.py --out durability.json --csv durability.csv
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv  # noqa: E402
from torch_api.core.basis import GaussianActionBasis  # noqa: E402
from torch_api.loop.durable import DurableRun  # noqa: E402
from torch_api.loop.iteration import ActivePolicyIteration  # noqa: E402
from torch_api.loop.spec import RunSpec  # noqa: E402
from torch_api.runs.codec import encode_tensordict  # noqa: E402
from torch_api.runs.store import RunStore  # noqa: E402

STEPS = 10  # N


def episode(trials: int, obs_dim: int) -> TensorDict:
    """One episode index ``[T, N]`` in the library's format (random numbers)."""
    shape = (trials, STEPS)
    return TensorDict(
        {
            "observation": torch.randn(*shape, obs_dim),
            "action": torch.randint(2, shape),
            "sample_probs": torch.full((*shape, 2), 0.5, dtype=torch.float64),
            ("next", "observation"): torch.randn(*shape, obs_dim),
            ("next", "terminated"): torch.zeros(shape, dtype=torch.bool),
            ("next", "reward"): torch.randn(*shape, 1),
            "mask": torch.ones(shape, dtype=torch.bool),
            "iteration": torch.ones(shape, dtype=torch.long),
            "policy_id": torch.zeros(shape, dtype=torch.long),
        },
        batch_size=shape,
    )


def time_store(trials: int, obs_dim: int, slice_size: int, repeats: int) -> dict:
    """Median seconds per episode index: commit in slices of ``slice_size``, then read."""
    commits, reads = [], []
    for r in range(repeats):
        with tempfile.TemporaryDirectory() as folder:
            store = RunStore(Path(folder) / "run.db", config={"bench": r})
            data = episode(trials, obs_dim)
            for it in range(1, 6):
                started = time.perf_counter()
                store.put_episodes(it, {m: data for m in range(slice_size)})
                commits.append((time.perf_counter() - started) / slice_size)
            store.close()
            started = time.perf_counter()
            RunStore.read(Path(folder) / "run.db")
            reads.append((time.perf_counter() - started) / (5 * slice_size))
    return {"commit": statistics.median(commits), "read": statistics.median(reads)}


def _fsync_floor(folder: Path, blob: bytes) -> float:
    """Seconds to write ``blob`` to a new file and fsync it: the floor of a durable write."""
    started = time.perf_counter()
    fd = os.open(folder / "floor.bin", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, blob)
        os.fsync(fd)
    finally:
        os.close(fd)
    return time.perf_counter() - started


def time_journals(trials: int, obs_dim: int, repeats: int) -> dict:
    """Median seconds of one commit of one episode index with the journal before (WAL,
    ``synchronous=FULL``) and after (rollback journal, ``synchronous=EXTRA``), and of the
    floor, interleaved so that the three see the same disk and load."""
    data = episode(trials, obs_dim)
    blob = encode_tensordict(data)
    times: dict[str, list[float]] = {"floor": [], "before": [], "after": []}
    for r in range(repeats):
        for name in ("before", "after"):
            with tempfile.TemporaryDirectory() as folder:
                store = RunStore(Path(folder) / "run.db", config={"bench": r})
                if name == "before":  # the store's settings before the change
                    store._db.execute("PRAGMA journal_mode=WAL")
                    store._db.execute("PRAGMA synchronous=FULL")
                for it in range(1, 11):
                    times["floor"].append(_fsync_floor(Path(folder), blob))
                    started = time.perf_counter()
                    store.put_episodes(it, {0: data})
                    times[name].append(time.perf_counter() - started)
                store.close()
    return {k: statistics.median(v) for k, v in times.items()}


def machine() -> dict:
    """Where the numbers were measured."""
    return {
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "load": os.getloadavg()[0],
        "tmp": tempfile.gettempdir(),
    }


def chain_walk_run(path: Path | None) -> float:
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    started = time.perf_counter()
    spec = RunSpec.of(
        schedule=(3, 2, 2),
        num_steps=STEPS,
        gamma=GAMMA,
        num_repeats=2,
        psi_mode="grouped",
        num_trials=3,
        seed=7,
    )
    ActivePolicyIteration(
        spec,
        env=lambda e: ChainWalkEnv(batch_size=e),
        basis=basis,
        durable=DurableRun(path),
    ).run()
    return time.perf_counter() - started


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="repeats behind each median")
    parser.add_argument("--out", default="", help="also write the numbers to this JSON file")
    parser.add_argument("--csv", default="", help="also write the journal rows to this CSV")
    parser.add_argument("--skip-run", action="store_true", help="leave out the whole run")
    args = parser.parse_args(argv)
    results: dict = {"rows": {}}
    torch.set_num_threads(1)
    print(
        f"{'episodes like':<28} {'commit 1 (ms)':>14} {'commit M (ms/ep)':>17} {'read (ms/ep)':>13}"
    )
    for name, trials, obs_dim, many in (
        ("chain walk, T = 1", 1, 1, 5),
        ("chain walk, T = 1000", 1000, 1, 5),
        ("batting arm, T = 1", 1, 4, 10),
        ("batting arm, T = 500", 500, 4, 10),
    ):
        one = time_store(trials, obs_dim, 1, args.repeats)
        batch = time_store(trials, obs_dim, many, args.repeats)
        results["rows"][name] = {"commit_1": one["commit"], "commit_m": batch["commit"]}
        results["rows"][name] |= {"read": batch["read"], "m": many}
        print(
            f"{name:<28} {1e3 * one['commit']:>14.2f} {1e3 * batch['commit']:>17.2f} "
            f"{1e3 * batch['read']:>13.3f}"
        )
    print(
        f"\n{'one commit of one episode':<28} {'floor (ms)':>11} {'before (ms)':>12} "
        f"{'after (ms)':>11} {'before/floor':>13} {'after/floor':>12}"
    )
    journal_rows = []
    for name, trials, obs_dim in (("chain walk, T = 1", 1, 1), ("batting arm, T = 500", 500, 4)):
        t = time_journals(trials, obs_dim, args.repeats)
        row = {"episodes like": name, "floor_s": t["floor"], "before_s": t["before"]}
        row |= {"after_s": t["after"], "before_ratio": t["before"] / t["floor"]}
        row |= {"after_ratio": t["after"] / t["floor"]}
        journal_rows.append(row)
        print(
            f"{name:<28} {1e3 * t['floor']:>11.2f} {1e3 * t['before']:>12.2f} "
            f"{1e3 * t['after']:>11.2f} {row['before_ratio']:>13.1f} {row['after_ratio']:>12.1f}"
        )
    results["journal"] = journal_rows
    if not args.skip_run:
        run_times(args, results)
    load = os.getloadavg()[0]
    print(f"load average {load:.2f} on {os.cpu_count()} CPUs")
    results |= {"load": load, "machine": machine()}
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1))
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=[*journal_rows[0], *machine()])
            writer.writeheader()
            for row in journal_rows:
                writer.writerow(row | results["machine"])


def run_times(args, results: dict) -> None:
    """A whole chain-walk run without and with a store."""
    plain, durable = [], []
    for _ in range(args.repeats):
        plain.append(chain_walk_run(None))
        with tempfile.TemporaryDirectory() as folder:
            durable.append(chain_walk_run(Path(folder) / "run.db"))
    p, d = statistics.median(plain), statistics.median(durable)
    print(
        f"\nchain-walk run (T = 3, schedule 3, 2, 2, 7 rewarded episode indices): "
        f"{p:.3f} s without a store, {d:.3f} s with ({1e3 * (d - p) / 7:.1f} ms per episode index)"
    )
    results |= {"run_plain_s": p, "run_durable_s": d}


if __name__ == "__main__":
    main()
