"""The benchmark scripts run (tiny sizes) and print their tables."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


@pytest.mark.parametrize(
    ("command", "expected"),
    [
        (["bench_j.py", "--quick"], "| n | batched J | floor (2 matmuls) |"),
        (["bench_scaling.py", "--quick"], "Order of growth: wall s ~ trials^"),
        (["profile_batting.py", "--trials", "1", "--iterations", "1"], "wall / floor (2 threads)"),
        (
            ["bench_figure10.py", "--trials", "2", "--iterations", "1", "--audit", "0.2"]
            + ["--out-dir", "{tmp}/runs"],
            "| processes (2 workers) |",
        ),
        (
            ["bench_collection.py", "--sizes", "4", "--budget", "0.01", "--repeats", "1"]
            + ["--slow-size", "4"],
            "| slow chain walk (500 µs per row-step) | 4 |",
        ),
        (["bench_device.py", "--quick"], "| cpu | 4 | "),
        (["bench_durability.py", "--repeats", "1"], "ms per episode index"),
        (["batting_ceiling.py", "--quick"], "ceiling (best LSPI score above):"),
    ],
)
def test_benchmark_runs_quick(command, expected, tmp_path):
    out = tmp_path / "bench.json"
    script, *flags = (part.format(tmp=tmp_path) for part in command)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    done = subprocess.run(  # in tmp_path: whatever a script writes by default lands there
        [sys.executable, str(BENCHMARKS / script), *flags, "--out", str(out)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert expected in done.stdout
    assert out.exists()
