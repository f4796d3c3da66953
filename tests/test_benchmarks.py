"""The benchmark scripts run (tiny sizes) and print their tables."""

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.parametrize(
    ("script", "expected"),
    [
        ("bench_j.py", "| n | batched J | floor (2 matmuls) |"),
        ("bench_scaling.py", "Order of growth: wall s ~ trials^"),
    ],
)
def test_benchmark_runs_quick(script, expected, tmp_path):
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert expected in done.stdout
    assert out.exists()
