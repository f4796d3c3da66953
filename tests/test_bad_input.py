"""Every row of the README's bad-input table not covered next to its module: a clear error."""

import pytest
import torch
from tensordict import TensorDict

from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.data import EpisodeBuffer
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.spec import RunSpec
from torch_api.policies import TabularPolicy

NO_SUCH_GPU = "cuda:99" if torch.cuda.is_available() else "cuda"


def _basis():
    return GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)


OBJECTS = {"env", "basis", "selector", "device"}  # the loop's arguments besides the spec


def _api(**overrides):
    settings = {
        "schedule": (2, 2),
        "num_steps": 5,
        "gamma": 0.9,
        "psi_mode": "grouped",
        "num_trials": 2,
    } | {k: v for k, v in overrides.items() if k not in OBJECTS}
    objects = {"env": lambda e: ChainWalkEnv(batch_size=e), "basis": _basis()} | {
        k: v for k, v in overrides.items() if k in OBJECTS
    }
    return ActivePolicyIteration(RunSpec.of(mode="passive", **settings), **objects)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"lam": 0.0}, r"evaluation.lam must be >= 1e-10 .* got 0.0"),
        ({"lam": -1e-3}, r"evaluation.lam must be >= 1e-10 .* got -0.001"),
        ({"gamma": 0.0}, r"evaluation.gamma must lie in \(0, 1\], got 0.0"),
        ({"gamma": 1.5}, r"evaluation.gamma must lie in \(0, 1\], got 1.5"),
        ({"schedule": (3, 0, 2)}, r"rewarded.schedule\[1\] must be >= 1, got 0"),
        ({"schedule": ()}, "rewarded.schedule must not be empty"),
        ({"epsilon": 1.5}, r"policy.epsilon must lie in \[0, 1\], got 1.5"),
        ({"epsilon": -0.1}, r"policy.epsilon must lie in \[0, 1\], got -0.1"),
        (
            {"initial_theta": tuple(torch.ones(11).tolist())},
            "policy.initial_theta has 11 values; the basis has B = 12 features",
        ),
        ({"selector": "active"}, "selector must be a SamplingPolicySelector or None"),
        (
            {"trial_seeds": [1, 2, 3]},
            "trials.trial_seeds needs one seed per trial: 3 seeds for num_trials=2",
        ),
        ({"num_trials": 0}, "trials.num_trials must be >= 1, got 0"),
        ({"env": ChainWalkEnv(batch_size=4)}, "num_trials needs env as a callable"),
        ({"lam": True}, "evaluation.lam must be a number, got True"),
        ({"lam": 1e-300}, "evaluation.lam must be >= 1e-10 .* got 1e-300"),
        ({"seed": 1.5}, "trials.seed must be an integer, got 1.5"),
        (
            {"candidate_offsets": (0.0, float("nan"))},
            r"policy.candidate_offsets\[1\] must be finite",
        ),
        ({"device": NO_SUCH_GPU}, f"device '{NO_SUCH_GPU}': torch sees"),
    ],
)
def test_api_arguments_are_checked_early(overrides, message):
    with pytest.raises(ValueError, match=message):
        _api(**overrides)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"tau": float("inf")}, "tau must be finite"),
        ({"tau": 1e-300}, "tau must be finite with 2·tau² a normal number, got 1e-300"),
        ({"num_actions": 2.5}, "num_actions must be an integer, got 2.5"),
    ],
)
def test_basis_arguments_are_checked_early(overrides, message):
    args = {"centers": torch.tensor(CENTERS)[:, None], "tau": TAU, "num_actions": 2} | overrides
    with pytest.raises(ValueError, match=message):
        GaussianActionBasis(**args)


def test_collapsed_importance_weights_warn_with_the_effective_sample_size():
    basis = _basis()
    psi = PsiHat(basis=basis, gamma=0.9, mode="grouped")

    def index(obs):
        return obs[..., 0].round().long() - 1

    uniform = TabularPolicy(
        table=torch.full((10, 2), 0.5, dtype=torch.float64), state_index=index, one_hot=False
    )
    env = ChainWalkEnv(batch_size=40, seed=0)
    td = env.rollout(80, uniform, break_when_any_done=False)
    episodes = TensorDict(
        {
            "observation": td["observation"],
            "action": td["action"],
            "sample_probs": td["sample_probs"],
            ("next", "observation"): td["next", "observation"],
            "mask": torch.ones(40, 80, dtype=torch.bool),
        },
        batch_size=[40, 80],
    )
    # an almost deterministic evaluation policy: products of up to 80 ratios of 1.998 or 0.002
    table = torch.tensor([[0.001, 0.999]] * 10, dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match=r"effective sample size \d+\.\d\d of n = 3200"):
        build_design(episodes, TabularPolicy(table=table, state_index=index), psi)


def test_buffers_refuse_episodes_of_other_trials():
    def episodes(trials):
        return TensorDict(
            {
                "observation": torch.ones(trials, 2, 3, 1),
                "action": torch.zeros(trials, 2, 3, dtype=torch.long),
                "sample_probs": torch.full((trials, 2, 3, 2), 0.5, dtype=torch.float64),
                ("next", "observation"): torch.ones(trials, 2, 3, 1),
                "mask": torch.ones(trials, 2, 3, dtype=torch.bool),
            },
            batch_size=[trials, 2, 3],
        )

    buffer = EpisodeBuffer(rewarded=False)
    buffer.extend(episodes(4))
    assert buffer.episodes().shape == (4, 2, 3)
    with pytest.raises(ValueError, match=r"episodes of trials \(4,\), got \(5,\)"):
        buffer.extend(episodes(5))
