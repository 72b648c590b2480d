"""The current model of Eq. (7), (13)-(16) and its inverse."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import current

R = jnp.array([1.0282, 0.3074, 1.9074])
L = jnp.array([0.5318, 1.4776, 0.3013])
T = 0.3


def test_eq16_limits_are_eq14_at_rest_and_eq15_when_moving():
    tau = jnp.array([0.7, -1.2, 0.05])
    at_rest = current.current(tau, jnp.zeros(3), R, L, T)
    np.testing.assert_allclose(at_rest, current.torque_friction_current(tau, R, L))
    dq = jnp.array([-0.5, 0.4, -2.0])  # above the threshold, against the torque
    moving = current.current(tau, dq, R, L, T)
    np.testing.assert_allclose(moving, current.velocity_friction_current(tau, dq, R, L))
    np.testing.assert_allclose(moving, R * tau + L * jnp.sign(dq))


def test_eq16_blends_linearly_below_threshold():
    tau, dq = jnp.array([1.0, 1.0, 1.0]), jnp.array([-0.075, -0.15, -0.225])  # a = 1/4, 1/2, 3/4
    a = np.array([0.25, 0.5, 0.75])
    expected = np.asarray(R) + np.asarray(L) * (a * (-1 - 1) + 1)
    np.testing.assert_allclose(current.current(tau, dq, R, L, T), expected, rtol=1e-12)


def test_inverse_round_trips_and_has_a_dead_zone():
    rng = np.random.default_rng(0)
    tau = jnp.asarray(rng.normal(0, 2, (500, 3)))
    dq = jnp.asarray(rng.normal(0, 0.4, (500, 3)))
    c = current.current(tau, dq, R, L, T)
    np.testing.assert_allclose(current.current_to_torque(c, dq, R, L, T), tau, atol=1e-12)
    # at rest, currents smaller than the friction loss produce no torque
    np.testing.assert_allclose(current.current_to_torque(0.9 * L, jnp.zeros(3), R, L, T), 0.0)


def test_sweep_current_is_eq13_and_differentiable():
    tau = jnp.array([0.5, -0.5, 1.0])
    d = jnp.array([1.0, -1.0, -1.0])
    np.testing.assert_allclose(current.sweep_current(tau, d, R, L), R * tau + L * d)
    grad_r = jax.grad(lambda r: current.sweep_current(tau, d, r, L).sum())(R)
    np.testing.assert_allclose(grad_r, tau)
