"""Calibration plans: which joint to sweep, where the others are held, how fast (paper IV-A).

A plan is an ordered list of ``Sweep``: joint ``joint`` moves from ``lower`` to ``upper`` and
back at constant ``speed`` while every other joint holds its ``hold`` angle. Before each sweep
the arm travels to the sweep's start (through the sweep's ``via`` poses, if any) at the plan's
``move_speed`` and settles there for ``settle`` s. Every move ramps up to its speed and down
again in ``ramp`` s (``Arm.move_to`` with accel = speed / ramp). Joint indices and poses refer
to the robot's current-controlled joints (``arm_joint_indices``), as in recordings. Units: rad,
rad/s, s.

``plan_for_joints`` builds a simple plan (chosen joints, one hold); the paper's plan, whose
held poses are searched on the robot's model, is ``identify.plan_design.default_plan``.

Plans are saved as JSON (``CalibrationPlan.save``, ``load_plan``)::

    {"format": "jaxcomp-calibration-plan", "version": 1,
     "units": {"hold": "rad", "lower": "rad", "upper": "rad", "speed": "rad/s", ...},
     "move_speed": 0.698, "settle": 0.5, "ramp": 0.25,
     "sweeps": [{"joint": 1, "hold": [0, 0, 1.571, 0, 0, 0], "lower": -1.745,
                 "upper": 1.745, "speed": 0.698, "via": []}, ...]}

``lower``, ``upper``, ``speed`` and ``via`` may be left out (defaults: -100 deg, +100 deg,
40 deg/s, none).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.move_profile import trapezoid_duration
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import arm_joint_indices, write_json_atomic

#: The paper's sweep: -100 deg .. +100 deg and back at 40 deg/s.
LOWER = math.radians(-100.0)
UPPER = math.radians(100.0)
SPEED = math.radians(40.0)
#: Speed of the transfer moves to each sweep, rad/s, and the hold at its start, s.
MOVE_SPEED = math.radians(40.0)
SETTLE = 0.5
#: Poses stay this far inside the joint limits, rad (the ``Arm``'s own command margin).
LIMIT_MARGIN = math.radians(1.0)
#: Each move ramps up to its speed, and down, in this time, s (``Arm.move_to``'s accel =
#: speed / ramp); gentler than the arm's default 0.1 s, it keeps the ramps' inertial torque
#: small next to gravity and friction.
RAMP = 0.25
#: An angle beyond this, rad, is taken for degrees; a speed beyond this, rad/s, for deg/s.
_MAX_ANGLE = 2 * math.pi + 0.5
_MAX_SPEED = 2 * math.pi
FORMAT = "jaxcomp-calibration-plan"
_UNITS = {
    "hold": "rad",
    "lower": "rad",
    "upper": "rad",
    "speed": "rad/s",
    "via": "rad",
    "move_speed": "rad/s",
    "settle": "s",
    "ramp": "s",
}
_SWEEP_KEYS = ("joint", "hold", "lower", "upper", "speed", "via")


def _float(value: Any, name: str) -> float:
    """``value`` as a finite float (``checks.number``), True and False refused."""
    if isinstance(value, bool):
        raise InputError(f"{name} must be a number, got {value!r}")
    return checks.number(value, name)


def _speed(value: Any, name: str) -> float:
    x = _float(value, name)
    if not 0 < x <= _MAX_SPEED:
        hint = " (deg/s? the plan wants rad/s)" if x > _MAX_SPEED else ""
        raise InputError(f"{name} must be in (0, {_MAX_SPEED:.3g}] rad/s, got {x:.4g}{hint}")
    return x


def _pose(value: Any, name: str) -> np.ndarray:
    """``value`` as a read-only copy, a finite non-empty pose (n,) rad."""
    q = np.array(checks.array(value, name, unit="rad"))
    if q.size == 0:
        raise InputError(f"{name} must be a pose (n,) in rad, got shape {q.shape}")
    q.flags.writeable = False
    return q


def _move_steps(distance: float, speed: float, ramp: float, settle: float = 0.0) -> int:
    """Cycles (= samples) of ``Arm.move_to`` over ``distance`` rad at ``speed`` rad/s with
    ramps of ``ramp`` s, then ``settle`` s."""
    duration = trapezoid_duration(distance, speed, speed / ramp)
    return math.ceil(duration / CONTROL_PERIOD - 1e-9) + int(round(settle / CONTROL_PERIOD))


@dataclass(frozen=True, eq=False)
class Sweep:
    """One sweep: ``joint`` from ``lower`` to ``upper`` and back, the others at ``hold``.

    Attributes:
        joint: index of the swept joint among the current-controlled joints.
        hold: (n,) rad, pose of the other joints (the swept joint's entry is ignored).
        lower, upper: rad, the swept range (lower < upper); the sweep starts at ``lower``.
        speed: rad/s, constant speed of the swept joint between the ramps.
        via: poses (n,) rad the transfer to the start passes through (to stay clear).
    """

    joint: int
    hold: np.ndarray
    lower: float = LOWER
    upper: float = UPPER
    speed: float = SPEED
    via: tuple[np.ndarray, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.joint, bool) or not isinstance(self.joint, int | np.integer):
            raise InputError(f"sweep 'joint' must be an integer index, got {self.joint!r}")
        object.__setattr__(self, "joint", int(self.joint))
        object.__setattr__(self, "hold", _pose(self.hold, "sweep 'hold'"))
        for name in ("lower", "upper"):
            object.__setattr__(self, name, _float(getattr(self, name), f"sweep {name!r}"))
        object.__setattr__(self, "speed", _speed(self.speed, "sweep 'speed'"))
        if not self.lower < self.upper:
            raise InputError(
                f"sweep 'lower' ({self.lower:.4g} rad) must be below 'upper' ({self.upper:.4g} rad)"
            )
        if isinstance(self.via, str) or not isinstance(self.via, Iterable):
            raise InputError(f"sweep 'via' must be a list of poses (rad), got {self.via!r}")
        via = tuple(_pose(v, f"sweep 'via' pose {k}") for k, v in enumerate(self.via))
        object.__setattr__(self, "via", via)

    def pose(self, angle: float) -> np.ndarray:
        """The hold pose with the swept joint at ``angle``.

        Args:
            angle: rad.

        Returns:
            (n,) rad.
        """
        q = np.array(self.hold)
        q[self.joint] = angle
        return q

    @property
    def start(self) -> np.ndarray:
        """(n,) rad: where the sweep starts and ends (swept joint at ``lower``)."""
        return self.pose(self.lower)

    @property
    def turn(self) -> np.ndarray:
        """(n,) rad: where the sweep turns back (swept joint at ``upper``)."""
        return self.pose(self.upper)

    def samples(self, ramp: float = RAMP) -> int:
        """1 kHz samples of the sweep's two moves (up and down).

        Args:
            ramp: s, time of each move's speed ramps.

        Returns:
            The sample count.
        """
        return 2 * _move_steps(self.upper - self.lower, self.speed, ramp)

    def to_dict(self) -> dict:
        return {
            "joint": self.joint,
            "hold": self.hold.tolist(),
            "lower": self.lower,
            "upper": self.upper,
            "speed": self.speed,
            "via": [v.tolist() for v in self.via],
        }

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sweep) and self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class CalibrationPlan:
    """An ordered list of sweeps and how the arm travels between them.

    Attributes:
        sweeps: the sweeps, recorded in this order.
        move_speed: rad/s, speed of the transfer moves (of the joint with the longest way).
        settle: s, hold at each sweep's start before it begins (> 0: it also separates
            consecutive sweeps in a recording).
        ramp: s, time of every move's speed ramps (acceleration = speed / ramp).
    """

    sweeps: tuple[Sweep, ...]
    move_speed: float = MOVE_SPEED
    settle: float = SETTLE
    ramp: float = RAMP

    def __post_init__(self) -> None:
        if isinstance(self.sweeps, Sweep) or not isinstance(self.sweeps, Iterable):
            raise InputError("plan 'sweeps' must be a list of Sweep")
        sweeps = tuple(self.sweeps)
        for i, s in enumerate(sweeps):
            if not isinstance(s, Sweep):
                raise InputError(f"plan sweep {i} must be a Sweep, got {type(s).__name__}")
        if not sweeps:
            raise InputError("plan 'sweeps' is empty: a calibration plan needs at least one sweep")
        object.__setattr__(self, "sweeps", sweeps)
        object.__setattr__(self, "move_speed", _speed(self.move_speed, "plan 'move_speed'"))
        settle = _float(self.settle, "plan 'settle'")
        if not 0 < settle <= 60:
            raise InputError(f"plan 'settle' must be in (0, 60] s, got {settle}")
        object.__setattr__(self, "settle", settle)
        ramp = _float(self.ramp, "plan 'ramp'")
        if not 0 < ramp <= 5:
            raise InputError(f"plan 'ramp' must be in (0, 5] s, got {ramp}")
        object.__setattr__(self, "ramp", ramp)

    def __len__(self) -> int:
        return len(self.sweeps)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CalibrationPlan) and self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]

    @property
    def joints(self) -> list[int]:
        """The swept joint of each sweep."""
        return [s.joint for s in self.sweeps]

    # ----------------------------------------------------------------- checks
    def validate(self, robot: Robot | str) -> CalibrationPlan:
        """Return the plan, or raise InputError unless every sweep fits ``robot``.

        Checks joint indices, pose sizes, and that every pose (hold, ``lower``, ``upper``,
        ``via``) lies inside the joint limits less ``LIMIT_MARGIN`` (1 deg), the range that
        ``Arm.move_to`` accepts; angles beyond 2 pi + 0.5 rad are reported as degrees.

        Args:
            robot: The robot (name, path or ``Robot``).

        Returns:
            The plan itself.

        Raises:
            InputError: naming the sweep, the field and the joint that do not fit.
        """
        robot = load_robot(robot)
        arm = arm_joint_indices(robot)
        n = len(arm)
        names = [robot.joint_names[j] for j in arm]
        lim = robot.joint_limits[arm] + np.array([LIMIT_MARGIN, -LIMIT_MARGIN])

        def check(where: str, key: str, q: np.ndarray, use: np.ndarray) -> None:
            if np.abs(q[use]).max(initial=0.0) > _MAX_ANGLE:
                raise InputError(
                    f"{where}: {key!r} has angles beyond {_MAX_ANGLE:.3g} rad: it looks like "
                    "degrees; the plan wants rad"
                )
            bad = use & ((q < lim[:, 0]) | (q > lim[:, 1]))
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise InputError(
                    f"{where}: {key!r} {math.degrees(q[k]):.1f} deg of {names[k]} is beyond "
                    f"its limits [{math.degrees(lim[k, 0]):.1f}, {math.degrees(lim[k, 1]):.1f}] "
                    "deg (less a 1 deg margin)"
                )

        for i, s in enumerate(self.sweeps):
            where = f"plan sweep {i}"
            if not 0 <= s.joint < n:
                raise InputError(
                    f"{where}: 'joint' {s.joint} is not a joint index 0..{n - 1} of {robot.name}"
                )
            for key, q in [("hold", s.hold)] + [("via", v) for v in s.via]:
                if q.shape != (n,):
                    raise InputError(
                        f"{where}: {key!r} must have {n} angles (joints {', '.join(names)}), "
                        f"got {q.size}"
                    )
            others = np.arange(n) != s.joint
            check(where, "hold", s.hold, others)
            only = ~others
            check(where, "lower", s.start, only)
            check(where, "upper", s.turn, only)
            for v in s.via:
                check(where, "via", v, np.ones(n, bool))
        return self

    # ----------------------------------------------------------------- estimates
    def moves(self, sweeps: Iterable[int] | None = None) -> Iterator[tuple]:
        """The ``Arm.move_to`` calls that record the plan, in order.

        Args:
            sweeps: Only these sweep indices (when resuming); None: all.

        Yields:
            (sweep index, kind, target (n,) rad, speed rad/s, accel rad/s^2, settle s); kind
            is "via", "start" (the transfer's last move, then ``settle``), "up" or "down".
        """
        todo = range(len(self.sweeps)) if sweeps is None else list(sweeps)
        for i in todo:
            s = self.sweeps[i]
            travel = self.move_speed / self.ramp
            for v in s.via:
                yield i, "via", np.array(v), self.move_speed, travel, 0.0
            yield i, "start", s.start, self.move_speed, travel, self.settle
            yield i, "up", s.turn, s.speed, s.speed / self.ramp, 0.0
            yield i, "down", s.start, s.speed, s.speed / self.ramp, 0.0

    def samples(
        self, start: Sequence[float] | None = None, sweeps: Iterable[int] | None = None
    ) -> int:
        """1 kHz samples (= cycles) that recording the plan takes.

        Args:
            start: (n,) rad, where the arm begins (default: at the first move's target).
            sweeps: Only these sweep indices (see ``moves``).

        Returns:
            The sample count.
        """
        total = 0
        pose = None if start is None else np.asarray(start, float)
        for _, _, target, speed, _, settle in self.moves(sweeps):
            dist = 0.0 if pose is None else float(np.abs(target - pose).max())
            total += _move_steps(dist, speed, self.ramp, settle)
            pose = target
        return total

    def duration(
        self, start: Sequence[float] | None = None, sweeps: Iterable[int] | None = None
    ) -> float:
        """The time that recording the plan takes.

        Args:
            start: (n,) rad, where the arm begins (see ``samples``).
            sweeps: Only these sweep indices.

        Returns:
            s.
        """
        return self.samples(start, sweeps) * CONTROL_PERIOD

    # ----------------------------------------------------------------- files
    def to_dict(self) -> dict:
        """The JSON contents (see the module docstring)."""
        return {
            "format": FORMAT,
            "version": 1,
            "units": dict(_UNITS),
            "move_speed": self.move_speed,
            "settle": self.settle,
            "ramp": self.ramp,
            "sweeps": [s.to_dict() for s in self.sweeps],
        }

    def save(self, path: str | Path) -> Path:
        """Write the plan as JSON (atomically: never half-written).

        Args:
            path: The file.

        Returns:
            The path written.
        """
        return write_json_atomic(path, self.to_dict())

    def describe(self, start: Sequence[float] | None = None) -> str:
        """A table of the sweeps for people (degrees, seconds).

        Args:
            start: (n,) rad, where the arm begins (for the total duration).

        Returns:
            The table, lines joined.
        """
        lines = [f"{'#':>3} {'joint':>5} {'range (deg)':>12} {'deg/s':>6} {'s':>5}  hold (deg)"]
        for i, s in enumerate(self.sweeps):
            hold = " ".join(
                "   *" if k == s.joint else f"{math.degrees(v):4.0f}" for k, v in enumerate(s.hold)
            )
            rng = f"{math.degrees(s.lower):.0f}..{math.degrees(s.upper):.0f}"
            via = f"  (via {len(s.via)} pose{'s' * (len(s.via) > 1)})" if s.via else ""
            lines.append(
                f"{i:>3} {s.joint:>5} {rng:>12} {math.degrees(s.speed):>6.1f} "
                f"{s.samples(self.ramp) * CONTROL_PERIOD:>5.1f}  {hold}{via}"
            )
        lines.append(
            f"{len(self.sweeps)} sweeps: {self.duration(start):.0f} s, "
            f"{self.samples(start)} samples at 1 kHz"
        )
        return "\n".join(lines)


def plan_from_dict(data: Mapping[str, Any]) -> CalibrationPlan:
    """A plan from its JSON contents.

    Args:
        data: The parsed JSON object (see the module doc).

    Returns:
        The plan (not yet validated against a robot).

    Raises:
        InputError: naming the field at fault.
    """
    if not isinstance(data, Mapping):
        raise InputError(f"a plan must be a JSON object, got {type(data).__name__}")
    if data.get("format", FORMAT) != FORMAT:
        raise InputError(f"plan field 'format' must be {FORMAT!r}, got {data['format']!r}")
    units = data.get("units")
    if units is not None and units != _UNITS:
        raise InputError(f"plan field 'units' must be {_UNITS} (SI, radians), got {units}")
    known = {"format", "version", "units", "move_speed", "settle", "ramp", "sweeps", "note"}
    unknown = set(data) - known
    if unknown:
        raise InputError(f"plan has unknown field(s) {sorted(unknown)}")
    if "sweeps" not in data:
        raise InputError("plan field 'sweeps' is missing")
    if not isinstance(data["sweeps"], list):
        raise InputError("plan field 'sweeps' must be a list of sweeps")
    sweeps = []
    for i, s in enumerate(data["sweeps"]):
        if not isinstance(s, Mapping):
            raise InputError(f"plan sweep {i} must be an object, got {s!r}")
        missing = [k for k in ("joint", "hold") if k not in s]
        if missing:
            raise InputError(f"plan sweep {i}: field(s) {missing} missing")
        extra = set(s) - set(_SWEEP_KEYS)
        if extra:
            raise InputError(f"plan sweep {i}: unknown field(s) {sorted(extra)}")
        try:
            sweeps.append(Sweep(**s))
        except InputError as exc:
            raise InputError(f"plan sweep {i}: {exc}") from None
    kw = {k: data[k] for k in ("move_speed", "settle", "ramp") if k in data}
    return CalibrationPlan(tuple(sweeps), **kw)


def load_plan(path: str | Path, robot: Robot | str | None = None) -> CalibrationPlan:
    """Read a plan JSON file.

    Args:
        path: The file.
        robot: Validate the plan against this robot (name, path or ``Robot``); None: don't.

    Returns:
        The plan.

    Raises:
        InputError: a missing or unreadable file, or a bad plan (naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"plan file not found: {path}")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a readable JSON plan ({exc})") from None
    try:
        plan = plan_from_dict(data)
        return plan if robot is None else plan.validate(robot)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


# --------------------------------------------------------------------- simple plans
def arm_pose(robot: Robot, pose: str | Sequence[float] | None = None) -> np.ndarray:
    """A pose of the current-controlled joints.

    Args:
        robot: The robot.
        pose: A named pose, an (n,) array in rad, or None: ``Robot.idle_pose`` (the "home"
            keyframe, else the rest pose).

    Returns:
        (n,) rad.

    Raises:
        InputError: an unknown pose name, or an array not finite (n,).
    """
    arm = arm_joint_indices(robot)
    if pose is None:
        pose = robot.idle_pose[arm]
    if isinstance(pose, str):
        return robot.pose(pose)[arm]
    return checks.array(pose, "pose", n=len(arm), unit="rad")


def plan_for_joints(
    robot: Robot | str,
    joints: int | Sequence[int],
    hold: str | Sequence[float] | None = None,
    *,
    lower: float = LOWER,
    upper: float = UPPER,
    speed: float = SPEED,
    move_speed: float = MOVE_SPEED,
    settle: float = SETTLE,
    ramp: float = RAMP,
) -> CalibrationPlan:
    """One sweep per joint of ``joints``, all from the same ``hold`` (validated).

    Args:
        robot: the robot (name, path or ``Robot``).
        joints: swept joint index, or indices, among the current-controlled joints.
        hold: (n,) rad or a named pose; default ``Robot.idle_pose`` (the "home" keyframe,
            else the rest pose).
        lower: rad, start of each sweep.
        upper: rad, where it turns back.
        speed: rad/s, of the sweeps.
        move_speed: rad/s, of the transfers.
        settle: s, the hold at each sweep's start.
        ramp: s, time of every move's speed ramps.

    Returns:
        The plan, validated against ``robot``.

    Raises:
        InputError: a bad value, or a sweep that does not fit the robot.

    ``plan_for_joints("gen3_lite", 1, lower=-0.35, upper=0.35)``: joint 1 over +-20 deg at
    40 deg/s from the home pose.
    """
    robot = load_robot(robot)
    q = arm_pose(robot, hold)
    joints = [joints] if isinstance(joints, int | np.integer) else list(joints)
    sweeps = tuple(Sweep(j, q, lower, upper, speed) for j in joints)
    return CalibrationPlan(sweeps, move_speed, settle, ramp).validate(robot)
