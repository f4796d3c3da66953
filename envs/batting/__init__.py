"""The ball-batting robot of Akiyama, Hachiya & Sugiyama (2010), section 5, on MuJoCo.

One concept a file:

* :mod:`~envs.batting.constants`: actions, noise, time steps, the episode (units in comments);
* :mod:`~envs.batting.simulator`: :class:`BattingSimulator`, the batched physics in plain numpy
  (E simulations of ``assets/batting.xml`` in MuJoCo's thread pool, one 75 ms control step at a
  time);
* :mod:`~envs.batting.impact`: the integration scheme ("coarse swing, fine impact window"), the
  look-ahead for the end of the first contact and the launch;
* :mod:`~envs.batting.swing`: the contact-free coarse swing as batched tensor dynamics, checked
  against MuJoCo, with the arm's coefficients read from the model in
  :mod:`~envs.batting.arm_model`;
* :mod:`~envs.batting.flight`: the ball's closed-form flight and its carry;
* :mod:`~envs.batting.env`: :class:`BattingEnv`, the batched TorchRL env that draws the noise;
* :mod:`~envs.batting.gym_env`: :class:`BattingGymEnv`, one arm as a Gymnasium env (registered
  in ``envs/__init__.py`` as ``"torch_api/Batting-v0"``);
* :mod:`~envs.batting.hooks`: :class:`PhysicsHook`, how instrumentation observes the physics;
* :mod:`~envs.batting.paper_basis`: the paper's Gaussian grid for the algorithm (eq. 64-65),
  apart from the physics.

Nothing here imports ``torch_api``: the environment is usable without the algorithm.

Example:
    >>> from envs.batting import BattingEnv
    >>> BattingEnv(batch_size=2, seed=0).rollout(3)["next", "reward"].shape
    torch.Size([2, 3, 1])
"""

from .audit import PhysicsAudit as PhysicsAudit  # (a re-export)
from .constants import (
    ACTION_TORQUES,
    COARSE_DT,
    CONTROL_DT,
    FINE_DT,
    INITIAL_ARM_STATE,
    MARGIN,
    MAX_STEPS,
    N_ACTIONS,
    NOISE_VARIANCE,
    XML_PATH,
    action_torques,
)
from .env import BattingEnv
from .flight import flight_carry, flight_time
from .gym_env import BattingGymEnv
from .hooks import PhysicsHook
from .paper_basis import BASIS_CENTER_GRID, BASIS_TAU, basis_centers
from .simulator import BattingSimulator

__all__ = [
    "ACTION_TORQUES",
    "BASIS_CENTER_GRID",
    "BASIS_TAU",
    "COARSE_DT",
    "CONTROL_DT",
    "FINE_DT",
    "INITIAL_ARM_STATE",
    "MARGIN",
    "MAX_STEPS",
    "N_ACTIONS",
    "NOISE_VARIANCE",
    "XML_PATH",
    "BattingEnv",
    "BattingGymEnv",
    "BattingSimulator",
    "PhysicsHook",
    "action_torques",
    "basis_centers",
    "flight_carry",
    "flight_time",
]
