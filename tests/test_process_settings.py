"""The command-line scripts' process settings (examples/_process.py): the garbage collector off
while they import and the imported objects frozen after, and freed memory kept for the next
tensor. Each runs in a fresh interpreter, as a user's command would, so that this test process
keeps its own collector and allocator."""

from __future__ import annotations

import ast
import gc
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
SCRIPTS = sorted(p for p in EXAMPLES.glob("*.py") if not p.name.startswith("_"))
TINY = ["--trials", "2", "--iterations", "1", "--test-episodes", "1", "--backend", "local"]


def _python(code: str, tmp_path: Path) -> str:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(EXAMPLES), env.get("PYTHONPATH", "")])
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def _main_guards(tree: ast.Module) -> list[list[str]]:
    """The names called in each module-level ``if __name__ == "__main__":`` block."""
    blocks = []
    for node in tree.body:
        if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test):
            calls = [n.func for n in ast.walk(node) if isinstance(n, ast.Call)]
            blocks.append([ast.unparse(f) for f in calls])
    return blocks


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_every_script_imports_without_the_collector_and_freezes_what_it_imported(script):
    blocks = _main_guards(ast.parse(script.read_text()))
    assert len(blocks) == 2, "a guard before the heavy imports and one that runs main"
    assert blocks[0][-1] == "collector_off_for_imports", blocks[0]
    assert blocks[1][0] == "freeze_imported_objects", blocks[1]


def test_a_script_run_as_a_command_reaches_main_with_the_collector_on_and_imports_frozen(
    tmp_path,
):
    out = _python(
        f"""
        import gc, runpy, sys
        import _harness
        run_experiment = _harness.run_experiment

        def spy(*args, **kwargs):
            print("collector on:", gc.isenabled(), "frozen:", gc.get_freeze_count())
            return run_experiment(*args, **kwargs)

        _harness.run_experiment = spy
        gc.unfreeze()  # (importing _harness here froze nothing: count from zero)
        sys.argv = ["chain_walk_api.py", *{TINY!r}, "--out-dir", "out"]
        runpy.run_path({str(EXAMPLES / "chain_walk_api.py")!r}, run_name="__main__")
        """,
        tmp_path,
    )
    line = next(x for x in out.splitlines() if x.startswith("collector on:"))
    enabled, frozen = line.split()[2], int(line.split()[-1])
    assert enabled == "True"
    assert frozen > 100_000, line  # torch's, TorchRL's and the library's objects
    assert (tmp_path / "out" / "chain_walk_api.csv").exists()


def test_a_script_runs_without_loading_torchs_compiler_and_gives_the_same_numbers(tmp_path):
    """A script run as a command never loads ``torch._dynamo`` (TensorDict's import-time
    decorators and TorchRL's rollouts answered by the stand-in), writes the CSV of a run in this
    process (where the real module is loaded) byte for byte, and ``torch.compile`` still works
    in it afterwards (the real module loaded on demand, a compiled module recognised)."""
    out = _python(
        f"""
        import runpy, sys
        sys.argv = ["chain_walk_api.py", *{TINY!r}, "--out-dir", "out"]
        runpy.run_path({str(EXAMPLES / "chain_walk_api.py")!r}, run_name="__main__")
        print("compiler loaded by the run:", "torch._dynamo.convert_frame" in sys.modules)
        import torch, torchrl.envs.utils
        compiled = torch.compile(torch.nn.Linear(2, 2), backend="eager")
        assert torch.equal(compiled(torch.ones(1, 2)), compiled._orig_mod(torch.ones(1, 2)))
        assert isinstance(compiled, torch._dynamo.eval_frame.OptimizedModule)
        print("compiled afterwards:", "torch._dynamo.convert_frame" in sys.modules)
        """,
        tmp_path,
    )
    assert "compiler loaded by the run: False" in out and "compiled afterwards: True" in out
    sys.path.insert(0, str(EXAMPLES))
    import chain_walk_api

    assert "torch._dynamo.convert_frame" in sys.modules  # here: TensorDict loaded the real one
    chain_walk_api.main([*TINY, "--out-dir", str(tmp_path / "in_process")])
    written = (tmp_path / "out" / "chain_walk_api.csv").read_bytes()
    assert written == (tmp_path / "in_process" / "chain_walk_api.csv").read_bytes()


def test_main_called_in_process_leaves_the_callers_collector_alone(tmp_path):
    sys.path.insert(0, str(EXAMPLES))
    import chain_walk_api

    before = gc.isenabled(), gc.get_freeze_count()
    chain_walk_api.main([*TINY, "--out-dir", str(tmp_path / "out")])
    assert (gc.isenabled(), gc.get_freeze_count()) == before


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt (Linux)")
@pytest.mark.parametrize("freed_memory", ["retain", "return"])
def test_freed_memory_setting_decides_whether_a_freed_tensor_faults_in_again(
    freed_memory, tmp_path
):
    """64 MiB made and freed again and again: with ``retain`` the freed pages are reused once
    the heap has grown to fit (a few rounds: small objects made in between pin a freed block
    for a while, and now and then one more round grows the heap), with ``return`` (glibc's
    defaults) every new tensor faults in its 16,384 pages again. The median round decides."""
    out = _python(
        f"""
        import resource, statistics, types, torch
        from _process import configure_process

        configure_process(types.SimpleNamespace(threads=0, freed_memory={freed_memory!r}))
        elements = 64 * 2**20 // 8
        for _ in range(8):  # the heap grows to fit, whatever the setting
            torch.ones(elements, dtype=torch.float64)
        faults = []
        for _ in range(9):
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            torch.ones(elements, dtype=torch.float64)
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
        print(statistics.median(faults))
        """,
        tmp_path,
    )
    faults, pages = float(out.split()[-1]), 64 * 2**20 // 4096
    if freed_memory == "retain":
        assert faults < 0.1 * pages, faults
    else:
        assert faults > 0.9 * pages, faults
