"""Quiet by default: the library logs through ``logging`` and keeps TorchRL's notices out.

TorchRL writes ``[torchrl][INFO] Initialized LazyTensorStorage ...`` to stdout through a handler
of its own the first time a storage is written. The checks run in a fresh interpreter, as a
user's script would, and read what reaches its stdout.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import torch

from envs.chain_walk import CENTERS, TAU, ChainWalkEnv
from torch_api import ActivePolicyIteration, GaussianActionBasis, RunSpec

ROOT = Path(__file__).resolve().parents[1]
NOTICE = "Initialized LazyTensorStorage"

SCRIPT = textwrap.dedent(
    """
    import logging, sys
    import torch
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    from torch_api.data import EpisodeBuffer

    if sys.argv[1] == "debug":
        logging.getLogger("torchrl").setLevel(logging.DEBUG)
    m, n = 2, 3
    episodes = TensorDict(
        {
            "observation": torch.ones(m, n, 1),
            "action": torch.zeros(m, n, dtype=torch.long),
            "sample_probs": torch.full((m, n, 2), 0.5, dtype=torch.float64),
            ("next", "observation"): torch.ones(m, n, 1),
            ("next", "terminated"): torch.zeros(m, n, dtype=torch.bool),
            ("next", "reward"): torch.zeros(m, n),
            "mask": torch.ones(m, n, dtype=torch.bool),
        },
        batch_size=[m, n],
    )
    torchrl_logger = logging.getLogger("torchrl")
    before = (torchrl_logger.level, list(torchrl_logger.filters), list(torchrl_logger.handlers))
    print("--library--", flush=True)
    EpisodeBuffer(rewarded=True, capacity=10).extend(episodes)
    sys.stdout.flush()
    after = (torchrl_logger.level, list(torchrl_logger.filters), list(torchrl_logger.handlers))
    print("--torchrl--", flush=True)
    TensorDictReplayBuffer(storage=LazyTensorStorage(10, ndim=1)).extend(episodes.clone())
    sys.stdout.flush()
    print("--unchanged--", before == after, flush=True)
    """
)


def _run(mode: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("RL_LOGGING_LEVEL", None)
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, mode],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    out = done.stdout
    library, rest = out.split("--library--")[1].split("--torchrl--")
    torchrl, unchanged = rest.split("--unchanged--")
    return {"library": library, "torchrl": torchrl, "unchanged": unchanged.strip()}


def test_buffers_do_not_print_torchrl_storage_notices_and_change_nothing_global():
    out = _run("default")
    assert NOTICE in out["torchrl"]  # TorchRL itself does print it: the check is live
    assert NOTICE not in out["library"]
    assert out["unchanged"] == "True"  # level, filters, handlers of "torchrl" as before


def test_the_notices_show_when_torchrl_detail_is_asked_for():
    assert NOTICE in _run("debug")["library"]


def test_the_loop_logs_each_iteration_on_the_torch_api_logger(caplog):
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    spec = RunSpec.of(schedule=(2, 1), num_steps=5, gamma=0.9, mode="passive", num_trials=1, seed=0)
    api = ActivePolicyIteration(
        spec, env=lambda rows: ChainWalkEnv(batch_size=rows, seed=0), basis=basis
    )
    with caplog.at_level(logging.INFO, logger="torch_api"):
        api.run()
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("torch_api")]
    assert len(lines) == 2 and "passive iteration 2/2 done" in lines[1]
    assert "15 rewarded transitions per trial" in lines[1]
    assert "flattening ν 1, effective sample size" in lines[1]
