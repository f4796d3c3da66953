"""The benchmark scripts run (tiny sizes) and print their tables."""

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.parametrize(
    ("command", "expected"),
    [
        (["bench_j.py", "--quick"], "| n | batched J | floor (2 matmuls) |"),
        (["bench_scaling.py", "--quick"], "Order of growth: wall s ~ trials^"),
        (["profile_batting.py", "--trials", "1", "--iterations", "1"], "wall / floor (2 threads)"),
        (
            ["bench_figure10.py", "--trials", "2", "--iterations", "1", "--audit", "0.2"],
            "| processes (2 workers) |",
        ),
        (
            ["bench_collection.py", "--sizes", "4", "--budget", "0.01", "--repeats", "1"]
            + ["--slow-size", "4"],
            "| slow chain walk (500 µs per row-step) | 4 |",
        ),
        (["bench_device.py", "--quick"], "| cpu | 4 | "),
        (["bench_durability.py", "--repeats", "1"], "ms per episode index"),
    ],
)
def test_benchmark_runs_quick(command, expected, tmp_path):
    out = tmp_path / "bench.json"
    script, *flags = command
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *flags, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert expected in done.stdout
    assert out.exists()
