"""Fidelity of the batting integration scheme (docs/batting.md, "Fidelity").

Runs all 2^10 = 1024 open-loop action sequences (N = 10, A = 2) without noise, once with the
env's scheme (coarse RK4 swing, fine impact window; the swing as tensor dynamics, and again in
MuJoCo, the engine of record, with the two compared directly) and once with a uniform Euler step
``ref_factor`` times finer than the scheme's fine step (or ``--ref-dt``), and compares: hit/miss
agreement, first-hit step agreement, carry error (mean, max, 95 % quantile) over sequences that
hit in both, and the physics steps spent per episode (coarse RK4 steps = steps - fine). A uniform
run at the scheme's own fine step is shown too, and with ``--baseline FILE`` the scheme of
another version of the batting module as one file (a revision before envs/batting/ became a
package, e.g. ``git show 9ceec5b:envs/batting.py > old.py``), for a before/after table against
one reference.

    python benchmarks/batting_fidelity.py --out results/batting_fidelity.json
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from _timing import write_result

from envs.batting import ACTION_TORQUES, FINE_DT, MAX_STEPS, XML_PATH, BattingSimulator


@dataclass
class Args:
    """Command-line arguments."""

    out: str = "results/batting_fidelity.json"  # where the JSON table goes
    ref_factor: int = 4  # the reference step is fine_dt / ref_factor
    ref_dt: float | None = None  # (s) the reference step, if not fine_dt / ref_factor
    baseline: str | None = None  # another envs/batting.py whose scheme is compared too
    nthread: int | None = None  # MuJoCo threads (None: all cores)
    skip_uniform_fine: bool = False  # leave out the uniform run at the scheme's fine step
    margins: str = ""  # comma-separated margins (m) of extra scheme runs, e.g. "0.05" (before)
    reference: str | None = None  # an .npz of the reference run: read if it exists, else written


def all_sequences(n_steps: int = MAX_STEPS) -> np.ndarray:
    """Every open-loop action sequence, int [2^N, N], in binary order (row i = bits of i)."""
    return np.array(list(itertools.product((0, 1), repeat=n_steps)), dtype=np.int64)


def load_baseline(path: str) -> type:
    """BattingSimulator class of another version of envs/batting.py, on this MJCF file."""
    spec = importlib.util.spec_from_file_location("batting_baseline", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.BattingSimulator.__init__.__kwdefaults__["xml_path"] = XML_PATH
    return module.BattingSimulator


def run_sequences(seqs: np.ndarray, simulator: type = BattingSimulator, **sim_kwargs) -> dict:
    """Noiseless episodes of the given sequences: carry, first-hit step and physics steps."""
    sim = simulator(num_envs=len(seqs), **sim_kwargs)
    sim.reset()
    torques = np.asarray(ACTION_TORQUES)
    hit_step = np.full(len(seqs), -1)
    obs = [sim.observation()]
    start = time.perf_counter()
    for t in range(seqs.shape[1]):
        ob, _, first_hit = sim.step(torques[seqs[:, t]])
        hit_step[first_hit] = t
        obs.append(ob)
    return {
        "obs": np.stack(obs, axis=1),  # [S, N + 1, 4] observed states (eq. 62)
        "carry": sim.carry.copy(),
        "hit": sim.hit.copy(),
        "hit_step": hit_step,
        "steps": sim.physics_steps.copy(),
        "fine_steps": sim.fine_steps.copy(),
        "seconds": time.perf_counter() - start,
    }


def load_reference(path: str | None, ref_dt: float) -> dict | None:
    """The reference run stored at ``path`` by an earlier invocation (None if absent)."""
    if not path or not Path(path).exists():
        return None
    with np.load(path) as stored:
        ref = {key: stored[key] for key in stored.files}
    if abs(float(ref.pop("ref_dt")) - ref_dt) > 1e-12:
        raise ValueError(f"{path} holds a reference of another step than {ref_dt} s")
    ref["seconds"] = float(ref["seconds"])
    return ref


def compare(run: dict, ref: dict) -> dict:
    """Agreement and carry error of ``run`` against ``ref`` (both from :func:`run_sequences`)."""
    both = run["hit"] & ref["hit"]
    err = np.abs(run["carry"] - ref["carry"])[both]
    # the observed states: each sequence's largest error over its steps, per state dimension
    state_err = np.abs(run["obs"] - ref["obs"]).max(axis=1)  # [S, 4]
    return {
        "state_err_p95": np.quantile(state_err, 0.95, axis=0).tolist(),
        "state_err_max": state_err.max(axis=0).tolist(),
        "hits": int(run["hit"].sum()),
        "hit_agreement": int((run["hit"] == ref["hit"]).sum()),
        "hit_step_agreement": int((run["hit_step"] == ref["hit_step"]).sum()),
        "carry_err_mean": float(err.mean()),
        "carry_err_p95": float(np.quantile(err, 0.95)),
        "carry_err_max": float(err.max()),
        "steps_per_episode": float(run["steps"].mean()),
        "fine_steps_per_episode": float(run["fine_steps"].mean()),
        "seconds": run["seconds"],
    }


def main(args: Args) -> dict:
    seqs = all_sequences()
    ref_dt = FINE_DT / args.ref_factor if args.ref_dt is None else args.ref_dt
    runs = {}
    if args.baseline:
        baseline = load_baseline(args.baseline)
        runs["baseline scheme"] = run_sequences(seqs, baseline, nthread=args.nthread)
    runs["scheme (adaptive)"] = run_sequences(seqs, nthread=args.nthread)
    runs["scheme, MuJoCo swing"] = run_sequences(seqs, nthread=args.nthread, swing="mujoco")
    for margin in filter(None, args.margins.split(",")):
        runs[f"scheme, margin {margin}"] = run_sequences(
            seqs, nthread=args.nthread, margin=float(margin)
        )
    if not args.skip_uniform_fine:
        runs[f"uniform {FINE_DT * 1e3:g} ms"] = run_sequences(
            seqs, scheme="uniform", nthread=args.nthread
        )
    ref = load_reference(args.reference, ref_dt)
    if ref is None:
        print(f"reference: uniform {ref_dt * 1e3:g} ms over {len(seqs)} sequences ...", flush=True)
        ref = run_sequences(seqs, scheme="uniform", fine_dt=ref_dt, nthread=args.nthread)
        if args.reference:
            np.savez(args.reference, ref_dt=ref_dt, **ref)
    rows = {name: compare(run, ref) for name, run in runs.items()}
    rows[f"reference {ref_dt * 1e3:g} ms"] = compare(ref, ref)

    header = (
        f"{'run':<22}{'hits':>6}{'hit agree':>11}{'step agree':>12}{'err mean':>10}"
        f"{'err p95':>9}{'err max':>9}{'steps/ep':>10}{'fine/ep':>9}{'s':>7}"
    )
    print(header)
    for name, r in rows.items():
        print(
            f"{name:<22}{r['hits']:>6}{r['hit_agreement']:>7}/{len(seqs)}"
            f"{r['hit_step_agreement']:>8}/{len(seqs)}{r['carry_err_mean']:>10.3f}"
            f"{r['carry_err_p95']:>9.3f}{r['carry_err_max']:>9.3f}"
            f"{r['steps_per_episode']:>10.1f}{r['fine_steps_per_episode']:>9.1f}"
            f"{r['seconds']:>7.1f}"
        )
    print("carry errors in m, over sequences that hit in both runs")
    print(
        f"\n{'run':<22}{'state error (each sequence its worst step) p95 / max':>58}\n{'':<22}"
        + "".join(f"{dim:>16}" for dim in ("phi1", "phi1_dot", "phi2", "phi2_dot"))
    )
    for name, r in rows.items():
        cells = zip(r["state_err_p95"], r["state_err_max"], strict=True)
        print(f"{name:<22}" + "".join(f"{p:>8.4f} /{m:>6.3f}" for p, m in cells))
    print("state errors in rad and rad/s against the reference")
    swings = compare(runs["scheme (adaptive)"], runs["scheme, MuJoCo swing"])
    print(
        f"\ntensor swing against MuJoCo's swing (same scheme): hit agreement "
        f"{swings['hit_agreement']}/{len(seqs)}, first-hit step agreement "
        f"{swings['hit_step_agreement']}/{len(seqs)}, carry error max "
        f"{swings['carry_err_max']:.2e} m, state error max "
        + ", ".join(f"{e:.1e}" for e in swings["state_err_max"])
        + " (rad, rad/s)"
    )
    result = {
        "args": asdict(args),
        "n_sequences": len(seqs),
        "rows": rows,
        "tensor_vs_mujoco_swing": swings,
    }
    return write_result(args.out, result)


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = Args()
    parser.add_argument("--out", default=defaults.out)
    parser.add_argument("--ref-factor", type=int, default=defaults.ref_factor)
    parser.add_argument("--ref-dt", type=float, default=defaults.ref_dt)
    parser.add_argument("--baseline", default=defaults.baseline)
    parser.add_argument("--nthread", type=int, default=defaults.nthread)
    parser.add_argument("--skip-uniform-fine", action="store_true")
    parser.add_argument("--margins", default=defaults.margins)
    parser.add_argument("--reference", default=defaults.reference)
    return Args(**vars(parser.parse_args(argv)))


if __name__ == "__main__":
    main(parse_args())
