"""Picture of one ball-batting episode: arm and bat snapshots and the ball's flight.

Simulates one noiseless episode of an open-loop action sequence (by default the reference
optimum found by examples/batting_reference.py: cock, cock, ..., swing) with the env's
integration scheme, and draws the arm every few milliseconds (darker = later), the ball while
on the bat, and its closed-form flight to the ground, from the simulated positions.

    python examples/plot_batting_episode.py --sequence 0100011110 --out results/batting_episode.png
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from _cli import field, first_line, out_dir_error, parse


@dataclass
class Args:
    """Command-line arguments of the episode picture."""

    sequence: str = "0100011110"
    """the actions, one digit per control step (0 cock, 1 swing), e.g. 0011111000"""
    out: str = "results/batting_episode.png"
    """the PNG file (its folder is created)"""
    snapshot_ms: float = field(7.5, above=0)
    """simulated time between two drawn arm snapshots (ms)"""


def check(args: Args) -> str | None:
    if not args.sequence or set(args.sequence) - {"0", "1"}:
        return f"--sequence must be digits 0 and 1, got {args.sequence!r}"
    if len(args.sequence) > 10:
        return f"--sequence must have at most 10 actions (N = 10), got {len(args.sequence)}"
    return out_dir_error(Path(args.out).parent, flag="--out (its folder)")


def parse_args(argv: list[str] | None = None) -> Args:
    return parse(
        Args,
        argv,
        description=first_line(__doc__),
        check=check,
        unavailable={
            "trials": "it draws one noiseless episode",
            "seed": "the episode is noiseless: nothing is random",
            "out_dir": "this script writes one file: use --out FILE",
            "device": "MuJoCo runs on the CPU",
            "resume": "nothing to resume: it takes seconds",
            "backend": "one episode runs here",
        },
    )


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.batting import ACTION_TORQUES, CONTROL_DT, BattingSimulator  # noqa: E402


def simulate(sequence: str) -> tuple[list[np.ndarray], list[float], BattingSimulator]:
    """qpos at every physics step of the episode, their times (s), and the simulator."""
    sim = BattingSimulator(num_envs=1, nthread=1, record=True)
    sim.reset()
    qpos, times = [sim.qpos()[0]], [0.0]
    torques = np.asarray(ACTION_TORQUES)
    for t, a in enumerate(sequence):
        sim.step(torques[[int(a)]])
        steps = sim.last_qpos[0]
        dt = CONTROL_DT / len(steps)
        qpos.extend(steps)
        times.extend(t * CONTROL_DT + dt * (np.arange(len(steps)) + 1))
    return qpos, times, sim


def arm_points(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """(x, z) of shoulder, elbow and bat tip, [3, 2] (m)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    shoulder = data.body("upper_arm").xpos
    elbow = data.body("bat").xpos
    tip = elbow + data.body("bat").xmat.reshape(3, 3) @ np.array([0.0, 0.0, -0.62])
    return np.array([shoulder, elbow, tip])[:, [0, 2]]


def main(args: Args) -> Path:
    qpos, times, sim = simulate(args.sequence)
    model = sim.coarse_model
    fig, (ax, ax_zoom) = plt.subplots(
        1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [2.2, 1]}
    )
    launch = sim.launch[0]
    hit = bool(sim.hit[0])
    for axis in (ax, ax_zoom):
        axis.axhline(0.0, color="0.4", lw=1)
        pin = model.geom("pin")
        axis.add_patch(
            plt.Rectangle(
                (pin.pos[0] - pin.size[0], 0), 2 * pin.size[0], 2 * pin.size[2], color="0.5"
            )
        )
        # arm snapshots
        last_drawn = -np.inf
        for q, t in zip(qpos, times, strict=True):
            if t - last_drawn < args.snapshot_ms / 1e3 - 1e-9:
                continue
            last_drawn = t
            pts = arm_points(model, q)
            shade = 0.15 + 0.85 * t / times[-1]
            axis.plot(pts[:2, 0], pts[:2, 1], color=plt.cm.Blues(shade), lw=2.5)
            axis.plot(pts[1:, 0], pts[1:, 1], color=plt.cm.Oranges(shade), lw=2)
        # ball while in the simulation (before it is parked beside the plane)
        ball = np.array([q[2:5] for q in qpos])
        on_plane = (
            np.abs(ball[:, 1]) < 1e-3
        )  # (interpolated records toward the parked ball leave it)
        axis.plot(ball[on_plane, 0], ball[on_plane, 2], "k.", ms=2)
        axis.add_patch(
            plt.Circle((ball[0, 0], ball[0, 2]), sim.ball_radius, fc="white", ec="k", zorder=5)
        )
        if hit:
            p, v = launch[:3], launch[3:]
            t_land = v[2] + np.sqrt(v[2] ** 2 + 2 * sim.gravity * (p[2] - sim.ball_radius))
            t_land /= sim.gravity
            ts = np.linspace(0.0, t_land, 200)
            axis.plot(
                p[0] + v[0] * ts,
                p[2] + v[2] * ts - 0.5 * sim.gravity * ts**2,
                "r--",
                lw=1.2,
                label="flight (closed form)",
            )
            axis.plot([p[0]], [p[2]], "r^", ms=6, label="launch")
        axis.set_aspect("equal")
        axis.set_xlabel("x (m)")
        axis.set_ylabel("z (m)")
    carry = sim.carry[0]
    title = f"actions {args.sequence} (0 cock, 1 swing): "
    title += f"carry {carry:.2f} m" if hit else "no hit"
    if hit:
        speed = np.linalg.norm(launch[3:])
        angle = np.degrees(np.arctan2(launch[5], launch[3]))
        title += f", launch {speed:.1f} m/s at {angle:.0f} deg"
    ax.set_title(title)
    ax.set_xlim(-1.0, max(2.0, sim.pin_xy[0] + carry + 0.5))
    ax.set_ylim(-0.1, max(1.8, ax.get_ylim()[1]))
    ax.legend(loc="upper right")
    ax_zoom.set_xlim(-0.9, 0.9)
    ax_zoom.set_ylim(-0.05, 1.6)
    ax_zoom.set_title("arm (blue: link 1, orange: bat; darker = later)")
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"{title}\nwrote {out}")
    return out


if __name__ == "__main__":
    main(parse_args())
