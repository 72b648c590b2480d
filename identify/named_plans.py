"""Calibration plans by name: "default" (the paper's, ``plan_design.default_plan``), "short"
(``short_plan``, for quick runs and CI), "random" or "random:K" (K seeded random plans,
``random_plans.random_plan``) or a plan JSON file. Angles in rad."""

import math
import re
from pathlib import Path

from jaxcomp.errors import InputError
from jaxcomp.identify.plan import CalibrationPlan, load_plan
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.identify.random_plans import plan_seed, random_plan
from jaxcomp.robot import Robot

#: Plan names of ``--plan`` (else a plan JSON file); "random:K" names K random plans.
PLANS = ("default", "short", "random", "random:K")


def short_plan(
    robot: Robot, speed: float = math.radians(55), move_speed: float = math.radians(55)
) -> CalibrationPlan:
    """A quick plan for CPU runs and CI (~30 s instead of ~230 s for the Gen3 Lite): one sweep
    per joint over -40..+40 deg (the default plan's held-pose search), sweeps at ``speed`` and
    transfers at ``move_speed`` rad/s (55 deg/s: within the arms' 1 rad/s speed limit), 0.2 s
    settling. One speed per joint: the fit holds viscous friction at 0.

    Args:
        robot: The robot.
        speed: rad/s, of the sweeps.
        move_speed: rad/s, of the transfers.

    Returns:
        The plan.
    """
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


def random_count(plan: str) -> int | None:
    """How many plans a random name stands for.

    Args:
        plan: A ``--plan`` value.

    Returns:
        K of "random:K", 1 of "random"; None for any other name.

    Raises:
        InputError: "random:" without a count K >= 1.
    """
    if plan == "random":
        return 1
    if not plan.startswith("random:"):
        return None
    match = re.fullmatch(r"random:([0-9]+)", plan)
    if match is None or int(match[1]) < 1:
        raise InputError(f"--plan random:K needs an integer K >= 1, got {plan!r}")
    return int(match[1])


def plan_count(plan: str) -> int:
    """How many plans ``plan`` names.

    Args:
        plan: A ``--plan`` value.

    Returns:
        K for "random:K", else 1.

    Raises:
        InputError: "random:" without a count K >= 1.
    """
    return random_count(plan) or 1


def check_plan_name(plan: str) -> None:
    """Refuse a ``--plan`` value that names no plan.

    Args:
        plan: A ``--plan`` value.

    Raises:
        InputError: ``plan`` is neither one of ``PLANS`` nor an existing file.
    """
    if random_count(plan) is None and plan not in PLANS and not Path(plan).is_file():
        raise InputError(f"--plan must be one of {', '.join(PLANS)} or a plan JSON file: {plan}")


def named_plan(robot: Robot, plan: str, *, seed: int = 0, group: int = 0) -> CalibrationPlan:
    """The plan a ``--plan`` value names.

    Args:
        robot: The robot.
        plan: "default" (``default_plan``), "short" (``short_plan``), a plan JSON file, or
            "random" / "random:K".
        seed: Of the random plans.
        group: Which of the K random plans, 0 <= group < K
            (``random_plan(robot, plan_seed(seed, group))``).

    Returns:
        The plan (a file's validated against ``robot``).

    Raises:
        InputError: an unknown name, a group outside 0..K-1, or a bad plan file.
    """
    check_plan_name(plan)
    count = random_count(plan)
    if count is not None:
        if not 0 <= group < count:
            raise InputError(f"plan {plan!r} has no group {group} (0..{count - 1})")
        return random_plan(robot, plan_seed(seed, group))
    if plan == "default":
        return default_plan(robot)
    if plan == "short":
        return short_plan(robot)
    return load_plan(plan, robot)
