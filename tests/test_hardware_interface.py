"""The Arm interface on the simulator: validation, modes, move_to, safe exit."""

import numpy as np
import pytest

from jaxcomp.errors import InputError
from jaxcomp.hardware import ArmCommand, ControlMode, Simulator
from jaxcomp.hardware.move_profile import trapezoid, trapezoid_duration


@pytest.fixture
def sim():
    return Simulator(seed=0)


@pytest.mark.parametrize(
    ("command", "match"),
    [
        (ArmCommand(position=[0.0, np.nan, 1.0, 0.0, 0.0, 0.0]), "NaN or inf at joint_1"),
        (ArmCommand(position=np.zeros(5)), r"shape \(6,\)"),
        (ArmCommand(position=[3.0, 0, 0, 0, 0, 0]), "position 3 rad for joint_0 is beyond"),
        (ArmCommand(current=[np.inf, 0, 0, 0, 0, 0]), "NaN or inf at joint_0"),
    ],
)
def test_bad_commands_are_refused_and_never_sent(sim, command, match):
    arm = sim.arm
    t, q = sim.t, arm.read().q
    with pytest.raises(InputError, match=match):
        arm.cycle(command)
    assert sim.t == t  # no step was taken
    np.testing.assert_array_equal(arm.read().q, q)


def test_current_and_velocity_limits(sim):
    arm = sim.arm
    arm.set_modes([ControlMode.CURRENT, ControlMode.VELOCITY] + [None] * 4)
    t = sim.t
    with pytest.raises(InputError, match=r"current 11.5 A for joint_0 is beyond .*\[-11, 11\] A"):
        arm.cycle(ArmCommand(current=[11.5, 0, 0, 0, 0, 0]))
    with pytest.raises(InputError, match="velocity 1.5 rad/s for joint_1 is beyond"):
        arm.cycle(ArmCommand(velocity=[0, 1.5, 0, 0, 0, 0]))
    assert sim.t == t
    # entries of joints in other modes are ignored (but must be finite)
    arm.cycle(ArmCommand(current=[0.0, 50.0, 0, 0, 0, 0]))
    assert sim.t == pytest.approx(t + 0.001)


def test_switching_to_current_while_moving_fast_is_refused(sim):
    arm = sim.arm
    arm.set_mode("joint_0", ControlMode.VELOCITY)
    v = np.array([0.5, 0, 0, 0, 0, 0])
    for _ in range(300):
        state = arm.cycle(ArmCommand(velocity=v))
    assert state.dq[0] == pytest.approx(0.5, rel=0.01)  # the velocity servo follows
    with pytest.raises(InputError, match="joint_0 moves at 0.5.* current mode is refused"):
        arm.set_mode(0, ControlMode.CURRENT)
    assert arm.modes[0] is ControlMode.VELOCITY
    for _ in range(300):
        arm.cycle(ArmCommand(velocity=np.zeros(6)))
    arm.set_mode(0, ControlMode.CURRENT)  # at rest it is allowed
    assert arm.modes[0] is ControlMode.CURRENT


def test_switch_to_current_is_bumpless(sim):
    arm = sim.arm
    q0 = arm.hold(0.3).q
    arm.set_modes(ControlMode.CURRENT)  # each joint starts at its measured current
    state = arm.hold(0.3)
    assert state.modes == (ControlMode.CURRENT,) * 6
    assert np.abs(state.q - q0).max() < 2e-3


def test_move_to_runs_at_constant_speed_and_reports_every_cycle(sim):
    arm = sim.arm
    start = arm.read().q
    target = start + np.deg2rad([30.0, -10.0, 15.0, 0.0, 20.0, -30.0])
    speed = np.deg2rad(20.0)
    states = []
    final = arm.move_to(target, speed, on_state=states.append)
    dist = np.deg2rad(30.0)
    expected = trapezoid_duration(dist, speed, speed / 0.1)
    assert len(states) == int(np.ceil(expected / arm.dt - 1e-9))
    np.testing.assert_allclose(np.diff([s.t for s in states]), arm.dt, atol=1e-9)
    mid = np.array([s.dq for s in states[len(states) // 4 : 3 * len(states) // 4]])
    np.testing.assert_allclose(np.abs(mid[:, 0]), speed, rtol=0.01)  # the longest way: 20 deg/s
    np.testing.assert_allclose(np.abs(mid[:, 1]), speed / 3, rtol=0.03)  # arrives together
    settled = arm.hold(0.3)
    assert np.abs(settled.q - target).max() < 0.01
    assert final.modes == (ControlMode.POSITION,) * 6
    with pytest.raises(InputError, match="speed must be in"):
        arm.move_to(target, 5.0)
    with pytest.raises(InputError, match="unknown pose 'nowhere'"):
        arm.move_to("nowhere", 0.2)


def test_trapezoid_profile():
    t = np.array([0.0, 0.05, 0.1, 1.0, 10.0])
    s = trapezoid(1.0, 0.5, 5.0, t)
    np.testing.assert_allclose(s[:3], [0.0, 0.5 * 5.0 * 0.05**2, 0.025])
    assert s[-1] == 1.0
    assert trapezoid_duration(1.0, 0.5, 5.0) == pytest.approx(2.1)
    assert trapezoid_duration(0.01, 0.5, 5.0) == pytest.approx(2 * np.sqrt(0.01 / 5.0))


def test_context_manager_always_ends_in_position_mode(sim):
    arm = sim.arm
    with pytest.raises(RuntimeError, match="controller bug"):
        with arm:
            arm.set_modes(ControlMode.CURRENT)
            arm.hold(0.01)
            raise RuntimeError("controller bug")
    assert arm.closed
    assert sim.modes == (ControlMode.POSITION,) * 6
    with pytest.raises(Exception, match="closed"):
        arm.cycle()


def test_mobile_simulator_closes_arm_and_base():
    with Simulator("mobile_gen3_lite") as sim:
        sim.arm.set_modes(ControlMode.CURRENT)
        sim.base.send_twist([0.3, 0.0, 0.0])
        sim.arm.hold(0.3)
        assert sim.base.odometry().twist[0] > 0.1
    assert sim.modes == (ControlMode.POSITION,) * 6
    sim.step(300)  # the base was told to stop: it decelerates at 0.6 m/s^2
    assert abs(sim.base_state().twist[0]) < 1e-3
