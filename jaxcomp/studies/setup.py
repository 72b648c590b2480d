"""What every study is set up with: the studied robot, its MJX simulator, the report folder."""

import os
import tempfile
from pathlib import Path

from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import MjxSimulator, batch_mesh
from jaxcomp.robot import Robot, load_robot

#: The robot the studies simulate (a built-in model).
MODEL = "gen3_lite"


def simulator(devices: int | None, robot: Robot | None = None) -> MjxSimulator:
    """The studies' ``MjxSimulator`` of ``robot`` (default: ``MODEL``, freshly loaded) with its
    worlds sharded over the first ``devices`` devices (None: all). One per robot and device
    count, kept on the robot (``Robot.cached``): its compiled programs serve every study run
    on that robot."""
    robot = load_robot(MODEL) if robot is None else robot
    return robot.cached(
        ("study_simulator", devices), lambda: MjxSimulator(robot, mesh=batch_mesh(devices))
    )


def check_out_dir(out: Path) -> Path:
    """Create ``out`` if needed and check that files can be written in it (InputError)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"cannot write to --out {out}: {exc.strerror or exc}") from None
    return out
