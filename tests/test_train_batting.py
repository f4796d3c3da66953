"""examples/train_batting.py end to end with tiny budgets: ``main(argv)`` in this process, and in
a process of its own where that is the point (``--help`` where no source can be read, SIGINT)."""

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import train_batting  # noqa: E402
from _processes import start_example, wait_for_episodes  # noqa: E402

from torch_api.experiment import read_results  # noqa: E402
from torch_api.runs.store import RunStore  # noqa: E402

TINY = ["--trials", "2", "--iterations", "2", "--episodes", "1", "--repeats", "2", "--seed", "3"]
TINY += ["--backend", "local", "--chunks", "1"]  # in this process (the default: two workers)
STEPS = 10  # N of the batting task


def run(out: Path, *extra: str) -> dict:
    """The script's ``main`` on the tiny budget, writing into ``out``."""
    return train_batting.main([*TINY, "--out-dir", str(out), *extra])


def refused(capsys, *argv: str, whole: bool = False) -> tuple[int, str]:
    """The exit status of a refused command line and the last line of its standard error (all
    of it with ``whole``; a ``SystemExit("error: ...")`` is printed by the interpreter, exit 1)."""
    with pytest.raises(SystemExit) as stop:
        train_batting.main(list(argv))
    code, err = stop.value.code, capsys.readouterr().err
    if isinstance(code, str):
        code, err = 1, err + code
    assert "Traceback" not in err
    return code, err if whole else err.strip().splitlines()[-1]


def numbers(out: Path) -> str:
    """Every per-trial number of a run (the CSV): what a resumed or chunked run must repeat."""
    return (out / "train_batting.csv").read_text()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("uninterrupted")
    run(out)
    return out


def test_a_tiny_run_writes_every_number_and_buys_its_schedule(uninterrupted):
    payload = json.loads((uninterrupted / "train_batting.json").read_text())
    assert set(payload["summary"]["decreasing"]["runs"]) == {"AL", "PL"}
    assert payload["args"]["repeats"] == 2 and payload["args"]["execution"]["chunks"] == 1
    results = read_results(uninterrupted / "train_batting.csv")
    for method in ("AL", "PL"):
        got = {(i, m): v for (_, me, i, m), v in results.items() if me == method}
        assert [got[i, "episodes_bought"] for i in (1, 2)] == [[1, 1], [1, 1]]
        assert [got[i, "rewarded_transitions"] for i in (1, 2)] == [[10, 10], [20, 20]]
        for i in (1, 2):
            assert all(math.isfinite(x) and x >= 0 for x in got[i, "performance"])
            assert got[i, "flattening"] == [1.0, 1.0]  # the paper's weights by default
        j = [got.get((i, f"j_mean_k{k}")) for i in (1, 2) for k in range(1, 5)]
        if method == "AL":  # Z·K·M·N reward-free transitions per trial and iteration
            assert all(len(v) == 2 and all(math.isfinite(x) for x in v) for v in j)
            assert [got[i, "reward_free_transitions"][0] for i in (1, 2)] == [80, 160]
        else:
            assert [got[i, "chosen"] for i in (1, 2)] == [[0, 0], [0, 0]] and j == [None] * 8
    rows = numbers(uninterrupted).splitlines()
    assert rows[0] == "schedule,method,seed,iteration,trial,measure,value"
    assert len(rows) - 1 == sum(len(v) for v in results.values())
    assert (uninterrupted / "fig10_performance.png").read_bytes()[:4] == b"\x89PNG"
    steps = payload["physics_steps"]
    runs = payload["summary"]["decreasing"]["runs"].values()
    assert steps["coarse"] > 0 and all(
        steps[k] == sum(r["physics_steps"][k] for r in runs) for k in steps
    )


def test_chunks_in_worker_processes_give_the_same_numbers(uninterrupted, tmp_path):
    """Two chunks of one trial each in two worker processes, their physics sampled by the
    audit: the numbers and the physics steps of one batch of two trials."""
    flags = ("--chunks", "2", "--backend", "processes", "--workers", "2", "--physics-audit", "0.5")
    payload = run(tmp_path, *flags)
    names = sorted(p.name for p in (tmp_path / "checkpoints").glob("*.db"))
    assert names == [f"decreasing_{m}_chunk{c}of2.db" for m in ("AL", "PL") for c in (1, 2)]
    assert numbers(tmp_path) == numbers(uninterrupted)
    expected = json.loads((uninterrupted / "train_batting.json").read_text())["physics_steps"]
    assert payload["physics_steps"] == expected
    assert payload["physics_audit"].sampled_steps("coarse") > 0


def test_the_beyond_the_paper_learner_runs(tmp_path):
    """Per-dimension widths, episodes that end at the hit (fewer transitions bought), LSTD-Q
    and ν chosen by importance-weighted cross-validation (recorded per trial and iteration)."""
    widths = ("--basis-widths", "0.785", "3.14", "0.785", "3.14")
    run(tmp_path, *widths, "--end-at-hit", "--fit", "lstd", "--flattening", "iwcv")
    bought = read_results(tmp_path / "train_batting.csv")
    for method in ("AL", "PL"):
        assert max(bought["decreasing", method, 2, "rewarded_transitions"]) <= 2 * STEPS
        for it in (1, 2):
            assert set(bought["decreasing", method, it, "flattening"]) <= {0, 0.25, 0.5, 0.75, 1}


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--lam", "-1"], "error: evaluation.lam must be >= 1e-10"),
        (["--trials", "0"], "error: trials.num_trials must be >= 1, got 0"),
        (["--iterations", "8"], "error: iterations must lie in 1..7, got 8"),
        (["--flattening", "1.5"], "error: evaluation.flattening must be 'iwcv' or lie in [0, 1]"),
        (["--basis-widths", "1", "2", "3", "-4"], "error: widths must be finite numbers > 0"),
        (["--physics-audit", "2"], "error: fraction must lie in [0, 1], got 2.0"),
        (["--trials", "2", "--chunks", "3"], "error: chunks must lie in 1..2 (the trials), got 3"),
        (["--device", "gpu"], "error: "),
        (["--device", "cuda:99"], "error: device 'cuda:99': torch sees"),
    ],
)
def test_a_bad_value_is_one_line_naming_it_exit_2(capsys, tmp_path, flags, message):
    code, err = refused(capsys, *flags, "--out-dir", str(tmp_path / "never"))
    assert code == 2 and err.startswith(message), err
    assert not (tmp_path / "never" / "checkpoints").exists()


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--repeats", "2.5"], "--repeats"),
        (["--schedule", "sometimes"], "--schedule"),
        (["--resume", "--overwrite"], "resume and overwrite exclude each other"),
        (["--backend", "local", "--workers", "2"], "workers applies to backend 'processes'"),
        (["--no-such-flag"], "--no-such-flag"),
    ],
)
def test_what_the_command_line_parser_refuses_exits_2_naming_it(capsys, flags, words):
    code, err = refused(capsys, *flags, whole=True)
    assert code == 2 and words in err, err


def test_an_unwritable_output_folder_is_one_line_before_any_work(capsys, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    code, err = refused(capsys, "--out-dir", str(blocker / "x"))
    assert code == 2 and err.startswith("error: ") and "a-file" in err, err


def test_a_folder_with_results_is_refused_without_resume_or_overwrite(capsys, uninterrupted):
    before = numbers(uninterrupted)
    code, err = refused(capsys, *TINY, "--out-dir", str(uninterrupted))
    assert code == 1 and err.startswith("error: runs are stored already") and "--overwrite" in err
    code, err = refused(capsys, *TINY, "--lam", "0.01", "--resume", "--out-dir", str(uninterrupted))
    assert code == 1 and "--lam 0.001, not 0.01" in err, err
    assert numbers(uninterrupted) == before


def test_help_answers_in_a_process_where_no_source_can_be_read(tmp_path):
    """Under ``python -m cProfile`` the script's classes have no source: tyro parses without
    the field docstrings; in this process ``--help`` shows them."""
    command = [sys.executable, "-m", "cProfile", "-o", str(tmp_path / "profile")]
    done = subprocess.run(
        [*command, str(ROOT / "examples" / "train_batting.py"), "--help"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert all(flag in done.stdout for flag in ("--out-dir", "--resume", "--lam", "--backend"))


def test_help_shows_every_field_s_docstring(capsys):
    with pytest.raises(SystemExit) as stop:
        train_batting.main(["--help"])
    shown = " ".join(capsys.readouterr().out.split())
    assert stop.value.code == 0 and "Z, J-values averaged into J'" in shown
    assert "--out-dir" in shown and "--execution.out-dir" not in shown  # flattened


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT of a process of its own")
def test_interrupted_run_resumes_to_the_same_numbers_and_buys_nothing_twice(
    uninterrupted, tmp_path, capsys
):
    """SIGINT mid-run: the commit in flight completes, one line, exit 130. A resume with other
    settings is refused naming the field; a resume gives the uninterrupted run's numbers, and
    resuming the finished run buys nothing again."""
    store = tmp_path / "checkpoints" / "decreasing_AL.db"
    proc = start_example("train_batting.py", *TINY, "--out-dir", str(tmp_path))
    wait_for_episodes(store, 1, proc)  # iteration 1's rewards committed
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGINT, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("interrupted at iteration ") and last.endswith("continue with --resume")
    assert "Traceback" not in err and not (tmp_path / "train_batting.json").exists()

    changed = (("--lam", "0.01", "evaluation.lam"), ("--repeats", "3", "selection.num_repeats"))
    for flag, value, field in changed:
        code, err = refused(capsys, *TINY, flag, value, "--resume", "--out-dir", str(tmp_path))
        assert code == 1 and err.startswith("error: the run stored in") and field in err, err

    run(tmp_path, "--resume")
    assert numbers(tmp_path) == numbers(uninterrupted)
    stored = {p.name: RunStore.read(p).num_episodes for p in store.parent.glob("*.db")}
    capsys.readouterr()
    run(tmp_path, "--resume")  # the finished run again: nothing to buy
    assert capsys.readouterr().out.count("at iteration 2/2") == 2
    assert {p.name: RunStore.read(p).num_episodes for p in store.parent.glob("*.db")} == stored
    assert numbers(tmp_path) == numbers(uninterrupted)


def test_the_paper_size_run_is_quoted_from_its_results_for_this_setting_only(
    uninterrupted, monkeypatch
):
    """The stored paper-size run (here the tiny run's JSON) is quoted for a run of the same
    settings whatever its trial count; a run of other settings gets the command instead."""
    monkeypatch.setattr(train_batting, "PAPER_RUN", uninterrupted / "train_batting.json")
    same = train_batting.Args(trials=500, seed=3, iterations=2, episodes=1, repeats=2)
    quoted = train_batting.paper_run(same, "decreasing")
    assert quoted.startswith("decreasing, 2 trials (") and "AL − PL" in quoted, quoted
    other = train_batting.paper_run(train_batting.Args(seed=3), "decreasing")
    assert other.endswith(train_batting.PAPER_SIZE)
