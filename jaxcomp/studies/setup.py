"""What every study is set up with: the studied robot and its MJX simulator."""

from jaxcomp.hardware.mjx import MjxSimulator, batch_mesh
from jaxcomp.robot import Robot, load_robot

#: The robot the studies simulate (a built-in model).
MODEL = "gen3_lite"


def simulator(devices: int | None, robot: Robot | None = None) -> MjxSimulator:
    """The studies' ``MjxSimulator`` of ``robot`` (default: ``MODEL``, freshly loaded) with its
    worlds sharded over the first ``devices`` devices (None: all). One per robot and device
    count, kept on the robot (``Robot.cached``): its compiled programs serve every study run
    on that robot.

    Args:
        devices: how many devices the worlds are sharded over (None: all).
        robot: the robot (None: ``MODEL``).

    Returns:
        The ``MjxSimulator``.
    """
    robot = load_robot(MODEL) if robot is None else robot
    return robot.cached(
        ("study_simulator", devices), lambda: MjxSimulator(robot, mesh=batch_mesh(devices))
    )
