"""Checks of the built-in Kinova Gen3 and WidowX-250 6DOF models against their public figures.

The expected numbers are typed here from the public descriptions (Kinova's gen3 7dof URDF,
Interbotix's wx250s URDF, Trossen's and Kinova's documentation, ROBOTIS' servo datasheets) and
derived with plain MuJoCo and numpy, independently of the XML files.
"""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner
from test_models import body_tensor

import jaxcomp
from jaxcomp.cli import cli
from jaxcomp.models import BUILTIN

GEN3_JOINTS = [f"joint_{i}" for i in range(1, 8)]
GEN3_CONTINUOUS = ["joint_1", "joint_3", "joint_5", "joint_7"]
#: Kinova user guide: the limited joints' range, deg.
GEN3_LIMITS_DEG = {"joint_2": 128.9, "joint_4": 147.8, "joint_6": 120.3}
#: URDF link masses, kg (the bracelet with the vision module).
GEN3_MASSES = {
    "base_link": 1.697,
    "shoulder_link": 1.3773,
    "half_arm_1_link": 1.1636,
    "half_arm_2_link": 1.1636,
    "forearm_link": 0.9302,
    "spherical_wrist_1_link": 0.6781,
    "spherical_wrist_2_link": 0.6781,
    "bracelet_link": 0.5,
}
#: Kinova's published weight of the 7-DOF arm, kg, and its reach, m.
GEN3_WEIGHT, GEN3_REACH = 8.2, 0.902

WX_ARM = ["waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate"]
WX_FINGERS = ["left_finger", "right_finger"]
#: wrist_rotate's XL430-W250 has no current mode: the other five are current-controlled.
WX_CONTROLLED = WX_ARM[:5]
#: URDF link masses, kg; gripper_link holds the gripper body, its servo horn and the bar.
WX_MASSES = {
    "base_link": 0.538736,
    "shoulder_link": 0.480879,
    "upper_arm_link": 0.430811,
    "upper_forearm_link": 0.234589,
    "lower_forearm_link": 0.220991,
    "wrist_link": 0.084957,
    "gripper_link": 0.072885 + 0.00434 + 0.034199,
    "left_finger_link": 0.016246,
    "right_finger_link": 0.016246,
}
#: Trossen's product-of-exponentials home configuration M: end effector at zero, m.
WX_M = (0.458325, 0.0, 0.36065)
#: ROBOTIS XM430-W350 at 12 V: stall torque N m, stall current A; Current Limit register max.
XM430_TORQUE, XM430_CURRENT, XM430_CURRENT_LIMIT = 4.1, 2.3, 1193 * 0.00269
XL430_TORQUE = 1.5

KEYS = ["home", "zero", "retract", "preferred"]
CONTROLLED = {"gen3": GEN3_JOINTS, "wx250s": WX_CONTROLLED}


# ----------------------------------------------------------------------------- helpers
def compiled(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(BUILTIN[name]))


def joint_names(m: mujoco.MjModel) -> list[str]:
    return [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)]


def custom_text(m: mujoco.MjModel, name: str) -> str | None:
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TEXT, name)
    if i < 0:
        return None
    adr, size = m.text_adr[i], m.text_size[i]
    return m.text_data[adr : adr + size - 1].decode()


def custom_numeric(m: mujoco.MjModel, name: str) -> np.ndarray:
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    assert i >= 0, name
    adr, size = m.numeric_adr[i], m.numeric_size[i]
    return m.numeric_data[adr : adr + size].copy()


def effort_limit(m: mujoco.MjModel, joint: str) -> float:
    return float(m.jnt_actfrcrange[m.joint(joint).id, 1])


def gravity_torque(m: mujoco.MjModel, qpos) -> np.ndarray:
    """Joint torques (nv,) holding the model still at ``qpos`` (MuJoCo inverse dynamics)."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    d.qacc[:] = 0
    mujoco.mj_inverse(m, d)
    return d.qfrc_inverse.copy()


def site_position(m: mujoco.MjModel, qpos, site: str = "end_effector") -> np.ndarray:
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    return d.site(site).xpos.copy()


def tensor(ixx, iyy, izz, ixy, ixz, iyz) -> np.ndarray:
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


@pytest.fixture(scope="module", params=["gen3", "wx250s"])
def arm(request) -> tuple[str, mujoco.MjModel]:
    return request.param, compiled(request.param)


# ----------------------------------------------------------------------------- both arms
def test_registered_and_style(arm):
    name, m = arm
    assert name in jaxcomp.builtin_models()
    assert m.opt.timestep == 0.001
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    np.testing.assert_array_equal(m.opt.gravity, [0, 0, -9.81])
    assert m.nu == 0 and m.nmesh == 0
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    assert np.all(m.dof_damping == 0) and np.all(m.dof_frictionloss == 0)
    assert np.all(m.dof_armature == 0)
    assert np.all(m.jnt_actfrclimited == 1) and np.all(m.jnt_actfrcrange[:, 1] > 0)


def test_masses_positive(arm):
    _, m = arm
    assert np.all(m.body_mass[1:] > 0)
    assert np.all(m.body_inertia[1:] > 0)


def test_keyframes_within_limits(arm):
    name, m = arm
    keys = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, k) for k in range(m.nkey)]
    assert keys == KEYS
    limited = m.jnt_limited.astype(bool)
    lo, hi = m.jnt_range.T
    for k, key in enumerate(keys):
        q = m.key_qpos[k]
        inside = (q >= lo - 1e-12) & (q <= hi + 1e-12)
        assert np.all(inside | ~limited), (name, key, q)


def test_gravity_within_effort_limits(arm):
    """Holding the arm at each keyframe needs at most a third of every joint's effort limit."""
    name, m = arm
    effort = m.jnt_actfrcrange[:, 1]
    for k in range(m.nkey):
        g = gravity_torque(m, m.key_qpos[k])
        assert np.all(np.abs(g) <= effort / 3), (name, k, g, effort)


def test_custom_fields_per_controlled_joint(arm):
    name, m = arm
    listed = custom_text(m, "jaxcomp_joints")
    controlled = listed.split() if listed else GEN3_JOINTS
    assert controlled == CONTROLLED[name]
    n = len(controlled)
    assert len(custom_text(m, "jaxcomp_actuator_types").split()) == n
    assert custom_numeric(m, "jaxcomp_nominal_ratio").shape == (n,)
    assert np.all(custom_numeric(m, "jaxcomp_nominal_ratio") > 0)
    assert custom_numeric(m, "jaxcomp_current_limit").shape == (n,)
    site = custom_text(m, "jaxcomp_end_effector")
    assert site == "end_effector" and m.site(site).id >= 0


def test_home_is_not_singular(arm):
    """At home the end-effector position Jacobian of the controlled joints has full rank."""
    name, m = arm
    d = mujoco.MjData(m)
    d.qpos[:] = m.key_qpos[KEYS.index("home")]
    mujoco.mj_forward(m, d)
    jac = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jac, None, m.site("end_effector").id)
    cols = [m.joint(j).dofadr[0] for j in CONTROLLED[name]]
    assert np.linalg.svd(jac[:, cols], compute_uv=False).min() > 0.1


# ----------------------------------------------------------------------------- gen3
def test_gen3_joints_and_limits():
    m = compiled("gen3")
    assert joint_names(m) == GEN3_JOINTS
    assert np.all(m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
    for j in GEN3_CONTINUOUS:
        assert not m.joint(j).limited[0], j
    for j, deg in GEN3_LIMITS_DEG.items():
        assert m.joint(j).limited[0]
        np.testing.assert_allclose(np.rad2deg(m.joint(j).range), [-deg, deg], atol=0.01)
    effort = {j: effort_limit(m, j) for j in GEN3_JOINTS}
    assert effort == dict.fromkeys(GEN3_JOINTS[:4], 39.0) | dict.fromkeys(GEN3_JOINTS[4:], 9.0)
    assert custom_text(m, "jaxcomp_actuator_types").split() == list("LLLLSSS")


def test_gen3_inertials():
    m = compiled("gen3")
    for body, mass in GEN3_MASSES.items():
        assert m.body(body).mass[0] == pytest.approx(mass)
    assert m.body_mass.sum() == pytest.approx(sum(GEN3_MASSES.values()))
    assert m.body_mass.sum() == pytest.approx(GEN3_WEIGHT, abs=0.02)
    # half_arm_1_link: the URDF's tensor, in the link frame
    np.testing.assert_allclose(
        body_tensor(m, "half_arm_1_link"),
        tensor(0.011088, 0.001072, 0.011255, 0.000005, 0, -0.000691),
        atol=1e-12,
    )
    np.testing.assert_allclose(m.body("bracelet_link").ipos, [0.000281, 0.011402, -0.029798])


def test_gen3_kinematics():
    """Straight up at zero: the flange 0.902 m from joint 2 (Kinova's reach), 1.187 m high."""
    m = compiled("gen3")
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    flange = d.site("end_effector").xpos
    reach = np.linalg.norm(flange - d.joint("joint_2").xanchor)
    assert reach == pytest.approx(GEN3_REACH, abs=0.001)
    urdf_z = 0.15643 + 0.12838 + 2 * 0.21038 + 0.20843 + 2 * 0.10593 + 0.061525
    assert flange[2] == pytest.approx(urdf_z, abs=1e-4)
    # the flange frame's z points out of the arm (up at zero)
    np.testing.assert_allclose(
        d.site("end_effector").xmat.reshape(3, 3)[:, 2], [0, 0, 1], atol=1e-4
    )
    # Kinova's home (0 15 180 -130 0 55 90 deg): the flange in front, pointing forward
    home = m.key_qpos[KEYS.index("home")]
    np.testing.assert_allclose(np.rad2deg(home), [0, 15, 180, -130, 0, 55, 90], atol=1e-6)
    d.qpos[:] = home
    mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(d.site("end_effector").xpos, [0.4567, 0.0013, 0.4337], atol=5e-4)


# ----------------------------------------------------------------------------- wx250s
def test_wx250s_joints_and_coupling():
    m = compiled("wx250s")
    assert joint_names(m) == WX_ARM + WX_FINGERS
    kinds = [m.joint(j).type[0] for j in WX_ARM + WX_FINGERS]
    assert kinds == [mujoco.mjtJoint.mjJNT_HINGE] * 6 + [mujoco.mjtJoint.mjJNT_SLIDE] * 2
    np.testing.assert_allclose(m.joint("left_finger").range, [0.015, 0.037])
    np.testing.assert_allclose(m.joint("right_finger").range, [-0.037, -0.015])
    deg = {j: np.rad2deg(m.joint(j).range) for j in ("shoulder", "elbow", "wrist_angle")}
    np.testing.assert_allclose(deg["shoulder"], [-108, 114], atol=1e-4)
    np.testing.assert_allclose(deg["elbow"], [-123, 92], atol=1e-4)
    np.testing.assert_allclose(deg["wrist_angle"], [-100, 123], atol=1e-4)
    # one joint equality ties the fingers: right = -left
    assert m.neq == 1 and m.eq_type[0] == mujoco.mjtEq.mjEQ_JOINT
    pair = {m.joint(int(m.eq_obj1id[0])).name, m.joint(int(m.eq_obj2id[0])).name}
    assert pair == set(WX_FINGERS)
    np.testing.assert_allclose(m.eq_data[0, :5], [0, -1, 0, 0, 0])
    for k in range(m.nkey):
        left, right = m.key_qpos[k, 6:8]
        assert right == pytest.approx(-left)


def test_wx250s_effort_and_current_figures():
    m = compiled("wx250s")
    effort = [effort_limit(m, j) for j in WX_ARM]
    stall = [XM430_TORQUE, 2 * XM430_TORQUE, 2 * XM430_TORQUE, XM430_TORQUE, XM430_TORQUE]
    np.testing.assert_allclose(effort, stall + [XL430_TORQUE])
    single = XM430_CURRENT / XM430_TORQUE
    ratio = custom_numeric(m, "jaxcomp_nominal_ratio")
    np.testing.assert_allclose(ratio, [single, single / 2, single / 2, single, single], rtol=1e-3)
    limit = custom_numeric(m, "jaxcomp_current_limit")
    np.testing.assert_allclose(limit, XM430_CURRENT_LIMIT, rtol=1e-3)
    # at the current limit each controlled joint reaches its stall torque
    assert np.all(limit / ratio >= np.array(stall))


def test_wx250s_inertials():
    m = compiled("wx250s")
    for body, mass in WX_MASSES.items():
        assert m.body(body).mass[0] == pytest.approx(mass)
    assert m.body_mass.sum() == pytest.approx(2.134879, abs=1e-6)
    # upper_arm_link: the URDF's tensor is given in a frame turned by (0 0 pi/2)
    given = tensor(0.003463, 0.003587, 0.0004566, -1e-10, -2e-10, 0.0004272)
    np.testing.assert_allclose(
        body_tensor(m, "upper_arm_link"), rot_z(np.pi / 2) @ given @ rot_z(np.pi / 2).T, atol=1e-12
    )
    # lower_forearm_link: turned by (pi 0 0)
    given = tensor(0.00006369, 0.0001677, 0.0001834, -0.00002292, 0, 0)
    np.testing.assert_allclose(
        body_tensor(m, "lower_forearm_link"), rot_x(np.pi) @ given @ rot_x(np.pi).T, atol=1e-12
    )
    # gripper_link: body, horn (at x 0.0485) and bar (at x 0.043) folded into one
    parts = [
        (0.072885, (0.021631, 0.0000002516, 0.01141)),
        (0.00434, (0.0485 + 0.000846, -0.0000016817, 0.000042)),
        (0.034199, (0.043 + 0.009687, 0.0000008177, 0.004962)),
    ]
    mass = sum(p[0] for p in parts)
    com = sum(p[0] * np.array(p[1]) for p in parts) / mass
    np.testing.assert_allclose(m.body("gripper_link").ipos, com, atol=1e-10)


def test_wx250s_kinematics():
    """At zero the end effector is Trossen's M; stretched out it reaches about 0.66 m."""
    m = compiled("wx250s")
    q = m.key_qpos[KEYS.index("zero")]
    np.testing.assert_allclose(site_position(m, q), WX_M, atol=1e-9)
    # the arm in one horizontal line: the upper arm leans forward to the horizontal, the
    # elbow turns back by the upper arm's own angle
    rise = np.arctan2(0.25, 0.04975)
    q = q.copy()
    q[1], q[2] = rise, -rise
    shoulder = np.array([0, 0, 0.072 + 0.03865])
    reach = np.linalg.norm(site_position(m, q) - shoulder)
    assert reach == pytest.approx(np.hypot(0.04975, 0.25) + 0.175 + 0.075 + 0.065 + 0.093575)
    assert reach == pytest.approx(0.65, abs=0.02)


# ----------------------------------------------------------------------------- jaxcomp
def test_load_robot_reduces_wx250s():
    robot = jaxcomp.load_robot("wx250s")
    assert robot.joint_names == tuple(WX_CONTROLLED) and robot.nv == 5
    held = robot.held_joints
    assert set(held) == {"wrist_rotate", *WX_FINGERS}
    assert 0.015 < held["left_finger"] < 0.037 and held["right_finger"] == -held["left_finger"]
    assert robot.end_effector == "end_effector"
    # gravity of the reduced robot = the full model's, the held joints at their positions
    full = compiled("wx250s")
    home = full.key_qpos[KEYS.index("home")].copy()
    for j, value in held.items():
        home[full.joint(j).qposadr[0]] = value
    g_full = gravity_torque(full, home)[:5]
    q = robot.pose("home")
    np.testing.assert_allclose(q, home[:5])
    g = np.asarray(robot.gravity(q))
    np.testing.assert_allclose(g, g_full, atol=1e-9)
    assert np.all(np.abs(g) <= robot.effort_limits)


def test_load_robot_gen3():
    robot = jaxcomp.load_robot("gen3")
    assert robot.joint_names == tuple(GEN3_JOINTS)
    assert robot.held_joints == {}
    limits = robot.joint_limits
    for j in GEN3_CONTINUOUS:
        assert np.all(np.isinf(limits[GEN3_JOINTS.index(j)]))
    g = np.asarray(robot.gravity(robot.pose("home")))
    np.testing.assert_allclose(g, gravity_torque(compiled("gen3"), robot.pose("home")), atol=1e-9)
    assert np.all(np.abs(g) <= robot.effort_limits)


def test_models_command_lists_every_builtin():
    result = CliRunner().invoke(cli, ["models"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert len(lines) == len(BUILTIN)
    line = {name: [ln for ln in lines if ln.split()[0] == name] for name in BUILTIN}
    assert all(len(found) == 1 for found in line.values()), lines
    assert "7 controlled  0 held" in line["gen3"][0]
    assert "6 controlled  0 held" in line["gen3_lite"][0]
    for name in ("gen3", "gen3_lite", "wx250s"):
        assert line[name][0].endswith(str(BUILTIN[name].resolve()))


def test_models_command_json_counts():
    result = CliRunner().invoke(cli, ["models", "--json"])
    assert result.exit_code == 0, result.output
    entries = {e["name"]: e for e in json.loads(result.output)}
    assert set(entries) == set(BUILTIN)
    expected = {
        "gen3": (GEN3_JOINTS, [], []),
        "gen3_lite": ([f"joint_{i}" for i in range(6)], [], []),
        "wx250s": (WX_CONTROLLED, ["wrist_rotate", *WX_FINGERS], []),
        "mobile_gen3_lite": (
            [f"joint_{i}" for i in range(6)],
            [],
            ["base_x", "base_y", "base_yaw"],
        ),
    }
    for name, (controlled, held, base) in expected.items():
        e = entries[name]
        assert e["controlled"] == controlled, name
        assert sorted(e["held"]) == sorted(held), name
        assert e["base"] == base, name
        assert e["source"] == str(BUILTIN[name].resolve())
