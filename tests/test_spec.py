"""The run's specification (torch_api/loop/spec.py): a bad value is refused when the spec is
made, naming the field; the spec reads back from its JSON as it was."""

from __future__ import annotations

import math

import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api import ActivePolicyIteration, GaussianActionBasis, RunSpec

BASE = {"schedule": (3, 2), "num_steps": 10, "gamma": 0.9}


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"gamma": "0.9"}, r"evaluation\.gamma must be a number, got '0\.9'"),
        ({"gamma": None}, r"evaluation\.gamma must be a number, got None"),
        ({"gamma": 1.5}, r"evaluation\.gamma must lie in \(0, 1\], got 1\.5"),
        ({"gamma": math.nan}, r"evaluation\.gamma must be finite, got nan"),
        ({"num_repeats": 2.5}, r"selection\.num_repeats must be an integer, got 2\.5"),
        ({"num_repeats": 0}, r"selection\.num_repeats must be >= 1, got 0"),
        ({"seed": -1}, r"trials\.seed must be >= 0, got -1"),
        ({"seed": 2**70}, rf"trials\.seed must be <= {2**63 - 1}, got {2**70}"),
        ({"seed": 1.5}, r"trials\.seed must be an integer, got 1\.5"),
        ({"schedule": (10**7,), "num_steps": 10**3}, r"rewarded\.schedule × num_steps = "),
        ({"schedule": (3, 0)}, r"rewarded\.schedule\[1\] must be >= 1, got 0"),
        ({"num_steps": True}, r"rewarded\.num_steps must be an integer, got True"),
        ({"lam": 0}, r"evaluation\.lam must be >= 1e-10 .*got 0"),
        ({"lam": -1.0}, r"evaluation\.lam must be >= 1e-10 .*got -1\.0"),
        ({"epsilon": 2}, r"policy\.epsilon must lie in \[0, 1\], got 2"),
        ({"epsilon_decay": "linear"}, r"policy\.epsilon_decay must be one of .*got 'linear'"),
        (
            {"candidate_offsets": (0.0, math.nan)},
            r"policy\.candidate_offsets\[1\] must be finite, got nan",
        ),
        ({"candidate_offsets": ()}, r"policy\.candidate_offsets must not be empty"),
        ({"num_trials": 2, "trial_seeds": (1, 2, 3)}, r"trials\.trial_seeds needs one seed per"),
        ({"trial_seeds": (1,)}, r"trials\.trial_seeds needs one seed per trial: 1 seeds for"),
        ({"num_trials": 2, "trial_seeds": (1, -2)}, r"trials\.trial_seeds\[1\] must be >= 0"),
        ({"fit": "lstd", "psi_mode": "grouped"}, r"evaluation\.fit='lstd' needs evaluation\."),
        ({"improvement": "softmax"}, r"policy\.improvement='softmax' needs policy\.beta > 0"),
        ({"beta": 1.0}, r"policy\.beta applies to improvement='softmax'"),
        ({"flattening": 1.5}, r"evaluation\.flattening must be 'iwcv' or lie in \[0, 1\]"),
        ({"rewarded_slice": "row"}, r"rewarded\.rewarded_slice must be one of"),
        ({"no_such_setting": 1}, r"unknown settings \['no_such_setting'\]"),
    ],
)
def test_a_bad_value_is_refused_when_the_spec_is_made_naming_the_field(settings, message):
    with pytest.raises(ValueError, match=message):
        RunSpec.of(**(BASE | settings))


def test_selection_settings_are_refused_in_a_passive_run():
    with pytest.raises(ValueError, match=r"\['num_repeats'\] are settings of active learning"):
        RunSpec.of(**BASE, num_repeats=2, mode="passive")
    with pytest.raises(ValueError, match="mode must be one of"):
        RunSpec.of(**BASE, mode="pasive")


def test_the_spec_is_normalised_frozen_and_reads_back_from_its_json():
    spec = RunSpec.of(
        **BASE, num_repeats=3, seed=4.0, num_trials=2, trial_seeds=[5, 6], initial_theta=[0.5] * 3
    )
    assert spec.trials.seed == 4 and isinstance(spec.trials.seed, int)
    assert spec.trials.trial_seeds == (5, 6) and spec.policy.initial_theta == (0.5, 0.5, 0.5)
    assert RunSpec.from_dict(spec.to_dict()) == spec
    assert RunSpec.of(**spec.flat()) == spec
    with pytest.raises(AttributeError):
        spec.trials.seed = 5  # frozen
    assert spec.replace(lam=1e-2).evaluation.lam == 1e-2 and spec.evaluation.lam == 1e-3
    passive = spec.replace(mode="passive")
    assert passive.selection is None and passive.mode == "passive"


def test_a_stored_spec_with_a_bad_value_is_refused_naming_the_field():
    data = RunSpec.of(**BASE).to_dict()
    data["evaluation"]["gamma"] = 1.5
    with pytest.raises(ValueError, match=r"evaluation\.gamma must lie in \(0, 1\], got 1\.5"):
        RunSpec.from_dict(data)
    data = RunSpec.of(**BASE).to_dict() | {"extra": {}}
    with pytest.raises(ValueError, match=r"unknown sections \['extra'\]"):
        RunSpec.from_dict(data)


def test_the_loop_takes_a_spec_and_checks_theta_0_against_the_basis():
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)

    def env(rows):
        return ChainWalkEnv(batch_size=rows)

    with pytest.raises(ValueError, match="spec must be a RunSpec"):
        ActivePolicyIteration(dict(BASE), env=env, basis=basis)  # the old flat keywords
    spec = RunSpec.of(schedule=(2,), num_steps=5, gamma=GAMMA, initial_theta=(1.0,) * 11)
    with pytest.raises(ValueError, match=r"policy\.initial_theta has 11 values; .* B = 12"):
        ActivePolicyIteration(spec, env=env, basis=basis)
    theta = tuple(torch.linspace(-1, 1, 12).tolist())
    api = ActivePolicyIteration(spec.replace(initial_theta=theta), env=env, basis=basis)
    assert api.theta.dtype == torch.float64 and api.theta.tolist() == list(theta)
