"""The ball's free flight after the impact, in closed form (no drag).

From the launch state (position p, velocity v) the ball's centre moves as
``p + v t - g t^2 e_z / 2``; its lowest point first touches the ground (centre height = radius
r) after ``t = (v_z + sqrt(v_z^2 + 2 g (p_z - r))) / g``, and the carry is the horizontal
distance from the pin to ``p + v t``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["flight_carry", "flight_time"]


def flight_time(pos: np.ndarray, vel: np.ndarray, radius: float, gravity: float) -> np.ndarray:
    """Time (s) until a ball launched at ``pos`` [..., 3] (m) with ``vel`` [..., 3] (m/s) first
    touches the ground, [...].

    Example:
        >>> float(flight_time(np.array([0.0, 0, 1.04]), np.array([2.0, 0, 0]), 0.04, 9.81)
        ...       .round(4))
        0.4515
    """
    height = np.maximum(pos[..., 2] - radius, 0.0)
    return (vel[..., 2] + np.sqrt(vel[..., 2] ** 2 + 2.0 * gravity * height)) / gravity


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
    t = flight_time(pos, vel, radius, gravity)
    land = pos[..., :2] + vel[..., :2] * t[..., None]
    return np.linalg.norm(land - pin_xy, axis=-1)
