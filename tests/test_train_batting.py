"""End-to-end runs of examples/train_batting.py with tiny budgets (subprocesses)."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "examples" / "train_batting.py"
TINY = ["--trials", "2", "--iterations", "2", "--episodes", "2", "--repeats", "2", "--seed", "3"]
STEPS = 10  # N of the batting task
MODES = ("active", "passive")
INTERRUPTED = 3  # exit code of the script's --stop-after-checkpoints testing aid


def run_script(out_dir: Path, *extra: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    return subprocess.run(
        [sys.executable, str(SCRIPT), *TINY, "--out-dir", str(out_dir), *extra],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def numbers(payload: dict) -> dict:
    """Everything a resumed run must reproduce exactly (wall times excluded)."""
    keep = ("performance", "hit_share", "chosen", "sampling_epsilon", "j_prime")
    keep += ("episodes_bought", "rewarded_transitions", "reward_free_transitions")
    return {
        name: {mode: {k: run[k] for k in keep} for mode, run in res["runs"].items()}
        for name, res in payload["results"].items()
    }


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("uninterrupted")
    return out, run_script(out)


def test_outputs_exist_and_rewards_match_schedule(uninterrupted):
    out, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "paired t-test AL vs PL at iteration 2" in proc.stdout
    payload = json.loads((out / "train_batting.json").read_text())
    runs = payload["results"]["decreasing"]["runs"]
    assert set(runs) == {"active", "passive"}
    for mode, run in runs.items():
        assert run["episodes_bought"] == [2, 2]
        assert run["rewarded_transitions"] == [2 * STEPS, 4 * STEPS]  # per trial, cumulative
        for row in run["performance"]:
            assert len(row) == 2 and all(math.isfinite(x) and x >= 0 for x in row)
        if mode == "active":
            assert all(len(j) == 2 and len(j[0]) == 4 for j in run["j_prime"])
            assert all(math.isfinite(x) and x >= 0 for j in run["j_prime"] for t in j for x in t)
            assert run["reward_free_transitions"] == [2 * 4 * 2 * STEPS, 2 * 2 * 4 * 2 * STEPS]
        else:
            assert run["chosen"] == [[0, 0], [0, 0]] and run["j_prime"] == [None, None]
    with open(out / "train_batting.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 1 * 2 * 2 * 2  # schedule × method × iteration × trial
    assert all(math.isfinite(float(r["performance"])) for r in rows)
    assert (out / "fig10_performance.png").stat().st_size > 1000


def test_interrupted_and_resumed_run_matches(uninterrupted, tmp_path):
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Stop right after the AL run bought its second batch (checkpoints: buy, iteration, buy).
    first = run_script(tmp_path, "--stop-after-checkpoints", "3")
    assert first.returncode == INTERRUPTED, first.stderr[-3000:]
    assert not (tmp_path / "train_batting.json").exists()
    # Resume: AL fits iteration 2 without buying again (1), PL buys (2) and fits (3), stop.
    second = run_script(tmp_path, "--resume", "--stop-after-checkpoints", "3")
    assert second.returncode == INTERRUPTED, second.stderr[-3000:]
    assert "decreasing_active.pt at iteration 1/2" in second.stdout
    # Resume again: AL is complete and is not recomputed; PL continues from iteration 1.
    third = run_script(tmp_path, "--resume")
    assert third.returncode == 0, third.stderr[-3000:]
    assert "decreasing_active.pt at iteration 2/2" in third.stdout
    assert "decreasing_passive.pt at iteration 1/2" in third.stdout
    expected = numbers(json.loads((reference / "train_batting.json").read_text()))
    resumed = numbers(json.loads((tmp_path / "train_batting.json").read_text()))
    assert resumed == expected
    for run in resumed["decreasing"].values():  # no rewarded episode bought twice
        assert run["rewarded_transitions"][-1] == (2 + 2) * STEPS


def test_chunked_run_gives_the_same_numbers(uninterrupted, tmp_path):
    """Two chunks of one trial each: per-chunk checkpoints, the numbers of one batch of two."""
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    chunked = run_script(tmp_path, "--chunks", "2")
    assert chunked.returncode == 0, chunked.stderr[-3000:]
    names = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    expected_names = [f"decreasing_{m}_chunk{c}of2.pt" for m in MODES for c in (1, 2)]
    assert names == expected_names
    expected = numbers(json.loads((reference / "train_batting.json").read_text()))
    assert numbers(json.loads((tmp_path / "train_batting.json").read_text())) == expected


def test_chunked_run_resumes_per_chunk(uninterrupted, tmp_path):
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Checkpoints: AL chunk 1 buys, fits, buys (3); stop. Resume: chunk 1 continues, chunk 2 anew.
    first = run_script(tmp_path, "--chunks", "2", "--stop-after-checkpoints", "3")
    assert first.returncode == INTERRUPTED, first.stderr[-3000:]
    second = run_script(tmp_path, "--chunks", "2", "--resume")
    assert second.returncode == 0, second.stderr[-3000:]
    assert "decreasing_active_chunk1of2.pt at iteration 1/2" in second.stdout
    assert "decreasing_active_chunk2of2.pt" not in second.stdout  # nothing to resume there
    expected = numbers(json.loads((reference / "train_batting.json").read_text()))
    assert numbers(json.loads((tmp_path / "train_batting.json").read_text())) == expected


def test_worker_processes_give_the_same_numbers_and_count_the_physics(uninterrupted, tmp_path):
    """--backend processes: chunks in two worker processes, the numbers of one batch; every
    run's physics steps counted (and, with --physics-audit, sampled without changing a thing)."""
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    flags = ("--backend", "processes", "--workers", "2", "--chunks", "2", "--physics-audit", "0.5")
    done = run_script(tmp_path, *flags)
    assert done.returncode == 0, done.stderr[-3000:]
    expected = json.loads((reference / "train_batting.json").read_text())
    payload = json.loads((tmp_path / "train_batting.json").read_text())
    assert numbers(payload) == numbers(expected)
    assert payload["physics_steps"] == expected["physics_steps"]
    runs = payload["results"]["decreasing"]["runs"].values()
    for kind in ("coarse", "fine"):
        assert payload["physics_steps"][kind] == sum(r["physics_steps"][kind] for r in runs)
    assert payload["physics_steps"]["coarse"] > 0


def test_beyond_the_paper_variant_runs_and_bad_widths_are_refused(tmp_path):
    """Scaled basis, episodes that end at the hit (fewer transitions bought) and LSTD-Q."""
    widths = ("--basis-widths", "0.785,3.14,0.785,3.14")
    proc = run_script(tmp_path, *widths, "--end-at-hit", "--fit", "lstd")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Found (2 trials" in proc.stdout and "--trials 500 --schedule both" in proc.stdout
    payload = json.loads((tmp_path / "train_batting.json").read_text())
    for run in payload["results"]["decreasing"]["runs"].values():
        assert run["rewarded_transitions"][-1] <= 4 * STEPS
    bad = run_script(tmp_path / "bad", "--basis-widths", "1,2,3")
    assert bad.returncode == 2 and "--basis-widths must be four positive numbers" in bad.stderr
