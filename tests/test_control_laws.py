"""Control laws: impedance controller (Eq. 3-5, 16) against pinocchio and its defining
properties, the reference velocity controller, and the base follower (Eq. 20)."""

import math

import jax
import numpy as np
import pytest

import jaxcomp
from jaxcomp import current as current_model
from jaxcomp.control import (
    BaseFollower,
    BaseGains,
    Diagnostics,
    ImpedanceControllerPinocchio,
    ImpedanceGains,
    VelocityGains,
    follow_twist,
    make_impedance_controller,
    make_velocity_controller,
)
from jaxcomp.control.impedance_terms import limit_current
from jaxcomp.current import friction_current
from jaxcomp.errors import InputError
from jaxcomp.hardware.mecanum import TwistLimits
from jaxcomp.robot_params import RobotParams

SITE = "end_effector"


@pytest.fixture(scope="module")
def robot():
    return jaxcomp.load_robot("gen3_lite")


@pytest.fixture(scope="module")
def params(robot):
    """Paper-like identified params with COM offsets of a few mm."""
    return RobotParams(
        model=robot.name,
        ratio=[1.0282, 0.3074, 1.0282, 1.9074, 2.0373, 1.9724],
        friction=[0.5318, 1.4776, 0.6695, 0.3013, 0.3732, 0.5923],
        com_offset={"ARM": [0.002, -0.001, 0.003], "FOREARM": [-0.003, 0.002, 0.001]},
        method="test",
    )


@pytest.fixture(scope="module")
def ctrl(robot, params):
    c = make_impedance_controller(robot, params, ImpedanceGains())
    c.compile()
    return c


@pytest.fixture(scope="module")
def pin_ctrl(robot, params):
    return ImpedanceControllerPinocchio(robot, params, ImpedanceGains())


@pytest.fixture(scope="module")
def identified_gravity(robot, params):
    inertial = params.inertial_params(robot)
    return lambda q: np.asarray(robot.gravity(q, inertial))


def _random_state(robot, rng):
    lo, hi = robot.joint_limits.T
    q = rng.uniform(lo, hi)
    x = np.asarray(robot.site_position(q, SITE))
    return q, rng.normal(0, 1.0, 6), x + rng.normal(0, 0.06, 3)


def _step(ctrl, q, dq, target, vel=None, acc=None, prev=None, rot=None):
    cur, diag = ctrl.checked_step(q, dq, target, vel, acc, prev, rot)
    return np.asarray(cur), diag.numpy()


def _quiet_prev(ctrl, q, dq, target, vel=None, acc=None, rot=None):
    """prev_current equal to the unlimited command, so the rate limit does not act."""
    _, diag = _step(ctrl, q, dq, target, vel, acc, None, rot)
    return diag.current_raw


# ----------------------------------------------------------------------------- impedance


def test_jax_matches_pinocchio_on_random_states(robot, ctrl, pin_ctrl):
    rng = np.random.default_rng(1)
    for _ in range(100):
        q, dq, target = _random_state(robot, rng)
        vel, acc, prev = rng.normal(0, 0.1, 3), rng.normal(0, 0.2, 3), rng.normal(0, 3, 6)
        cur, diag = _step(ctrl, q, dq, target, vel, acc, prev)
        cur_p, diag_p = pin_ctrl.step(q, dq, target, vel, acc, prev)
        np.testing.assert_allclose(cur, cur_p, rtol=0, atol=1e-9)
        np.testing.assert_allclose(diag.data, diag_p.data, rtol=0, atol=1e-9)


def test_feedforward_and_orientation_match_pinocchio(robot, params):
    gains = ImpedanceGains(
        feedforward=True, orientation_stiffness=2.0, orientation_damping=0.2, deadband=0.0
    )
    ctrl = make_impedance_controller(robot, params, gains)
    pin_ctrl = ImpedanceControllerPinocchio(robot, params, gains)
    rng = np.random.default_rng(2)
    for _ in range(20):
        q, dq, target = _random_state(robot, rng)
        vel, acc, prev = rng.normal(0, 0.1, 3), rng.normal(0, 0.5, 3), rng.normal(0, 3, 6)
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        cur, diag = _step(ctrl, q, dq, target, vel, acc, prev, rot)
        cur_p, diag_p = pin_ctrl.step(q, dq, target, vel, acc, prev, rot)
        np.testing.assert_allclose(cur, cur_p, rtol=0, atol=1e-9)
        np.testing.assert_allclose(diag.data, diag_p.data, rtol=0, atol=1e-9)
    with pytest.raises(InputError, match="target_rot"):
        ctrl.check_state(q, dq, target)


def test_tracking_gains_match_pinocchio_and_packed_step_matches_step(robot, params):
    """The motion-torque friction direction with its linear zone, in both implementations,
    and the loop's packed step against the step."""
    gains = ImpedanceGains.tracking()
    ctrl = make_impedance_controller(robot, params, gains)
    pin_ctrl = ImpedanceControllerPinocchio(robot, params, gains)
    rng = np.random.default_rng(3)
    for k in range(50):
        q, dq, target = _random_state(robot, rng)
        dq = dq * (0.01 if k % 2 else 1.0)  # inside and beyond the threshold velocity
        vel, acc, prev = rng.normal(0, 0.1, 3), rng.normal(0, 0.2, 3), rng.normal(0, 3, 6)
        cur, diag = _step(ctrl, q, dq, target, vel, acc, prev)
        cur_p, diag_p = pin_ctrl.step(q, dq, target, vel, acc, prev)
        np.testing.assert_allclose(cur, cur_p, rtol=0, atol=1e-9)
        np.testing.assert_allclose(diag.data, diag_p.data, rtol=0, atol=1e-9)
        out = np.asarray(ctrl.packed_step(ctrl.pack(q, dq, prev, target, vel, acc)))
        assert ctrl.packed_size == 40 and out.shape == (6 + 46,)  # current | diagnostics
        np.testing.assert_allclose(out[:6], cur, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out[6:], diag.data, rtol=0, atol=1e-12)


def test_friction_direction_at_rest(robot, params):
    """Eq. (16) at rest: "torque" pushes l along sign(tau) (a gravity-loaded joint along its
    gravity torque, whatever the spring asks); "motion" along the torque beyond gravity, and
    continuously through zero with a friction band."""
    r, l = np.asarray(params.ratio), np.asarray(params.friction)
    tau = np.array([0.2, 5.0, -3.0, 0.01, -0.02, 0.0])  # N m
    g = np.array([0.0, 5.5, -2.5, 0.0, 0.0, 0.0])  # N m: joints 1, 2 carry gravity
    dq = np.zeros(6)
    paper = friction_current(tau, tau, dq, r, l, 0.3, 0.0, np)
    np.testing.assert_allclose(paper, current_model.current(tau, dq, r, l, 0.3), atol=1e-15)
    np.testing.assert_allclose(paper - r * tau, l * np.sign(tau))
    motion = friction_current(tau, tau - g, dq, r, l, 0.3, 0.0, np)
    np.testing.assert_allclose(motion - r * tau, l * np.sign(tau - g))  # joints 1, 2 flip
    band = friction_current(tau, tau - g, dq, r, l, 0.3, 0.05, np)
    np.testing.assert_allclose(band - r * tau, l * np.clip((tau - g) / 0.05, -1, 1))
    moving = friction_current(tau, tau - g, np.full(6, 0.5), r, l, 0.3, 0.05, np)
    np.testing.assert_allclose(moving - r * tau, l)  # beyond t: along the motion only
    ctrl = make_impedance_controller(robot, params, ImpedanceGains.tracking())
    q = ctrl.joint.posture  # at the target and the posture: no torque but gravity
    cur, diag = _step(ctrl, q, dq, np.asarray(robot.site_position(q, SITE)), prev=None)
    np.testing.assert_allclose(diag.current_raw, r * diag.tau, atol=1e-12)  # no kick at rest


def test_gain_presets():
    assert ImpedanceGains.paper() == ImpedanceGains() == ImpedanceGains.preset("paper")
    t = ImpedanceGains.tracking()
    assert t == ImpedanceGains.preset("tracking")
    assert t.stiffness == (400.0,) * 3 and t.damping == (30.0,) * 3
    assert t.friction_direction == "motion" and t.friction_threshold == 0.02
    assert t.friction_band == 0.05 and t.nullspace_damping == 0.3 and not t.feedforward
    assert ImpedanceGains.tracking(stiffness=200.0).stiffness == (200.0,) * 3
    assert ImpedanceGains().friction_direction == "torque" and ImpedanceGains().friction_band == 0
    with pytest.raises(InputError, match="unknown gains preset"):
        ImpedanceGains.preset("stiff")
    with pytest.raises(InputError, match="friction_direction"):
        ImpedanceGains(friction_direction="velocity")
    with pytest.raises(InputError, match="friction_band"):
        ImpedanceGains(friction_band=-0.1)


def test_at_target_at_rest_current_is_eq16_of_gravity(robot, params, ctrl, identified_gravity):
    q, dq = ctrl.joint.posture, np.zeros(6)  # at the posture: no nullspace torque either
    target = np.asarray(robot.site_position(q, SITE))
    g = identified_gravity(q)
    t = ctrl.gains.friction_threshold
    expected = np.asarray(current_model.current(g, dq, params.ratio, params.friction, t))
    assert np.abs(expected).max() > 0.5  # gravity loads the arm here
    cur, diag = _step(ctrl, q, dq, target, prev=expected)
    np.testing.assert_allclose(diag.error, 0.0, atol=1e-12)
    np.testing.assert_allclose(diag.force, 0.0, atol=1e-12)
    np.testing.assert_allclose(diag.tau, g, atol=1e-12)
    np.testing.assert_allclose(cur, expected, atol=1e-12)
    assert not diag.rate_limited.any() and not diag.saturated.any()


def test_cartesian_error_gives_stiffness_force(robot, ctrl, identified_gravity):
    q = ctrl.joint.posture  # zero posture torque at rest
    x = np.asarray(robot.site_position(q, SITE))
    jac = np.asarray(robot.jacobian(q, SITE))[:3]
    k_d = np.asarray(ctrl.gains.stiffness)
    for e in ([0.02, -0.03, 0.01], [0.0, 0.0, 0.05], [-0.04, 0.01, -0.02]):
        e = np.asarray(e)
        _, diag = _step(ctrl, q, np.zeros(6), x + e)
        np.testing.assert_allclose(diag.error, e, atol=1e-12)
        np.testing.assert_allclose(diag.force, k_d * e, atol=1e-12)
        # tau - g = J^T F: the force recovered through the pseudo-inverse of J^T is K_d e
        f_rec = np.linalg.lstsq(jac.T, diag.tau - identified_gravity(q), rcond=None)[0]
        np.testing.assert_allclose(f_rec, k_d * e, atol=1e-9)
        assert not diag.clipped


def test_error_clipped_at_error_clip(robot, ctrl):
    q = ctrl.joint.posture
    x = np.asarray(robot.site_position(q, SITE))
    e = np.array([0.3, -0.2, 0.1])
    _, diag = _step(ctrl, q, np.zeros(6), x + e)
    assert diag.clipped
    np.testing.assert_allclose(np.linalg.norm(diag.error), ctrl.gains.error_clip, atol=1e-12)
    np.testing.assert_allclose(diag.error, 0.1 * e / np.linalg.norm(e), atol=1e-12)
    np.testing.assert_allclose(diag.force, 40.0 * diag.error, atol=1e-12)


def test_deadband(robot, ctrl):
    q = ctrl.joint.posture
    x = np.asarray(robot.site_position(q, SITE))
    u = np.array([1.0, 2.0, -2.0]) / 3.0
    _, inside = _step(ctrl, q, np.zeros(6), x + 0.0009 * u)
    np.testing.assert_allclose(inside.error, 0.0, atol=0)
    np.testing.assert_allclose(inside.force, 0.0, atol=1e-15)
    _, outside = _step(ctrl, q, np.zeros(6), x + 0.0011 * u)
    np.testing.assert_allclose(outside.error, 0.0011 * u, atol=1e-12)


def test_nullspace_torque_causes_no_task_acceleration(robot, params, ctrl, identified_gravity):
    rng = np.random.default_rng(4)
    inertial = params.inertial_params(robot)
    for _ in range(10):
        q, dq, target = _random_state(robot, rng)
        _, diag = _step(ctrl, q, dq, target)
        jac = np.asarray(robot.jacobian(q, SITE))[:3]
        mass = np.asarray(robot.mass_matrix(q, inertial))
        tau_null = diag.tau - identified_gravity(q) - jac.T @ diag.force  # = N^T tau_2
        tau2 = ctrl.joint.stiffness * (ctrl.joint.posture - q) - ctrl.joint.damping * dq
        assert np.linalg.norm(tau_null) > 1e-3 * np.linalg.norm(tau2)  # not vacuous
        acc = jac @ np.linalg.solve(mass, tau_null)  # J M^-1 N^T tau_2
        scale = np.linalg.norm(jac @ np.linalg.solve(mass, tau2))
        assert np.linalg.norm(acc) <= 1e-5 * scale  # 0 up to the singularity damping


def test_rate_limit_and_saturation(robot, ctrl):
    q = ctrl.joint.posture
    x = np.asarray(robot.site_position(q, SITE))
    raw = _quiet_prev(ctrl, q, np.zeros(6), x)
    step_a = ctrl.gains.max_current_step  # 2 A per 1 ms cycle
    assert step_a == pytest.approx(2.0)
    prev = raw + np.array([5.0, -5.0, 1.0, -1.0, 0.0, 3.0])
    cur, diag = _step(ctrl, q, np.zeros(6), x, prev=prev)
    np.testing.assert_allclose(diag.rate_limited, [1, 1, 0, 0, 0, 1])
    np.testing.assert_allclose(cur[[0, 1, 5]], prev[[0, 1, 5]] - np.array([2.0, -2.0, 2.0]))
    np.testing.assert_allclose(cur[[2, 3, 4]], raw[[2, 3, 4]], atol=1e-12)
    assert not diag.saturated.any()
    prev = np.array([14.0, -14.0, 12.0, 0.0, 0.0, 0.0])  # beyond the 11 A limit
    cur, diag = _step(ctrl, q, np.zeros(6), x, prev=prev)
    np.testing.assert_allclose(cur[:3], [11.0, -11.0, 10.0])
    np.testing.assert_allclose(diag.saturated, [1, 1, 0, 0, 0, 0])
    assert np.all(np.abs(cur) <= 11.0)
    c, rl, sat = limit_current(np.array([20.0, -3.0]), np.array([19.5, 0.0]), 2.0, 11.0, np)
    np.testing.assert_allclose(c, [11.0, -2.0])
    assert list(rl) == [False, True] and list(sat) == [True, False]


def test_check_state_rejects_bad_inputs(ctrl):
    q, x = ctrl.joint.posture, np.zeros(3)
    with pytest.raises(InputError, match=r"q \(rad\) contains NaN .*joint_2"):
        ctrl.check_state(np.where(np.arange(6) == 2, np.nan, q), np.zeros(6), x)
    with pytest.raises(InputError, match=r"dq \(rad/s\) must have shape \(6,\)"):
        ctrl.check_state(q, np.zeros(5), x)
    with pytest.raises(InputError, match=r"target_pos must have shape \(3,\)"):
        ctrl.check_state(q, np.zeros(6), np.zeros(2))
    with pytest.raises(InputError, match="target_vel contains NaN"):
        ctrl.check_state(q, np.zeros(6), x, [0.0, np.inf, 0.0])
    with pytest.raises(InputError, match="current"):
        ctrl.check_state(q, np.zeros(6), x, None, None, np.zeros(7))
    state = ctrl.check_state(q, np.zeros(6), x)
    assert len(state) == 6 and all(isinstance(a, jax.Array) for a in state)


def test_step_takes_its_own_output(robot, ctrl):
    q = ctrl.joint.posture
    x = np.asarray(robot.site_position(q, SITE)) + 0.05
    args = ctrl.check_state(q, np.zeros(6), x)
    cur, diag = ctrl.step(*args)
    cur2, diag2 = ctrl.step(*args[:5], cur)  # the loop passes the last command back in
    assert isinstance(diag, Diagnostics) and cur2.shape == (6,) and diag2.n == 6
    np.testing.assert_allclose(diag2.numpy().current_raw, diag.numpy().current_raw)


def test_gains_validation(robot):
    with pytest.raises(InputError, match="stiffness"):
        ImpedanceGains(stiffness=(-1.0, 40.0, 40.0))
    with pytest.raises(InputError, match="deadband"):
        ImpedanceGains(deadband=0.2)
    with pytest.raises(InputError, match="current_rate_limit"):
        ImpedanceGains(current_rate_limit=0.0)
    with pytest.raises(InputError, match="posture has 3 values"):
        ImpedanceGains(posture=(0.0, 0.1, 0.2)).joint_arrays(robot)
    with pytest.raises(InputError, match="no field"):
        ImpedanceGains().replace(stifness=1.0)
    with pytest.raises(InputError, match="feedforward"):
        ImpedanceGains(feedforward="yes")
    with pytest.raises(InputError, match="base joints"):
        ImpedanceGains().joint_arrays(jaxcomp.load_robot("mobile_gen3_lite"))
    g = ImpedanceGains()
    assert g.stiffness == (40.0, 40.0, 40.0) and g.damping == (3.0, 3.0, 3.0)
    assert not g.orientation and not g.feedforward
    joint = g.joint_arrays(robot)
    np.testing.assert_allclose(joint.posture, robot.pose("preferred"))
    np.testing.assert_allclose(joint.stiffness, 0.125)
    np.testing.assert_allclose(joint.damping, 0.025)
    np.testing.assert_allclose(joint.limit, 11.0)
    assert g.replace(stiffness=10.0).stiffness == (10.0, 10.0, 10.0)
    with pytest.raises(InputError, match="yaw_joint"):
        BaseGains(yaw_joint=-1)
    with pytest.raises(InputError, match="joint_velocity_limit"):
        VelocityGains(joint_velocity_limit=0.0)


def test_params_must_match_robot(robot):
    other = RobotParams(model="other", ratio=np.ones(6), friction=np.zeros(6))
    with pytest.raises(InputError, match="model 'other'"):
        ImpedanceControllerPinocchio(robot, other)
    nominal = ImpedanceControllerPinocchio(robot)  # params None: nominal ratios, no friction
    q = robot.pose("home")
    cur, _ = nominal.step(q, np.zeros(6), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(6))
    assert np.all(np.isfinite(cur)) and np.all(np.abs(cur) <= 2.0 + 1e-12)  # rate limit from 0


# ----------------------------------------------------------------------------- velocity


def test_velocity_controller_converges_in_kinematic_simulation(robot):
    gains = VelocityGains()
    ctrl = make_velocity_controller(robot, gains)
    dt = 0.001
    q = robot.pose("home")
    target = np.asarray(robot.site_position(q, SITE)) + np.array([0.06, -0.05, 0.04])
    target_dev = ctrl.check_state(q, target)[1]
    zero = ctrl.check_state(q, target)[2]
    limit = np.asarray(gains.joint_velocity_limit)
    for _ in range(3000):
        dq, diag = ctrl.step(jax.numpy.asarray(q), target_dev, zero)
        dq = np.asarray(dq)
        assert np.all(np.abs(dq) <= limit + 1e-12)
        q = q + dt * dq
    err = np.linalg.norm(np.asarray(robot.site_position(q, SITE)) - target)
    assert err < 1e-4  # 0.1 mm (the damped pseudo-inverse leaks a little posture motion)
    # a far target is clipped: the speed command stays within max_speed and the joint limits
    dq, diag = ctrl.checked_step(robot.pose("home"), target + 1.0)
    diag = jax.tree.map(np.asarray, diag)
    assert np.linalg.norm(diag.error) == pytest.approx(gains.error_clip)
    assert np.all(np.abs(np.asarray(dq)) <= limit + 1e-12)
    with pytest.raises(InputError, match="target_pos"):
        ctrl.check_state(q, [0.0, np.nan, 0.0])
    x = np.concatenate([q, np.zeros(12), target, np.zeros(19)])  # the loop's packed input
    out = np.asarray(ctrl.packed_step(x))
    want_dq, want_diag = ctrl.checked_step(q, target)
    np.testing.assert_allclose(out[:6], want_dq, atol=1e-12)
    np.testing.assert_allclose(out[6:], want_diag.data, atol=1e-12)


# ----------------------------------------------------------------------------- base follower


def test_base_follower_deadband_gain_saturation_and_limits():
    gains, limits = BaseGains(), TwistLimits()
    q = np.zeros(6)
    p_d = np.array([0.5, 0.0, 0.3])

    def twist(offset, q=q, gains=gains, limits=limits):
        return follow_twist(p_d + np.asarray(offset), p_d, q, gains, limits)

    np.testing.assert_allclose(twist([0.007, -0.007, 0.5]), 0.0)  # |e_xy| < 1 cm, z ignored
    np.testing.assert_allclose(twist([0.05, -0.02, 0.3]), [0.2, -0.08, 0.0])  # K_b = 4 1/s
    v = twist([0.3, 0.4, 0.0])  # 4 * 0.5 = 2 m/s: cut to 1 m/s, direction kept
    np.testing.assert_allclose(v, [0.6, 0.8, 0.0])
    # yaw: 10 deg deadband on joint 0, gain 0.5 1/s, saturated at 0.5 rad/s
    for angle, wz in [(math.radians(9), 0.0), (math.radians(20), 0.5 * math.radians(20))]:
        np.testing.assert_allclose(twist([0, 0, 0], q=np.r_[angle, np.zeros(5)])[2], wz)
        np.testing.assert_allclose(twist([0, 0, 0], q=np.r_[-angle, np.zeros(5)])[2], -wz)
    np.testing.assert_allclose(twist([0, 0, 0], q=np.r_[2.0, np.zeros(5)])[2], 0.5)
    # the base's own twist limits cut each axis
    tight = TwistLimits(velocity=(0.3, 0.1, 0.2))
    v = twist([0.3, 0.4, 0.0], q=np.r_[2.0, np.zeros(5)], limits=tight)
    np.testing.assert_allclose(v, [0.3, 0.1, 0.2])
    tight.check(v)
    follower = BaseFollower()
    out = follower.twist(p_d + [0.1, 0, 0], p_d, q)
    assert out is follower.twist(p_d, p_d, q)  # reused buffer, no allocation
    np.testing.assert_allclose(out, 0.0)
