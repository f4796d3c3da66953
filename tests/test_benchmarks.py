"""The benchmark scripts run (tiny sizes) and print their tables."""

import json
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
        (
            [
                "profile_batting.py",
                "--trials",
                "2",
                "--iterations",
                "1",
                "--command",
                "--repeats",
                "1",
            ],
            "| **the command** |",
        ),
        (
            ["bench_batting_iteration.py", "--trials", "1", "--iterations", "1", "--audit", "1"],
            "| part / floor | |",
        ),
        (
            ["bench_batting_swing.py", "--sizes", "16", "--repeats", "1", "--audit-fraction", "1"],
            "tensor / mujoco",
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


def test_dqn_baseline_holds_both_tasks_beside_the_library(tmp_path, monkeypatch, capsys):
    """benchmarks/dqn_baseline.py on CartPole and Acrobot (tiny, in this process): one DQN run a
    seed and task, stored and read back; the library's JSONs merged per env into a paired row
    and three baselines per task; the headline puts each task's DQN beside its own row only."""
    library = []
    for env, returns in (("CartPole-v1", (20.0, 30.0, 25.0)), ("Acrobot-v1", (-400, -300, -500))):
        runs = {
            mode: {
                str(s): {"history": [{"greedy_test_return": r + 3 * s, "rewarded_transitions": 9}]}
                for s, r in enumerate(returns)
            }
            for mode, returns in (("AL", returns), ("PL", tuple(r - 1 for r in returns)))
        }
        settings = {"env": env, "iterations": 2, "first_episodes": 3, "episodes": 1}
        library.append(tmp_path / f"{env}.json")
        library[-1].write_text(json.dumps({"args": settings, "runs": runs}))
    out = tmp_path / "dqn_baseline.json"
    flags = ["--seeds", "2", "--envs", "CartPole-v1", "Acrobot-v1", "--frames", "1000", "1000"]
    flags += ["--test-episodes", "1", "--test-steps", "5", "--out-dir", str(tmp_path / "dqn")]
    flags += ["--library", *map(str, library), "--out", str(out)]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / "dqn_baseline.py"), *flags])
    monkeypatch.setattr(sys, "path", [str(BENCHMARKS), str(ROOT), *sys.path])
    for _ in range(2):  # the second run reads every seed back
        runpy.run_path(str(BENCHMARKS / "dqn_baseline.py"), run_name="__main__")
    assert capsys.readouterr().out.count("DQN Acrobot-v1 seed") == 2  # (the first run's only)
    e = json.loads(out.read_text())
    assert [r["task"] for r in e["rows"]] == ["CartPole-v1", "Acrobot-v1"]
    assert e["rows"][1]["schedule"] == "Acrobot-v1: showcase (3, 1 × 1)"
    assert e["rows"][1]["difference"]["mean"] == pytest.approx(1.0)  # seeds 0, 1 paired
    assert [(b["task"], b["learner"].split(" (")[0]) for b in e["baselines"]] == [
        (task, learner)
        for task in ("CartPole-v1", "Acrobot-v1")
        for learner in ("DQN", "library AL", "library PL")
    ]
    assert {r["test_iteration"] for r in e["dqn_runs"]} == {8, 6}  # the showcase's L per env
    assert e["dqn_config"]["Acrobot-v1"]["init_random_frames"] == round(1000 / 500_100 * 10_000)
    import report  # (benchmarks/ is first on the patched sys.path)

    table = "\n".join(report.headline_table(report.headline([e])))
    cartpole = next(line for line in table.splitlines() if "CartPole-v1: showcase" in line)
    assert "DQN (TorchRL's example, 1,000 frames)" in cartpole and cartpole.count("DQN (") == 1
