"""The benchmark scripts run (tiny sizes) and print their tables."""

import runpy
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


@pytest.mark.parametrize(
    ("command", "expected"),
    [
        (["bench_j.py", "--quick"], "| n | batched J | floor (2 matmuls) |"),
        (["bench_scaling.py", "--quick"], "Order of growth: wall s ~ trials^"),
        (["profile_batting.py", "--trials", "1", "--iterations", "1"], "| **the main job** |"),
        (
            ["bench_batting_iteration.py", "--trials", "1", "--iterations", "1", "--audit", "1"],
            "| part / floor | |",
        ),
        (
            ["bench_figure10.py", "--trials", "2", "--iterations", "1", "--audit", "0.2"]
            + ["--out-dir", "{tmp}/runs"],
            "| processes (2 workers) |",
        ),
        (
            ["bench_collection.py", "--sizes", "4", "--budget", "0.01", "--repeats", "1"]
            + ["--warmup", "0", "--slow-size", "4", "--tasks", "chain"],
            "| slow chain walk (500 µs per row-step) | 4 |",
        ),
        (["bench_device.py", "--quick"], "| cpu | 4 | "),
        (["bench_durability.py", "--repeats", "1"], "ms per episode index"),
        (
            ["bench_figure8.py", "--trials", "2", "--startup-repeats", "1", "--count-trials", "2"]
            + ["--backend", "processes", "--quick"],
            "| 2 | processes | ",
        ),
        (
            ["durability_attacks.py", "--kills", "0", "--signals", "0", "--damages", "4"]
            + ["--commit-signals", "1"],
            "| all | ",
        ),
        (["batting_ceiling.py", "--quick"], "ceiling (best LSPI score above):"),
        (["cartpole_remedies.py", "--quick", "--only", "LSTD PL iwcv"], "| LSTD PL iwcv | "),
    ],
)
def test_benchmark_runs_quick(command, expected, tmp_path, monkeypatch, capsys):
    """Each script run as ``python benchmarks/<script>`` runs it, in this process (torch is
    imported once for all), from tmp_path: whatever a script writes by default lands there."""
    out = tmp_path / "bench.json"
    script, *flags = (part.format(tmp=tmp_path) for part in command)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / script), *flags, "--out", str(out)])
    monkeypatch.setattr(sys, "path", [str(BENCHMARKS), str(ROOT), *sys.path])
    try:
        runpy.run_path(str(BENCHMARKS / script), run_name="__main__")
    except SystemExit as done:
        assert done.code in (0, None), capsys.readouterr().err[-2000:]
    assert expected in capsys.readouterr().out
    assert out.exists()


def test_aggregating_identical_rows_changes_nothing():
    """``benchmarks/_aggregate.py``: J and θ on merged identical rows equal those on all rows."""
    sys.path.insert(0, str(BENCHMARKS))
    from _aggregate import aggregate_identical_rows

    from torch_api.core.solve import DEFAULT_LAMBDA as LAM
    from torch_api.core.solve import j_criterion, weighted_ridge

    gen = torch.Generator().manual_seed(3)
    distinct = torch.randn(2, 5, 6, generator=gen, dtype=torch.float64)
    pick = torch.randint(0, 5, (2, 300), generator=gen)
    x = torch.gather(distinct, 1, pick.unsqueeze(-1).expand(2, 300, 6))
    w = torch.rand(2, 300, generator=gen, dtype=torch.float64)
    r = torch.randn(2, 300, generator=gen, dtype=torch.float64)
    u = torch.eye(6, dtype=torch.float64)
    agg = aggregate_identical_rows(x, w, r)
    assert agg.x.shape[-2] <= 5
    j_full = j_criterion(x, w, u, LAM)
    j_agg = j_criterion(
        agg.x, agg.w, u, LAM, num_samples=agg.num_samples, sq_weights=agg.sq_weights
    )
    torch.testing.assert_close(j_agg, j_full, rtol=1e-10, atol=0)
    theta_full = weighted_ridge(x, w, r, LAM)
    theta_agg = weighted_ridge(agg.x, agg.w, agg.r, LAM, num_samples=agg.num_samples)
    torch.testing.assert_close(theta_agg, theta_full, rtol=1e-9, atol=1e-12)
