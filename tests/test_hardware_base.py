"""Mecanum kinematics, twist limits, the simulated Dingo-O and the ROS-free Dingo adapter."""

import numpy as np
import pytest

from jaxcomp.errors import InputError
from jaxcomp.hardware import DingoBase, MecanumGeometry, Simulator, TwistLimiter, TwistLimits
from jaxcomp.hardware.dingo import yaw_from_quaternion


def test_mecanum_round_trip_and_wheel_patterns():
    geo = MecanumGeometry()
    np.testing.assert_allclose(geo.wheel_speeds([0.5, 0, 0]), [10.0] * 4)  # 0.5 / 0.05
    np.testing.assert_allclose(geo.wheel_speeds([0, 0.5, 0]), [-10.0, 10.0, 10.0, -10.0])
    np.testing.assert_allclose(geo.wheel_speeds([0, 0, 1.0]), np.array([-1, 1, -1, 1]) * 9.9)
    twist = np.array([0.3, -0.2, 0.7])
    np.testing.assert_allclose(geo.twist(geo.wheel_speeds(twist)), twist, atol=1e-12)


def test_limits_refuse_bad_twists():
    limits = TwistLimits()
    with pytest.raises(InputError, match="exceeds .* on vy"):
        limits.check([0.0, 1.5, 0.0])
    with pytest.raises(InputError, match="NaN"):
        limits.check([np.nan, 0.0, 0.0])
    with pytest.raises(InputError, match="shape"):
        limits.check([0.0, 0.0])


def test_limiter_ramps_and_times_out():
    lim = TwistLimiter(TwistLimits())
    lim.command(np.array([1.0, 0.0, 4.0]), t=0.0)
    lim.update(0.0)
    np.testing.assert_allclose(lim.update(0.2), [0.12, 0.0, 0.4])  # 0.6 m/s^2, 2 rad/s^2
    np.testing.assert_allclose(lim.update(0.25), [0.15, 0.0, 0.5])
    out = lim.update(0.5)  # command older than 0.25 s: ramp down
    np.testing.assert_allclose(out, [0.0, 0.0, 0.0])


def test_simulated_base_follows_twist_within_limits_and_stops():
    sim = Simulator("dingo_o")
    base = sim.base
    for _ in range(25):  # 2.5 s of vx = 1 m/s, re-sent every 0.1 s
        base.send_twist([1.0, 0.0, 0.0])
        state = base.advance(0.1)
    assert state.twist[0] == pytest.approx(1.0, abs=0.03)
    assert state.pose[0] == pytest.approx(0.5 * 1.0**2 / 0.6 + 1.0 * (2.5 - 1.0 / 0.6), abs=0.05)
    t_cmd = state.t - 0.1  # the last command
    v = base.advance(0.1).twist[0]
    assert v == pytest.approx(1.0, abs=0.03)  # still within the 0.25 s timeout
    state = base.advance(1.0)  # timed out at t_cmd + 0.25, decelerating at 0.6 m/s^2
    assert state.twist[0] == pytest.approx(1.0 - 0.6 * (state.t - t_cmd - 0.25), abs=0.03)
    state = base.advance(1.0)
    assert abs(state.twist[0]) < 1e-3
    np.testing.assert_allclose(base.wheel_speeds(), 0.0, atol=0.05)


def test_simulated_base_turns_and_reports_body_twist():
    sim = Simulator("dingo_o")
    base = sim.base
    for _ in range(30):
        base.send_twist([0.2, 0.0, 0.5])
        state = base.advance(0.1)
    assert state.twist == pytest.approx([0.2, 0.0, 0.5], abs=0.01)  # body frame
    yaw = state.pose[2]
    # 3 s at 0.5 rad/s, less the 0.25 s ramp (2 rad/s^2) and the 20 ms velocity-servo lag
    assert yaw == pytest.approx(0.5 * 3.0 - 0.5 * 0.25 / 2 - 0.5 * 0.02, abs=0.005)
    with pytest.raises(InputError):
        base.send_twist([2.0, 0.0, 0.0])


def test_mobile_manipulator_arm_holds_while_base_drives():
    sim = Simulator("mobile_gen3_lite")
    arm, base = sim.arm, sim.base
    q0 = arm.read().q
    for _ in range(10):
        base.send_twist([0.3, 0.2, 0.0])
        state = arm.hold(0.1)
    assert np.abs(state.q - q0).max() < 0.01
    odo = base.odometry()
    assert odo.pose[0] > 0.1 and odo.pose[1] > 0.05


def test_dingo_adapter_logic_without_ros():
    sent, now = [], [0.0]
    base = DingoBase(publish=sent.append, clock=lambda: now[0])
    base.send_twist([1.0, 0.0, 0.0])
    base.update()
    for k in range(1, 11):
        now[0] = 0.02 * k
        base.update()
    assert sent[-1][0] == pytest.approx(0.12)  # 0.2 s at 0.6 m/s^2
    now[0] = 0.5  # no command for 0.5 s > 0.25 s: ramps down
    assert base.update()[0] == pytest.approx(0.0)
    base.on_odometry(3.0, (1.0, 2.0, 0.3), (0.1, 0.0, 0.0))
    assert base.odometry().pose[1] == 2.0
    with pytest.raises(InputError):
        base.send_twist([0.0, 0.0, 5.0])
    base.close()
    np.testing.assert_array_equal(sent[-1], 0.0)


def test_yaw_from_quaternion():
    half = 0.6 / 2
    assert yaw_from_quaternion(0.0, 0.0, np.sin(half), np.cos(half)) == pytest.approx(0.6)


def test_dingo_without_ros_explains_how_to_get_it():
    with pytest.raises(ImportError, match="ROS 2"):
        DingoBase()
