"""The calibration plan and the simulator's true robot for arms other than the Gen3 Lite.

The arms are written by the tests: serial MJCF arms with continuous joints, a short-ranged
joint, limits that exclude zero, a coupled two-finger gripper on slide joints, a small light
arm with low effort limits, no keyframes and no sites; and a URDF. The Gen3 Lite's plan and
truth are pinned bit for bit.
"""

import hashlib
import json
import math

import numpy as np
import pytest

import jaxcomp
from jaxcomp.errors import ModelError
from jaxcomp.hardware.mjx.truth import BatchTruth
from jaxcomp.hardware.truth import (
    FRICTION_LOSS,
    PAPER_FRICTION,
    PAPER_RATIO,
    RATIO_SPREAD,
    TrueRobot,
    current_scale,
    friction_loss_range,
    model_current_noise,
    stated_truth,
    truth_centre,
)
from jaxcomp.identify.plan_checks import plan_issues
from jaxcomp.identify.plan_design import default_plan, inner_limits, sweep_window
from jaxcomp.robot_params import arm_joint_indices

AXES = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1"}


def serial_mjcf(name: str, joints: list[tuple], gripper: bool = False, custom: str = "") -> str:
    """A serial arm: one capsule link per joint (axis "x"/"y"/"z", range (lo, hi) deg or None
    for a continuous joint, effort limit N m or None, link length m, link mass kg); with
    ``gripper``, two fingers on slide joints that an equality couples. No keyframes, no sites."""
    bodies, ends = [], []
    for k, (axis, limits, effort, length, mass) in enumerate(joints):
        attrs = f'name="j{k}" axis="{AXES[axis]}"'
        attrs += f' range="{limits[0]} {limits[1]}"' if limits else ' limited="false"'
        if effort is not None:
            attrs += f' actuatorfrcrange="{-effort} {effort}"'
        pos = 0.05 if k == 0 else joints[k - 1][3]
        radius = 0.02 if mass > 0.3 else 0.012
        bodies.append(
            f'<body name="link{k}" pos="0 0 {pos}"><joint {attrs}/>'
            f'<geom type="capsule" fromto="0 0 0 0 0 {length}" size="{radius}" mass="{mass}"/>'
        )
        ends.append("</body>")
    fingers = equality = ""
    if gripper:
        tip = joints[-1][3]
        fingers = "".join(
            f'<body name="finger_{s}" pos="0 {0.01 * y} {tip}"><joint name="finger_{s}" '
            f'type="slide" axis="0 {y} 0" range="0 0.03"/><geom type="box" size="0.005 0.005 '
            f'0.02" pos="0 0 0.02" mass="0.02"/></body>'
            for s, y in (("a", 1), ("b", -1))
        )
        equality = (
            '<equality><joint joint1="finger_a" joint2="finger_b" polycoef="0 1 0 0 0"/></equality>'
        )
    return (
        f'<mujoco model="{name}"><compiler angle="degree" autolimits="true"/>'
        '<option gravity="0 0 -9.81"/><worldbody>'
        '<geom type="plane" size="1 1 0.01" contype="0" conaffinity="0"/>'
        + "".join(bodies)
        + fingers
        + "".join(ends)
        + f"</worldbody>{equality}{custom}</mujoco>"
    )


def urdf_arm() -> str:
    """A 5-joint URDF arm: a continuous base joint, revolute joints with limits and efforts."""
    links, joints = [], []
    spec = [  # type, axis, (lower, upper) rad, effort N m, offset z m, link mass kg
        ("continuous", "0 0 1", None, 20.0, 0.08, 1.0),
        ("revolute", "0 1 0", (-2.0, 2.0), 20.0, 0.10, 0.8),
        ("revolute", "0 1 0", (-2.5, 2.5), 10.0, 0.25, 0.6),
        ("revolute", "0 1 0", (-1.8, 1.8), 5.0, 0.22, 0.3),
        ("revolute", "1 0 0", (-2.9, 2.9), 5.0, 0.08, 0.2),
    ]
    for k, mass in enumerate([1.5] + [row[-1] for row in spec]):  # base link, then each
        i = 0.002 * mass
        links.append(
            f'<link name="l{k}"><inertial><origin xyz="0 0.005 0.06"/><mass value="{mass}"/>'
            f'<inertia ixx="{i}" iyy="{i}" izz="{i / 2}" ixy="0" ixz="0" iyz="0"/></inertial>'
            "</link>"
        )
    for k, (kind, axis, limits, effort, z, _) in enumerate(spec):
        lim = f'lower="{limits[0]}" upper="{limits[1]}" ' if limits else ""
        joints.append(
            f'<joint name="q{k}" type="{kind}"><parent link="l{k}"/><child link="l{k + 1}"/>'
            f'<origin xyz="0 0 {z}"/><axis xyz="{axis}"/>'
            f'<limit {lim}effort="{effort}" velocity="2"/></joint>'
        )
    return '<robot name="urdf5">' + "".join(links + joints) + "</robot>"


#: 7 joints: three continuous, one of +-30 deg, a gripper; heavy enough that joint 1's sweeps
#: are cut by its effort limit.
SEVEN = serial_mjcf(
    "seven",
    [
        ("z", None, 40, 0.25, 2.0),
        ("y", (-130, 130), 40, 0.3, 1.8),
        ("z", None, 20, 0.25, 1.2),
        ("y", (-30, 30), 20, 0.25, 1.0),
        ("z", (-170, 170), 8, 0.1, 0.6),
        ("y", (-120, 120), 8, 0.1, 0.5),
        ("z", None, 4, 0.08, 0.3),
    ],
    gripper=True,
)
#: A small light arm (Dynamixel-like: 1-1.5 N m at 0.6 A/(N m), no current limit stated)
#: with a gripper.
SMALL = serial_mjcf(
    "small",
    [
        ("z", (-170, 170), 1.5, 0.06, 0.12),
        ("y", (-105, 105), 1.5, 0.13, 0.14),
        ("y", (-100, 90), 1.5, 0.124, 0.13),
        ("y", (-100, 110), 1.0, 0.126, 0.1),
    ],
    gripper=True,
    custom='<custom><numeric name="jaxcomp_nominal_ratio" data="0.6"/></custom>',
)
#: 3 joints, two whose limits exclude zero, one without an effort limit.
THREE = serial_mjcf(
    "three",
    [
        ("z", (-90, 90), None, 0.1, 0.5),
        ("y", (20, 160), 10, 0.2, 0.5),
        ("y", (-150, -40), 10, 0.2, 0.4),
    ],
)
ARMS = {"seven.xml": SEVEN, "small.xml": SMALL, "three.xml": THREE, "urdf5.urdf": urdf_arm()}


@pytest.fixture(scope="module")
def robots(tmp_path_factory):
    folder = tmp_path_factory.mktemp("arms")
    out = {}
    for name, text in ARMS.items():
        path = folder / name
        path.write_text(text)
        out[name.split(".")[0]] = jaxcomp.load_robot(path)
    return out


@pytest.fixture(scope="module")
def plans(robots):
    return {name: default_plan(robot) for name, robot in robots.items()}


# --------------------------------------------------------------------- the plan
def test_sweep_window_and_inner_limits():
    deg = math.radians
    assert sweep_window(-1.0, 1.0, -2.0, 2.0) == (-1.0, 1.0)  # inside: as asked
    assert sweep_window(-1.0, 1.0, -0.5, 0.5) == (-0.5, 0.5)  # cut at both limits
    assert sweep_window(-1.0, 1.0, 0.5, 3.0) == (0.5, 2.5)  # moved away from the lower limit
    assert sweep_window(-1.0, 1.0, -3.0, -0.5) == (-2.5, -0.5)
    inner = inner_limits(np.array([[-np.inf, np.inf], [-deg(30), deg(30)], [-1e-3, 1e-3]]))
    assert np.isinf(inner[0]).all()
    np.testing.assert_allclose(np.degrees(inner[1]), [-27.0, 27.0])  # 5 % of the range
    assert inner[2, 0] > inner[2, 1]  # 1 deg at least: nothing left


@pytest.mark.parametrize("name", list(ARMS))
def test_default_plan_of_any_arm(robots, plans, name):
    """Every current-controlled joint swept, inside its limits less the margin, and the model
    finds nothing wrong (effort limits, floor, self-contact), transfers from the idle pose
    included."""
    robot, plan = robots[name.split(".")[0]], plans[name.split(".")[0]]
    arm = arm_joint_indices(robot)
    assert not any(n.startswith("finger") for n in robot.joint_names)
    assert sorted(set(plan.joints)) == list(range(len(arm)))
    inner = inner_limits(robot.joint_limits[arm])
    for s in plan.sweeps:
        assert inner[s.joint, 0] - 1e-12 <= s.lower < s.upper <= inner[s.joint, 1] + 1e-12
        assert s.upper - s.lower >= math.radians(30) - 1e-9
        held = np.delete(np.arange(len(arm)), s.joint)
        assert np.all(s.hold[held] >= inner[held, 0] - 1e-12)
        assert np.all(s.hold[held] <= inner[held, 1] + 1e-12)
    assert plan_issues(robot, plan, start=robot.idle_pose[arm]) == []
    assert 30 < plan.duration(robot.idle_pose[arm]) < 400


def test_plan_ranges_follow_each_joint(plans, robots):
    seven, three = plans["seven"], plans["three"]
    by_joint = {j: [s for s in seven.sweeps if s.joint == j] for j in range(7)}
    for j in (0, 2, 6):  # continuous: the paper's -100..+100 deg
        assert all(
            np.isclose(np.degrees([s.lower, s.upper]), [-100, 100]).all() for s in by_joint[j]
        )
    for s in by_joint[3]:  # +-30 deg: its range less 5 %
        np.testing.assert_allclose(np.degrees([s.lower, s.upper]), [-27.0, 27.0])
    # joint 1 carries the heavy arm: its sweeps are cut where gravity and the ramp would take
    # more than 60 % of its 40 N m, shorter than the usual 100 deg
    assert all(30 <= np.degrees(s.upper - s.lower) < 100 for s in by_joint[1])
    # limits that exclude zero: the sweeps lie inside them, from the zero pose (27 deg) on
    lim = np.degrees(robots["three"].joint_limits)
    for s in three.sweeps:
        lo, hi = np.degrees([s.lower, s.upper])
        assert lim[s.joint, 0] < lo < hi < lim[s.joint, 1]
    assert {round(float(np.degrees(s.lower))) for s in three.sweeps if s.joint == 1} == {27}


def test_gen3_lite_default_plan_is_unchanged():
    """The Gen3 Lite's plan, bit for bit: its JSON's SHA-256 and a few of its numbers."""
    plan = default_plan("gen3_lite")
    digest = hashlib.sha256(json.dumps(plan.to_dict(), sort_keys=True).encode()).hexdigest()
    assert digest == "f508c6e4977ba4948ab6458d375aa8ff47087e28b513d0a401dbc84d8e270897"
    assert plan.joints == [0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4, 5]
    s = plan.sweeps[1]  # joint 1: cut at -45 deg by its effort limit
    assert (s.lower, s.upper, s.speed) == (
        -0.7853981633974483,
        1.7453292519943295,
        0.6981317007977318,
    )
    np.testing.assert_array_equal(np.degrees(s.hold).round(9), [0, 0, 90, -45, -90, -45])
    assert plan.sweeps[3].lower == -1.6580627893946132 and len(plan.sweeps[3].via) == 2
    home = jaxcomp.load_robot("gen3_lite").pose("home")
    assert plan.samples(home) == 233125


# --------------------------------------------------------------------- the truth
def test_gen3_lite_truth_is_the_papers():
    """The Gen3 Lite (and on its mobile base) states the paper's values: the drawn truths are
    bit for bit what they were, for every seed."""
    for model in ("gen3_lite", "mobile_gen3_lite"):
        robot = jaxcomp.load_robot(model)
        ratio, friction = stated_truth(robot)
        assert ratio.tolist() == list(PAPER_RATIO) and friction.tolist() == list(PAPER_FRICTION)
        assert model_current_noise(robot) == 0.05
        for seed in (0, 11):
            t = TrueRobot.draw(robot, seed)
            assert t.ratio.tolist() == list(PAPER_RATIO)
            assert t.friction.tolist() == list(PAPER_FRICTION)
            assert t.current_noise == 0.05
        assert [r.tolist() for r in truth_centre(robot)] == [
            list(PAPER_RATIO),
            list(PAPER_FRICTION),
        ]
    t = TrueRobot.draw(jaxcomp.load_robot("gen3_lite"), 0)
    assert t.params.com_offset["ARM"].tolist() == [
        -0.003867778915771767,
        0.002506161913602179,
        0.0033020446182217738,
    ]


def test_batched_draw_is_the_cpu_draw(robots):
    for robot in (jaxcomp.load_robot("gen3_lite"), robots["small"]):
        batch = BatchTruth.draw(robot, [3, 5], viscous=np.full(len(arm_joint_indices(robot)), 0.01))
        for w, seed in enumerate((3, 5)):
            one = TrueRobot.draw(robot, seed, viscous=np.full(len(arm_joint_indices(robot)), 0.01))
            np.testing.assert_array_equal(batch.ratio[w], one.ratio)
            np.testing.assert_array_equal(batch.friction[w], one.friction)
            assert batch.current_noise[w] == one.current_noise
            back = batch.true_robot(robot, w)
            for link, off in one.params.com_offset.items():
                np.testing.assert_array_equal(back.params.com_offset[link], off)
    bt = BatchTruth.from_arrays(robots["small"], 1.0, 0.01)  # the model's current noise
    assert bt.current_noise[0] == model_current_noise(robots["small"])


def test_truth_of_any_arm_follows_its_own_figures(robots):
    """Ratios around the nominal (the model's, else 1 A/(N m)); friction losses in the range
    that scales with each joint's current limit; current noise scaled alike."""
    for name, robot in robots.items():
        n = len(arm_joint_indices(robot))
        nominal = robot.custom_numeric("jaxcomp_nominal_ratio")
        nominal = np.ones(n) if nominal is None else nominal
        span = friction_loss_range(robot)
        assert stated_truth(robot) is None
        for seed in range(5):
            t = TrueRobot.draw(robot, seed)
            rel = t.ratio / nominal
            assert np.all((RATIO_SPREAD[0] <= rel) & (rel <= RATIO_SPREAD[1])), name
            assert np.all((span[:, 0] <= t.friction) & (t.friction <= span[:, 1])), name
            assert t.current_noise == model_current_noise(robot)
    # the small arm: current limits 0.6 A/(N m) x 1.5 N m = 0.9 A, so friction losses of
    # 0.016-0.049 A, not the 0.2-0.6 A of an 11 A joint
    small = robots["small"]
    np.testing.assert_allclose(current_scale(small) * 11, [0.9, 0.9, 0.9, 0.6])
    np.testing.assert_allclose(
        span := friction_loss_range(small)[0], np.array(FRICTION_LOSS) * 0.9 / 11
    )
    assert span[1] < 0.05
    assert model_current_noise(small) == pytest.approx(0.05 * 0.825 / 11)
    # no effort limit and no current limit: the 11 A figures (0.2-0.6 A)
    three = robots["three"]
    assert current_scale(three)[0] == 1.0
    np.testing.assert_array_equal(friction_loss_range(three)[0], FRICTION_LOSS)
    # the built-in DYNAMIXEL arm: 3.209 A servos
    wx = jaxcomp.load_robot("wx250s")
    np.testing.assert_allclose(friction_loss_range(wx), [np.array(FRICTION_LOSS) * 3.209 / 11] * 5)
    assert model_current_noise(wx) == pytest.approx(0.05 * 3.209 / 11)
    # friction torque (loss / ratio) stays a few % of the effort limit
    t = TrueRobot.draw(small, 0)
    assert np.all(t.friction_torque < 0.06 * small.effort_limits[arm_joint_indices(small)])


def test_stated_truth_must_be_whole(tmp_path):
    def robot(custom: str):
        path = tmp_path / f"arm{abs(hash(custom))}.xml"
        path.write_text(
            serial_mjcf(
                "arm", [("z", None, 5, 0.1, 0.5), ("y", (-90, 90), 5, 0.2, 0.5)], custom=custom
            )
        )
        return jaxcomp.load_robot(path)

    only = robot('<custom><numeric name="jaxcomp_sim_ratio" data="1 1"/></custom>')
    with pytest.raises(ModelError, match="without the other"):
        TrueRobot.draw(only, 0)
    size = robot(
        '<custom><numeric name="jaxcomp_sim_ratio" data="1 1 1"/>'
        '<numeric name="jaxcomp_sim_friction" data="0.1 0.1"/></custom>'
    )
    with pytest.raises(ModelError, match="jaxcomp_sim_ratio has 3 entries"):
        TrueRobot.draw(size, 0)
    stated = robot(
        '<custom><numeric name="jaxcomp_sim_ratio" data="0.5 2"/>'
        '<numeric name="jaxcomp_sim_friction" data="0.1 0"/>'
        '<numeric name="jaxcomp_sim_current_noise" data="0.01"/></custom>'
    )
    t = TrueRobot.draw(stated, 4)
    assert t.ratio.tolist() == [0.5, 2.0] and t.friction.tolist() == [0.1, 0.0]
    assert t.current_noise == 0.01
