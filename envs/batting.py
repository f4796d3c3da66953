"""The ball-batting robot of Akiyama, Hachiya & Sugiyama (2010), section 5, on MuJoCo.

Three layers in one file:

* :class:`BattingSimulator`, the batched physics in plain numpy: E simulations of
  ``assets/batting.xml`` stepped in MuJoCo's native thread pool (:class:`mujoco.batch.Batch`),
  one control step (75 ms, the paper's 10 x 7.5 ms) at a time, with the integration scheme
  below and the look-ahead carry of the ball;
* :class:`BattingEnv`, a thin batched TorchRL wrapper that draws the torque noise;
* :class:`BattingGymEnv`, a single Gymnasium environment (registered in ``envs/__init__.py``
  as ``"torch_api/Batting-v0"``).

State s = (phi1, phi1_dot, phi2, phi2_dot) (eq. 62). Action 0 applies the torques (50, -35) N m
to joints 1 and 2 (it cocks the arm), action 1 applies (-50, 10) N m (it swings the bat) (eq.
63); the actual torque is the chosen one plus N(0, 3) noise (variance 3) per joint, drawn once
per control step. Initial state (pi/4, 0, 0, 0) with the ball resting on its pin. Reward: the
carry of the ball, given at the control step in which the bat first touches the ball, 0 at every
other step. Episodes never terminate; they are truncated after ``max_steps`` (10) steps.

Integration scheme ("coarse swing, fine impact window"). A uniform 7.5 ms step makes the impact
unphysical and a uniform fine step is expensive (docs/batting.md). Each control step is first
integrated at ``coarse_dt`` (the paper's 7.5 ms: 10 coarse intervals, with MuJoCo's RK4 so that
the swing stays accurate) on a coarse model in which the ball is frozen: coarse steps never
resolve a contact (the arm touches only the ball, and only in fine steps), so contacts and
sensors are off there and the ball's weight is compensated; a ball in play rests on its pin at
zero velocity whenever it is stepped coarsely, so it stays where it is. From the coarse states
at the interval boundaries the bat-ball gap inside every interval is predicted (cubic Hermite
interpolation of the arm angles through the boundary angles and velocities, the exact capsule
geometry of the bat, ``PREDICT_POINTS`` points per interval). A simulation whose ball is in play
and whose predicted gap falls below ``margin`` (5 cm) in some interval is re-integrated from the
saved boundary state before its first such interval: interval by interval, at ``fine_dt``
(0.125 ms Euler, 60 steps per interval; the ball-bat contact's time constant of 4 ms spans 32 of
them) where the predicted gap is below ``margin``, the ball touches the bat, or its launch is
still pending, and coarsely elsewhere. Once the ball has been launched and no longer touches the
bat it is parked (below) and the rest of the control step is coarse. So only the few intervals
(7.5 ms each) around an impact or a near miss are fine, not whole 75 ms control steps. In 2048
random episodes the predicted minimum gap of a fine interval was never more than 0.02 mm above
the fine simulation's, so the 5 cm margin is wide (benchmarks/batting_fidelity.py gives the
scheme's fidelity).

Carry. In the fine interval of the first contact, the launch is the first physics step after that
contact at which the ball touches neither the bat nor the pin (searched on through the following
fine intervals). From the launch state (position p, velocity v) the flight has no drag, so the
ball's lowest point first touches the ground (centre height = radius r) after
``t = (v_z + sqrt(v_z^2 + 2 g (p_z - r))) / g`` and the carry is the horizontal distance from
the pin to ``p + v t``. If the contact has not ended at the end of the control step, the
look-ahead continues a copy of the simulation at ``fine_dt`` with the same torque until it has.
After the ball has left the bat for good (launched, and not touching the bat at the end of an
interval), it is parked at rest on the ground beside the arm's plane (it plays no further part),
so later steps never meet a flying ball; the episode itself goes on.

MuJoCo stops a simulation whose accelerations blow up (its warning counters rise) instead of
stepping it: the simulator checks the counters after every call and raises ``RuntimeError``.

This module does not import ``torch_api``: the environment is usable without the algorithm.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import torch
from mujoco.batch import Batch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = [
    "ACTION_TORQUES",
    "BASIS_CENTER_GRID",
    "BASIS_TAU",
    "COARSE_DT",
    "CONTROL_DT",
    "FINE_DT",
    "basis_centers",
    "INITIAL_ARM_STATE",
    "MARGIN",
    "MAX_STEPS",
    "N_ACTIONS",
    "NOISE_VARIANCE",
    "XML_PATH",
    "BattingEnv",
    "BattingGymEnv",
    "BattingSimulator",
    "PhysicsAudit",
    "flight_carry",
]

XML_PATH = Path(__file__).parent / "assets" / "batting.xml"
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
MARGIN = 0.05  # (m) predicted bat-ball gap below which a coarse interval is stepped at FINE_DT
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
# The paper's basis (eq. 64-65), for the algorithm's side: 54 Gaussian centres on this grid
# (per state dimension: phi1 (rad), phi1_dot (rad/s), phi2 (rad), phi2_dot (rad/s)) and width τ.
BASIS_CENTER_GRID = (
    (0.0, math.pi / 4),
    (-math.pi, 0.0, math.pi),
    (-math.pi / 4, 0.0, math.pi / 4),
    (-math.pi, 0.0, math.pi),
)
BASIS_TAU = 3 * math.pi / 2  # (rad) kernel width τ of eq. 64

_QPOS_ARM = slice(0, 2)  # phi1, phi2 (rad)
_QPOS_BALL = slice(2, 9)  # ball position (m) and orientation quaternion
_QVEL_BALL = slice(2, 8)  # ball linear (m/s, world frame) and angular velocity (rad/s)
_SENSORS = ("bat_ball_dist", "bat_ball_contact", "pin_ball_contact")
_INTEGRATION_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}


def basis_centers() -> torch.Tensor:
    """The 54 Gaussian centres of the paper's batting basis (eq. 65), float64 ``[54, 4]``."""
    grids = torch.meshgrid(
        *[torch.tensor(g, dtype=torch.float64) for g in BASIS_CENTER_GRID], indexing="ij"
    )
    return torch.stack([g.reshape(-1) for g in grids], dim=-1)


def flight_carry(
    pos: np.ndarray, vel: np.ndarray, pin_xy: np.ndarray, radius: float, gravity: float
) -> np.ndarray:
    """Carry of a ball in free flight without drag, in closed form.

    The ball's centre moves as ``pos + vel t - g t^2 e_z / 2``; its lowest point first touches the
    ground when the centre height equals ``radius``. The carry is the horizontal distance from
    the pin to that point.

    Args:
        pos: ball centre at launch, [..., 3] (m).
        vel: ball velocity at launch, [..., 3] (m/s).
        pin_xy: the pin's horizontal position, [2] (m).
        radius: ball radius (m).
        gravity: magnitude of the gravitational acceleration (m/s^2).

    Returns:
        The carry [...] (m).

    Example:
        >>> float(flight_carry(np.array([0.0, 0, 1.04]), np.array([2.0, 0, 0]),
        ...                    np.zeros(2), 0.04, 9.81).round(4))
        0.903
    """
    height = np.maximum(pos[..., 2] - radius, 0.0)
    t = (vel[..., 2] + np.sqrt(vel[..., 2] ** 2 + 2.0 * gravity * height)) / gravity
    land = pos[..., :2] + vel[..., :2] * t[..., None]
    return np.linalg.norm(land - pin_xy, axis=-1)


def _positive_dt(value: float, name: str) -> float:
    value = float(value)
    if not value > 0.0:
        raise ValueError(f"{name} must be a positive time step (s), got {value!r}")
    steps = CONTROL_DT / value
    if abs(steps - round(steps)) > 1e-6:
        raise ValueError(f"{name} must divide CONTROL_DT = {CONTROL_DT} s, got {value!r}")
    return value


class PhysicsAudit:
    """Counts the physics steps of one or more simulators and keeps a random sample to replay.

    The physics floor of a run, the time bare MuJoCo needs for the same physics steps, depends
    on the states stepped (joint limits and contacts cost solver work), so it is estimated by
    replaying a uniform sample of the run's rollouts (start state, torque, number of steps)
    with nothing else around them and scaling by the counted steps
    (``benchmarks/_physics_floor.py``). The sampling draws from a stream of its own and never
    touches the environment's.

    Args:
        fraction: probability with which each simulation of each rollout call is sampled
            (0: count only).
        seed: seed of the sampling stream.

    Attributes:
        steps: physics steps counted, ``{"coarse": int, "fine": int}``.
        samples: per kind, a list of ``(states [r, nstate], torques [r, 2], nstep)``.
    """

    KINDS = ("coarse", "fine")

    def __init__(self, fraction: float = 0.0, seed: int = 0) -> None:
        if not 0.0 <= float(fraction) <= 1.0:
            raise ValueError(f"fraction must lie in [0, 1], got {fraction!r}")
        self.fraction = float(fraction)
        self.rng = np.random.default_rng(seed)
        self.steps = dict.fromkeys(self.KINDS, 0)
        self.samples: dict[str, list] = {kind: [] for kind in self.KINDS}

    def record(
        self, kind: str, states: np.ndarray, ids: np.ndarray, torque: np.ndarray, nstep: int
    ) -> None:
        """Count rollouts of ``nstep`` steps of simulations ``ids`` and sample some of them.

        ``states`` [E, nstate] are all simulations' states before the call, ``torque``
        [len(ids), 2] the torques of the simulations ``ids``.
        """
        self.steps[kind] += len(ids) * nstep
        if self.fraction > 0.0:
            keep = self.rng.random(len(ids)) < self.fraction
            if keep.any():
                self.samples[kind].append((states[ids[keep]], torque[keep].copy(), nstep))

    def merge(self, other: PhysicsAudit) -> PhysicsAudit:
        """Add another audit's counts and samples to this one (returns self)."""
        for kind in self.KINDS:
            self.steps[kind] += other.steps[kind]
            self.samples[kind].extend(other.samples[kind])
        return self

    def sampled_steps(self, kind: str) -> int:
        return sum(len(torque) * nstep for _, torque, nstep in self.samples[kind])


class BattingSimulator:
    """Batched MuJoCo physics of the batting arm, one control step at a time (numpy).

    Holds E simulations of ``assets/batting.xml``; :meth:`step` applies one torque pair per
    simulation for one control step (75 ms) with the scheme of the module docstring
    (``scheme="adaptive"``), or at ``fine_dt`` throughout (``scheme="uniform"``, the reference
    used to measure the scheme's fidelity). Noise is not drawn here: the torques given are the
    torques applied.

    Args:
        num_envs: number of simulations E.
        scheme: ``"adaptive"`` (coarse swing, fine impact) or ``"uniform"`` (fine everywhere).
        coarse_dt: physics step away from the ball (s); must divide 75 ms.
        fine_dt: physics step near the ball (s); must divide ``coarse_dt``.
        margin: predicted bat-ball gap (m) below which a coarse interval is re-integrated at
            ``fine_dt``; in (0, 1).
        coarse_integrator: ``"rk4"`` or ``"euler"``, the integrator of the coarse steps.
        nthread: threads of MuJoCo's pool; ``None``: ``min(E, os.cpu_count())``.
        record: keep the last control step's ``qpos`` in ``last_qpos``, one per ``fine_dt``
            (interpolated linearly across coarse steps; for pictures; slow).
        xml_path: the MJCF file.
        audit: a :class:`PhysicsAudit` to count (and sample) every physics rollout into.

    Example:
        >>> sim = BattingSimulator(num_envs=2)
        >>> obs = sim.reset()
        >>> obs, carry, first_hit = sim.step(np.array([[-50.0, 10.0], [50.0, -35.0]]))
        >>> obs.shape, carry.shape, first_hit.shape
        ((2, 4), (2,), (2,))
    """

    def __init__(
        self,
        *,
        num_envs: int,
        scheme: str = "adaptive",
        coarse_dt: float = COARSE_DT,
        fine_dt: float = FINE_DT,
        margin: float = MARGIN,
        coarse_integrator: str = COARSE_INTEGRATOR,
        nthread: int | None = None,
        record: bool = False,
        xml_path: str | Path = XML_PATH,
        audit: PhysicsAudit | None = None,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        if scheme not in ("adaptive", "uniform"):
            raise ValueError(f"scheme must be 'adaptive' or 'uniform', got {scheme!r}")
        self.num_envs = num_envs
        self.scheme = scheme
        self.coarse_dt = _positive_dt(coarse_dt, "coarse_dt")
        self.fine_dt = _positive_dt(fine_dt, "fine_dt")
        self.n_coarse = round(CONTROL_DT / self.coarse_dt)  # physics steps per coarse control step
        self.n_fine = round(CONTROL_DT / self.fine_dt)  # physics steps per fine control step
        self.record = bool(record)
        self.audit = audit

        spec = mujoco.MjSpec.from_file(str(xml_path))
        spec.body("ball").gravcomp = 1.0  # see below; compiled in, as MuJoCo counts such bodies
        self.coarse_model = spec.compile()
        self.coarse_model.opt.timestep = self.coarse_dt
        if coarse_integrator not in _INTEGRATORS:
            raise ValueError(
                f"coarse_integrator must be 'euler' or 'rk4', got {coarse_integrator!r}"
            )
        self.coarse_model.opt.integrator = _INTEGRATORS[coarse_integrator]
        # Coarse steps never see a contact: the arm touches only the ball, and only in fine
        # steps; a ball in play rests on its pin (a parked one on the ground) at zero velocity
        # whenever it is stepped coarsely. So the coarse model freezes the ball instead of
        # resolving its pin or ground contact at every RK4 stage (about 40 % of a step's cost):
        # contacts and sensors are off and the ball's weight is compensated.
        self.coarse_model.opt.disableflags |= (
            mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_SENSOR
        )
        self.fine_model = mujoco.MjModel.from_xml_path(str(xml_path))
        self.fine_model.opt.timestep = self.fine_dt
        model = self.fine_model
        self._sensor_adr = {name: int(model.sensor_adr[model.sensor(name).id]) for name in _SENSORS}
        if not 0.0 < float(margin) < 1.0:
            raise ValueError(f"margin must lie in (0, 1) m, got {margin!r}")
        self.margin = float(margin)
        if abs(self.coarse_dt / self.fine_dt - round(self.coarse_dt / self.fine_dt)) > 1e-6:
            raise ValueError(f"fine_dt {fine_dt!r} must divide coarse_dt {coarse_dt!r}")
        self.n_sub = round(self.coarse_dt / self.fine_dt)  # fine steps per coarse interval
        # arm geometry for the predicted bat-ball gap (the arm's bodies and the bat's capsules)
        self._shoulder = np.array(model.body("upper_arm").pos, dtype=np.float64)
        self._elbow_offset = np.array(model.body("bat").pos, dtype=np.float64)
        tau = np.linspace(0.0, 1.0, PREDICT_POINTS)[:, None]  # cubic Hermite basis [points, 4]
        self._hermite = np.concatenate(
            [
                2 * tau**3 - 3 * tau**2 + 1,
                tau**3 - 2 * tau**2 + tau,
                3 * tau**2 - 2 * tau**3,
                tau**3 - tau**2,
            ],
            axis=1,
        )
        self._capsules = []
        for geom_id in np.flatnonzero(model.geom_bodyid == model.body("bat").id):
            geom = model.geom(int(geom_id))
            if geom.type[0] != mujoco.mjtGeom.mjGEOM_CAPSULE or np.abs(geom.pos[:2]).max() > 0:
                raise ValueError("the bat must consist of capsules along its body's z axis")
            if not np.allclose(np.abs(geom.quat), (1.0, 0.0, 0.0, 0.0)):
                raise ValueError("the bat must consist of capsules along its body's z axis")
            lo, hi = geom.pos[2] - geom.size[1], geom.pos[2] + geom.size[1]
            self._capsules.append((float(lo), float(hi), float(geom.size[0])))
        self.ball_radius = float(model.geom("ball").size[0])  # (m)
        self.gravity = float(-model.opt.gravity[2])  # (m/s^2)
        pin = model.geom("pin")
        self.pin_xy = np.array(pin.pos[:2], dtype=np.float64)  # (m)

        if nthread is None:
            nthread = min(num_envs, os.cpu_count() or 1)
        self.main = Batch(self.coarse_model, nsim=num_envs, nthread=nthread)
        self.fine = Batch(self.fine_model, nsim=num_envs, nthread=nthread)
        self._nstate = self.main.nstate
        self._qpos_adr, _ = self._state_slice(mujoco.mjtState.mjSTATE_QPOS)
        self._qvel_adr, _ = self._state_slice(mujoco.mjtState.mjSTATE_QVEL)
        self._initial_state = self._settled_initial_state()

        self.hit = np.zeros(num_envs, dtype=bool)  # the bat has touched the ball
        self.in_play = np.ones(num_envs, dtype=bool)  # the ball is not yet parked
        self.carry = np.zeros(num_envs)  # (m) look-ahead carry of the first contact, 0 if none
        self.launch = np.full((num_envs, 6), np.nan)  # ball position (m), velocity (m/s)
        self.physics_steps = np.zeros(num_envs, dtype=np.int64)  # since the last reset
        self.fine_steps = np.zeros(num_envs, dtype=np.int64)  # of which at fine_dt
        self.last_qpos: list[np.ndarray] = []
        self._trace: dict | None = None
        self._warnings = self._warning_counts()

    # -- physics queries ----------------------------------------------------------------------

    def _state_slice(self, component: mujoco.mjtState) -> tuple[int, int]:
        """Offset and size of one component inside a state row."""
        offset = 0
        for bit in range(mujoco.mjtState.mjNSTATE.value):
            flag = 1 << bit
            if not flag & _INTEGRATION_STATE.value:
                continue
            size = mujoco.mj_stateSize(self.coarse_model, flag)
            if flag == component.value:
                return offset, size
            offset += size
        raise ValueError(f"state component {component} is not in the integration state")

    def _settled_initial_state(self) -> np.ndarray:
        """Integration state row of (pi/4, 0, 0, 0) with the ball at rest on its pin."""
        model, data = self.fine_model, mujoco.MjData(self.fine_model)
        phi1, dphi1, phi2, dphi2 = INITIAL_ARM_STATE
        for _ in range(round(SETTLE_TIME / self.fine_dt)):
            data.qpos[_QPOS_ARM] = (phi1, phi2)
            data.qvel[:2] = (dphi1, dphi2)
            mujoco.mj_step(model, data)
        data.qpos[_QPOS_ARM] = (phi1, phi2)
        data.qvel[:] = 0.0
        data.time = 0.0
        mujoco.mj_forward(model, data)
        row = np.empty(self._nstate)
        mujoco.mj_getState(model, data, row, _INTEGRATION_STATE)
        return row

    def _warning_counts(self) -> np.ndarray:
        return np.concatenate([self.main.warning[:, :, 1], self.fine.warning[:, :, 1]], axis=1)

    def _check_warnings(self) -> None:
        """Raise if MuJoCo flagged an unstable simulation (it then stops stepping it)."""
        counts = self._warning_counts()
        rose = (counts > self._warnings).any(axis=1)
        self._warnings = counts
        if rose.any():
            ids = np.flatnonzero(rose)
            raise RuntimeError(
                f"MuJoCo reported an unstable simulation (NaN or huge QACC) in envs "
                f"{ids.tolist()[:10]}; warning counts {counts[ids[0]].tolist()}"
            )

    def _qpos(self, states: np.ndarray) -> np.ndarray:
        return states[..., self._qpos_adr : self._qpos_adr + self.coarse_model.nq]

    def _qvel(self, states: np.ndarray) -> np.ndarray:
        return states[..., self._qvel_adr : self._qvel_adr + self.coarse_model.nv]

    def _sensor(self, sensordata: np.ndarray, name: str) -> np.ndarray:
        return sensordata[..., self._sensor_adr[name]]

    def _run(
        self,
        batch: Batch,
        ids: np.ndarray,
        torque: np.ndarray,
        nstep: int,
        qpos: bool = False,
        states: bool = False,
    ) -> dict:
        """Advance ``batch``'s simulations ``ids`` by ``nstep`` physics steps at fixed torque.

        Records ``sensordata`` (record k: the state before physics step k), and ``qpos`` and
        ``qvel`` if ``qpos``, the integration state (key ``_INTEGRATION_STATE.value``) if ``states``
        (record k: the state after physics step k).
        """
        if self.audit is not None:
            kind = "fine" if batch is self.fine else "coarse"
            self.audit.record(kind, batch.state, ids, torque, nstep)
        control = np.broadcast_to(torque[:, None, :], (len(ids), nstep, 2))
        record = ["sensordata"]
        if qpos:
            record += ["qpos", "qvel"]
        if states:
            record.append(_INTEGRATION_STATE.value)
        out = batch.rollout(nstep, control=control, record=record, ids=ids)
        self.physics_steps[ids] += nstep
        if batch is self.fine:
            self.fine_steps[ids] += nstep
        self._check_warnings()
        return out

    def observation(self) -> np.ndarray:
        """(phi1, phi1_dot, phi2, phi2_dot) of every simulation, float64 [E, 4]."""
        qpos, qvel = self._qpos(self.main.state), self._qvel(self.main.state)
        return np.stack([qpos[:, 0], qvel[:, 0], qpos[:, 1], qvel[:, 1]], axis=-1)

    def qpos(self) -> np.ndarray:
        """Generalised positions of every simulation, [E, nq] (phi1, phi2, ball pose)."""
        return self._qpos(self.main.state).copy()

    def ball_position(self) -> np.ndarray:
        """Ball centre of every simulation, [E, 3] (m)."""
        return self._qpos(self.main.state)[:, 2:5].copy()

    # -- episode control ----------------------------------------------------------------------

    def reset(self, ids: np.ndarray | None = None) -> np.ndarray:
        """Put simulations ``ids`` (all by default) back to the initial state; returns [E, 4]."""
        ids = np.arange(self.num_envs) if ids is None else np.asarray(ids, dtype=np.int64)
        self.main.state[ids] = self._initial_state
        self.hit[ids] = False
        self.in_play[ids] = True
        self.carry[ids] = 0.0
        self.launch[ids] = np.nan
        self.physics_steps[ids] = 0
        self.fine_steps[ids] = 0
        return self.observation()

    def step(self, torque: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance every simulation by one control step (75 ms) at the given torques.

        Args:
            torque: applied torques [E, 2] (N m) on joints 1 and 2.

        Returns:
            observation [E, 4]; carry [E] (m), nonzero only where ``first_hit``; first_hit [E],
            True in the control step in which the bat first touched the ball.
        """
        torque = np.asarray(torque, dtype=np.float64)
        if torque.shape != (self.num_envs, 2):
            raise ValueError(f"torque must have shape ({self.num_envs}, 2), got {torque.shape}")
        if not np.isfinite(torque).all():
            raise ValueError("torque must be finite")
        everyone = np.arange(self.num_envs)
        self._trace = {} if self.record else None
        if self.scheme == "uniform":
            states = None
            fine = np.ones((self.num_envs, self.n_coarse), dtype=bool)
        else:
            start = self.main.state.copy()
            out = self._run(self.main, everyone, torque, self.n_coarse, states=True)
            states = np.concatenate([start[:, None], out[_INTEGRATION_STATE.value]], axis=1)
            fine = self._near_intervals(states)
            if self.record:
                for i in everyone:
                    self._trace[i] = [(0, self._qpos(states[i, 0]))] + [
                        ((j + 1) * self.n_sub, self._qpos(states[i, j + 1]))
                        for j in range(self.n_coarse)
                    ]
        first_hit = np.zeros(self.num_envs, dtype=bool)
        carry = np.zeros(self.num_envs)
        ids = np.flatnonzero(fine.any(axis=1))
        if len(ids):
            self._refine(ids, states, fine[ids], torque[ids], first_hit, carry)
        self.hit |= first_hit
        self.carry[first_hit] = carry[first_hit]
        if self.record:
            self._finish_record()
        return self.observation(), carry, first_hit

    # -- the integration scheme ---------------------------------------------------------------

    def bat_ball_gap(self, phi1: np.ndarray, phi2: np.ndarray, ball: np.ndarray) -> np.ndarray:
        """Signed bat-ball distance (m) at arm angles ``phi1``, ``phi2`` [...] and ball centre
        ``ball`` [..., 3]: the same quantity as the ``bat_ball_dist`` sensor, without cutoff."""
        c1, s1 = np.cos(phi1), np.sin(phi1)
        ex, ey, ez = self._elbow_offset
        elbow = np.stack(
            [
                self._shoulder[0] + ex * c1 + ez * s1,
                self._shoulder[1] + ey + 0 * c1,
                self._shoulder[2] - ex * s1 + ez * c1,
            ],
            axis=-1,
        )
        c2, s2 = np.cos(phi1 - phi2), np.sin(phi1 - phi2)
        rel = ball - elbow
        # the ball centre in the bat's frame (rotation about y by phi1 - phi2, inverted)
        bx = rel[..., 0] * c2 - rel[..., 2] * s2
        bz = rel[..., 0] * s2 + rel[..., 2] * c2
        by = rel[..., 1]
        gap = np.full(np.shape(bx), np.inf)
        for z_lo, z_hi, radius in self._capsules:  # capsules along the bat's z axis
            dz = bz - np.clip(bz, z_lo, z_hi)
            gap = np.minimum(gap, np.sqrt(bx**2 + by**2 + dz**2) - radius)
        return gap - self.ball_radius

    def _near_intervals(self, states: np.ndarray) -> np.ndarray:
        """Coarse intervals to integrate at the fine step, bool [E, n_coarse].

        ``states`` [E, n_coarse + 1, nstate] are the coarse trajectory's states at the interval
        boundaries. Within each interval the arm angles are interpolated by cubic Hermite
        polynomials through the boundary angles and velocities (the ball, at rest on its pin,
        at the mean of its boundary positions), and the bat-ball gap is evaluated at
        ``PREDICT_POINTS`` points; an interval is near if that predicted gap falls below
        ``margin``. A hit ball still in play (it touched the bat at the end of the last step)
        makes every interval near; a parked ball none.
        """
        near = np.zeros((len(states), self.n_coarse), dtype=bool)
        rows = np.flatnonzero(self.in_play & ~self.hit)  # balls resting on their pins
        if len(rows):
            qpos, qvel = self._qpos(states[rows]), self._qvel(states[rows])
            # [E', n, 4 knots, 2 angles] -> [E', n, points, 2] by the Hermite basis
            knots = np.stack(
                [
                    qpos[:, :-1, :2],
                    qvel[:, :-1, :2] * self.coarse_dt,
                    qpos[:, 1:, :2],
                    qvel[:, 1:, :2] * self.coarse_dt,
                ],
                axis=2,
            )
            arm = self._hermite @ knots
            ball = 0.5 * (qpos[:, :-1, None, 2:5] + qpos[:, 1:, None, 2:5])  # at rest
            gap = self.bat_ball_gap(arm[..., 0], arm[..., 1], ball).min(axis=-1)
            near[rows] = gap < self.margin
        near[self.in_play & self.hit] = True  # a hit ball still touching the bat
        return near

    def _refine(
        self,
        ids: np.ndarray,
        states: np.ndarray | None,
        near: np.ndarray,
        torque: np.ndarray,
        first_hit: np.ndarray,
        carry: np.ndarray,
    ) -> None:
        """Re-integrate simulations ``ids`` from their first near interval to the step's end.

        Interval by interval, a simulation is stepped at ``fine_dt`` (``n_sub`` Euler steps)
        where ``near`` says so or where its ball is touching the bat or awaits its launch, and
        at ``coarse_dt`` (one step) elsewhere. A launched ball that no longer touches the bat
        is parked at the end of the interval. ``states`` None (uniform scheme) starts every
        simulation from its current state and steps every interval finely.
        """
        n = self.n_coarse
        start = np.argmax(near, axis=1)  # first near interval
        if states is None:
            cur = self.main.state[ids].copy()
        else:
            cur = states[ids, start].copy()
        pending = np.zeros(len(ids), dtype=bool)  # first contact made, launch not yet found
        touching = np.zeros(len(ids), dtype=bool)  # bat contact at the end of the last interval
        finished = np.zeros(len(ids), dtype=bool)  # stepped to the end of the control step
        for j in range(int(start.min()), n):
            active = (start <= j) & ~finished
            if self.scheme == "uniform":
                fine = active
            else:
                fine = active & self.in_play[ids] & (near[:, j] | pending | touching)
                # the rest of the step is coarse where no fine interval can follow: one call
                rest = active & ~fine & (~self.in_play[ids] | ~near[:, j:].any(axis=1))
                rest &= ~pending & ~touching
                self._coarse_intervals(ids, np.flatnonzero(rest), cur, torque, j, n - j)
                finished |= rest
                self._coarse_intervals(
                    ids, np.flatnonzero(active & ~fine & ~rest), cur, torque, j, 1
                )
            fine = np.flatnonzero(fine)
            if len(fine) == 0:
                continue
            chunk_start = cur[fine].copy()
            self.fine.state[ids[fine]] = chunk_start
            out = self._run(self.fine, ids[fine], torque[fine], self.n_sub, qpos=True)
            cur[fine] = self.fine.state[ids[fine]]
            self._trace_add(ids[fine], j, out, coarse=False)
            bat = self._sensor(out["sensordata"], "bat_ball_contact") > 0  # [F, n_sub]
            pin = self._sensor(out["sensordata"], "pin_ball_contact") > 0
            for f, i in enumerate(fine):
                env = ids[i]
                k0 = 0
                if not (self.hit[env] or first_hit[env] or pending[i]) and bat[f].any():
                    first_hit[env] = pending[i] = True
                    k0 = int(np.argmax(bat[f]))
                if not pending[i]:
                    continue
                free = np.flatnonzero(~bat[f, k0:] & ~pin[f, k0:])
                if len(free) == 0:
                    continue
                k = k0 + int(free[0])  # state k: the chunk's start or after physics step k - 1
                state = chunk_start[f] if k == 0 else None
                pos = self._qpos(state)[2:5] if k == 0 else out["qpos"][f, k - 1, 2:5]
                vel = self._qvel(state)[2:5] if k == 0 else out["qvel"][f, k - 1, 2:5]
                carry[env] = self._record_launch(env, pos, vel)
                pending[i] = False
            touching[fine] = bat[:, -1]
            launched = self.hit[ids[fine]] | first_hit[ids[fine]]
            park = launched & ~pending[fine] & ~touching[fine] & self.in_play[ids[fine]]
            cur[fine[park]] = self._parked(ids[fine[park]], cur[fine[park]])
        if pending.any():  # the first contact lasts beyond the step: look ahead on a copy
            p = np.flatnonzero(pending)
            self.fine.state[ids[p]] = cur[p]
            carry[ids[p]] = self._look_ahead(ids[p], torque[p])
        self.main.state[ids] = cur

    def _coarse_intervals(
        self,
        ids: np.ndarray,
        rows: np.ndarray,
        cur: np.ndarray,
        torque: np.ndarray,
        j: int,
        nstep: int,
    ) -> None:
        """Step ``cur[rows]`` (simulations ``ids[rows]``) coarsely over intervals j .. j+nstep."""
        if len(rows) == 0:
            return
        self.main.state[ids[rows]] = cur[rows]
        out = self._run(self.main, ids[rows], torque[rows], nstep, qpos=self.record)
        cur[rows] = self.main.state[ids[rows]]
        self._trace_add(ids[rows], j, out, coarse=True)

    def _trace_add(self, ids: np.ndarray, j: int, out: dict, coarse: bool) -> None:
        """Keep the qpos of interval ``j``'s physics steps for ``last_qpos`` (record mode)."""
        if not self.record:
            return
        for r, env in enumerate(ids):
            trace = self._trace.setdefault(env, [])
            base = j * self.n_sub
            trace[:] = [(t, q) for t, q in trace if t <= base]
            if coarse:
                nstep = out["qpos"].shape[1]
                trace.extend((base + (k + 1) * self.n_sub, out["qpos"][r, k]) for k in range(nstep))
            else:
                trace.extend((base + k + 1, out["qpos"][r, k]) for k in range(self.n_sub))

    def _finish_record(self) -> None:
        """``last_qpos``: qpos at every fine step of the last control step, interpolated."""
        grid = np.arange(1, self.n_fine + 1)
        self.last_qpos = []
        for env in range(self.num_envs):
            trace = self._trace.get(env)
            if not trace:  # stepped finely from the start (uniform): trace holds every step
                self.last_qpos.append(
                    np.repeat(self._qpos(self.main.state[env])[None], len(grid), 0)
                )
                continue
            t = np.array([t for t, _ in trace], dtype=np.float64)
            q = np.array([q for _, q in trace])
            self.last_qpos.append(
                np.stack([np.interp(grid, t, q[:, c]) for c in range(q.shape[1])], 1)
            )

    # -- reward logic -------------------------------------------------------------------------

    def _record_launch(self, env: int, pos: np.ndarray, vel: np.ndarray) -> float:
        self.launch[env] = np.concatenate([pos, vel])
        return float(flight_carry(pos, vel, self.pin_xy, self.ball_radius, self.gravity))

    def _look_ahead(self, ids: np.ndarray, torque: np.ndarray) -> np.ndarray:
        """Carry of balls still touching the bat or pin at the end of the first-contact step.

        Continues the fine simulations (a copy: the main state is already saved) at the same
        torque, in chunks of 10 ms, until the ball touches neither bat nor pin. A ball still
        held after ``LOOKAHEAD_MAX`` is launched from its last state.
        """
        carry = np.zeros(len(ids))
        todo = np.arange(len(ids))
        chunk = max(1, round(0.01 / self.fine_dt))
        for _ in range(math.ceil(LOOKAHEAD_MAX / (chunk * self.fine_dt))):
            before = self.fine.state[ids[todo]].copy()
            out = self._run(self.fine, ids[todo], torque[todo], chunk, qpos=True)
            bat = self._sensor(out["sensordata"], "bat_ball_contact") > 0
            pin = self._sensor(out["sensordata"], "pin_ball_contact") > 0
            free = ~bat & ~pin
            released = free.any(axis=1)
            for j in np.flatnonzero(released):
                k = int(np.argmax(free[j]))  # state k: the chunk's start or after step k - 1
                qpos = self._qpos(before[j]) if k == 0 else out["qpos"][j, k - 1]
                qvel = self._qvel(before[j]) if k == 0 else out["qvel"][j, k - 1]
                carry[todo[j]] = self._record_launch(ids[todo[j]], qpos[2:5], qvel[2:5])
            todo = todo[~released]
            if len(todo) == 0:
                return carry
        for j in todo:  # never released: launch from the last state
            state = self.fine.state[ids[j]]
            carry[j] = self._record_launch(ids[j], self._qpos(state)[2:5], self._qvel(state)[2:5])
        return carry

    def _parked(self, ids: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """State ``rows`` of simulations ``ids`` with their launched balls taken out of play.

        The ball is put at rest on the ground at its landing point, ``PARK_Y`` beside the arm's
        plane, where nothing can reach it; its flight was already accounted for in closed form.
        """
        rows = rows.copy()
        if len(ids) == 0:
            return rows
        pos, vel = self.launch[ids, :3], self.launch[ids, 3:]
        height = np.maximum(pos[:, 2] - self.ball_radius, 0.0)
        t = (vel[:, 2] + np.sqrt(vel[:, 2] ** 2 + 2.0 * self.gravity * height)) / self.gravity
        qpos, qvel = self._qpos(rows), self._qvel(rows)
        qpos[:, _QPOS_BALL] = 0.0
        qpos[:, 2] = pos[:, 0] + vel[:, 0] * t
        qpos[:, 3] = PARK_Y
        qpos[:, 4] = self.ball_radius
        qpos[:, 5] = 1.0  # identity quaternion
        qvel[:, _QVEL_BALL] = 0.0
        self.in_play[ids] = False
        return rows


def _action_torques(action: np.ndarray) -> np.ndarray:
    """Chosen torques [..., 2] (N m) of action indices [...]."""
    return np.asarray(ACTION_TORQUES, dtype=np.float64)[action]


class BattingEnv(EnvBase):
    """Batched ball-batting robot (paper section 5, Figure 9) as a TorchRL environment.

    A stateful env: the MuJoCo states live in a :class:`BattingSimulator` (see the module
    docstring for the integration scheme and the look-ahead carry). Each step adds N(0, 3) noise
    (variance 3, std sqrt(3) N m) to the chosen torques, independently per joint and env, drawn
    from the env's own ``torch.Generator`` (``set_seed``); equal seeds give equal episodes.

    Keys: ``"observation"`` float32 [E, 4] = (phi1, phi1_dot, phi2, phi2_dot) (rad, rad/s);
    ``"step_count"`` int64 [E, 1]; ``"action"`` int64 [E] (``Categorical(2)``: 0 = (50, -35) N m,
    1 = (-50, 10) N m on joints 1 and 2; a one-hot [E, 2] is accepted too); ``"reward"`` float32
    [E, 1], the carry (m) in the step of the first ball-bat contact, else 0; ``"done"``,
    ``"terminated"`` (False, or with ``end_at_hit`` True from the step of the first contact
    on), ``"truncated"`` bool [E, 1], True at step ``max_steps``.

    Args:
        batch_size: number of parallel arms E (an int or a 1-d shape).
        max_steps: control steps per episode (10 in the paper).
        device: device of the env's tensors (CPU by default); physics runs on the CPU.
        seed: seed of the noise generator; ``None`` draws a fresh one (not from global state).
        noise_variance: variance of the torque noise per joint ((N m)^2).
        scheme, coarse_dt, fine_dt, margin, coarse_integrator, nthread: fidelity knobs of
            :class:`BattingSimulator`.
        audit: a :class:`PhysicsAudit` counting (and sampling) the env's physics rollouts.
        end_at_hit: end the episode (``terminated``) at the step of the first ball-bat
            contact: the ball is gone, nothing after it can earn a reward. Off by default
            (the paper's episodes run all ``max_steps`` steps).

    Example:
        >>> env = BattingEnv(batch_size=4, seed=0)
        >>> td = env.rollout(10, break_when_any_done=False)
        >>> td["observation"].shape, td["action"].shape, td["next", "reward"].shape
        (torch.Size([4, 10, 4]), torch.Size([4, 10]), torch.Size([4, 10, 1]))
    """

    def __init__(
        self,
        *,
        batch_size: int | Sequence[int] = 1,
        max_steps: int = MAX_STEPS,
        device: torch.device | str | None = None,
        seed: int | None = None,
        noise_variance: float = NOISE_VARIANCE,
        scheme: str = "adaptive",
        coarse_dt: float = COARSE_DT,
        fine_dt: float = FINE_DT,
        margin: float = MARGIN,
        coarse_integrator: str = COARSE_INTEGRATOR,
        nthread: int | None = None,
        audit: PhysicsAudit | None = None,
        end_at_hit: bool = False,
    ) -> None:
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(f"batch_size must be one positive size E, got {tuple(batch_size)}")
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
        if not float(noise_variance) >= 0.0:
            raise ValueError(f"noise_variance must be >= 0, got {noise_variance!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise ValueError(f"seed must be an int or None, got {seed!r}")
        super().__init__(
            device=torch.device("cpu") if device is None else device,
            batch_size=batch_size,
        )
        self.max_steps = max_steps
        self.end_at_hit = bool(end_at_hit)
        self.noise_std = math.sqrt(float(noise_variance))  # (N m)
        self.sim = BattingSimulator(
            num_envs=batch_size[0],
            scheme=scheme,
            coarse_dt=coarse_dt,
            fine_dt=fine_dt,
            margin=margin,
            coarse_integrator=coarse_integrator,
            nthread=nthread,
            audit=audit,
        )
        self._steps = np.zeros(batch_size[0], dtype=np.int64)
        self.last_torque = np.zeros((batch_size[0], 2))  # (N m) applied in the last step
        self._make_spec()
        if seed is None:
            seed = int(torch.Generator().seed())  # fresh entropy, leaves the global RNG alone
        self.set_seed(seed)

    # -- specs --------------------------------------------------------------------------------

    def _make_spec(self) -> None:
        shape = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*shape, 4), dtype=torch.float32, device=self.device),
            step_count=Bounded(
                low=0,
                high=self.max_steps,
                shape=(*shape, 1),
                dtype=torch.int64,
                device=self.device,
            ),
            shape=shape,
            device=self.device,
        )
        self.action_spec = Categorical(
            N_ACTIONS, shape=shape, dtype=torch.int64, device=self.device
        )
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=flag.clone(),
            terminated=flag.clone(),
            truncated=flag.clone(),
            shape=shape,
            device=self.device,
        )

    # -- seeding and noise --------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.Generator().seed())
        self.rng = torch.Generator().manual_seed(int(seed))
        self.block_rngs: list[torch.Generator] | None = None

    def set_block_seeds(self, seeds) -> None:
        """Give each of ``len(seeds)`` equal, consecutive blocks of arms its own noise stream.

        With arms laid out block-major (e.g. one block per independent trial), block ``b`` then
        draws exactly the noise an env of one block seeded with ``seeds[b]`` would: a batched
        run of many trials reproduces one-at-a-time runs. ``set_seed`` returns to one stream.
        """
        arms = self.batch_size.numel()
        if not seeds or arms % len(seeds):
            raise ValueError(
                f"seeds must split the {arms} arms into equal blocks, got {len(seeds)} seeds"
            )
        self.block_rngs = [torch.Generator().manual_seed(int(seed)) for seed in seeds]

    def sample_noise(self, num: int) -> torch.Tensor:
        """Torque noise for ``num`` arms, float64 [num, 2] (N m), from the env's generator(s)."""
        if self.block_rngs is None or num != self.batch_size.numel():
            noise = torch.randn((num, 2), generator=self.rng, dtype=torch.float64)
        else:
            per_block = num // len(self.block_rngs)
            noise = torch.cat(
                [
                    torch.randn((per_block, 2), generator=rng, dtype=torch.float64)
                    for rng in self.block_rngs
                ]
            )
        return noise * self.noise_std

    # -- dynamics -----------------------------------------------------------------------------

    @property
    def hit(self) -> torch.Tensor:
        """bool [E]: the bat has touched the ball in the current episode."""
        return torch.as_tensor(self.sim.hit.copy(), device=self.device)

    def _output(self, reward: np.ndarray | None) -> TensorDict:
        shape = self.batch_size
        obs = torch.as_tensor(self.sim.observation(), dtype=torch.float32, device=self.device)
        steps = torch.as_tensor(self._steps, device=self.device).unsqueeze(-1)
        truncated = steps >= self.max_steps
        terminated = torch.zeros_like(truncated)
        if self.end_at_hit:
            terminated = torch.as_tensor(self.sim.hit.copy(), device=self.device).unsqueeze(-1)
        out = {
            "observation": obs,
            "step_count": steps.clone(),
            "done": truncated | terminated,
            "terminated": terminated,
            "truncated": truncated & ~terminated,
        }
        if reward is not None:
            out["reward"] = torch.as_tensor(reward, dtype=torch.float32, device=self.device)
            out["reward"] = out["reward"].unsqueeze(-1)
        return TensorDict(out, batch_size=shape, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if mask is None:
            ids = np.arange(self.batch_size[0])
        else:
            ids = np.flatnonzero(mask.reshape(self.batch_size).cpu().numpy())
        self.sim.reset(ids)
        self._steps[ids] = 0
        return self._output(None)

    def _action_indices(self, action: torch.Tensor) -> np.ndarray:
        """Action indices [E] from indices [E], [E, 1] or a one-hot [E, 2]."""
        if action.ndim == 2 and action.shape[-1] == N_ACTIONS:
            action = action.argmax(-1)
        elif action.ndim == 2 and action.shape[-1] == 1:
            action = action.squeeze(-1)
        if action.shape != self.batch_size:
            raise ValueError(
                f"action must have shape {tuple(self.batch_size)} (indices) or "
                f"{(*self.batch_size, N_ACTIONS)} (one-hot), got {tuple(action.shape)}"
            )
        action = action.long().cpu().numpy()
        if ((action < 0) | (action >= N_ACTIONS)).any():
            raise ValueError(f"action indices must be 0 or 1, got {np.unique(action).tolist()}")
        return action

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self._action_indices(tensordict["action"])
        noise = self.sample_noise(self.batch_size[0]).numpy()
        torque = _action_torques(action) + noise
        _, carry, first_hit = self.sim.step(torque)
        self.last_torque = torque
        self._steps += 1
        return self._output(np.where(first_hit, carry, 0.0))


class BattingGymEnv(gymnasium.Env):
    """One ball-batting arm as a Gymnasium environment (``"torch_api/Batting-v0"``).

    Same physics, actions, noise and reward as :class:`BattingEnv`; the noise comes from the
    env's ``np_random`` (seeded by ``reset(seed=...)``). Observation: float32 (4,) =
    (phi1, phi1_dot, phi2, phi2_dot); action: ``Discrete(2)``. ``truncated`` is True at step
    ``max_steps``; ``terminated`` is always False. ``info`` holds ``"hit"`` (the bat has touched
    the ball) and ``"torque"`` (the applied torques, N m).

    Example:
        >>> env = BattingGymEnv()
        >>> obs, info = env.reset(seed=0)
        >>> obs, reward, terminated, truncated, info = env.step(1)
        >>> obs.shape, terminated
        ((4,), False)
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        *,
        max_steps: int = MAX_STEPS,
        noise_variance: float = NOISE_VARIANCE,
        **sim_kwargs,
    ) -> None:
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
        self.max_steps = max_steps
        self.noise_std = math.sqrt(float(noise_variance))  # (N m)
        self.sim = BattingSimulator(num_envs=1, nthread=1, **sim_kwargs)
        bound = np.array(OBSERVATION_BOUND, dtype=np.float32)
        self.observation_space = gymnasium.spaces.Box(-bound, bound, (4,), np.float32)
        self.action_space = gymnasium.spaces.Discrete(N_ACTIONS)
        self._steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._steps = 0
        obs = self.sim.reset()[0].astype(np.float32)
        return obs, {"hit": False}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0 or 1, got {action!r}")
        torque = _action_torques(int(action)) + self.np_random.normal(0.0, self.noise_std, 2)
        obs, carry, first_hit = self.sim.step(torque[None, :])
        self._steps += 1
        reward = float(carry[0]) if first_hit[0] else 0.0
        truncated = self._steps >= self.max_steps
        info = {"hit": bool(self.sim.hit[0]), "torque": torque}
        return obs[0].astype(np.float32), reward, False, truncated, info
