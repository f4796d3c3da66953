"""The same code on every device torch sees here: CPU always, CUDA where a GPU is present.

Each test runs a computation on ``device`` and compares it with the same computation on the
CPU. On a machine without a GPU only ``device = "cpu"`` runs (then the comparison checks that
an explicit device changes nothing); on a GPU machine the CUDA case checks that the GPU gives
the CPU's numbers: the same random episodes (random numbers are drawn on the CPU), the same
choices, and J and θ equal to rounding.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from envs.batting import MAX_STEPS, BattingEnv
from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api._checks import _check_device
from torch_api.core.basis import GaussianActionBasis
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.policies import LinearQPolicy

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import chain_walk_api  # noqa: E402
import chain_walk_one_step  # noqa: E402
from train_batting import make_basis  # noqa: E402

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
RTOL = 1e-9  # float64 algebra: CPU and GPU differ by the order of their sums only


def _chain_walk_run(device: str, mode: str) -> ActivePolicyIteration:
    """Three batched chain-walk trials with the walks, the rollouts and the algebra on device."""
    spec = RunSpec.of(
        schedule=(5, 3, 2),
        num_steps=10,
        gamma=GAMMA,
        psi_mode="grouped",
        num_trials=3,
        seed=5,
        mode=mode,
        **({"num_repeats": 3} if mode == "active" else {}),
    )
    api = ActivePolicyIteration(
        spec,
        env=lambda e: ChainWalkEnv(batch_size=e, seed=11, device=device),
        selector=SamplingPolicySelector(
            env=lambda e: ChainWalkEnv(batch_size=e, seed=12, device=device)
        )
        if mode == "active"
        else None,
        basis=GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2),
        device=device,
    )
    api.run()
    return api


def _assert_same_history(run: ActivePolicyIteration, reference: ActivePolicyIteration) -> None:
    torch.testing.assert_close(run.theta, reference.theta, rtol=RTOL, atol=1e-12)
    for ours, theirs in zip(run.history, reference.history, strict=True):
        assert ours.chosen == theirs.chosen
        if theirs.j_mean is not None:
            torch.testing.assert_close(
                torch.tensor(ours.j_mean), torch.tensor(theirs.j_mean), rtol=RTOL, atol=0
            )
    ours, theirs = run.rewarded.episodes(), reference.rewarded.episodes()
    assert torch.equal(ours["observation"].cpu(), theirs["observation"].cpu())
    assert torch.equal(ours["action"].cpu(), theirs["action"].cpu())


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", ["active", "passive"])
def test_chain_walk_iteration_on_device_gives_the_cpu_numbers(device, mode):
    run = _chain_walk_run(device, mode)
    assert run.theta.isfinite().all()
    _assert_same_history(run, _chain_walk_run("cpu", mode))


@pytest.mark.parametrize("device", DEVICES)
def test_chain_walk_env_on_device_draws_the_cpu_walks(device):
    env = ChainWalkEnv(batch_size=6, max_steps=4, device=device, seed=3)
    env.set_block_seeds([1, 2, 3])
    cpu = ChainWalkEnv(batch_size=6, max_steps=4, seed=3)
    cpu.set_block_seeds([1, 2, 3])
    policy = LinearQPolicy(
        basis=GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2),
        theta=torch.linspace(-1, 1, 12, dtype=torch.float64),
        epsilon=0.3,
        action_spec=env.action_spec,
    )
    ours = env.rollout(
        8, policy=policy.with_streams(torch.Generator().manual_seed(0)), break_when_any_done=False
    )
    theirs = cpu.rollout(
        8, policy=policy.with_streams(torch.Generator().manual_seed(0)), break_when_any_done=False
    )
    assert ours["next", "observation"].device.type == torch.device(device).type
    assert torch.equal(ours["next", "observation"].cpu(), theirs["next", "observation"])
    assert torch.equal(ours["action"].cpu(), theirs["action"])


@pytest.mark.parametrize("device", DEVICES)
def test_batting_algebra_on_device_gives_the_cpu_numbers(device):
    """Physics on the CPU, psi_hat, J and the solves on ``device`` (2 trials, tiny budget)."""

    def run(where: str) -> ActivePolicyIteration:
        spec = RunSpec.of(
            schedule=(3, 2), num_steps=MAX_STEPS, gamma=1.0, num_repeats=2, num_trials=2, seed=4
        )
        api = ActivePolicyIteration(
            spec,
            env=lambda e: BattingEnv(batch_size=e, seed=1),
            selector=SamplingPolicySelector(env=lambda e: BattingEnv(batch_size=e, seed=2)),
            basis=make_basis(),
            device=where,
        )
        api.run()
        return api

    _assert_same_history(run(device), run("cpu"))


@pytest.mark.parametrize("device", DEVICES)
def test_one_step_example_on_device_gives_the_cpu_numbers(device, tmp_path):
    tiny = ["--trials", "3", "--repeats", "2", "--candidates", "3", "--episodes", "4"]
    ours = chain_walk_one_step.main([*tiny, "--device", device, "--out-dir", str(tmp_path / "a")])
    theirs = chain_walk_one_step.main([*tiny, "--out-dir", str(tmp_path / "b")])
    for base, result in ours["results"].items():
        for key in ("j_prime", "g_true"):
            torch.testing.assert_close(
                torch.tensor(result[key]),
                torch.tensor(theirs["results"][base][key]),
                rtol=RTOL,
                atol=1e-15,
            )


@pytest.mark.parametrize("device", DEVICES)
def test_figure8_example_on_device_gives_the_cpu_numbers(device, tmp_path):
    tiny = ["--trials", "3", "--iterations", "2", "--repeats", "2", "--test-episodes", "4"]
    ours = chain_walk_api.main([*tiny, "--device", device, "--out-dir", str(tmp_path / "a")])
    theirs = chain_walk_api.main([*tiny, "--out-dir", str(tmp_path / "b")])
    for name, result in ours["results"].items():
        for method, run in result["runs"].items():
            reference = theirs["results"][name]["runs"][method]["iterations"]
            for it, it_cpu in zip(run["iterations"], reference, strict=True):
                assert it.get("chosen") == it_cpu.get("chosen")
                for key in ("test_return", "exact_return"):
                    torch.testing.assert_close(
                        torch.tensor(it[key]), torch.tensor(it_cpu[key]), rtol=RTOL, atol=1e-12
                    )


def test_device_argument_is_checked(tmp_path, capsys):
    assert _check_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="device must name a torch device, got 'no-such-device'"):
        _check_device("no-such-device")
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ValueError, match=f"torch sees {gpus} CUDA GPUs here"):
        _check_device(f"cuda:{gpus}")
    if gpus:
        assert _check_device("cuda") == torch.device("cuda")
    # the examples: a device torch cannot name is one line, exit 2, before any work
    with pytest.raises(SystemExit) as stop:
        chain_walk_api.main(["--device", "no-such-device", "--out-dir", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.startswith("error: ") and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()
