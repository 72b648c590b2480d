"""A calibration plan as the 1 kHz signals the simulated worlds follow and record: whole
(``plan_signal``) or cut into its sweeps, to be simulated side by side (``plan_segments``).

Plans by name: "default" (the paper's, ``identify.plan_design.default_plan``), "short"
(``short_plan``) or a plan JSON file. Angles in rad, one sample per 1 ms step.
"""

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import Move, reference_trajectory
from jaxcomp.identify.plan import CalibrationPlan, arm_pose, load_plan
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.identify.recorder import MOVE_DIRECTION
from jaxcomp.robot import Robot

#: Plan names of ``--plan`` (else a plan JSON file).
PLANS = ("default", "short")


def short_plan(robot: Robot) -> CalibrationPlan:
    """A quick plan for CPU runs and CI (~26 s instead of ~230 s for the Gen3 Lite): one sweep
    per joint over -40..+40 deg at 60 deg/s (the default plan's held-pose search), transfers
    at 90 deg/s, 0.2 s settling. One speed per joint: the fit holds viscous friction at 0."""
    return default_plan(
        robot,
        sweeps_per_joint=1,
        lower=math.radians(-40),
        upper=math.radians(40),
        speed=math.radians(60),
        slow_speed=None,
        move_speed=math.radians(90),
        settle=0.2,
        min_span=math.radians(60),
    )


def check_study_plan(plan: str) -> None:
    """InputError unless ``plan`` is one of ``PLANS`` or an existing file."""
    if plan not in PLANS and not Path(plan).is_file():
        raise InputError(f"--plan must be one of {', '.join(PLANS)} or a plan JSON file: {plan}")


def load_study_plan(robot: Robot, plan: str) -> CalibrationPlan:
    """``plan``: "default" (the paper's, ``default_plan``), "short" or a plan JSON file."""
    if plan == "default":
        return default_plan(robot)
    if plan == "short":
        return short_plan(robot)
    return load_plan(plan, robot)


def start_pose(robot: Robot) -> np.ndarray:
    """(n,) rad: where every world starts (the "home" pose), as ``identify.plan.arm_pose``."""
    return arm_pose(robot)


class PlanSignal(NamedTuple):
    """A calibration plan as the 1 kHz signals an MJX run follows and records (T steps).

    q_ref (T, n) rad: what ``Arm.move_to`` sends for the plan's moves; joint (T,): swept joint
    (-1 outside sweeps); direction (T,): +1 / -1 (0 outside sweeps), as ``identify.recorder``
    labels them; sweep (T,): index of the plan sweep (its transfer included) of each step.
    """

    q_ref: np.ndarray
    joint: np.ndarray
    direction: np.ndarray
    sweep: np.ndarray


def plan_signal(plan: CalibrationPlan, start: np.ndarray) -> PlanSignal:
    """The ``PlanSignal`` of ``plan`` from the pose ``start`` (n,) rad."""
    pos = np.asarray(start, float)
    parts, labels = [], []
    for i, kind, target, speed, accel, settle in plan.moves():
        ref = reference_trajectory([Move(target, speed, accel, settle)], pos)
        if len(ref):
            pos = ref[-1].copy()
            d = MOVE_DIRECTION[kind]
            parts.append(ref)
            labels.append(np.tile([plan.sweeps[i].joint if d else -1, d, i], (len(ref), 1)))
    lab = np.concatenate(labels)
    return PlanSignal(np.concatenate(parts), lab[:, 0], lab[:, 1], lab[:, 2])


class Segments(NamedTuple):
    """A ``PlanSignal`` cut into K segments, one a plan sweep (its passes up and down, then the
    transfer to the next sweep's start and the settling there; segment 0 also holds the
    transfer from the plan's start), to be simulated side by side as separate worlds
    (``plan_recording.simulate(parallel=True)``).

    Segment k starts at rest at ``start[k]`` (n,) rad (where segment k - 1 has settled; the
    plan's start pose for k = 0) at plan step ``first[k]``, a multiple of the recording
    decimation at or up to ``every`` - 1 steps before its sweep's first step ``begin[k]``,
    and ends at step ``end[k]``. ``q_ref`` (L, K, n) rad: the references side by side, each
    held at its last pose up to the longest length L; ``signals``: each segment's
    ``PlanSignal`` (steps first[k] .. end[k]; the steps before begin[k], the end of segment
    k - 1, are labelled outside sweeps).
    """

    q_ref: np.ndarray
    start: np.ndarray
    first: np.ndarray
    begin: np.ndarray
    end: np.ndarray
    signals: list[PlanSignal]


def plan_segments(signal: PlanSignal, start: np.ndarray, every: int) -> Segments:
    """``Segments`` of ``signal`` (from the pose ``start`` (n,) rad), aligned to ``every``."""
    d = signal.direction
    cuts = (np.flatnonzero((d[1:] != 0) & (d[:-1] == 0)) + 1)[1:]  # the sweeps' first steps
    begin = np.r_[0, cuts]
    end = np.r_[cuts, len(signal.sweep)]
    first = begin - begin % every
    for f, a in zip(first[1:], begin[1:], strict=True):
        if np.ptp(signal.q_ref[f - 1 : a], axis=0).max() > 0:
            raise InputError("a plan sweep does not start at rest: sweeps cannot run in parallel")
    length = int((end - first).max())
    q_ref = np.empty((length, len(begin), signal.q_ref.shape[1]))
    starts, signals = [], []
    for k, (a, b, f) in enumerate(zip(begin, end, first, strict=True)):
        ref = signal.q_ref[f:b]
        q_ref[:, k] = np.concatenate([ref, np.repeat(ref[-1:], length - len(ref), axis=0)])
        starts.append(np.asarray(start, float) if f == 0 else signal.q_ref[f - 1])
        outside = np.arange(f, b) < a  # the tail of segment k - 1
        signals.append(
            PlanSignal(
                ref,
                np.where(outside, -1, signal.joint[f:b]),
                np.where(outside, 0, signal.direction[f:b]),
                np.full(b - f, k),
            )
        )
    return Segments(q_ref, np.array(starts), first, begin, end, signals)
