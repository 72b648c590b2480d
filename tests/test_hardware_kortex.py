"""The Kortex adapter against the Kortex emulator: protocol, sessions, every exit path, hold
frames around mode switches, lost replies, timeouts, arm faults and states, host jitter."""

import dataclasses

import numpy as np
import pytest

import jaxcomp.cli
from jaxcomp import hardware
from jaxcomp.control import make_velocity_controller
from jaxcomp.control.loop import run_control
from jaxcomp.errors import InputError
from jaxcomp.hardware import ArmCommand, ControlMode, HardwareFault, KortexArm, Simulator
from jaxcomp.hardware.interface import Base, BaseState
from jaxcomp.hardware.kortex import DEVICE_IDS
from jaxcomp.hardware.kortex_emulator import KortexEmulator
from jaxcomp.hardware.kortex_injections import LOST_KINDS
from jaxcomp.hardware.kortex_messages import JOINT_FAULT, MAXIMUM_CURRENT, KServerException
from jaxcomp.hardware.kortex_protocol import FOLLOWING_ERROR
from jaxcomp.hardware.mecanum import TwistLimits
from jaxcomp.robot import load_robot
from jaxcomp.robot_params import RobotParams


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
    state_name = api.Common_pb2.ArmState.Name
    assert state_name(base.GetArmState().active_state) == "ARMSTATE_SERVOING_READY"
    options = api.RouterClientSendOptions()  # kortex_api's fields and defaults, no other
    assert (options.andForget, options.delay_ms, options.timeout_ms) == (False, 0, 10000)
    with pytest.raises(AttributeError):
        options.delay_before_timeout = 0
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
    assert state_name(fb.base.active_state) == "ARMSTATE_SERVOING_LOW_LEVEL"
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
    assert fb.base.fault_bank_a == JOINT_FAULT  # the arm is in fault with its actuator
    assert state_name(fb.base.active_state) == "ARMSTATE_IN_FAULT"
    assert len(emu.violations) == 3
    with pytest.raises(KServerException, match="UDP connection on port 10001"):
        api.BaseCyclicClient(router).RefreshFeedback()
    # switches without a hold frame: the last frame's current (0 A) is not the measured one;
    # then no frame at all since the previous switch
    mode.control_mode = api.ActuatorConfig_pb2.ControlMode.Value("CURRENT")
    config.SetControlMode(mode, 1)
    config.SetControlMode(mode, 2)
    assert [(r.device, r.frames, r.held) for r in emu.switches] == [(1, 2, False), (2, 0, False)]
    assert len(emu.violations) == 6 and "without a hold frame" in emu.violations[-1]
    base.ClearFaults()
    assert state_name(base.GetArmState().active_state) == "ARMSTATE_SERVOING_LOW_LEVEL"


def test_adapter_without_kortex_api_explains_the_install():
    try:
        import kortex_api  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="not on PyPI.*--no-deps"):
            KortexArm("192.168.1.10")
    else:  # pragma: no cover - only where Kinova's wheel is installed
        pytest.skip("kortex_api is installed")


# ----------------------------------------------------------------- reliability of the real-arm path
def _settled_current_session(arm):
    """Hold 50 ms (the simulated servo takes up the load), all joints to CURRENT at the
    measured current; returns that current."""
    arm.hold(0.05)
    arm.set_modes(ControlMode.CURRENT)
    return arm.read().current


def test_a_hold_frame_from_the_feedback_precedes_every_mode_switch():
    """Each configuration call takes 20 ms: a hold frame goes before each switch (one
    between two joints' switches) and one after the last; the 20 ms gaps are counted as
    missed cycles."""
    emu = KortexEmulator(Simulator(seed=0), config_latency=0.02)
    with KortexArm.emulated(emu) as arm:
        opened = len(emu.switches)
        missed = arm.missed_cycles
        c = _settled_current_session(arm)  # holding (cycles 1 ms apart), then the switch
        assert arm.missed_cycles - missed == 6 * (21 - 1)  # frames 21 ms apart
        to_current = emu.switches[opened:]
        for _ in range(20):
            arm.cycle(ArmCommand(current=c))
        arm.set_mode(0, ControlMode.VELOCITY)
        arm.hold(0.02)
    assert opened == 6  # every actuator to POSITION when the session opens
    assert [(r.device, r.mode) for r in to_current] == [(d, "CURRENT") for d in DEVICE_IDS]
    assert np.diff([r.t for r in to_current]) == pytest.approx(0.021, abs=1e-9)
    # every switch in low-level servoing, each starting where the last feedback left the
    # actuator, a hold frame since the previous switch (more frames: the cycles between)
    assert [(r.low_level, r.held) for r in emu.switches] == [(True, True)] * 25
    frames = [r.frames for r in emu.switches]
    between = [1] * 5
    assert frames == [
        *(2, *between),  # open: the frame that saw low-level servoing, the hold frame
        *(1 + 50 + 1, *between),  # CURRENT: the last hold frame, 50 cycles, a hold frame
        1 + 20 + 1,  # VELOCITY, 20 cycles after
        *(1 + 20 + 1, *between),  # close: every joint back to POSITION, 20 cycles after
        *(2, *between),  # the way out: all six to POSITION again
    ]
    _assert_safe_and_closed(emu)


@pytest.mark.parametrize("what", LOST_KINDS)
def test_a_lost_reply_is_tolerated_and_counted(what):
    """One lost exchange at 0.1 s and two in a row at 0.2 s: the cycles go on with the last
    feedback (a repeated state each), no fault; a timeout costs its 3 ms (2 missed ticks)."""
    emu = _emulator()
    emu.inject_lost(0.1, what=what)
    emu.inject_lost(0.2, count=2, what=what)
    with KortexArm.emulated(emu) as arm:
        c = _settled_current_session(arm)
        missed = arm.missed_cycles
        states = [arm.cycle(ArmCommand(current=c)) for _ in range(250)]
        assert all(s.ok for s in states)
        repeated = sum(
            np.array_equal(a.q, b.q) and np.array_equal(a.current, b.current)
            for a, b in zip(states, states[1:], strict=False)
        )
        assert repeated == 3
        assert (arm.lost_replies, arm.lost_in_a_row) == (3, 0)
        assert emu.lost[what] == 3 and sum(emu.lost.values()) == 3
        assert arm.missed_cycles - missed == (0 if what == "client" else 3 * 2)
        assert np.abs(states[-1].q - states[0].q).max() < 2e-3  # it held throughout
    _assert_safe_and_closed(emu)


def _lost(what, count):
    return lambda emu: emu.inject_lost(0.2, count=count, what=what)


def _losses_then_arm_fault(emu):
    emu.inject_lost(0.1)
    emu.inject_lost(0.15, count=2, what="command")
    emu.inject_arm_fault(0.2)


@pytest.mark.parametrize(
    ("inject", "match"),
    [
        (_lost("reply", 3), r"3 consecutive cyclic replies lost \(limit 3\).*reply lost"),
        # the link stays down through the way out: POSITION mode all the same
        (_lost("command", 50), r"3 consecutive cyclic replies lost \(limit 3\).*command lost"),
        (_lost("client", 50), r"3 consecutive cyclic replies lost .*KClientException"),
        (
            _losses_then_arm_fault,
            r"arm fault bank A 0x800000 \(EMERGENCY_STOP_ACTIVATED\); arm state ARMSTATE_IN_FAULT",
        ),
        (
            lambda emu: emu.inject_arm_fault(0.2, MAXIMUM_CURRENT | JOINT_FAULT),
            r"arm fault bank A 0x2010 \(JOINT_FAULT, MAXIMUM_CURRENT\)",
        ),
    ],
)
def test_lost_replies_and_arm_faults_end_the_session_in_position_mode(inject, match):
    emu = _emulator()
    inject(emu)
    with pytest.raises(HardwareFault, match=match) as info:
        with KortexArm.emulated(emu) as arm:
            c = _settled_current_session(arm)
            for _ in range(400):
                arm.cycle(ArmCommand(current=c))
    assert 0.2 < emu.clock() < 0.3  # it stopped at the fault, not at the end
    assert info.value.state.modes == (ControlMode.CURRENT,) * 6
    assert arm.closed
    _assert_safe_and_closed(emu)


def test_a_mode_switch_without_a_reply_ends_the_session_in_position_mode():
    """The third SetControlMode(CURRENT) gets no reply (500 ms): the two switched joints go
    back to POSITION with the others, the first call of the way out (no reply either) is
    tried again."""
    emu = _emulator()
    with pytest.raises(
        HardwareFault,
        match=r"mode switch aborted: SetControlMode\(CURRENT\) of actuator 3: no reply within 500",
    ):
        with KortexArm.emulated(emu) as arm:
            arm.hold(0.05)
            # frames 1 ms apart: the third call comes 3 ms after the first hold frame
            emu.inject_config_timeout(emu.clock() + 0.0025, count=2)
            arm.set_modes(ControlMode.CURRENT)
    assert [r.mode for r in emu.switches[6:8]] == ["CURRENT", "CURRENT"]
    assert emu.config_timeouts == 2
    assert arm.closed
    _assert_safe_and_closed(emu)


class _RecordingBase(Base):
    """A base that records the twists sent to it and stands still."""

    def __init__(self):
        super().__init__(TwistLimits())
        self.sent: list[np.ndarray] = []

    def _send(self, twist: np.ndarray) -> None:
        self.sent.append(np.array(twist, dtype=float))

    def odometry(self) -> BaseState:
        return BaseState(0.0, np.zeros(3), np.zeros(3))


def test_a_control_run_with_lost_replies_timeouts_and_an_arm_fault_ends_safely(tmp_path):
    """run_control on the emulated arm: the lost reply and the two timeouts are tolerated
    (the watchdog too takes their repeated states), the arm fault ends the run, named, with
    the arm in POSITION mode, single-level servoing and the base stopped."""
    emu = _emulator()
    _losses_then_arm_fault(emu)
    base = _RecordingBase()
    arm = KortexArm.emulated(emu)
    arm.hold(0.05)
    controller = make_velocity_controller(load_robot("gen3_lite"))
    result = run_control(arm, base, controller, "guidance", None, 1.0, tmp_path)
    assert result.kind == "hardware_fault", result.reason
    assert "EMERGENCY_STOP_ACTIVATED" in result.reason and "ARMSTATE_IN_FAULT" in result.reason
    # the run starts after 8 opening frames and 50 ms of holding, the fault comes at 0.2 s
    assert result.duration == pytest.approx(0.2 - 0.008 - 0.05, abs=0.0015)
    assert arm.lost_replies == 3
    assert emu.lost == {"reply": 1, "command": 2, "client": 0}
    assert len(base.sent) > 100 and np.array_equal(base.sent[-1], np.zeros(3))  # stopped
    assert arm.closed
    _assert_safe_and_closed(emu)


def test_emulator_servoing_states_and_the_adapter_waits_for_low_level():
    emu = KortexEmulator(Simulator(seed=0), servoing_delay=0.02)
    name = emu.api.Common_pb2.ArmState.Name
    assert name(emu.arm_state) == "ARMSTATE_SERVOING_READY"
    with KortexArm.emulated(emu) as arm:
        assert name(emu.arm_state) == "ARMSTATE_SERVOING_LOW_LEVEL"
        # hold frames until the arm reported low-level servoing, then the actuators
        assert emu.switches[0].t == pytest.approx(0.02 + 0.001, abs=1e-9)
        arm.hold(0.01)
    assert name(emu.arm_state) == "ARMSTATE_SERVOING_READY"
    _assert_safe_and_closed(emu)
    emu = KortexEmulator(Simulator(seed=0), servoing_delay=1.0)
    with pytest.raises(
        HardwareFault,
        match="did not enter low-level servoing: arm state ARMSTATE_SERVOING_READY after 0.5 s",
    ):
        KortexArm.emulated(emu)
    assert {r.mode for r in emu.switches} == {"POSITION"}  # the way out only
    _assert_safe_and_closed(emu)


def test_host_jitter_is_reported_and_a_late_send_is_a_missed_cycle():
    emu = KortexEmulator(Simulator(seed=0), jitter=0.0005, seed=1)
    with KortexArm.emulated(emu) as arm:
        state = arm.hold(0.3)
        assert state.ok
        assert 400 < arm.max_jitter_us <= emu.max_jitter_us < 500  # |late_k - late_k-1| us
    _assert_safe_and_closed(emu)
    emu = KortexEmulator(Simulator(seed=0), jitter=0.004, seed=1)
    with pytest.raises(HardwareFault, match=r"missed cycle: [345]\.\d ms since the last one"):
        with KortexArm.emulated(emu) as arm:
            arm.hold(0.3)
    _assert_safe_and_closed(emu)


def test_the_real_arm_path_refuses_implausible_params_before_any_current(
    tmp_path, monkeypatch, capsys
):
    """`jaxcomp control --robot kortex` on the emulator with ratios of 1e-17 A/(N m): one
    error line, status 2, and no actuator ever leaves POSITION mode."""
    gen3 = load_robot("gen3_lite")
    params = dataclasses.replace(RobotParams.nominal(gen3), ratio=np.full(6, 1e-17))
    path = params.save(tmp_path / "params.json")
    emu = _emulator()
    monkeypatch.setattr(
        hardware, "KortexArm", lambda ip, **kwargs: KortexArm.emulated(emu, **kwargs)
    )
    argv = ["jaxcomp", "control", "--robot", "kortex", "--params", str(path)]
    argv += ["--duration", "0.05", "--rt-priority", "0", "--out", str(tmp_path / "run")]
    monkeypatch.setattr("sys.argv", argv)
    monkeypatch.setenv("JAXCOMP_CACHE", "off")  # no persistent XLA cache from this process
    with pytest.raises(SystemExit) as exc:
        jaxcomp.cli.main()
    assert {r.mode for r in emu.switches} <= {"POSITION"}
    assert not emu.low_level and not emu.session_open
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2, err
    assert sum(line.startswith("error: ") for line in err) == 1 and err[-1].startswith("error: ")
    assert not any("Traceback" in line for line in err)
