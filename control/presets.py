"""The impedance presets of any arm: declared by its model, else the Gen3 Lite's scaled to it.

``ImpedanceGains.preset(name)`` holds the figures tuned on the Kinova Gen3 Lite (the paper's
arm). ``impedance_gains(robot, name)`` gives the same preset for another arm:

- declared: a model may state a preset's figures in a custom numeric
  ``jaxcomp_impedance_<name>`` = "K D K_n D_n clip" (Cartesian stiffness N/m, Cartesian damping
  N s/m, nullspace stiffness N m/rad, nullspace damping N m s/rad, error clip m). The Gen3 Lite
  declares its own (paper: 40 3 0.125 0.025 0.1; tracking: 400 30 0.125 0.3 0.1), so its gains
  are exactly ``ImpedanceGains.preset(name)``.
- derived (``ArmFigures`` of the arm at its start pose ``robot.pose("home")``, nominal
  inertials): with the mass scale s_m = m / ``REFERENCE_APPARENT_MASS`` and the size scale
  s_L = L / ``REFERENCE_REACH``,

      K, D       = Gen3 Lite's x s_m
      K_n, D_n   = Gen3 Lite's x s_m s_L^2, then D_n,j <= ``DAMPING_NUMBER`` I_j / T per joint
      clip       = Gen3 Lite's x s_L

  m (kg) is the end effector's apparent mass in its lightest direction, the smallest
  eigenvalue of Lambda = (J M^-1 J^T)^-1: the Cartesian loop keeps the Gen3 Lite's natural
  frequency and damping ratio in that direction, and its damping number D T / m (T the 1 ms
  control period; tracking: 30 N s/m x 1 ms / 0.12 kg = 1/4, the most damping a loop with a
  one-cycle delay takes without ringing). L (m) is the reach, the length of the chain of joint
  anchors from the first joint moving the end effector to its site; joint-space stiffness
  scales like J^T K J, i.e. like K L^2, and the error clip (which bounds the spring force)
  like the arm. I_j = 1 / (M^-1)_jj (kg m^2) is joint j's effective inertia: the nullspace
  damping of a light joint is capped so that D_n,j T / I_j stays at ``DAMPING_NUMBER`` (the
  Gen3 Lite's tracking preset exceeds it on its last wrist joint, 0.3 N m s/rad on
  1.3e-4 kg m^2, and relies on that joint's friction).

  The Gen3 Lite's own figures (m 0.1203 kg, L 0.914 m) give its presets within 0.1 %, but for
  that cap.

In both cases the current rate limit scales with each joint's current limit (2000 A/s per
11 A: a full-scale step takes 5.5 ms on every arm), one number when all joints share it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control.gains import IMPEDANCE_PRESETS, ImpedanceGains, check_fixed_base
from jaxcomp.errors import InputError, ModelError
from jaxcomp.robot import Robot
from jaxcomp.robot_params import DEFAULT_CURRENT_LIMIT, current_limits

#: kg: the Gen3 Lite's apparent mass (smallest eigenvalue of Lambda) at its home pose.
REFERENCE_APPARENT_MASS = 0.1203
#: m: the Gen3 Lite's reach (chain of joint anchors to the end effector).
REFERENCE_REACH = 0.914
#: Largest D_n,j T / I_j of a derived nullspace damping (T = ``CONTROL_PERIOD``).
DAMPING_NUMBER = 0.25
#: The most Cartesian stiffness a person may set, in multiples of the arm's tracking preset.
STIFFNESS_LIMIT = 2.5
#: Custom numeric a model declares a preset's figures in (``.format(preset=name)``).
DECLARED_PRESET = "jaxcomp_impedance_{preset}"
#: What the declared figures are, in order.
DECLARED_FIELDS = ("stiffness", "damping", "nullspace_stiffness", "nullspace_damping", "error_clip")


class ArmFigures(NamedTuple):
    """What the derived presets are scaled by (nominal inertials, at the start pose).

    Attributes:
        apparent_mass: kg, smallest eigenvalue of the end effector's Lambda.
        reach: m, length of the chain of joint anchors up to the end-effector site.
        joint_inertia: (n,) kg m^2 (or kg for a slide), 1 / (M^-1)_jj.
        current_limit: (n,) A (``current_limits``).
        pose: (n,) rad, where the figures were taken (``robot.pose("home")``).
    """

    apparent_mass: float
    reach: float
    joint_inertia: np.ndarray
    current_limit: np.ndarray
    pose: np.ndarray


def arm_figures(robot: Robot) -> ArmFigures:
    """The ``ArmFigures`` of a fixed-base arm (kept on the robot, ``Robot.cached``).

    Args:
        robot: The arm-alone model.

    Returns:
        Its figures at ``robot.pose("home")``, nominal inertials.

    Raises:
        InputError: ``robot`` has base joints.
        ModelError: no joint moves the end effector at that pose.
    """
    check_fixed_base(robot)
    return robot.cached(("control", "arm_figures"), lambda: _figures(robot))


def _figures(robot: Robot) -> ArmFigures:
    tree, site = robot.tree, robot.end_effector
    q = robot.pose("home")
    mass = np.asarray(robot.mass_matrix(q))
    jac = np.asarray(robot.jacobian(q, site))[:3]
    anchor = np.asarray(robot.forward_kinematics(q).anchor)
    pos = np.asarray(robot.site_position(q, site))
    mass_inv = np.linalg.inv(mass)
    mobility = np.linalg.eigvalsh(jac @ mass_inv @ jac.T)  # 1/kg, eigenvalues of Lambda^-1
    if not mobility[-1] > 0:
        raise ModelError(
            f"{robot.name}: no joint moves the end effector {robot.end_effector!r} at the start "
            "pose (choose another site with --site, or other joints with --joints)"
        )
    chain = [j for j in range(robot.nv) if tree.moves[j, tree.site_body[robot.site_index(site)]]]
    points = np.concatenate([anchor[chain], pos[None]])
    reach = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
    return ArmFigures(
        apparent_mass=float(1.0 / mobility[-1]),
        reach=reach,
        joint_inertia=1.0 / np.diag(mass_inv),
        current_limit=current_limits(robot),
        pose=q,
    )


def declared_preset(robot: Robot, preset: str) -> dict[str, float] | None:
    """The figures ``robot``'s model declares for ``preset``.

    Args:
        robot: The arm's model.
        preset: A name of ``IMPEDANCE_PRESETS``.

    Returns:
        {field: value} over ``DECLARED_FIELDS`` (N/m, N s/m, N m/rad, N m s/rad, m), or None
        when the model declares none.

    Raises:
        ModelError: the custom numeric does not hold five positive numbers.
    """
    name = DECLARED_PRESET.format(preset=preset)
    values = robot.custom_numeric(name)
    if values is None:
        return None
    if values.shape != (len(DECLARED_FIELDS),) or not np.all(np.isfinite(values) & (values > 0)):
        raise ModelError(
            f"{robot.name}: custom numeric {name} must hold {len(DECLARED_FIELDS)} positive "
            f"numbers ({', '.join(DECLARED_FIELDS)}), got {values.tolist()}"
        )
    return {f: float(v) for f, v in zip(DECLARED_FIELDS, values, strict=True)}


def derived_preset(robot: Robot, preset: str) -> dict[str, float | tuple[float, ...]]:
    """The figures of ``preset`` scaled to ``robot`` (see the module doc).

    Args:
        robot: The arm-alone model.
        preset: A name of ``IMPEDANCE_PRESETS``.

    Returns:
        {field: value} over ``DECLARED_FIELDS``; ``nullspace_damping`` one number when every
        joint's agrees, else one per joint (the cap is per joint).
    """
    ref = ImpedanceGains.preset(preset)
    fig = arm_figures(robot)
    s_m = fig.apparent_mass / REFERENCE_APPARENT_MASS
    s_l = fig.reach / REFERENCE_REACH
    cap = DAMPING_NUMBER * fig.joint_inertia / CONTROL_PERIOD
    d_n = np.minimum(np.asarray(ref.nullspace_damping) * s_m * s_l**2, cap)
    return {
        "stiffness": ref.stiffness[0] * s_m,
        "damping": ref.damping[0] * s_m,
        "nullspace_stiffness": float(np.asarray(ref.nullspace_stiffness) * s_m * s_l**2),
        "nullspace_damping": _one_or_each(d_n),
        "error_clip": ref.error_clip * s_l,
    }


def current_rate_limits(robot: Robot) -> float | tuple[float, ...]:
    """``ImpedanceGains().current_rate_limit`` (2000 A/s, meant for the Gen3 Lite's 11 A,
    ``DEFAULT_CURRENT_LIMIT``) scaled by each joint's current limit over 11 A.

    Args:
        robot: The arm's model.

    Returns:
        A/s, one number when all joints agree, else one per joint.
    """
    rate = ImpedanceGains().current_rate_limit
    return _one_or_each(rate * (current_limits(robot) / DEFAULT_CURRENT_LIMIT))


def impedance_gains(robot: Robot, preset: str = "tracking", **changes) -> ImpedanceGains:
    """``ImpedanceGains.preset(preset)`` for ``robot``: the figures its model declares, else
    the Gen3 Lite's scaled to it, with the current rate limit scaled to its current limits
    (see the module doc). For the Gen3 Lite this is exactly
    ``ImpedanceGains.preset(preset, **changes)``.

    Args:
        robot: The arm-alone model.
        preset: A name of ``IMPEDANCE_PRESETS``.
        **changes: ``ImpedanceGains`` fields to override.

    Returns:
        The gains.

    Raises:
        InputError: an unknown preset, base joints on ``robot``, or a bad field value.
        ModelError: a malformed declared preset, or no joint moving the end effector.
    """
    if preset not in IMPEDANCE_PRESETS:
        known = ", ".join(IMPEDANCE_PRESETS)
        raise InputError(f"unknown gains preset {preset!r}; presets: {known}")
    check_fixed_base(robot)
    figures = declared_preset(robot, preset)
    if figures is None:
        figures = derived_preset(robot, preset)
    values = {**figures, "current_rate_limit": current_rate_limits(robot)}
    values.update(changes)
    return ImpedanceGains.preset(preset, **values)


class GainLimits(NamedTuple):
    """The Cartesian gains a person may set (``jaxcomp control --stiffness``, the console):
    ``stiffness`` N/m and ``damping`` N s/m, the most per axis (0 the least)."""

    stiffness: float
    damping: float


def gain_limits(robot: Robot) -> GainLimits:
    """``robot``'s ``GainLimits``: stiffness up to ``STIFFNESS_LIMIT`` times its tracking
    preset's (Gen3 Lite: 1000 N/m); damping up to ``DAMPING_NUMBER`` m / T (m its apparent
    mass, T the 1 ms period: more rings with the loop's one-cycle delay; Gen3 Lite: 30.1
    N s/m), or the tracking preset's if that is higher.

    Args:
        robot: The arm-alone model.

    Returns:
        The most stiffness N/m and damping N s/m per axis.
    """
    tracking = impedance_gains(robot, "tracking")
    damping = DAMPING_NUMBER * arm_figures(robot).apparent_mass / CONTROL_PERIOD
    return GainLimits(
        STIFFNESS_LIMIT * max(tracking.stiffness), max(damping, max(tracking.damping))
    )


def check_live_gains(robot: Robot, stiffness, damping) -> tuple[float, float]:
    """Live Cartesian gains checked against ``gain_limits(robot)``.

    Args:
        robot: The arm-alone model.
        stiffness: N/m, one number for every axis.
        damping: N s/m, one number for every axis.

    Returns:
        (stiffness N/m, damping N s/m) as floats.

    Raises:
        InputError: a gain that is not a number or lies outside its safe range (named in
            the message).
    """
    limits = gain_limits(robot)
    checked = []
    for name, value, unit, most in (
        ("stiffness", stiffness, "N/m", limits.stiffness),
        ("damping", damping, "N s/m", limits.damping),
    ):
        x = checks.number(value, name, unit=unit)
        if not 0.0 <= x <= most:
            raise InputError(
                f"{name} {x:g} {unit} is outside the safe range 0-{most:.4g} {unit} for "
                f"{robot.name} ({_WHY[name]})"
            )
        checked.append(x)
    return checked[0], checked[1]


_WHY = {
    "stiffness": f"{STIFFNESS_LIMIT:g} times its tracking preset",
    "damping": f"damping x 1 ms / apparent mass at most {DAMPING_NUMBER:g}: more rings",
}


def _one_or_each(values: np.ndarray) -> float | tuple[float, ...]:
    values = np.asarray(values, dtype=float)
    if np.all(values == values[0]):
        return float(values[0])
    return tuple(float(v) for v in values)


__all__ = [
    "DAMPING_NUMBER",
    "DECLARED_FIELDS",
    "DECLARED_PRESET",
    "REFERENCE_APPARENT_MASS",
    "REFERENCE_REACH",
    "STIFFNESS_LIMIT",
    "ArmFigures",
    "GainLimits",
    "arm_figures",
    "check_live_gains",
    "current_rate_limits",
    "declared_preset",
    "derived_preset",
    "gain_limits",
    "impedance_gains",
]
