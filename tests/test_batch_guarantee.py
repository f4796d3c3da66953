"""The batch guarantee: trial t draws, and learns, exactly what it would alone.

Trials 0-3 of a 4-trial run, of an 8-trial run, of a run split into chunks and of four 1-trial
runs with the same trial seeds are identical to the bit, in the loop and in every CLI's
outputs (trials 0-3 of ``--trials 4`` and ``--trials 8``).
"""

from __future__ import annotations

import csv
import importlib
import json
import sys
from pathlib import Path

import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.spec import RunSpec
from torch_api.runs.dispatch import trial_seeds

SEED = 3
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run(seeds: list[int]) -> dict:
    """An active chain-walk run of the trials with these seeds: per-trial θ, choices, J'."""
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    spec = RunSpec.of(
        schedule=(3, 1),
        num_steps=10,
        gamma=GAMMA,
        psi_mode="grouped",
        num_repeats=2,
        num_trials=len(seeds),
        seed=SEED,
        trial_seeds=seeds,
    )
    api = ActivePolicyIteration(spec, env=lambda rows: ChainWalkEnv(batch_size=rows), basis=basis)
    history = api.run()
    return {
        "theta": api.theta,
        "chosen": [torch.tensor(r.chosen) for r in history],
        "j_mean": [torch.tensor(r.j_mean) for r in history],
    }


def first_trials(result: dict, count: int) -> dict:
    return {
        "theta": result["theta"][:count],
        "chosen": [c[:count] for c in result["chosen"]],
        "j_mean": [j[:count] for j in result["j_mean"]],
    }


def cat(parts: list[dict]) -> dict:
    return {
        "theta": torch.cat([p["theta"] for p in parts]),
        "chosen": [torch.cat([p["chosen"][i] for p in parts]) for i in range(2)],
        "j_mean": [torch.cat([p["j_mean"][i] for p in parts]) for i in range(2)],
    }


def same(a: dict, b: dict) -> bool:
    return torch.equal(a["theta"], b["theta"]) and all(
        torch.equal(x, y)
        for key in ("chosen", "j_mean")
        for x, y in zip(a[key], b[key], strict=True)
    )


def test_trials_of_a_batch_learn_what_they_learn_alone_or_in_any_batch():
    seeds = trial_seeds(SEED, range(8))
    four = run(seeds[:4])
    assert same(first_trials(run(seeds), 4), four)  # the first 4 of an 8-trial batch
    assert same(cat([run(seeds[:1]), run(seeds[1:3]), run(seeds[3:4])]), four)  # chunks
    assert same(cat([run([s]) for s in seeds[:4]]), four)  # each alone
    assert not torch.equal(four["theta"][0], four["theta"][1])  # trials do differ


# -- every CLI: trials 0-3 of --trials 4 and --trials 8 --------------------------------------


def _cli(script: str, out: Path, *args: str) -> None:
    """The example's command line, run in this process (its entry point, ``main(argv)``)."""
    if str(EXAMPLES) not in sys.path:
        sys.path.insert(0, str(EXAMPLES))
    importlib.import_module(script.removesuffix(".py")).main([*args, "--out-dir", str(out)])


def _rows_of_first_trials(path: Path, count: int) -> list[tuple]:
    with path.open() as fh:
        rows = [r for r in csv.DictReader(fh) if int(r["trial"]) < count]
    return sorted(tuple(r.values()) for r in rows)


CLIS = {
    "chain_walk_api": ("--iterations", "1", "--test-episodes", "3", "--test-steps", "10"),
    "gym_drop_in": ("--schedule", "2", "2", "--steps", "10", "--repeats", "2")
    + ("--test-episodes", "2", "--test-steps", "20"),
    "train_batting": ("--iterations", "1", "--repeats", "2", "--schedule", "decreasing"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CLIS))
def test_cli_trials_0_to_3_of_4_and_of_8_agree_in_the_csv(name, tmp_path):
    for trials in (4, 8):
        _cli(f"{name}.py", tmp_path / str(trials), "--trials", str(trials), *CLIS[name])
    four = _rows_of_first_trials(tmp_path / "4" / f"{name}.csv", 4)
    eight = _rows_of_first_trials(tmp_path / "8" / f"{name}.csv", 4)
    assert four and four == eight


@pytest.mark.slow
def test_one_step_trials_0_to_3_of_4_and_of_8_agree(tmp_path):
    args = ("--episodes", "5", "--repeats", "2")
    for trials in (4, 8):
        _cli("chain_walk_one_step.py", tmp_path / str(trials), "--trials", str(trials), *args)
    four, eight = (
        json.loads((tmp_path / str(t) / "one_step.json").read_text())["results"] for t in (4, 8)
    )
    for base in four:
        for measure in ("j_prime", "g_true"):
            assert four[base][measure] == eight[base][measure][:4], (base, measure)


# -- episodes that end early: each trial's own transition counts ------------------------------


def batting_counts(seeds: list[int]) -> list[dict]:
    """An active batting run whose episodes end at the hit (so trials buy different numbers of
    transitions): per iteration, the per-trial counts its records report and the per-trial
    counts of the rewarded episodes it holds."""
    from envs.batting import BASIS_TAU, N_ACTIONS, BattingEnv, basis_centers

    basis = GaussianActionBasis(centers=basis_centers(), tau=BASIS_TAU, num_actions=N_ACTIONS)
    spec = RunSpec.of(
        schedule=(3, 2),
        num_steps=10,
        gamma=1.0,
        psi_mode="single",
        num_repeats=1,
        num_trials=len(seeds),
        seed=SEED,
        trial_seeds=seeds,
    )
    api = ActivePolicyIteration(
        spec, env=lambda rows: BattingEnv(batch_size=rows, end_at_hit=True), basis=basis
    )
    rows = []
    for _ in range(2):
        record = api.step()
        mask = api.rewarded.episodes()["mask"]  # [T, M, N]
        rows.append(
            {
                "rewarded": record.rewarded_transitions,
                "reward_free": record.reward_free_transitions,
                "held": mask.sum((-2, -1)).tolist(),
            }
        )
    api.close()
    return rows


def test_early_ends_each_trial_reports_its_own_transitions_in_any_batch():
    """With episodes that end at the hit, trial t's counts are its own (not the batch's mean):
    the same alone as in a batch, and equal to what its episodes hold."""
    seeds = trial_seeds(SEED, range(3))
    batch = batting_counts(seeds)
    alone = [batting_counts([s]) for s in seeds]
    for l, row in enumerate(batch):
        assert row["rewarded"] == row["held"]
        assert len(set(row["held"])) > 1 or l == 0  # the trials do differ (early ends)
        for t in range(3):
            assert alone[t][l]["rewarded"] == [row["rewarded"][t]]
            assert alone[t][l]["reward_free"] == [row["reward_free"][t]]
