"""Bit identity of the examples' numbers across a refactoring: run them, then compare.

Runs Figure 8 at 100 trials (both tie rules), the batting main job at 4 trials, the one-step
experiment at 20 trials and the TorchRL pipeline (small budget) from one checkout, writing
each run's CSV/JSON under ``--out``; ``compare`` then checks two such folders file by file.
CSV files must be equal byte for byte; JSON files must be equal once the wall times (keys
naming ``seconds``) and the output folder (``out_dir``) are left out, every number exact; the
stored runs (``checkpoints/*.db``) must record the same settings (what a resume checks) and
the same θ_l of every iteration.

    python benchmarks/bit_identity.py run --root /tmp/before --out /tmp/bit_before
    python benchmarks/bit_identity.py run --out /tmp/bit_after
    python benchmarks/bit_identity.py compare /tmp/bit_before /tmp/bit_after

(The "before" of the layout's refactoring, issue #23, is commit 16990bf. Figure 8's
``test_return`` rows changed on purpose after it, in 888ef35, the test episodes walked with the
actions summed out; Figure 8 is compared against 9d5c80f, main just before the layout landed.)
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# (name, script, arguments): small budgets, each a few seconds to a minute on one core
RUNS = [
    ("fig8_uniform", "chain_walk_api.py", ["--trials", "100", "--tie-break", "uniform"]),
    ("fig8_lowest", "chain_walk_api.py", ["--trials", "100", "--tie-break", "lowest"]),
    ("batting", "train_batting.py", ["--trials", "4"]),
    ("one_step", "chain_walk_one_step.py", ["--trials", "20"]),
    (
        "pipeline",
        "torchrl_pipeline.py",
        ["--iterations", "2", "--episodes", "3", "--steps", "60", "--test-episodes", "2"],
    ),
]

_TIMING = ("seconds",)  # keys whose values are wall times, not the algorithm's numbers
_LEFT_OUT = {"out_dir"}


def _run(root: Path, out: Path, only: list[str]) -> None:
    env = dict(os.environ, PYTHONPATH=str(root))
    for name, script, args in RUNS:
        if only and name not in only:
            continue
        started = time.perf_counter()
        command = [sys.executable, str(root / "examples" / script), *args]
        command += ["--out-dir", str(out / name)]
        shutil.rmtree(out / name, ignore_errors=True)  # a fresh folder: nothing to resume
        subprocess.run(command, cwd=root, env=env, check=True, capture_output=True)
        print(f"{name}: {time.perf_counter() - started:.1f} s", flush=True)


def _strip(value):
    """The JSON value without wall times and the output folder."""
    if isinstance(value, dict):
        return {
            k: _strip(v)
            for k, v in value.items()
            if k not in _LEFT_OUT and not any(t in k for t in _TIMING)
        }
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def _files(folder: Path) -> list[Path]:
    return sorted(
        p.relative_to(folder)
        for p in folder.rglob("*")
        if p.suffix in {".csv", ".json"} and "checkpoints" not in p.parts
    )


def _compare(before: Path, after: Path) -> bool:
    names = _files(before)
    missing = sorted(set(names) ^ set(_files(after)))
    for name in missing:
        print(f"{name}: in only one folder")
    same = not missing
    for name in names:
        if name in missing:
            continue
        a, b = (before / name).read_bytes(), (after / name).read_bytes()
        if name.suffix == ".json":
            equal = _strip(json.loads(a)) == _strip(json.loads(b))
            how = "equal (wall times left out)"
        else:
            equal, how = a == b, "equal to the byte"
        print(f"{name}: {how if equal else 'DIFFERENT'}")
        same &= equal
    for name in sorted(p.relative_to(before) for p in before.rglob("checkpoints/*.db")):
        equal = _same_run(before / name, after / name)
        print(f"{name}: {'settings and θ equal' if equal else 'DIFFERENT'}")
        same &= equal
        names.append(name)
    print(f"{len(names)} files compared: {'all equal' if same else 'NOT all equal'}")
    return same


def _same_run(before: Path, after: Path) -> bool:
    """Two stored runs with the same settings and θ_l in every record (read by this checkout)."""
    sys.path.insert(0, str(ROOT))
    from torch_api.runs.store import RunStore

    if not after.exists():
        return False
    a, b = RunStore.read(before), RunStore.read(after)
    theta = [r["theta"] for _, r in sorted(a.records.items())]
    return a.config == b.config and theta == [r["theta"] for _, r in sorted(b.records.items())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the examples of one checkout")
    run.add_argument("--root", type=Path, default=ROOT, help="the checkout (default: this one)")
    run.add_argument("--out", type=Path, required=True, help="where the runs' files go")
    run.add_argument("--only", nargs="*", default=[], help="run only these (names of RUNS)")
    compare = sub.add_parser("compare", help="compare two folders written by run")
    compare.add_argument("before", type=Path)
    compare.add_argument("after", type=Path)
    args = parser.parse_args()
    if args.command == "run":
        _run(args.root.resolve(), args.out.resolve(), args.only)
    else:
        sys.exit(0 if _compare(args.before, args.after) else 1)


if __name__ == "__main__":
    main()
