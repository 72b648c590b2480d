"""The simulated Dingo-O base: the ``Base`` interface on a ``Simulator`` with base joints.

The base follows the commanded body twist through ``TwistLimiter`` (Clearpath's velocity and
acceleration limits, stop after 0.25 s without a command) and a stiff velocity servo on the
planar joints base_x, base_y (m, world) and base_yaw (rad). Odometry is exact: pose in the
world frame, twist in the base frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from jaxcomp.hardware.interface import Base, BaseState
from jaxcomp.hardware.mecanum import MecanumGeometry

if TYPE_CHECKING:
    from jaxcomp.hardware.simulator import Simulator


class SimBase(Base):
    """``Base`` on a ``Simulator``; time advances with the arm's cycles or ``advance``."""

    def __init__(self, sim: Simulator):
        super().__init__(sim.twist_limits)
        self.sim = sim
        self.geometry = MecanumGeometry.from_robot(sim.robot)

    def _send(self, twist: np.ndarray) -> None:
        self.sim.command_twist(twist)

    def stop(self) -> None:
        self.sim.stop_base()

    def odometry(self) -> BaseState:
        return self.sim.base_state()

    def wheel_speeds(self) -> np.ndarray:
        """(4,) wheel speeds rad/s (FL, FR, RL, RR) matching the current body twist."""
        return self.geometry.wheel_speeds(self.odometry().twist)

    def advance(self, seconds: float) -> BaseState:
        """Lock step: simulate ``seconds`` s (for a base without an arm being cycled).

        Args:
            seconds: s, rounded to whole physics steps.

        Returns:
            The odometry after them.
        """
        self.sim.step(int(round(seconds / self.sim.model.opt.timestep)))
        return self.odometry()
