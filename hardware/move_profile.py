"""The path of ``Arm.move_to``: a trapezoidal speed profile and the joint targets along it.

``trapezoid`` gives the distance travelled along a trapezoidal (or, for a short way,
triangular) speed profile and ``trapezoid_duration`` its length in time; ``move_path`` turns
one move into the 1 kHz position targets the arm's servo follows: the joint with the longest
way follows the profile, the others are scaled to arrive together. Units: rad, rad/s, rad/s^2,
s (``trapezoid`` in any unit of length).
"""

from __future__ import annotations

import math

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD


def trapezoid(distance: float, speed: float, accel: float, t):
    """Distance travelled at time(s) t s along a trapezoidal (or triangular) speed profile.

    Args:
        distance: the whole way, any unit L (rad in ``move_path``); <= 0: no motion.
        speed: L/s, the top speed (a short way never reaches it). accel: L/s^2 of both ramps.
        t: s from the start, any shape.

    Returns:
        L travelled at ``t``, shaped as ``t`` (0 before the start, ``distance`` after the end).
    """
    t = np.asarray(t, dtype=float)
    if distance <= 0:
        return np.zeros_like(t)
    t_acc = speed / accel
    if accel * t_acc**2 > distance:  # triangular: never reaches ``speed``
        t_acc = math.sqrt(distance / accel)
        speed = accel * t_acc
    t_total = 2 * t_acc + (distance - accel * t_acc**2) / speed
    tc = np.clip(t, 0.0, t_total)
    r = t_total - tc
    return np.where(
        tc < t_acc,
        0.5 * accel * tc**2,
        np.where(
            r < t_acc,
            distance - 0.5 * accel * r**2,
            0.5 * accel * t_acc**2 + speed * (tc - t_acc),
        ),
    )


def trapezoid_duration(distance: float, speed: float, accel: float) -> float:
    """Duration of ``trapezoid`` over ``distance``.

    Args:
        distance: the whole way, L. speed: L/s, the top speed. accel: L/s^2 of both ramps.

    Returns:
        s from the start to the end of the motion (0 for ``distance`` <= 0).
    """
    if distance <= 0:
        return 0.0
    t_acc = speed / accel
    if accel * t_acc**2 > distance:
        return 2 * math.sqrt(distance / accel)
    return 2 * t_acc + (distance - accel * t_acc**2) / speed


def move_path(
    start: np.ndarray,
    target: np.ndarray,
    speed: float,
    accel: float,
    settle: float = 0.0,
    dt: float = CONTROL_PERIOD,
) -> np.ndarray:
    """The position targets of one ``Arm.move_to``: the joint with the longest way follows
    ``trapezoid``, the others are scaled to arrive together; then ``settle`` s at the target.

    Args:
        start: (n,) rad, the current targets. target: (n,) rad.
        speed: rad/s, top speed of the longest way. accel: rad/s^2 of its ramps.
        settle: s held at the target. dt: s, the control period.

    Returns:
        (T, n) rad, row i the target at (i + 1) ``dt`` s.
    """
    delta = target - start
    dist = float(np.abs(delta).max())
    steps = math.ceil(trapezoid_duration(dist, speed, accel) / dt - 1e-9)
    steps += int(round(settle / dt))
    times = np.arange(1, steps + 1) * dt
    frac = trapezoid(dist, speed, accel, times) / dist if dist > 0 else np.ones(steps)
    return start + frac[:, None] * delta
