"""ActivePolicyIteration checkpoints: resume equals an uninterrupted run; bad files are refused."""

import pickle

import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.basis import GaussianActionBasis
from torch_api.iteration import ActivePolicyIteration


def _api(path=None, trials=3, mode="active"):
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    return ActivePolicyIteration(
        env=lambda e: ChainWalkEnv(batch_size=e),
        basis=basis,
        schedule=(3, 2, 2),
        num_steps=10,
        gamma=GAMMA,
        mode=mode,
        num_repeats=2,
        psi_mode="grouped",
        num_trials=trials,
        seed=7,
        checkpoint_path=path,
    )


def _same_history(a, b):
    assert torch.equal(a.theta, b.theta)
    for ra, rb in zip(a.history, b.history, strict=True):
        assert (ra.chosen, ra.j_mean, ra.rewarded_transitions) == (
            rb.chosen,
            rb.j_mean,
            rb.rewarded_transitions,
        )


@pytest.mark.parametrize("interrupt", ["after_buy", "after_iteration"])
def test_resume_reproduces_the_uninterrupted_run(tmp_path, interrupt):
    full = _api()
    full.run()
    path = tmp_path / "run.pt"
    first = _api(path)
    first.step()
    if interrupt == "after_buy":
        first._buy()  # rewards of iteration 2 bought and saved, θ_2 not yet fitted
    resumed = _api(path)
    resumed.load(path)
    assert resumed.iteration == 1
    bought_before = len(resumed.rewarded)
    resumed.run()
    _same_history(full, resumed)
    assert resumed.rewarded_transitions == (3 + 2 + 2) * 10  # nothing bought twice
    if interrupt == "after_buy":
        assert bought_before == 3 + 2


def test_checkpoint_of_other_settings_is_refused(tmp_path):
    path = tmp_path / "run.pt"
    _api(path).step()
    with pytest.raises(ValueError, match=r"other settings: \['num_trials', 'trial_seeds'\]"):
        _api(trials=2).load(path)
    with pytest.raises(ValueError, match=r"other settings: \['mode'\]"):
        _api(mode="passive").load(path)


def test_truncated_checkpoint_is_refused_and_leaves_state_alone(tmp_path):
    path = tmp_path / "run.pt"
    _api(path).step()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    fresh = _api()
    with pytest.raises(ValueError, match="cannot read the checkpoint"):
        fresh.load(path)
    assert fresh.iteration == 0 and len(fresh.rewarded) == 0


class _Payload:
    def __reduce__(self):
        return (print, ("code ran",))


def test_checkpoint_carrying_a_pickled_object_is_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format": 1, "evil": _Payload()}, path, pickle_module=pickle)
    with pytest.raises(ValueError, match="cannot read the checkpoint"):
        _api().load(path)


def test_wrong_format_version_is_refused(tmp_path):
    path = tmp_path / "run.pt"
    api = _api(path)
    api.step()
    state = api.state_dict()
    state["format"] = 99
    torch.save(state, path)
    with pytest.raises(ValueError, match="checkpoint format 99"):
        _api().load(path)


def test_save_is_atomic_no_temporary_file_left(tmp_path):
    path = tmp_path / "run.pt"
    _api(path).step()
    assert path.exists() and not (tmp_path / "run.pt.tmp").exists()


class _FaultyChain(ChainWalkEnv):
    """A robot that breaks down on its 3rd step of rewarded collection in iteration 2."""

    steps = 0

    def _step(self, td):
        if self.batch_size[0] == 3 * 2:  # the rewarded env of T = 3 trials, M_2 = 2
            type(self).steps += 1
            if type(self).steps == 3:
                raise OSError("arm controller stopped responding")
        return super()._step(td)


def test_env_fault_while_buying_keeps_earlier_rewards_and_names_the_failure(tmp_path):
    path = tmp_path / "run.pt"
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    api = ActivePolicyIteration(
        env=lambda e: _FaultyChain(batch_size=e),
        basis=basis,
        schedule=(3, 2, 2),
        num_steps=10,
        gamma=GAMMA,
        num_repeats=2,
        psi_mode="grouped",
        num_trials=3,
        seed=7,
        checkpoint_path=path,
    )
    api.step()
    with pytest.raises(RuntimeError, match="iteration 2 failed: OSError: arm controller") as info:
        api.step()
    assert "The 3 episodes bought before (per trial) are kept" in str(info.value)
    assert len(api.rewarded) == 3
    resumed = _api()  # same settings, a healthy robot
    resumed.load(path)
    assert len(resumed.rewarded) == 3 and resumed.iteration == 1
    resumed.run()
    full = _api()
    full.run()
    _same_history(full, resumed)
