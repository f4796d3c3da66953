"""The batting arm's parameters, read out of a compiled MuJoCo model (no copied constants).

The arm is a planar chain of two hinges about parallel axes (the world's ±y): link 1 turns
about the shoulder, link 2 (the bat) about the elbow. With ``s_i = ±1`` the sign of joint i's
axis along +y, the links' angles about +y are ``theta_1 = s_1 phi_1`` and
``theta_2 = theta_1 + s_2 phi_2``; a vector ``(x, z)`` of a link's frame is
``R(theta) (x, z) = (x cos theta + z sin theta, -x sin theta + z cos theta)`` in the world's
x-z plane. Only the x-z components of the centres of mass, the inertias about y and the x-z
components of gravity enter the hinges' equations of motion (docs/batting.md, "The tensor
swing"); :class:`ArmModel` holds exactly those, as the coefficients the closed form uses, and
the joint limits' constraint parameters as MuJoCo resolves them (``jnt_solref``,
``jnt_solimp``, ``dof_invweight0``; engine_core_constraint.c, ``getsolparam``).

Whatever the closed form does not model (friction loss, sleeping islands, parameter overrides,
actuators other than plain motors on the two hinges, a ball coupled to the arm) is refused with
a ``ValueError`` naming it, so that a model it cannot reproduce never runs silently.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

__all__ = ["ArmModel", "impedance_coefficients"]

_OFF = mujoco.mjtDisableBit
_ON = mujoco.mjtEnableBit
# enable bits the closed form ignores safely: energy and inverse-dynamics bookkeeping
_HARMLESS_ENABLES = _ON.mjENBL_ENERGY | _ON.mjENBL_FWDINV | _ON.mjENBL_DIAGEXACT


def _perp_coefficients(vec_xz: np.ndarray, gravity_xz: np.ndarray) -> tuple[float, float]:
    """(p, r) with ``g . d/dtheta [R(theta) v] = p cos theta + r sin theta`` (g, v in x-z)."""
    (gx, gz), (x, z) = gravity_xz, vec_xz
    return float(gx * z - gz * x), float(-gx * x - gz * z)


def _inertia_about_y(model: mujoco.MjModel, body: int) -> float:
    """Rotational inertia (kg m^2) of ``body`` about the y axis through its centre of mass."""
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, model.body_iquat[body])
    rot = rot.reshape(3, 3)
    return float((rot @ np.diag(model.body_inertia[body]) @ rot.T)[1, 1])


def _check_planar_arm(model: mujoco.MjModel) -> tuple[int, int]:
    """The arm's two bodies, after checking that the closed form describes the model."""
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    if model.njnt < 2 or list(model.jnt_type[:2]) != [hinge, hinge]:
        raise ValueError(f"the arm must be the model's first two joints, hinges: {model.jnt_type}")
    b1, b2 = (int(b) for b in model.jnt_bodyid[:2])
    if model.body_parentid[b1] != 0 or model.body_parentid[b2] != b1:
        raise ValueError(f"the arm must be a chain world -> body {b1} -> body {b2}")
    for joint, body in ((0, b1), (1, b2)):
        axis = model.jnt_axis[joint]
        if not np.allclose(np.abs(axis), (0.0, 1.0, 0.0), atol=1e-12):
            raise ValueError(f"joint {joint}'s axis must be +-y, got {axis.tolist()}")
        if np.abs(model.jnt_pos[joint]).max() > 0.0:
            raise ValueError(f"joint {joint} must sit at its body's origin: {model.jnt_pos[joint]}")
        if not np.array_equal(model.body_quat[body], (1.0, 0.0, 0.0, 0.0)):
            raise ValueError(f"body {body} must not be rotated in its parent: {model.body_quat}")
        if (model.body_dofnum[body], model.body_jntnum[body]) != (1, 1):
            raise ValueError(f"body {body} must carry exactly one joint (its hinge)")
    others = model.body_rootid[int(model.dof_bodyid[2]) :] if model.nv > 2 else []
    if np.any(np.asarray(others) == model.body_rootid[b1]):
        raise ValueError("the arm's tree must carry no other degree of freedom")
    if model.neq or model.ntendon or model.nflex:
        raise ValueError("equality constraints, tendons and flexes are not modelled")
    return b1, b2


def impedance_coefficients(solimp: np.ndarray) -> np.ndarray:
    """Per-joint coefficients [7, J] of MuJoCo's impedance function from ``solimp`` [J, 5].

    Rows: dmin, dmax - dmin, 1 / width, midpoint, power, ``1 / mid^(p-1)`` and
    ``1 / (1 - mid)^(p-1)`` (eq. S5), after MuJoCo's clamping (``getsolparam``). A flat
    function (dmin = dmax, or no width) becomes dmin = (dmin + dmax) / 2 with no span.

    Example:
        >>> impedance_coefficients(np.array([[0.9, 0.95, 0.001, 0.5, 2.0]]))[:, 0].round(4).tolist()
        [0.9, 0.05, 1000.0, 0.5, 2.0, 2.0, 2.0]
    """
    solimp = np.array(solimp, dtype=np.float64)
    lo, hi = mujoco.mjMINIMP, mujoco.mjMAXIMP
    solimp[:, [0, 1, 3]] = np.clip(solimp[:, [0, 1, 3]], lo, hi)
    solimp[:, 2] = np.maximum(solimp[:, 2], 0.0)
    solimp[:, 4] = np.maximum(solimp[:, 4], 1.0)
    dmin, dmax, width, mid, power = solimp.T
    flat = (dmin == dmax) | (width <= mujoco.mjMINVAL)
    return np.stack(
        [
            np.where(flat, 0.5 * (dmin + dmax), dmin),
            np.where(flat, 0.0, dmax - dmin),
            np.where(flat, 0.0, 1.0 / np.where(flat, 1.0, width)),
            mid,
            power,
            1.0 / mid ** (power - 1),
            1.0 / (1.0 - mid) ** (power - 1),
        ]
    )


@dataclass(frozen=True)
class ArmModel:
    """The coefficients of the arm's closed-form dynamics and of its joint limits.

    Use :meth:`from_mujoco`; every field comes from the compiled model. Tensors are float64 on
    the model's device, laid out joint-major: per-joint values are [2, 1] columns that broadcast
    over states [2, E]. With ``theta = (theta1, theta2, delta)`` the links' angles and their
    difference, the closed form (docs/batting.md, eq. S1-S3) reads, for column vectors:
    ``theta = angle_map @ phi``; ``(c, c', G1, G2) = trig_map @ [cos theta; sin theta]`` (the
    coupling ``c(delta)``, its slope and the gravity torques on the links);
    ``(M11, M12, M22) = mass_const + c * mass_slope``; forces on the links become joint torques
    by ``force_map @``; the velocity products, ``c' (-theta2_dot^2, theta1_dot^2)`` on the
    links, are ``c' bias_map @ (theta2_dot^2, theta1_dot^2)`` with
    ``(theta2_dot, theta1_dot) = speed_map @ phi_dot``.

    Example:
        >>> from envs.batting import XML_PATH
        >>> arm = ArmModel.from_mujoco(mujoco.MjModel.from_xml_path(str(XML_PATH)))
        >>> arm.angle_map.tolist(), arm.lower.flatten().tolist()
        ([[1.0, 0.0], [1.0, -1.0], [0.0, -1.0]], [0.0, -0.7853981633974483])
    """

    angle_map: torch.Tensor  # [3, 2] joint angles -> (theta1, theta2, delta)
    trig_map: torch.Tensor  # [4, 6] (cos, sin of theta) -> (c, c', G1, G2) (kg m^2, N m)
    mass_const: tuple[float, float, float]  # (kg m^2) M11, M12, M22 at c = 0, with armature
    mass_slope: tuple[float, float, float]  # d(M11, M12, M22) / dc
    speed_map: torch.Tensor  # [2, 2] joint speeds -> (theta2_dot, theta1_dot)
    force_map: torch.Tensor  # [2, 2] forces on (theta1, theta2) -> joint torques (S^T)
    bias_map: torch.Tensor  # [2, 2] (theta2_dot^2, theta1_dot^2) -> torques per unit of c'
    damping: torch.Tensor  # [2, 1] (N m s/rad)
    stiffness: torch.Tensor  # [2, 1] (N m/rad)
    spring_ref: torch.Tensor  # [2, 1] (rad)
    passive: bool  # any damping or stiffness
    actuation: torch.Tensor  # [2, U] joint torque (N m) per unit of each control
    limited: torch.Tensor  # [2, 1] bool: the joint's limit is active
    all_limited: bool  # every joint's limit is active
    lower: torch.Tensor  # [2, 1] (rad) jnt_range
    upper: torch.Tensor  # [2, 1] (rad)
    margin: torch.Tensor  # [2, 1] (rad) jnt_margin: a limit row exists where distance < margin
    stiff_k: torch.Tensor  # [2, 1] K of the reference acceleration (1/s^2), solref resolved
    neg_damp_b: torch.Tensor  # [2, 1] -B of the reference acceleration (1/s)
    impedance: torch.Tensor  # [7, 2, 1] impedance_coefficients of jnt_solimp
    impedance_power: float | None  # solimp's power where both joints share it
    invweight: torch.Tensor  # [2, 1] dof_invweight0, the regulariser's diagonal approximation
    diag_exact: bool  # mjENBL_DIAGEXACT: the diagonal is (M^-1)_jj instead of invweight
    timestep: float  # (s) the model's opt.timestep, the RK4 step

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel, device: torch.device | str | None = None):
        """The arm of ``model`` (its first two joints), on ``device`` (CPU by default)."""
        b1, b2 = _check_planar_arm(model)
        opt = model.opt
        off = lambda bit: bool(opt.disableflags & bit)  # noqa: E731
        if opt.enableflags & ~_HARMLESS_ENABLES:
            raise ValueError(f"enable flags {opt.enableflags:#x} are not modelled (sleep, ...)")
        if np.abs(opt.wind).max() > 0 or opt.density > 0 or opt.viscosity > 0:
            raise ValueError("wind, density and viscosity are not modelled")
        if not off(_OFF.mjDSBL_FRICTIONLOSS) and np.abs(model.dof_frictionloss[:2]).max() > 0:
            raise ValueError(f"friction loss is not modelled: {model.dof_frictionloss[:2]}")
        s1, s2 = (float(np.sign(model.jnt_axis[j, 1])) for j in (0, 1))
        mass = model.body_mass[[b1, b2]]
        weight = mass * (1.0 - model.body_gravcomp[[b1, b2]])
        xz = [0, 2]
        a1, a2 = model.body_ipos[b1, xz], model.body_ipos[b2, xz]  # centres of mass
        elbow = model.body_pos[b2, xz]
        inertia = [_inertia_about_y(model, b) for b in (b1, b2)]
        inertia2 = float(mass[1] * a2 @ a2 + inertia[1])
        inertia1 = float(mass[0] * a1 @ a1 + inertia[0] + mass[1] * elbow @ elbow)
        cross_cos = float(mass[1] * elbow @ a2)  # c(delta) = cross_cos cos + cross_sin sin
        cross_sin = float(mass[1] * (elbow[0] * a2[1] - elbow[1] * a2[0]))
        gravity = np.zeros(2) if off(_OFF.mjDSBL_GRAVITY) else opt.gravity[xz].copy()
        p1, r1 = _perp_coefficients(weight[0] * a1 + weight[1] * elbow, gravity)
        p2, r2 = _perp_coefficients(weight[1] * a2, gravity)
        dofs = model.jnt_dofadr[:2]
        armature = [float(x) for x in model.dof_armature[dofs]]
        trig_map = np.zeros((6, 4))  # rows: cos theta1, theta2, delta, sin theta1, ...
        trig_map[[2, 5], 0] = cross_cos, cross_sin
        trig_map[[2, 5], 1] = cross_sin, -cross_cos
        trig_map[[0, 3], 2] = p1, r1
        trig_map[[1, 4], 3] = p2, r2

        def tensor(values, dtype=torch.float64):
            return torch.as_tensor(np.asarray(values), dtype=dtype, device=device)

        actuation = np.zeros((model.nu, 2))
        for u in range(model.nu):
            _check_motor(model, u)
            if not off(_OFF.mjDSBL_ACTUATION):
                joint = int(model.actuator_trnid[u, 0])
                actuation[u, joint] = model.actuator_gear[u, 0] * model.actuator_gainprm[u, 0]
        limited = model.jnt_limited[:2].astype(bool) & ~off(_OFF.mjDSBL_LIMIT)
        limited &= ~off(_OFF.mjDSBL_CONSTRAINT)
        solref = model.jnt_solref[:2].copy()
        if np.any((solref[:, 0] > 0) != (solref[:, 1] > 0)):
            raise ValueError(f"mixed solref formats are not modelled: {solref.tolist()}")
        standard = solref[:, 0] > 0
        if not off(_OFF.mjDSBL_REFSAFE):  # MuJoCo's integrator safety: timeconst >= 2 dt
            solref[standard, 0] = np.maximum(solref[standard, 0], 2.0 * opt.timestep)
        dmax = np.clip(model.jnt_solimp[:2, 1], mujoco.mjMINIMP, mujoco.mjMAXIMP)
        tiny = mujoco.mjMINVAL
        stiff_k = np.where(
            standard,
            1.0 / np.maximum(tiny, dmax**2 * solref[:, 0] ** 2 * solref[:, 1] ** 2),
            -solref[:, 0] / np.maximum(tiny, dmax**2),
        )
        damp_b = np.where(
            standard,
            2.0 / np.maximum(tiny, dmax * solref[:, 0]),
            -solref[:, 1] / np.maximum(tiny, dmax),
        )
        margin = model.jnt_margin[:2]
        if np.any(limited & (model.jnt_range[:2, 1] - model.jnt_range[:2, 0] <= 2 * margin)):
            raise ValueError(f"a joint's range must be wider than twice its margin {margin}")
        impedance = impedance_coefficients(model.jnt_solimp[:2])
        damping = model.dof_damping[dofs] * (not off(_OFF.mjDSBL_DAMPER))
        stiffness = model.jnt_stiffness[:2] * (not off(_OFF.mjDSBL_SPRING))
        column = lambda values, dtype=torch.float64: tensor(values, dtype).reshape(2, 1)  # noqa: E731
        return cls(
            angle_map=tensor([[s1, 0.0], [s1, s2], [0.0, s2]]),
            trig_map=tensor(trig_map.T),
            mass_const=(
                inertia1 + inertia2 + armature[0],
                s1 * s2 * inertia2,
                inertia2 + armature[1],
            ),
            mass_slope=(2.0, s1 * s2, 0.0),
            speed_map=tensor([[s1, s2], [s1, 0.0]]),
            force_map=tensor([[s1, s1], [0.0, s2]]),
            bias_map=tensor([[-s1, s1], [0.0, s2]]),
            damping=column(damping),
            stiffness=column(stiffness),
            spring_ref=column(model.qpos_spring[model.jnt_qposadr[:2]]),
            passive=bool(np.any(damping != 0) or np.any(stiffness != 0)),
            actuation=tensor(actuation.T),
            limited=column(limited, torch.bool),
            all_limited=bool(limited.all()),
            lower=column(model.jnt_range[:2, 0]),
            upper=column(model.jnt_range[:2, 1]),
            margin=column(margin),
            stiff_k=column(stiff_k),
            neg_damp_b=column(-damp_b),
            impedance=tensor(impedance).unsqueeze(-1),
            impedance_power=float(impedance[4, 0]) if impedance[4, 0] == impedance[4, 1] else None,
            invweight=column(model.dof_invweight0[dofs]),
            diag_exact=bool(opt.enableflags & _ON.mjENBL_DIAGEXACT),
            timestep=float(opt.timestep),
        )


def _check_motor(model: mujoco.MjModel, u: int) -> None:
    """Raise unless actuator ``u`` is a plain motor (force = gain x ctrl) on hinge 0 or 1."""
    plain = (
        model.actuator_trntype[u] == mujoco.mjtTrn.mjTRN_JOINT
        and model.actuator_trnid[u, 0] in (0, 1)
        and model.actuator_dyntype[u] == mujoco.mjtDyn.mjDYN_NONE
        and model.actuator_gaintype[u] == mujoco.mjtGain.mjGAIN_FIXED
        and model.actuator_biastype[u] == mujoco.mjtBias.mjBIAS_NONE
        and not model.actuator_ctrllimited[u]
        and not model.actuator_forcelimited[u]
        and not model.jnt_actfrclimited[model.actuator_trnid[u, 0]]
    )
    if not plain:
        raise ValueError(f"actuator {u} must be an unlimited motor on one of the arm's hinges")
