"""The example scripts end to end, each in a subprocess with a tiny budget (CleanRL-style).

Each run must finish, and its JSON / CSV / PNG outputs must exist and hold finite numbers.
"""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
from _harness import COLUMNS, read_results  # noqa: E402
from _processes import (  # noqa: E402  (tests/ is on sys.path)
    run_example,
    start_example,
    wait_for_episodes,
)

pytestmark = pytest.mark.slow


_run = run_example  # tiny budgets, one thread (much faster on a busy machine)


def _numbers(value):
    """Every number inside a JSON value."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return
    if isinstance(value, int | float):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _numbers(v)
    elif isinstance(value, list):
        for v in value:
            yield from _numbers(v)


def _check_json(path: Path) -> dict:
    payload = json.loads(path.read_text())
    numbers = list(_numbers(payload["summary"] if "summary" in payload else payload["results"]))
    assert numbers and all(math.isfinite(x) for x in numbers)
    return payload


def _check_png(path: Path) -> None:
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_chain_walk_one_step(tmp_path):
    _run("chain_walk_one_step.py", "--trials", "2", "--out-dir", str(tmp_path))
    payload = _check_json(tmp_path / "one_step.json")
    assert len(payload["results"]) == 3
    for name in ("fig3_true_error.png", "fig4_j_estimate.png", "fig5_obtained_error.png"):
        _check_png(tmp_path / name)


def _check_csv(path: Path) -> dict:
    """The long CSV of an experiment: its header, finite values; read back."""
    with path.open() as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == COLUMNS
    assert all(math.isfinite(float(row[-1])) for row in rows[1:])
    return read_results(path)


def test_chain_walk_api(tmp_path):
    out = _run(
        "chain_walk_api.py",
        *("--trials", "2", "--iterations", "2", "--test-episodes", "3", "--test-steps", "10"),
        *("--out-dir", str(tmp_path), "--logger", "csv"),
    )
    assert "Paired two-tailed t-test" in out
    payload = _check_json(tmp_path / "chain_walk_api.json")
    results = _check_csv(tmp_path / "chain_walk_api.csv")
    for schedule in ("decreasing", "fixed"):
        assert set(payload["summary"][schedule]["runs"]) == {"AL", "PL"}
        iterations = {i for (s, m, i, _) in results if (s, m) == (schedule, "AL")}
        assert iterations == {0, 1, 2}
        bought = sum(payload["summary"][schedule]["schedule"]) * 10
        assert results[schedule, "AL", 2, "rewarded_transitions"] == [bought, bought]
        assert results[schedule, "PL", 2, "chosen"] == [0, 0]
        for method in ("AL", "PL"):
            for i in (0, 1, 2):
                for key in ("test_return", "exact_return", "percent_optimal"):
                    assert len(results[schedule, method, i, key]) == 2  # one value per trial
    _check_png(tmp_path / "fig8_performance.png")
    # --logger csv: TorchRL's CSVLogger, one file per curve, one "step,value" row per iteration
    curves = tmp_path / "logs" / "chain_walk_api" / "scalars"
    curve = curves / "fixed" / "PL" / "percent_optimal.csv"
    steps = [line.split(",")[0] for line in curve.read_text().splitlines()]
    assert steps == ["0", "1", "2"]
    # the fit's flattening ν and effective sample size: in the CSV and the logger's curves
    assert results["fixed", "AL", 2, "flattening"] == [1.0, 1.0]
    assert len(results["fixed", "AL", 2, "effective_sample_size"]) == 2
    assert (curves / "fixed" / "AL" / "effective_sample_size.csv").exists()


GYM_TINY = ("--trials", "2", "--schedule", "2,2", "--steps", "10", "--repeats", "2")
GYM_TINY += ("--test-episodes", "2", "--test-steps", "20")


@pytest.fixture(scope="module")
def gym_drop_in_run(tmp_path_factory) -> tuple[Path, str]:
    """``gym_drop_in.py`` at a tiny budget, uninterrupted, asked to ``--resume`` a folder that
    holds no runs yet: its folder and its output."""
    out = tmp_path_factory.mktemp("gym_drop_in")
    return out, _run("gym_drop_in.py", *GYM_TINY, "--out-dir", str(out), "--resume")


def test_gym_drop_in(gym_drop_in_run):
    tmp_path, _ = gym_drop_in_run
    payload = _check_json(tmp_path / "gym_drop_in.json")
    runs = payload["summary"]["custom"]["runs"]
    assert set(runs) == {"AL", "PL"}
    for run in runs.values():
        check = run["data_check"]
        assert check["episodes"] == 2 * 4 and check["transitions"] > 0
    results = _check_csv(tmp_path / "gym_drop_in.csv")
    balanced = [v for (_, _, _, m), v in results.items() if m == "steps_balanced"]
    assert len(balanced) == 2 * 3 and all(len(v) == 2 for v in balanced)  # methods × l = 0..2
    _check_png(tmp_path / "performance.png")


def test_batting_reference(tmp_path):
    out = tmp_path / "reference.json"
    _run("batting_reference.py", "--episodes", "16", "--out", str(out))
    payload = json.loads(out.read_text())
    assert len(payload["reference_optimum"]["best_sequence"]) == 10
    assert payload["random_policy"]["episodes"] == 16


def test_plot_batting_episode(tmp_path):
    out = tmp_path / "episode.png"
    stdout = _run("plot_batting_episode.py", "--sequence", "0011111000", "--out", str(out))
    assert "carry 13.74 m" in stdout
    _check_png(out)


# -- chunks of trials (torch_api/runs/dispatch.py): the same numbers however trials are split ----

CHUNK_RUN = ("--trials", "3", "--iterations", "2", "--schedule", "decreasing")
CHUNK_RUN += ("--test-episodes", "3", "--test-steps", "10")


def _without_times(value):
    """A JSON value without its wall times and arguments (what differs between chunkings)."""
    if isinstance(value, dict):
        skip = ("seconds", "wall_seconds", "args")
        return {k: _without_times(v) for k, v in value.items() if k not in skip}
    if isinstance(value, list):
        return [_without_times(v) for v in value]
    return value


def _outputs(out: Path, name: str = "chain_walk_api") -> tuple[str, dict]:
    """Every number of a run (its CSV) and its JSON summary, wall times and arguments left out."""
    payload = json.loads((out / f"{name}.json").read_text())
    return (out / f"{name}.csv").read_text(), _without_times(payload)


@pytest.fixture(scope="module")
def chain_walk_one_chunk(tmp_path_factory) -> tuple[str, dict]:
    out = tmp_path_factory.mktemp("one_chunk")
    _run("chain_walk_api.py", *CHUNK_RUN, "--chunks", "1", "--out-dir", str(out))
    return _outputs(out)


def test_chain_walk_api_chunks_give_the_same_numbers(chain_walk_one_chunk, tmp_path):
    _run("chain_walk_api.py", *CHUNK_RUN, "--chunks", "3", "--out-dir", str(tmp_path))
    assert _outputs(tmp_path) == chain_walk_one_chunk
    chosen = read_results(tmp_path / "chain_walk_api.csv")["decreasing", "AL", 2, "chosen"]
    assert len(chosen) == 3


def test_chain_walk_api_in_worker_processes_gives_the_local_numbers(chain_walk_one_chunk, tmp_path):
    _run(
        "chain_walk_api.py",
        *CHUNK_RUN,
        *("--backend", "processes", "--workers", "2", "--chunks", "2", "--out-dir", str(tmp_path)),
    )
    assert _outputs(tmp_path) == chain_walk_one_chunk


HAVE_RAY = importlib.util.find_spec("ray") is not None


@pytest.mark.skipif(not HAVE_RAY, reason="the ray extra is not installed (pip install ray)")
def test_chain_walk_api_on_ray_gives_the_local_numbers(chain_walk_one_chunk, tmp_path):
    out = _run(
        "chain_walk_api.py",
        *CHUNK_RUN,
        *("--backend", "ray", "--chunks", "2", "--ray-cpus", "2", "--out-dir", str(tmp_path)),
    )
    assert "4 chunks" in out  # (AL, PL) × 2 chunks, as Ray tasks
    assert _outputs(tmp_path) == chain_walk_one_chunk
    _check_png(tmp_path / "fig8_performance.png")


PIPELINE_TINY = ("--iterations", "2", "--first-episodes", "3", "--episodes", "2")
PIPELINE_TINY += ("--reward-free-episodes", "1", "--repeats", "1", "--steps", "20")
PIPELINE_TINY += ("--test-episodes", "2", "--test-steps", "30")


@pytest.fixture(scope="module")
def pipeline_two_seeds(tmp_path_factory) -> dict:
    """The showcase's defaults (CartPole, AL and PL) at a tiny budget over seeds 0 and 1, in
    one process: its JSON."""
    out = tmp_path_factory.mktemp("pipeline_two_seeds")
    _run("torchrl_pipeline.py", *PIPELINE_TINY, "--seeds", "2", "--out-dir", str(out))
    _check_png(out / "torchrl_pipeline.png")
    return json.loads((out / "torchrl_pipeline.json").read_text())


def test_torchrl_pipeline_runs_cartpole_by_default_al_and_pl_paired(pipeline_two_seeds):
    payload = pipeline_two_seeds
    args = payload["args"]
    assert args["env"] == "CartPole-v1" and args["basis"] == "quadratic" and args["fit"] == "lstd"
    assert set(payload["runs"]) == {"AL", "PL"} and set(payload["runs"]["AL"]) == {"0", "1"}
    for mode in ("AL", "PL"):
        for run in payload["runs"][mode].values():
            history = run["history"]
            assert [h["iteration"] for h in history] == [1, 2]
            assert all(h["flattening"] == 0.0 and h["ess_percent"] == 100.0 for h in history)
            assert 5 <= history[-1]["rewarded_transitions"] <= 5 * 20  # early ends: fewer
            assert all(1 <= h["greedy_test_return"] <= 30 for h in history)
            assert all(len(h["j_mean"]) == (4 if mode == "AL" else 0) for h in history)
    assert payload["summary"]["PL"]["seeds"] == [0, 1] and payload["t_test"] is not None
    assert all(math.isfinite(x) for x in _numbers(payload["runs"]))


def test_torchrl_pipeline_active_runs_are_reproducible(tmp_path):
    """The same seed twice: AL's reward-free episodes (so J' and the choice) are the same.
    Before, the selector's env of Z·K·M rows was never seeded (the example seeded Z·M)."""
    flags = ("--modes", "AL", "--seeds", "1", "--iterations", "2", "--first-episodes", "3")
    flags += ("--episodes", "2", "--reward-free-episodes", "2", "--repeats", "2")
    flags += ("--steps", "40", "--test-episodes", "1", "--test-steps", "20")
    runs = []
    for name in ("first", "second"):
        _run("torchrl_pipeline.py", *flags, "--out-dir", str(tmp_path / name))
        payload = json.loads((tmp_path / name / "torchrl_pipeline.json").read_text())
        history = payload["runs"]["AL"]["0"]["history"]
        runs.append([(h["j_mean"], h["reward_free_transitions"], h["chosen"]) for h in history])
    assert runs[0] == runs[1]


PIPELINE_RUN = ("--env", "MountainCar-v0", "--modes", "AL", "--seeds", "1")
PIPELINE_RUN += ("--first-sampler", "actor", "--iterations", "3", "--first-episodes", "2")
PIPELINE_RUN += ("--episodes", "2", "--reward-free-episodes", "1")
PIPELINE_RUN += ("--repeats", "1", "--steps", "20", "--test-episodes", "2")


@pytest.fixture(scope="module")
def mountain_car_run(tmp_path_factory) -> dict:
    """MountainCar, AL alone, iteration 1 bought by the user's actor, in one uninterrupted
    process: its JSON."""
    out = tmp_path_factory.mktemp("mountain_car")
    _run("torchrl_pipeline.py", *PIPELINE_RUN, "--out-dir", str(out))
    return json.loads((out / "torchrl_pipeline.json").read_text())


def test_torchrl_pipeline_mountain_car_with_the_actor_s_warm_start(mountain_car_run):
    payload = mountain_car_run
    assert payload["args"]["fit"] == "brm" and payload["args"]["test_steps"] == 200
    history = payload["runs"]["AL"]["0"]["history"]
    assert history[0]["chosen"] == "the actor's warm start" and history[0]["j_mean"] == []
    assert len(history[1]["j_mean"]) == 5  # four θ policies and the actor
    assert history[-1]["rewarded_transitions"] == 3 * 2 * 20  # MountainCar: no early end here
    assert payload["runs"]["PL"] == {} and payload["t_test"] is None
    assert all(math.isfinite(x) for x in _numbers(payload["runs"]))


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (("--flattening", "2"), "--flattening must lie in [0, 1], got 2.0"),
        (("--flattening", "half"), "--flattening must be a number in [0, 1], iwcv or auto"),
        (("--env", "Pong-v5"), "--env"),
        (("--modes", "PL,AL"), "--modes"),
    ],
)
def test_torchrl_pipeline_refuses_bad_flags_in_one_line(flags, message, tmp_path):
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "torchrl_pipeline.py"), *flags],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr


# -- durable runs: a killed or interrupted example resumes to the uninterrupted numbers ----------


def test_chain_walk_api_killed_then_resumed_gives_the_same_numbers(chain_walk_one_chunk, tmp_path):
    args = (*CHUNK_RUN, "--chunks", "1", "--out-dir", str(tmp_path))
    proc = start_example("chain_walk_api.py", *args)
    wait_for_episodes(tmp_path / "checkpoints" / "decreasing_AL.db", 5, proc)  # iteration 1
    proc.kill()
    proc.communicate(timeout=60)
    again = start_example("chain_walk_api.py", *args)
    _, err = again.communicate(timeout=120)
    assert again.returncode == 1 and "add --resume to continue them or --overwrite" in err
    out = _run("chain_walk_api.py", *args, "--resume")
    assert "resumed" in out and "decreasing_AL.db at iteration" in out
    assert _outputs(tmp_path) == chain_walk_one_chunk


def test_gym_drop_in_interrupted_says_so_in_one_line_and_resumes(gym_drop_in_run, tmp_path):
    reference, fresh = gym_drop_in_run
    assert "starting it fresh" in fresh
    expected = _outputs(reference, "gym_drop_in")
    args = (*GYM_TINY, "--out-dir", str(tmp_path))
    proc = start_example("gym_drop_in.py", *args)
    wait_for_episodes(tmp_path / "checkpoints" / "active.db", 2, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    last = err.strip().splitlines()[-1]  # (after the progress bars)
    assert "Traceback" not in err and last.startswith("interrupted at iteration "), err[-3000:]
    assert last.endswith(f"stored in {tmp_path / 'checkpoints'}; continue with --resume")
    _run("gym_drop_in.py", *args, "--resume")
    assert _outputs(tmp_path, "gym_drop_in") == expected


def test_merged_pipeline_runs_equal_one_run_over_their_seeds(pipeline_two_seeds, tmp_path):
    """The showcase's seeds run as separate processes (AL beside PL, seeds split), merged by
    ``merge_pipeline_runs.py``: the summary, the paired t-test and every run's numbers are
    those of one process over all the seeds; another setting or a conflicting seed is
    refused."""
    import merge_pipeline_runs

    parts = {"al": ("--modes", "AL", "--seeds", "2"), "pl0": ("--modes", "PL", "--seeds", "1")}
    parts["pl1"] = ("--modes", "PL", "--seeds", "1", "--seed", "1")
    for name, flags in parts.items():
        _run("torchrl_pipeline.py", *PIPELINE_TINY, *flags, "--out-dir", str(tmp_path / name))
    dirs = ",".join(str(tmp_path / name) for name in parts)
    merge_pipeline_runs.main(["--runs", dirs, "--out-dir", str(tmp_path / "merged")])
    one = pipeline_two_seeds
    merged = json.loads((tmp_path / "merged" / "torchrl_pipeline.json").read_text())
    assert merged["summary"]["AL"]["seeds"] == [0, 1] == merged["summary"]["PL"]["seeds"]
    assert _without_times(merged) == _without_times(one)  # runs, summary, t-test, the actor
    _check_png(tmp_path / "merged" / "torchrl_pipeline.png")

    other = json.loads((tmp_path / "pl1" / "torchrl_pipeline.json").read_text())
    other["args"]["gamma"] = 0.99
    with pytest.raises(ValueError, match=r"another setting: \['gamma'\]"):
        merge_pipeline_runs.merge([one, other])
    other = json.loads((tmp_path / "pl1" / "torchrl_pipeline.json").read_text())
    other["runs"]["PL"]["1"]["history"][-1]["greedy_test_return"] += 1.0
    with pytest.raises(ValueError, match="PL seed 1 appears twice with different numbers"):
        merge_pipeline_runs.merge([one, other])


def test_torchrl_pipeline_killed_then_resumed_gives_the_same_numbers(mountain_car_run, tmp_path):
    """The user's Collector and ProbabilisticActor, SIGKILLed once a bought episode is stored:
    --resume keeps every stored reward (buys only the rest) and ends with the numbers of an
    uninterrupted run; a second run into the folder without --resume/--overwrite is refused."""
    from torch_api.runs.store import RunStore

    expected = _without_times(mountain_car_run)
    args = (*PIPELINE_RUN, "--out-dir", str(tmp_path))
    store = tmp_path / "checkpoints" / "AL_seed0.db"
    proc = start_example("torchrl_pipeline.py", *args)
    wait_for_episodes(store, 2, proc)  # iteration 1's rewarded episodes are committed
    proc.kill()
    proc.communicate(timeout=60)
    kept = RunStore.read(store).num_episodes
    assert 2 <= kept < 3 * 2  # killed before its end
    again = start_example("torchrl_pipeline.py", *args)
    _, err = again.communicate(timeout=120)
    assert again.returncode == 1 and "Traceback" not in err
    assert err.strip().splitlines() == [
        f"error: runs are stored already ({store}); add --resume to continue them or "
        "--overwrite to discard them"
    ]
    out = _run("torchrl_pipeline.py", *args, "--resume")
    assert f"resumed {store} at iteration" in out
    assert f"AL seed 0: bought {3 * 2 - kept} rewarded episodes in this run" in out  # none twice
    payload = json.loads((tmp_path / "torchrl_pipeline.json").read_text())
    for run in (payload, expected):  # what this process bought differs by design
        run["runs"]["AL"]["0"].pop("bought")
    assert _without_times(payload) == expected


def test_the_long_layout_holds_every_number_once_and_reads_back(tmp_path):
    """``_harness``: chunks concatenated along the trial axis, one CSV row per number (a number
    of the iteration repeated per trial, J' per candidate), read back as written."""
    from _harness import Experiment, concatenate, paired_test, write_results

    def part(returns, j, seconds):
        row = {"iteration": 1, "rewarded_transitions": 30, "test_return": returns, "j_mean": j}
        return {"seed": 7, "seconds": seconds, "iterations": [row | {"seconds": seconds}]}

    al = concatenate(
        [part([1.5, 2.0], [[0.1, 0.2], [0.3, 0.4]], 1.0), part([3.0], [[0.5, 0.6]], 2.0)]
    )
    assert al["seconds"] == 3.0 and al["iterations"][0]["test_return"] == [1.5, 2.0, 3.0]
    pl = part([1.5, 2.0, 3.0], None, 1.0)
    results = {"fixed": {"schedule": [3], "runs": {"AL": al, "PL": pl}, "t_tests": {}}}
    results["fixed"]["t_tests"]["test_return"] = paired_test([1.5, 2.0, 3.0], [1.5, 2.0, 3.0])
    assert results["fixed"]["t_tests"]["test_return"]["t"] is None  # no spread: undefined

    @dataclasses.dataclass
    class Args:  # what write_results reads of the script's arguments
        out_dir: str
        logger: str = "none"

    experiment = Experiment(
        name="x", schedules={"fixed": [3]}, run_chunk=print, t_tests=(), report=print
    )
    write_results(Args(str(tmp_path)), experiment, results, wall=0.5)
    table = read_results(tmp_path / "x.csv")
    assert table["fixed", "AL", 1, "test_return"] == [1.5, 2.0, 3.0]
    assert table["fixed", "AL", 1, "rewarded_transitions"] == [30, 30, 30]
    assert table["fixed", "AL", 1, "j_mean_k2"] == [0.2, 0.4, 0.6]
    assert ("fixed", "PL", 1, "j_mean_k1") not in table  # PL has no J'
    rows = (tmp_path / "x.csv").read_text().splitlines()
    assert rows[0] == ",".join(COLUMNS) and len(rows) == 1 + 3 * (2 + 2) + 3 * 2
    assert "seconds" not in (tmp_path / "x.csv").read_text()  # wall times: in the JSON only


def test_the_csv_lines_are_what_csv_writer_writes():
    """``csv_lines`` formats the rows itself (faster than ``csv.writer``): its bytes equal
    ``csv.writer``'s of the same rows, and ``csv.reader`` reads back every field, texts that
    need quoting, bools and missing entries of a vector included."""
    import csv
    import io

    from _results import csv_lines

    row = {
        "iteration": 2,
        "seconds": 0.1,
        "test_return": [0.1, 1e-300, -2.5e17],
        "chosen": [1, None, 3],
        "rule": ['eps, "0.1"', "line\nbreak", "plain"],
        "flag": True,
        "j_mean": [[0.25, None], None, [1.0, 2.0]],
    }
    results = {"a,b": {"runs": {"AL": {"seed": -3, "iterations": [row]}}}}
    expected = [list(COLUMNS)]
    for t in range(3):
        head = ["a,b", "AL", "-3", "2", str(t)]
        for key in ("test_return", "chosen", "rule", "flag", "j_mean"):
            value = row[key][t] if isinstance(row[key], list) else row[key]
            if isinstance(value, list):
                for k, x in enumerate(value, 1):
                    expected.append([*head, f"{key}_k{k}", "" if x is None else str(x)])
            elif value is not None:
                expected.append([*head, key, str(value)])
    text = "".join(csv_lines(results))
    assert list(csv.reader(io.StringIO(text, newline=""))) == expected
    handle = io.StringIO(newline="")
    csv.writer(handle).writerows(expected)
    assert text == handle.getvalue()


def test_the_paired_test_is_scipys_ttest_rel():
    """``paired_test`` (Student's t from scipy.special, lighter to import than scipy.stats)
    gives ``scipy.stats.ttest_rel``'s statistic and two-tailed p-value, to 1e-12."""
    import numpy as np
    import scipy.stats
    from _results import paired_test

    rng = np.random.default_rng(0)
    for n in (2, 3, 32, 500, 1000):
        a = rng.normal(size=n)
        p = a + rng.normal(size=n) * 0.3 + rng.normal() * 0.1
        ours, theirs = paired_test(a, p), scipy.stats.ttest_rel(a, p)
        assert ours["t"] == pytest.approx(theirs.statistic, rel=1e-12)
        assert ours["p"] == pytest.approx(theirs.pvalue, rel=1e-12, abs=1e-300)
    assert paired_test([1.0, 2.0], [0.5, 1.5])["t"] is None  # no spread in the differences
