"""Motor current model of a current-controlled joint (paper Eq. 7, 13, 14, 15, 16).

Per joint: ratio r (A per N m, or A per N for a slide), friction loss l (A), threshold velocity
t (rad/s), viscous coefficient b (A s/rad). Torques in N m, velocities in rad/s, currents in A.
All functions are elementwise and pure; arrays broadcast over joints. They are jit/vmap/grad-able
JAX functions; those that take ``xp`` run on numpy arrays too with ``xp=numpy`` (the pinocchio
controller's).

    Eq. (7)   torque_to_current            c = r tau
    Eq. (13)  sweep_current                c = r tau + l d
              viscous_sweep_current        c = r tau + l d + b v  (the joint fit's model)
    Eq. (14)  torque_friction_current      c = r tau + l sign(tau)
    Eq. (15)  velocity_friction_current    c = r tau + l sign(dq)
    Eq. (16)  current                      c = r tau + l (a (sign dq - sign tau) + sign tau)
              friction_current             Eq. (16) with the at-rest direction taken from any
                                           torque, optionally made continuous (the controller's)
              current_to_torque            the inverse of Eq. (16)
"""

from types import ModuleType

import jax
import jax.numpy as jnp


def torque_to_current(tau: jax.Array, ratio: jax.Array) -> jax.Array:
    """Eq. (7): c = r tau, a frictionless actuator."""
    return ratio * tau


def sweep_current(
    tau: jax.Array, direction: jax.Array, ratio: jax.Array, friction: jax.Array
) -> jax.Array:
    """Eq. (13): c = r tau + l d, the current of a joint moving in direction d (+1 or -1).

    ``tau`` is the torque the actuator applies (for a slow sweep: g(q), the gravity torque).
    """
    return ratio * tau + friction * direction


def viscous_sweep_current(
    tau: jax.Array,
    direction: jax.Array,
    velocity: jax.Array,
    ratio: jax.Array,
    friction: jax.Array,
    viscous: jax.Array,
) -> jax.Array:
    """Eq. (13) plus viscous friction: c = r tau + l d + b v, the joint fit's model.

    ``velocity`` v (rad/s) is the joint's speed in direction d; ``viscous`` b in A s/rad (a
    viscous torque coefficient in N m s/rad times r).
    """
    return sweep_current(tau, direction, ratio, friction) + viscous * velocity


def torque_friction_current(tau: jax.Array, ratio: jax.Array, friction: jax.Array) -> jax.Array:
    """Eq. (14): c = r tau + sign(tau) l, friction compensated along the torque."""
    return ratio * tau + jnp.sign(tau) * friction


def velocity_friction_current(
    tau: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array
) -> jax.Array:
    """Eq. (15): c = r tau + sign(dq) l, friction compensated along the motion."""
    return ratio * tau + jnp.sign(dq) * friction


def blend(dq: jax.Array, threshold: jax.Array | float, xp: ModuleType = jnp) -> jax.Array:
    """The weight a = min(|dq| / t, 1) of velocity-based compensation in Eq. (16)."""
    return xp.minimum(xp.abs(dq) * (1.0 / threshold), 1.0)


def rest_sign(x: jax.Array, band: float = 0.0, xp: ModuleType = jnp) -> jax.Array:
    """sign(x), or with ``band`` > 0 (same unit as x) its continuous version clip(x / band,
    -1, 1)."""
    if band > 0:
        return xp.clip(x * (1.0 / band), -1.0, 1.0)
    return xp.sign(x)


def friction_current(
    tau: jax.Array,
    tau_rest: jax.Array,
    dq: jax.Array,
    ratio: jax.Array,
    friction: jax.Array,
    threshold: jax.Array | float,
    band: float = 0.0,
    xp: ModuleType = jnp,
) -> jax.Array:
    """Eq. (16) with its at-rest direction taken from ``tau_rest`` (N m):

        c = r tau + l (a (sign dq - s) + s),  a = min(|dq| / t, 1),  s = rest_sign(tau_rest)

    With ``tau_rest`` = tau and ``band`` = 0 it is the paper's Eq. (16) (``current``). The
    impedance controller's "motion" direction passes the torque beyond gravity compensation
    as ``tau_rest``, and a friction band makes s continuous where it crosses zero.
    """
    a = blend(dq, threshold, xp)
    s = rest_sign(tau_rest, band, xp)
    return ratio * tau + friction * (a * (xp.sign(dq) - s) + s)


def current(
    tau: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array, threshold: jax.Array
) -> jax.Array:
    """Eq. (16): c = r tau + l (a (sign dq - sign tau) + sign tau), a = min(|dq| / t, 1).

    Torque-based friction compensation at rest, velocity-based above the threshold velocity.
    """
    return friction_current(tau, tau, dq, ratio, friction, threshold)


def current_to_torque(
    c: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array, threshold: jax.Array
) -> jax.Array:
    """Inverse of Eq. (16): the torque tau whose commanded current is c.

    Eq. (16) is increasing in tau with a step of 2 l (1 - a) at tau = 0; currents inside that
    step map to tau = 0.
    """
    a = blend(dq, threshold)
    y = c - friction * a * jnp.sign(dq)
    step = friction * (1.0 - a)
    return jnp.where(y > step, (y - step) / ratio, jnp.where(y < -step, (y + step) / ratio, 0.0))
