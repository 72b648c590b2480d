"""Motor current model of a current-controlled joint (paper Eq. 7, 13, 14, 15, 16).

Per joint: ratio r (A per N m, or A per N for a slide), friction loss l (A), threshold velocity
t (rad/s), viscous coefficient b (A s/rad). Torques in N m, velocities in rad/s (N and m/s for
a slide), currents in A. All functions are elementwise and pure; arrays broadcast over joints.
They are jit/vmap/grad-able JAX functions; those that take ``xp`` run on numpy arrays too with
``xp=numpy`` (the pinocchio controller's).

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
    """Eq. (7): c = r tau, a frictionless actuator.

    Args:
        tau: joint torque, N m.
        ratio: r, A/(N m).

    Returns:
        c, A.
    """
    return ratio * tau


def sweep_current(
    tau: jax.Array, direction: jax.Array, ratio: jax.Array, friction: jax.Array
) -> jax.Array:
    """Eq. (13): c = r tau + l d, the current of a joint moving in direction d (+1 or -1).

    Args:
        tau: the torque the actuator applies, N m (for a slow sweep: g(q), the gravity torque).
        direction: d, +1 or -1.
        ratio: r, A/(N m).
        friction: l, the friction loss, A.

    Returns:
        c, A.
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

    Args:
        tau: the torque the actuator applies, N m.
        direction: d, +1 or -1.
        velocity: v, the joint's velocity, rad/s (in a sweep: its speed times d).
        ratio: r, A/(N m).
        friction: l, the friction loss, A.
        viscous: b, A s/rad (a viscous torque coefficient in N m s/rad times r).

    Returns:
        c, A.
    """
    return sweep_current(tau, direction, ratio, friction) + viscous * velocity


def torque_friction_current(tau: jax.Array, ratio: jax.Array, friction: jax.Array) -> jax.Array:
    """Eq. (14): c = r tau + sign(tau) l, friction compensated along the torque.

    Args:
        tau: joint torque, N m.
        ratio: r, A/(N m).
        friction: l, the friction loss, A.

    Returns:
        c, A.
    """
    return ratio * tau + jnp.sign(tau) * friction


def velocity_friction_current(
    tau: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array
) -> jax.Array:
    """Eq. (15): c = r tau + sign(dq) l, friction compensated along the motion.

    Args:
        tau: joint torque, N m.
        dq: joint velocity, rad/s.
        ratio: r, A/(N m).
        friction: l, the friction loss, A.

    Returns:
        c, A.
    """
    return ratio * tau + jnp.sign(dq) * friction


def blend(dq: jax.Array, threshold: jax.Array | float, xp: ModuleType = jnp) -> jax.Array:
    """The weight a = min(|dq| / t, 1) of velocity-based compensation in Eq. (16).

    Args:
        dq: joint velocity, rad/s.
        threshold: t, rad/s.
        xp: the array module, ``jax.numpy`` or ``numpy``.

    Returns:
        a, in [0, 1].
    """
    return xp.minimum(xp.abs(dq) * (1.0 / threshold), 1.0)


def rest_sign(x: jax.Array, band: float = 0.0, xp: ModuleType = jnp) -> jax.Array:
    """sign(x), or with ``band`` > 0 (same unit as x) its continuous version clip(x / band,
    -1, 1).

    Args:
        x: the values.
        band: the width of the linear band, x's unit; 0 for the plain sign.
        xp: the array module, ``jax.numpy`` or ``numpy``.

    Returns:
        Values in [-1, 1], x's shape.
    """
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

    Args:
        tau: joint torque to command, N m.
        tau_rest: the torque whose sign s gives the friction direction at rest, N m.
        dq: joint velocity, rad/s.
        ratio: r, A/(N m).
        friction: l, the friction loss, A.
        threshold: t, rad/s.
        band: the friction band of ``rest_sign``, N m; 0 for the plain sign.
        xp: the array module, ``jax.numpy`` or ``numpy``.

    Returns:
        c, A.
    """
    a = blend(dq, threshold, xp)
    s = rest_sign(tau_rest, band, xp)
    return ratio * tau + friction * (a * (xp.sign(dq) - s) + s)


def current(
    tau: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array, threshold: jax.Array
) -> jax.Array:
    """Eq. (16): c = r tau + l (a (sign dq - sign tau) + sign tau), a = min(|dq| / t, 1).

    Torque-based friction compensation at rest, velocity-based above the threshold velocity.

    Args:
        tau: joint torque, N m.
        dq: joint velocity, rad/s.
        ratio: r, A/(N m).
        friction: l, the friction loss, A.
        threshold: t, rad/s.

    Returns:
        c, A.
    """
    return friction_current(tau, tau, dq, ratio, friction, threshold)


def current_to_torque(
    c: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array, threshold: jax.Array
) -> jax.Array:
    """Inverse of Eq. (16): the torque tau whose commanded current is c.

    Eq. (16) is increasing in tau with a step of 2 l (1 - a) at tau = 0; currents inside that
    step map to tau = 0.

    Args:
        c: commanded current, A.
        dq: joint velocity, rad/s.
        ratio: r, A/(N m).
        friction: l, the friction loss, A.
        threshold: t, rad/s.

    Returns:
        tau, N m.
    """
    a = blend(dq, threshold)
    y = c - friction * a * jnp.sign(dq)
    step = friction * (1.0 - a)
    return jnp.where(y > step, (y - step) / ratio, jnp.where(y < -step, (y + step) / ratio, 0.0))
