"""The MJX simulator: plans, batched truths, and agreement with the CPU Simulator.

MJX compiles slowly on a 2-core CPU (~25-40 s for the chunk function): one module-scoped run of
4 worlds (settle 500 steps + a 350-step plan) serves every unmarked MJX test.
"""

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcomp import dynamics
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware import ArmCommand, Push, Simulator, TrueRobot
from jaxcomp.hardware.mjx import (
    AGREEMENT,
    FAULT_EFFORT,
    FAULT_STOPPED,
    BatchTruth,
    MjxSimulator,
    Move,
    Policy,
    PushSchedule,
    Reduction,
    fault_names,
    reference_trajectory,
    servo_gains,
    true_inertial_params,
)
from jaxcomp.robot_params import RobotParams

ROOT = Path(__file__).resolve().parents[1]
STEP = np.deg2rad([6.0, 6.0, 5.0, 4.0, -5.0, 6.0])  # rad, the plan's move (joint 1 saturates)
TILT = 9.81 * np.array([-np.sin(0.35), 0.0, -np.cos(0.35)])  # m/s^2, a base tilted 20 deg


def _cpu_truth(noise: float = 0.0) -> TrueRobot:
    sim = Simulator("gen3_lite", seed=3)
    return dataclasses.replace(sim.truth, current_noise=noise)


def _plan(start):
    """Move every joint (up to 6 deg at 0.6 rad/s), then hold 75 ms: 350 steps."""
    return [Move(start + STEP, 0.6), Move(None, 0.6, settle=0.075)]


# ----------------------------------------------------------------------------- no MJX
def test_reference_trajectory_is_what_move_to_sends():
    sim = Simulator("gen3_lite", seed=1)
    arm = sim.arm
    sent = []
    exchange = arm._exchange

    def spy(modes, position, velocity, current):
        sent.append(position.copy())
        return exchange(modes, position, velocity, current)

    arm._exchange = spy
    start = arm.read().q.copy()
    a = np.deg2rad([10.0, 30.0, 80.0, 20.0, 50.0, -30.0])
    b = np.deg2rad([0.0, 20.0, 90.0, 0.0, 60.0, 0.0])
    moves = [Move(a, 0.7), Move(None, 0.3, settle=0.013), Move(b, 0.2, accel=1.0, settle=0.01)]
    moves.append((a, 0.35))  # plain tuples work too
    arm.move_to(a, 0.7)
    arm.move_to(sent[-1].copy(), 0.3, settle=0.013)  # Move(None): stay at the target
    arm.move_to(b, 0.2, accel=1.0, settle=0.01)
    arm.move_to(a, 0.35)
    q_ref = reference_trajectory(moves, start, limits=arm.limits.position, max_speed=1.0)
    np.testing.assert_array_equal(q_ref, np.array(sent))  # bit for bit


def test_reference_trajectory_refuses_bad_moves():
    start = np.zeros(6)
    assert reference_trajectory([], start).shape == (0, 6)
    with pytest.raises(InputError, match="speed"):
        reference_trajectory([(np.ones(6), 0.0)], start)
    with pytest.raises(InputError, match=r"speed must be in \(0, 1\]"):
        reference_trajectory([(np.ones(6), 1.5)], start, max_speed=1.0)
    with pytest.raises(InputError, match="pose must be a finite"):
        reference_trajectory([(np.full(6, np.nan), 0.5)], start)
    with pytest.raises(InputError, match="beyond its limits"):
        reference_trajectory([(np.full(6, 3.0), 0.5)], start, limits=np.tile([-2.0, 2.0], (6, 1)))


def test_batch_truth_from_truths_and_arrays():
    sim = Simulator("gen3_lite", seed=3)
    robot, t = sim.robot, sim.truth
    other = TrueRobot.draw(robot, seed=4, viscous=[0.1] * 6)
    bt = BatchTruth.from_truths(robot, [t, other], payload=[0.0, 0.4], gravity=TILT)
    assert bt.worlds == 2 and bt.com_offset.shape == (2, 7, 3)
    np.testing.assert_array_equal(
        bt.com_offset[0, robot.link_index("ARM")], t.params.com_offset["ARM"]
    )
    np.testing.assert_array_equal(bt.viscous[1], 0.1)
    np.testing.assert_array_equal(bt.gravity, [TILT, TILT])
    back = bt.true_robot(robot, 0)
    np.testing.assert_array_equal(back.friction, t.friction)
    np.testing.assert_array_equal(back.params.com_offset["ARM"], t.params.com_offset["ARM"])
    arrays = BatchTruth.from_arrays(robot, t.ratio, t.friction, payload=np.zeros(5))
    assert arrays.worlds == 5 and np.all(arrays.gravity == [0.0, 0.0, -9.81])
    with pytest.raises(InputError, match="ratio must be > 0"):
        BatchTruth.from_arrays(robot, -t.ratio, t.friction)
    with pytest.raises(InputError, match="does not fit"):
        BatchTruth.from_arrays(robot, t.ratio, np.ones(4))


@pytest.mark.parametrize("seed", range(4))
def test_device_rows_find_each_recorded_world_on_its_device(seed):
    """Random recorded worlds of a batch split over 1-4 devices: each world's local index on
    its device and its place in the devices' stacked outputs lead back to it, in order."""
    from jaxcomp.hardware.mjx.mesh import device_rows

    rng = np.random.default_rng(seed)
    d = int(rng.integers(1, 5))
    worlds = d * int(rng.integers(1, 9))
    rows = rng.choice(worlds, int(rng.integers(0, worlds + 1)), replace=False)
    local, where = device_rows(rows, worlds, d, 4)
    m = local.size // d
    assert local.size == d * m and m % 4 == 0 and m >= 4
    per = worlds // d
    back = local[where] + (where // m) * per  # device k's block starts at world k per
    np.testing.assert_array_equal(back, rows)
    assert ((local >= 0) & (local < per)).all() and len(set(where)) == rows.size


def test_servo_gains_are_the_cpu_simulators():
    truth = _cpu_truth()
    sim = Simulator("gen3_lite", truth=truth)
    bt = BatchTruth.from_truths(sim.robot, [truth, TrueRobot.draw(sim.robot, seed=9)])
    kp, kv = servo_gains(sim.robot, true_inertial_params(sim.robot, bt), bt.gravity)
    np.testing.assert_allclose(kp[0], sim.servo_kp, rtol=1e-12)
    np.testing.assert_allclose(kv[0], sim.servo_kv, rtol=1e-12)
    assert np.abs(kp[1] / kp[0] - 1).max() > 1e-4  # each world's own inertia


def test_servo_holds_a_heavily_loaded_roll_joint(tmp_path):
    """A generated arm whose roll joint 3 carries a bent wrist (I_min ~1.6e-4 kg m^2, up to
    ~2.7 N m of gravity): I_min w^2 alone would let it sag ~66 mrad (and fault a plan's
    following-error check); the servo is stiffened to hold its largest gravity load within
    HOLD_SAG, the same on the CPU Simulator and in the MJX worlds, and the CPU Simulator holds
    the worst of its gain poses within it."""
    from odd_arms import serial_arm

    from jaxcomp.hardware.mjx.gains import servo_loads
    from jaxcomp.hardware.servo import HOLD_SAG, gain_poses, pd_gains
    from jaxcomp.robot import load_robot
    from jaxcomp.robot_params import arm_joint_indices

    path = tmp_path / "bent_wrist.xml"
    path.write_text(serial_arm(33, n=7, scale=0.9, continuous=(0,), gripper=True))
    robot = load_robot(path)
    truth = TrueRobot.draw(robot, seed=5)
    bt = BatchTruth.from_truths(robot, [truth])
    params = true_inertial_params(robot, bt)
    kp, kv = servo_gains(robot, params, bt.gravity)
    poses = gain_poses(robot.joint_limits[arm_joint_indices(robot)])
    i_min, i_max, load = (a[0] for a in servo_loads(robot, params, bt.gravity))
    soft, _ = pd_gains(i_min, i_max, np.zeros_like(load), 500.0)
    j = int(np.argmax(load / soft))
    assert load[j] / soft[j] > 3 * HOLD_SAG  # the inertia rule alone sags beyond the hold
    assert load[j] / kp[0, j] == pytest.approx(HOLD_SAG, rel=1e-9)
    stiff = kp[0] > soft * (1 + 1e-9)
    assert stiff.sum() == 1 and stiff[j]  # only that joint's servo is stiffened
    world = jax.tree_util.tree_map(lambda a: a[0], params)
    grav = jax.jit(jax.vmap(lambda q: dynamics.gravity(robot.tree, q, world)))(poses)
    pose = poses[np.argmax(np.abs(np.asarray(grav)[:, j]))]
    sim = Simulator(robot, truth=truth, initial_pose=pose)
    np.testing.assert_allclose(sim.servo_kp, kp[0], rtol=1e-9)
    np.testing.assert_allclose(sim.servo_kv, kv[0], rtol=1e-9)
    for _ in range(500):  # 0.5 s of holding the pose
        state = sim.arm.cycle(ArmCommand(position=pose))
    sag = abs(state.q[j] - pose[j])
    friction = truth.friction_torque[j]
    assert (load[j] - friction) / kp[0, j] - 2e-3 < sag <= HOLD_SAG, sag  # what the servo gives


# ----------------------------------------------------------------------------- one MJX run
@pytest.fixture(scope="session")  # session: never torn down between a worker's tests
def batch():
    """4 worlds through one plan: 0 = the CPU test truth, 1 = the same with current noise,
    2 = friction-free with a 0.6 kg payload, 3 = friction-free on a base tilted 20 deg."""
    truth = _cpu_truth()
    cpu = Simulator("gen3_lite", truth=truth)
    robot, arm = cpu.robot, cpu.arm
    start = arm.read().q.copy()
    q_ref = reference_trajectory(_plan(start), start)
    cpu_rec = [arm.cycle(ArmCommand(position=r)) for r in q_ref]
    bare = dataclasses.replace(truth, params=RobotParams("gen3_lite", truth.ratio, [0.0] * 6))
    truths = [truth, dataclasses.replace(truth, current_noise=0.05), bare, bare]
    gravity = np.array([[0.0, 0.0, -9.81]] * 3 + [TILT])
    bt = BatchTruth.from_truths(robot, truths, payload=[0.0, 0.0, 0.6, 0.0], gravity=gravity)
    mjx_sim = MjxSimulator(robot, payload=True)
    chunks, calls = [], []
    rows = np.arange(len(q_ref))[:, None] % 7.0  # a weight per sample, for the reduction
    reduce = Reduction(
        lambda c, x, q, dq, cur, ok: (c[0] + ok * x * cur, c[1] + ok), (np.zeros(6), 0.0), rows, 1
    )
    rec = mjx_sim.run(
        bt,
        q_ref,
        seed=5,
        progress=lambda done, total: calls.append((done, total)),
        on_chunk=lambda first, c: chunks.append((first, c)),
        reduce=reduce,
    )
    return dict(
        cpu=cpu,
        cpu_rec=cpu_rec,
        start=start,
        q_ref=q_ref,
        truth=bt,
        sim=mjx_sim,
        rec=rec,
        chunks=chunks,
        calls=calls,
    )


@pytest.mark.xdist_group("mjx-batch")  # one worker computes the batch fixture
def test_mjx_agrees_with_the_cpu_simulator(batch):
    """Same truth, no noise, same q_ref in POSITION mode: the tolerances of ``AGREEMENT``,
    through stick-slip and the servo clamped at joint 1's effort limit."""
    rec, cpu_rec = batch["rec"], batch["cpu_rec"]
    q = np.array([s.q for s in cpu_rec])
    dq = np.array([s.dq for s in cpu_rec])
    cur = np.array([s.current for s in cpu_rec])
    assert rec.q.shape == (4, len(q), 6)
    np.testing.assert_allclose(rec.q_start[0], batch["start"], atol=AGREEMENT["q"], rtol=0)
    np.testing.assert_allclose(rec.q[0], q, atol=AGREEMENT["q"], rtol=0)
    np.testing.assert_allclose(rec.dq[0], dq, atol=AGREEMENT["dq"], rtol=0)
    np.testing.assert_allclose(rec.current[0], cur, atol=AGREEMENT["current"], rtol=0)
    np.testing.assert_allclose(rec.t, [s.t for s in cpu_rec], atol=1e-12)
    assert np.abs(dq).max() > 0.3 and np.abs(cur).max() > 1.0  # a real motion under load
    limit = batch["cpu"].effort[1] * batch["truth"].ratio[0, 1]
    assert (np.abs(cur[:, 1]) >= limit - 1e-9).sum() > 5  # the servo saturated
    assert (rec.fault_step == -1).all()


@pytest.mark.xdist_group("mjx-batch")  # one worker computes the batch fixture
def test_noise_is_additive_gaussian_and_leaves_the_motion_alone(batch):
    rec = batch["rec"]
    np.testing.assert_array_equal(rec.q[1], rec.q[0])
    e = rec.current[1] - rec.current[0]
    assert abs(e.mean()) < 0.01 and 0.045 < e.std() < 0.055


def _residual(robot, rec, w, params, gravity, ratio):
    """Friction-free world w: applied torque minus M qacc + C dq + g (N m), at every step the
    servo is not clamped; the step's qacc is the recorded velocity difference / dt."""
    q, dq = rec.q[w, :-1], rec.dq[w, :-1]  # the state each step starts from
    qacc = np.diff(rec.dq[w], axis=0) / CONTROL_PERIOD
    tau = rec.current[w, 1:] / ratio
    mass, bias = _dynamics(robot)(q, dq, params, jnp.asarray(gravity))
    inertial = np.einsum("tij,tj->ti", np.asarray(mass), qacc)
    model = inertial + np.asarray(bias)
    free = (np.abs(tau) < 0.999 * robot.effort_limits).all(axis=1)
    return (tau - model)[free]


def _dynamics(robot, cache={}):  # noqa: B006 - one compiled function per robot
    if id(robot) not in cache:
        tree = robot.tree

        @jax.jit
        def fn(q, dq, params, g):
            mass = jax.vmap(lambda x: dynamics.mass_matrix(tree, x, params))(q)
            bias = jax.vmap(lambda x, v: dynamics.bias(tree, x, v, params, g))(q, dq)
            return mass, bias

        cache[id(robot)] = (robot, fn)
    return cache[id(robot)][1]


@pytest.mark.xdist_group("mjx-batch")  # one worker computes the batch fixture
def test_payload_and_mounting_follow_the_true_dynamics(batch):
    """Friction-free worlds 2 (0.6 kg payload: its own MJX body) and 3 (tilted base): the
    recorded torque is M qacc + C dq + g of jaxcomp's dynamics with the payload folded into
    GRIPPER_FRAME / the tilted gravity, to 1e-6 N m: the servo's damping is measured as the
    implicit integrator applies it (at the step's new velocity)."""
    rec, bt, robot = batch["rec"], batch["truth"], batch["cpu"].robot
    params = true_inertial_params(robot, bt)
    for w in (2, 3):
        pw = jax.tree_util.tree_map(lambda a, w=w: a[w], params)
        res = _residual(robot, rec, w, pw, bt.gravity[w], bt.ratio[w])
        assert len(res) > 300 and np.abs(res).max() < 1e-6, np.abs(res).max()
        # without the payload / with upright gravity the model misses by far
        plain = jax.tree_util.tree_map(lambda a: a[0], params)
        wrong = _residual(robot, rec, w, plain, bt.gravity[0], bt.ratio[w])
        assert np.abs(wrong).max() > 0.1


@pytest.mark.xdist_group("mjx-batch")  # one worker computes the batch fixture
def test_chunks_stream_the_same_samples(batch):
    rec, chunks, calls = batch["rec"], batch["chunks"], batch["calls"]
    t = len(batch["q_ref"])
    assert calls[-1] == (t, t) and [c[0] for c in calls] == sorted(c[0] for c in calls)
    q = np.concatenate([c.q for _, c in chunks], axis=1)
    cur = np.concatenate([c.current for _, c in chunks], axis=1)
    np.testing.assert_array_equal(q, rec.q)
    np.testing.assert_array_equal(cur, rec.current)
    assert [first for first, _ in chunks][0] == 0
    # the reduction on the device saw every recorded sample once, noise included
    weights = np.arange(t) % 7.0
    np.testing.assert_allclose(rec.reduced[0], np.einsum("r,wrn->wn", weights, rec.current))
    np.testing.assert_array_equal(rec.reduced[1], np.full(4, t))


# ----------------------------------------------------------------------------- closed loop
# (its agreement with the CPU Simulator + control loop: tests/test_study_control.py)
def _hold_policy(p, s, obs):
    """A joint PD about the settled pose (per-world gain ``k`` A/rad) that counts its samples
    and stops at sample ``stop_at``."""
    cmd = -p["k"] * (obs.q - s["q0"]) - 0.05 * obs.dq
    return cmd, {"q0": s["q0"], "n": s["n"] + 1}, s["n"] + 1 > p["stop_at"]


def test_push_schedule_from_pushes_and_checks():
    sched = PushSchedule.from_pushes([[Push(0.1, 0.2, np.array([1.0, 2.0, 3.0]))], []])
    assert sched.force.shape == (2, 1, 3) and sched.start[0, 0] == 0.1
    assert not sched.force[1].any() and sched.duration[1, 0] > 0  # padding: no force
    with pytest.raises(InputError, match="forces only"):
        PushSchedule.from_pushes([[Push(0.0, 1.0, np.ones(3), np.ones(3))]])
    with pytest.raises(InputError, match=r"shape \(3, P\)"):
        sched.checked(3)
    bad = sched._replace(duration=np.array([[0.0], [1.0]]))
    with pytest.raises(InputError, match="duration > 0"):
        bad.checked(2)
    assert fault_names(FAULT_EFFORT | FAULT_STOPPED) == ["effort limit", "stopped by the policy"]


def test_closed_loop_refuses_bad_input():
    sim = MjxSimulator("gen3_lite")
    truth = BatchTruth.from_truths(sim.robot, [_cpu_truth()] * 2)
    params = {"k": np.ones(2), "stop_at": np.full(2, 10)}
    state = {"q0": np.zeros((2, 6)), "n": np.zeros(2, int)}

    def run(**kw):
        args = dict(
            truth=truth, policy=Policy(None, _hold_policy), params=params, state=state, steps=10
        )
        args.update(kw)
        return sim.run_closed_loop(**args)

    with pytest.raises(InputError, match="steps must be >= 1"):
        run(steps=0)
    with pytest.raises(InputError, match="settle_steps must be >= 1"):
        run(settle_steps=0)
    with pytest.raises(InputError, match="every must be >= 0"):
        run(every=-1)
    with pytest.raises(InputError, match=r"reference must be a finite \(steps \+ 1 = 11, m\)"):
        run(reference=np.zeros((10, 3)))
    with pytest.raises(InputError, match="reference must be a finite"):
        run(reference=np.full((11, 3), np.nan))
    with pytest.raises(InputError, match="leading axis of 2 worlds"):
        run(params={"k": np.ones(3), "stop_at": np.full(2, 10)})
    with pytest.raises(InputError, match="leading axis of 2 worlds"):
        run(state={"q0": np.zeros(6), "n": np.zeros(2, int)})
    with pytest.raises(InputError, match="start >= 0"):
        run(pushes=PushSchedule(np.full((2, 1), -0.1), np.ones((2, 1)), np.zeros((2, 1, 3))))
    with pytest.raises(InputError, match="policy must be a function"):
        run(policy=None)
    assert not sim.compiled_keys  # nothing was compiled for any of them


# ----------------------------------------------------------------------------- slow
@pytest.mark.slow
@pytest.mark.xdist_group("mjx-batch")  # one worker computes the batch fixture
def test_float32_decimated_run_tracks_float64(batch):
    """float32, every 2nd sample: within 1e-4 rad and 0.05 A (the current noise) of the
    float64 run (measured: 2.4e-5 rad, 0.036 A at the start of a move, median 1e-4 A)."""
    sim32 = MjxSimulator(batch["cpu"].robot, payload=True, dtype=jnp.float32)
    rec = sim32.run(batch["truth"], batch["q_ref"], seed=5, every=2)
    ref = batch["rec"]
    assert rec.q.dtype == np.float32 and rec.q.shape[1] == -(-ref.q.shape[1] // 2)
    np.testing.assert_allclose(rec.t, ref.t[::2])
    np.testing.assert_allclose(rec.q, ref.q[:, ::2], atol=1e-4)
    quiet = [0, 2, 3]  # world 1's noise draws differ between float32 and float64
    cur, cur64 = rec.current[quiet], ref.current[quiet, ::2]
    np.testing.assert_allclose(cur, cur64, atol=0.05)
    assert np.median(np.abs(cur - cur64)) < 1e-3


@pytest.mark.slow
def test_sharded_over_two_devices_agrees_with_the_cpu_simulator():
    """A 2-device CPU mesh (forced host devices), 3 worlds padded to 4."""
    script = textwrap.dedent(
        """
        import dataclasses, numpy as np
        from jaxcomp.hardware import ArmCommand, Simulator
        from jaxcomp.hardware.mjx import (AGREEMENT, BatchTruth, Move, MjxSimulator,
            batch_mesh, reference_trajectory)
        sim = Simulator("gen3_lite", seed=3)
        truth = dataclasses.replace(sim.truth, current_noise=0.0)
        cpu = Simulator("gen3_lite", truth=truth)
        start = cpu.arm.read().q.copy()
        q_ref = reference_trajectory([Move(start + 0.05, 0.5)], start)[:150]
        q = np.array([cpu.arm.cycle(ArmCommand(position=r)).q for r in q_ref])
        mesh = batch_mesh(2)
        bt = BatchTruth.from_truths(cpu.robot, [truth] * 3)
        rec = MjxSimulator(cpu.robot, mesh=mesh, chunk_steps=50).run(bt, q_ref)
        assert rec.q.shape == (3, 150, 6), rec.q.shape
        err = np.abs(rec.q - q[None]).max()
        assert err < AGREEMENT["q"], err
        print("sharded ok", err)
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "sharded ok" in out.stdout


@pytest.mark.slow
def test_bench_runs_on_cpu():
    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "experiments" / "bench_mjx.py"),
            "--worlds",
            "2",
            "--steps",
            "20",
            "--settle",
            "10",
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "world-steps/s" in out.stdout and "backend" in out.stdout


@pytest.mark.slow
def test_closed_loop_sharded_stops_and_holds():
    """The closed loop on a 2-device CPU mesh, 3 worlds padded to 4: a joint PD policy that
    stops at sample 30 (world 0) or never (1, 2); world 2's target is 0.5 rad off on joint 1,
    so that its first command, 10 A, asks 32 N m of joint 1 (effort fault at sample 1).
    The same numbers on one device with another chunking."""
    script = textwrap.dedent(
        """
        import numpy as np
        from jaxcomp.hardware.mjx import (BatchTruth, FAULT_EFFORT, FAULT_STOPPED,
            MjxSimulator, Policy, batch_mesh)
        from jaxcomp.hardware import TrueRobot
        from jaxcomp.robot import load_robot

        def policy(p, s, obs):
            cmd = -p["k"] * (obs.q - s["q0"]) - 0.05 * obs.dq
            return cmd, {"q0": s["q0"], "n": s["n"] + 1}, s["n"] + 1 > p["stop_at"]

        def init(p, obs):
            return {"q0": obs.q + p["offset"], "n": obs.q[0].astype(int) * 0}

        robot = load_robot("gen3_lite")
        truth = BatchTruth.from_truths(robot, [TrueRobot.draw(robot, seed=s) for s in range(3)])
        offset = np.zeros((3, 6)); offset[2, 1] = 0.5
        params = {"k": np.full(3, 20.0), "stop_at": np.array([30, 10**6, 10**6]),
                  "offset": offset}
        sim = MjxSimulator(robot, mesh=batch_mesh(2), chunk_steps=50)
        rec = sim.run_closed_loop(truth, Policy(init, policy), params, None, 120, every=1, seed=1)
        assert rec.q.shape == (3, 120, 6), rec.q.shape
        assert list(rec.fault_step) == [30, -1, 1], rec.fault_step
        assert list(rec.fault_code) == [FAULT_STOPPED, 0, FAULT_EFFORT], rec.fault_code
        assert list(rec.state["n"]) == [30, 121, 1], rec.state["n"]
        held = np.abs(rec.q[0, 30:] - rec.q[0, 29]).max()  # the servo catches the sag
        assert held < 0.02 and np.abs(rec.dq[0, -20:]).max() < 0.01, held
        again = MjxSimulator(robot, chunk_steps=40).run_closed_loop(
            truth, Policy(init, policy), params, None, 120, every=1, seed=1)
        err = np.abs(again.q - rec.q).max()
        assert err < 1e-12, err
        print("closed loop sharded ok", held, err)
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "closed loop sharded ok" in out.stdout


def test_light_joint_friction_solve_converges(tmp_path):
    """The friction-loss solve converges on a light distal joint (``LS_ITERATIONS``).

    A state of the calibration study (``serial_arm(31, n=6, continuous=(0, 3))``, its world
    261, plan random:4 group 1, sweep 2, step 1030) where the last roll joint (1.8e-4 kg m^2,
    friction loss 1.35 N m) sticks: with the line search capped at 12 steps the Newton solve
    stopped with a gradient of 1.47 N m and the joint reached -2.2 rad/s in this one step (an
    overspeed fault in 671 of the study's 1024 worlds, never on the CPU Simulator)."""
    from mujoco.mjx._src import solver
    from odd_arms import serial_arm

    from jaxcomp.hardware.mjx.model import WORLD_MODEL_FIELDS
    from jaxcomp.hardware.mjx.step import implicitfast_step
    from jaxcomp.robot import load_robot
    from jaxcomp.studies.truth_draw import TruthSpread, draw_truth, truth_rows

    path = tmp_path / "light_wrist.xml"
    path.write_text(serial_arm(31, n=6, continuous=(0, 3)))
    robot = load_robot(path)
    truth = truth_rows(draw_truth(robot, 262, 0, TruthSpread()), [261])
    sim = MjxSimulator(robot)
    f = {k: jnp.asarray(v[0]) for k, v in sim.world_fields(truth).items()}
    m = sim.mjx_model.tree_replace({k: f[k] for k in WORLD_MODEL_FIELDS if k in f})
    qpos = [-1.1885909612824683, -1.3925628773968488, -0.36986310476332523]
    qpos += [1.1796018047594437, 1.3229811692632665, -1.2083089309194148]
    qvel = [0.043674238818253996, 0.5317859851026709, 0.0020764718494438246]
    qvel += [-0.03704584491771476, 0.008857710276969875, -0.0107970808281381]
    warm = [-58.390835486917304, -0.18541741370240436, -2.9057061693150503]
    warm += [42.074798157248225, -8.300016117775453, 16.887257402342463]
    target = [-1.1887383698154108, -1.3880598926175611, -0.3692281280467291]
    target += [1.178732247465514, 1.3227243072141768, -1.207787412146084]
    with jax.enable_x64(True):
        d = sim.mjx_data.replace(
            qpos=jnp.asarray(qpos),
            qvel=jnp.asarray(qvel),
            qacc_warmstart=jnp.asarray(warm),
            ctrl=f["kp"] * jnp.asarray(target),
        )
        _, dq, _, _, d_fwd = jax.jit(implicitfast_step(sim.model, jnp.float64))(m, d)
        grad = float(jnp.linalg.norm(solver.Context.create(m, d_fwd).grad))
    assert grad < 1e-6  # N m (capped line search: 1.47)
    assert abs(float(dq[5])) < 0.05  # rad/s: the joint sticks (capped: 2.2, the limit is 2)
