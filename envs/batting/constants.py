"""Constants of the ball-batting task (paper section 5): actions, noise, time steps, episode.

Units in the comments. The state is (phi1, phi1_dot, phi2, phi2_dot) (eq. 62).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

XML_PATH = Path(__file__).parents[1] / "assets" / "batting.xml"
N_ACTIONS = 2  # action 0 cocks the arm, action 1 swings it
ACTION_TORQUES = (
    (50.0, -35.0),
    (-50.0, 10.0),
)  # (N m) on joints 1 and 2, per action (eq. 63)
NOISE_VARIANCE = 3.0  # (N m)^2 variance of the Gaussian torque noise per joint
CONTROL_DT = 0.075  # (s) one control step: the paper's 10 physics steps of 7.5 ms
COARSE_DT = 0.0075  # (s) physics step of the swing away from the ball (the paper's, with RK4)
COARSE_INTEGRATOR = "rk4"  # integrator of the swing; the fine impact steps use Euler
FINE_DT = 0.000125  # (s) physics step of a coarse interval in which the bat nears the ball
# (m) predicted bat-ball gap below which a coarse interval is stepped at FINE_DT: 250 times the
# largest prediction error measured (0.02 mm); 5 cm before, which re-integrated near misses too
# (benchmarks/batting_fidelity.py: the same fidelity, 155 physics steps per episode, not 188)
MARGIN = 0.005
MAX_STEPS = 10  # control steps per episode (N of the paper)
# (rad, rad/s, rad, rad/s): phi1, phi1_dot, phi2, phi2_dot at the start of every episode
INITIAL_ARM_STATE = (math.pi / 4, 0.0, 0.0, 0.0)
LOOKAHEAD_MAX = 1.0  # (s) longest look-ahead for the end of the first ball-bat contact
PARK_Y = 1.0  # (m) a ball out of play rests on the ground this far beside the arm's plane
# (rad, rad/s, rad, rad/s) loose bounds of |observation| for Gymnasium's Box (joint limits are
# [0, pi/4] and [-pi/4, pi/4], soft by a few hundredths of a radian; speeds stay below 40 rad/s)
OBSERVATION_BOUND = (math.pi / 2, 100.0, math.pi / 2, 100.0)
PREDICT_POINTS = 8  # points per coarse interval at which the bat-ball gap is predicted
SETTLE_TIME = 0.2  # (s) time the ball is left to settle on its pin when the model is built


def action_torques(action: np.ndarray) -> np.ndarray:
    """Chosen torques [..., 2] (N m) of action indices [...] (eq. 63).

    Example:
        >>> action_torques(np.array([1, 0])).tolist()
        [[-50.0, 10.0], [50.0, -35.0]]
    """
    return np.asarray(ACTION_TORQUES, dtype=np.float64)[action]


# layout of MuJoCo's qpos / qvel rows of the model
QPOS_ARM = slice(0, 2)  # phi1, phi2 (rad)
QPOS_BALL = slice(2, 9)  # ball position (m) and orientation quaternion
QVEL_BALL = slice(2, 8)  # ball linear (m/s, world frame) and angular velocity (rad/s)
