"""The TorchRL examples end to end with tiny budgets: ``gym_drop_in.py``, ``torchrl_pipeline.py``
and ``merge_pipeline_runs.py``, their ``main(argv)`` run in this process (one kill-and-resume in
a subprocess); ``torchrl_pipeline.py``'s runs, through the user's ``Collector``, against
``ActivePolicyIteration``'s own rollouts."""

from __future__ import annotations

import json
import math
import signal
import sys
from functools import cache, partial
from pathlib import Path

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import gym_drop_in  # noqa: E402
import merge_pipeline_runs  # noqa: E402
import torchrl_pipeline  # noqa: E402
from _processes import start_example, wait_for_episodes  # noqa: E402

import torch_api.experiment.pipeline as pipe  # noqa: E402
from torch_api import ActivePolicyIteration, DurableRun, SamplingPolicySelector  # noqa: E402
from torch_api.core.quadratic_basis import QuadraticActionBasis  # noqa: E402
from torch_api.experiment import read_results  # noqa: E402
from torch_api.runs.store import RunStore  # noqa: E402

SCRIPTS = {"gym_drop_in": gym_drop_in, "torchrl_pipeline": torchrl_pipeline}
SCRIPTS["merge_pipeline_runs"] = merge_pipeline_runs
PNG = b"\x89PNG\r\n\x1a\n"


def _numbers(value):
    """Every number inside a JSON value."""
    if isinstance(value, dict):
        for v in value.values():
            yield from _numbers(v)
    elif isinstance(value, list):
        for v in value:
            yield from _numbers(v)
    elif isinstance(value, int | float) and not isinstance(value, bool):
        yield value


def _without(value, keys=("seconds", "wall_seconds", "args")):
    """A payload without its wall times and arguments (what differs between equal runs)."""
    if isinstance(value, dict):
        return {k: _without(v, keys) for k, v in value.items() if k not in keys}
    if isinstance(value, list):
        return [_without(v, keys) for v in value]
    return value


# -- the command lines -----------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_shows_the_docstring_and_every_option(name, capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as done:
        SCRIPTS[name].main(["--help"])
    out = capsys.readouterr().out
    assert done.value.code == 0 and SCRIPTS[name].__doc__.splitlines()[0] in out
    assert "--out-dir" in out and "(default:" in out


BAD = [
    ("gym_drop_in", ["--trials", "1"], "error: trials must be >= 2, got 1"),
    ("gym_drop_in", ["--gamma", "1.5"], "error: evaluation.gamma must lie in (0, 1], got 1.5"),
    ("gym_drop_in", ["--chunks", "9", "--trials", "2"], "error: chunks must lie in 1..2"),
    ("gym_drop_in", ["--resume", "--overwrite"], "resume and overwrite exclude each other"),
    ("gym_drop_in", ["--schedule", "3", "x"], "--schedule"),
    ("torchrl_pipeline", ["--episodes", "-3"], "rewarded.schedule[1] must be >= 1, got -3"),
    ("torchrl_pipeline", ["--flattening", "2"], "evaluation.flattening must be 'iwcv' or lie"),
    ("torchrl_pipeline", ["--flattening", "half"], "--flattening"),
    ("torchrl_pipeline", ["--env", "Pong-v5"], "--env"),
    ("torchrl_pipeline", ["--resume", "--overwrite"], "resume and overwrite exclude each other"),
    ("torchrl_pipeline", ["--backend", "ray"], "error: --backend: not for runs over seeds"),
    ("merge_pipeline_runs", [], "error: --runs must name at least one folder"),
    ("merge_pipeline_runs", ["--runs", "nowhere"], "error: --runs: no torchrl_pipeline.json"),
]


@pytest.mark.parametrize(("name", "argv", "message"), BAD, ids=[" ".join(b[1]) for b in BAD])
def test_a_bad_value_ends_the_script_with_exit_2_naming_it(name, argv, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as done:
        SCRIPTS[name].main([*argv, "--out-dir", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert done.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()  # refused before any work


@pytest.mark.parametrize("name", ["gym_drop_in", "torchrl_pipeline"])
def test_an_output_folder_in_the_way_is_one_line_exit_2(name, capsys, tmp_path):
    (tmp_path / "a-file").write_text("not a folder")
    with pytest.raises(SystemExit) as done:
        SCRIPTS[name].main(["--out-dir", str(tmp_path / "a-file" / "x")])
    err = capsys.readouterr().err
    assert done.value.code == 2 and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: ") and "a-file" in err


# -- gym_drop_in.py --------------------------------------------------------------------------

GYM_TINY = ["--trials", "2", "--schedule", "2", "2", "--steps", "10", "--repeats", "2"]
GYM_TINY += ["--test-episodes", "2", "--test-steps", "20"]


@pytest.fixture(scope="module")
def gym_run(tmp_path_factory) -> tuple[Path, dict]:
    """``gym_drop_in.main`` at a tiny budget, asked to ``--resume`` a folder without runs."""
    out = tmp_path_factory.mktemp("gym_drop_in")
    return out, gym_drop_in.main([*GYM_TINY, "--out-dir", str(out), "--resume"])


def test_gym_drop_in_writes_every_number_and_checks_its_data(gym_run):
    out, payload = gym_run
    runs = payload["summary"]["custom"]["runs"]
    assert set(runs) == {"AL", "PL"} and payload["args"]["execution"]["resume"] is True
    for run in runs.values():
        assert run["data_check"]["episodes"] == 2 * 4 and run["data_check"]["transitions"] > 0
    assert all(math.isfinite(x) for x in _numbers(payload["summary"]))
    results = read_results(out / "gym_drop_in.csv")
    balanced = [v for (_, _, _, m), v in results.items() if m == "steps_balanced"]
    assert len(balanced) == 2 * 3 and all(len(v) == 2 for v in balanced)  # methods × l = 0..2
    assert (out / "performance.png").read_bytes()[:8] == PNG
    assert (out / "checkpoints" / "active.db").is_file()


def test_gym_drop_in_interrupted_says_so_in_one_line_and_resumes(gym_run, tmp_path):
    """SIGINT once iteration 1's episodes are stored: one line, exit 130; ``--resume`` ends
    (here, in this process) ends with the uninterrupted run's numbers, byte for byte."""
    reference, _ = gym_run
    args = (*GYM_TINY, "--out-dir", str(tmp_path))
    proc = start_example("gym_drop_in.py", *args)
    wait_for_episodes(tmp_path / "checkpoints" / "active.db", 2, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    last = err.strip().splitlines()[-1]  # (after the progress bar)
    assert "Traceback" not in err and last.startswith("interrupted at iteration "), err[-3000:]
    assert last.endswith(f"stored in {tmp_path / 'checkpoints'}; continue with --resume")
    gym_drop_in.main([*args, "--resume"])
    csv = "gym_drop_in.csv"
    assert (tmp_path / csv).read_bytes() == (reference / csv).read_bytes()


# -- torchrl_pipeline.py and merge_pipeline_runs.py ------------------------------------------

PIPELINE_TINY = ["--iterations", "2", "--first-episodes", "3", "--episodes", "2"]
PIPELINE_TINY += ["--reward-free-episodes", "1", "--repeats", "1", "--steps", "20"]
PIPELINE_TINY += ["--test-episodes", "2", "--test-steps", "30"]


@pytest.fixture(scope="module")
def pipeline_two_seeds(tmp_path_factory) -> dict:
    """CartPole (the default), AL and PL over seeds 0 and 1, in one call: its payload."""
    out = tmp_path_factory.mktemp("pipeline")
    payload = torchrl_pipeline.main([*PIPELINE_TINY, "--seeds", "2", "--out-dir", str(out)])
    assert (out / "torchrl_pipeline.png").read_bytes()[:8] == PNG
    assert json.loads((out / "torchrl_pipeline.json").read_text()) == json.loads(
        json.dumps(payload)
    )
    return payload


def test_torchrl_pipeline_runs_cartpole_by_default_al_and_pl_paired(pipeline_two_seeds):
    payload = pipeline_two_seeds
    assert payload["args"]["env"] == "CartPole-v1" and payload["args"]["fit"] == "lstd"
    assert set(payload["runs"]) == {"AL", "PL"} and set(payload["runs"]["AL"]) == {"0", "1"}
    for mode in ("AL", "PL"):
        for run in payload["runs"][mode].values():
            history = run["history"]
            assert [h["iteration"] for h in history] == [1, 2]
            assert all(h["flattening"] == 0.0 for h in history)  # ν = 0: every weight 1
            assert all(h["effective_sample_size"] == h["rewarded_transitions"] for h in history)
            assert 5 <= history[-1]["rewarded_transitions"] <= 5 * 20  # early ends: fewer
            assert all(1 <= h["greedy_test_return"] <= 30 for h in history)
            assert all(len(h["j_mean"]) == (4 if mode == "AL" else 0) for h in history)
            free = [h["reward_free_transitions"] for h in history]  # (so far: cumulative)
            assert (free[0] > 0 and free[1] > free[0]) if mode == "AL" else free == [0, 0]
            assert run["bought"] == 5 and "ε-greedy θ (ε = " in history[0]["chosen"]
    assert payload["summary"]["PL"]["seeds"] == [0, 1] and payload["t_test"] is not None
    assert all(math.isfinite(x) for x in _numbers(payload["runs"]))


def test_merged_pipeline_runs_equal_one_run_over_their_seeds(pipeline_two_seeds, tmp_path):
    """AL beside PL, the seeds split over processes, merged: the numbers of one run over all
    the seeds; another setting or a conflicting seed is refused."""
    parts = {"al": ["--modes", "AL", "--seeds", "2"], "pl0": ["--modes", "PL", "--seeds", "1"]}
    parts["pl1"] = ["--modes", "PL", "--seeds", "1", "--seed", "1"]
    for name, flags in parts.items():
        torchrl_pipeline.main([*PIPELINE_TINY, *flags, "--out-dir", str(tmp_path / name)])
    folders = [str(tmp_path / name) for name in parts]
    merged = merge_pipeline_runs.main(["--runs", *folders, "--out-dir", str(tmp_path / "m")])
    assert merged["summary"]["AL"]["seeds"] == [0, 1] == merged["summary"]["PL"]["seeds"]
    assert merged["args"]["merged_from"] == folders
    assert _without(merged) == _without(pipeline_two_seeds)  # runs, summary, t-test, the actor
    assert (tmp_path / "m" / "torchrl_pipeline.png").read_bytes()[:8] == PNG

    one = json.loads(json.dumps(pipeline_two_seeds))
    other = json.loads((tmp_path / "pl1" / "torchrl_pipeline.json").read_text())
    other["args"]["gamma"] = 0.99
    with pytest.raises(ValueError, match=r"another setting: \['gamma'\]"):
        merge_pipeline_runs.merge([one, other])
    other = json.loads((tmp_path / "pl1" / "torchrl_pipeline.json").read_text())
    other["runs"]["PL"]["1"]["history"][-1]["greedy_test_return"] += 1.0
    with pytest.raises(ValueError, match="PL seed 1 appears twice with different numbers"):
        merge_pipeline_runs.merge([one, other])


def test_torchrl_pipeline_active_runs_are_reproducible(tmp_path):
    """The same seed twice: AL's reward-free episodes (so J' and the choice) are the same.
    Before, the selector's env of Z·K·M rows was never seeded (the example seeded Z·M)."""
    flags = ["--modes", "AL", "--seeds", "1", "--iterations", "2", "--first-episodes", "3"]
    flags += ["--episodes", "2", "--reward-free-episodes", "2", "--repeats", "2"]
    flags += ["--steps", "40", "--test-episodes", "1", "--test-steps", "20"]
    runs = []
    for name in ("first", "second"):
        payload = torchrl_pipeline.main([*flags, "--out-dir", str(tmp_path / name)])
        history = payload["runs"]["AL"]["0"]["history"]
        runs.append([(h["j_mean"], h["reward_free_transitions"], h["chosen"]) for h in history])
    assert runs[0] == runs[1] and all(len(j) == 4 for j, _, _ in runs[0])


MOUNTAIN_CAR = ["--env", "MountainCar-v0", "--modes", "AL", "--seeds", "1"]
MOUNTAIN_CAR += ["--iterations", "3", "--first-episodes", "2", "--episodes", "2"]
MOUNTAIN_CAR += ["--reward-free-episodes", "1", "--repeats", "1", "--steps", "20"]
MOUNTAIN_CAR += ["--test-episodes", "2", "--test-steps", "20"]


def test_torchrl_pipeline_failed_then_resumed_buys_nothing_twice(tmp_path, monkeypatch, capsys):
    """MountainCar, AL, the user's actor a candidate. A run that fails at its third purchase,
    resumed, keeps every stored reward and ends with an uninterrupted run's numbers; the folder
    is refused without --resume."""
    expected = torchrl_pipeline.main([*MOUNTAIN_CAR, "--out-dir", str(tmp_path / "whole")])
    history = expected["runs"]["AL"]["0"]["history"]
    assert all(len(h["j_mean"]) == 5 for h in history)  # four θ policies and the actor
    assert history[-1]["rewarded_transitions"] == 3 * 2 * 20  # no early end on MountainCar
    assert expected["runs"]["PL"] == {} and expected["t_test"] is None

    buy, calls = torchrl_pipeline.Collector, []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("the robot broke")
        return buy(*args, **kwargs)

    args = [*MOUNTAIN_CAR, "--out-dir", str(tmp_path / "cut")]
    monkeypatch.setattr(torchrl_pipeline, "Collector", failing)
    with pytest.raises(RuntimeError, match="the robot broke"):
        torchrl_pipeline.main(args)
    monkeypatch.setattr(torchrl_pipeline, "Collector", buy)
    store = tmp_path / "cut" / "checkpoints" / "AL_seed0.db"
    assert RunStore.read(store).num_episodes == 2 * 2  # iterations 1 and 2
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        torchrl_pipeline.main(args)
    assert str(refused.value.code).startswith("error: runs are stored already")  # exit 1
    resumed = torchrl_pipeline.main([*args, "--resume"])
    assert f"resumed {store} at iteration 2/3" in capsys.readouterr().out
    assert resumed["runs"]["AL"]["0"].pop("bought") == 2  # only iteration 3's
    expected["runs"]["AL"]["0"].pop("bought")
    assert _without(resumed) == _without(expected)


@pytest.mark.parametrize("mode", ["AL", "PL"])
def test_the_pipeline_run_is_the_users_own_loop_step_by_step(mode):
    """A run of the example (``ActivePolicyIteration.run`` with the user's ``Collector`` as its
    source, every purchase stored) is the README's own loop on the same spec, seed and envs:
    ``choose()``, the user's Collector with ``sampling_policy()`` into their replay buffer,
    ``fit(buffer[:])``, ``improve()``: the same J', choices, θ and greedy returns, bit for bit.
    (The loop's own ``env.rollout`` draws otherwise: a Collector calls the policy once when it
    is made, to read its output keys, which moves the policy's stream on by one step.)"""
    args, spec = torchrl_pipeline.resolved(
        torchrl_pipeline.Args(
            iterations=3,
            first_episodes=4,
            episodes=2,
            steps=20,
            repeats=2,
            reward_free_episodes=2,
            test_episodes=2,
            test_steps=50,
        )  # fmt: skip
    )
    example = torchrl_pipeline.run(args, spec, mode, 3, DurableRun(None))

    rows = cache(partial(pipe.serial_env, partial(torchrl_pipeline.make_env, args.env, 20)))

    def tested(policy, seed: int) -> dict:
        greedy = policy.with_rule(epsilon=0.0)
        return {"greedy_test_return": torchrl_pipeline.mean_test_return(args, greedy, seed)}

    api = ActivePolicyIteration(
        spec.replace(seed=3, mode="active" if mode == "AL" else "passive"),
        env=rows,
        basis=torchrl_pipeline.BASIS[args.env](),
        selector=SamplingPolicySelector(env=rows) if mode == "AL" else None,
        evaluate=tested,
    )
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(8, ndim=1))
    with api:
        for m in api.schedule:
            api.choose()
            collector = Collector(rows(m), api.sampling_policy(), frames_per_batch=m * 20,
                                  total_frames=-1, trajs_per_batch=m, traj_format="padded",
                                  auto_register_policy_transforms=False)  # fmt: skip
            buffer.extend(next(iter(collector)))
            collector.shutdown()
            api.fit(buffer[:])
            api.improve()
    assert example["theta"] == api.theta.tolist() and example["bought"] == 8
    for row, record in zip(example["history"], api.history, strict=True):
        assert row["j_mean"] == (record.j_mean or []) and len(row["j_mean"]) == 4 * (mode == "AL")
        assert row["sampling_rule"] == record.sampling_rule
        assert row["rewarded_transitions"] == record.rewarded_transitions
        assert row["reward_free_transitions"] == record.reward_free_transitions
        assert row["greedy_test_return"] == record.performance["greedy_test_return"]


def test_acrobot_is_a_pipeline_env_of_at_most_15000_rewarded_transitions_a_run():
    """Acrobot-v1: observations scaled into [-1, 1] (cos, sin; the speeds by 4π and 9π), a
    quadratic Q̂ per action (3 × 28 features), and a default run that buys at most 15,000
    rewarded transitions (episodes of at most 500 steps: a DQN beside it runs 15,000 frames)."""
    args, spec = torchrl_pipeline.resolved(torchrl_pipeline.Args(env="Acrobot-v1"))
    assert sum(spec.rewarded.schedule) * spec.rewarded.num_steps <= 15_000
    assert spec.rewarded.num_steps == args.test_steps == 500 and spec.evaluation.fit == "lstd"
    env = torchrl_pipeline.make_env("Acrobot-v1", 50)
    env.set_seed(0)
    rollout = env.rollout(50, torchrl_pipeline.make_actor("Acrobot-v1"))
    obs = torch.cat([rollout["observation"], rollout["next", "observation"]])
    assert obs.shape[-1] == 6 and obs.abs().max() <= 1.0 and obs[:, 4:].abs().max() < 0.5
    assert torchrl_pipeline.BASIS["Acrobot-v1"]().num_features == 3 * 28


# -- the library's part ----------------------------------------------------------------------


def test_the_quadratic_basis_is_one_block_of_1_s_and_s_s_per_action():
    basis = QuadraticActionBasis(obs_dim=2, num_actions=3)
    s = torch.tensor([[2.0, 3.0]])
    assert basis.num_features == 3 * 6
    assert basis.kernels(s).tolist() == [[1.0, 2.0, 3.0, 4.0, 6.0, 9.0]]
    with pytest.raises(ValueError, match="obs must end in 2"):
        basis.kernels(torch.ones(1, 3))


def test_a_resume_with_other_test_settings_is_refused_naming_them(tmp_path, capsys):
    """The stored runs' greedy returns were measured with the first call's test: a resume with
    another (more test episodes, longer ones) would write them under the new settings."""
    args = [*PIPELINE_TINY, "--modes", "PL", "--seeds", "1", "--out-dir", str(tmp_path)]
    first = torchrl_pipeline.main(args)
    for flags, name in (
        (["--test-episodes", "3"], "test_episodes"),
        (["--test-steps", "25"], "test_steps"),
    ):
        with pytest.raises(SystemExit):
            torchrl_pipeline.main([*args, *flags, "--resume"])
        assert f"was made with other settings: ['settings.{name}']" in capsys.readouterr().err
    resumed = torchrl_pipeline.main([*args, "--resume"])["runs"]["PL"]["0"]  # the same test
    assert resumed["history"] == first["runs"]["PL"]["0"]["history"] and resumed["bought"] == 0
