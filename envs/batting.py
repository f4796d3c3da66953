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

Integration scheme ("coarse swing, fine impact"). A uniform 7.5 ms step makes the impact
unphysical and a uniform fine step is expensive (SPEC section 5). Each control step is first
integrated at ``coarse_dt`` (the paper's 7.5 ms, 10 physics steps, with MuJoCo's RK4 so that the
swing stays accurate) while a distance sensor samples the bat-ball gap at every physics step.
If the ball is still in play and the gap fell below ``margin`` (0.3 m; the bat's surface moves at
most about 25 m/s, i.e. 0.19 m per coarse step, so it cannot cross the margin band between two
samples), that control step is thrown away and re-simulated from its saved start state at
``fine_dt`` (0.25 ms, 300 Euler steps), where the ball-bat contact (time constant 4 ms) is
resolved over about sixteen steps. Only the one or two control steps around the impact are fine.

Carry. In the fine control step of the first contact, the launch is the first physics step after
that contact at which the ball touches neither the bat nor the pin. From the launch state
(position p, velocity v) the flight has no drag, so the ball's lowest point first touches the
ground (centre height = radius r) after ``t = (v_z + sqrt(v_z^2 + 2 g (p_z - r))) / g`` and the
carry is the horizontal distance from the pin to ``p + v t``. If the contact has not ended at the
end of that control step, the look-ahead continues a copy of the simulation at ``fine_dt`` with
the same torque until it has. After the ball has left the bat for good, it is parked at rest on
the ground beside the arm's plane (it plays no further part), so later coarse steps never meet a
flying ball; the episode itself goes on.

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
    "flight_carry",
]

XML_PATH = Path(__file__).parent / "assets" / "batting.xml"
N_ACTIONS = 2  # action 0 cocks the arm, action 1 swings it
ACTION_TORQUES = ((50.0, -35.0), (-50.0, 10.0))  # (N m) on joints 1 and 2, per action (eq. 63)
NOISE_VARIANCE = 3.0  # (N m)^2 variance of the Gaussian torque noise per joint
CONTROL_DT = 0.075  # (s) one control step: the paper's 10 physics steps of 7.5 ms
COARSE_DT = 0.0075  # (s) physics step of the swing away from the ball (the paper's, with RK4)
COARSE_INTEGRATOR = "rk4"  # integrator of the swing; the fine impact steps use Euler
FINE_DT = 0.00025  # (s) physics step of a control step in which the bat nears the ball
MARGIN = 0.3  # (m) bat-ball gap below which a control step is re-simulated at FINE_DT
MAX_STEPS = 10  # control steps per episode (N of the paper)
# (rad, rad/s, rad, rad/s): phi1, phi1_dot, phi2, phi2_dot at the start of every episode
INITIAL_ARM_STATE = (math.pi / 4, 0.0, 0.0, 0.0)
LOOKAHEAD_MAX = 1.0  # (s) longest look-ahead for the end of the first ball-bat contact
PARK_Y = 1.0  # (m) a ball out of play rests on the ground this far beside the arm's plane
# (rad, rad/s, rad, rad/s) loose bounds of |observation| for Gymnasium's Box (joint limits are
# [0, pi/4] and [-pi/4, pi/4], soft by a few hundredths of a radian; speeds stay below 40 rad/s)
OBSERVATION_BOUND = (math.pi / 2, 100.0, math.pi / 2, 100.0)
SETTLE_TIME = 0.2  # (s) time the ball is left to settle on its pin when the model is built

_QPOS_ARM = slice(0, 2)  # phi1, phi2 (rad)
_QPOS_BALL = slice(2, 9)  # ball position (m) and orientation quaternion
_QVEL_BALL = slice(2, 8)  # ball linear (m/s, world frame) and angular velocity (rad/s)
_SENSORS = ("bat_ball_dist", "bat_ball_contact", "pin_ball_contact")
_STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
_INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4}


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
        fine_dt: physics step near the ball (s); must divide 75 ms.
        margin: bat-ball gap (m) that triggers a fine re-simulation; must stay below the
            distance sensor's cutoff.
        nthread: threads of MuJoCo's pool; ``None``: ``min(E, os.cpu_count())``.
        record: keep every physics step's ``qpos`` of the last control step in
            ``last_qpos`` (for pictures; slow).
        xml_path: the MJCF file.

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

        self.coarse_model = mujoco.MjModel.from_xml_path(str(xml_path))
        self.coarse_model.opt.timestep = self.coarse_dt
        if coarse_integrator not in _INTEGRATORS:
            raise ValueError(
                f"coarse_integrator must be 'euler' or 'rk4', got {coarse_integrator!r}"
            )
        self.coarse_model.opt.integrator = _INTEGRATORS[coarse_integrator]
        self.fine_model = mujoco.MjModel.from_xml_path(str(xml_path))
        self.fine_model.opt.timestep = self.fine_dt
        model = self.fine_model
        self._sensor_adr = {name: int(model.sensor_adr[model.sensor(name).id]) for name in _SENSORS}
        cutoff = float(model.sensor_cutoff[model.sensor("bat_ball_dist").id])
        if not 0.0 < margin < cutoff:
            raise ValueError(f"margin must lie in (0, {cutoff}) m (sensor cutoff), got {margin!r}")
        self.margin = float(margin)
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
        self._warnings = self._warning_counts()

    # -- physics queries ----------------------------------------------------------------------

    def _state_slice(self, component: mujoco.mjtState) -> tuple[int, int]:
        """Offset and size of one component inside a state row."""
        offset = 0
        for bit in range(mujoco.mjtState.mjNSTATE.value):
            flag = 1 << bit
            if not flag & _STATE_SPEC.value:
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
        mujoco.mj_getState(model, data, row, _STATE_SPEC)
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
        self, batch: Batch, ids: np.ndarray, torque: np.ndarray, nstep: int, qpos: bool = False
    ) -> dict:
        """Advance ``batch``'s simulations ``ids`` by ``nstep`` physics steps at fixed torque."""
        control = np.broadcast_to(torque[:, None, :], (len(ids), nstep, 2))
        record = ("sensordata", "qpos", "qvel") if qpos else ("sensordata",)
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
        start = self.main.state.copy()
        if self.scheme == "uniform":
            fine_ids = everyone
        else:
            coarse = self._run(self.main, everyone, torque, self.n_coarse, qpos=self.record)
            gap = self._sensor(coarse["sensordata"], "bat_ball_dist").min(axis=1)
            fine_ids = np.flatnonzero(self.in_play & (gap < self.margin))
            if self.record:
                self.last_qpos = [coarse["qpos"][i] for i in everyone]
        first_hit = np.zeros(self.num_envs, dtype=bool)
        carry = np.zeros(self.num_envs)
        bat_contact_at_end = np.zeros(len(fine_ids), dtype=bool)
        if len(fine_ids):
            self.fine.state[fine_ids] = start[fine_ids]
            out = self._run(self.fine, fine_ids, torque[fine_ids], self.n_fine, qpos=True)
            self.main.state[fine_ids] = self.fine.state[fine_ids]
            if self.record:
                for j, i in enumerate(fine_ids):
                    self.last_qpos[i] = out["qpos"][j]
            first_hit[fine_ids], carry[fine_ids] = self._resolve_contacts(
                fine_ids, out, torque[fine_ids]
            )
            bat_contact_at_end = self._sensor(out["sensordata"][:, -1], "bat_ball_contact") > 0
        self.hit |= first_hit
        self.carry[first_hit] = carry[first_hit]
        self._park_free_balls(fine_ids, bat_contact_at_end)
        return self.observation(), carry, first_hit

    # -- reward logic -------------------------------------------------------------------------

    def _resolve_contacts(
        self, ids: np.ndarray, out: dict, torque: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """First contacts among fine-stepped simulations ``ids`` and their look-ahead carries.

        ``out`` holds the fine rollout's records: record k of ``sensordata`` describes the state
        before physics step k, record k of ``qpos``/``qvel`` the state after it.
        """
        bat = self._sensor(out["sensordata"], "bat_ball_contact") > 0  # [F, n_fine]
        pin = self._sensor(out["sensordata"], "pin_ball_contact") > 0
        first = ~self.hit[ids] & bat.any(axis=1)
        carry = np.zeros(len(ids))
        pending = []
        for j in np.flatnonzero(first):
            k0 = int(np.argmax(bat[j]))
            free = np.flatnonzero(~bat[j, k0:] & ~pin[j, k0:])
            if len(free) == 0:
                pending.append(j)
                continue
            k = k0 + int(free[0])  # state k is free; it is the state after physics step k - 1
            pos = out["qpos"][j, k - 1, 2:5]
            vel = out["qvel"][j, k - 1, 2:5]
            carry[j] = self._record_launch(ids[j], pos, vel)
        if pending:
            pending = np.asarray(pending)
            carry[pending] = self._look_ahead(ids[pending], torque[pending])
        return first, carry

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

    def _park_free_balls(self, fine_ids: np.ndarray, bat_contact_at_end: np.ndarray) -> None:
        """Take out of play every hit ball that no longer touches the bat.

        The ball is put at rest on the ground at its landing point, ``PARK_Y`` beside the arm's
        plane, where nothing can reach it; its flight was already accounted for in closed form.
        """
        touching = np.zeros(self.num_envs, dtype=bool)
        touching[fine_ids] = bat_contact_at_end
        ids = np.flatnonzero(self.hit & self.in_play & ~touching)
        if len(ids) == 0:
            return
        pos, vel = self.launch[ids, :3], self.launch[ids, 3:]
        height = np.maximum(pos[:, 2] - self.ball_radius, 0.0)
        t = (vel[:, 2] + np.sqrt(vel[:, 2] ** 2 + 2.0 * self.gravity * height)) / self.gravity
        qpos = self._qpos(self.main.state)
        qvel = self._qvel(self.main.state)
        qpos[ids, _QPOS_BALL] = 0.0
        qpos[ids, 2] = pos[:, 0] + vel[:, 0] * t
        qpos[ids, 3] = PARK_Y
        qpos[ids, 4] = self.ball_radius
        qpos[ids, 5] = 1.0  # identity quaternion
        qvel[ids, _QVEL_BALL] = 0.0
        self.in_play[ids] = False


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
    ``"terminated"`` (always False), ``"truncated"`` bool [E, 1], True at step ``max_steps``.

    Args:
        batch_size: number of parallel arms E (an int or a 1-d shape).
        max_steps: control steps per episode (10 in the paper).
        device: device of the env's tensors (CPU by default); physics runs on the CPU.
        seed: seed of the noise generator; ``None`` draws a fresh one (not from global state).
        noise_variance: variance of the torque noise per joint ((N m)^2).
        scheme, coarse_dt, fine_dt, margin, coarse_integrator, nthread: fidelity knobs of
            :class:`BattingSimulator`.

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
            device=torch.device("cpu") if device is None else device, batch_size=batch_size
        )
        self.max_steps = max_steps
        self.noise_std = math.sqrt(float(noise_variance))  # (N m)
        self.sim = BattingSimulator(
            num_envs=batch_size[0],
            scheme=scheme,
            coarse_dt=coarse_dt,
            fine_dt=fine_dt,
            margin=margin,
            coarse_integrator=coarse_integrator,
            nthread=nthread,
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

    def sample_noise(self, num: int) -> torch.Tensor:
        """Torque noise for ``num`` arms, float64 [num, 2] (N m), from the env's generator."""
        noise = torch.randn((num, 2), generator=self.rng, dtype=torch.float64)
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
        out = {
            "observation": obs,
            "step_count": steps.clone(),
            "done": truncated.clone(),
            "terminated": torch.zeros_like(truncated),
            "truncated": truncated,
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
        self, *, max_steps: int = MAX_STEPS, noise_variance: float = NOISE_VARIANCE, **sim_kwargs
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
