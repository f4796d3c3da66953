"""A run of ActivePolicyIteration that kills itself at the K-th event (for tests/test_faults.py).

Events: every environment step (so kills land inside reward-free and rewarded collection),
the middle of every checkpoint write (half the bytes written to the temporary file), and every
boundary between iterations. The process dies with ``os._exit`` — no cleanup, no flush — as a
SIGKILL would leave it.

    python tests/fault_driver.py CHECKPOINT RESULT.json KILL_AT   (KILL_AT < 0: never)
"""

import json
import os
import sys

import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api import iteration as iteration_module
from torch_api.basis import GaussianActionBasis
from torch_api.iteration import ActivePolicyIteration

KILLED = 137


def main(checkpoint: str, result: str, kill_at: int) -> None:
    events = {"count": 0}

    def event() -> None:
        events["count"] += 1
        if events["count"] == kill_at:
            os._exit(KILLED)

    step = ChainWalkEnv._step

    def dying_step(self, td):
        event()
        return step(self, td)

    ChainWalkEnv._step = dying_step
    save = torch.save

    def dying_save(obj, path, *args, **kwargs):
        save(obj, path, *args, **kwargs)
        with open(path, "rb+") as handle:  # leave a half-written temporary file behind
            size = os.path.getsize(path)
            if events["count"] + 1 == kill_at:
                handle.truncate(size // 2)
        event()

    iteration_module.torch.save = dying_save
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    api = ActivePolicyIteration(
        env=lambda e: ChainWalkEnv(batch_size=e),
        basis=basis,
        schedule=(3, 2, 2, 1),
        num_steps=10,
        gamma=GAMMA,
        num_repeats=2,
        psi_mode="grouped",
        num_trials=2,
        seed=3,
        checkpoint_path=checkpoint,
    )
    if os.path.exists(checkpoint):
        api.load(checkpoint)
    while api.iteration < len(api.schedule):
        event()
        api.step()
    episodes = api.rewarded.episodes()
    out = {
        "events": events["count"],
        "theta": api.theta.tolist(),
        "chosen": [r.chosen for r in api.history],
        "j_mean": [r.j_mean for r in api.history],
        "episodes_per_trial": len(api.rewarded),
        "iteration_tags": episodes["iteration"][:, :, 0].tolist(),
        "observations": episodes["observation"].flatten().tolist(),
        "rewards": episodes["next", "reward"].flatten().tolist(),
    }
    with open(result, "w") as handle:
        json.dump(out, handle)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]))
