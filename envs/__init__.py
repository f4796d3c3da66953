"""TorchRL environments of the paper: the 10-state chain walk and the MuJoCo batting arm."""

import gymnasium

BATTING_GYM_ID = "torch_api/Batting-v0"  # Gymnasium id of envs.batting.BattingGymEnv

if BATTING_GYM_ID not in gymnasium.registry:  # importing twice must not register twice
    gymnasium.register(id=BATTING_GYM_ID, entry_point="envs.batting:BattingGymEnv")
