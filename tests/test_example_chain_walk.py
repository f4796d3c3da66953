"""The chain-walk examples (Figures 3-5 and Figure 8) end to end with tiny budgets.

``main(argv)`` runs in this process wherever a process of its own is not the point; two tests
start one: ``--help`` (a real start, nothing done) and a run interrupted by SIGINT, resumed.
"""

from __future__ import annotations

import ast
import csv
import gc
import importlib.util
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import torch_api.loop.iteration
from torch_api.experiment import COLUMNS, read_results
from torch_api.runs.store import RunStore

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
sys.path.insert(0, str(EXAMPLES))
import chain_walk_api  # noqa: E402
import chain_walk_one_step  # noqa: E402
from _processes import start_example, wait_for_episodes  # noqa: E402  (tests/ is on sys.path)

TINY = ("--trials", "2", "--iterations", "2", "--test-episodes", "2", "--test-steps", "5")
TINY += ("--backend", "local")
# one schedule, 4 iterations: long enough to be interrupted after the first
CHUNK_RUN = ("--trials", "2", "--schedule", "decreasing", "--iterations", "4")
CHUNK_RUN += ("--test-episodes", "2", "--test-steps", "5")


def _without_times(value):
    """A JSON value without its wall times (what differs between equal runs)."""
    if isinstance(value, dict):
        return {k: _without_times(v) for k, v in value.items() if not k.endswith("seconds")}
    return [_without_times(v) for v in value] if isinstance(value, list) else value


def _outputs(out: Path) -> tuple[str, dict]:
    """Every number of a run (its CSV) and its JSON summary without its times."""
    payload = json.loads((out / "chain_walk_api.json").read_text())
    return (out / "chain_walk_api.csv").read_text(), _without_times(payload["summary"])


def _is_png(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _exit_code(main, argv) -> int:
    """The exit status of ``main(argv)``; a message given to ``SystemExit`` goes to stderr with
    status 1, as Python does it at the top of a script."""
    with pytest.raises(SystemExit) as done:
        main(list(argv))
    if isinstance(done.value.code, str):
        print(done.value.code, file=sys.stderr)
        return 1
    return done.value.code


def _run_as_command(script: str, argv, monkeypatch) -> None:
    """``python -m cProfile examples/<script> argv``, here: the script runs as ``__main__`` in
    globals of its own, importable under no name (its annotations must not need resolving)."""
    path = EXAMPLES / script
    monkeypatch.setattr(sys, "argv", [str(path), *argv])
    code = compile(path.read_text(), str(path), "exec", dont_inherit=True)  # (as cProfile does)
    exec(code, {"__name__": "__main__", "__file__": str(path)})


@pytest.fixture(scope="module")
def one_chunk(tmp_path_factory) -> Path:
    """The folder of an uninterrupted run of CHUNK_RUN, one chunk, here."""
    out = tmp_path_factory.mktemp("one_chunk")
    chain_walk_api.main([*CHUNK_RUN, "--backend", "local", "--out-dir", str(out)])
    return out


# -- Figure 8 ---------------------------------------------------------------------------------


def test_figure8_writes_every_number_its_figure_and_its_curves(tmp_path, capsys, monkeypatch):
    argv = [*TINY, "--out-dir", str(tmp_path), "--logger", "csv"]
    _run_as_command("chain_walk_api.py", argv, monkeypatch)
    assert "Paired two-tailed t-test" in capsys.readouterr().out
    payload = json.loads((tmp_path / "chain_walk_api.json").read_text())
    with (tmp_path / "chain_walk_api.csv").open() as handle:
        rows = list(csv.reader(handle))
    assert tuple(rows[0]) == COLUMNS and all(math.isfinite(float(r[-1])) for r in rows[1:])
    results = read_results(tmp_path / "chain_walk_api.csv")
    for schedule in ("decreasing", "fixed"):
        summary = payload["summary"][schedule]
        assert set(summary["runs"]) == {"AL", "PL"}
        assert set(summary["t_tests"]) == {"test_return", "exact_return"}
        bought = sum(summary["schedule"]) * 10
        assert results[schedule, "AL", 2, "rewarded_transitions"] == [bought, bought]
        assert results[schedule, "PL", 2, "chosen"] == [0, 0]  # PL: pi_l itself samples
        for method in ("AL", "PL"):
            for i in (0, 1, 2):  # iteration 0: pi_1
                for key in ("test_return", "exact_return", "percent_optimal"):
                    assert len(results[schedule, method, i, key]) == 2  # one value a trial
    assert results["fixed", "AL", 2, "flattening"] == [1.0, 1.0]
    assert _is_png(tmp_path / "fig8_performance.png")
    curves = tmp_path / "logs" / "chain_walk_api" / "scalars"
    steps = (curves / "fixed" / "PL" / "percent_optimal.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in steps] == ["0", "1", "2"]
    assert (curves / "fixed" / "AL" / "effective_sample_size.csv").exists()
    assert gc.isenabled() and gc.get_freeze_count() == 0  # the caller's process left alone


def test_chunks_give_the_same_numbers(one_chunk, tmp_path):
    argv = [*CHUNK_RUN, "--backend", "local", "--chunks", "2", "--out-dir", str(tmp_path)]
    chain_walk_api.main(argv)
    assert _outputs(tmp_path) == _outputs(one_chunk)
    assert (tmp_path / "checkpoints" / "decreasing_AL_chunk2of2.db").is_file()


def test_worker_processes_give_the_local_numbers(one_chunk, tmp_path):
    processes = ("--backend", "processes", "--workers", "2")  # AL and PL side by side
    chain_walk_api.main([*CHUNK_RUN, *processes, "--out-dir", str(tmp_path)])
    assert _outputs(tmp_path) == _outputs(one_chunk)


@pytest.mark.slow  # a local Ray instance starts (many seconds)
@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed")
def test_ray_gives_the_local_numbers(one_chunk, tmp_path):
    import ray.cloudpickle

    # Ray's workers cannot import examples/: the example travels by value, as its __main__ does
    ray.cloudpickle.register_pickle_by_value(chain_walk_api)
    ray_flags = ("--backend", "ray", "--chunks", "2", "--ray-cpus", "2")
    chain_walk_api.main([*CHUNK_RUN, *ray_flags, "--out-dir", str(tmp_path)])
    assert _outputs(tmp_path) == _outputs(one_chunk)


@pytest.mark.parametrize(
    ("flag", "value", "field"),
    [("--lam", "0.01", "evaluation.lam"), ("--repeats", "2", "selection.num_repeats"),
     ("--seed", "1", "trials.seed")],
)  # fmt: skip
def test_resume_with_another_setting_is_refused_naming_it(
    one_chunk, tmp_path, capsys, flag, value, field
):
    """Runs stored without their results (stopped before the report): the store names the
    specification's field; with the results written, the results name the flag."""
    shutil.copytree(one_chunk / "checkpoints", tmp_path / "checkpoints")
    stored = {p.name: p.read_bytes() for p in (tmp_path / "checkpoints").iterdir()}
    argv = [*CHUNK_RUN, "--backend", "local", "--out-dir", str(tmp_path), "--resume", flag, value]
    capsys.readouterr()
    assert _exit_code(chain_walk_api.main, argv) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("error: the run stored in ") and f"['{field}'" in err
    assert {p.name: p.read_bytes() for p in (tmp_path / "checkpoints").iterdir()} == stored
    shutil.copy(one_chunk / "chain_walk_api.json", tmp_path)
    assert _exit_code(chain_walk_api.main, argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [err[0]] and f"other arguments ({flag} " in err[0]


def _words(text: str) -> str:
    """Text without tyro's box drawing and line wrapping."""
    return " ".join(re.sub("[│╭╮╰╯─]", " ", text).split())


OURS = [  # (script, argv, the one line's words): refused by the example or RunSpec
    (chain_walk_api, ["--lam", "-1"], "evaluation.lam must be >= 1e-10"),
    (chain_walk_api, ["--lam", "inf"], "evaluation.lam must be finite, got inf"),
    (chain_walk_api, ["--trials", "1"], "trials must lie in [2, inf], got 1"),
    (chain_walk_api, ["--seed", "-1"], "seed must lie in [0, inf], got -1"),
    (chain_walk_api, ["--iterations", "8"], "iterations must lie in [1, 7], got 8"),
    (chain_walk_api, ["--steps", str(10**8)], "rewarded.schedule × num_steps = 21 × 100000000"),
    (chain_walk_api, ["--trials", "2", "--chunks", "3"], "chunks must lie in 1..2"),
    (chain_walk_api, ["--device", "gpu"], "device string: gpu"),
    (chain_walk_one_step, ["--trials", "0"], "trials must lie in [1, inf], got 0"),
    (chain_walk_one_step, ["--eval-epsilon", "1.5"], "eval_epsilon must lie in [0.0, 1.0]"),
]
TYROS = [  # refused while tyro parses (a type, or Execution's own check)
    (chain_walk_api, ["--repeats", "2.5"], "--repeats: invalid literal for int()"),
    (chain_walk_api, ["--backend", "local", "--workers", "4"], "workers applies to backend"),
    (chain_walk_api, ["--resume", "--overwrite"], "resume and overwrite exclude each other"),
    (chain_walk_api, ["--threads", "100000"], "threads must be <= 1024, got 100000"),
    (chain_walk_one_step, ["--steps", "ten"], "--steps: invalid literal for int()"),
    (chain_walk_one_step, ["--resume"], "Unrecognized options: --resume"),
]


@pytest.mark.parametrize(("script", "argv", "words"), OURS + TYROS)
def test_a_bad_value_exits_2_naming_it_before_any_work(script, argv, words, tmp_path, capsys):
    out = tmp_path / "out"
    assert _exit_code(script.main, [*argv, "--out-dir", str(out)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and words in _words(err) and not out.exists()
    if (script, argv, words) in OURS:
        assert len(err.strip().splitlines()) == 1 and err.startswith("error: ")


@pytest.mark.parametrize(
    ("script", "flags"), [(chain_walk_api, TINY), (chain_walk_one_step, ("--trials", "1"))]
)
def test_an_output_folder_in_the_way_is_one_line_exit_2(script, flags, tmp_path, capsys):
    (tmp_path / "a-file").write_text("not a folder")
    argv = [*flags, "--out-dir", str(tmp_path / "a-file" / "x")]
    assert _exit_code(script.main, argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "a-file" in err[0]


@pytest.mark.parametrize("script", ["chain_walk_api.py", "chain_walk_one_step.py"])
def test_every_argument_has_its_one_line_docstring(script):
    """``--help`` shows a field's docstring (tyro reads it from the source)."""
    tree = ast.parse((EXAMPLES / script).read_text())
    args = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Args")
    body = args.body[1:]  # after the class's docstring
    for field, doc in zip(body[::2], body[1::2], strict=True):
        assert isinstance(field, ast.AnnAssign), ast.dump(field)
        assert isinstance(doc, ast.Expr) and "\n" not in doc.value.value.strip(), field.target.id


# -- Figures 3-5 ------------------------------------------------------------------------------


def test_one_step_writes_its_numbers_and_figures_and_a_trial_is_its_own(tmp_path, monkeypatch):
    small = ("--repeats", "2", "--episodes", "4")
    argv = [*small, "--trials", "2", "--out-dir", str(tmp_path / "two")]
    _run_as_command("chain_walk_one_step.py", argv, monkeypatch)
    two = json.loads((tmp_path / "two" / "one_step.json").read_text())["results"]
    assert list(two) == list(chain_walk_one_step.BASE_POLICIES)
    for name in ("fig3_true_error.png", "fig4_j_estimate.png", "fig5_obtained_error.png"):
        assert _is_png(tmp_path / "two" / name)
    one = chain_walk_one_step.main([*small, "--trials", "1", "--out-dir", str(tmp_path / "one")])
    for base, res in one["results"].items():  # trial 0's numbers do not depend on --trials
        assert res["g_true"][0] == two[base]["g_true"][0]
        assert res["j_prime"][0] == two[base]["j_prime"][0]
    assert all(s["summary"]["g_al"][0] >= s["summary"]["g_opt"][0] for s in two.values())


# -- real processes ---------------------------------------------------------------------------


def test_help_lists_the_flags_and_does_nothing_else(tmp_path):
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / "chain_walk_api.py"), "--help"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "100"},
    )  # fmt: skip
    assert done.returncode == 0 and done.stderr == "", done.stderr[-2000:]
    for flag in ("--trials", "--lam", "--repeats", "--out-dir", "--resume", "--backend"):
        assert flag in done.stdout
    assert "--execution." not in done.stdout and list(tmp_path.iterdir()) == []


def test_interrupted_by_sigint_then_resumed_buys_nothing_twice(
    one_chunk, tmp_path, monkeypatch, capsys
):
    args = (*CHUNK_RUN, "--backend", "local", "--out-dir", str(tmp_path))
    first = tmp_path / "checkpoints" / "decreasing_AL.db"
    proc = start_example("chain_walk_api.py", *args)
    wait_for_episodes(first, 5, proc)  # iteration 1 of 4 committed
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert err.strip().splitlines()[-1].startswith("interrupted at iteration ")
    stores = sorted((tmp_path / "checkpoints").glob("*.db"))
    kept = sum(RunStore.read(p).num_episodes for p in stores)
    total = 2 * sum(chain_walk_api.SCHEDULES["decreasing"][:4])  # AL and PL
    assert 5 <= kept < total
    assert _exit_code(chain_walk_api.main, args) == 1  # neither --resume nor --overwrite
    assert "add --resume to continue them or --overwrite" in capsys.readouterr().err

    bought = []  # the rewarded episodes (per trial) of each collection of this process
    rollouts_or = torch_api.loop.iteration.rollouts_or

    def counting(collector):
        collect = rollouts_or(collector)

        def counted(*args, **kwargs):
            bought.append(kwargs["num_episodes"])
            return collect(*args, **kwargs)

        return counted

    monkeypatch.setattr(torch_api.loop.iteration, "rollouts_or", counting)
    chain_walk_api.main([*args, "--resume"])
    assert kept + sum(bought) == total
    assert _outputs(tmp_path) == _outputs(one_chunk)
