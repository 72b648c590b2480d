"""The simulated arm: the ``Arm`` interface on a ``Simulator``, in lock step.

Each cycle sets the simulator's targets in the joints' modes and advances it one 1 ms step;
mode switches, fault clearing and the named poses are the simulator's (``hardware.simulator``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.hardware.interface import Arm, ArmLimits, ArmState, ControlMode

if TYPE_CHECKING:
    from jaxcomp.hardware.simulator import Simulator


class SimArm(Arm):
    """The ``Arm`` interface on a ``Simulator`` (lock step: each cycle is one 1 ms step).

    Args:
        sim: the simulator (``Simulator.arm`` makes its one ``SimArm``).
        limits: the arm's limits (default: the robot's, ``ArmLimits.from_robot``).
    """

    #: The current reported with a state is the one the servo computed at the state before,
    #: one 1 ms step earlier, and drove through that step.
    current_lag = CONTROL_PERIOD

    def __init__(self, sim: Simulator, limits: ArmLimits | None = None):
        robot = sim.robot
        poses = {k: v[sim.arm_qposadr] for k, v in robot.named_poses.items()}
        limits = limits or ArmLimits.from_robot(robot, sim.arm_joints)
        super().__init__(sim.arm_joint_names, limits, poses)
        self.sim = sim
        self._start(sim.arm_state())
        sim.set_modes(dict(enumerate(self.modes)))

    def _exchange(self, modes, position, velocity, current) -> ArmState:
        self.sim.set_targets(position, velocity, current)
        self.sim.step()
        return self.sim.arm_state()

    def _switch(self, changes: dict[int, ControlMode]) -> None:
        self.sim.set_modes(changes)

    def _clear_faults(self) -> None:
        self.sim.clear_faults()

    def _shutdown(self) -> None:
        pass
