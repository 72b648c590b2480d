"""Motor current model of a current-controlled joint (paper Eq. 7, 13, 14, 15, 16).

Per joint: ratio r (A per N m, or A per N for a slide), friction loss l (A), threshold velocity
t (rad/s). Torques in N m, velocities in rad/s, currents in A. All functions are elementwise,
pure and jit/vmap/grad-able; arrays broadcast over joints.
"""

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


def torque_friction_current(tau: jax.Array, ratio: jax.Array, friction: jax.Array) -> jax.Array:
    """Eq. (14): c = r tau + sign(tau) l, friction compensated along the torque."""
    return ratio * tau + jnp.sign(tau) * friction


def velocity_friction_current(
    tau: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array
) -> jax.Array:
    """Eq. (15): c = r tau + sign(dq) l, friction compensated along the motion."""
    return ratio * tau + jnp.sign(dq) * friction


def blend(dq: jax.Array, threshold: jax.Array) -> jax.Array:
    """The weight min(|dq| / t, 1) of velocity-based compensation in Eq. (16)."""
    return jnp.minimum(jnp.abs(dq) / threshold, 1.0)


def current(
    tau: jax.Array, dq: jax.Array, ratio: jax.Array, friction: jax.Array, threshold: jax.Array
) -> jax.Array:
    """Eq. (16): c = r tau + l (a (sign dq - sign tau) + sign tau), a = min(|dq| / t, 1).

    Torque-based friction compensation at rest, velocity-based above the threshold velocity.
    """
    a = blend(dq, threshold)
    return ratio * tau + friction * (a * (jnp.sign(dq) - jnp.sign(tau)) + jnp.sign(tau))


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
