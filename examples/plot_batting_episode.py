"""Picture of one ball-batting episode: arm and bat snapshots and the ball's flight.

Simulates one noiseless episode of an open-loop action sequence (by default the reference
optimum found by examples/batting_reference.py: cock, cock, ..., swing) with the env's
integration scheme, and draws the arm every few milliseconds (darker = later), the ball while
on the bat, and its closed-form flight to the ground, from the simulated positions.

    python examples/plot_batting_episode.py --sequence 0100011110 --out results/batting_episode.png
"""

import sys
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import mujoco
import numpy as np
import tyro

from envs.batting import ACTION_TORQUES, CONTROL_DT, BattingSimulator, PhysicsHook


@dataclass(frozen=True)
class Args:
    """The episode picture's arguments."""

    sequence: str = "0100011110"
    """the actions, one digit per control step (0 cock, 1 swing), e.g. 0011111000"""
    out: str = "results/batting_episode.png"
    """the PNG file (its folder is created)"""
    snapshot_ms: float = 7.5
    """simulated time between two drawn arm snapshots (ms)"""


class ArmTrace(PhysicsHook):
    """Keeps the qpos of every physics step of the last control step (a simulator hook): after
    each step, ``last_qpos[i]`` holds simulation i's qpos at every ``fine_dt`` of it, [n_fine,
    nq], interpolated linearly across coarse steps (the env's adaptive integration scheme)."""

    wants_qpos = True  # coarse rollouts record qpos too

    def __init__(self) -> None:
        self.last_qpos: list[np.ndarray] = []
        self._trace: dict = {}

    def on_step_start(self, sim: BattingSimulator, states: np.ndarray | None) -> None:
        bounds = range(sim.n_coarse + 1)  # the coarse pass: the states at the intervals' ends
        self._trace = {
            i: [(j * sim.n_sub, sim._qpos(states[i, j])) for j in bounds]
            for i in range(sim.num_envs)
        }

    def on_interval(self, sim, ids: np.ndarray, j: int, out: dict, coarse: bool) -> None:
        for r, env in enumerate(ids):
            trace = self._trace.setdefault(env, [])
            base = j * sim.n_sub
            trace[:] = [(t, q) for t, q in trace if t <= base]
            if coarse:
                nstep = out["qpos"].shape[1]
                trace.extend((base + (k + 1) * sim.n_sub, out["qpos"][r, k]) for k in range(nstep))
            else:
                trace.extend((base + k + 1, out["qpos"][r, k]) for k in range(sim.n_sub))

    def on_step_end(self, sim: BattingSimulator) -> None:
        grid = np.arange(1, sim.n_fine + 1)
        self.last_qpos = []
        for env in range(sim.num_envs):
            trace = self._trace[env]
            t = np.array([t for t, _ in trace], dtype=np.float64)
            q = np.array([q for _, q in trace])
            interpolated = [np.interp(grid, t, q[:, c]) for c in range(q.shape[1])]
            self.last_qpos.append(np.stack(interpolated, 1))


def simulate(sequence: str) -> tuple[list[np.ndarray], list[float], BattingSimulator]:
    """qpos at every physics step of the episode, their times (s), and the simulator."""
    trace = ArmTrace()
    sim = BattingSimulator(num_envs=1, nthread=1, hook=trace)
    sim.reset()
    qpos, times = [sim.qpos()[0]], [0.0]
    torques = np.asarray(ACTION_TORQUES)
    for t, a in enumerate(sequence):
        sim.step(torques[[int(a)]])
        steps = trace.last_qpos[0]
        dt = CONTROL_DT / len(steps)
        qpos.extend(steps)
        times.extend(t * CONTROL_DT + dt * (np.arange(len(steps)) + 1))
    return qpos, times, sim


def arm_points(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """(x, z) of shoulder, elbow and bat tip, [3, 2] (m)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    shoulder, elbow = data.body("upper_arm").xpos, data.body("bat").xpos
    tip = elbow + data.body("bat").xmat.reshape(3, 3) @ np.array([0.0, 0.0, -0.62])
    return np.array([shoulder, elbow, tip])[:, [0, 2]]


def draw_scene(axis, model, qpos, times, sim, snapshot_ms: float) -> None:
    """Ground, pin, arm snapshots (darker = later), the ball on the bat and its flight."""
    axis.axhline(0.0, color="0.4", lw=1)
    pin = model.geom("pin")
    width, height = 2 * pin.size[0], 2 * pin.size[2]
    axis.add_patch(plt.Rectangle((pin.pos[0] - pin.size[0], 0), width, height, color="0.5"))
    last_drawn = -np.inf
    for q, t in zip(qpos, times, strict=True):
        if t - last_drawn < snapshot_ms / 1e3 - 1e-9:
            continue
        last_drawn = t
        pts = arm_points(model, q)
        shade = 0.15 + 0.85 * t / times[-1]
        axis.plot(pts[:2, 0], pts[:2, 1], color=plt.cm.Blues(shade), lw=2.5)
        axis.plot(pts[1:, 0], pts[1:, 1], color=plt.cm.Oranges(shade), lw=2)
    ball = np.array([q[2:5] for q in qpos])
    on_plane = np.abs(ball[:, 1]) < 1e-3  # (a ball out of play is parked beside the plane)
    axis.plot(ball[on_plane, 0], ball[on_plane, 2], "k.", ms=2, label="ball (simulated)")
    start = plt.Circle((ball[0, 0], ball[0, 2]), sim.ball_radius, fc="white", ec="k", zorder=5)
    axis.add_patch(start)
    if sim.hit[0]:
        launch = sim.launch[0]
        p, v = launch[:3], launch[3:]
        t_land = v[2] + np.sqrt(v[2] ** 2 + 2 * sim.gravity * (p[2] - sim.ball_radius))
        ts = np.linspace(0.0, t_land / sim.gravity, 200)
        flight_x, flight_z = p[0] + v[0] * ts, p[2] + v[2] * ts - 0.5 * sim.gravity * ts**2
        axis.plot(flight_x, flight_z, "k--", lw=1.2, label="flight (closed form, no drag)")
        axis.plot([p[0]], [p[2]], "k^", ms=6, label="launch")
    axis.set(aspect="equal", xlabel="x (m)", ylabel="height z (m)")


def draw_angles(axis, qpos, times, sequence: str, launch_ms: float | None) -> None:
    """Joint angles over the episode, each control step shaded by its action."""
    ms = 1e3 * np.asarray(times)
    angles = np.array([q[:2] for q in qpos])
    step_ms = 1e3 * CONTROL_DT
    on_top = dict(fontsize=6, ha="center", va="top", transform=axis.get_xaxis_transform())
    for t, a in enumerate(sequence):
        colour = "0.88" if a == "0" else "lightyellow"
        axis.axvspan(t * step_ms, (t + 1) * step_ms, color=colour, lw=0)
        axis.text((t + 0.5) * step_ms, 0.97, "cock" if a == "0" else "swing", **on_top)
    axis.plot(ms, angles[:, 0], color="tab:blue", label="φ1 (shoulder, link 1)")
    axis.plot(ms, angles[:, 1], color="tab:orange", label="φ2 (elbow, bat)")
    for limit, colour in ((0.0, "tab:blue"), (np.pi / 4, "tab:blue"), (-np.pi / 4, "tab:orange")):
        axis.axhline(limit, color=colour, ls=":", lw=0.8)
    if launch_ms is not None:
        axis.axvline(launch_ms, color="k", ls="--", lw=1, label="ball leaves the pin")
    axis.set(xlim=(0, len(sequence) * step_ms), ylabel="joint angle (rad); dotted: limits")
    axis.set_xlabel("time (ms); shading: the action of each 75 ms control step")
    axis.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, 0.72))


def main(argv: list[str] | None = None) -> Path:
    args = tyro.cli(Args, args=argv, description=__doc__)
    try:  # checked before any work: one line naming the value, exit 2
        if not args.sequence or set(args.sequence) - {"0", "1"} or len(args.sequence) > 10:
            raise ValueError(f"sequence must be 1 to 10 digits 0 and 1, got {args.sequence!r}")
        if not args.snapshot_ms > 0:
            raise ValueError(f"snapshot_ms must be > 0, got {args.snapshot_ms}")
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    qpos, times, sim = simulate(args.sequence)
    fig = plt.figure(figsize=(12, 6.9))
    axes = fig.subplot_mosaic("FF;AJ", height_ratios=[0.62, 1.45], width_ratios=[1, 1.25])
    ax_flight, ax_arm, ax_angles = axes["F"], axes["A"], axes["J"]  # flight, arm, joint angles
    hit, carry, launch = bool(sim.hit[0]), sim.carry[0], sim.launch[0]
    for axis in (ax_flight, ax_arm):
        draw_scene(axis, sim.coarse_model, qpos, times, sim, args.snapshot_ms)
    ball = np.array([q[2:5] for q in qpos])
    moved = np.flatnonzero(np.linalg.norm(ball - ball[0], axis=1) > 1e-3)
    launch_ms = 1e3 * times[moved[0]] if hit and len(moved) else None
    draw_angles(ax_angles, qpos, times, args.sequence, launch_ms)

    speed, angle = np.linalg.norm(launch[3:]), np.degrees(np.arctan2(launch[5], launch[3]))
    title = f"actions {args.sequence} (0 cock, 1 swing), one noiseless episode: "
    title += f"carry {carry:.2f} m, launch {speed:.1f} m/s at {angle:.0f}°" if hit else "no hit"
    fig.suptitle(title)
    ax_flight.set_title("the whole flight", fontsize=9)
    ax_flight.set_xlim(-1.0, max(2.0, sim.pin_xy[0] + carry + 0.8))
    ax_flight.set_ylim(-0.1, max(1.8, ax_flight.get_ylim()[1]))
    ax_flight.legend(loc="upper right", fontsize=8)
    ax_arm.set(xlim=(-0.9, 0.9), ylim=(-0.05, 1.6))
    arm = f"the arm every {args.snapshot_ms:g} ms (blue: link 1, orange: bat; darker = later)"
    ax_arm.set_title(arm, fontsize=9)
    ax_angles.set_title("joint angles", fontsize=9)
    fig.tight_layout()
    out = Path(args.out)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"{title}\nwrote {out}")
    return out


if __name__ == "__main__":
    main()
