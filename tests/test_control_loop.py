"""The 1 kHz control loop: watchdog trips, safe exits, recording, timing, modes, trajectories.

Lock-step runs on the simulated mobile Gen3 Lite. The simulator's true robot keeps the paper's
ratios and COM offsets but 5 % of its friction, and the controller gets the true params, with
stiff, well-damped gains (K 300 N/m, D 30 N s/m, posture = the start pose): the arm then holds
its target to the 1 mm deadband, so pushes, returns and F/K are measured without the friction
band that the paper's soft 40 N/m spring leaves (about 2 cm in this simulator). Pushes ramp up
over 0.1 s (five staggered pushes) as a hand would: a step of 10 N on the end effector spins
the light wrist past the simulator's 2 rad/s overspeed fault. The same behaviour against the
full friction, with identified params, is in test_control_behaviour.py.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.util
import json
import math
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner

from jaxcomp.cli import main as cli_main
from jaxcomp.cli.control import parse_push
from jaxcomp.cli.group import cli
from jaxcomp.cli.robot_session import target_marker
from jaxcomp.control import (
    ImpedanceGains,
    make_impedance_controller,
    make_velocity_controller,
)
from jaxcomp.control.cycle import Cycle
from jaxcomp.control.impedance_io import live_gains
from jaxcomp.control.loop import run_control
from jaxcomp.control.mount import ArmMount, arm_model
from jaxcomp.control.run_link import RunLink, Tuning
from jaxcomp.control.run_setup import default_max_error
from jaxcomp.control.timing import CycleTimer
from jaxcomp.control.trajectory import Trajectory, parse_trajectory
from jaxcomp.control.watchdog import Watchdog, WatchdogTrip
from jaxcomp.control.workspace import arm_reach
from jaxcomp.errors import InputError
from jaxcomp.hardware import (
    ArmState,
    ControlMode,
    HardwareFault,
    KortexArm,
    KortexEmulator,
    Simulator,
    TrueRobot,
)
from jaxcomp.plausibility import checked_arm_params
from jaxcomp.recording import load_recording
from jaxcomp.robot import load_robot
from jaxcomp.robot_params import RobotParams

MOBILE = load_robot("mobile_gen3_lite")
ARM = arm_model(MOBILE)
K, D = 300.0, 30.0  # N/m, N s/m
FORCE = 10.0  # N: F / K = 33 mm, inside the 0.1 m error clip


def _truth(robot=MOBILE) -> TrueRobot:
    drawn = TrueRobot.draw(MOBILE, 0)
    p = drawn.params
    params = RobotParams(robot.name, p.ratio, 0.05 * p.friction, p.com_offset, method="test")
    return TrueRobot(params, drawn.current_noise, None, 0)


def _sim(robot=MOBILE) -> Simulator:
    return Simulator(robot, _truth(robot), seed=0)


def _ramped_push(sim: Simulator, start: float, length: float, force) -> float:
    """Five pushes of force / 5, 20 ms apart: ramps over 0.1 s; returns the release end (s)."""
    for k in range(5):
        sim.push(start + 0.02 * k, length, np.asarray(force, float) / 5)
    return start + 0.08 + length


@pytest.fixture(scope="module")
def controller():
    gains = ImpedanceGains(stiffness=K, damping=D, posture=tuple(ARM.pose("home")))
    ctrl = make_impedance_controller(ARM, checked_arm_params(_truth().params, ARM), gains)
    ctrl.compile()
    return ctrl


def _rec(result):
    """The run's joined recording (a clear failure when it could not be joined)."""
    assert result.recording is not None, f"no recording: {result.stop_errors}"
    return result.recording


def _base_cmd(sim: Simulator) -> np.ndarray:
    return sim._limiter._cmd  # the twist the simulated base was last told to follow


def _assert_safe(sim: Simulator) -> None:
    """Arm in POSITION mode (interface and simulator), base (if any) told to stop; then,
    stepping the simulator on, the arm holds still and the base comes to rest."""
    assert all(m is ControlMode.POSITION for m in sim.arm.modes)
    assert all(m is ControlMode.POSITION for m in sim.modes)
    if sim.has_base:
        np.testing.assert_array_equal(_base_cmd(sim), 0.0)
    sim.interaction.pushes.clear()
    q0 = sim.arm.read().q.copy()
    sim.step(300)
    q1 = sim.arm_state().q
    assert np.abs(q1 - q0).max() < 0.01  # caught where it was
    sim.step(300)
    assert np.abs(sim.arm_state().q - q1).max() < 1e-4  # and held still
    if sim.has_base:
        np.testing.assert_allclose(sim.base_state().twist, 0.0, atol=1e-3)


# ----------------------------------------------------------------------------- guidance run


@pytest.fixture(scope="module")
def guidance_run(controller, tmp_path_factory):
    sim = _sim()
    release = _ramped_push(sim, 0.3, 0.8, [FORCE, 0.0, 0.0])
    out = tmp_path_factory.mktemp("guidance")
    result = run_control(sim.arm, sim.base, controller, "guidance", None, 2.8, out)
    return sim, result, release, out


def test_guidance_push_moves_base_then_ee_returns_and_base_stops(guidance_run):
    sim, result, release, _ = guidance_run
    assert result.kind == "completed", result.reason
    rec = _rec(result)
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    base = rec.extra["base"]
    pushed = (t > release - 0.3) & (t < release - 0.1)
    assert err[pushed].mean() == pytest.approx(FORCE / K, rel=0.1)  # pushed away by F / K
    speed = np.linalg.norm(np.diff(base[:, :2], axis=0), axis=1) / np.diff(rec.t)
    assert speed[pushed[1:]].mean() > 0.08  # the base follows (4 / s x 33 mm = 0.13 m/s)
    assert base[-1, 0] > 0.05  # ... forward, with the push
    after = t > release
    back = t[after][np.flatnonzero(err[after] > 3e-3)[-1]] - release
    stopped = t[1:][after[1:]][np.flatnonzero(speed[after[1:]] > 2e-3)[-1]] - release
    assert back < 1.0  # s: the end effector is back at its target
    assert stopped < 2.0  # s: the base has stopped
    # the target stayed fixed in the base frame
    mount = ArmMount.from_model(MOBILE)
    target = rec.extra["target"]
    target_b = np.array([mount.world_to_base(p, b) for p, b in zip(target, base, strict=True)])
    assert np.abs(target_b - target_b[0]).max() < 1e-9
    # the external force estimate (world frame) sees the push, within its friction band
    wrench, band = rec.extra["wrench"][pushed], rec.extra["wrench_band"][pushed]
    assert np.all(np.abs(wrench.mean(0) - [FORCE, 0.0, 0.0]) <= band.mean(0) + 0.15 * FORCE)
    _assert_safe(sim)


def test_recording_fields_are_present_and_valid(guidance_run):
    sim, result, _, out = guidance_run
    rec = load_recording(out / "recording.npz", require_sweep=False)
    n = rec.n_samples
    assert n == result.cycles + 1 == 2801
    assert rec.model == "mobile_gen3_lite" and rec.n_joints == 6
    np.testing.assert_allclose(np.diff(rec.t), 0.001, atol=1e-9)
    np.testing.assert_array_equal(rec.joint, -1)
    np.testing.assert_array_equal(rec.direction, 0)
    for key, shape in {"target": (n, 3), "ee": (n, 3), "base": (n, 3), "command": (n, 6)}.items():
        assert rec.extra[key].shape == shape and np.isfinite(rec.extra[key]).all()
    assert np.abs(rec.extra["command"]).max() <= 11.0
    for key, shape in {"current_model": (n, 6), "wrench": (n, 3), "wrench_band": (n, 3)}.items():
        assert rec.extra[key].shape == shape and np.isfinite(rec.extra[key]).all()
    # ee is the end effector of the recorded q, in the world at the recorded base pose
    mount = ArmMount.from_model(MOBILE)
    for i in (0, n // 2, n - 1):
        ee_a = np.asarray(ARM.site_position(rec.q[i], "end_effector"))
        np.testing.assert_allclose(
            mount.arm_to_world(ee_a, rec.extra["base"][i]), rec.extra["ee"][i], atol=1e-12
        )
    assert not (out / "recording.npz.parts").exists()


def test_timing_json(guidance_run):
    _, result, _, out = guidance_run
    timing = json.loads((out / "timing.json").read_text())
    assert timing["mode"] == "lockstep" and timing["cycles"] == result.cycles
    for key in ("compute", "exchange", "cycle", "period"):
        stats = timing[key]
        assert 0 < stats["median_us"] <= stats["p99_us"] <= stats["max_us"]
        assert sum(stats["histogram"]["counts"]) == stats["count"]
    assert 0 <= timing["missed_fraction"] <= 1
    assert timing["missed_deadlines"] == round(timing["missed_fraction"] * result.cycles)
    assert timing["speed_x_realtime"] > 0 and timing["sim_time_s"] == pytest.approx(2.8)
    assert 0 < timing["cpu_s"] and timing["speed_x_realtime_cpu"] > 0
    assert timing["run"]["kind"] == "completed"
    assert timing["run"]["rms_error_m"] == pytest.approx(result.rms_error)


# ----------------------------------------------------------------------------- tracking


@pytest.fixture(scope="module")
def tracking_run(controller, tmp_path_factory):
    sim = _sim()
    release = _ramped_push(sim, 0.6, 0.8, [FORCE, 0.0, 0.0])
    out = tmp_path_factory.mktemp("tracking")
    result = run_control(
        sim.arm, sim.base, controller, "tracking", "circle:r=0.05,v=0.05", 2.6, out
    )
    return sim, result, release


def test_tracking_ee_returns_to_the_moving_target_after_a_push(tracking_run):
    sim, result, release = tracking_run
    assert result.kind == "completed", result.reason
    rec = _rec(result)
    t = rec.t - rec.t[0]
    target, ee = rec.extra["target"], rec.extra["ee"]
    err = np.linalg.norm(ee - target, axis=1)
    assert err[(t > 0.2) & (t < 0.6)].max() < 3e-3  # tracks before the push
    pushed = (t > release - 0.3) & (t < release - 0.1)
    assert err[pushed].mean() == pytest.approx(FORCE / K, rel=0.1)
    after = t > release
    back = t[after][np.flatnonzero(err[after] > 3e-3)[-1]] - release
    assert back < 1.0
    assert np.linalg.norm(target[-1] - target[0]) > 0.05  # the target moved on meanwhile
    assert np.linalg.norm(rec.extra["base"][-1, :2]) > 0.01  # and the base followed
    _assert_safe(sim)


def test_steady_push_displaces_ee_by_f_over_k(controller, tmp_path):
    """Arm alone, static target: pushes along x then y, each held 0.6 s."""
    sim = _sim(ARM)
    pushes = [(0.1, [FORCE, 0.0, 0.0]), (0.9, [0.0, -FORCE, 0.0])]
    for start, force in pushes:
        _ramped_push(sim, start, 0.6, force)
    result = run_control(sim.arm, None, controller, "tracking", "static", 1.6, tmp_path)
    assert result.kind == "completed", result.reason
    rec = _rec(result)
    t = rec.t - rec.t[0]
    for start, force in pushes:
        window = (t > start + 0.45) & (t < start + 0.65)
        d = (rec.extra["ee"] - rec.extra["target"])[window].mean(axis=0)
        want = np.asarray(force) / K
        assert np.linalg.norm(d) == pytest.approx(np.linalg.norm(want), rel=0.1)
        assert np.dot(d, want) / (np.linalg.norm(d) * np.linalg.norm(want)) > 0.98


# ----------------------------------------------------------------------------- watchdog trips

TRIP_AT = 250  # cycle at which a fault is injected


def _inject(monkeypatch, sim: Simulator, how: str, controller):
    """Patch the arm (or the controller) so that cycle TRIP_AT goes wrong; returns the list
    of cycle calls made (one entry per call)."""
    arm = sim.arm
    calls: list[int] = []
    last: list[ArmState] = []
    orig = arm.cycle

    def cycle(command=None):
        calls.append(1)
        if len(calls) >= TRIP_AT:
            if how == "stale":  # no new frame: the previous state again
                return last[-1]
            if how == "nan_state":
                state = orig(command)
                q = state.q.copy()
                q[2] = np.nan
                return dataclasses.replace(state, q=q)
            if how == "actuator_fault":
                sim.fault("joint_3: encoder fault (injected)", 3)
            if how == "interrupt":
                raise KeyboardInterrupt
            if how == "crash":
                raise RuntimeError("driver crashed (injected)")
        last.append(orig(command))
        return last[-1]

    monkeypatch.setattr(arm, "cycle", cycle)
    if how in ("current_limit", "nan_command"):
        step = controller.packed_step  # what the loop calls: current (n) | diagnostics
        count = [0]

        def bad_step(x):
            count[0] += 1
            out = step(x)
            if count[0] >= TRIP_AT + 2:  # the setup check and cycle 0 come first
                out = out.at[1].set(20.0 if how == "current_limit" else np.nan)
            return out

        monkeypatch.setattr(controller, "packed_step", bad_step)
    return calls


def _spy_stop(monkeypatch, sim: Simulator) -> list[int]:
    stops: list[int] = []
    orig = sim.base.stop
    monkeypatch.setattr(sim.base, "stop", lambda: (stops.append(1), orig())[1])
    return stops


@pytest.mark.parametrize(
    "how, kind",
    [
        ("stale", "stale_feedback"),
        ("nan_state", "nan_state"),
        ("actuator_fault", "hardware_fault"),
        ("current_limit", "current_limit"),
        ("nan_command", "nan_command"),
    ],
)
def test_watchdog_trip_ends_within_one_cycle_safely(how, kind, controller, monkeypatch, tmp_path):
    sim = _sim()
    _ramped_push(sim, 0.05, 1.0, [FORCE, 0.0, 0.0])  # the base is moving when it trips
    calls = _inject(monkeypatch, sim, how, controller)
    stops = _spy_stop(monkeypatch, sim)
    result = run_control(sim.arm, sim.base, controller, "guidance", None, 1.0, tmp_path)
    assert result.kind == kind, result.reason
    assert not result.ok
    assert result.cycles == TRIP_AT == len(calls)  # no cycle after the trip
    assert stops  # the base was told to stop
    assert np.linalg.norm(sim.base_state().twist[:2]) > 0.01  # it was moving
    _assert_safe(sim)
    rec = load_recording(tmp_path / "recording.npz", require_sweep=False)
    assert rec.n_samples == TRIP_AT  # samples 0 .. TRIP_AT - 1: the bad one is not kept
    assert json.loads((tmp_path / "timing.json").read_text())["run"]["kind"] == kind


def test_ctrl_c_ends_cleanly_with_the_recording_saved(controller, monkeypatch, tmp_path):
    sim = _sim()
    _ramped_push(sim, 0.05, 1.0, [FORCE, 0.0, 0.0])
    calls = _inject(monkeypatch, sim, "interrupt", controller)
    stops = _spy_stop(monkeypatch, sim)
    result = run_control(sim.arm, sim.base, controller, "guidance", None, 1.0, tmp_path)
    assert result.kind == "interrupted" and result.ok
    assert len(calls) == TRIP_AT and stops
    _assert_safe(sim)
    assert load_recording(tmp_path / "recording.npz", require_sweep=False).n_samples == TRIP_AT
    assert (tmp_path / "timing.json").is_file()


def test_unexpected_exception_is_raised_after_the_safe_stop(controller, monkeypatch, tmp_path):
    sim = _sim()
    _inject(monkeypatch, sim, "crash", controller)
    with pytest.raises(RuntimeError, match="injected"):
        run_control(sim.arm, sim.base, controller, "guidance", None, 1.0, tmp_path)
    _assert_safe(sim)
    assert load_recording(tmp_path / "recording.npz", require_sweep=False).n_samples == TRIP_AT


def test_kortex_adapter_stale_feedback_trips_before_the_adapter(controller, tmp_path):
    """The real-robot adapter on its emulator: frames stop at 0.1 s; the watchdog trips on
    the first repeated frame beyond the adapter's tolerance for lost replies (2; the adapter
    itself would wait 10 ms) and the session ends in POSITION mode."""
    emulator = KortexEmulator()
    arm = KortexArm.emulated(emulator)
    emulator.inject_stale(0.1, 0.05)
    result = run_control(arm, None, controller, "guidance", None, 0.3, tmp_path)
    assert result.kind == "stale_feedback", result.reason
    # 1 ms per frame: 8 open the session, 7 switch the six joints (hold frames)
    assert arm.stale_tolerance == 2
    assert result.cycles == 100 - 8 - 7 + 2
    assert all(m is ControlMode.POSITION for m in arm.modes) and emulator.all_position
    arm.close()
    assert not emulator.low_level and not emulator.session_open and not emulator.violations


def test_velocity_controller_runs_in_velocity_mode(tmp_path):
    """The reference (non-compliant) controller: VELOCITY mode, commands in rad/s."""
    sim = _sim(ARM)
    modes = []
    result = run_control(
        sim.arm,
        None,
        make_velocity_controller(ARM),
        "tracking",
        "circle:r=0.05,v=0.05",
        0.3,
        tmp_path,
        on_cycle=lambda k, state, command, target: modes.append(sim.modes[0]),
    )
    assert result.kind == "completed", result.reason
    assert set(modes) == {ControlMode.VELOCITY}
    assert result.rms_error < 1e-3
    _assert_safe(sim)


def test_refuses_to_start_on_a_faulted_arm(controller, tmp_path):
    sim = _sim()
    sim.fault("joint_1: over temperature (injected)", 1)
    with pytest.raises(HardwareFault):
        sim.arm.cycle()
    with pytest.raises(WatchdogTrip, match="over temperature"):
        run_control(sim.arm, sim.base, controller, "guidance", None, 0.1, tmp_path)
    assert all(m is ControlMode.POSITION for m in sim.arm.modes)


def test_realtime_run_paces_at_1khz(controller, tmp_path):
    sim = _sim(ARM)
    result = run_control(sim.arm, None, controller, "guidance", None, 0.3, tmp_path, True)
    assert result.kind in ("completed", "loop_stall"), result.reason
    timing = json.loads((tmp_path / "timing.json").read_text())
    assert timing["mode"] == "realtime"
    if result.kind == "completed":  # a badly overloaded machine may stall the loop
        assert timing["cycles"] == 300
        assert timing["loop_wall_s"] >= 0.299  # never faster than the wall clock
        assert timing["period"]["median_us"] >= 950
        assert load_recording(tmp_path / "recording.npz", require_sweep=False).n_samples == 301


# ----------------------------------------------------------------------------- units


def test_watchdog_checks():
    names = [f"j{i}" for i in range(3)]
    wd = Watchdog(names, [2.0, 2.0, 2.0], [1.5, 1.5, 1.5], max_saturated_cycles=3)
    s = ArmState(0.0, np.zeros(3), np.zeros(3), np.zeros(3))
    wd.check_state(s)
    with pytest.raises(WatchdogTrip, match="time did not advance") as exc:
        wd.check_state(dataclasses.replace(s, q=np.ones(3)))
    assert exc.value.kind == "stale_feedback"
    wd = Watchdog(names, 2.0)
    wd.check_state(s)
    with pytest.raises(WatchdogTrip, match="identical"):
        wd.check_state(dataclasses.replace(s, t=0.001))
    with pytest.raises(WatchdogTrip, match="NaN") as exc:
        Watchdog(names, 2.0).check_state(dataclasses.replace(s, dq=np.array([0, np.inf, 0])))
    assert exc.value.joints == ("j1",)
    with pytest.raises(WatchdogTrip, match="fault"):
        Watchdog(names, 2.0).check_state(dataclasses.replace(s, faults=("j2: hot",)))
    wd = Watchdog(names, [2.0, 2.0, 2.0], [1.5, 1.5, 1.5], max_saturated_cycles=3)
    with pytest.raises(WatchdogTrip, match="beyond its limit") as exc:
        wd.check_command(np.array([0.0, -2.5, 0.0]))
    assert exc.value.kind == "current_limit"
    for _ in range(3):
        wd.check_command(np.array([1.5, 0.0, 0.0]))
    with pytest.raises(WatchdogTrip, match="saturated"):
        wd.check_command(np.array([1.5, 0.0, 0.0]))
    wd = Watchdog(names, 2.0, max_gap=0.01)
    wd.check_state(s, now_ns=0)
    with pytest.raises(WatchdogTrip, match="stalled"):
        wd.check_state(dataclasses.replace(s, t=0.001, q=np.ones(3)), now_ns=20_000_000)


def test_arm_mount_matches_the_simulator():
    mount = ArmMount.from_model(MOBILE)
    np.testing.assert_allclose(mount.position, [0.16, 0.0, 0.11], atol=1e-12)
    sim = Simulator(MOBILE)
    rng = np.random.default_rng(1)
    for _ in range(5):
        pose = rng.uniform([-2, -2, -np.pi], [2, 2, np.pi])
        sim.data.qpos[sim.base_qposadr] = pose
        sim.data.qpos[sim.arm_qposadr] = rng.uniform(-1, 1, 6)
        mujoco.mj_forward(sim.model, sim.data)
        ee_a = np.asarray(ARM.site_position(sim.data.qpos[sim.arm_qposadr], "end_effector"))
        np.testing.assert_allclose(mount.arm_to_world(ee_a, pose), sim.ee_position(), atol=1e-12)
        np.testing.assert_allclose(mount.world_to_arm(sim.ee_position(), pose), ee_a, atol=1e-12)
    assert ArmMount.from_model(ARM).position.tolist() == [0.0, 0.0, 0.0]


def test_cycle_frames_match_arm_mount():
    """The loop's float frame maths against ``ArmMount`` (a tilted mount with a pivot)."""
    rng = np.random.default_rng(7)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.linalg.det(rot)  # a rotation
    mount = ArmMount([0.16, 0.02, 0.11], rot, [0.05, -0.03, 0.0])
    traj = parse_trajectory("circle:r=0.1,v=0.05").build(np.array([0.5, 0.1, 0.4]))
    law = SimpleNamespace(target=np.zeros(9))
    for guidance in (True, False):
        args = (None, traj, 0.0, None, None, mount, guidance, np.zeros(3), None, True)
        work = Cycle(law, *args)
        for _ in range(5):
            pose, twist, t = rng.uniform(-1, 1, 3), rng.uniform(-0.5, 0.5, 3), rng.uniform(0, 9)
            tb, tw, c, s, ox, oy = work.targets(t, *pose, *twist, True)
            sample = traj(t)
            if guidance:
                want_b, vel_b, acc_b = sample.pos, sample.vel, sample.acc
            else:
                rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
                want_b = mount.world_to_base(sample.pos, pose)
                vel_b, acc_b = rz.T @ sample.vel, rz.T @ sample.acc
                w = twist[2]  # minus the base's velocity at the target point
                vel_b = vel_b - [twist[0] - w * want_b[1], twist[1] + w * want_b[0], 0.0]
            np.testing.assert_allclose(tb, want_b, atol=1e-12)
            np.testing.assert_allclose(tw, mount.base_to_world(want_b, pose), atol=1e-12)
            np.testing.assert_allclose(mount.base_to_world(np.zeros(3), pose), [ox, oy, 0], 1e-12)
            want = np.r_[mount.base_to_arm(want_b), rot.T @ vel_b, rot.T @ acc_b]
            np.testing.assert_allclose(law.target, want, atol=1e-12)


def test_trajectories():
    start, origin = np.array([0.61, 0.22, 0.56]), np.array([0.16, 0.0, 0.11])
    half = parse_trajectory("half-circle").build(start, origin, np.eye(3))
    times = np.arange(0.0, half.duration + 0.5, 0.002)
    s = half.sample(times)
    lead = np.linalg.norm(start - np.array([0.16, 0.315, 0.56]))
    arc = math.pi * 0.315
    assert half.duration > lead / 0.101 + 4 * arc / 0.101  # plus the speed ramps
    on_arc = times > half.duration - 4 * arc / 0.101
    r = np.linalg.norm(s.pos[on_arc, :2] - origin[:2], axis=1)
    np.testing.assert_allclose(r, 0.315, atol=1e-9)
    np.testing.assert_allclose(s.pos[:, 2], 0.56)
    assert (s.pos[on_arc, 0] >= origin[0] - 1e-9).all()  # in front of the arm
    speed = np.linalg.norm(s.vel, axis=1)
    assert speed.max() == pytest.approx(0.101)
    np.testing.assert_allclose(s.pos[0], start)
    np.testing.assert_allclose(np.gradient(s.pos, times, axis=0)[1:-1], s.vel[1:-1], atol=5e-4)
    # back and forth: the y coordinate crosses from one end to the other four times
    ends = np.flatnonzero(np.abs(np.diff(np.sign(s.vel[on_arc, 1]))) > 0)
    assert len(ends) >= 3
    circle = parse_trajectory("circle:r=0.1,v=0.05,turns=1").build(start, origin, np.eye(3))
    c = circle.sample(np.arange(0.0, circle.duration, 0.01))
    np.testing.assert_allclose(c.pos[0], start)
    centre = start + 0.1 * np.r_[(origin - start)[:2] / np.linalg.norm((origin - start)[:2]), 0]
    np.testing.assert_allclose(np.linalg.norm(c.pos - centre, axis=1), 0.1, atol=1e-9)
    np.testing.assert_allclose(circle(circle.duration + 1).pos, start, atol=1e-9)
    static = parse_trajectory("static:dz=0.05").build(start)
    np.testing.assert_allclose(static(3.0).pos, start + [0, 0, 0.05])
    for bad, match in [
        ("spiral", "unknown trajectory"),
        ("circle:r=-1", "must be > 0"),
        ("circle:radius=1", "unknown key"),
        ("circle:r", "not key=value"),
        ("half-circle:passes=1.5", "whole number"),
        ("static:x=1,dx=1", "not both"),
    ]:
        with pytest.raises(InputError, match=match):
            parse_trajectory(bad)


def test_cycle_timer_counts_missed_deadlines():
    timer = CycleTimer(0.001, capacity=2)
    for k, work in enumerate([200_000, 1_500_000, 300_000]):
        sent = k * 1_000_000
        timer.record(sent, sent + 50_000, sent + 50_000 + work, sent + 1_000_000)
    timer.finish(0.003)
    s = timer.summary()
    assert s["cycles"] == 3 and s["missed_deadlines"] == 1
    assert s["compute"]["max_us"] == pytest.approx(1500)
    assert s["period"]["median_us"] == pytest.approx(1000)


def test_cli_help_and_errors():
    runner = CliRunner()
    out = runner.invoke(cli, ["control", "--help"])
    assert out.exit_code == 0
    for text in ("guidance", "tracking", "N/m", "START,DURATION,FX,FY,FZ", "half-circle"):
        assert text in out.output
    assert parse_push("0.5,1,10,0,-2") == (0.5, 1.0, (10.0, 0.0, -2.0))
    with pytest.raises(InputError, match="five numbers"):
        parse_push("0.5,1,10")
    out = runner.invoke(cli, ["control", "--trajectory", "spiral"])
    assert isinstance(out.exception, InputError)
    out = runner.invoke(cli, ["control", "--robot", "kortex", "--push", "0,1,1,0,0"])
    assert isinstance(out.exception, InputError) and "simulator only" in str(out.exception)


def test_cli_runs_the_simulator(tmp_path):
    runner = CliRunner()
    args = [
        "control",
        "--mode",
        "tracking",
        "--trajectory",
        "circle:r=0.05",
        "--duration",
        "0.3",
        "--push",
        "0.1,0.1,2,0,0",
        "--out",
        str(tmp_path),
    ]
    out = runner.invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    assert "ended: completed" in out.output and "RMS" in out.output
    assert load_recording(tmp_path / "recording.npz", require_sweep=False).n_samples == 301
    assert json.loads((tmp_path / "timing.json").read_text())["cycles"] == 300


def test_cli_guidance_with_a_params_file(tmp_path):
    """`--mode guidance --params FILE` on the mobile robot: the controller reads the params
    file (here the simulator's own truth), a push moves the end effector and the base follows."""
    params = TrueRobot.draw(MOBILE, 3).params
    path = params.save(tmp_path / "params.json")
    args = ["control", "--mode", "guidance", "--params", str(path), "--duration", "1.0"]
    args += ["--seed", "3", "--push", "0.1,0.6,10,0,0", "--out", str(tmp_path / "run")]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    assert "ended: completed" in out.output
    rec = load_recording(tmp_path / "run" / "recording.npz", require_sweep=False)
    assert rec.n_samples == 1001
    base = rec.extra["base"]
    assert base[-1, 0] - base[0, 0] > 0.005  # pushed along +x: the base followed, m
    bad = args[:4] + [str(tmp_path / "missing.json")] + args[5:]
    out = CliRunner().invoke(cli, bad)
    assert isinstance(out.exception, InputError) and "missing.json" in str(out.exception)


def test_viewer_target_marker():
    sim = Simulator(ARM)
    assert target_marker(sim) is None  # headless: no viewer, no hook
    scene = mujoco.MjvScene(sim.model, maxgeom=4)
    fake = SimpleNamespace(viewer=SimpleNamespace(lock=contextlib.nullcontext, user_scn=scene))
    hook = target_marker(fake)
    hook(20, None, None, np.array([0.1, 0.2, 0.3]))
    assert scene.ngeom == 1
    np.testing.assert_allclose(scene.geoms[0].pos, [0.1, 0.2, 0.3])


# ----------------------------------------------------------------------------- runs that cannot
# do what was asked: refused up front, or ended with a named reason and status 1


def test_the_reach_bounds_every_pose_and_is_tight():
    """The reach (from the kinematic chain) is never exceeded by a sampled pose, and some
    pose comes within 2 % of it (the Gen3 Lite's is about 0.91 m)."""
    reach = arm_reach(ARM, "end_effector")
    m = ARM.model
    d = mujoco.MjData(m)
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
    lo, hi = ARM.joint_limits.T
    rng = np.random.default_rng(0)
    far = 0.0
    for _ in range(3000):
        d.qpos[:] = rng.uniform(np.maximum(lo, -np.pi), np.minimum(hi, np.pi))
        mujoco.mj_kinematics(m, d)
        far = max(far, float(np.linalg.norm(d.site_xpos[site] - reach.origin)))
    assert far <= reach.radius and far > 0.98 * reach.radius
    np.testing.assert_allclose(reach.origin[:2], 0.0, atol=1e-9)  # on joint_0's vertical axis


def test_farthest_target_is_exact_and_stops_at_the_run_end():
    """``Trajectory.farthest`` of lines and arcs (exact) is never nearer than the 10 ms
    samples of the generic method and within 10 um of them; only targets up to ``until``."""
    rng = np.random.default_rng(3)
    start = np.array([0.4, 0.1, 0.3])
    for spec in ("circle:r=0.2,v=0.1", "circle:r=0.1,cx=0.5,cy=0.3,turns=1", "half-circle"):
        traj = parse_trajectory(spec).build(start)
        for _ in range(5):
            p, until = rng.normal(size=3), rng.uniform(0.5, 20.0)
            exact = np.linalg.norm(traj.farthest(p, until) - p)
            sampled = np.linalg.norm(Trajectory.farthest(traj, p, until) - p)
            assert sampled - 1e-12 <= exact < sampled + 1e-5
    line = parse_trajectory("line:dx=1,v=0.1,a=1").build(start)  # 0.05 m ramp, then 0.1 m/s
    np.testing.assert_allclose(line.farthest(start, 2.05), start + [0.2, 0, 0], atol=1e-12)


def test_unreachable_targets_are_refused_before_anything_is_switched(controller, tmp_path):
    """The issue's circle (r 5 m, 0.3 m/s) in guidance mode and a far static target with the
    arm alone: InputError naming the reach, the arm untouched, no output folder."""
    sim = _sim()
    out = tmp_path / "run"
    with pytest.raises(InputError, match=r"beyond its reach of 0\.91\d m"):
        run_control(sim.arm, sim.base, controller, "guidance", "circle:r=5,v=0.3", None, out)
    alone = _sim(ARM)
    with pytest.raises(InputError, match=r"1\.100 m from the base of gen3_lite's arm"):
        run_control(alone.arm, None, controller, "tracking", "static:x=0,y=1.1,z=0.12825", 1, out)
    assert all(m is ControlMode.POSITION for m in sim.modes + alone.modes)
    assert not out.exists()


def test_a_run_that_does_not_track_ends_not_tracking(controller, tmp_path):
    """A target the end effector stays more than max_error from for max_error_time ends the
    run (not ok) after that time, in position mode."""
    sim = _sim(ARM)
    result = run_control(
        sim.arm, None, controller, "tracking", "static:dx=0.02", 1.0, tmp_path,
        max_error=0.005, max_error_time=0.05,
    )  # fmt: skip
    assert result.kind == "not_tracking" and not result.ok
    assert "more than 5 mm from its target for 0.05 s" in result.reason
    assert result.cycles == 50 and result.max_error > 0.005  # 51 checks, the first at t = 0
    _assert_safe(sim)


def test_guidance_has_no_default_tracking_limit(controller):
    """A person may hold the arm off its target in guidance mode; tracking allows twice the
    error clip (0.1 m on the Gen3 Lite's paper gains) by default."""
    clip = controller.gains.error_clip
    assert default_max_error("tracking", controller) == pytest.approx(2 * clip) == 0.2
    assert default_max_error("guidance", controller) == math.inf


def test_watchdog_counts_the_cycles_off_target():
    wd = Watchdog(["j0"], 2.0, max_error=0.1, max_error_cycles=3)
    for err in (0.2, 0.2, 0.2, 0.05, 0.2, 0.2, 0.2):  # three in a row, then reset
        wd.check_error(err, 0.0)
    with pytest.raises(WatchdogTrip, match="not tracking") as exc:
        wd.check_error(0.2, 0.007)
    assert exc.value.kind == "not_tracking"
    Watchdog(["j0"], 2.0).check_error(1e9)  # off by default


def test_a_simulator_instability_is_named_and_the_arm_held(controller, tmp_path):
    """A force MuJoCo cannot integrate (slipped past the push bound): the run ends as a
    hardware fault naming the simulator's instability, arm in position mode, holding."""
    sim = _sim(ARM)
    sim.interaction.add_push(0.05, 1.0, (1e9, 0.0, 0.0))
    result = run_control(sim.arm, None, controller, "guidance", None, 0.5, tmp_path)
    assert result.kind == "hardware_fault" and "simulator unstable" in result.reason
    assert result.cycles == 51 and not sim.interaction.pushes
    _assert_safe(sim)


def _main(argv, monkeypatch, capsys) -> tuple[int, str, str]:
    """(status, stdout, stderr) of ``jaxcomp ARGV`` run as the console script."""
    monkeypatch.setattr("sys.argv", ["jaxcomp", *argv])
    monkeypatch.setenv("JAXCOMP_CACHE", "off")  # no persistent XLA cache from this process
    with pytest.raises(SystemExit) as exc:
        cli_main()
        raise SystemExit(0)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def _digests(folder) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir()}


def _short_ratio(folder):
    data = RobotParams.nominal(ARM).to_dict()
    data["ratio"] = data["ratio"][:5]
    path = folder / "short.json"
    path.write_text(json.dumps(data))
    return str(path)


GEN3_LITE = ["control", "--model", "gen3_lite"]


@pytest.mark.parametrize(
    "argv, message",
    [
        ([*GEN3_LITE, "--trajectory", "circle:r=5,v=0.3"], "beyond its reach of 0.914 m"),
        ([*GEN3_LITE, "--push", "100,1,10,0,0", "--duration", "3"], "starts at 100 s, after"),
        ([*GEN3_LITE, "--push", "1,1,1e9,0,0"], "beyond 396 N, 10 times the weight of"),
        ([*GEN3_LITE, "--params", "SHORT"], "ratio must have 6 entries, one per joint"),
        ([*GEN3_LITE, "--stiffness", "5000"], "stiffness 5000 N/m is outside the safe range"),
        (["control", "--robot", "kortex"], "needs Kinova's kortex_api"),
        (["calibrate", "--robot", "kortex", "--plan", "short"], "needs Kinova's kortex_api"),
    ],
)
def test_cli_refuses_runs_that_cannot_work_with_one_error_line(
    argv, message, tmp_path, monkeypatch, capsys
):
    """Status 2, one `error:` line naming the problem, no traceback, and the files of the
    output folder as they were."""
    if "kortex" in argv and importlib.util.find_spec("kortex_api") is not None:
        pytest.skip("kortex_api is installed")
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("the user's own file")
    before = _digests(out)
    argv = [_short_ratio(tmp_path) if a == "SHORT" else a for a in argv]
    status, _, err = _main([*argv, "--out", str(out)], monkeypatch, capsys)
    lines = err.strip().splitlines()
    assert status == 2, err
    assert [x for x in lines if x.startswith("error:")] == [lines[-1]] and message in lines[-1]
    assert "Traceback" not in err
    assert _digests(out) == before


def test_cli_run_that_does_not_track_ends_with_status_1(tmp_path, monkeypatch, capsys):
    argv = ["control", "--model", "gen3_lite", "--trajectory", "static:dx=0.01"]
    argv += ["--max-error", "0.005", "--max-error-time", "0.05", "--duration", "0.3"]
    status, out, err = _main([*argv, "--out", str(tmp_path)], monkeypatch, capsys)
    assert status == 1
    assert "ended: not_tracking (not tracking: the end effector stayed more than 5 mm" in out
    assert "Traceback" not in err and "error:" not in err


# ----------------------------------------------------------------------------- run link


class _Monitor:
    """A ``LoopMonitor`` keeping what it is given; sets the run's stop at ``stop_at`` s."""

    every = 33

    def __init__(self, link: RunLink, stop_at: float):
        self.link, self.stop_at = link, stop_at
        self.rows, self.ks, self.start, self.result = [], [], None, None

    def started(self, start):
        self.start = start

    def sample(self, k, row):
        self.ks.append(k)
        self.rows.append(row.copy())
        if row[self.start.columns["t"]][0] - self.rows[0][0] >= self.stop_at:
            self.link.stop.set()

    def ended(self, result):
        self.result = result


def test_run_link_live_gains_monitor_and_stop(controller, tmp_path):
    """A push of 10 N in guidance: new live gains (K doubled) halve the deflection F / K at
    once (no recompiling); the monitor gets every 33rd sample; the stop request ends the run
    ("stopped", ok) with the arm in position mode and the base stopped."""
    sim = _sim()
    _ramped_push(sim, 0.2, 5.0, [FORCE, 0.0, 0.0])
    link = RunLink(tuning=Tuning())
    monitor = link.monitor = _Monitor(link, stop_at=2.4)

    def retune(k, state, command, target):
        if k == 1300:  # 1.3 s, from another thread in the console: the same hand-over
            link.tuning.set(live_gains(2 * K, D, True))

    result = run_control(
        sim.arm,
        sim.base,
        controller,
        "guidance",
        None,
        10.0,
        tmp_path,
        on_cycle=retune,
        link=link,
    )
    assert result.kind == "stopped" and result.ok, result.reason
    assert monitor.result is result and monitor.start.mode == "guidance"
    assert link.tuning.applied == link.tuning.version == 1
    assert 2.4 <= result.duration < 2.5
    np.testing.assert_array_equal(np.diff(monitor.ks), 33)
    rec = result.recording
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    assert err[(t > 1.0) & (t < 1.3)].mean() == pytest.approx(FORCE / K, rel=0.1)
    assert err[(t > 2.0) & (t < 2.4)].mean() == pytest.approx(FORCE / (2 * K), rel=0.15)
    rows = np.array(monitor.rows)
    cols = monitor.start.columns
    np.testing.assert_array_equal(rows[:, cols["wrench"]], rec.extra["wrench"][monitor.ks])
    _assert_safe(sim)
