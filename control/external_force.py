"""The force a person (or anything else) applies on the end effector, from the motor currents.

A current-controlled arm has no force sensor, but its motors report their currents c (A). The
identified model (ratio r A/(N m), friction loss l A, gravity torque g(q) N m) predicts the
current the joints draw with nothing touching the arm; what a push adds shows as the
difference. Quasi-static (the arm's own inertial and Coriolis torques are neglected: slow,
guided motion; at the 5 cm/s of a tracked circle they are below 0.1 N), per joint, then
mapped to the end effector:

    c_model = r g(q) + a l sign(dq),  a = min(|dq| / t, 1)              A
    tau_ext = (c_model - c) / r                                         N m
    b       = (1 - a) l / r                                             N m
    F       = (J^T)^+ tau_ext,   (J^T)^+ = (J J^T + eps I)^-1 J          N
    B_i     = sum_j |(J^T)^+_ij| b_j                                    N

- c_model (``model_current``): the current the model predicts: gravity held, plus the
  kinetic friction of a joint moving faster than t (Eq. 16's velocity part); a joint at rest
  holds with static friction, which can take up any torque within +-l / r.
- tau_ext (``external_torque``): the torque the external force puts on each joint. The
  motors push back on whoever pushes: the torque they add beyond the model, (c - c_model) / r,
  is minus the external one.
- b (``friction_band``): what static friction may still be taking up at a joint (partly) at
  rest, so the true tau_ext lies within tau_ext +- b.
- F (``torque_to_force``): the force at the end-effector site whose joint torques J^T F fit
  tau_ext best (least squares over the joints: a force, no moment, is what a hand on the
  end effector applies), in the frame of J: the arm's base frame, N.
- B (``force_band``): the box F +- B (per axis, same frame) that holds every force whose
  joint torques lie within tau_ext +- b: the band a person at rest cannot be resolved within.

``external_force`` composes them (the impedance controller calls it in its jitted step).
Every function is pure and elementwise over joints; ``xp`` = ``numpy`` runs them on numpy.
"""

from __future__ import annotations

from types import ModuleType
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcomp.control.linalg import damped_pinv
from jaxcomp.current import blend, friction_current

#: m^2: damping of (J J^T + eps I)^-1 in the force map (J of a position, m/rad): keeps the map
#: finite at a singular pose, negligible against J J^T of an arm reaching tens of cm.
FORCE_MAP_DAMPING = 1e-6


def model_current(
    gravity_torque: jax.Array,
    dq: jax.Array,
    ratio: jax.Array,
    friction: jax.Array,
    threshold: float,
    xp: ModuleType = jnp,
) -> jax.Array:
    """c_model = r g(q) + a l sign(dq), a = min(|dq| / t, 1): Eq. (16)
    (``current.friction_current``) with no at-rest direction: a joint at rest holds with static
    friction, whatever its sign.

    Args:
        gravity_torque: g(q), (n,) N m.
        dq: Joint velocities, (n,) rad/s.
        ratio: r, (n,) A/(N m).
        friction: Friction loss l, (n,) A.
        threshold: t, rad/s, the speed above which a joint counts as moving.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        The predicted current, (n,) A.
    """
    no_rest_sign = xp.zeros_like(dq)
    return friction_current(gravity_torque, no_rest_sign, dq, ratio, friction, threshold, 0.0, xp)


def external_torque(current: jax.Array, current_model: jax.Array, ratio: jax.Array) -> jax.Array:
    """The torque on the joints from outside: tau_ext = (c_model - c) / r.

    Args:
        current: Measured motor currents c, (n,) A.
        current_model: c_model from ``model_current``, (n,) A.
        ratio: r, (n,) A/(N m).

    Returns:
        tau_ext, (n,) N m.
    """
    return (current_model - current) / ratio


def friction_band(
    dq: jax.Array,
    ratio: jax.Array,
    friction: jax.Array,
    threshold: float,
    xp: ModuleType = jnp,
) -> jax.Array:
    """b = (1 - a) l / r, the static friction a joint (partly) at rest may hold.

    Args:
        dq: Joint velocities, (n,) rad/s.
        ratio: r, (n,) A/(N m).
        friction: Friction loss l, (n,) A.
        threshold: t, rad/s.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        b, (n,) N m.
    """
    return (1.0 - blend(dq, threshold, xp)) * friction / ratio


def torque_to_force(jac: jax.Array, xp: ModuleType = jnp) -> jax.Array:
    """(J^T)^+ = (J J^T + eps I)^-1 J, eps = ``FORCE_MAP_DAMPING``.

    Args:
        jac: The site's position Jacobian J, (3, n) m/rad.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        (3, n), maps joint torques N m to a force N in J's frame.
    """
    return damped_pinv(jac, FORCE_MAP_DAMPING, xp).T


def force_band(force_map: jax.Array, band: jax.Array, xp: ModuleType = jnp) -> jax.Array:
    """B = |(J^T)^+| b, the per-axis half width of the forces whose joint torques lie within
    +-b of the estimate's.

    Args:
        force_map: (J^T)^+ from ``torque_to_force``, (3, n).
        band: b from ``friction_band``, (n,) N m.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        B, (3,) N, in the force map's frame.
    """
    return xp.abs(force_map) @ band


class ExternalForce(NamedTuple):
    """The estimate at one instant: ``current_model`` (n,) A, ``force`` (3,) N and its
    ``band`` (3,) N (per axis, force +- band), in the frame of the Jacobian given."""

    current_model: jax.Array
    force: jax.Array
    band: jax.Array


def external_force(
    jac: jax.Array,
    gravity_torque: jax.Array,
    dq: jax.Array,
    current: jax.Array,
    ratio: jax.Array,
    friction: jax.Array,
    threshold: float,
    xp: ModuleType = jnp,
) -> ExternalForce:
    """The external force on the end-effector site (see the module doc).

    Args:
        jac: The site's position Jacobian, (3, n) m/rad, in the frame wanted (the controller's:
            the arm's base frame).
        gravity_torque: g(q), (n,) N m.
        dq: Joint velocities, (n,) rad/s.
        current: Measured motor currents, (n,) A.
        ratio: (n,) A/(N m).
        friction: Friction loss, (n,) A.
        threshold: rad/s, the speed above which a joint counts as moving.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        The model current (n,) A, the force (3,) N and its band (3,) N, in the frame of ``jac``.
    """
    c_model = model_current(gravity_torque, dq, ratio, friction, threshold, xp)
    force_map = torque_to_force(jac, xp)
    tau = external_torque(current, c_model, ratio)
    band = force_band(force_map, friction_band(dq, ratio, friction, threshold, xp), xp)
    return ExternalForce(c_model, force_map @ tau, band)


__all__ = [
    "FORCE_MAP_DAMPING",
    "ExternalForce",
    "external_force",
    "external_torque",
    "force_band",
    "friction_band",
    "model_current",
    "torque_to_force",
]
