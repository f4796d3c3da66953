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


def _map_in_process(monkeypatch):
    """benchmarks/reward_budget_map.py imported as its script runs it (its own sys.path)."""
    monkeypatch.setattr(sys, "path", [str(ROOT / "benchmarks"), str(ROOT), *sys.path])
    return _load("reward_budget_map")


def test_gym_rows_are_seeded_per_trial(monkeypatch):
    """A trial's rows draw from its own seed: the same block seed, the same first observations,
    whatever the other trials of the batch (as ChainWalkEnv's and BattingEnv's blocks)."""
    monkeypatch.setattr(sys, "path", [str(ROOT), *sys.path])
    gym_tasks = _load("_budget_map_gym")
    from torch_api.streams import has_block_seeds

    pair, alone = gym_tasks.make_env("cartpole", 4, 3), gym_tasks.make_env("cartpole", 2, 3)
    assert has_block_seeds(pair)
    pair.set_block_seeds([11, 22])
    alone.set_block_seeds([22])
    first_pair, first_alone = pair.reset()["observation"], alone.reset()["observation"]
    assert torch_equal(first_pair[2:], first_alone) and not torch_equal(first_pair[:2], first_alone)
    with pytest.raises(ValueError, match="equal blocks"):
        pair.set_block_seeds([1, 2, 3])
    acrobot = gym_tasks.make_env("acrobot", 2, 3)
    acrobot.set_seed(0)
    rollout = acrobot.rollout(3, break_when_any_done=False)
    assert rollout["observation"].abs().max() <= 1.0  # the box to [-1, 1]
    assert gym_tasks.make_basis("acrobot").num_features == 3 * (1 + 6 + 21)
    for env in (pair, alone, acrobot):
        env.close()


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


def test_a_gym_cell_runs_in_process_and_renders(tmp_path, monkeypatch):
    """A CartPole cell through ActivePolicyIteration, tiny: its pilot, its cap, its measure
    (the greedy test return at l = L only), its row and the page."""
    rbm = _map_in_process(monkeypatch)
    out = tmp_path / "data" / "reward_budget_map.json"
    flags = ["--tasks", "cartpole", "--cartpole-episodes", "1", "--cartpole-reward-free"]
    flags += ["--levers", "--iterations", "2", "--gym-pilot", "3", "--cartpole-cap", "2"]
    e = rbm.main([*flags, "--out-dir", str(tmp_path / "runs"), "--out", str(out)])
    assert json.loads(out.read_text())["cells"] == e["cells"]
    (cell,) = e["cells"]
    assert cell["cell"]["name"] == "cartpole_M1_RM_Z5_L2"  # ν = 0 is the task's own: no suffix
    assert cell["cell"]["axis"] == "rewarded" and cell["cell"]["flattening"] == 0.0
    assert cell["measure"] == "greedy_test_return" and cell["difference"]["trials"] == 2
    assert cell["trials_cap"] == 2 and cell["al"]["trials"] == 2
    assert cell["reward_free_transitions"]["PL"] == 0 < cell["reward_free_transitions"]["AL"]
    assert 0 < cell["pl"]["mean"] <= 500
    assert e["rows"][0]["schedule"].startswith("CartPole-v1: M = 1")
    stored = json.loads((tmp_path / "runs" / "cells" / "cartpole_M1_RM_Z5_L2.json").read_text())
    assert stored["difference"] == cell["difference"]  # a rerun reads it back
    again = rbm.main([*flags, "--out-dir", str(tmp_path / "runs")])
    assert again["cells"][0]["cell_wall_seconds"] == cell["cell_wall_seconds"]
    page = _load("report").index_page([e])
    assert "| cartpole | 1 | M | 5 | 0.0 | 2 |" in page


def test_cells_keep_the_stored_names_and_add_the_gym_ones(monkeypatch):
    rbm = _map_in_process(monkeypatch)
    names = [c.name for c in rbm.cells(rbm.Args(tasks="all"))]
    assert names[:2] == ["chain_M1_RM_Z5_L7", "chain_M2_RM_Z5_L7"]
    assert "batting_M1_RM_Z5_nuiwcv_L7" in names and "chain_M1_R1_Z1_L7" in names
    gym = [n for n in names if n.startswith(("cartpole", "acrobot"))]
    assert gym == ["cartpole_M1_RM_Z5_L7", "cartpole_M4_RM_Z5_L7", "cartpole_M4_R1_Z1_L7"] + [
        "acrobot_M2_RM_Z5_L7"
    ]
