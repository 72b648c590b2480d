"""Calibration plans by name: "default" (the paper's, ``plan_design.default_plan``), "short"
(``short_plan``, for quick runs and CI) or a plan JSON file. Angles in rad."""

import math
from pathlib import Path

from jaxcomp.errors import InputError
from jaxcomp.identify.plan import CalibrationPlan, load_plan
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.robot import Robot

#: Plan names of ``--plan`` (else a plan JSON file).
PLANS = ("default", "short")


def short_plan(
    robot: Robot, speed: float = math.radians(55), move_speed: float = math.radians(55)
) -> CalibrationPlan:
    """A quick plan for CPU runs and CI (~30 s instead of ~230 s for the Gen3 Lite): one sweep
    per joint over -40..+40 deg (the default plan's held-pose search), sweeps at ``speed`` and
    transfers at ``move_speed`` rad/s (55 deg/s: within the arms' 1 rad/s speed limit), 0.2 s
    settling. One speed per joint: the fit holds viscous friction at 0."""
    return default_plan(
        robot,
        sweeps_per_joint=1,
        lower=math.radians(-40),
        upper=math.radians(40),
        speed=speed,
        slow_speed=None,
        move_speed=move_speed,
        settle=0.2,
        min_span=math.radians(60),
    )


def check_plan_name(plan: str) -> None:
    """InputError unless ``plan`` is one of ``PLANS`` or an existing file."""
    if plan not in PLANS and not Path(plan).is_file():
        raise InputError(f"--plan must be one of {', '.join(PLANS)} or a plan JSON file: {plan}")


def named_plan(robot: Robot, plan: str) -> CalibrationPlan:
    """``plan``: "default" (``default_plan``), "short" (``short_plan``) or a plan JSON file."""
    check_plan_name(plan)
    if plan == "default":
        return default_plan(robot)
    if plan == "short":
        return short_plan(robot)
    return load_plan(plan, robot)
