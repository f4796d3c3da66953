"""Batched MuJoCo physics of the batting arm (plain numpy), one control step at a time.

E simulations of ``assets/batting.xml`` stepped in MuJoCo's native thread pool
(:class:`mujoco.batch.Batch`), one control step (75 ms, the paper's 10 x 7.5 ms) at a time, with
the integration scheme of :mod:`envs.batting.impact` and the closed-form flight of
:mod:`envs.batting.flight`. The contact-free coarse swing runs either in MuJoCo or, by default,
as batched tensor dynamics checked against it (:mod:`envs.batting.swing`); the impact window is
always MuJoCo's. Noise is not drawn here (the envs draw it).

MuJoCo stops a simulation whose accelerations blow up (its warning counters rise) instead of
stepping it: the simulator checks the counters after every call and raises ``RuntimeError``.
"""

from __future__ import annotations

import os
from pathlib import Path

import mujoco
import numpy as np
import torch
from mujoco.batch import Batch

from .constants import (
    COARSE_DT,
    COARSE_INTEGRATOR,
    CONTROL_DT,
    FINE_DT,
    INITIAL_ARM_STATE,
    MARGIN,
    PREDICT_POINTS,
    QPOS_ARM,
    SETTLE_TIME,
    XML_PATH,
)
from .hooks import PhysicsHook
from .impact import ImpactWindow
from .swing import TensorSwing, state_offsets

__all__ = ["BattingSimulator"]

_SENSORS = ("bat_ball_dist", "bat_ball_contact", "pin_ball_contact")
_INTEGRATION_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
_OFF = mujoco.mjtDisableBit
# What the coarse steps leave out: contacts and sensors (see BattingSimulator), and passes that
# compute nothing in this model (no friction loss, no damping, no collisions to filter): the
# same numbers to the bit, about 13 % less time per coarse step (measured). Not springs and
# dampers together: MuJoCo then skips its passive forces, the ball's gravity compensation too.
_COARSE_OFF = (
    _OFF.mjDSBL_CONTACT
    | _OFF.mjDSBL_SENSOR
    | _OFF.mjDSBL_FRICTIONLOSS
    | _OFF.mjDSBL_EULERDAMP
    | _OFF.mjDSBL_FILTERPARENT
    | _OFF.mjDSBL_MIDPHASE
)
_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}


def _positive_dt(value: float, name: str) -> float:
    value = float(value)
    if not value > 0.0:
        raise ValueError(f"{name} must be a positive time step (s), got {value!r}")
    steps = CONTROL_DT / value
    if abs(steps - round(steps)) > 1e-6:
        raise ValueError(f"{name} must divide CONTROL_DT = {CONTROL_DT} s, got {value!r}")
    return value


class BattingSimulator(ImpactWindow):
    """Batched MuJoCo physics of the batting arm, one control step at a time (numpy).

    Holds E simulations of ``assets/batting.xml``; :meth:`step` applies one torque pair per
    simulation for one control step (75 ms) with the scheme of :mod:`envs.batting.impact`
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
        swing: ``"tensor"`` (the coarse swing of all simulations as batched tensor dynamics,
            :mod:`envs.batting.swing`; RK4 only) or ``"mujoco"`` (MuJoCo's own coarse
            rollout, the engine of record). The impact window is MuJoCo's either way.
        device: where the tensor swing runs (CPU by default).
        nthread: threads of MuJoCo's pool; ``None``: ``min(E, os.cpu_count())``.
        xml_path: the MJCF file.
        hook: a :class:`~envs.batting.PhysicsHook` observing every physics rollout (e.g. a
            physics audit or an arm trace); it only reads, the numbers do not depend on it.

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
        swing: str = "tensor",
        device: torch.device | str | None = None,
        nthread: int | None = None,
        xml_path: str | Path = XML_PATH,
        hook: PhysicsHook | None = None,
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
        self.hook = hook

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
        self.coarse_model.opt.disableflags |= _COARSE_OFF
        if swing not in ("tensor", "mujoco"):
            raise ValueError(f"swing must be 'tensor' or 'mujoco', got {swing!r}")
        if swing == "tensor" and coarse_integrator != "rk4":
            raise ValueError(f"swing='tensor' reproduces RK4, got {coarse_integrator=!r}")
        self.swing = swing
        self.tensor_swing, self._swing_rows = None, None
        if swing == "tensor" and scheme == "adaptive":
            self.tensor_swing = TensorSwing(self.coarse_model, device=device)
            self._swing_rows = np.empty((num_envs, self.n_coarse + 1, self.tensor_swing.nstate))
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
        # how far a bat point can be from the elbow, and the elbow from the shoulder (m): a
        # turn of the bat by d (rad) moves no bat point more than _bat_reach * d, and so on
        self._bat_reach = max(max(abs(lo), abs(hi)) + radius for lo, hi, radius in self._capsules)
        self._elbow_reach = float(np.linalg.norm(self._elbow_offset))
        self.ball_radius = float(model.geom("ball").size[0])  # (m)
        self.gravity = float(-model.opt.gravity[2])  # (m/s^2)
        pin = model.geom("pin")
        self.pin_xy = np.array(pin.pos[:2], dtype=np.float64)  # (m)

        if nthread is None:
            nthread = min(num_envs, os.cpu_count() or 1)
        self.main = Batch(self.coarse_model, nsim=num_envs, nthread=nthread)
        self.fine = Batch(self.fine_model, nsim=num_envs, nthread=nthread)
        self._nstate = self.main.nstate
        offsets = state_offsets(self.coarse_model)
        self._qpos_adr = offsets[mujoco.mjtState.mjSTATE_QPOS.value]
        self._qvel_adr = offsets[mujoco.mjtState.mjSTATE_QVEL.value]
        self._initial_state = self._settled_initial_state()

        self.hit = np.zeros(num_envs, dtype=bool)  # the bat has touched the ball
        self.in_play = np.ones(num_envs, dtype=bool)  # the ball is not yet parked
        self.carry = np.zeros(num_envs)  # (m) look-ahead carry of the first contact, 0 if none
        self.launch = np.full((num_envs, 6), np.nan)  # ball position (m), velocity (m/s)
        self.physics_steps = np.zeros(num_envs, dtype=np.int64)  # since the last reset
        self.fine_steps = np.zeros(num_envs, dtype=np.int64)  # of which at fine_dt
        self._warnings = self._warning_counts()

    @property
    def _hook_wants_qpos(self) -> bool:
        return self.hook is not None and self.hook.wants_qpos

    # -- physics queries ----------------------------------------------------------------------

    def _settled_initial_state(self) -> np.ndarray:
        """Integration state row of (pi/4, 0, 0, 0) with the ball at rest on its pin."""
        model, data = self.fine_model, mujoco.MjData(self.fine_model)
        phi1, dphi1, phi2, dphi2 = INITIAL_ARM_STATE
        for _ in range(round(SETTLE_TIME / self.fine_dt)):
            data.qpos[QPOS_ARM] = (phi1, phi2)
            data.qvel[:2] = (dphi1, dphi2)
            mujoco.mj_step(model, data)
        data.qpos[QPOS_ARM] = (phi1, phi2)
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
        if self.hook is not None:
            kind = "fine" if batch is self.fine else "coarse"
            self.hook.on_rollout(kind, batch.state, ids, torque, nstep)
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
        if self.scheme == "uniform":
            states = None
            fine = np.ones((self.num_envs, self.n_coarse), dtype=bool)
        else:
            states = self._swing(torque)
            fine = self._near_intervals(states)
        if self.hook is not None:
            self.hook.on_step_start(self, states)
        first_hit = np.zeros(self.num_envs, dtype=bool)
        carry = np.zeros(self.num_envs)
        ids = np.flatnonzero(fine.any(axis=1))
        if len(ids):
            self._refine(ids, states, fine[ids], torque[ids], first_hit, carry)
        self.hit |= first_hit
        self.carry[first_hit] = carry[first_hit]
        if self.hook is not None:
            self.hook.on_step_end(self)
        return self.observation(), carry, first_hit

    def _swing(self, torque: np.ndarray) -> np.ndarray:
        """The coarse swing of every simulation through the control step; the main batch is
        left at its end. Returns the states [E, n_coarse + 1, nstate] at the interval
        boundaries (index 0: the start)."""
        everyone = np.arange(self.num_envs)
        if self.tensor_swing is None:
            start = self.main.state.copy()
            out = self._run(self.main, everyone, torque, self.n_coarse, states=True)
            return np.concatenate([start[:, None], out[_INTEGRATION_STATE.value]], axis=1)
        if self.hook is not None:
            self.hook.on_rollout("coarse", self.main.state, everyone, torque, self.n_coarse)
        rows = self._swing_rows  # (reused step after step: its pages stay mapped)
        states, bad = self.tensor_swing.rollout(self.main.state, torque, self.n_coarse, out=rows)
        if bad.any():
            raise RuntimeError(
                f"the tensor swing diverged like an unstable MuJoCo simulation (NaN or huge "
                f"QACC) in envs {np.flatnonzero(bad).tolist()[:10]}"
            )
        self.main.state[:] = states[:, -1]
        self.physics_steps += self.n_coarse
        return states

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
