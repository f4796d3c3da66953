"""Speed of BattingEnv against raw mujoco.mj_step on the same models, in the same run.

For E = 1, 16, 256 parallel arms: episodes of a uniformly random policy through the TorchRL env
(noise, integration scheme, look-ahead, TensorDicts), counting the physics steps it spends
(coarse RK4 and fine Euler separately), and, side by side in the same repeat, the same numbers
of coarse and fine steps done by raw MuJoCo on the env's own two models:

* raw 1 thread: a plain Python loop of ``mujoco.mj_step`` on one MjData per model, in chunks
  as long as the env's (``n_coarse`` coarse steps, ``n_sub`` fine steps), reset between chunks;
* raw 2 threads (or ``--raw-threads``): ``mujoco.batch.Batch`` with 64 simulations on that many
  threads, each call stepping every simulation one chunk; its steps/s per model, measured on
  at least the env's step count, give the time of the env's mix of steps.

The env steps its simulations on ``min(E, cores)`` threads (the ``threads`` column). With
``--baseline FILE`` another version of the batting module as one file (a revision before
``envs/batting/`` became a package, e.g. ``git show 9ceec5b:envs/batting.py > old.py``) is
timed in the same repeats, interleaved, for a before/after table.
Several repeats, medians.

    python benchmarks/bench_batting_env.py --repeats 5
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from dataclasses import asdict, dataclass

import mujoco
import numpy as np
import torch
from _timing import write_result
from mujoco.batch import Batch

from envs.batting import MAX_STEPS, XML_PATH, BattingEnv


@dataclass
class Args:
    """Command-line arguments."""

    sizes: tuple[int, ...] = (1, 16, 256)  # batch sizes E
    repeats: int = 5  # timed repeats per size (medians reported)
    min_episodes: int = 256  # at least this many episodes per repeat
    seed: int = 0  # seed of the env noise and the random actions
    raw_threads: int = 2  # threads of the batched raw baseline
    baseline: str | None = None  # another envs/batting.py to time alongside (before/after)
    out: str = "results/bench_batting_env.json"  # where the JSON table goes


def load_baseline(path: str):
    """BattingEnv class of another version of envs/batting.py, on this checkout's MJCF file."""
    spec = importlib.util.spec_from_file_location("batting_baseline", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.BattingSimulator.__init__.__kwdefaults__["xml_path"] = XML_PATH
    return module.BattingEnv


def env_run(env, n_batches: int, gen: torch.Generator) -> tuple[float, int, int]:
    """Seconds, coarse and fine physics steps for ``n_batches`` batches of random episodes."""
    E = env.batch_size[0]
    coarse = fine = 0
    start = time.perf_counter()
    for _ in range(n_batches):
        td = env.reset()
        for _ in range(MAX_STEPS):
            td["action"] = torch.randint(0, 2, (E,), generator=gen)
            td = env.step(td)["next"]
        fine += int(env.sim.fine_steps.sum())
        coarse += int(env.sim.physics_steps.sum() - env.sim.fine_steps.sum())
    return time.perf_counter() - start, coarse, fine


def _models(env) -> tuple[tuple[mujoco.MjModel, int], tuple[mujoco.MjModel, int]]:
    """(coarse model, coarse chunk) and (fine model, fine chunk) of the env's simulator."""
    sim = env.sim
    fine_chunk = getattr(sim, "n_sub", sim.n_fine)  # older versions: whole fine control steps
    return (sim.coarse_model, sim.n_coarse), (sim.fine_model, fine_chunk)


def raw_run(env, coarse: int, fine: int) -> float:
    """Seconds for ``coarse`` + ``fine`` raw mj_step calls, one thread, in the env's chunks."""
    start = time.perf_counter()
    initial = env.sim._initial_state
    for (model, chunk), n in zip(_models(env), (coarse, fine), strict=True):
        data = mujoco.MjData(model)
        mujoco.mj_setState(model, data, initial, mujoco.mjtState.mjSTATE_INTEGRATION)
        data.ctrl[:] = (-50.0, 10.0)
        done = 0
        while done < n:
            k = min(chunk, n - done)
            for _ in range(k):
                mujoco.mj_step(model, data)
            done += k
            mujoco.mj_setState(model, data, initial, mujoco.mjtState.mjSTATE_INTEGRATION)
            data.ctrl[:] = (-50.0, 10.0)
    return time.perf_counter() - start


def raw_batch_run(env, coarse: int, fine: int, nthread: int) -> float:
    """Seconds the env's ``coarse`` + ``fine`` steps take in a 64-simulation Batch on
    ``nthread`` threads (each model timed on at least its count, in the env's chunks)."""
    total = 0.0
    initial = env.sim._initial_state
    for (model, chunk), n in zip(_models(env), (coarse, fine), strict=True):
        if n == 0:
            continue
        batch = Batch(model, nsim=64, nthread=nthread)
        done = 0
        start = time.perf_counter()
        while done < n:
            batch.state[:] = initial
            batch.ctrl = (-50.0, 10.0)
            batch.step(nstep=chunk)
            done += 64 * chunk
        total += (time.perf_counter() - start) * n / done
    return total


def main(args: Args) -> dict:
    rows = []
    print(
        f"{'version':<9}{'E':>5}{'thr':>4}{'steps/ep':>10}{'fine/ep':>9}{'env eps/s':>11}"
        f"{'raw1 eps/s':>12}{f'raw{args.raw_threads} eps/s':>12}{'env/raw1':>10}"
        f"{f'env/raw{args.raw_threads}':>10}" + (f"{'vs base':>10}" if args.baseline else "")
    )
    versions = {"current": BattingEnv}
    if args.baseline:
        versions = {"baseline": load_baseline(args.baseline), **versions}
    for E in args.sizes:
        envs = {name: cls(batch_size=E, seed=args.seed) for name, cls in versions.items()}
        gens = {name: torch.Generator().manual_seed(args.seed) for name in versions}
        n_batches = max(1, args.min_episodes // E)
        for name, env in envs.items():
            env_run(env, 1, gens[name])  # warm-up
        times = {
            name: {"env": [], "raw1": [], "rawN": [], "steps": [], "fine": []} for name in envs
        }
        for _ in range(args.repeats):
            for name, env in envs.items():  # interleaved, so that load changes hit both alike
                seconds, coarse, fine = env_run(env, n_batches, gens[name])
                t = times[name]
                t["env"].append(seconds)
                t["raw1"].append(raw_run(env, coarse, fine))
                t["rawN"].append(raw_batch_run(env, coarse, fine, args.raw_threads))
                t["steps"].append(coarse + fine)
                t["fine"].append(fine)
        episodes = n_batches * E
        for name, env in envs.items():
            t = {k: np.array(v, dtype=np.float64) for k, v in times[name].items()}
            row = {
                "version": name,
                "E": E,
                "env_threads": env.sim.main.nthread,
                "raw_threads": [1, args.raw_threads],
                "episodes_per_repeat": episodes,
                "steps_per_episode": float(np.median(t["steps"])) / episodes,
                "fine_steps_per_episode": float(np.median(t["fine"])) / episodes,
                "env_episodes_per_s": float(np.median(episodes / t["env"])),
                "raw1_episodes_per_s": float(np.median(episodes / t["raw1"])),
                "rawN_episodes_per_s": float(np.median(episodes / t["rawN"])),
                "env_over_raw1": float(np.median(t["raw1"] / t["env"])),
                "env_over_rawN": float(np.median(t["rawN"] / t["env"])),
                "env_steps_per_s": float(np.median(t["steps"] / t["env"])),
            }
            if name != "baseline" and "baseline" in times:
                base = np.array(times["baseline"]["env"], dtype=np.float64)
                row["speedup_over_baseline"] = float(np.median(base / t["env"]))
            rows.append(row)
            print(
                f"{name:<9}{E:>5}{row['env_threads']:>4}{row['steps_per_episode']:>10.1f}"
                f"{row['fine_steps_per_episode']:>9.1f}{row['env_episodes_per_s']:>11.1f}"
                f"{row['raw1_episodes_per_s']:>12.1f}{row['rawN_episodes_per_s']:>12.1f}"
                f"{row['env_over_raw1']:>10.2f}{row['env_over_rawN']:>10.2f}"
                + (
                    f"{row['speedup_over_baseline']:>9.2f}x"
                    if "speedup_over_baseline" in row
                    else ""
                )
            )
    print(
        "env/raw: env speed over raw MuJoCo doing the same coarse and fine steps (medians of "
        f"per-repeat ratios); raw1: Python mj_step loop, 1 thread; raw{args.raw_threads}: "
        f"mujoco.batch on {args.raw_threads} threads; thr: env threads = min(E, cores); "
        "vs base: median over repeats of baseline env time / current env time"
    )
    result = {"args": asdict(args), "rows": rows}
    return write_result(args.out, result)


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = Args()
    parser.add_argument("--sizes", type=int, nargs="+", default=list(defaults.sizes))
    parser.add_argument("--repeats", type=int, default=defaults.repeats)
    parser.add_argument("--min-episodes", type=int, default=defaults.min_episodes)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--raw-threads", type=int, default=defaults.raw_threads)
    parser.add_argument("--baseline", default=defaults.baseline)
    parser.add_argument("--out", default=defaults.out)
    ns = parser.parse_args(argv)
    ns.sizes = tuple(ns.sizes)
    return Args(**vars(ns))


if __name__ == "__main__":
    main(parse_args())
