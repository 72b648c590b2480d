"""The paper's calibration (identify.baseline) on synthetic sweeps made from the model.

A synthetic recording sweeps each joint from -100 to +100 deg and back at 40 deg/s (ramps of
0.1 s), 1 kHz, the other joints held; the swept joint's current is
``r_true g_true(q) + l_true d + noise`` with g_true the nominal model's gravity with known COM
offsets (jaxcomp dynamics, independent of the fit's pinocchio model).
"""

import time

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxcomp
from jaxcomp import dynamics
from jaxcomp.constants import CONTROL_RATE
from jaxcomp.errors import InputError
from jaxcomp.identify.baseline import fit_baseline, phase_fit
from jaxcomp.identify.bins import bin_sweeps
from jaxcomp.params import InertialParams
from jaxcomp.recording import Recording
from jaxcomp.robot_params import RobotParams

RATIO = np.array([1.0282, 0.3074, 1.0282, 1.9074, 2.0373, 1.9724])
FRICTION = np.array([0.5318, 1.4776, 0.6695, 0.3013, 0.3732, 0.5923])
NOISE = 0.05  # A
#: (swept joint, held pose deg): gravity levers of 12, 4.4, 0.76 and 0.72 N m on joints 1-4;
#: joint 0 (vertical axis) and joint 5 (gripper COM on its axis) are not excited.
PLAN = [
    (0, [0, 0, 0, 0, 0, 0]),
    (1, [0, 0, 0, 0, 0, 0]),
    (2, [0, 0, 0, 0, 0, 0]),
    (3, [0, 90, 0, 0, 90, 0]),
    (4, [0, 0, 0, 0, 0, 0]),
    (5, [0, 0, 0, 0, 90, 0]),
]
#: Phase errors of the truth, rad, per joint (the COM of the link each joint moves, rotated).
DELTA = np.deg2rad([0.0, 1.5, -2.0, 4.0, -5.0, 0.0])


@pytest.fixture(scope="module")
def robot():
    return jaxcomp.load_robot("gen3_lite")


def _profile(speed_deg=40.0, span_deg=100.0, ramp=0.1, rate=CONTROL_RATE):
    """Angle (rad), velocity (rad/s), direction of -span -> +span -> -span, trapezoidal speed."""
    speed, span = np.deg2rad(speed_deg), np.deg2rad(span_deg)
    acc = speed / ramp
    length = 2 * span
    total = length / speed + ramp
    t = np.arange(0.0, total, 1 / rate)
    pos = np.where(
        t < ramp,
        0.5 * acc * t**2,
        np.where(
            t < total - ramp,
            0.5 * acc * ramp**2 + speed * (t - ramp),
            length - 0.5 * acc * (total - t) ** 2,
        ),
    )
    vel = np.gradient(pos, t)
    theta = np.r_[-span + pos, span - pos]
    dtheta = np.r_[vel, -vel]
    direction = np.r_[np.ones_like(t), -np.ones_like(t)].astype(int)
    return theta, dtheta, direction


def _payload_params(robot, params, mass, com):
    """params with a point mass (kg) at com (m, end-effector frame) merged into its body."""
    s = robot.site_index("end_effector")
    b = robot.tree.site_body[s]
    p = robot.tree.site_pos[s] + robot.tree.site_rot[s] @ np.asarray(com)
    masses, coms = np.array(params.mass), np.array(params.com)
    coms[b] = (masses[b] * coms[b] + mass * p) / (masses[b] + mass)
    masses[b] += mass
    return InertialParams(masses, coms, params.inertia)


def synthetic(
    robot,
    offsets=None,
    plan=PLAN,
    ratio=RATIO,
    friction=FRICTION,
    noise=NOISE,
    gravity=(0.0, 0.0, -9.81),
    payload=(0.0, (0.0, 0.0, 0.0)),
    seed=0,
):
    """A validated Recording of ``plan``'s sweeps of the truth described by the arguments."""
    truth = RobotParams(robot.name, ratio, friction, offsets or {}).inertial_params(robot)
    if payload[0] > 0:
        truth = _payload_params(robot, truth, *payload)
    theta, dtheta, direction = _profile()
    qs, dqs, js, ds = [], [], [], []
    for j, held in plan:
        base = np.deg2rad(held)
        gap = np.tile(base, (100, 1))  # 0.1 s holding between sweeps (joint -1)
        gap[:, j] = theta[0]
        q = np.tile(base, (len(theta), 1))
        q[:, j] = theta
        dq = np.zeros_like(q)
        dq[:, j] = dtheta
        qs += [gap, q]
        dqs += [np.zeros_like(gap), dq]
        js += [np.full(len(gap), -1), np.full(len(q), j)]
        ds += [np.zeros(len(gap), int), direction]
    q, dq, joint, d = (np.concatenate(x) for x in (qs, dqs, js, ds))
    g = jax.jit(jax.vmap(lambda x: dynamics.gravity(robot.tree, x, truth, np.asarray(gravity))))
    tau = np.asarray(g(q))
    current = ratio * tau + friction * d[:, None] * (joint[:, None] == np.arange(6))
    current += np.random.default_rng(seed).normal(0.0, noise, current.shape)
    return Recording(
        t=np.arange(len(q)) / CONTROL_RATE,
        q=q,
        dq=dq,
        current=current,
        joint=joint,
        direction=d,
        model=robot.name,
        gravity=np.asarray(gravity, float),
        payload_mass=float(payload[0]),
        payload_com=np.asarray(payload[1], float),
    )


def phase_only_offsets(robot, delta=DELTA, plan=PLAN):
    """COM offsets that turn each joint's subtree gravity moment by delta_j (last joint first).

    Each offset lies in the plane perpendicular to the joint axis, on the link the joint moves
    directly, and is computed at the held pose of that joint's sweep with the offsets of the
    later links already applied: a pure phase error of delta_j for the sweep of joint j.
    """
    tree = robot.tree
    offsets = {}
    for j in reversed(range(6)):
        if delta[j] == 0:
            continue
        params = RobotParams(robot.name, RATIO, FRICTION, offsets).inertial_params(robot)
        q = np.deg2rad(dict(plan)[j])
        body = int(tree.joint_body[j])
        frames = robot.forward_kinematics(q)
        com, mass = robot.subtree_com(q, params)
        rot, pos = np.asarray(frames.rot[body]), np.asarray(frames.pos[body])
        moment = float(mass[body]) * rot.T @ (np.asarray(com[body]) - pos)
        turn = Rotation.from_rotvec(delta[j] * tree.joint_axis[j]).as_matrix() - np.eye(3)
        offsets[tree.body_names[body]] = turn @ moment / float(params.mass[body])
    return offsets


@pytest.fixture(scope="module")
def clean(robot):
    return synthetic(robot)


@pytest.fixture(scope="module")
def shifted(robot):
    offsets = phase_only_offsets(robot)
    return synthetic(robot, offsets, seed=1), offsets


# ----------------------------------------------------------------------------- Eq. (19)
def test_phase_fit():
    rng = np.random.default_rng(3)
    theta = np.linspace(-1.7, 1.7, 400)
    s, delta = phase_fit(theta, 1.7 * np.sin(theta - 0.3))
    assert s == pytest.approx(1.7, abs=1e-12) and delta == pytest.approx(-0.3, abs=1e-12)
    # a negative amplitude is a phase of pi: s >= 0, delta in [-pi, pi)
    s, delta = phase_fit(theta, -0.8 * np.sin(theta + 0.2))
    assert s == pytest.approx(0.8, abs=1e-12)
    assert delta == pytest.approx(0.2 - np.pi, abs=1e-12)
    noisy = 2.0 * np.sin(theta + 1.0) + rng.normal(0, 0.05, theta.size)
    s, delta = phase_fit(theta, noisy)
    assert abs(s - 2.0) < 0.02 and abs(delta - 1.0) < 0.01
    # weights: zero-weight samples do not count
    w = np.r_[np.ones(200), np.zeros(200)]
    bad = np.r_[np.sin(theta[:200] + 0.5), np.full(200, 99.0)]
    s, delta = phase_fit(theta, bad, w)
    assert s == pytest.approx(1.0, abs=1e-9) and delta == pytest.approx(0.5, abs=1e-9)
    assert phase_fit(theta, np.zeros_like(theta)) == (0.0, 0.0)
    with pytest.raises(InputError):
        phase_fit(theta, theta[:-1])
    with pytest.raises(InputError):
        phase_fit(theta, np.sin(theta), -np.ones_like(theta))


# ----------------------------------------------------------------------------- fits
def test_no_com_error(robot, clean):
    params = fit_baseline(clean, robot=robot)
    assert params.method == "scipy" and params.model == "gen3_lite"
    excited = [1, 2, 3, 4]
    np.testing.assert_allclose(params.ratio[excited], RATIO[excited], rtol=5e-3)
    np.testing.assert_allclose(params.friction, FRICTION, rtol=5e-3)
    assert np.all(np.abs(params.phase_shift) < np.deg2rad(0.05))
    assert params.phase_shift[0] == 0 and params.phase_shift[5] == 0
    for off in params.com_offset.values():
        assert np.linalg.norm(off) < 1e-3
    # joints gravity cannot excite borrow the mean ratio of their actuator type (M L M S S S)
    assert params.ratio[0] == params.ratio[2]
    assert params.ratio[5] == pytest.approx(params.ratio[3:5].mean(), abs=1e-15)


def test_phase_only_errors(robot, shifted, tmp_path):
    rec, offsets = shifted
    params = fit_baseline(rec, robot=robot)
    excited = [1, 2, 3, 4]
    np.testing.assert_allclose(params.ratio[excited], RATIO[excited], rtol=1e-2)
    np.testing.assert_allclose(params.friction, FRICTION, rtol=1e-2)
    np.testing.assert_allclose(params.phase_shift, DELTA, atol=np.deg2rad(0.2))
    # one link per excited joint moved, in the plane of its joint's motion, to the truth
    assert (
        set(params.com_offset) == set(offsets) == {"ARM", "FOREARM", "LOWER_WRIST", "UPPER_WRIST"}
    )
    for link, off in offsets.items():
        found = params.com_offset[link]
        b = robot.link_index(link)
        j = list(robot.tree.joint_body).index(b)
        assert abs(found @ robot.tree.joint_axis[j]) < 1e-12
        assert np.linalg.norm(found - off) < 0.1 * np.linalg.norm(off)
    assert params.ratio[0] == params.ratio[2]
    assert params.ratio[5] == pytest.approx(params.ratio[3:5].mean(), abs=1e-15)
    # standard errors: finite, small
    assert params.std is not None
    assert all(0 < s < 0.01 for s in params.std["ratio"])
    # validates, saves and loads
    path = params.save(tmp_path / "baseline.json")
    back = RobotParams.load(path, robot)
    np.testing.assert_array_equal(back.ratio, params.ratio)
    np.testing.assert_array_equal(back.friction, params.friction)
    np.testing.assert_array_equal(back.phase_shift, params.phase_shift)
    for link, off in params.com_offset.items():
        np.testing.assert_array_equal(back.com_offset[link], off)
    assert back.method == "scipy" and back.fit_seconds == params.fit_seconds


def test_nothing_excited_falls_back_to_nominal_ratios(robot, clean):
    """With no joint over the threshold there is no type mean: Kinova's nominal ratios."""
    params = fit_baseline(clean, robot=robot, threshold=np.inf)
    assert np.all(params.phase_shift == 0) and params.com_offset == {}
    np.testing.assert_array_equal(params.ratio, RobotParams.nominal(robot).ratio)
    assert params.std["ratio"] == [None] * 6


def test_payload_and_tilted_gravity(robot):
    """A wall-mounted arm (gravity along -x, tilted) with a 0.4 kg payload: no COM error."""
    gravity = 9.81 * np.array([-np.sin(0.5), 0.0, -np.cos(0.5)])
    payload = (0.4, (0.01, -0.02, 0.03))
    rec = synthetic(robot, gravity=gravity, payload=payload, seed=2)
    params = fit_baseline(rec, robot=robot)
    # joint 0 now carries a gravity lever and joint 5 the off-axis payload (about 0.09 N m):
    # both are fitted, not borrowed; joint 5's small lever makes it the noisiest
    excited = [0, 1, 2, 3, 4]
    np.testing.assert_allclose(params.ratio[excited], RATIO[excited], rtol=5e-3)
    np.testing.assert_allclose(params.friction, FRICTION, rtol=5e-3)
    assert np.all(np.abs(params.phase_shift[excited]) < np.deg2rad(0.1))
    assert params.ratio[5] != params.ratio[3:5].mean()
    assert abs(params.ratio[5] / RATIO[5] - 1) < 0.02
    assert abs(params.phase_shift[5]) < np.deg2rad(0.5)
    # ignoring the payload is visibly wrong on the wrist joints
    plain = Recording(**{**rec.__dict__, "payload_mass": 0.0})
    wrong = fit_baseline(plain, robot=robot)
    assert abs(wrong.ratio[4] / RATIO[4] - 1) > 0.05


def test_unswept_joint_borrows_its_type(robot, clean):
    """Refused by default; with ``complete=False`` (the studies' random plans) a joint without
    sweeps borrows its type's ratio and friction."""
    rec = clean.select(clean.joint != 5)
    with pytest.raises(InputError, match="joint_5 is never swept"):
        fit_baseline(rec, robot=robot)
    params = fit_baseline(rec, robot=robot, complete=False)
    assert params.ratio[5] == pytest.approx(params.ratio[3:5].mean(), abs=1e-15)
    assert params.friction[5] == pytest.approx(params.friction[3:5].mean(), abs=1e-15)


def test_timing(robot, clean):
    """About 200k samples (three rounds of the plan): the fit on its bins well under 0.5 s."""
    n = clean.n_samples
    big = Recording(
        **{
            **clean.__dict__,
            **{k: np.concatenate([getattr(clean, k)] * 3) for k in ("q", "dq", "current")},
            "joint": np.concatenate([clean.joint] * 3),
            "direction": np.concatenate([clean.direction] * 3),
            "t": np.arange(3 * n) / CONTROL_RATE,
        }
    )
    bins = bin_sweeps(big)
    fit_baseline(big, robot=robot, bins=bins)  # warm up
    start = time.process_time()  # CPU time: robust to a busy machine
    params = fit_baseline(big, robot=robot, bins=bins)
    elapsed = time.process_time() - start
    np.testing.assert_allclose(params.ratio[1:5], RATIO[1:5], rtol=5e-3)
    assert elapsed < 0.5, f"fit of {big.n_samples} samples took {elapsed:.2f} s CPU"
