"""The TorchRL plumbing of ``examples/torchrl_pipeline.py`` that is not the user's own.

Rows of an env in one ``SerialEnv`` (:func:`serial_env`) and the mean return of seeded test
episodes (:func:`mean_return`). Each run of the example is one
:class:`~torch_api.ActivePolicyIteration` (its steps, stores and streams); the runs over seeds,
their summary and files: :mod:`torch_api.experiment.seeds`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchrl.envs import EnvBase, SerialEnv
from torchrl.envs.utils import set_exploration_type

from torch_api.data.episodes import as_episodes

__all__ = ["mean_return", "serial_env"]


def serial_env(make_env: Callable[[], EnvBase], rows: int, seed: int | None = None) -> SerialEnv:
    """``rows`` envs of ``make_env`` in one ``SerialEnv`` ``[rows]``, seeded if ``seed`` is set."""
    env = SerialEnv(rows, make_env)
    if seed is not None:
        env.set_seed(seed)
    return env


def mean_return(
    policy, make_env: Callable[[], EnvBase], rows: int, steps: int, seed: int, exploration
) -> float:
    """The mean return of ``policy`` under ``exploration`` over ``rows`` test episodes of at
    most ``steps`` steps: one rollout of ``rows`` envs of ``make_env`` in a ``SerialEnv``, the
    envs and torch's generator seeded with ``seed``, the steps after each end masked."""
    torch.manual_seed(seed)
    env = serial_env(make_env, rows, seed)
    with set_exploration_type(exploration):
        rollout = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    done = as_episodes(rollout, rewarded=True)
    return float((done["next", "reward"] * done["mask"]).sum(-1).mean())
