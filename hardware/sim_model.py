"""The simulators' MuJoCo model of a robot: its reduced model with one drive per joint.

``simulation_spec`` is what the CPU ``Simulator`` and the MJX simulator (``mjx.model``)
compile: the robot's reduced model (``Robot.spec``) with a 1 ms implicitfast step, no
contacts, and the model's own actuators replaced by one drive per simulated joint (gain 1,
affine bias: the simulator makes it a position servo or a torque source).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.robot import Robot


def simulation_spec(robot: Robot, joints: Sequence[int]) -> mujoco.MjSpec:
    """The simulators' model of ``robot`` (its reduced model, ``Robot.spec``) before compiling:
    a 1 ms implicitfast step, no contacts, the model's own actuators removed and one actuator
    per joint index in ``joints``, named ``jaxcomp_drive_<joint>`` (gain 1, affine bias: a
    servo or a torque source, set by the simulator).

    Args:
        robot: the nominal model.
        joints: indices (into ``robot.joint_names``) of the joints that get a drive.

    Returns:
        The MuJoCo spec, not compiled.
    """
    spec = robot.spec()
    for act in list(spec.actuators):  # the model's own actuators give way to the drives
        spec.delete(act)
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    spec.option.timestep = CONTROL_PERIOD
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    names = robot.joint_names
    for j in joints:
        act = spec.add_actuator(
            name=f"jaxcomp_drive_{names[j]}",
            target=names[j],
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            gaintype=mujoco.mjtGain.mjGAIN_FIXED,
            biastype=mujoco.mjtBias.mjBIAS_AFFINE,
        )
        act.gainprm[0] = 1.0
    return spec
