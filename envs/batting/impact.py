"""The impact window of the batting simulator: where the coarse swing is re-integrated finely.

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
and whose predicted gap falls below ``margin`` (5 mm) in some interval is re-integrated from the
saved boundary state before its first such interval: interval by interval, at ``fine_dt``
(0.125 ms Euler, 60 steps per interval; the ball-bat contact's time constant of 4 ms spans 32 of
them) where the predicted gap is below ``margin``, the ball touches the bat, or its launch is
still pending, and coarsely elsewhere. Once the ball has been launched and no longer touches the
bat it is parked (below) and the rest of the control step is coarse. So only the few intervals
(7.5 ms each) around an impact or a near miss are fine, not whole 75 ms control steps. In 2048
random episodes the predicted minimum gap of a fine interval was never more than 0.02 mm above
the fine simulation's, so the 5 mm margin is still 250 times that error; the 5 cm of before
re-integrated near misses as well, for the same fidelity (benchmarks/batting_fidelity.py).

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

"""

from __future__ import annotations

import math

import numpy as np

from .constants import LOOKAHEAD_MAX, PARK_Y, QPOS_BALL, QVEL_BALL
from .flight import flight_carry, flight_time

__all__ = ["ImpactWindow"]

_BOUND_SLACK = 1e-9  # (m) kept below the lower bound of the gap: rounding never prunes a point


class ImpactWindow:
    """The fine impact window and the launch of :class:`~envs.batting.BattingSimulator`.

    A mixin: its methods work on the simulator's state (``main`` and ``fine`` batches, ``hit``,
    ``in_play``, ``launch``, the arm geometry) and are called from its ``step``. One concept,
    kept in its own file: which intervals are stepped finely, the re-integration, the look-ahead
    for the end of the first contact, the launch and the parking of the ball.
    """

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
            # (the columns first, a view, then the rows: a copy of nq + nv columns only)
            qpos, qvel = self._qpos(states)[rows], self._qvel(states)[rows]  # [E', n + 1, *]
            q0, q1 = qpos[:, :-1, :2], qpos[:, 1:, :2]
            v0, v1 = qvel[:, :-1, :2], qvel[:, 1:, :2]
            ball = 0.5 * (qpos[:, :-1, 2:5] + qpos[:, 1:, 2:5])  # at rest, [E', n, 3]
            # Most intervals are far from the ball: a lower bound of the gap at every point,
            # the gap at the interval's start less the most any bat point can move in it,
            # leaves only the rest to evaluate point by point (the same points, the same
            # gaps). The Hermite cubic lies in the convex hull of its Bezier control points
            # (start, start + v0 dt / 3, end - v1 dt / 3, end), so no angle of the interval
            # moves further from its start than one of them.
            third = self.coarse_dt / 3.0
            moves = (v0 * third, (q1 - q0) - v1 * third, q1 - q0)  # control points - start
            turn1 = np.maximum.reduce([np.abs(m[..., 0]) for m in moves])  # the shoulder's
            turn_bat = np.maximum.reduce([np.abs(m[..., 0] - m[..., 1]) for m in moves])
            reach = self._elbow_reach * turn1 + self._bat_reach * turn_bat  # (phi1 - phi2)
            bound = self.bat_ball_gap(q0[..., 0], q0[..., 1], ball) - reach
            check = bound < self.margin + _BOUND_SLACK  # [E', n]
            if check.any():
                e, k = np.nonzero(check)
                dt = self.coarse_dt  # [C, 4 knots, 2 angles] -> [C, points, 2]
                knots = np.stack([q0[e, k], v0[e, k] * dt, q1[e, k], v1[e, k] * dt], axis=1)
                points = self._hermite @ knots
                gap = self.bat_ball_gap(points[..., 0], points[..., 1], ball[e, k][:, None])
                near[rows[e], k] = gap.min(axis=-1) < self.margin
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
            if self.hook is not None:
                self.hook.on_interval(self, ids[fine], j, out, coarse=False)
            bat = self._sensor(out["sensordata"], "bat_ball_contact") > 0  # [F, n_sub]
            pin = self._sensor(out["sensordata"], "pin_ball_contact") > 0
            env = ids[fine]
            # the episode's first contact: its launch is searched from that physics step on
            first = bat.any(axis=1) & ~(self.hit[env] | first_hit[env] | pending[fine])
            first_hit[env[first]] = pending[fine[first]] = True
            since = np.where(first, bat.argmax(axis=1), 0)
            free = ~bat & ~pin & (np.arange(bat.shape[1]) >= since[:, None])
            f = np.flatnonzero(pending[fine] & free.any(axis=1))  # the launches in this interval
            if len(f):
                k = free[f].argmax(axis=1)[:, None]  # state k: the start, or after step k - 1
                at_start = self._qpos(chunk_start[f])[:, 2:5], self._qvel(chunk_start[f])[:, 2:5]
                after = out["qpos"][f, k[:, 0] - 1, 2:5], out["qvel"][f, k[:, 0] - 1, 2:5]
                pos, vel = (np.where(k == 0, a, b) for a, b in zip(at_start, after, strict=True))
                carry[env[f]] = self._record_launch(env[f], pos, vel)
                pending[fine[f]] = False
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
        out = self._run(self.main, ids[rows], torque[rows], nstep, qpos=self._hook_wants_qpos)
        cur[rows] = self.main.state[ids[rows]]
        if self.hook is not None:
            self.hook.on_interval(self, ids[rows], j, out, coarse=True)

    # -- the launch and the flight ------------------------------------------------------------

    def _record_launch(self, env, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """Record the launch of simulations ``env`` (an index or [L]) from ``pos``, ``vel``
        ([3] or [L, 3]); returns their carries."""
        self.launch[env] = np.concatenate([pos, vel], axis=-1)
        return flight_carry(pos, vel, self.pin_xy, self.ball_radius, self.gravity)

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
        t = flight_time(pos, vel, self.ball_radius, self.gravity)
        qpos, qvel = self._qpos(rows), self._qvel(rows)
        qpos[:, QPOS_BALL] = 0.0
        qpos[:, 2] = pos[:, 0] + vel[:, 0] * t
        qpos[:, 3] = PARK_Y
        qpos[:, 4] = self.ball_radius
        qpos[:, 5] = 1.0  # identity quaternion
        qvel[:, QVEL_BALL] = 0.0
        self.in_play[ids] = False
        return rows
