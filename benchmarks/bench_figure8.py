"""Figure 8's cost against the number of trials, next to its floors.

For each T it runs ``examples/chain_walk_api.py --trials T`` (both schedules, AL and PL, the
paper's sizes otherwise) in a fresh process and reports:

- ``wall``: the whole command, start-up included; ``compute``: the experiment's own time (the
  ``wall_seconds`` of its JSON); ``peak RSS`` of its largest process; for each ``--backend``
  (``processes``, the CLI's default: a forked worker per core; ``local``: one process);
- ``start-up``: the CLI up to its parsed arguments, ``--help`` (its imports), then exit;
- the floors of the same work in this process: ``rng`` — drawing the run's count of 32-bit
  words from :class:`counter_rng.CounterStreams` in calls of the run's mean draw size (the
  count comes from an instrumented in-process run of a few trials: every draw is per trial);
  ``algebra`` — the J criterion of every AL iteration and the fit of every iteration, both
  schedules, on episodes drawn beforehand (the arithmetic alone: no rollout, no Python loop
  over steps), in one process on ``--threads`` threads.

Run::

    python benchmarks/bench_figure8.py                     # T = 100, 1000, 10000 (minutes)
    python benchmarks/bench_figure8.py --trials 20 100     # a quick look
    python benchmarks/bench_figure8.py --threads 2         # the CLI's and the floors' threads
    python benchmarks/bench_figure8.py --backend local     # one process only
    python benchmarks/bench_figure8.py --trials 1000 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _timing import machine_info

ROOT = Path(__file__).resolve().parents[1]
CLI = ROOT / "examples" / "chain_walk_api.py"
SCHEDULES = {"decreasing": (5, 5, 3, 3, 3, 1, 1), "fixed": (3,) * 7}
Z, K, N = 5, 4, 10  # repeats, candidates, steps (section 4.2)


def run_cli(trials: int, threads: int, out: Path, backend: str, chunk_trials: int) -> dict:
    """Wall time, the experiment's own time and the peak RSS (of its largest process) of one
    run of the CLI, its trials in chunks of at most ``chunk_trials``."""
    command = [sys.executable, str(CLI), "--trials", str(trials), "--threads", str(threads)]
    command += ["--out-dir", str(out), "--overwrite", "--backend", backend]
    command += ["--chunks", str(-(-trials // chunk_trials))]
    wrapper = (
        "import resource, subprocess, sys, time\n"
        "t = time.perf_counter()\n"
        "code = subprocess.run(sys.argv[1:], capture_output=True).returncode\n"
        "wall = time.perf_counter() - t\n"
        "rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"
        "print(code, wall, rss)\n"
    )
    done = subprocess.run([sys.executable, "-c", wrapper, *command], capture_output=True, text=True)
    code, wall, rss = done.stdout.split()
    if int(code):
        raise RuntimeError(f"{' '.join(command)} failed with exit status {code}")
    payload = json.loads((out / "chain_walk_api.json").read_text())
    return {"wall_s": float(wall), "compute_s": payload["wall_seconds"], "rss_mb": int(rss) / 1024}


def startup_seconds(repeats: int = 3) -> float:
    """Median time of the CLI started with ``--help``: its imports and its parsed arguments,
    then exit (what every run pays before its work)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, str(CLI), "--help"], check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def count_draws(trials: int) -> tuple[int, int]:
    """32-bit words and draw calls of a whole run of ``trials`` trials (instrumented, in
    process, quiet)."""
    from counter_rng import streams as counter_streams

    sys.path.insert(0, str(CLI.parent))
    import chain_walk_api

    words = calls = 0
    original = counter_streams.CounterStreams._words

    def counting(self, shape, device):
        nonlocal words, calls
        out = original(self, shape, device)
        words, calls = words + out.numel(), calls + 1
        return out

    counter_streams.CounterStreams._words = counting
    try:
        with tempfile.TemporaryDirectory() as out:
            chain_walk_api.main(["--trials", str(trials), "--out-dir", out, "--backend", "local"])
    finally:
        counter_streams.CounterStreams._words = original
    return words, calls


def rng_floor(words: int, calls: int) -> float:
    """Seconds to draw ``words`` 32-bit words in ``calls`` calls of equal size."""
    from counter_rng import CounterStreams

    streams = CounterStreams(1)
    size = max(1, words // calls)
    start = time.perf_counter()
    for _ in range(calls):
        streams._words((size,), None)
    return time.perf_counter() - start


def algebra_floor(trials: int) -> float:
    """Seconds of the J criterion (AL) and the fits (AL and PL) of both schedules on episodes
    drawn beforehand, at the paper's sizes."""
    from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
    from torch_api.collection.collect import collect_episodes
    from torch_api.core.basis import GaussianActionBasis
    from torch_api.core.criterion import j_values
    from torch_api.core.fit import fit_theta
    from torch_api.core.psi import PsiHat
    from torch_api.policies import LinearQPolicy

    basis = GaussianActionBasis(centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2)
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="grouped")
    theta = torch.linspace(-1, 1, 12, dtype=torch.float64).expand(trials, 12).contiguous()
    policy = LinearQPolicy(basis=basis, theta=theta, epsilon=0.3)

    def draw(rows: int, rewarded: bool):
        env = ChainWalkEnv(batch_size=trials * rows, seed=rows)
        return collect_episodes(env, policy, num_episodes=rows, num_steps=N, rewarded=rewarded)

    total = 0.0
    for schedule in SCHEDULES.values():
        for l, m in enumerate(schedule):
            bought = sum(schedule[: l + 1])
            rewarded = draw(bought, True)
            free = draw(Z * K * m, False).reshape(trials, Z, K, m, N)
            earlier = None if l == 0 else draw(sum(schedule[:l]), False)
            start = time.perf_counter()
            for _ in ("AL", "PL"):
                fit_theta("brm", rewarded, policy, psi, basis, 1e-3)
            j_values(free, earlier, policy, psi, 1e-3)
            total += time.perf_counter() - start
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, nargs="+", default=[100, 1000, 10000])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--backend",
        nargs="+",
        default=["processes", "local"],
        help="the CLI's --backend, each measured (processes: its default, a worker per core)",
    )
    parser.add_argument(
        "--chunk-trials", type=int, default=2500, help="trials per chunk (bounds the memory)"
    )
    parser.add_argument("--startup-repeats", type=int, default=3)
    parser.add_argument(
        "--quick", action="store_true", help="a smoke run: the start-up measured once"
    )
    parser.add_argument(
        "--repeats", type=int, default=1, help="runs of each configuration (medians shown)"
    )
    parser.add_argument(
        "--count-trials", type=int, default=10, help="trials of the run whose draws are counted"
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the table as JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(machine_info())
    startup_repeats = 1 if args.quick else args.startup_repeats
    startup = startup_seconds(startup_repeats)
    print(
        f"start-up (the CLI's imports and arguments, --help, then exit): {startup:.2f} s "
        f"(median of {startup_repeats})"
    )
    words, calls = count_draws(args.count_trials)
    rows = []
    print(
        "| trials | backend | wall s | compute s | start-up s | rng floor s | algebra floor s "
        "| peak RSS MB |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    for trials in args.trials:
        runs = {backend: [] for backend in args.backend}
        for _ in range(args.repeats):  # the backends side by side, in turn
            for backend in args.backend:
                with tempfile.TemporaryDirectory() as out:
                    runs[backend].append(
                        run_cli(trials, args.threads, Path(out), backend, args.chunk_trials)
                    )
        floors = {  # after the CLI's runs: what the floors hold does not shrink their memory check
            "rng_floor_s": rng_floor(words * trials // args.count_trials, calls),
            "algebra_floor_s": algebra_floor(trials),
        }
        for backend, done in runs.items():
            run = {key: statistics.median(r[key] for r in done) for key in done[0]}
            row = {"trials": trials, "backend": backend, **run}
            row.update(startup_s=startup, repeats=args.repeats, **floors)
            rows.append(row)
            print(
                f"| {trials:,} | {backend} | {row['wall_s']:.1f} | {row['compute_s']:.1f} | "
                f"{startup:.1f} | {row['rng_floor_s']:.2f} | {row['algebra_floor_s']:.2f} | "
                f"{row['rss_mb']:.0f} |"
            )
    for backend in args.backend:
        mine = [r for r in rows if r["backend"] == backend]
        if len(mine) > 1:
            first, last = mine[0], mine[-1]
            print(
                f"{backend}: wall ratio T={last['trials']} / T={first['trials']}: "
                f"{last['wall_s'] / first['wall_s']:.2f}"
            )
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"machine": machine_info(), "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
