"""Models jaxcomp was not built around: which joints it controls, what it welds, the end
effector and poses it picks, and the clear errors for models that cannot work."""

import numpy as np
import pytest
from odd_arms import serial_arm
from synthetic import recording

import jaxcomp
from arms import offset_arm_7dof
from jaxcomp.errors import InputError, ModelError
from jaxcomp.recording import load_recording
from jaxcomp.robot_params import RobotParams


def _write(tmp_path, text: str, name: str = "arm.xml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_gripper_fingers_are_held_and_the_weld_keeps_the_dynamics(tmp_path):
    path = _write(tmp_path, serial_arm(3, gripper=True, scale=0.6))
    robot = jaxcomp.load_robot(path)
    assert robot.controlled_joints == tuple(f"j{k}" for k in range(6))
    assert set(robot.held_joints) == {"finger_l", "finger_r"}
    # held inside the 0..30 mm range, 5 % of it from the lower limit
    assert robot.held_joints["finger_l"] == pytest.approx(0.0015)
    full = jaxcomp.load_robot(path, joints=[*robot.controlled_joints, "finger_l", "finger_r"])
    assert full.nv == 8
    rng = np.random.default_rng(0)
    for _ in range(3):
        q = rng.uniform(-1.5, 1.5, 6)
        qf = np.concatenate([q, [robot.held_joints["finger_l"], robot.held_joints["finger_r"]]])
        np.testing.assert_allclose(robot.gravity(q), np.asarray(full.gravity(qf))[:6], atol=1e-12)
        hand = np.asarray(robot.forward_kinematics(q).pos)[robot.link_index("hand")]
        hand_full = np.asarray(full.forward_kinematics(qf).pos)[full.link_index("hand")]
        np.testing.assert_allclose(hand, hand_full, atol=1e-12)
    # the added end effector sits at the hand (the chain branches into the two fingers there)
    assert robot.reduction.add_site_body == "hand"


def test_a_held_hinge_is_welded_at_its_angle(tmp_path):
    path = _write(tmp_path, serial_arm(4, n=5))
    full = jaxcomp.load_robot(path)
    part = jaxcomp.load_robot(path, joints=["j0", "j1", "j3", "j4"])
    assert set(part.held_joints) == {"j2"}
    held = part.held_joints["j2"]
    lo, hi = full.joint_limits[2]
    assert lo < held < hi and held == pytest.approx(float(np.clip(0.0, lo, hi)), abs=0.25)
    q = np.array([0.3, -0.4, 0.8, 0.2])
    qf = np.insert(q, 2, held)
    np.testing.assert_allclose(part.gravity(q), np.asarray(full.gravity(qf))[[0, 1, 3, 4]])
    # the override is also readable from the model's own custom text
    text = serial_arm(4, n=5).replace(
        "</mujoco>", '<custom><text name="jaxcomp_joints" data="j0 j1 j3 j4"/></custom></mujoco>'
    )
    assert jaxcomp.load_robot(_write(tmp_path, text, "custom.xml")).held_joints.keys() == {"j2"}


def test_end_effector_site_order(tmp_path):
    no_site = jaxcomp.load_robot(_write(tmp_path, serial_arm(5, n=4)))
    assert no_site.end_effector == "end_effector"
    assert no_site.reduction.add_site_body == "link3"  # the last body of the chain
    tip = no_site.site_position(np.zeros(4), "end_effector")
    frames = no_site.forward_kinematics(np.zeros(4))
    np.testing.assert_allclose(tip, frames.pos[no_site.link_index("link3")])
    with_site = jaxcomp.load_robot(_write(tmp_path, serial_arm(5, n=4, site=True), "s.xml"))
    assert with_site.reduction.add_site_body is None
    cylinder = '<geom type="cylinder"'
    text = serial_arm(5, n=4).replace(cylinder, '<site name="tool"/>' + cylinder)
    chosen = jaxcomp.load_robot(_write(tmp_path, text, "tool.xml"), site="tool")
    assert chosen.end_effector == "tool"
    with pytest.raises(ModelError, match="unknown site 'nope'"):
        jaxcomp.load_robot(_write(tmp_path, text, "tool2.xml"), site="nope")


def test_urdf_without_sites_and_a_continuous_joint(tmp_path):
    text = offset_arm_7dof(11).replace(
        'type="revolute"><parent link="link6"', 'type="continuous"><parent link="link6"'
    )
    robot = jaxcomp.load_robot(_write(tmp_path, text, "arm.urdf"))
    assert robot.nv == 7 and robot.end_effector == "end_effector"
    assert np.isinf(robot.joint_limits[6]).all()
    assert robot.site_names == ("end_effector",)


def test_poses_without_keyframes(tmp_path):
    robot = jaxcomp.load_robot(_write(tmp_path, serial_arm(6, n=7, continuous=(0, 2, 4, 6))))
    assert robot.named_poses == {}
    np.testing.assert_array_equal(robot.pose("home"), robot.start_pose)
    np.testing.assert_array_equal(robot.pose("preferred"), robot.start_pose)
    np.testing.assert_array_equal(robot.idle_pose, robot.rest_pose)
    limits = robot.joint_limits
    finite = np.isfinite(limits).all(axis=1)
    q = robot.start_pose
    room = np.minimum(q - limits[:, 0], limits[:, 1] - q)[finite]
    assert np.all(room >= 0.19 * (limits[finite, 1] - limits[finite, 0]))
    # far from singular: the position Jacobian's smallest singular value is a good fraction
    # of the best one's among random poses
    jac = np.asarray(robot.jacobian(q, robot.end_effector))[:3]
    sv = np.linalg.svd(jac, compute_uv=False)
    straight = np.asarray(robot.jacobian(np.zeros(7), robot.end_effector))[:3]
    assert sv[-1] > 5 * np.linalg.svd(straight, compute_uv=False)[-1]
    assert sv[-1] > 0.05
    with pytest.raises(InputError, match="unknown pose 'sideways'"):
        robot.pose("sideways")


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            '<body><joint type="slide" axis="1 0 0"/><geom size="0.1" mass="1"/></body>',
            "no joints to current-control",
        ),
        ('<body><freejoint name="float"/><geom size="0.1" mass="1"/></body>', r"float \(free\)"),
        (
            '<body name="a"><joint name="spin" axis="0 0 1"/>'
            '<inertial pos="0 0 0" mass="0" diaginertia="0 0 0"/></body>',
            "moves no mass",
        ),
    ],
)
def test_models_that_cannot_work_say_why(tmp_path, body, message):
    path = _write(tmp_path, f"<mujoco><worldbody>{body}</worldbody></mujoco>")
    with pytest.raises(ModelError, match=message):
        jaxcomp.load_robot(path)


def test_unknown_joints_are_refused(tmp_path):
    path = _write(tmp_path, serial_arm(2, n=3))
    with pytest.raises(ModelError, match="unknown joint.*elbow"):
        jaxcomp.load_robot(path, joints=["j0", "elbow"])


def test_params_and_recordings_name_their_joints(tmp_path):
    robot = jaxcomp.load_robot("gen3_lite")
    params = RobotParams.nominal(robot)
    assert params.joints == robot.joint_names
    assert RobotParams.from_json(params.to_json(), robot).joints == robot.joint_names
    wrong = RobotParams.from_dict(params.to_dict() | {"joints": [f"x{k}" for k in range(6)]})
    with pytest.raises(InputError, match="params are for joints x0"):
        wrong.check(robot)
    # files without joints still load
    old = {k: v for k, v in params.to_dict().items() if k != "joints"}
    assert RobotParams.from_dict(old, robot).joints is None
    data = recording(robot, params, [(0, np.zeros(6), -0.2, 0.2, 0.5)]).to_arrays()
    data["joints"] = np.array(robot.joint_names)
    np.savez(tmp_path / "r.npz", **data)
    assert load_recording(tmp_path / "r.npz").joints == robot.joint_names
    data["joints"] = np.array(["a", "b"])
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(InputError, match="unknown joint"):
        load_recording(tmp_path / "bad.npz")
