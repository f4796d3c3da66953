"""Test-session settings.

One intra-op thread: the suite's tensors are small, and on a busy 2-core machine two OpenMP
threads made tiny operations 100-300 times slower (measured while writing the suite).
Subprocesses (the examples run end to end) inherit the setting through OMP_NUM_THREADS.

Tests write only into temporary folders: the session fails if the checkout holds files (ignored
ones included) afterwards that it did not hold before.
"""

import atexit
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
# written by the tools themselves, not by the tests
_TOOL_LITTER = (".pytest_cache", "__pycache__", ".ruff_cache", ".venv", ".venv-ci", ".egg-info")

os.environ.setdefault("OMP_NUM_THREADS", "1")
torch.set_num_threads(1)

try:  # Hypothesis keeps caches (e.g. .hypothesis/constants/) in the working directory
    from hypothesis.configuration import set_hypothesis_home_dir
except ImportError:  # the test extra is not installed; test_properties.py will say so
    pass
else:
    _HYPOTHESIS_HOME = tempfile.mkdtemp(prefix="hypothesis-")
    set_hypothesis_home_dir(_HYPOTHESIS_HOME)
    atexit.register(shutil.rmtree, _HYPOTHESIS_HOME, ignore_errors=True)


def _checkout_files() -> set[str] | None:
    """Untracked paths of the checkout, ignored ones included (None: not a git checkout)."""
    try:
        done = subprocess.run(
            ["git", "status", "--porcelain", "--ignored", "--untracked-files=all"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if done.returncode != 0:
        return None
    paths = {line[3:] for line in done.stdout.splitlines() if line[:2] in ("??", "!!")}
    return {p for p in paths if not any(part in p for part in _TOOL_LITTER)}


@pytest.fixture(scope="session", autouse=True)
def _checkout_stays_clean():
    before = _checkout_files()
    yield
    after = _checkout_files()
    if before is not None and after is not None and (new := sorted(after - before)):
        pytest.fail(f"tests wrote into the checkout (write into tmp_path instead): {new}")
