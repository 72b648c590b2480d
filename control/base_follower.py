"""The base follower of paper Eq. (20): the mobile base keeps the end effector near p_d.

In the horizontal plane of the base frame (x forward, y left; the arm's base frame is the
Dingo-O's translated by the mount offset, axes parallel, so p - p_d is the same in both):

    v_b = K_b (p - p_d)[x, y]   zero when |p - p_d|_xy < deadband, norm cut to max_speed
    w_z = yaw_gain q_j          zero when |q_j| < yaw_deadband, cut to +-max_yaw_rate

with p the end-effector position, p_d the desired one (m), q_j the yaw joint's angle (rad,
joint 0: positive turns the arm counter-clockwise, so the base turns after it). The twist
(vx m/s, vy m/s, wz rad/s) is then cut to the base's ``TwistLimits`` per axis; the base's own
limiter applies the acceleration limits. Plain float maths: about a microsecond per call.
"""

from __future__ import annotations

import math

import numpy as np

from jaxcomp.control.gains import BaseGains
from jaxcomp.hardware.mecanum import TwistLimits


def _cut(x: float, limit: float) -> float:
    return limit if x > limit else (-limit if x < -limit else x)


def follow_twist(
    ee_pos,
    desired_pos,
    q,
    gains: BaseGains,
    limits: TwistLimits,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Body twist of Eq. (20) plus the yaw term.

    Args:
        ee_pos: The end effector's position p, (3,) m, base frame (z is ignored).
        desired_pos: p_d, (3,) m, base frame (z is ignored).
        q: The arm's joint positions, (n,) rad.
        gains: The follower's gains.
        limits: The base's twist limits, per axis.
        out: (3,) array to write into (no allocation), or None.

    Returns:
        (3,) vx m/s, vy m/s, wz rad/s, base frame (``out`` when given).
    """
    ex = float(ee_pos[0]) - float(desired_pos[0])
    ey = float(ee_pos[1]) - float(desired_pos[1])
    dist = math.hypot(ex, ey)
    if dist < gains.deadband or dist == 0.0:
        vx = vy = 0.0
    else:
        k = gains.gain
        if k * dist > gains.max_speed:
            k = gains.max_speed / dist
        vx, vy = k * ex, k * ey
    angle = float(q[gains.yaw_joint])
    wz = (
        0.0 if abs(angle) < gains.yaw_deadband else _cut(gains.yaw_gain * angle, gains.max_yaw_rate)
    )
    lim = limits.velocity
    if out is None:
        out = np.empty(3)
    out[0], out[1], out[2] = _cut(vx, lim[0]), _cut(vy, lim[1]), _cut(wz, lim[2])
    return out


class BaseFollower:
    """``follow_twist`` with fixed gains and limits, writing into one reused buffer.

    ``twist(ee_pos, desired_pos, q)`` returns the same (3,) array every call (copy it to keep
    it); ``limits`` default: Clearpath's Dingo-O figures (``TwistLimits()``).
    """

    def __init__(self, gains: BaseGains | None = None, limits: TwistLimits | None = None):
        self.gains = BaseGains() if gains is None else gains
        self.limits = TwistLimits() if limits is None else limits
        self._out = np.zeros(3)

    def twist(self, ee_pos, desired_pos, q) -> np.ndarray:
        """The base's twist (``follow_twist``).

        Args:
            ee_pos: (3,) m, base frame.
            desired_pos: (3,) m, base frame.
            q: The arm's joint positions, (n,) rad.

        Returns:
            (3,) vx m/s, vy m/s, wz rad/s, base frame; the same array every call.
        """
        return follow_twist(ee_pos, desired_pos, q, self.gains, self.limits, self._out)
