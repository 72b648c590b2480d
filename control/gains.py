"""Gains of the arm's impedance controller, the reference velocity controller and the base follower.

Frozen, validated dataclasses (``InputError`` on a bad value) with the paper's figures as
defaults (de Wolde et al., Eq. 3-5, 16, 20 and Section V; the paper authors' code for the
figures the text leaves out): figures of the Gen3 Lite, which ``control.presets`` carries over
to other arms (``impedance_gains(robot, preset)``). Cartesian quantities are per axis x, y, z
of the arm's base frame; per-joint quantities accept one number for every joint or one per
joint, and are expanded by ``joint_arrays(robot)`` against a robot model (``None`` = the
model's own figure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.robot_params import current_limits

if TYPE_CHECKING:
    from jaxcomp.robot import Robot

Vec3 = tuple[float, float, float]
PerJoint = float | tuple[float, ...]

#: Keyframe used as nullspace posture when a gains object names none.
POSTURE_KEYFRAME = "preferred"
#: Values of ``ImpedanceGains.friction_direction``.
FRICTION_DIRECTIONS = ("torque", "motion")
#: Fields that ``ImpedanceGains.tracking()`` changes from the paper's figures.
TRACKING_PRESET = {
    "stiffness": 400.0,
    "damping": 30.0,
    "friction_direction": "motion",
    "friction_threshold": 0.02,
    "friction_band": 0.05,
    "nullspace_damping": 0.3,
}
#: Units of the ``BaseGains`` figures, each a number >= 0.
_BASE_UNITS = {
    "gain": "1/s",
    "max_speed": "m/s",
    "deadband": "m",
    "yaw_gain": "1/s",
    "max_yaw_rate": "rad/s",
    "yaw_deadband": "rad",
}
#: Named presets of ``ImpedanceGains`` (``ImpedanceGains.preset(name)``).
IMPEDANCE_PRESETS = ("paper", "tracking")


def _vec3(value, name: str) -> Vec3:
    """A gain per axis x, y, z (one number for all three), each finite and >= 0."""
    arr = checks.array(value, name, n=3, labels=("x", "y", "z"), nonneg=True, scalar=True)
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _per_joint(value, name: str, *, positive: bool = False, signed: bool = False) -> PerJoint:
    """One number for every joint or a non-empty list of one per joint, finite, > 0
    (``positive``), else >= 0 unless ``signed``."""
    nonneg = not (positive or signed)
    arr = checks.array(value, name, positive=positive, nonneg=nonneg, scalar=True)
    if arr.ndim == 0:
        return float(arr)
    if arr.size == 0:
        raise InputError(f"{name} must be a number or a non-empty list of numbers, got []")
    return tuple(float(x) for x in arr)


def _expand(value: PerJoint, name: str, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise InputError(f"{name} has {arr.size} values but the robot has {n} joints")
    return arr.copy()


def _check_bool(value, name: str) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be True or False, got {value!r}")


class JointGains(NamedTuple):
    """Per-joint figures resolved against a robot.

    Attributes:
        posture: Nullspace posture q_pref, (n,) rad.
        stiffness: (n,) N m/rad (impedance) or 1/s (velocity controller).
        damping: (n,) N m s/rad (impedance); zeros for the velocity controller.
        limit: (n,) A (impedance: current limit) or rad/s (velocity limit).
    """

    posture: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    limit: np.ndarray


def _posture(posture, robot: Robot) -> np.ndarray:
    if posture is None:
        return robot.pose(POSTURE_KEYFRAME)
    return _expand(posture, "posture", robot.nv)


def check_fixed_base(robot: Robot) -> None:
    """Refuse a model with base joints (the controllers work in the arm-alone model).

    Args:
        robot: The model.

    Raises:
        InputError: ``robot`` has base joints.
    """
    from jaxcomp.robot_params import BASE_JOINTS

    base = [n for n in robot.joint_names if n in BASE_JOINTS]
    if base:
        raise InputError(
            f"the arm controllers work in the arm's own model; {robot.name} has base joints "
            f"{', '.join(base)} (load the arm alone, e.g. load_robot('gen3_lite'))"
        )


@dataclass(frozen=True)
class ImpedanceGains:
    """Current-based Cartesian impedance control (paper Eq. 3-5 and 16).

    Attributes:
        stiffness: K_d, N/m per base-frame axis (paper: 40).
        damping: D_d, N s/m per axis (paper: 3).
        orientation_stiffness: N m/rad per axis about the base frame; 0 = no orientation task.
            A nonzero value adds an orientation spring towards ``target_rot`` as a secondary
            task projected into the position task's nullspace (with the posture).
        orientation_damping: N m s/rad per axis.
        feedforward: add Lambda xdd_d + mu xd_d of Eq. (3) to the Cartesian force (paper: off).
        posture: nullspace posture q_pref, rad, (n,); None = ``robot.pose("preferred")`` (the
            model's keyframe, else the start pose chosen on the model).
        nullspace_stiffness: K_n, N m/rad, one or per joint (paper's code: 0.125).
        nullspace_damping: D_n, N m s/rad, one or per joint (paper's code: 0.025).
        error_clip: m, the Cartesian error's norm is clipped to this (paper: 0.1).
        deadband: m, errors of smaller norm count as zero (paper's code: 0.001).
        friction_threshold: t of Eq. (16), rad/s (paper's code: 0.3).
        friction_direction: which torque gives the direction of the at-rest (torque-based)
            friction compensation of Eq. (16): "torque" = sign(tau), the paper's; "motion" =
            sign(tau - g(q)), the torque meant to move the joint (gravity compensation holds a
            joint, it does not move it: with "torque" a gravity-loaded joint at rest is pushed
            by l towards its gravity torque and needs 2 l of spring torque to move the other way).
        friction_band: N m, width of the linear zone of that at-rest sign: sign(x) becomes
            clip(x / friction_band, -1, 1), continuous at x = 0, so a joint at rest whose torque
            hovers around zero is not kicked by +-l every cycle (0 = the paper's hard sign).
        current_limit: A, magnitude per joint; None = the model's
            (``jaxcomp.robot_params.current_limits``: its ``jaxcomp_current_limit``
            custom numeric (Gen3 Lite: 11 A), else effort limit x nominal ratio, else 11 A).
        current_rate_limit: A/s, one or per joint, the most a joint's current may change per
            second (default 2000 A/s = 2 A per 1 ms cycle: a full-scale 11 A step takes 5.5 ms,
            and the friction compensation's sign flip of Eq. (16), up to 2 l ~ 3 A, takes 2
            cycles; ``control.presets`` scales it to other current limits).
        period: s, control period the rate limit refers to (``CONTROL_PERIOD``, 1 kHz).
        singularity_damping: 1/kg added to the diagonal of J M^-1 J^T before it is inverted,
            keeping the nullspace projector and Lambda finite at singular poses; small against
            its smallest eigenvalue (Gen3 Lite: 0.4-0.54 1/kg at home, preferred, retract;
            0.016 1/kg stretched upright at zero).
    """

    stiffness: Vec3 = (40.0, 40.0, 40.0)
    damping: Vec3 = (3.0, 3.0, 3.0)
    orientation_stiffness: Vec3 = (0.0, 0.0, 0.0)
    orientation_damping: Vec3 = (0.0, 0.0, 0.0)
    feedforward: bool = False
    posture: tuple[float, ...] | None = None
    nullspace_stiffness: PerJoint = 0.125
    nullspace_damping: PerJoint = 0.025
    error_clip: float = 0.1
    deadband: float = 0.001
    friction_threshold: float = 0.3
    friction_direction: str = "torque"
    friction_band: float = 0.0
    current_limit: PerJoint | None = None
    current_rate_limit: PerJoint = 2000.0
    period: float = CONTROL_PERIOD
    singularity_damping: float = 1e-6

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        for name in ("stiffness", "damping", "orientation_stiffness", "orientation_damping"):
            set_(self, name, _vec3(getattr(self, name), name))
        _check_bool(self.feedforward, "feedforward")
        if self.posture is not None:
            set_(self, "posture", _per_joint(self.posture, "posture", signed=True))
            if np.ndim(self.posture) == 0:
                raise InputError("posture must list one angle (rad) per joint")
        set_(
            self, "nullspace_stiffness", _per_joint(self.nullspace_stiffness, "nullspace_stiffness")
        )
        set_(self, "nullspace_damping", _per_joint(self.nullspace_damping, "nullspace_damping"))
        set_(self, "error_clip", checks.number(self.error_clip, "error_clip (m)", positive=True))
        set_(self, "deadband", checks.number(self.deadband, "deadband (m)", nonneg=True))
        if self.deadband >= self.error_clip:
            raise InputError(
                f"deadband ({self.deadband} m) must be smaller than error_clip "
                f"({self.error_clip} m)"
            )
        t = checks.number(self.friction_threshold, "friction_threshold (rad/s)", positive=True)
        set_(self, "friction_threshold", t)
        if self.friction_direction not in FRICTION_DIRECTIONS:
            raise InputError(
                f"friction_direction must be one of {', '.join(FRICTION_DIRECTIONS)}, got "
                f"{self.friction_direction!r}"
            )
        band = checks.number(self.friction_band, "friction_band (N m)", nonneg=True)
        set_(self, "friction_band", band)
        if self.current_limit is not None:
            lim = _per_joint(self.current_limit, "current_limit (A)", positive=True)
            set_(self, "current_limit", lim)
        rate = _per_joint(self.current_rate_limit, "current_rate_limit (A/s)", positive=True)
        set_(self, "current_rate_limit", rate)
        set_(self, "period", checks.number(self.period, "period (s)", positive=True))
        damp = checks.number(self.singularity_damping, "singularity_damping (1/kg)", nonneg=True)
        set_(self, "singularity_damping", damp)

    @classmethod
    def preset(cls, name: str, **changes) -> ImpedanceGains:
        """A named preset (``IMPEDANCE_PRESETS``: "paper", "tracking") with ``changes``: the
        Gen3 Lite's figures (``control.presets.impedance_gains`` gives them for any arm).

        Args:
            name: The preset.
            **changes: Fields to override.

        Returns:
            The gains.

        Raises:
            InputError: an unknown preset or a bad field value.
        """
        if name not in IMPEDANCE_PRESETS:
            raise InputError(
                f"unknown gains preset {name!r}; presets: {', '.join(IMPEDANCE_PRESETS)}"
            )
        return getattr(cls, name)(**changes)

    @classmethod
    def paper(cls, **changes) -> ImpedanceGains:
        """The paper's figures (Section V-B and its authors' code): K_d 40 N/m, D_d 3 N s/m,
        Eq. (16) with sign(tau) at rest and t = 0.3 rad/s, nullspace K_n 0.125, D_n 0.025;
        the same as ``ImpedanceGains()``. ``changes`` override fields."""
        return cls(**changes)

    @classmethod
    def tracking(cls, **changes) -> ImpedanceGains:
        """Gains that hold the Exp. 2 and 3 behaviour against the Gen3 Lite's full friction
        (joint 1 loses 1.48 A = 4.8 N m): K_d 400 N/m and D_d 30 N s/m (a 4 N spring cannot
        move a joint that sticks with 4.8 N m), Eq. (16)'s at-rest direction from the motion
        torque tau - g (``friction_direction="motion"``) with a 0.05 N m linear zone, full
        velocity-based compensation from t = 0.02 rad/s, and nullspace damping D_n 0.3 N m s/rad
        (with its friction compensated, the light wrist would otherwise swing towards the
        posture at the 2 rad/s overspeed limit). ``changes`` override fields."""
        values = dict(TRACKING_PRESET)
        values.update(changes)
        return cls(**values)

    @property
    def orientation(self) -> bool:
        """Whether the orientation task is on (any orientation gain nonzero)."""
        return any(self.orientation_stiffness) or any(self.orientation_damping)

    @property
    def max_current_step(self) -> float | np.ndarray:
        """A: the most a current may change in one control period (one, or (n,) per joint)."""
        if np.ndim(self.current_rate_limit) == 0:
            return self.current_rate_limit * self.period
        return np.asarray(self.current_rate_limit) * self.period

    def joint_arrays(self, robot: Robot) -> JointGains:
        """The per-joint figures expanded against ``robot``.

        Args:
            robot: The arm-alone model (n joints).

        Returns:
            Posture rad, K_n N m/rad, D_n N m s/rad, current limit A, each (n,).

        Raises:
            InputError: base joints on ``robot``, or a per-joint figure not of n values.
        """
        check_fixed_base(robot)
        n = robot.nv
        if self.current_limit is None:
            limit = current_limits(robot)
        else:
            limit = _expand(self.current_limit, "current_limit", n)
        _expand(self.current_rate_limit, "current_rate_limit", n)  # one, or one per joint
        return JointGains(
            posture=_posture(self.posture, robot),
            stiffness=_expand(self.nullspace_stiffness, "nullspace_stiffness", n),
            damping=_expand(self.nullspace_damping, "nullspace_damping", n),
            limit=limit,
        )

    def replace(self, **changes) -> ImpedanceGains:
        """A copy with some fields changed (validated)."""
        return _replace(self, changes)


@dataclass(frozen=True)
class VelocityGains:
    """The reference, non-compliant Cartesian velocity controller (the robot's default).

    dq = dq_n + J^+ (v - J dq_n), v = K_p clip(x_d - x) + xd_d, dq_n = k_n (q_pref - q), with
    the damped pseudo-inverse J^+ = J^T (J J^T + lambda^2 I)^-1 (the posture velocity dq_n acts
    in J's nullspace), scaled down uniformly so that no joint exceeds its velocity limit.

    Attributes:
        gain: K_p, 1/s per base-frame axis.
        max_speed: m/s, the Cartesian velocity command's norm is limited to this.
        error_clip: m, the position error's norm is clipped to this.
        pinv_damping: lambda, m, of the damped pseudo-inverse.
        posture: rad, (n,); None = ``robot.pose("preferred")`` (keyframe, else start pose).
        nullspace_gain: k_n, 1/s, one or per joint.
        joint_velocity_limit: rad/s, one or per joint (1 rad/s = ``ArmLimits`` default).
    """

    gain: Vec3 = (5.0, 5.0, 5.0)
    max_speed: float = 0.25
    error_clip: float = 0.1
    pinv_damping: float = 0.01
    posture: tuple[float, ...] | None = None
    nullspace_gain: PerJoint = 0.5
    joint_velocity_limit: PerJoint = 1.0

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "gain", _vec3(self.gain, "gain"))
        set_(self, "max_speed", checks.number(self.max_speed, "max_speed (m/s)", positive=True))
        set_(self, "error_clip", checks.number(self.error_clip, "error_clip (m)", positive=True))
        set_(
            self, "pinv_damping", checks.number(self.pinv_damping, "pinv_damping (m)", nonneg=True)
        )
        if self.posture is not None:
            set_(self, "posture", _per_joint(self.posture, "posture", signed=True))
            if np.ndim(self.posture) == 0:
                raise InputError("posture must list one angle (rad) per joint")
        set_(self, "nullspace_gain", _per_joint(self.nullspace_gain, "nullspace_gain (1/s)"))
        lim = _per_joint(self.joint_velocity_limit, "joint_velocity_limit (rad/s)", positive=True)
        set_(self, "joint_velocity_limit", lim)

    def joint_arrays(self, robot: Robot) -> JointGains:
        """The per-joint figures expanded against ``robot``.

        Args:
            robot: The arm-alone model (n joints).

        Returns:
            Posture rad, k_n 1/s, zeros, joint velocity limit rad/s, each (n,).

        Raises:
            InputError: base joints on ``robot``, or a per-joint figure not of n values.
        """
        check_fixed_base(robot)
        n = robot.nv
        return JointGains(
            posture=_posture(self.posture, robot),
            stiffness=_expand(self.nullspace_gain, "nullspace_gain", n),
            damping=np.zeros(n),
            limit=_expand(self.joint_velocity_limit, "joint_velocity_limit", n),
        )

    def replace(self, **changes) -> VelocityGains:
        """A copy with some fields changed (validated)."""
        return _replace(self, changes)


@dataclass(frozen=True)
class BaseGains:
    """The base follower of Eq. (20), v_b = K_b (p - p_d), plus a yaw rate for joint 0.

    Attributes:
        gain: K_b, 1/s (paper's code: 4).
        max_speed: m/s, the planar velocity's norm is limited to this (paper's code: 1).
        deadband: m, horizontal errors of smaller norm give no motion (paper's code: 0.01).
        yaw_gain: 1/s, yaw rate per rad of the yaw joint's angle (paper's code: 0.5).
        max_yaw_rate: rad/s (paper's code: 0.5).
        yaw_deadband: rad, yaw-joint angles of smaller magnitude give no rotation (10 deg).
        yaw_joint: index of the arm joint kept near its neutral angle 0 (joint 0).
    """

    gain: float = 4.0
    max_speed: float = 1.0
    deadband: float = 0.01
    yaw_gain: float = 0.5
    max_yaw_rate: float = 0.5
    yaw_deadband: float = math.radians(10.0)
    yaw_joint: int = 0

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        for name, unit in _BASE_UNITS.items():
            set_(self, name, checks.number(getattr(self, name), f"{name} ({unit})", nonneg=True))
        if isinstance(self.yaw_joint, bool) or not isinstance(self.yaw_joint, (int, np.integer)):
            raise InputError(f"yaw_joint must be a joint index, got {self.yaw_joint!r}")
        if self.yaw_joint < 0:
            raise InputError(f"yaw_joint must be >= 0, got {self.yaw_joint}")
        set_(self, "yaw_joint", int(self.yaw_joint))

    def replace(self, **changes) -> BaseGains:
        """A copy with some fields changed (validated)."""
        return _replace(self, changes)


def _replace(obj, changes: dict):
    names = {f.name for f in fields(obj)}
    unknown = sorted(set(changes) - names)
    if unknown:
        raise InputError(
            f"{type(obj).__name__} has no field(s) {', '.join(unknown)}; "
            f"fields: {', '.join(sorted(names))}"
        )
    values = {f.name: getattr(obj, f.name) for f in fields(obj)}
    values.update(changes)
    return type(obj)(**values)
