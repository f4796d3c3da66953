"""End-to-end runs of examples/train_batting.py with tiny budgets (subprocesses)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "examples" / "train_batting.py"
DRIVER = ROOT / "tests" / "batting_driver.py"  # the script, stopped abruptly at the K-th commit
TINY = ["--trials", "2", "--iterations", "2", "--episodes", "2", "--repeats", "2", "--seed", "3"]
STEPS = 10  # N of the batting task
MODES = ("active", "passive")
INTERRUPTED = 3  # exit code of the driver when it stopped the run

sys.path.insert(0, str(ROOT / "examples"))
from _harness import read_results  # noqa: E402
from _processes import children, running, start_example, wait_for_episodes  # noqa: E402


def run_script(out_dir: Path, *extra: str, stop_after: int = 0) -> subprocess.CompletedProcess:
    """The script with ``extra`` flags; ``stop_after`` > 0: ended after that many commits."""
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    command = [str(DRIVER), str(stop_after)] if stop_after else [str(SCRIPT)]
    return subprocess.run(
        [sys.executable, *command, *TINY, "--out-dir", str(out_dir), *extra],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def numbers(out_dir: Path) -> str:
    """Everything a resumed run must reproduce exactly: every per-trial number (the CSV)."""
    return (out_dir / "train_batting.csv").read_text()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("uninterrupted")
    return out, run_script(out)


def test_outputs_exist_and_rewards_match_schedule(uninterrupted):
    out, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "paired t-test AL vs PL at iteration 2" in proc.stdout
    payload = json.loads((out / "train_batting.json").read_text())
    assert set(payload["summary"]["decreasing"]["runs"]) == {"AL", "PL"}
    results = read_results(out / "train_batting.csv")
    for method in ("AL", "PL"):
        run = {(i, m): v for (s, me, i, m), v in results.items() if me == method}
        assert [run[i, "episodes_bought"] for i in (1, 2)] == [[2, 2], [2, 2]]
        # per trial, cumulative
        assert [run[i, "rewarded_transitions"] for i in (1, 2)] == [[20, 20], [40, 40]]
        for i in (1, 2):
            assert len(run[i, "performance"]) == 2
            assert all(math.isfinite(x) and x >= 0 for x in run[i, "performance"])
            assert run[i, "flattening"] == [1.0, 1.0]  # the paper's weights by default
        j = [run.get((i, f"j_mean_k{k}")) for i in (1, 2) for k in range(1, 5)]
        if method == "AL":
            assert all(len(v) == 2 and all(math.isfinite(x) and x >= 0 for x in v) for v in j)
            free = [run[i, "reward_free_transitions"][0] for i in (1, 2)]
            assert free == [2 * 4 * 2 * STEPS, 2 * 2 * 4 * 2 * STEPS]
        else:
            assert [run[i, "chosen"] for i in (1, 2)] == [[0, 0], [0, 0]] and j == [None] * 8
    rows = (out / "train_batting.csv").read_text().splitlines()
    assert rows[0] == "schedule,method,seed,iteration,trial,measure,value"
    assert len(rows) - 1 == sum(len(v) for v in results.values())
    assert (out / "fig10_performance.png").stat().st_size > 1000


def test_interrupted_and_resumed_run_matches(uninterrupted, tmp_path):
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Stop right after the AL run bought its second batch (commits: selection, episodes,
    # iteration; selection, episodes).
    first = run_script(tmp_path, stop_after=5)
    assert first.returncode == INTERRUPTED, first.stderr[-3000:]
    assert not (tmp_path / "train_batting.json").exists()
    # Resume: AL fits iteration 2 without buying again (1), PL selects (2), buys (3) and fits
    # (4), stop.
    second = run_script(tmp_path, "--resume", stop_after=4)
    assert second.returncode == INTERRUPTED, second.stderr[-3000:]
    assert "decreasing_active.db at iteration 1/2" in second.stdout
    # Resume again: AL is complete and is not recomputed; PL continues from iteration 1.
    third = run_script(tmp_path, "--resume")
    assert third.returncode == 0, third.stderr[-3000:]
    assert "decreasing_active.db at iteration 2/2" in third.stdout
    assert "decreasing_passive.db at iteration 1/2" in third.stdout
    expected = numbers(reference)
    resumed = numbers(tmp_path)
    assert resumed == expected
    bought = read_results(tmp_path / "train_batting.csv")  # no rewarded episode bought twice
    for method in ("AL", "PL"):
        assert bought["decreasing", method, 2, "rewarded_transitions"] == [(2 + 2) * STEPS] * 2


def test_chunked_run_gives_the_same_numbers(uninterrupted, tmp_path):
    """Two chunks of one trial each: per-chunk checkpoints, the numbers of one batch of two."""
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    chunked = run_script(tmp_path, "--chunks", "2")
    assert chunked.returncode == 0, chunked.stderr[-3000:]
    names = sorted(p.name for p in (tmp_path / "checkpoints").glob("*.db"))
    expected_names = [f"decreasing_{m}_chunk{c}of2.db" for m in MODES for c in (1, 2)]
    assert names == expected_names
    expected = numbers(reference)
    assert numbers(tmp_path) == expected


def test_chunked_run_resumes_per_chunk(uninterrupted, tmp_path):
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Commits: AL chunk 1 selects, buys, fits, selects, buys (5); stop. Resume: chunk 1
    # continues, chunk 2 anew.
    first = run_script(tmp_path, "--chunks", "2", stop_after=5)
    assert first.returncode == INTERRUPTED, first.stderr[-3000:]
    second = run_script(tmp_path, "--chunks", "2", "--resume")
    assert second.returncode == 0, second.stderr[-3000:]
    assert "decreasing_active_chunk1of2.db at iteration 1/2" in second.stdout
    assert "nothing stored in" in second.stdout  # chunk 2 had not started: it starts fresh
    assert "decreasing_active_chunk2of2.db: starting it fresh" in second.stdout
    expected = numbers(reference)
    assert numbers(tmp_path) == expected


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
    assert numbers(tmp_path) == numbers(reference)
    assert payload["physics_steps"] == expected["physics_steps"]
    runs = payload["summary"]["decreasing"]["runs"].values()
    for kind in ("coarse", "fine"):
        assert payload["physics_steps"][kind] == sum(r["physics_steps"][kind] for r in runs)
    assert payload["physics_steps"]["coarse"] > 0


def test_a_folder_with_stored_runs_is_refused_without_resume_or_overwrite(tmp_path):
    first = run_script(tmp_path, stop_after=2)  # iteration 1 bought
    assert first.returncode == INTERRUPTED
    stored = (tmp_path / "checkpoints" / "decreasing_active.db").read_bytes()
    again = run_script(tmp_path)
    assert again.returncode == 1
    assert "runs are stored already" in again.stderr and "--resume" in again.stderr
    assert len(again.stderr.strip().splitlines()) == 1
    assert (tmp_path / "checkpoints" / "decreasing_active.db").read_bytes() == stored
    both = run_script(tmp_path, "--resume", "--overwrite")
    assert both.returncode == 2 and "exclude each other" in both.stderr
    fresh = run_script(tmp_path, "--overwrite", stop_after=1)  # a selection
    assert fresh.returncode == INTERRUPTED, fresh.stderr[-3000:]
    from torch_api.runs.store import RunStore

    assert RunStore.read(tmp_path / "checkpoints" / "decreasing_active.db").episodes == {}


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc to find the workers")
def test_sigkill_then_sigterm_then_resume_and_workers_die_with_a_killed_parent(
    uninterrupted, tmp_path
):
    """A SIGKILL mid-run, then a resume stopped by SIGTERM (the commit in flight completes, one
    line, exit 143), then a resume to the end: the uninterrupted run's numbers. SIGKILL of the
    parent with --backend processes: its workers are gone within seconds."""
    reference, proc = uninterrupted
    assert proc.returncode == 0, proc.stderr[-3000:]
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    store = tmp_path / "checkpoints" / "decreasing_active.db"

    def start(*extra):
        return start_example("train_batting.py", *TINY, "--out-dir", str(tmp_path), *extra)

    def once_storing(proc, seconds):
        """Until ``proc`` holds the run's lock (its pid is in the lock file), then seconds."""
        lock = Path(f"{store}.lock")
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if lock.exists() and f"pid {proc.pid} " in lock.read_text():
                break
            time.sleep(0.05)
        time.sleep(seconds)

    killed = start()
    wait_for_episodes(store, 1, killed)  # iteration 1's rewards committed, iteration 2 to come
    killed.kill()
    killed.communicate(timeout=60)
    stopped = start("--resume")
    # At once: the tiny resumed run can end within a second on an idle machine, and a SIGTERM
    # after main() has restored the default handlers would kill it silently (exit -15).
    once_storing(stopped, 0.1)
    stopped.send_signal(signal.SIGTERM)
    _, err = stopped.communicate(timeout=120)
    assert stopped.returncode == 128 + signal.SIGTERM, err[-3000:]
    last = err.strip().splitlines()[-1]  # (after the progress bars)
    assert "Traceback" not in err and last.startswith("interrupted at iteration "), err[-3000:]
    assert last.endswith(f"episodes stored in {tmp_path / 'checkpoints'}; continue with --resume")
    done = run_script(tmp_path, "--resume")
    assert done.returncode == 0, done.stderr[-3000:]
    expected = numbers(reference)
    assert numbers(tmp_path) == expected

    out = tmp_path / "processes"
    parent = subprocess.Popen(
        [
            sys.executable,
            str(SCRIPT),
            *TINY,
            "--out-dir",
            str(out),
            "--backend",
            "processes",
            "--workers",
            "2",
            "--chunks",
            "2",
        ],
        env=env,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while not list((out / "checkpoints").glob("*.db")) and time.monotonic() < deadline:
        time.sleep(0.05)
    workers = [k for k in children(parent.pid) if running(k)]
    assert workers, "no worker processes found"
    parent.kill()
    parent.wait(timeout=30)
    deadline = time.monotonic() + 60  # (a worker still importing torch dies once it is done)
    while any(running(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(running(w) for w in workers), "workers outlived their killed parent"


def test_beyond_the_paper_variant_runs_and_bad_widths_are_refused(tmp_path):
    """Scaled basis, episodes that end at the hit (fewer transitions bought), LSTD-Q and ν
    chosen by IWCV (recorded per trial and iteration in the CSV)."""
    widths = ("--basis-widths", "0.785,3.14,0.785,3.14")
    proc = run_script(tmp_path, *widths, "--end-at-hit", "--fit", "lstd", "--flattening", "iwcv")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Found (2 trials" in proc.stdout and "--trials 500 --schedule both" in proc.stdout
    assert "no measured ceiling for this basis and learner" in proc.stdout
    assert "paper-basis ceiling" not in proc.stdout  # measured for the paper's learner only
    bought = read_results(tmp_path / "train_batting.csv")
    for method in ("AL", "PL"):
        assert max(bought["decreasing", method, 2, "rewarded_transitions"]) <= 4 * STEPS
        for it in (1, 2):
            assert set(bought["decreasing", method, it, "flattening"]) <= {0, 0.25, 0.5, 0.75, 1}
    bad = run_script(tmp_path / "bad", "--basis-widths", "1,2,3")
    assert bad.returncode == 2 and "--basis-widths must be four positive numbers" in bad.stderr
    bad = run_script(tmp_path / "bad", "--flattening", "1.5")
    assert bad.returncode == 2 and "--flattening must lie in [0, 1], got 1.5" in bad.stderr
