"""TorchRL environments of the paper: the 10-state chain walk and the MuJoCo batting arm.

>>> from envs import BattingEnv, ChainWalkEnv
>>> ChainWalkEnv(batch_size=4).batch_size
torch.Size([4])

The environments' modules load on first use: ``import envs.chain_walk`` does not load
``envs.batting`` (the arm's model and its MuJoCo set-up).
"""

import importlib

import gymnasium

BATTING_GYM_ID = "torch_api/Batting-v0"  # Gymnasium id of envs.batting.BattingGymEnv

if BATTING_GYM_ID not in gymnasium.registry:  # importing twice must not register twice
    gymnasium.register(id=BATTING_GYM_ID, entry_point="envs.batting:BattingGymEnv")

_EXPORTS = {
    "BattingEnv": "envs.batting",
    "BattingGymEnv": "envs.batting",
    "BattingSimulator": "envs.batting",
    "ChainWalkEnv": "envs.chain_walk",
    "ChainWalkModel": "envs.chain_walk",
    "chain_walk_model": "envs.chain_walk",
}

__all__ = ["BATTING_GYM_ID", *_EXPORTS]


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'envs' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
