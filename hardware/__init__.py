"""jaxcomp.hardware: one robot interface, the simulated robot, and the real-robot adapters.

Identification and control drive an ``Arm`` (1 kHz ``cycle``, per-joint POSITION / VELOCITY /
CURRENT modes, ``move_to``) and a ``Base`` (body twist, odometry) and never know whether a
``Simulator`` (MuJoCo, the default backend), a ``KortexArm`` (Kinova Gen3 Lite through
kortex_api, or its ``KortexEmulator``) or a ``DingoBase`` (ROS 2) is behind them.
``jaxcomp.hardware.mjx`` (imported on its own: it loads MJX) runs thousands of simulated arms at
once, in POSITION mode through a plan or in CURRENT mode driven by a ``Policy``. This package
knows nothing of identification or control laws.
"""

from jaxcomp.hardware.dingo import DingoBase
from jaxcomp.hardware.interaction import Push, Rope
from jaxcomp.hardware.interface import (
    Arm,
    ArmCommand,
    ArmLimits,
    ArmState,
    Base,
    BaseState,
    ControlMode,
    HardwareFault,
)
from jaxcomp.hardware.kortex import KortexArm
from jaxcomp.hardware.kortex_emulator import KortexEmulator
from jaxcomp.hardware.mecanum import MecanumGeometry, TwistLimiter, TwistLimits
from jaxcomp.hardware.sim_arm import SimArm
from jaxcomp.hardware.sim_base import SimBase
from jaxcomp.hardware.simulator import Simulator
from jaxcomp.hardware.truth import PAPER_FRICTION, PAPER_RATIO, TrueRobot

__all__ = [
    "PAPER_FRICTION",
    "PAPER_RATIO",
    "Arm",
    "ArmCommand",
    "ArmLimits",
    "ArmState",
    "Base",
    "BaseState",
    "ControlMode",
    "DingoBase",
    "HardwareFault",
    "KortexArm",
    "KortexEmulator",
    "MecanumGeometry",
    "Push",
    "Rope",
    "SimArm",
    "SimBase",
    "Simulator",
    "TrueRobot",
    "TwistLimiter",
    "TwistLimits",
]
