"""The set-up of a control run: everything checked and prepared before the arm is switched.

``set_up_run`` (``loop.run_control``'s first stage) checks that the arm is healthy and still
and that the controller can move its end effector in all three directions, resolves the mount
(``control.mount``), the trajectory in the mode's frame (base frame in guidance, world in
tracking) and the run's duration, refuses targets beyond the arm's reach when the arm alone
must reach them (``workspace.arm_reach``), compiles and checks the first command, and opens the
recording (``control.run_recording``). A ``JaxcompError`` here leaves the robot as it was.
Frames: the arm's base frame for the controller; SI units (m, rad, s, A).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control.base_follower import BaseFollower
from jaxcomp.control.cycle import Cycle
from jaxcomp.control.gains import BaseGains
from jaxcomp.control.impedance import ImpedanceController
from jaxcomp.control.law_adapter import LawAdapter
from jaxcomp.control.mount import ArmMount, check_site_mobility, mobile_model_name
from jaxcomp.control.run_recording import Recorder, open_recorder
from jaxcomp.control.timing import CycleTimer
from jaxcomp.control.trajectory import Static, Trajectory, TrajectorySpec, parse_trajectory
from jaxcomp.control.velocity import VelocityController
from jaxcomp.control.watchdog import Watchdog
from jaxcomp.control.workspace import arm_reach, check_reachable
from jaxcomp.errors import InputError
from jaxcomp.hardware.interface import Arm, ArmState, Base, HardwareFault
from jaxcomp.robot import Robot

#: Cycles of timing stamps preallocated (10 min at 1 kHz, 19 MB): a longer run grows them.
TIMER_CAPACITY = 600_000


class Mode(enum.Enum):
    """Operational mode (paper IV-B)."""

    GUIDANCE = "guidance"
    TRACKING = "tracking"


@dataclass
class PreparedRun:
    """What the set-up prepared for the loop.

    Attributes:
        mode: the run's mode. law: the controller adapted to the loop. watchdog: its checks.
        work: the per-cycle work. state: the start state (healthy and still). n_cycles: the
        cycles to run. duration: s. out: the output folder. recorder: the run's recorder.
        timer: the cycle timer.
    """

    mode: Mode
    law: LawAdapter
    watchdog: Watchdog
    work: Cycle
    state: ArmState
    n_cycles: int
    duration: float
    out: Path
    recorder: Recorder
    timer: CycleTimer


def default_max_error(mode: Mode | str, controller) -> float:
    """How far the end effector may stay from its target (``run_control``'s ``max_error``
    when none is given).

    Args:
        mode: "guidance" or "tracking".
        controller: the run's controller (its gains' ``error_clip``, m; 0.1 m without one).

    Returns:
        m: in tracking mode twice the controller's error clip; in guidance mode no limit
        (inf), as a person may hold the arm off its target at will.
    """
    if Mode(mode) is Mode.GUIDANCE:
        return math.inf
    return 2.0 * float(getattr(controller.gains, "error_clip", 0.1))


def set_up_run(
    arm: Arm,
    base: Base | None,
    controller: ImpedanceController | VelocityController,
    mode: Mode,
    trajectory: TrajectorySpec | Trajectory | str | None,
    duration: float | None,
    out_dir: str | Path,
    realtime: bool,
    *,
    mount: ArmMount | None,
    base_gains: BaseGains | None,
    model: str | None,
    watchdog: Watchdog | None,
    max_saturated_cycles: int,
    base_velocity_compensation: bool,
    default_duration: float,
    max_error: float | None,
    max_error_time: float,
    before_start: Callable[[float], None] | None,
    stall_limit: float | None,
) -> PreparedRun:
    """The set-up of a run: check that the arm is healthy and still, resolve the frames and
    the trajectory, compile and check the first command, open the recording; nothing is
    switched.

    Args:
        arm, base, controller, trajectory, duration, out_dir, realtime: as ``run_control``'s.
        mode: the run's ``Mode``.
        mount, base_gains, model, watchdog, max_saturated_cycles, base_velocity_compensation,
            default_duration, max_error, max_error_time, before_start, stall_limit: as
            ``run_control``'s (keywords).

    Returns:
        The ``PreparedRun``.

    Raises:
        JaxcompError: the robot cannot start as asked (it is left as it was).
    """
    law = LawAdapter(controller, arm)
    robot = controller.robot
    if model is None:
        model = mobile_model_name(robot) if base is not None else robot.reference
    if mount is None:
        mount = ArmMount.from_model(model) if base is not None else ArmMount()
    checks.number(max_error_time, "max_error_time", positive=True, unit="s")
    if watchdog is None:
        if max_error is None:
            max_error = default_max_error(mode, controller)
        limit = stall_limit if realtime else None
        watchdog = _watchdog(arm, law, max_saturated_cycles, limit, max_error, max_error_time)
    follower = BaseFollower(base_gains, base.limits) if base is not None else None
    state, pose0 = _start(arm, base, watchdog)
    check_site_mobility(robot, state.q, controller.site)
    ee0, rot0 = (np.asarray(x, dtype=float) for x in robot.site_pose(state.q, controller.site))
    guidance = mode is Mode.GUIDANCE
    traj = _trajectory(trajectory, mount, guidance, ee0, pose0)
    duration = _duration(duration, traj, default_duration)
    if guidance or base is None:  # the arm alone must reach every target
        _check_reach(robot, controller.site, traj, duration, mount, guidance, pose0)
    if before_start is not None:
        before_start(duration)
    desired_b = mount.arm_to_base(ee0)  # tracking: the base keeps the EE where it started
    args = (law, watchdog, traj, state.t, base, follower, mount, guidance, desired_b, None)
    work = Cycle(*args, base_velocity_compensation)
    _check_first_command(work, law, watchdog, state, rot0, pose0)
    out = Path(out_dir)
    recorder = open_recorder(out, model, tuple(arm.joint_names), realtime, law.estimates)
    n_cycles = int(round(duration / CONTROL_PERIOD))
    capacity = min(n_cycles + 2, TIMER_CAPACITY)  # longer runs grow it (by doubling)
    timer = CycleTimer(CONTROL_PERIOD, capacity=capacity, realtime=realtime)
    work.recorder = recorder
    return PreparedRun(mode, law, watchdog, work, state, n_cycles, duration, out, recorder, timer)


def _watchdog(
    arm: Arm,
    law: LawAdapter,
    max_saturated_cycles: int,
    max_gap: float | None,
    max_error: float,
    max_error_time: float,
) -> Watchdog:
    """The default watchdog of a run: the arm's limits, the law's saturation and unit."""
    return Watchdog(
        arm.joint_names,
        law.limit,
        law.saturation,
        max_saturated_cycles=max_saturated_cycles,
        stale_cycles=arm.stale_tolerance,
        max_gap=max_gap,
        unit=law.unit,
        max_error=max_error,
        max_error_cycles=max(int(round(max_error_time / CONTROL_PERIOD)), 1),
    )


def _start(arm: Arm, base: Base | None, wd: Watchdog) -> tuple[ArmState, np.ndarray]:
    """The start state (healthy, still) and the base's start pose (x m, y m, yaw rad; zeros
    without a base), both checked."""
    state = arm.read()
    wd.check_state(state)
    if arm.closed:
        raise HardwareFault("the arm is closed")
    fast = np.abs(state.dq) > arm.limits.switch_speed
    if fast.any():
        j = int(np.flatnonzero(fast)[0])
        raise InputError(
            f"{arm.joint_names[j]} moves at {state.dq[j]:.3f} rad/s: the arm must be still "
            f"(below {arm.limits.switch_speed:.3f} rad/s) to start"
        )
    if base is None:
        return state, np.zeros(3)
    odom0 = base.odometry()
    wd.check_odometry(odom0.pose, odom0.twist, state.t)
    return state, np.array(odom0.pose, float)


def _trajectory(
    trajectory: TrajectorySpec | Trajectory | str | None,
    mount: ArmMount,
    guidance: bool,
    ee0: np.ndarray,
    pose0: np.ndarray,
) -> Trajectory:
    """The run's trajectory in the mode's frame (base frame in guidance, world in tracking),
    built from the end effector's start position ``ee0`` (arm frame, m)."""
    if guidance:  # trajectory frame = base frame
        start, origin, rot = mount.arm_to_base(ee0), mount.position, mount.rotation
    else:
        start = mount.arm_to_world(ee0, pose0)
        origin, rot = mount.arm_pose(pose0)
    if trajectory is None:
        return Static(start, description="static at the start position")
    if isinstance(trajectory, Trajectory):
        return trajectory
    spec = parse_trajectory(trajectory) if isinstance(trajectory, str) else trajectory
    return spec.build(start, origin, rot)


def _duration(duration: float | None, traj: Trajectory, default: float) -> float:
    """s of control: ``duration``, else the trajectory's own, else ``default``; checked."""
    if duration is None:
        duration = traj.duration if 0 < traj.duration < math.inf else default
    return checks.number(duration, "duration", positive=True, unit="s")


def _check_reach(
    robot: Robot,
    site: str,
    traj: Trajectory,
    duration: float,
    mount: ArmMount,
    guidance: bool,
    pose0: np.ndarray,
) -> None:
    """InputError when a target of ``traj`` lies beyond the arm's reach from its base."""
    reach = arm_reach(robot, site)
    o = mount.arm_to_base(reach.origin)  # in the trajectory's frame:
    o = o if guidance else mount.base_to_world(o, pose0)
    check_reachable(traj, duration, o, reach.radius, robot.name)


def _check_first_command(
    work: Cycle,
    law: LawAdapter,
    wd: Watchdog,
    state: ArmState,
    rot0: np.ndarray,
    pose0: np.ndarray,
) -> None:
    """Compile and check the first command before anything is switched (the held
    orientation set first); the command memory is reset after it."""
    if law.orientation:
        work.hold_orientation(rot0, pose0)
    law.start(state)
    wd.check_command(work.first_command(state, pose0), state.t)
    law.start(state)


__all__ = ["TIMER_CAPACITY", "Mode", "PreparedRun", "default_max_error", "set_up_run"]
