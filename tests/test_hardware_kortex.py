"""The Kortex adapter against the Kortex emulator: protocol, sessions, every exit path."""

import numpy as np
import pytest

from jaxcomp.errors import InputError
from jaxcomp.hardware import ArmCommand, ControlMode, HardwareFault, KortexArm, Simulator
from jaxcomp.hardware.kortex_emulator import FOLLOWING_ERROR, KortexEmulator, KServerException


def _emulator():
    return KortexEmulator(Simulator(seed=0))


def _assert_safe_and_closed(emu):
    assert emu.all_position, emu.control_modes
    assert not emu.low_level
    assert not emu.session_open
    assert emu.connected == set()
    assert emu.violations == []


def test_two_second_current_mode_session_without_protocol_violation():
    emu = _emulator()
    sim = emu.sim
    r = sim.truth.ratio
    with KortexArm.emulated(emu) as arm:
        q0 = arm.hold(0.05).q
        c0 = arm.read().current
        arm.set_modes(ControlMode.CURRENT)
        for _ in range(2000):  # 2 s: bumpless holding current plus a joint PD
            s = arm.read()
            arm.cycle(ArmCommand(current=c0 + r * (20.0 * (q0 - s.q) - 0.5 * s.dq)))
        state = arm.read()
        assert state.modes == (ControlMode.CURRENT,) * 6
        assert emu.control_modes == dict.fromkeys((1, 2, 3, 4, 5, 7), 4)  # CURRENT
    assert emu.refresh_count >= 2050
    assert np.abs(state.q - q0).max() < 2e-3
    # 50 ms of holding, a hold frame before each of the 6 switches and one after, 2 s
    assert state.t == pytest.approx(0.05 + 0.007 + 2.0, abs=1e-6)
    assert arm.max_jitter_us == 0
    _assert_safe_and_closed(emu)


def _inject_stall(emu):
    emu.inject_stall(0.2, 0.005)


def _inject_fault(emu):
    emu.inject_fault(0.2, device=3)


def _inject_stale(emu):
    emu.inject_stale(0.2, 0.05)


@pytest.mark.parametrize(
    ("inject", "raise_at", "error", "match"),
    [
        (_inject_stall, None, HardwareFault, "missed cycle: 6.0 ms"),
        (_inject_fault, None, HardwareFault, r"actuator 3 \(joint_2\): fault bank A 0x8000"),
        (_inject_stale, None, HardwareFault, "stale feedback: no new frame for 1[01]"),
        (None, RuntimeError("caller bug"), RuntimeError, "caller bug"),
        (None, KeyboardInterrupt(), KeyboardInterrupt, None),
    ],
)
def test_every_exit_path_restores_position_mode_and_closes(inject, raise_at, error, match):
    emu = _emulator()
    if inject is not None:
        inject(emu)
    with pytest.raises(error, match=match):
        with KortexArm.emulated(emu) as arm:
            arm.hold(0.05)  # the simulated servo takes up the load the opening frames moved
            arm.set_modes(ControlMode.CURRENT)
            c = arm.read().current
            for k in range(400):
                if raise_at is not None and k == 150:
                    raise raise_at
                arm.cycle(ArmCommand(current=c))
    assert 0.15 < emu.clock() < 0.3  # it stopped at the fault, not at the end
    assert arm.closed
    _assert_safe_and_closed(emu)


def test_bad_commands_never_reach_the_arm():
    emu = _emulator()
    with KortexArm.emulated(emu) as arm:
        arm.set_modes(ControlMode.CURRENT)
        n = emu.refresh_count
        with pytest.raises(InputError, match="NaN"):
            arm.cycle(ArmCommand(current=[0, 0, np.nan, 0, 0, 0]))
        with pytest.raises(InputError, match="beyond its limits"):
            arm.cycle(ArmCommand(current=[0, 0, 12.0, 0, 0, 0]))
        with pytest.raises(InputError, match="current"):
            arm.cycle(ArmCommand(current=[0.0] * 5))  # wrong length
        arm.set_modes(ControlMode.POSITION)
        n = emu.refresh_count
        beyond = arm.read().q
        beyond[3] = np.deg2rad(170.0)  # joint 3's limit is 154 deg
        with pytest.raises(InputError, match="beyond its limits"):
            arm.cycle(ArmCommand(position=beyond))
        assert emu.refresh_count == n


def test_switching_to_current_while_moving_fast_is_refused_on_the_arm():
    emu = _emulator()
    with KortexArm.emulated(emu) as arm:
        arm.set_mode(0, ControlMode.VELOCITY)
        for _ in range(300):
            state = arm.cycle(ArmCommand(velocity=[0.5, 0, 0, 0, 0, 0]))
        assert state.dq[0] == pytest.approx(0.5, rel=0.02)
        with pytest.raises(InputError, match="joint_0 moves at 0.5.* current mode is refused"):
            arm.set_mode(0, ControlMode.CURRENT)
        assert arm.modes[0] is ControlMode.VELOCITY
    _assert_safe_and_closed(emu)


def test_position_moves_through_low_level_servoing():
    emu = _emulator()
    with KortexArm.emulated(emu) as arm:
        target = arm.read().q + np.deg2rad([10, -5, 5, 10, -10, 20])
        arm.move_to(target, 0.5)
        state = arm.hold(0.3)
        assert np.abs(state.q - target).max() < 0.01
    _assert_safe_and_closed(emu)


def test_emulator_enforces_the_protocol():
    emu = _emulator()
    api = emu.api
    tcp, udp = api.TCPTransport(), api.UDPTransport()
    router, router_rt = api.RouterClient(tcp), api.RouterClient(udp)
    tcp.connect("192.168.1.10", 10000)
    udp.connect("192.168.1.10", 10001)
    info = api.Session_pb2.CreateSessionInfo()
    info.username, info.password = "admin", "admin"
    for r in (router, router_rt):
        api.SessionManager(r).CreateSession(info)
    base, cyclic = api.BaseClient(router), api.BaseCyclicClient(router_rt)
    config = api.ActuatorConfigClient(router)
    mode = api.ActuatorConfig_pb2.ControlModeInformation()
    mode.control_mode = api.ActuatorConfig_pb2.ControlMode.Value("CURRENT")
    with pytest.raises(KServerException, match="needs LOW_LEVEL_SERVOING"):
        config.SetControlMode(mode, 1)
    with pytest.raises(KServerException, match="device id 6"):
        config.SetControlMode(mode, 6)
    with pytest.raises(AttributeError):  # message fields are checked like protobuf's
        mode.mode = 4
    servo = api.Base_pb2.ServoingModeInformation()
    servo.servoing_mode = api.Base_pb2.ServoingMode.Value("LOW_LEVEL_SERVOING")
    base.SetServoingMode(servo)
    fb = cyclic.RefreshFeedback()
    cmd = api.BaseCyclic_pb2.Command()
    for a in fb.actuators:
        c = cmd.actuators.add()
        c.flags = 1
        c.position = a.position
    cmd.frame_id = 7
    for c in cmd.actuators:
        c.command_id = 7
    cyclic.Refresh(cmd)
    with pytest.raises(KServerException, match="frame_id 7 did not advance"):
        cyclic.Refresh(cmd)
    cmd.frame_id = 8
    for c in cmd.actuators:
        c.command_id = 8
    cmd.actuators[1].position += 20.0  # far from the measured position
    fb = cyclic.Refresh(cmd)
    assert fb.actuators[1].fault_bank_a & FOLLOWING_ERROR
    assert fb.actuators[0].fault_bank_a == 0
    assert len(emu.violations) == 3
    with pytest.raises(KServerException, match="UDP connection on port 10001"):
        api.BaseCyclicClient(router).RefreshFeedback()


def test_adapter_without_kortex_api_explains_the_install():
    try:
        import kortex_api  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="not on PyPI.*--no-deps"):
            KortexArm("192.168.1.10")
    else:  # pragma: no cover - only where Kinova's wheel is installed
        pytest.skip("kortex_api is installed")
