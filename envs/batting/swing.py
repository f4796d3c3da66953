"""The contact-free swing of the batting arm as batched tensor dynamics (float64, any device).

MuJoCo is the engine of record; this file reproduces, for all rollouts at once, what MuJoCo
computes for the arm during the coarse swing, where the ball is frozen and nothing touches
(:mod:`envs.batting.impact`). Per physics step (docs/batting.md, "The tensor swing"):

* the arm's closed-form equations of motion ``M(phi) phi_ddot = f(phi, phi_dot, tau)``
  (eq. S1-S3) with the coefficients of :class:`~envs.batting.arm_model.ArmModel`;
* MuJoCo's soft joint limits (eq. S4-S6): a limit row where the distance to the range falls
  below the margin, impedance ``d`` of the distance (``solimp``), reference acceleration
  ``aref = -B v - K d (dist - margin)`` (``solref``), regulariser
  ``R = (1 - d) / d * dof_invweight0``; the constrained acceleration minimises
  ``1/2 (a - a0)^T M (a - a0) + sum 1/2 R^-1 min(0, J a - aref)^2`` (MuJoCo's primal problem,
  which its Newton solver solves exactly), found here by trying every set of active rows;
* MuJoCo's RK4 step (engine_forward.c, ``mj_RungeKutta``): the tableau, the stage states and
  the final update in MuJoCo's order of operations.

:class:`TensorSwing` applies it to MuJoCo's integration-state rows, so the rest of the
simulator (the impact window, the hooks) sees the same arrays as after a MuJoCo rollout.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np
import torch

from .arm_model import ArmModel

__all__ = ["TensorSwing", "arm_acceleration", "limit_impedance", "rk4_swing", "state_offsets"]

_MINVAL = mujoco.mjMINVAL
_BAD = mujoco.mjMAXVAL  # MuJoCo's threshold of a diverged state or acceleration (mju_isBad)


def limit_impedance(
    coefficients: torch.Tensor, dist: torch.Tensor, common_power: float | None = None
) -> torch.Tensor:
    """MuJoCo's constraint impedance ``d`` (eq. S5) of limit rows at ``dist`` = pos - margin.

    Args:
        coefficients: [7, 2, 1] per joint, :func:`~envs.batting.arm_model.impedance_coefficients`
            of the joints' ``solimp`` (dmin, dmax, width, midpoint, power).
        dist: [2, E] (rad) signed distance beyond the margin (negative: past the limit).
        common_power: the power p if it is the same for every joint (a faster path), or None.

    Returns:
        d [2, E]: ``dmin + y(x) (dmax - dmin)`` with ``x = min(|dist| / width, 1)`` and MuJoCo's
        two-piece power sigmoid ``y = a x^p`` up to the midpoint, ``1 - b (1 - x)^p`` beyond
        (engine_core_constraint.c, ``getimpedance``).

    Example:
        >>> from envs.batting.arm_model import impedance_coefficients
        >>> solimp = np.array([[0.9, 0.95, 0.001, 0.5, 2.0]] * 2)
        >>> coef = torch.tensor(impedance_coefficients(solimp)).unsqueeze(-1)
        >>> limit_impedance(coef, torch.tensor([[0.0], [-0.0005]], dtype=torch.float64))
        tensor([[0.9000],
                [0.9250]], dtype=torch.float64)
    """
    dmin, span, inv_width, mid, power, low_scale, high_scale = coefficients.unbind(0)
    if common_power is not None:  # the same power for every joint: a scalar power is faster
        power = common_power
    x = (dist.abs() * inv_width).clamp_max(1.0)
    y = torch.where(x <= mid, low_scale * x.pow(power), 1.0 - high_scale * (1.0 - x).pow(power))
    return dmin + y * span


def arm_acceleration(
    arm: ArmModel, q: torch.Tensor, v: torch.Tensor, force: torch.Tensor
) -> torch.Tensor:
    """The arm's joint accelerations as MuJoCo's ``mj_forward`` gives them.

    States are joint-major (one contiguous row per joint, which keeps every elementwise
    kernel on long rows): ``q[j]`` holds joint j's values for all E arms.

    Args:
        arm: the model's coefficients.
        q: [2, E] joint angles (phi1, phi2) (rad).
        v: [2, E] joint speeds (rad/s).
        force: [2, E] actuator torques on the joints (N m), ``arm.actuation @ ctrl``.

    Returns:
        ``qacc`` [2, E] (rad/s^2): the acceleration of eq. S1-S3 under the joint limits'
        constraint forces (eq. S4-S6).

    Example:
        >>> from envs.batting import XML_PATH
        >>> arm = ArmModel.from_mujoco(mujoco.MjModel.from_xml_path(str(XML_PATH)))
        >>> zero = torch.zeros(2, 5, dtype=torch.float64)
        >>> arm_acceleration(arm, zero + 0.3, zero, zero).shape
        torch.Size([2, 5])
    """
    angle = arm.angle_map @ q  # [3, E] theta1, theta2, delta
    terms = arm.trig_map @ torch.cat([angle.cos(), angle.sin()])  # [4, E] c, c', G1, G2
    coupling, slope = terms[0], terms[1]
    m11 = coupling * arm.mass_slope[0] + arm.mass_const[0]  # eq. S1
    m12 = coupling * arm.mass_slope[1] + arm.mass_const[1]
    m22 = arm.mass_const[2]
    omega = arm.speed_map @ v  # theta2_dot, theta1_dot
    # gravity and velocity products on the links (eq. S2), as torques on (phi1, phi2) (eq. S3)
    f = arm.force_map @ terms[2:] + slope * (arm.bias_map @ (omega * omega)) + force
    if arm.passive:
        f = f - arm.damping * v - arm.stiffness * (q - arm.spring_ref)

    # joint limits (eq. S4-S5): a row where the nearer bound is closer than the margin, with
    # J = +1 (lower bound) or -1 (upper bound)
    below, above = q - arm.lower, arm.upper - q
    sign = torch.sign(above - below)  # 0 only half-way, where no row can be
    dist = torch.minimum(below, above) - arm.margin
    row = dist < 0 if arm.all_limited else (dist < 0) & arm.limited
    imp = limit_impedance(arm.impedance, dist, arm.impedance_power)
    if arm.diag_exact:  # (J M^-1 J^T)_jj
        diag = torch.stack([torch.full_like(m11, m22), m11]) / (m11 * m22 - m12 * m12)
    else:
        diag = arm.invweight
    stiff = row / ((1.0 - imp) * diag / imp).clamp_min(_MINVAL)  # D = 1 / R, 0 without a row
    aref = (arm.neg_damp_b * sign) * v - (arm.stiff_k * imp) * dist
    push = stiff * sign * aref  # J^T D aref, [2, E]

    # eq. S6: the minimiser of 1/2 (a - a0)^T M (a - a0) + sum 1/2 D min(0, J a - aref)^2.
    # For each set of active rows (none, joint 1's, joint 2's, both: the rows [4, E] below) it
    # solves (M + J^T D J) a = f + J^T D aref; the minimiser is the candidate of least cost.
    on1, on2 = _active_sets(q.device)  # [4, 1] each
    (d1, d2), (p1, p2), (f1, f2) = stiff.unbind(0), push.unbind(0), f.unbind(0)
    # (in place where a [4, E] temporary is updated: the same values, fewer passes over memory)
    a11, a22 = torch.addcmul(m11, on1, d1), (on2 * d2).add_(m22)
    r1, r2 = torch.addcmul(f1, on1, p1), torch.addcmul(f2, on2, p2)
    inv_det = (a11 * a22).sub_(m12 * m12).reciprocal_()
    acc1, acc2 = (a22 * r1).sub_(m12 * r2).mul_(inv_det), (a11 * r2).sub_(m12 * r1).mul_(inv_det)
    (sign1, sign2), (aref1, aref2) = sign.unbind(0), aref.unbind(0)
    slack1 = (sign1 * acc1).sub_(aref1).clamp_max_(0.0)
    slack2 = (sign2 * acc2).sub_(aref2).clamp_max_(0.0)
    # 1/2 a^T M a - f^T a (the Gauss term less a constant) plus the rows' cost
    cost = (m11 * acc1).add_(2.0 * m12 * acc2).mul_(0.5).sub_(f1).mul_(acc1)
    cost += (0.5 * m22 * acc2).sub_(f2).mul_(acc2)
    cost += 0.5 * (d1 * slack1 * slack1 + d2 * slack2 * slack2)
    return torch.stack(_least(cost, acc1, acc2))


def _least(cost: torch.Tensor, *values: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The entries [E] of each of ``values`` [4, E] at the least of ``cost`` [4, E], by a
    knock-out of elementwise comparisons (a reduction over 4 rows is slower)."""
    c0, c1, c2, c3 = cost.unbind(0)
    first, second = c1 < c0, c3 < c2
    final = torch.minimum(c2, c3) < torch.minimum(c0, c1)
    picked = []
    for value in values:
        v0, v1, v2, v3 = value.unbind(0)
        picked.append(torch.where(final, torch.where(second, v3, v2), torch.where(first, v1, v0)))
    return tuple(picked)


@functools.cache
def _active_sets(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Whether row 1 and row 2 are active in each of the four sets, [4, 1] each (float64)."""
    on1 = torch.tensor([[0.0], [1.0], [0.0], [1.0]], dtype=torch.float64, device=device)
    on2 = torch.tensor([[0.0], [0.0], [1.0], [1.0]], dtype=torch.float64, device=device)
    return on1, on2


def rk4_swing(
    arm: ArmModel, q: torch.Tensor, v: torch.Tensor, force: torch.Tensor, nstep: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``nstep`` RK4 steps of ``arm.timestep`` at constant actuator torques, as MuJoCo takes them.

    Args:
        arm: the model's coefficients.
        q: [2, E] joint angles at the start (rad), joint-major as in :func:`arm_acceleration`.
        v: [2, E] joint speeds at the start (rad/s).
        force: [2, E] actuator torques on the joints (N m), held throughout.
        nstep: number of physics steps.

    Returns:
        angles [nstep + 1, 2, E] and speeds [nstep + 1, 2, E] at the step boundaries (index 0:
        the start), and the last stage's accelerations [nstep, 2, E] of every step (what MuJoCo
        keeps as the next step's warm start).

    Example:
        >>> from envs.batting import XML_PATH
        >>> arm = ArmModel.from_mujoco(mujoco.MjModel.from_xml_path(str(XML_PATH)))
        >>> q = torch.tensor([[0.78], [0.0]], dtype=torch.float64)
        >>> angles, speeds, _ = rk4_swing(arm, q, torch.zeros_like(q), torch.zeros_like(q), 3)
        >>> angles.shape, speeds.shape
        (torch.Size([4, 2, 1]), torch.Size([4, 2, 1]))
    """
    h = arm.timestep
    angles, speeds, last = [q], [v], []
    for _ in range(nstep):  # eq. S7 (engine_forward.c, mj_RungeKutta)
        a0 = arm_acceleration(arm, q, v, force)
        q1, v1 = q.add(v, alpha=0.5 * h), v.add(a0, alpha=0.5 * h)
        a1 = arm_acceleration(arm, q1, v1, force)
        q2, v2 = q.add(v1, alpha=0.5 * h), v.add(a1, alpha=0.5 * h)
        a2 = arm_acceleration(arm, q2, v2, force)
        q3, v3 = q.add(v2, alpha=h), v.add(a2, alpha=h)
        a3 = arm_acceleration(arm, q3, v3, force)
        q = q.add((v + v3).add(v1 + v2, alpha=2.0), alpha=h / 6.0)
        v = v.add((a0 + a3).add(a1 + a2, alpha=2.0), alpha=h / 6.0)
        angles.append(q)
        speeds.append(v)
        last.append(a3)
    return torch.stack(angles), torch.stack(speeds), torch.stack(last)


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """``index`` as a slice where it is a run of consecutive columns (a faster copy), else as is."""
    index = np.asarray(index)
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


def state_offsets(model: mujoco.MjModel) -> dict[int, int]:
    """Offset of each component (keyed by its ``mjtState`` bit) in an integration-state row.

    Example:
        >>> from envs.batting import XML_PATH
        >>> offsets = state_offsets(mujoco.MjModel.from_xml_path(str(XML_PATH)))
        >>> offsets[mujoco.mjtState.mjSTATE_TIME.value], offsets[mujoco.mjtState.mjSTATE_QVEL.value]
        (0, 10)
    """
    offsets, position = {}, 0
    for bit in range(mujoco.mjtState.mjNSTATE.value):
        flag = 1 << bit
        if flag & mujoco.mjtState.mjSTATE_INTEGRATION.value:
            offsets[flag] = position
            position += mujoco.mj_stateSize(model, flag)
    return offsets


class TensorSwing:
    """The coarse rollout of a MuJoCo model's arm in tensors, on MuJoCo's state rows.

    Reproduces ``mujoco.batch.Batch.rollout`` of the coarse model (RK4, the ball frozen, nothing
    touching) for the arm: the returned integration-state rows hold the arm's angles and speeds
    of :func:`rk4_swing`, the time, the controls and the warm start as MuJoCo leaves them, and
    every other entry (the frozen ball's pose and speed) as at the start.

    Args:
        model: the compiled coarse model (its ``opt.timestep`` and RK4 integrator are used).
        device: where the dynamics run (CPU by default); the rows stay numpy on the host.

    Example:
        >>> from envs.batting import BattingSimulator
        >>> sim = BattingSimulator(num_envs=2, swing="mujoco")
        >>> swing = TensorSwing(sim.coarse_model)
        >>> states, bad = swing.rollout(sim.main.state, np.array([[-50.0, 10.0]] * 2), 10)
        >>> states.shape, bad.tolist()
        ((2, 11, 60), [False, False])
    """

    def __init__(self, model: mujoco.MjModel, *, device: torch.device | str | None = None) -> None:
        if model.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4:
            raise ValueError(f"the swing reproduces MuJoCo's RK4 only, got {model.opt.integrator}")
        self.device = torch.device("cpu") if device is None else torch.device(device)
        self.model = model
        self.arm = ArmModel.from_mujoco(model, self.device)
        self.timestep = float(model.opt.timestep)
        offset = state_offsets(model)
        self.nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION.value)
        state = mujoco.mjtState
        self._time = offset[state.mjSTATE_TIME.value]
        self._qpos = _as_slice(offset[state.mjSTATE_QPOS.value] + model.jnt_qposadr[:2])
        dofs = model.jnt_dofadr[:2]
        self._qvel = _as_slice(offset[state.mjSTATE_QVEL.value] + dofs)
        warm = offset[state.mjSTATE_WARMSTART.value]
        self._warm_arm, self._warm = _as_slice(warm + dofs), slice(warm, warm + model.nv)
        qpos, qvel = offset[state.mjSTATE_QPOS.value], offset[state.mjSTATE_QVEL.value]
        self._qpos_all, self._qvel_all = slice(qpos, qpos + model.nq), slice(qvel, qvel + model.nv)
        self._others = qvel + np.setdiff1d(np.arange(model.nv), dofs)  # the ball's dofs
        self._ctrl = slice(
            offset[state.mjSTATE_CTRL.value], offset[state.mjSTATE_CTRL.value] + model.nu
        )

    def rollout(
        self, start: np.ndarray, ctrl: np.ndarray, nstep: int, out: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``nstep`` physics steps of every row at constant controls.

        Args:
            start: [E, nstate] integration-state rows at the start.
            ctrl: [E, U] controls (N m for the batting arm's motors), held throughout.
            nstep: number of physics steps.
            out: where to write the rows, float64 [E, nstep + 1, nstate] (a buffer the caller
                reuses from call to call), or None for a new array.

        Returns:
            rows [E, nstep + 1, nstate] (index 0: ``start``), and bad [E], True where a state or
            acceleration is not finite or beyond MuJoCo's bound 1e10 (MuJoCo would reset it).
        """
        if start.shape[-1] != self.nstate or ctrl.shape[0] != start.shape[0]:
            raise ValueError(
                f"start must be [E, {self.nstate}] and ctrl [E, U], got {start.shape}, {ctrl.shape}"
            )
        shape = (len(start), nstep + 1, self.nstate)
        if out is not None and (out.shape != shape or out.dtype != np.float64):
            raise ValueError(f"out must be float64 {shape}, got {out.dtype} {out.shape}")

        def tensor(x: np.ndarray) -> torch.Tensor:  # joint-major rows on the device
            return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64).to(self.device)

        q, v = tensor(start[:, self._qpos].T), tensor(start[:, self._qvel].T)  # [2, E]
        force = self.arm.actuation @ tensor(ctrl.T)
        swing = rk4_swing(self.arm, q, v, force, nstep)  # [n + 1, 2, E] ...
        # bad: on the contiguous tensors, before they are spread over the rows
        fine = [(x.abs() <= _BAD).all(0).all(0) for x in swing]  # (NaN compares False)
        bad = ~(fine[0] & fine[1] & fine[2]).cpu().numpy()
        angles, speeds, accs = (x.permute(2, 0, 1).cpu().numpy() for x in swing)
        rows = np.empty(shape) if out is None else out
        rows[:] = start[:, None]
        rows[:, :, self._qpos] = angles
        rows[:, :, self._qvel] = speeds
        rows[:, 1:, self._warm] = 0.0  # the other degrees of freedom do not accelerate
        rows[:, 1:, self._warm_arm] = accs
        rows[:, 1:, self._ctrl] = ctrl[:, None]
        self._drift(rows)
        time = start[:, self._time]
        for k in range(1, nstep + 1):  # MuJoCo adds one step at a time
            time = time + self.timestep
            rows[:, k, self._time] = time
        return rows, bad

    def _drift(self, rows: np.ndarray) -> None:
        """Move the other degrees of freedom of ``rows`` [E, nstep + 1, nstate] as MuJoCo's RK4
        moves them where no force reaches them: at their constant speeds (``mj_integratePos``
        of the stages' weighted speed). Rows at rest (the ball on its pin) are left as they are;
        only a ball left with a residual speed by an impact window drifts."""
        moving = np.flatnonzero((rows[:, 0, self._others] != 0.0).any(-1))
        for r in moving:
            speed = rows[r, 0, self._qvel_all].copy()
            speed[self.model.jnt_dofadr[:2]] = 0.0
            # the RK4 weights of four equal stage speeds, summed in MuJoCo's order
            weighted = speed * (1.0 / 6.0) + speed * (1.0 / 3.0) + speed * (1.0 / 3.0)
            weighted = weighted + speed * (1.0 / 6.0)
            qpos = rows[r, 0, self._qpos_all].copy()
            for k in range(1, rows.shape[1]):
                arm = rows[r, k, self._qpos].copy()
                mujoco.mj_integratePos(self.model, qpos, weighted, self.timestep)
                rows[r, k, self._qpos_all] = qpos
                rows[r, k, self._qpos] = arm
