"""CPU against GPU in one run: the same experiments on each device, their wall times and numbers.

1. Figure 8 complete (``examples/chain_walk_api.py``: T trials × 2 schedules × AL and PL) on
   each device. With ``--device cuda`` all of it runs on the GPU: the batched walks, the
   rollouts, psi_hat, J and the solves.
2. Batting (``examples/train_batting.py``, T trials, the decreasing schedule, AL and PL) with
   the algebra on each device; the physics is MuJoCo on the CPU either way.
3. The batched algebra alone: one J evaluation (``j_criterion`` on ``[T, Z, K, n, B]``) and one
   ``weighted_ridge`` solve (``[T, n, B]``), median of repeats, the GPU synchronised.

Random numbers are drawn on the CPU on every device, so both devices see the same episodes;
each experiment row says how far its numbers are from the CPU's: the share of identical
choices (the candidate chosen per trial and iteration) and the largest difference of a
performance number. Without a GPU only the CPU rows are printed.

Run::

    python benchmarks/bench_device.py                  # about 4 minutes with a GPU
    python benchmarks/bench_device.py --fig8-trials 1000 --batting-trials 16 --out dev.json
    python benchmarks/bench_device.py --quick          # smoke test, seconds
"""

from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import tyro
from _timing import machine_info, median_times

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import chain_walk_api  # noqa: E402
import train_batting  # noqa: E402

from torch_api.core.solve import j_criterion, weighted_ridge  # noqa: E402


@dataclass
class Args:
    """Command-line arguments of the device benchmark."""

    fig8_trials: int = 1000
    """T of the chain-walk Figure 8 run (the paper: 1000)"""
    batting_trials: int = 16
    """T of the batting run (decreasing schedule, AL and PL)"""
    batting_iterations: int = 7
    """iterations of the batting run"""
    algebra_trials: int = 64
    """T of the algebra-alone table (Z = 5, K = 4, B = 110)"""
    algebra_samples: int = 500
    """n, samples per set in the algebra-alone table"""
    threads: int = 1
    """torch intra-op threads for the experiments (1: fastest for their small tensors)"""
    quick: bool = False
    """tiny sizes, for a smoke test"""
    out: str = ""
    """write the numbers as JSON to this path"""


def devices() -> list[str]:
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def largest_difference(ours, theirs) -> float:
    """max |a - b| over two nested lists of numbers (None entries skipped)."""
    if ours is None or theirs is None:
        return 0.0
    if isinstance(ours, list):
        return max((largest_difference(a, b) for a, b in zip(ours, theirs, strict=True)), default=0)
    return abs(float(ours) - float(theirs))


def same_share(ours, theirs) -> float:
    """Share of equal leaves of two nested lists (1.0 when there are none)."""
    pairs = []

    def walk(a, b):
        if isinstance(a, list):
            for x, y in zip(a, b, strict=True):
                walk(x, y)
        elif a is not None:
            pairs.append(a == b)

    walk(ours, theirs)
    return sum(pairs) / len(pairs) if pairs else 1.0


def compare_devices(name: str, run_on) -> list[dict]:
    """Run ``run_on(device) -> (trials, wall s, choices, performance)`` on every device.

    Each row: wall time, its ratio to the CPU's, the share of choices equal to the CPU's and
    the largest difference of a performance number from the CPU's.
    """
    rows, reference = [], None
    for device in devices():
        trials, seconds, chosen, performance = run_on(device)
        reference = reference or (chosen, performance, seconds)
        rows.append(
            {
                "device": device,
                "trials": trials,
                "seconds": seconds,
                "vs_cpu": seconds / reference[2],
                "same_choices": same_share(chosen, reference[0]),
                "max_return_difference": largest_difference(performance, reference[1]),
            }
        )
        print(f"  {name} on {device}: {seconds:.1f} s", flush=True)
    return rows


def figure8(args: Args, tmp: Path) -> list[dict]:
    trials, iterations = (4, 2) if args.quick else (args.fig8_trials, 7)

    def run_on(device: str):
        payload = chain_walk_api.main(
            [
                *("--trials", str(trials), "--iterations", str(iterations), "--device", device),
                *("--out-dir", str(tmp / f"fig8_{device}"), "--overwrite"),
            ]
        )
        runs = [run for res in payload["results"].values() for run in res["runs"].values()]
        chosen = [[it.get("chosen") for it in run["iterations"]] for run in runs]
        returns = [[it["test_return"] for it in run["iterations"]] for run in runs]
        return trials, payload["wall_seconds"], chosen, returns

    return compare_devices("Figure 8", run_on)


def batting(args: Args, tmp: Path) -> list[dict]:
    trials, iterations = (2, 1) if args.quick else (args.batting_trials, args.batting_iterations)

    def run_on(device: str):
        payload = train_batting.main(
            [
                *("--trials", str(trials), "--iterations", str(iterations), "--device", device),
                *("--out-dir", str(tmp / f"batting_{device}"), "--overwrite"),
                *(("--episodes", "2", "--repeats", "2") if args.quick else ()),
            ]
        )
        runs = list(payload["results"]["decreasing"]["runs"].values())
        chosen = [[it["chosen"] for it in run["iterations"]] for run in runs]
        performance = [[it["performance"] for it in run["iterations"]] for run in runs]
        return trials, payload["wall_seconds"], chosen, performance

    return compare_devices("batting", run_on)


def algebra(args: Args) -> list[dict]:
    """One J evaluation and one solve per device; CPU with one thread and with all cores."""
    t, n = (4, 50) if args.quick else (args.algebra_trials, args.algebra_samples)
    z, k, b = 5, 4, 110
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(t, z, k, n, b, generator=gen, dtype=torch.float64)
    w = torch.rand(t, z, k, n, generator=gen, dtype=torch.float64) + 0.5
    u = (lambda m: m @ m.mT / b)(torch.randn(t, z, 1, b, b, generator=gen, dtype=torch.float64))
    r = torch.randn(t, n, generator=gen, dtype=torch.float64)
    budget = 0.05 if args.quick else 2.0
    settings = [("cpu", 1), ("cpu", torch.get_num_threads())]
    settings += [("cuda", 0)] if "cuda" in devices() else []
    rows, j_ref, theta_ref = [], None, None
    threads = torch.get_num_threads()
    for device, num_threads in settings:
        if num_threads:
            torch.set_num_threads(num_threads)
        xd, wd, ud, rd = (v.to(device) for v in (x, w, u, r))
        sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

        def run_j(xd=xd, wd=wd, ud=ud, sync=sync):
            out = j_criterion(xd, wd, ud, 1e-3)
            sync()
            return out

        def run_solve(xd=xd, wd=wd, rd=rd, sync=sync):
            out = weighted_ridge(xd[:, 0, 0], wd[:, 0, 0], rd, 1e-3)
            sync()
            return out

        timing = median_times({"j": run_j, "solve": run_solve}, budget_s=budget)
        j, theta = timing["j"].result.cpu(), timing["solve"].result.cpu()
        j_ref = j if j_ref is None else j_ref
        theta_ref = theta if theta_ref is None else theta_ref
        rows.append(
            {
                "device": device if device == "cuda" else f"cpu, {num_threads} thread(s)",
                "shape": f"[{t}, {z}, {k}, {n}, {b}]",
                "j_ms": timing["j"].median_ms,
                "solve_ms": timing["solve"].median_ms,
                "j_relative_difference": float(((j - j_ref).abs() / j_ref.abs()).max()),
                "theta_relative_difference": float(
                    (theta - theta_ref).abs().max() / theta_ref.abs().max()
                ),
            }
        )
    torch.set_num_threads(threads)
    return rows


def print_experiment(title: str, rows: list[dict]) -> None:
    print(f"\n{title}")
    print("| device | trials | wall s | vs CPU | same choices | max |Δ performance| |")
    print("|---|---:|---:|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['device']} | {row['trials']} | {row['seconds']:.1f} | {row['vs_cpu']:.2f}x "
            f"| {100 * row['same_choices']:.1f} % | {row['max_return_difference']:.2e} |"
        )


def main(argv=None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__.split("\n")[0])
    if "cuda" not in devices():
        print("no CUDA GPU here: CPU rows only")
    else:
        print(f"GPU: {torch.cuda.get_device_name()}")
    algebra_rows = algebra(args)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        fig8_rows = figure8(args, Path(tmp))
        batting_rows = batting(args, Path(tmp))

    print_experiment("Figure 8, chain walk (everything on the device)", fig8_rows)
    print_experiment(
        "Batting, decreasing schedule (algebra on the device, physics on CPU)", batting_rows
    )
    print("\nAlgebra alone: one J evaluation and one solve (median ms)")
    print("| device | [T, Z, K, n, B] | J ms | solve ms | J rel. Δ | θ rel. Δ |")
    print("|---|---|---:|---:|---:|---:|")
    for row in algebra_rows:
        print(
            f"| {row['device']} | {row['shape']} | {row['j_ms']:.1f} | {row['solve_ms']:.2f} "
            f"| {row['j_relative_difference']:.1e} | {row['theta_relative_difference']:.1e} |"
        )
    result = {
        "machine": machine_info(),
        "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        "args": asdict(args),
        "figure8": fig8_rows,
        "batting": batting_rows,
        "algebra": algebra_rows,
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
