"""The Dingo-O omnidirectional drive: mecanum kinematics and Clearpath's twist limits.

Shared by the simulated base and the real Dingo-O adapter. Frames: the twist (vx, vy, wz) is
in the base's own frame (x forward, y left, z up), m/s and rad/s. Wheels are ordered front-left,
front-right, rear-left, rear-right; wheel speeds in rad/s, positive = rolling forward.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError

if TYPE_CHECKING:
    from jaxcomp.robot import Robot

WHEEL_RADIUS = 0.05  # m
LX_LY = (0.285, 0.21)  # m: half wheelbase, half track (lx + ly = 0.495 m)
TWIST_LIMITS = (1.3, 1.3, 4.0)  # m/s, m/s, rad/s
TWIST_ACCEL_LIMITS = (0.6, 0.6, 2.0)  # m/s^2, m/s^2, rad/s^2
CMD_TIMEOUT = 0.25  # s without a command before the base stops


def _numeric(robot: Robot | None, name: str, default) -> np.ndarray:
    value = robot.custom_numeric(name) if robot is not None else None
    return np.asarray(default if value is None else value, dtype=float)


@dataclass(frozen=True)
class MecanumGeometry:
    """The drive's geometry.

    Attributes:
        wheel_radius: m. lx: m, half the wheelbase. ly: m, half the track.
    """

    wheel_radius: float = WHEEL_RADIUS
    lx: float = LX_LY[0]
    ly: float = LX_LY[1]

    @classmethod
    def from_robot(cls, robot: Robot | None) -> MecanumGeometry:
        """From the model's ``jaxcomp_wheel_radius`` / ``jaxcomp_wheel_lx_ly``, else defaults.

        Args:
            robot: the model, or None for the defaults.

        Returns:
            The ``MecanumGeometry``.
        """
        lx, ly = _numeric(robot, "jaxcomp_wheel_lx_ly", LX_LY)
        return cls(float(_numeric(robot, "jaxcomp_wheel_radius", [WHEEL_RADIUS])[0]), lx, ly)

    @property
    def _matrix(self) -> np.ndarray:
        k = self.lx + self.ly
        return np.array([[1, -1, -k], [1, 1, k], [1, 1, -k], [1, -1, k]]) / self.wheel_radius

    def wheel_speeds(self, twist) -> np.ndarray:
        """The wheel speeds that drive a body twist.

        Args:
            twist: (3,) body twist (vx m/s, vy m/s, wz rad/s) in the base frame.

        Returns:
            (4,) wheel speeds, rad/s (FL, FR, RL, RR).
        """
        return self._matrix @ np.asarray(twist, dtype=float)

    def twist(self, wheel_speeds) -> np.ndarray:
        """The body twist of the wheel speeds (least squares).

        Args:
            wheel_speeds: (4,) rad/s (FL, FR, RL, RR).

        Returns:
            (3,) body twist (vx m/s, vy m/s, wz rad/s) in the base frame.
        """
        return np.linalg.pinv(self._matrix) @ np.asarray(wheel_speeds, dtype=float)


@dataclass(frozen=True)
class TwistLimits:
    """The base's twist limits.

    Attributes:
        velocity: per-axis speed limits (vx m/s, vy m/s, wz rad/s).
        accel: per-axis acceleration limits (m/s^2, m/s^2, rad/s^2).
        timeout: s without a command before the base stops.
    """

    velocity: tuple[float, float, float] = TWIST_LIMITS
    accel: tuple[float, float, float] = TWIST_ACCEL_LIMITS
    timeout: float = CMD_TIMEOUT

    @classmethod
    def from_robot(cls, robot: Robot | None) -> TwistLimits:
        """From the model's ``jaxcomp_twist_limits``, ``jaxcomp_twist_accel_limits`` and
        ``jaxcomp_cmd_timeout``, else Clearpath's figures.

        Args:
            robot: the model, or None for Clearpath's figures.

        Returns:
            The ``TwistLimits``.
        """
        return cls(
            tuple(_numeric(robot, "jaxcomp_twist_limits", TWIST_LIMITS).tolist()),
            tuple(_numeric(robot, "jaxcomp_twist_accel_limits", TWIST_ACCEL_LIMITS).tolist()),
            float(_numeric(robot, "jaxcomp_cmd_timeout", [CMD_TIMEOUT])[0]),
        )

    def check(self, twist) -> np.ndarray:
        """Check a commanded twist.

        Args:
            twist: body twist (vx m/s, vy m/s, wz rad/s) in the base frame.

        Returns:
            The twist as a (3,) float array.

        Raises:
            InputError: not shape (3,), NaN or inf, or beyond ``velocity``.
        """
        arr = checks.array(twist, "twist (m/s, m/s, rad/s)", n=3, labels=("vx", "vy", "wz"))
        over = np.abs(arr) > np.asarray(self.velocity) + 1e-9
        if over.any():
            names = [n for n, o in zip(("vx", "vy", "wz"), over, strict=True) if o]
            raise InputError(
                f"twist {arr} exceeds the base's velocity limits {self.velocity} on "
                f"{', '.join(names)}"
            )
        return arr


class TwistLimiter:
    """Turns commanded twists into the twist the base may follow.

    The output ramps towards the latest command at the acceleration limits and ramps to zero
    when no command arrived for ``limits.timeout`` s. Times are in s on any monotonic clock.
    """

    def __init__(self, limits: TwistLimits):
        self.limits = limits
        self._accel = np.asarray(limits.accel, dtype=float)
        self._cmd = np.zeros(3)
        self._cmd_time = -np.inf
        self._t: float | None = None
        self.output = np.zeros(3)

    def command(self, twist: np.ndarray, t: float) -> None:
        """Record a (validated) twist commanded at time t.

        Args:
            twist: (3,) body twist (vx m/s, vy m/s, wz rad/s) in the base frame.
            t: s, the command's time.
        """
        self._cmd = np.array(twist, dtype=float)
        self._cmd_time = t

    def stop(self) -> None:
        """Drop the command: the output ramps to zero."""
        self._cmd = np.zeros(3)

    def timed_out(self, t: float) -> bool:
        """Whether the last command is older than ``limits.timeout``.

        Args:
            t: s, now.

        Returns:
            True when no command came in the ``limits.timeout`` s before ``t`` (or none ever).
        """
        return t - self._cmd_time > self.limits.timeout

    def update(self, t: float) -> np.ndarray:
        """Step the output towards the command (zero once timed out) at the acceleration limits.

        Args:
            t: s, now; the step covers the time since the last update (none at the first).

        Returns:
            (3,) the limited twist (vx m/s, vy m/s, wz rad/s) the base may follow at ``t``.
        """
        target = np.zeros(3) if self.timed_out(t) else self._cmd
        dt = 0.0 if self._t is None else max(t - self._t, 0.0)
        self._t = t
        step = np.clip(target - self.output, -self._accel * dt, self._accel * dt)
        self.output = self.output + step
        return self.output
