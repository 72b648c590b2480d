"""The simulated Gen3 Lite: currents, friction, truth, limits and interaction."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import jaxcomp
from jaxcomp import dynamics
from jaxcomp.errors import InputError
from jaxcomp.hardware import (
    PAPER_FRICTION,
    PAPER_RATIO,
    ArmCommand,
    ControlMode,
    HardwareFault,
    Simulator,
    TrueRobot,
)
from jaxcomp.hardware.interaction import Rope
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names

SWEEP_POSE = np.deg2rad([0.0, 20.0, 90.0, 0.0, 60.0, 0.0])  # gravity loads joints 1-4


def _gravity_fn(robot, params):
    g = jnp.array([0.0, 0.0, -9.81])
    return jax.jit(jax.vmap(lambda q: dynamics.gravity(robot.tree, q, params, g)))


def _sweep(arm, j, speed, amp):
    """Records of joint j swept -amp..+amp..-amp about SWEEP_POSE at constant speed (rad/s)."""
    lo, hi = SWEEP_POSE.copy(), SWEEP_POSE.copy()
    lo[j] -= amp
    hi[j] += amp
    arm.move_to(lo, speed)
    arm.hold(0.1)
    recs = []
    arm.move_to(hi, speed, on_state=recs.append)
    half = len(recs)
    arm.move_to(lo, speed, on_state=recs.append)
    k = np.arange(len(recs)) % half
    ramp = int(0.25 / arm.dt)  # leave out the 0.1 s speed ramps and the servo's settling
    keep = (k > ramp) & (k < half - ramp)
    q = np.array([s.q for s in recs])[keep]
    dq = np.array([s.dq for s in recs])[keep]
    c = np.array([s.current for s in recs])[keep]
    return q, dq, c


@pytest.mark.parametrize("speed_deg", [10.0, 40.0])
def test_sweep_current_is_ratio_times_true_gravity_plus_friction(speed_deg):
    """Must show: c = r (g_true(q) + l/r sign(dq)) within the noise; friction within 2%."""
    sim = Simulator("gen3_lite", seed=3)
    truth, robot, arm = sim.truth, sim.robot, sim.arm
    g_true = _gravity_fn(robot, truth.params.inertial_params(robot))
    g_nominal = _gravity_fn(robot, robot.nominal_params())
    speed = np.deg2rad(speed_deg)
    noise = truth.current_noise
    offsets_visible = False
    for j in range(6):
        q, dq, c = _sweep(arm, j, speed, np.deg2rad(12.0))
        assert np.abs(np.abs(dq[:, j]) - speed).max() < 0.02 * speed  # constant speed
        r, sign = truth.ratio[j], np.sign(dq[:, j])
        g = np.asarray(g_true(q))[:, j]
        resid = c[:, j] - r * g - truth.friction[j] * sign
        assert abs(resid.mean()) < 0.1 * noise, (j, resid.mean())
        assert 0.9 * noise < resid.std() < 1.1 * noise, (j, resid.std())
        friction = np.mean((c[:, j] / r - g) * sign)  # N m
        assert friction == pytest.approx(truth.friction_torque[j], rel=0.02), j
        # against the nominal model the hidden COM offsets show (>= 0.2 x noise on average,
        # > 10 standard errors), on some loaded joint
        gn = np.asarray(g_nominal(q))[:, j]
        offsets_visible |= abs(np.mean(c[:, j] - r * gn - truth.friction[j] * sign)) > 0.2 * noise
    assert offsets_visible
    assert not arm.read().faults


def test_default_truth_is_the_papers_arm_with_seeded_com_offsets(tmp_path):
    sim = Simulator(seed=11)
    t = sim.truth
    np.testing.assert_array_equal(t.ratio, PAPER_RATIO)
    np.testing.assert_array_equal(t.friction, PAPER_FRICTION)
    offsets = np.array(list(t.params.com_offset.values()))
    assert sorted(t.params.com_offset) == sorted(sim.robot.link_names[1:])  # BASE never moves
    assert np.abs(offsets).max() <= 0.004 and np.abs(offsets).max() > 0.002
    again = TrueRobot.draw(sim.robot, seed=11)
    other = TrueRobot.draw(sim.robot, seed=12)
    np.testing.assert_array_equal(again.params.com_offset["ARM"], t.params.com_offset["ARM"])
    assert not np.allclose(other.params.com_offset["ARM"], t.params.com_offset["ARM"])
    # written out in the params format and read back (extra keys: noise, viscous)
    path = t.save(tmp_path / "truth.json")
    params = RobotParams.load(path, sim.robot)
    np.testing.assert_array_equal(params.ratio, PAPER_RATIO)
    back = TrueRobot.load(path, sim.robot)
    assert back.current_noise == t.current_noise
    np.testing.assert_array_equal(back.params.com_offset["ARM"], t.params.com_offset["ARM"])
    # the simulated true model carries the offsets and the friction torque l / r
    b = sim.model.body("ARM").id
    nominal = sim.robot.model.body_ipos[b]
    np.testing.assert_allclose(sim.model.body_ipos[b] - nominal, t.params.com_offset["ARM"])
    np.testing.assert_allclose(sim.model.dof_frictionloss, t.friction / t.ratio)


def test_current_mode_torque_is_current_over_true_ratio():
    """A joint free of friction and gravity accelerates at c / (r I)."""
    robot_truth = TrueRobot(RobotParams("gen3_lite", PAPER_RATIO, [0.0] * 6), current_noise=0.0)
    sim = Simulator(truth=robot_truth, initial_pose="zero")
    arm = sim.arm
    arm.set_mode(0, ControlMode.CURRENT)  # joint 0: vertical axis, no gravity
    c = np.zeros(6)
    c[0] = 0.5
    s0 = arm.read()
    for _ in range(50):
        s = arm.cycle(ArmCommand(current=c))
    torque = sim.applied_torque[0]
    assert torque == pytest.approx(0.5 / PAPER_RATIO[0], rel=1e-9)
    assert s.current[0] == pytest.approx(0.5, rel=1e-9)  # measured = r x applied
    full = np.zeros((6, 6))
    mujoco.mj_fullM(sim.model, sim.data, full)
    inertia = full[0, 0]  # the other joints are held
    accel = (s.dq[0] - s0.dq[0]) / (s.t - s0.t)
    assert accel == pytest.approx(torque / inertia, rel=0.02)


@pytest.mark.parametrize("arm_name", ["gen3_lite", "odd7"])
def test_a_moving_arms_current_is_its_inverse_dynamics(arm_name, tmp_path):
    """Every joint swinging under its position servo (no friction, no noise): the measured
    current is r (M ddq + C dq + g) of the true robot at the pose where it flowed
    (q - current_lag dq), ddq the recorded velocity's step over the time step, to 1e-3 of
    the servo damping's implicit share kv (dq_new - dq_old), which ``qfrc_actuator`` leaves
    out (as an inertia of 1 ms x kv it would bias a fit of the transfers)."""
    from odd_arms import serial_arm

    if arm_name == "gen3_lite":
        robot = jaxcomp.load_robot("gen3_lite")
    else:
        path = tmp_path / "odd7.xml"
        path.write_text(serial_arm(7, n=5, continuous=(0,)))
        robot = jaxcomp.load_robot(str(path))
    n, idx = len(arm_joint_names(robot)), arm_joint_indices(robot)
    moved = robot.tree.moves[idx].any(axis=0)  # the links the arm joints move
    links = [k for k, m in zip(robot.link_names, moved, strict=True) if m]
    rng = np.random.default_rng(1)
    truth = TrueRobot(
        RobotParams(
            robot.name,
            rng.uniform(0.3, 2.0, n),
            np.zeros(n),
            {k: rng.uniform(-0.004, 0.004, 3) for k in links},
            joints=arm_joint_names(robot),
        ),
        current_noise=0.0,
    )
    sim = Simulator(robot, truth, initial_pose="zero")
    arm = sim.arm
    q0 = arm.read().q
    phase = rng.uniform(0, 2 * np.pi, n)
    swing = lambda t: 0.2 * (np.sin(2 * np.pi * 0.5 * t + phase) - np.sin(phase))  # noqa: E731
    states = [arm.cycle(ArmCommand(position=q0 + swing(k * arm.dt))) for k in range(1500)]
    assert not states[-1].faults
    q, dq, c = (np.array([getattr(s, f) for s in states]) for f in ("q", "dq", "current"))
    ddq = np.diff(dq, axis=0) / arm.dt
    pose = q[1:] - arm.current_lag * dq[1:]
    params = truth.params.inertial_params(robot)
    full = lambda x: jnp.zeros(robot.nv).at[idx].set(x)  # noqa: E731
    tau = jax.jit(
        jax.vmap(
            lambda a, b, e: dynamics.inverse_dynamics(robot.tree, full(a), full(b), full(e), params)
        )
    )(pose, dq[1:], ddq)
    model = truth.ratio * np.asarray(tau)[:, idx]
    share = truth.ratio * sim.servo_kv * np.diff(dq, axis=0)  # what qfrc_actuator leaves out
    assert np.sqrt(np.mean(share**2)) > 1e-2  # A: tens of mA
    np.testing.assert_allclose(c[1:], model, atol=1e-3 * np.abs(share).max(), rtol=0)


def test_viscous_friction_adds_damping_torque():
    truth = TrueRobot(
        RobotParams("gen3_lite", PAPER_RATIO, [0.0] * 6), current_noise=0.0, viscous=[0.5] * 6
    )
    sim = Simulator(truth=truth, initial_pose="zero")
    arm = sim.arm
    arm.set_mode(0, ControlMode.VELOCITY)
    v = np.zeros(6)
    v[0] = 0.4
    for _ in range(400):
        s = arm.cycle(ArmCommand(velocity=v))
    assert s.dq[0] == pytest.approx(0.4, rel=0.01)
    assert s.current[0] / PAPER_RATIO[0] == pytest.approx(0.5 * s.dq[0], rel=0.02)


def test_effort_limit_in_current_mode_faults_and_holds():
    sim = Simulator(seed=0)
    arm = sim.arm
    arm.set_mode(0, ControlMode.CURRENT)
    c = np.zeros(6)
    c[0] = 11.0  # 11 A / 1.0282 A/(N m) = 10.7 N m > 10 N m
    with pytest.raises(HardwareFault, match="joint_0.*effort limit 10 N m") as info:
        arm.cycle(ArmCommand(current=c))
    assert sim.applied_torque[0] == pytest.approx(10.0)  # MuJoCo clipped it to the limit
    assert arm.modes == (ControlMode.POSITION,) * 6  # holding
    q = info.value.state.q
    s = arm.hold(0.2)
    assert np.abs(s.q - q).max() < 0.01
    arm.clear_faults()
    assert arm.cycle().faults == ()


def test_joint_limit_faults():
    sim = Simulator(seed=0, initial_pose=[2.74, 0.0, 0.0, 0.0, 0.0, 0.0])  # limit 2.76 rad
    arm = sim.arm
    arm.set_mode(0, ControlMode.CURRENT)
    c = np.zeros(6)
    c[0] = 0.8
    with pytest.raises(HardwareFault, match="joint_0: position .* at its limit"):
        for _ in range(1000):
            arm.cycle(ArmCommand(current=c))
    assert sim.t < 0.5


def test_external_wrench_is_felt_as_jacobian_transpose_torque():
    truth = TrueRobot(RobotParams("gen3_lite", PAPER_RATIO, [0.0] * 6), current_noise=0.0)
    sim = Simulator(truth=truth, initial_pose="home")
    arm = sim.arm
    s0 = arm.hold(0.3)
    force = np.array([5.0, -3.0, 4.0])  # N, world frame, at the end-effector point
    sim.set_wrench(force)
    s1 = arm.hold(0.5)
    jac = np.asarray(sim.robot.jacobian(s1.q, "end_effector"))[:3]
    # the servo takes up the external torque J^T F (up to 2.4 N m here) on top of gravity
    delta = (s1.current - s0.current) / truth.ratio
    np.testing.assert_allclose(delta, -jac.T @ force, atol=1e-2)
    sim.set_wrench()
    s2 = arm.hold(0.5)
    np.testing.assert_allclose(s2.current, s0.current, atol=2e-3)


def test_scripted_push_acts_only_in_its_window():
    truth = TrueRobot(RobotParams("gen3_lite", PAPER_RATIO, [0.0] * 6), current_noise=0.0)
    sim = Simulator(truth=truth)
    arm = sim.arm
    base = arm.hold(1.0).current
    sim.push(start=1.1, duration=0.3, force=[0.0, 0.0, -10.0])
    during = arm.hold(0.3).current  # t = 1.3
    after = arm.hold(1.2).current  # t = 2.5
    assert np.abs(during - base).max() > 0.5
    np.testing.assert_allclose(after, base, atol=5e-3)


@pytest.mark.parametrize("model", ["gen3_lite", "mobile_gen3_lite"])
def test_forces_beyond_ten_times_the_arms_weight_are_refused(model):
    """The push bound is 10 g times the mass the arm's first joint carries (the base's own
    mass does not count): a force just below passes, just above is refused, as is NaN."""
    sim = Simulator(model)
    m = sim.model
    carried = m.body_subtreemass[m.jnt_bodyid[sim.arm_joints[0]]]
    bound = 10 * 9.81 * carried
    assert sim.max_push_force == pytest.approx(bound) and 390 < bound < 400
    sim.push(0.0, 1.0, [0.0, 0.99 * bound, 0.0])
    sim.set_wrench([0.0, 0.0, -0.99 * bound])
    for force in ([0.0, 1.01 * bound, 0.0], [1e9, 0.0, 0.0]):
        with pytest.raises(InputError, match="push force of .* times the weight of"):
            sim.push(0.0, 1.0, force)
        with pytest.raises(InputError, match="wrench force of"):
            sim.set_wrench(force)
    with pytest.raises(InputError, match="finite vector"):
        sim.push(0.0, 1.0, [np.nan, 0.0, 0.0])
    assert len(sim.interaction.pushes) == 1


def test_rope_pulls_only_when_stretched():
    rope = Rope(np.zeros(3), free_length=0.26, stiffness=120.0)
    np.testing.assert_array_equal(rope.force(np.array([0.2, 0.0, 0.0])), 0.0)
    np.testing.assert_allclose(rope.force(np.array([0.3, 0.0, 0.0])), [-120.0 * 0.04, 0, 0])
    sim = Simulator(seed=0)
    arm = sim.arm
    ee = sim.ee_position()
    sim.attach_rope(ee + [0.3, 0.0, 0.0], free_length=0.26, stiffness=40.0)
    arm.hold(0.01)
    np.testing.assert_allclose(sim.interaction.rope_force, [40.0 * 0.04, 0, 0], atol=0.1)
    sim.detach_rope()
    sim.attach_rope(ee + [0.1, 0.0, 0.0], free_length=0.26, stiffness=40.0)
    arm.hold(0.01)
    np.testing.assert_array_equal(sim.interaction.rope_force, 0.0)
    with pytest.raises(InputError, match="stiffness"):
        sim.attach_rope(ee, 0.2, -1.0)


def test_viewer_without_display_runs_headless(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with Simulator(viewer=True) as sim:
        assert sim.viewer is None
        sim.arm.hold(0.01)


def test_realtime_pacing_follows_the_wall_clock():
    import time

    sim = Simulator(realtime=True)
    t0 = time.perf_counter()
    sim.arm.hold(0.05)
    assert time.perf_counter() - t0 >= 0.045


def test_lock_step_is_deterministic():
    a, b = Simulator(seed=5).arm, Simulator(seed=5).arm
    for arm in (a, b):
        arm.move_to(np.deg2rad([10, 0, 60, 0, -40, 0]), 0.5)
    np.testing.assert_array_equal(a.read().q, b.read().q)
    np.testing.assert_array_equal(a.read().current, b.read().current)
