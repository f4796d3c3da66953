"""The README's Python examples run as written, and the own loop gives the θ of ``run()``."""

import re
import warnings
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, StepCounter, TransformedEnv

from torch_api import ActivePolicyIteration, SamplingPolicySelector

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks() -> list[str]:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    assert len(blocks) == 2, "the README has its two Python examples"
    return blocks


def _run(block: str) -> dict:
    namespace: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        exec(compile(block, str(README), "exec"), namespace)  # noqa: S102
    # In a few of the chain walk's 100 trials an early sampling policy is far from the
    # evaluation policy and the library says so; that is the only warning an example may give.
    unexpected = [
        w
        for w in caught
        if "importance weights collapsed" not in str(w.message)
        and not issubclass(w.category, DeprecationWarning)
    ]
    assert not unexpected, [f"{w.category.__name__}: {w.message}" for w in unexpected]
    return namespace


def test_the_own_loop_gives_the_theta_of_run():
    mine = _run(_blocks()[0])
    n, spec = mine["N"], mine["spec"]
    env = TransformedEnv(GymEnv("CartPole-v1"), StepCounter(max_steps=n))
    api = ActivePolicyIteration(
        spec,
        env=env,
        basis=mine["basis"],
        selector=SamplingPolicySelector(env=env),  # reward-free episodes from the env, as there
        collector=lambda policy, m: Collector(
            env,
            policy,
            frames_per_batch=m * n,
            total_frames=-1,
            trajs_per_batch=m,
            traj_format="padded",
            auto_register_policy_transforms=False,
        ),
    )
    api.run()
    assert len(mine["api"].history) == len(api.history) == len(spec.rewarded.schedule)
    assert torch.equal(mine["api"].theta, api.theta)


def test_the_loop_in_one_call_runs_and_stores_its_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the example stores its run under runs/
    namespace = _run(_blocks()[1])
    assert len(namespace["history"]) == 7
    assert namespace["api"].rewarded_transitions == (5 + 5 + 3 + 3 + 3 + 1 + 1) * 10
    assert (tmp_path / "runs" / "chain.db").exists()
