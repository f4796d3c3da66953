"""The example scripts' command lines: fast, uniform, honest (examples/_cli.py).

Every script parses its arguments before it imports anything heavy, so ``--help`` and a bad
flag answer at once; each test runs the script as a user would, in a subprocess.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
sys.path.insert(0, str(EXAMPLES))

import _cli  # noqa: E402

SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py") if not p.name.startswith("_"))
HEAVY = {"torch", "torchrl", "tensordict", "mujoco", "matplotlib", "scipy", "numpy"}
HEAVY |= {"gymnasium", "tqdm", "torch_api", "envs"}
HELP_SECONDS = 2.0

# one out-of-range value per script: (flag, value, the message's words)
BAD_FLAG = {
    "batting_reference.py": ("--episodes", "-3", "--episodes must be >= 1, got -3"),
    "chain_walk_api.py": ("--trials", "-3", "--trials must be >= 2"),
    "chain_walk_one_step.py": ("--trials", "-3", "--trials must be >= 1, got -3"),
    "gym_drop_in.py": ("--trials", "-3", "--trials must be >= 2"),
    "merge_pipeline_runs.py": ("--runs", "", "--runs must name at least one folder"),
    "plot_batting_episode.py": ("--snapshot-ms", "-3", "--snapshot-ms must be > 0, got -3.0"),
    "train_batting.py": ("--trials", "-3", "--trials must be >= 1, got -3"),
    "torchrl_pipeline.py": ("--episodes", "-3", "--episodes must be >= 0, got -3"),
}


def _run(script: str, *args: str, python_flags: tuple[str, ...] = ()):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, *python_flags, str(EXAMPLES / script), *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    return done, time.perf_counter() - started


def test_every_script_is_covered():
    assert set(BAD_FLAG) == set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_help_answers_fast_without_heavy_imports(script):
    done, seconds = _run(script, "--help", python_flags=("-X", "importtime"))
    assert done.returncode == 0, done.stderr[-2000:]
    assert seconds < HELP_SECONDS, f"{script} --help took {seconds:.2f} s"
    imported = {
        line.split("|")[-1].strip().split(".")[0]
        for line in done.stderr.splitlines()
        if line.startswith("import time:")
    }
    assert not imported & HEAVY, f"{script} --help imports {sorted(imported & HEAVY)}"
    assert "(default:" in done.stdout


def _args_class(script: str) -> ast.ClassDef:
    tree = ast.parse((EXAMPLES / script).read_text())
    return next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Args")


def _fields(script: str) -> set[str]:
    """The options of a script: its ``Args`` fields and those of the ``_cli`` classes it
    extends (``RunOptions``, ``ChunkOptions``)."""
    args = _args_class(script)
    names = {n.target.id for n in args.body if isinstance(n, ast.AnnAssign)}
    for base in args.bases:
        if isinstance(base, ast.Name) and hasattr(_cli, base.id):
            names |= {f.name for f in dataclasses.fields(getattr(_cli, base.id))}
    return names


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_option_has_help_text(script):
    """Declared as ``field(..., help="...")``: kept where no source can be read."""
    for node in _args_class(script).body:
        if isinstance(node, ast.AnnAssign):
            help_ = [k for k in getattr(node.value, "keywords", ()) if k.arg == "help"]
            assert help_ and ast.literal_eval(help_[0].value), (
                f"{script}: option {node.target.id} has no help text"
            )


def test_a_script_runs_under_the_profiler(tmp_path):
    """``python -m cProfile`` runs a script as ``__main__`` of its own module, so no class of
    the script has source to read: the help texts were read from the source (``OSError: could
    not find class definition``)."""
    profile, out = tmp_path / "p", tmp_path / "out"
    tiny = ("--iterations", "1", "--steps", "5", "--test-episodes", "2", "--test-steps", "5")
    tiny += ("--schedule", "decreasing", "--repeats", "1", "--threads", "1")
    done, _ = _run(
        "chain_walk_api.py",
        *("--trials", "10", *tiny, "--out-dir", str(out)),
        python_flags=("-m", "cProfile", "-o", str(profile)),
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert (out / "chain_walk_api.json").is_file() and profile.stat().st_size > 0


def test_the_shared_run_options_have_help_text():
    for options in (_cli.RunOptions, _cli.ChunkOptions):
        docs = _cli.field_docs(options)
        assert {f.name for f in dataclasses.fields(options)} <= set(docs), options.__name__
        assert all(docs.values())


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [
        ("--lam", "inf", "--lam must be a finite number, got inf"),
        ("--lam", "1e-300", "--lam must be >= 1e-10, got 1e-300"),
        ("--seed", "-1", "--seed must lie in 0..9223372036854775807, got -1"),
        ("--threads", "100000", "--threads must lie in 0..1024, got 100000"),
        ("--steps", str(10**8), "GiB of memory available: lower --trials, --steps"),
    ],
)
def test_values_that_failed_late_are_one_line_exit_2_at_once(flag, value, message):
    """Each was a traceback or a failure after seconds of work (``--lam 1e-300`` after the
    rewards were stored; ``--steps 10**8`` no answer in a minute)."""
    done, seconds = _run("chain_walk_api.py", flag, value)
    assert done.returncode == 2, done.stderr[-2000:]
    assert message in done.stderr.strip().splitlines()[-1], done.stderr[-2000:]
    assert "Traceback" not in done.stderr and seconds < HELP_SECONDS


def test_the_smallest_lambda_is_the_librarys():
    from torch_api import _checks

    assert _cli.TINY_LAMBDA == _checks.TINY_LAMBDA


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_bad_value_is_one_line_naming_it_exit_2(script):
    flag, value, message = BAD_FLAG[script]
    done, seconds = _run(script, flag, value)
    assert done.returncode == 2, done.stderr[-2000:]
    assert message in done.stderr
    assert "Traceback" not in done.stderr
    assert seconds < HELP_SECONDS


@pytest.mark.parametrize("script", SCRIPTS)
def test_an_unwritable_output_folder_is_one_line_before_any_work(script, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    flag, target = ("--out", blocker / "x" / "out.json")
    if script not in ("batting_reference.py", "plot_batting_episode.py"):
        flag, target = ("--out-dir", blocker / "x")
    done, seconds = _run(script, flag, str(target))
    assert done.returncode == 2, done.stderr[-2000:]
    assert "is not writable" in done.stderr and "Traceback" not in done.stderr
    assert seconds < HELP_SECONDS  # refused before the heavy imports, let alone the work


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_flag_the_script_cannot_honour_is_refused_with_the_reason(script):
    fields = _fields(script)
    for name in ("trials", "seed", "out_dir", "device", "resume", "backend"):
        if name in fields:
            continue
        done, _ = _run(script, f"--{name.replace('_', '-')}", "1")
        assert done.returncode == 2
        assert f"is not available in {script}:" in done.stderr, done.stderr


DURABLE = [script for script in SCRIPTS if {"resume", "overwrite"} <= _fields(script)]


def test_the_durable_scripts_are_known():
    assert "torchrl_pipeline.py" in DURABLE and "gym_drop_in.py" in DURABLE


@pytest.mark.parametrize("script", DURABLE)
def test_resume_with_overwrite_is_one_line_before_any_work(script, tmp_path):
    done, seconds = _run(script, "--resume", "--overwrite", "--out-dir", str(tmp_path))
    assert done.returncode == 2, done.stderr[-2000:]
    assert "error: --resume and --overwrite exclude each other" in done.stderr
    assert "Traceback" not in done.stderr and seconds < HELP_SECONDS


def test_backends_match_the_library():
    from torch_api.runs.dispatch import BACKENDS

    assert _cli.BACKENDS == BACKENDS


def test_out_dir_error_on_a_full_disk(tmp_path, monkeypatch):
    assert _cli.out_dir_error(tmp_path / "new") is None
    assert (tmp_path / "new").is_dir()
    usage = _cli.shutil.disk_usage(tmp_path)
    monkeypatch.setattr(_cli.shutil, "disk_usage", lambda path: usage._replace(free=3 * 2**20))
    why = _cli.out_dir_error(tmp_path)
    assert why is not None and "has 3 MB free" in why


def test_device_syntax_is_checked_without_torch():
    assert _cli.device_syntax_error("cuda:1") is None
    assert "got 'gpu'" in _cli.device_syntax_error("gpu")


@pytest.mark.skipif(
    importlib.util.find_spec("tensorboard") is not None, reason="tensorboard is installed here"
)
def test_a_logger_whose_package_is_missing_is_refused_before_any_work():
    done, seconds = _run("chain_walk_api.py", "--logger", "tensorboard")
    assert done.returncode == 2
    assert "--logger tensorboard needs the tensorboard package" in done.stderr
    assert seconds < HELP_SECONDS
