"""benchmarks/reward_budget_map.py: the map runs end to end with a tiny budget, sizes its cells
by the paired t-test's power rule and writes a data file the results report renders."""

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    """benchmarks/<name>.py by its path (torchrl installs a namespace package ``benchmarks``)."""
    spec = importlib.util.spec_from_file_location(
        f"_map_{name}", ROOT / "benchmarks" / f"{name}.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (its dataclasses look their module up)
    spec.loader.exec_module(module)
    return module


def test_trials_needed_is_the_power_rule():
    power = _load("reward_budget_map")
    # n = ((1.960 + 0.842) σ / δ)²: σ = δ needs 7.85, so 8 pairs
    assert power.trials_needed(1.0, 1.0) == 8
    assert power.trials_needed(2.0, 0.5) == math.ceil((power.Z_POWER * 4) ** 2)
    assert power.trials_needed(1.0, 0.0) == sys.maxsize  # no gap: no size finds it


def test_the_map_runs_tiny_and_the_report_renders_it(tmp_path):
    out, figure = tmp_path / "data" / "reward_budget_map.json", tmp_path / "map.png"
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    flags = ["--tasks", "chain", "--chain-episodes", "1", "2", "--chain-reward-free", "1", "1", "1"]
    flags += ["--levers", "--iterations", "1", "--pilot", "4", "--chain-cap", "6"]
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "reward_budget_map.py"), *flags]
        + ["--out-dir", str(tmp_path / "runs"), "--out", str(out), "--figure", str(figure)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    e = json.loads(out.read_text())
    assert [c["cell"]["name"] for c in e["cells"]] == [
        "chain_M1_RM_Z5_L1",
        "chain_M2_RM_Z5_L1",
        "chain_M1_R1_Z1_L1",
    ]
    for c in e["cells"]:
        d = c["difference"]
        assert 4 <= d["trials"] <= 6 and c["al"]["trials"] == d["trials"]
        assert c["detectable_80"] == pytest.approx(_load("reward_budget_map").Z_POWER * d["se"])
        assert c["reward_free_transitions"]["PL"] == 0 < c["reward_free_transitions"]["AL"]
    assert e["rows"] and figure.stat().st_size > 0
    page = _load("report").index_page([e])
    assert "Every cell of the map" in page and "chain_M" not in page
