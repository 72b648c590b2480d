"""Physical plausibility of recordings and params: what no real current-controlled arm gives.

Each check is one bound, stated here and in docs/plausibility.md. A value outside it is refused
with one error that names the joint or link, the value and the bound (``InputError``):

- ratio (A/(N m)): within ``RATIO_RANGE``; and where the model states its joints' scale (a
  ``jaxcomp_nominal_ratio``, or a ``jaxcomp_current_limit`` with an effort limit: ratio ~
  current limit / effort limit), within ``SCALE_FACTOR`` of that scale;
- friction loss (A): at most the joint's current limit (``robot_params.current_limits``): a
  joint whose friction takes all of its current cannot move;
- COM offset (m, link frame): at most ``COM_SIZE`` radii of gyration of the link
  (``params.gyration_radii``), and at least ``COM_MIN`` is always allowed;
- recorded current (A): at most ``CURRENT_FACTOR`` times the joint's current limit where the
  model states the scale (a current in mA breaks it), and a swept joint's current not zero
  (RMS over its own sweeps at least ``ZERO_CURRENT`` of its current limit);
- coverage: every current-controlled joint swept in both directions (``MIN_SAMPLES`` samples
  each) in at least one of the recordings fitted together, so that its friction can be told
  from its gravity torque.

Params on their way to the controller are checked here once (``checked_arm_params``: renamed
for the arm-alone model when they were identified on the mobile manipulator, then
``RobotParams.check`` and the bounds above); the ``CheckedParams`` it returns say so, and the
controller takes them without checking them again.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.params import InertialParams, gyration_radii
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names, current_limits

#: A/(N m): the physical range of a joint's current/torque ratio, from large industrial
#: joints (~0.01) to small hobby servos (~10).
RATIO_RANGE = (1e-3, 1e2)
#: A ratio within this factor of the scale the model states for the joint.
SCALE_FACTOR = 10.0
#: A COM offset of at most this many radii of gyration of its link ...
COM_SIZE = 2.0
#: ... and at least this, m, on any link.
COM_MIN = 0.02
#: Recorded currents of at most this many times the joint's current limit.
CURRENT_FACTOR = 2.0
#: A swept joint's RMS current over its own sweeps, as a fraction of its current limit, below
#: which it counts as not recorded.
ZERO_CURRENT = 1e-3
#: Samples a joint needs in each direction of its own sweeps.
MIN_SAMPLES = 20


def stated_scale(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Each current-controlled joint's ratio scale and whether the model states it: its
    ``jaxcomp_nominal_ratio``, else its ``jaxcomp_current_limit`` over its effort limit (both
    finite), else unstated (scale 1 A/(N m)).

    Args:
        robot: the model.

    Returns:
        (scale (n,) A/(N m), stated (n,) bool).
    """
    limits = current_limits(robot)
    effort = robot.effort_limits[arm_joint_indices(robot)]
    nominal = robot.joint_numeric("jaxcomp_nominal_ratio")
    declared = robot.joint_numeric("jaxcomp_current_limit")
    has_ratio = np.zeros(len(limits), bool) if nominal is None else np.isfinite(nominal)
    has_limit = np.zeros(len(limits), bool) if declared is None else np.isfinite(declared)
    by_limit = has_limit & np.isfinite(effort) & (effort > 0)
    scale = np.where(has_ratio, RobotParams.nominal(robot).ratio, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(~has_ratio & by_limit, limits / effort, scale)
    return scale, has_ratio | by_limit


def params_problems(params: RobotParams, robot: Robot) -> list[str]:
    """What in ``params`` is physically implausible (the module's bounds).

    Args:
        params: params already ``check``-ed against ``robot`` (ratio A/(N m), friction A, COM
            offsets m, link frame).
        robot: the model they are for.

    Returns:
        One sentence per problem; empty when nothing is.
    """
    names = arm_joint_names(robot)
    out = []
    lo, hi = RATIO_RANGE
    scale, stated = stated_scale(robot)
    limits = current_limits(robot)
    for j, (r, f) in enumerate(zip(params.ratio, params.friction, strict=True)):
        if not lo <= r <= hi:
            out.append(
                f"the ratio of {names[j]} is {r:.3g} A/(N m), outside the physical range "
                f"{lo:g}-{hi:g} A/(N m)"
            )
        elif stated[j] and not scale[j] / SCALE_FACTOR <= r <= scale[j] * SCALE_FACTOR:
            out.append(
                f"the ratio of {names[j]} is {r:.3g} A/(N m), more than {SCALE_FACTOR:g} times "
                f"off the {scale[j]:.3g} A/(N m) that {robot.name} states"
            )
        if f > limits[j]:
            out.append(
                f"the friction loss of {names[j]} is {f:.3g} A, more than its current limit "
                f"{limits[j]:.3g} A"
            )
    size = np.maximum(COM_SIZE * gyration_radii(robot.nominal_params()), COM_MIN)
    for link, offset in params.com_offset.items():
        i = robot.link_index(link)
        length = float(np.linalg.norm(offset))
        if length > size[i]:
            out.append(
                f"the COM offset of {link} is {length:.3g} m, more than {size[i]:.3g} m "
                f"({COM_SIZE:g} radii of gyration of the link, at least {COM_MIN:g} m)"
            )
    return out


def check_params(params: RobotParams, robot: Robot, source: str = "the params") -> RobotParams:
    """``params`` checked against ``robot`` (``RobotParams.check``) and for plausibility
    (``params_problems``).

    Args:
        params: the params.
        robot: the model they are for.
        source: what they are, for the error ("the params in FILE").

    Returns:
        ``params``.

    Raises:
        InputError: one, naming every problem and ``source``.
    """
    _refuse(params_problems(params.check(robot), robot), robot, source)
    return params


class CheckedParams(NamedTuple):
    """Params that passed ``RobotParams.check`` and the plausibility bounds for an arm-alone
    model (made by ``checked_arm_params``; the controller takes them as they are).

    Attributes:
        params: the params, named for the arm-alone model (``params.model``): ratio (n,)
            A/(N m), friction (n,) A, COM offsets m (link frame).
        inertial: that model's inertials with the COM offsets applied
            (``RobotParams.inertial_params``): mass (nb,) kg, com (nb, 3) m, inertia
            (nb, 3, 3) kg m^2, link frames.
    """

    params: RobotParams
    inertial: InertialParams


def checked_arm_params(
    params: RobotParams, arm: Robot, robot: Robot | None = None, file: str | None = None
) -> CheckedParams:
    """``params`` for the arm-alone model ``arm``, checked once on their way to the controller.

    Params that name another model (e.g. the mobile manipulator they were identified on) are
    renamed for ``arm`` (same joints and links: checked), then checked against it
    (``RobotParams.check``) and for plausibility (``params_problems``).

    Args:
        params: identified (or nominal) params.
        arm: the arm-alone model the controller works in (``control.mount.arm_model``).
        robot: the whole model that carries the arm (the mobile manipulator, or ``arm``
            itself); when given, params that name neither it nor ``arm`` (by name or by file,
            as a fit names its recording's model) are refused.
        file: the params file, named in the errors (None: "the params").

    Returns:
        The ``CheckedParams``.

    Raises:
        InputError: params for another model, not fitting ``arm``, or implausible for it.
    """
    if robot is not None:
        names = {r.name for r in (robot, arm)} | {r.reference for r in (robot, arm)}
        if params.model not in names:
            where = f"{file}: " if file is not None else ""
            raise InputError(
                f"{where}the params are for model {params.model!r}, the robot is {robot.name!r}"
            )
    if params.model != arm.name:
        params = replace(params, model=arm.name)
    inertial = params.inertial_params(arm)  # RobotParams.check, then the COM offsets applied
    source = f"the params in {file}" if file is not None else "the params"
    _refuse(params_problems(params, arm), arm, source)
    return CheckedParams(params, inertial)


def _refuse(problems: list[str], robot: Robot, source: str) -> None:
    """One InputError naming every problem of the params ``source`` for ``robot``, if any."""
    if problems:
        raise InputError(
            f"{source} are implausible for {robot.name}: {'; '.join(problems)} (a wrong robot, "
            "a current in mA, or a failed calibration?)"
        )


def recording_problems(recordings: Sequence[Recording], robot: Robot | None = None) -> list[str]:
    """What makes ``recordings`` implausible or unusable (currents, coverage).

    Args:
        recordings: recordings of one robot, to be fitted together (current A).
        robot: their robot (``Recording.robot()``) when the caller holds it already.

    Returns:
        One sentence per problem; empty when nothing is.
    """
    out = []
    robot = recordings[0].robot() if robot is None else robot
    names = arm_joint_names(robot)
    n = len(names)
    limits = current_limits(robot)
    _, stated = stated_scale(robot)
    counts = np.zeros((n, 2), int)
    for k, rec in enumerate(recordings):
        label = f"recording {k + 1}: " if len(recordings) > 1 else ""
        current = rec.current
        # column by column: numpy reduces an (N, n) array over its long axis 8x slower
        peak = np.array([max(c.max(), -c.min()) if c.size else 0.0 for c in current.T], dtype=float)
        over = np.flatnonzero(stated & (peak > CURRENT_FACTOR * limits))
        if over.size:
            worst = ", ".join(
                f"{names[j]} {peak[j]:.4g} A ({peak[j] / limits[j]:.3g}x)" for j in over
            )
            out.append(
                f"{label}the current exceeds {CURRENT_FACTOR:g} times the current limit: "
                f"{worst} (a current in mA? jaxcomp wants A)"
            )
        # each swept sample's own joint: its current, and its direction
        rows = np.flatnonzero((rec.joint >= 0) & (rec.joint < n))
        joint = rec.joint[rows]
        own = current[rows, joint]
        samples = np.bincount(joint, minlength=n)
        square = np.bincount(joint, weights=own * own, minlength=n)
        direction = rec.direction[rows]
        counts[:, 0] += np.bincount(joint[direction > 0], minlength=n)
        counts[:, 1] += np.bincount(joint[direction < 0], minlength=n)
        for j in np.flatnonzero(samples):
            rms = float(np.sqrt(square[j] / samples[j]))
            if rms < ZERO_CURRENT * limits[j]:
                out.append(
                    f"{label}the current of {names[j]} is zero over its sweeps (RMS {rms:.3g} A): "
                    "was the current recorded?"
                )
    for j in np.flatnonzero(counts.min(axis=1) < MIN_SAMPLES):
        what = "never swept" if counts[j].max() < MIN_SAMPLES else "swept in one direction only"
        out.append(
            f"{names[j]} is {what} (samples up/down: {counts[j, 0]}/{counts[j, 1]}), so its "
            "friction cannot be told from its gravity torque: record it both ways, or calibrate "
            "only the joints recorded (--joints)"
        )
    return out


def check_recordings(recordings: Sequence[Recording]) -> None:
    """Refuse recordings that cannot be fitted.

    Args:
        recordings: recordings of one robot, to be fitted together.

    Raises:
        InputError: one, naming every problem (``recording_problems``).
    """
    problems = recording_problems(recordings)
    if problems:
        raise InputError("the recordings cannot be fitted: " + "; ".join(problems))
