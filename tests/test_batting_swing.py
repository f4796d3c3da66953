"""Tests of envs/batting/swing.py: the tensor swing against MuJoCo, the engine of record.

Ground truth is MuJoCo itself: ``mj_forward`` for the accelerations, the coarse model's own
RK4 rollout (``BattingSimulator(swing="mujoco")``) for the swing and for whole episodes.
"""

from __future__ import annotations

import itertools

import mujoco
import numpy as np
import pytest
import torch

from envs.batting import ACTION_TORQUES, MAX_STEPS, BattingEnv, BattingSimulator, PhysicsHook
from envs.batting.arm_model import ArmModel
from envs.batting.swing import TensorSwing, arm_acceleration, rk4_swing, state_offsets

INTEGRATION_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
STATE_TOL = (1e-5, 1e-3)  # (rad, rad/s): worst difference of an observed state allowed


def coarse_model() -> tuple[mujoco.MjModel, np.ndarray]:
    """The simulator's coarse model (RK4, frozen ball) and its initial state row."""
    sim = BattingSimulator(num_envs=1, nthread=1, swing="mujoco")
    return sim.coarse_model, sim.main.state[0].copy()


def mujoco_accelerations(model, initial, q, v, ctrl) -> tuple[np.ndarray, np.ndarray]:
    """``qacc`` of the arm [n, 2] from ``mj_forward`` and the number of limit rows [n]."""
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, initial, INTEGRATION_STATE)
    acc, rows = np.empty((len(q), 2)), np.empty(len(q), dtype=np.int64)
    for i in range(len(q)):
        data.qpos[:2], data.qvel[:2], data.ctrl[:] = q[i], v[i], ctrl[i]
        mujoco.mj_forward(model, data)
        acc[i], rows[i] = data.qacc[:2], data.nefc
    return acc, rows


def random_states(n: int, seed: int) -> tuple[np.ndarray, ...]:
    """Angles reaching 0.2 rad past both limits of both joints, speeds to 40 rad/s, torques."""
    rng = np.random.default_rng(seed)
    q = rng.uniform([-0.2, -1.0], [1.0, 1.0], (n, 2))
    return q, rng.uniform(-40.0, 40.0, (n, 2)), rng.uniform(-60.0, 60.0, (n, 2))


def tensor_accelerations(arm: ArmModel, q, v, ctrl) -> np.ndarray:
    joint_major = [torch.as_tensor(np.ascontiguousarray(x.T)) for x in (q, v, ctrl)]
    force = arm.actuation @ joint_major[2]
    return arm_acceleration(arm, joint_major[0], joint_major[1], force).numpy().T


def assert_close_relative(got, expected, tol):
    error = np.abs(got - expected) / np.maximum(np.abs(expected), 1.0)
    assert error.max() <= tol, (error.max(), np.unravel_index(error.argmax(), error.shape))


def test_accelerations_match_mj_forward_past_the_limits():
    """20,000 states, most of them with one or two joints past a limit (MuJoCo's soft limit
    constraint active): the closed form with the limit rows gives MuJoCo's qacc."""
    model, initial = coarse_model()
    q, v, ctrl = random_states(20_000, seed=0)
    expected, rows = mujoco_accelerations(model, initial, q, v, ctrl)
    assert (rows == 1).sum() > 5000 and (rows == 2).sum() > 1000  # limits are exercised
    got = tensor_accelerations(ArmModel.from_mujoco(model), q, v, ctrl)
    assert_close_relative(got, expected, 1e-9)


def test_accelerations_follow_the_models_parameters():
    """Armature, damping, springs, a joint margin, another impedance curve, MuJoCo's exact
    diagonal and gravity compensation: every parameter is read from the model, none copied."""
    model, initial = coarse_model()
    model.dof_armature[:2] = (0.02, 0.01)
    model.dof_damping[:2] = (0.5, 0.3)
    model.jnt_stiffness[:2] = (2.0, 1.0)
    model.qpos_spring[:2] = (0.3, -0.1)
    model.jnt_margin[:2] = (0.01, 0.02)
    model.jnt_solimp[0] = (0.8, 0.99, 0.05, 0.3, 3.0)
    model.jnt_solref[1] = (-5000.0, -50.0)  # the direct format (stiffness, damping)
    model.body_gravcomp[1] = 0.25
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_DIAGEXACT
    q, v, ctrl = random_states(5000, seed=1)
    expected, rows = mujoco_accelerations(model, initial, q, v, ctrl)
    assert (rows == 2).sum() > 200
    got = tensor_accelerations(ArmModel.from_mujoco(model), q, v, ctrl)
    assert_close_relative(got, expected, 1e-9)


def test_models_it_cannot_reproduce_are_refused():
    model, _ = coarse_model()
    model.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS)
    model.dof_frictionloss[0] = 0.1
    with pytest.raises(ValueError, match="friction loss"):
        ArmModel.from_mujoco(model)
    model, _ = coarse_model()
    model.jnt_axis[0] = (1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="axis"):
        ArmModel.from_mujoco(model)
    model, _ = coarse_model()
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    with pytest.raises(ValueError, match="RK4"):
        TensorSwing(model)
    with pytest.raises(ValueError, match="swing"):
        BattingSimulator(num_envs=1, swing="jax")
    with pytest.raises(ValueError, match="RK4"):
        BattingSimulator(num_envs=1, swing="tensor", coarse_integrator="euler")


def test_one_control_step_gives_mujocos_state_rows():
    """From varied start states (the arm anywhere, moving, past its limits; the ball resting or
    drifting) one control step of 10 RK4 steps equals MuJoCo's rollout in every entry of the
    integration state: the arm to the fidelity bound, the rest (time, ball, controls, warm
    start of the ball) exactly where the ball rests."""
    sim = BattingSimulator(num_envs=256, nthread=1, swing="mujoco")
    rng = np.random.default_rng(2)
    start = np.repeat(sim.main.state[:1], 256, axis=0)
    q, v, ctrl = random_states(256, seed=3)
    qpos = state_offsets(sim.coarse_model)[mujoco.mjtState.mjSTATE_QPOS.value]
    qvel = state_offsets(sim.coarse_model)[mujoco.mjtState.mjSTATE_QVEL.value]
    start[:, qpos : qpos + 2], start[:, qvel : qvel + 2] = q, 0.3 * v
    # a ball left moving by a fine window (its linear and angular speed)
    start[::4, qvel + 2 : qvel + 8] = rng.normal(0.0, 1e-4, (64, 6))
    sim.main.state[:] = start
    expected = sim._swing(ctrl)  # MuJoCo's coarse rollout
    got, bad = TensorSwing(sim.coarse_model).rollout(start, ctrl, sim.n_coarse)
    assert not bad.any() and got.shape == expected.shape
    offsets = state_offsets(sim.coarse_model)
    arm_pos, arm_vel, warm = (
        [offsets[component.value], offsets[component.value] + 1]
        for component in (
            mujoco.mjtState.mjSTATE_QPOS,
            mujoco.mjtState.mjSTATE_QVEL,
            mujoco.mjtState.mjSTATE_WARMSTART,
        )
    )
    assert np.abs(got[..., arm_pos] - expected[..., arm_pos]).max() < STATE_TOL[0]
    assert np.abs(got[..., arm_vel] - expected[..., arm_vel]).max() < STATE_TOL[1]
    assert_close_relative(got[..., warm], expected[..., warm], 1e-4)  # last stage's qacc
    rest = np.setdiff1d(np.arange(got.shape[-1]), arm_pos + arm_vel + warm)
    resting = np.arange(256) % 4 != 0
    np.testing.assert_array_equal(got[resting][..., rest], expected[resting][..., rest])
    # a moving ball drifts as in MuJoCo (whose gravity compensation of a turning ball leaves
    # accelerations of 1e-15 m/s^2 from rounding)
    np.testing.assert_allclose(got[..., rest], expected[..., rest], rtol=0, atol=1e-12)


class NearIntervals(PhysicsHook):
    """Records the coarse intervals each control step re-integrates finely, bool [E, n]."""

    def __init__(self):
        self.near = []

    def on_step_start(self, sim, states):
        self.near.append(sim._near_intervals(states))


def episodes(swing: str, torques: np.ndarray) -> dict:
    """Episodes of given applied torques [E, N, 2] with the coarse swing in ``swing``."""
    hook = NearIntervals()
    sim = BattingSimulator(num_envs=len(torques), swing=swing, hook=hook)
    obs, hit_step = [sim.reset()], np.full(len(torques), -1)
    for t in range(torques.shape[1]):
        ob, _, first_hit = sim.step(torques[:, t])
        obs.append(ob)
        hit_step[first_hit] = t
    return {
        "obs": np.stack(obs, 1),
        "near": np.stack(hook.near, 1),
        "hit_step": hit_step,
        "carry": sim.carry.copy(),
        "fine_steps": sim.fine_steps.copy(),
    }


@pytest.mark.parametrize("noise", [False, True], ids=["all 1024 open-loop", "noisy"])
def test_episodes_match_the_mujoco_swing(noise):
    """Whole episodes, impact windows included: every one of the 2^10 = 1024 noiseless
    open-loop action sequences (N = 10, A = 2), and 1024 random noisy ones. The observed states
    agree to the bound, the same intervals are flagged for the impact window, the same episodes
    hit in the same steps, and the carries agree (measured: 1.6e-5 m at most)."""
    seqs = np.array(list(itertools.product((0, 1), repeat=MAX_STEPS)))
    torques = np.asarray(ACTION_TORQUES)[seqs]
    if noise:
        rng = np.random.default_rng(4)
        torques = torques[rng.permutation(len(seqs))] + rng.normal(0.0, 3**0.5, torques.shape)
    ref, got = episodes("mujoco", torques), episodes("tensor", torques)
    error = np.abs(got["obs"] - ref["obs"]).max((0, 1))
    assert error[[0, 2]].max() < STATE_TOL[0] and error[[1, 3]].max() < STATE_TOL[1], error
    np.testing.assert_array_equal(got["near"], ref["near"])
    np.testing.assert_array_equal(got["hit_step"], ref["hit_step"])
    np.testing.assert_array_equal(got["fine_steps"], ref["fine_steps"])
    assert (ref["hit_step"] >= 0).sum() > 400  # hits and misses both
    assert np.abs(got["carry"] - ref["carry"]).max() < 1e-3


def test_env_default_is_the_tensor_swing_and_mujoco_stays_available():
    """The same seed and actions give the same episode with either swing (noise included)."""
    actions = torch.randint(0, 2, (MAX_STEPS, 8), generator=torch.Generator().manual_seed(0))
    runs = []
    for swing in ("tensor", "mujoco"):
        env = BattingEnv(batch_size=8, seed=0, **({} if swing == "tensor" else {"swing": swing}))
        assert env.sim.swing == swing
        td, out = env.reset(), []
        for action in actions:
            td = env.step(td.set("action", action))
            out.append(td["next"].select("observation", "reward"))
            td = td["next"]
        runs.append(torch.stack(out, 1))
    torch.testing.assert_close(runs[0]["observation"], runs[1]["observation"])
    torch.testing.assert_close(runs[0]["reward"], runs[1]["reward"], atol=1e-3, rtol=0)


def test_a_rows_swing_does_not_depend_on_its_batch():
    """Every row is computed on its own (no reduction across arms): the same start state and
    torque give the same bits alone, in any batch and at any position (batched trials
    reproduce one-at-a-time runs)."""
    model, initial = coarse_model()
    swing = TensorSwing(model)
    q, v, ctrl = random_states(37, seed=5)
    start = np.repeat(initial[None], 37, axis=0)
    start[:, 1:3], start[:, 10:12] = q, 0.3 * v
    batch, _ = swing.rollout(start, ctrl, 10)
    for i in (0, 5, 36):
        alone, _ = swing.rollout(start[i : i + 1], ctrl[i : i + 1], 10)
        np.testing.assert_array_equal(alone[0], batch[i])
    order = np.random.default_rng(6).permutation(37)
    shuffled, _ = swing.rollout(start[order], ctrl[order], 10)
    np.testing.assert_array_equal(shuffled, batch[order])


def test_the_swing_dynamics_stay_on_the_device_they_are_given():
    """Without a GPU: on PyTorch's meta device (shapes, no numbers) every tensor of the model
    and of the RK4 swing must be made there, or an operation mixing it with a CPU tensor
    raises; a state on another device than the model's is refused the same way."""
    model, _ = coarse_model()
    arm = ArmModel.from_mujoco(model, torch.device("meta"))
    q = torch.zeros(2, 8, dtype=torch.float64, device="meta")
    force = arm.actuation @ torch.ones(2, 8, dtype=torch.float64, device="meta")
    angles, speeds, accelerations = rk4_swing(arm, q, torch.zeros_like(q), force, 10)
    assert (angles.shape, speeds.shape, accelerations.shape) == ((11, 2, 8),) * 2 + ((10, 2, 8),)
    assert {x.device.type for x in (angles, speeds, accelerations)} == {"meta"}
    with pytest.raises(RuntimeError, match="device"):
        rk4_swing(arm, torch.zeros(2, 8, dtype=torch.float64), torch.zeros_like(q), force, 10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_swing_on_cuda_equals_the_cpu_swing():
    model, initial = coarse_model()
    start = np.repeat(initial[None], 64, axis=0)
    ctrl = np.asarray(ACTION_TORQUES)[np.arange(64) % 2]
    cpu, _ = TensorSwing(model).rollout(start, ctrl, 10)
    cuda, _ = TensorSwing(model, device="cuda").rollout(start, ctrl, 10)
    np.testing.assert_allclose(cuda, cpu, rtol=0, atol=1e-9)
