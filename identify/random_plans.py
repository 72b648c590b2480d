"""Random calibration plans: held poses, spans, speeds and swept joints drawn from a seed.

They validate the joint fit on plans it was not tuned on. ``random_plan(robot, seed)`` sweeps
a random subset of at least half the current-controlled joints, each from ``holds`` (2) held
poses, in random order. Each sweep holds the other joints at a pose drawn uniformly within the
middle ``hold_fraction`` (80 %) of their ranges and moves its joint over a random span
(``spans``: 90-200 deg, or the joint's whole range if shorter) inside its limits less a margin
(``plan_design.inner_limits``), at a speed U(10, 40) deg/s. Continuous joints count as limited
to +-pi. A draw the plan's validation refuses, or (``check``) whose sweep or transfer the model
refuses (``plan_checks.plan_issues``: gravity beyond ``effort_fraction`` of an effort limit, the
floor, self-contact), is drawn again, up to ``attempts`` times; then the whole plan is drawn
again (``RESTARTS`` times in all).

``plan_seed(seed, k)`` derives the seed of the k-th of several plans from one seed. Units:
rad, rad/s, s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.identify.plan import RAMP, CalibrationPlan, Sweep, arm_pose
from jaxcomp.identify.plan_checks import plan_issues
from jaxcomp.identify.plan_design import inner_limits
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import arm_joint_indices

#: Sweep speeds, rad/s: U(10, 40) deg/s.
SPEEDS = (math.radians(10.0), math.radians(40.0))
#: Sweep spans, rad: U(90, 200) deg (cut at the joint's range).
SPANS = (math.radians(90.0), math.radians(200.0))
#: Held joints stay within this middle fraction of their ranges.
HOLD_FRACTION = 0.8
#: The short plan's transfers (rad/s) and settling (s).
MOVE_SPEED = math.radians(55.0)
SETTLE = 0.2
#: Sweeps of each chosen joint, each from its own held pose (one hold leaves COM directions
#: unseen that random poses load).
HOLDS = 2
#: Draws of a sweep before giving up.
ATTEMPTS = 100
#: Draws of the whole plan before giving up.
RESTARTS = 5
#: Seed stream of the plans: SeedSequence([seed, PLAN_STREAM, k]) (truths 1, noise 2).
PLAN_STREAM = 3


def plan_seed(seed: int, k: int) -> int:
    """The seed of one of several random plans drawn from one seed (independent streams).

    Args:
        seed: the seed of the plans.
        k: which plan (>= 0).

    Returns:
        The k-th plan's seed, a 64-bit int.
    """
    state = np.random.SeedSequence([int(seed), PLAN_STREAM, int(k)]).generate_state(2, np.uint32)
    return int(state[0]) << 32 | int(state[1])


def plan_limits(robot: Robot) -> np.ndarray:
    """The limits random plans sweep within.

    Args:
        robot: the robot.

    Returns:
        (n, 2) rad, the current-controlled joints' limits, continuous ones clamped to +-pi.
    """
    return np.clip(robot.joint_limits[arm_joint_indices(robot)], -math.pi, math.pi)


def _range(values: Sequence[float], name: str) -> tuple[float, float]:
    lo, hi = (float(v) for v in values)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise InputError(f"{name} must be (lo, hi) with 0 < lo <= hi, got ({lo}, {hi})")
    return lo, hi


def random_plan(
    robot: Robot | str,
    seed: int,
    *,
    speeds: Sequence[float] = SPEEDS,
    spans: Sequence[float] = SPANS,
    hold_fraction: float = HOLD_FRACTION,
    move_speed: float = MOVE_SPEED,
    settle: float = SETTLE,
    ramp: float = RAMP,
    check: bool = True,
    effort_fraction: float = 0.6,
    floor: float = 0.05,
    start: str | Sequence[float] | None = None,
    attempts: int = ATTEMPTS,
    holds: int = HOLDS,
) -> CalibrationPlan:
    """A random calibration plan for ``robot`` from ``seed`` (see the module docstring).

    Args:
        robot: the robot (name, path or ``Robot``).
        seed: the seed; the same seed gives the same plan.
        speeds: (lo, hi) rad/s, sweep speeds U(lo, hi).
        spans: (lo, hi) rad, swept spans U(lo, hi), each cut at the joint's range.
        hold_fraction: held joints lie within this middle fraction of their ranges.
        move_speed: rad/s, transfers; settle, ramp: s (as ``CalibrationPlan``).
        check: also refuse sweeps and transfers the model finds wrong (``plan_issues`` with
            ``effort_fraction`` and ``floor`` m), the transfers from ``start`` (a pose name or
            (n,) rad; default ``Robot.idle_pose``, where recording starts).
        attempts: draws of each sweep before the plan is drawn again.
        holds: sweeps of each chosen joint, each from its own held pose (>= 1).

    Returns:
        The validated plan.

    Raises:
        InputError: an argument is out of range, or no draw passes (naming the last problem).
    """
    robot = load_robot(robot)
    speeds, spans = _range(speeds, "speeds"), _range(spans, "spans")
    if not 0 < hold_fraction <= 1:
        raise InputError(f"hold_fraction must be in (0, 1], got {hold_fraction}")
    if int(attempts) < 1:
        raise InputError(f"attempts must be >= 1, got {attempts}")
    if int(holds) < 1:
        raise InputError(f"holds must be >= 1, got {holds}")
    limits = plan_limits(robot)
    inner = inner_limits(limits)
    mid, half = limits.mean(axis=1), hold_fraction * (limits[:, 1] - limits[:, 0]) / 2
    hold_lo = np.maximum(mid - half, inner[:, 0])
    hold_hi = np.minimum(mid + half, inner[:, 1])
    n = len(limits)
    rng = np.random.default_rng(int(seed))
    names = [robot.joint_names[a] for a in arm_joint_indices(robot)]
    home = arm_pose(robot, start)

    def draw_sweep(j: int, prev: np.ndarray) -> Sweep | str:
        """A sweep of joint j from the pose ``prev``, or the last draw's problem."""
        lo, hi = inner[j]
        if not lo < hi:
            return f"joint {j} ({names[j]}): its limits (less the margin) leave no range to sweep"
        problem = ""
        for _ in range(int(attempts)):
            hold = rng.uniform(hold_lo, hold_hi)
            span = rng.uniform(*np.minimum(spans, hi - lo))
            lower = rng.uniform(lo, hi - span)
            speed = rng.uniform(*speeds)
            try:
                sweep = Sweep(j, hold, lower, lower + span, speed)
                one = CalibrationPlan((sweep,), move_speed, settle, ramp).validate(robot)
            except InputError as exc:
                problem = str(exc)
                continue
            if not check:
                return sweep
            issues = plan_issues(robot, one, prev, effort_fraction=effort_fraction, floor=floor)
            if not issues:
                return sweep
            problem = issues[0]
        return f"no admissible sweep of joint {j} ({names[j]}) in {attempts} draws: {problem}"

    count = int(rng.integers(math.ceil(n / 2), n + 1))
    chosen = [int(j) for j in rng.permutation(n)[:count]]
    joints = [chosen[k % count] for k in rng.permutation(count * int(holds))]
    # a sweep may start where no transfer can leave (a load near a limit): then draw the
    # whole plan again
    for _ in range(RESTARTS):
        sweeps: list[Sweep] = []
        for j in joints:
            got = draw_sweep(j, sweeps[-1].start if sweeps else home)
            if isinstance(got, str):
                break
            sweeps.append(got)
        else:
            return CalibrationPlan(tuple(sweeps), move_speed, settle, ramp).validate(robot)
    raise InputError(f"random plan (seed {seed}): {got}")
