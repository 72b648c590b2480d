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


def test_viscous_sweep_current_adds_b_v_to_eq13():
    rng = np.random.default_rng(1)
    tau, v, b = rng.normal(0, 2, 3), rng.normal(0, 0.5, 3), np.array([0.02, 0.0, 0.1])
    d = np.sign(v)
    expected = np.asarray(R) * tau + np.asarray(L) * d + b * v
    got = current.viscous_sweep_current(tau, d, v, R, L, b)
    np.testing.assert_allclose(got, expected, rtol=1e-14)
    np.testing.assert_array_equal(
        current.viscous_sweep_current(tau, d, v, R, L, 0.0 * b), current.sweep_current(tau, d, R, L)
    )


def test_rest_sign_is_sign_or_a_clipped_ramp():
    x = np.array([-1.0, -0.02, -1e-9, 0.0, 1e-9, 0.03, 2.0])
    np.testing.assert_array_equal(current.rest_sign(x, 0.0, np), np.sign(x))
    np.testing.assert_allclose(current.rest_sign(x, 0.05, np), np.clip(x / 0.05, -1, 1))
    np.testing.assert_allclose(current.rest_sign(jnp.asarray(x), 0.05), np.clip(x / 0.05, -1, 1))


def test_friction_current_general_form():
    """c = r tau + l (a (sign dq - s) + s), s from tau_rest (banded), on numpy and JAX."""
    rng = np.random.default_rng(2)
    r, l = np.asarray(R), np.asarray(L)
    for band in (0.0, 0.1):
        tau, rest = rng.normal(0, 1, (200, 3)), rng.normal(0, 0.2, (200, 3))
        dq = rng.normal(0, 0.3, (200, 3)) * rng.integers(0, 2, (200, 3))  # some at rest
        a = np.minimum(np.abs(dq) / T, 1.0)
        s = np.sign(rest) if band == 0 else np.clip(rest / band, -1.0, 1.0)
        expected = r * tau + l * (a * (np.sign(dq) - s) + s)
        got_np = current.friction_current(tau, rest, dq, r, l, T, band, np)
        assert isinstance(got_np, np.ndarray)
        np.testing.assert_allclose(got_np, expected, rtol=1e-13, atol=1e-15)
        got = current.friction_current(jnp.asarray(tau), rest, dq, R, L, T, band)
        np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-15)
    # the paper's Eq. (16) is its special case
    np.testing.assert_array_equal(
        current.friction_current(tau, tau, dq, R, L, T), current.current(tau, dq, R, L, T)
    )
