"""`jaxcomp control` on arms other than the Gen3 Lite, written by the test itself.

Three arms with neither keyframes nor sites: a Kinova-Gen3-like 7-joint MJCF arm (joints 1, 3,
5, 7 continuous, 39 / 9 N m, 8.2 kg), a small light MJCF arm (1.1 kg, 2-5 N m) with two
finger slides coupled by a joint equality, and a URDF arm with a side branch (a camera mast
on its own joint) in the style of ``arms.py``. Each tracks the 5 cm circle in the simulator
with the simulator's own truth as params: the start pose, posture, current limits and gains
all come from the model. The Gen3 Lite's presets are pinned.
"""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

import jaxcomp.cli
from arms import branched_prismatic
from jaxcomp.cli.group import cli
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control import ImpedanceGains, impedance_gains, make_impedance_controller
from jaxcomp.control.presets import DAMPING_NUMBER, arm_figures, derived_preset
from jaxcomp.errors import InputError
from jaxcomp.hardware import ArmLimits, Simulator
from jaxcomp.recording import load_recording
from jaxcomp.robot import load_robot

CIRCLE = "circle:r=0.05,v=0.05"
SETTLE = 3.0  # s: the RMS error is taken after this
DURATION = 6.0  # s: 3 s after the settle (a bit over half a turn at 0.05 m/s)


# ----------------------------------------------------------------------------- the arms


def _body(name, pos, mass, inertia, com, joint, inner="") -> str:
    return (
        f'<body name="{name}" pos="{pos}"><inertial pos="{com}" mass="{mass}" '
        f'diaginertia="{inertia}"/>{joint}<geom type="capsule" fromto="0 0 0 {com}" '
        f'size="0.03"/>{inner}</body>'
    )


def _mjcf(name: str, base: str, chain: str, extra: str = "") -> str:
    return (
        f'<mujoco model="{name}"><compiler angle="radian" autolimits="true"/>'
        '<default><geom contype="0" conaffinity="0" density="0"/></default>'
        f'<worldbody><body name="base">{base}{chain}</body></worldbody>{extra}</mujoco>'
    )


def gen3_like() -> str:
    """7 joints about z y z y z y z, 1 3 5 7 continuous, 39 N m (1-4) and 9 N m (5-7)."""
    links = [  # name, pos in the parent, kg, diag inertia kg m^2, COM, axis, range, N m
        ("l1", "0 0 0.156", 1.38, "0.0046 0.0048 0.0014", "0 0 0.07", "0 0 1", None, 39),
        ("l2", "0 0 0.128", 1.16, "0.011 0.011 0.001", "0 0 0.1", "0 1 0", 2.25, 39),
        ("l3", "0 0 0.210", 1.16, "0.011 0.011 0.001", "0 0 0.1", "0 0 1", None, 39),
        ("l4", "0 0 0.210", 0.93, "0.008 0.008 0.0006", "0 0 0.08", "0 1 0", 2.58, 39),
        ("l5", "0 0 0.208", 0.68, "0.0016 0.0016 0.0004", "0 0 0.06", "0 0 1", None, 9),
        ("l6", "0 0 0.106", 0.68, "0.0016 0.0016 0.0004", "0 0 0.05", "0 1 0", 2.1, 9),
        ("l7", "0 0 0.106", 0.50, "0.0006 0.0006 0.0006", "0 0 0.03", "0 0 1", None, 9),
    ]
    inner = ""
    for name, pos, mass, inertia, com, axis, rng, effort in reversed(links):
        limit = f'range="{-rng} {rng}"' if rng else 'limited="false"'
        joint = (
            f'<joint name="j_{name}" axis="{axis}" {limit} actuatorfrcrange="-{effort} {effort}"/>'
        )
        inner = _body(name, pos, mass, inertia, com, joint, inner)
    base = '<inertial pos="0 0 0.08" mass="1.7" diaginertia="0.0046 0.0045 0.0021"/>'
    return _mjcf("gen3like", base, inner)


def small_gripper_arm(site: str = "") -> str:
    """1.1 kg, five hinges of 2-5 N m, two finger slides coupled by a joint equality."""
    finger = (
        '<body name="finger_{s}" pos="0.06 {y} 0"><inertial pos="0.01 0 0" mass="0.02" '
        'diaginertia="2e-6 2e-6 2e-6"/><joint name="finger_{s}" type="slide" axis="0 1 0" '
        'range="{lo} {hi}" actuatorfrcrange="-5 5"/></body>'
    )
    inner = finger.format(s="l", y=0.01, lo=0, hi=0.03) + finger.format(
        s="r", y=-0.01, lo=-0.03, hi=0
    )
    inner += site
    links = [
        ("waist", "0 0 0.07", 0.22, "3e-4 3e-4 3e-4", "0 0 0.01", "0 0 1", 3.1, 5),
        ("shoulder", "0 0 0.04", 0.20, "1.5e-3 1.5e-3 1e-4", "0.02 0 0.1", "0 1 0", 1.8, 5),
        ("elbow", "0.03 0 0.2", 0.14, "6e-4 6e-4 5e-5", "0.09 0 0", "0 1 0", 2.0, 3),
        ("wrist", "0.18 0 0", 0.08, "3e-5 3e-5 3e-5", "0.03 0 0", "0 1 0", 1.8, 2),
        ("roll", "0.05 0 0", 0.09, "4e-5 4e-5 4e-5", "0.03 0 0", "1 0 0", 3.1, 2),
    ]
    for name, pos, mass, inertia, com, axis, rng, effort in reversed(links):
        joint = (
            f'<joint name="{name}" axis="{axis}" range="{-rng} {rng}" '
            f'actuatorfrcrange="-{effort} {effort}"/>'
        )
        inner = _body(f"{name}_link", pos, mass, inertia, com, joint, inner)
    base = '<inertial pos="0 0 0.02" mass="0.3" diaginertia="5e-4 5e-4 5e-4"/>'
    equality = (
        '<equality><joint joint1="finger_r" joint2="finger_l" polycoef="0 -1 0 0 0"/></equality>'
    )
    return _mjcf("smallarm", base, inner, equality)


def _urdf_link(name: str, mass: float, com, inertia) -> str:
    return (
        f'<link name="{name}"><inertial><origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0 0 0"/>'
        f'<mass value="{mass}"/><inertia ixx="{inertia[0]}" ixy="0" ixz="0" '
        f'iyy="{inertia[1]}" iyz="0" izz="{inertia[2]}"/></inertial></link>'
    )


def _urdf_joint(name, parent, child, xyz, axis, effort, limit=3.0) -> str:
    return (
        f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="{axis}"/>'
        f'<limit lower="{-limit}" upper="{limit}" effort="{effort}" velocity="3"/></joint>'
    )


def branched_urdf_arm() -> str:
    """A 6-joint URDF arm (z y y y z y, 20-5 N m) and, on its base, a camera mast turning on a
    joint of its own: a branched tree whose mast joint moves nothing the end effector feels."""
    parts = ['<robot name="branched6">', _urdf_link("base", 1.0, (0, 0, 0.05), (3e-3,) * 3)]
    chain = [  # child, origin in the parent, axis, kg, COM, N m
        ("link1", "0 0 0.1", "0 0 1", 1.2, (0, 0, 0.05), 20),
        ("link2", "0 0 0.08", "0 1 0", 1.0, (0.12, 0, 0), 20),
        ("link3", "0.25 0 0", "0 1 0", 0.8, (0.1, 0, 0), 10),
        ("link4", "0.22 0 0", "0 1 0", 0.4, (0.03, 0, 0), 5),
        ("link5", "0.06 0 0", "0 0 1", 0.3, (0.02, 0, 0), 5),
        ("link6", "0.05 0 0", "0 1 0", 0.2, (0.03, 0, 0), 5),
    ]
    parent = "base"
    for k, (child, xyz, axis, mass, com, effort) in enumerate(chain, start=1):
        parts += [
            _urdf_link(child, mass, com, (2e-3 * mass,) * 3),
            _urdf_joint(f"joint{k}", parent, child, xyz, axis, effort),
        ]
        parent = child
    parts += [
        _urdf_link("mast", 0.3, (0, 0, 0.1), (1e-3, 1e-3, 2e-4)),
        _urdf_joint("mast_pan", "base", "mast", "-0.1 0 0.05", "0 0 1", 2),
    ]
    return "\n".join(parts + ["</robot>"])


ARMS = {
    "gen3like.xml": gen3_like,
    "smallarm.xml": small_gripper_arm,
    "branched6.urdf": branched_urdf_arm,
}


@pytest.fixture(scope="module")
def arm_files(tmp_path_factory):
    where = tmp_path_factory.mktemp("arms")
    files = {}
    for name, make in ARMS.items():
        files[name] = where / name
        files[name].write_text(make())
    return files


def _truth_file(model, path, **load) -> str:
    """The simulator's truth (seed 0, what `jaxcomp control --seed 0` simulates) as params."""
    sim = Simulator(load_robot(model, **load), seed=0)
    return str(sim.truth.params.save(path))


def _rms_after_settle(out_dir) -> tuple[float, np.ndarray]:
    rec = load_recording(out_dir / "recording.npz", require_sweep=False)
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    return float(np.sqrt(np.mean(err[t >= SETTLE] ** 2))), rec.q[0]


# ----------------------------------------------------------------------------- tracking


@pytest.mark.parametrize("name", list(ARMS))
def test_tracks_the_circle_to_3_mm(name, arm_files, tmp_path):
    """`control --mode tracking` on each generated arm: completes without a fault, and the end
    effector follows the 5 cm circle to 3 mm RMS after the settle (about 1 mm: the deadband),
    starting at the robot's start pose."""
    model = str(arm_files[name])
    robot = load_robot(model)
    assert not robot.named_poses  # no keyframes: start and posture are chosen on the model
    params = _truth_file(model, tmp_path / "truth.json")
    out_dir = tmp_path / "run"
    args = ["control", "--mode", "tracking", "--model", model, "--params", params]
    args += ["--trajectory", CIRCLE, "--duration", str(DURATION), "--out", str(out_dir)]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    assert "ended: completed" in out.output and f"gains (tracking) for {robot.name}" in out.output
    rms, q0 = _rms_after_settle(out_dir)
    assert rms <= 3e-3
    np.testing.assert_allclose(q0, robot.pose("home"), atol=0.02)  # = robot.start_pose


def test_params_name_the_joints_and_site_option(arm_files, tmp_path):
    """Params made for some of the joints load the robot reduced to them; --joints must agree
    with them; --site picks the end effector of a model that names none."""
    small = str(arm_files["smallarm.xml"])
    joints = ["waist", "shoulder", "elbow", "wrist"]  # roll held
    params = _truth_file(small, tmp_path / "four.json", joints=joints)
    out_dir = tmp_path / "four"
    args = ["control", "--mode", "tracking", "--model", small, "--params", params]
    args += ["--trajectory", CIRCLE, "--duration", "0.3", "--out", str(out_dir)]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    rec = load_recording(out_dir / "recording.npz", require_sweep=False)
    assert rec.joints == tuple(joints) and rec.q.shape[1] == 4
    out = CliRunner().invoke(cli, args + ["--joints", "waist,shoulder,elbow,roll"])
    assert isinstance(out.exception, InputError) and "differ from the joints" in str(out.exception)

    with_site = tmp_path / "small_tcp.xml"
    tcp = '<site name="tcp" pos="0.1 0 0"/>'
    with_site.write_text(small_gripper_arm(site=tcp).replace('model="smallarm"', 'model="tcp"'))
    robot = load_robot(with_site, site="tcp")
    assert robot.end_effector == "tcp"
    out_dir = tmp_path / "tcp"
    args = ["control", "--mode", "tracking", "--model", str(with_site), "--site", "tcp"]
    args += ["--trajectory", "static", "--duration", "0.2", "--out", str(out_dir)]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    rec = load_recording(out_dir / "recording.npz", require_sweep=False)
    np.testing.assert_allclose(rec.extra["ee"][0], robot.site_position(rec.q[0], "tcp"), atol=1e-9)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--model", "BRANCHED"], "in only 1 of 3 directions"),
        (["--model", "dingo_o"], "has no arm joints"),
        (["--model", "SMALL", "--joints", "waist,nope"], "unknown joint(s) nope"),
        (["--model", "SMALL", "--site", "nope"], "unknown site 'nope'"),
        (["--model", "SMALL", "--params", "GEN3"], "do not fit"),
        (["--robot", "kortex", "--model", "SMALL"], "for the simulator only"),
    ],
)
def test_models_that_cannot_work_end_in_one_error_line(
    extra, message, arm_files, tmp_path, monkeypatch, capsys
):
    """`jaxcomp control` on a model it cannot control prints one `error:` line, no traceback."""
    branched = tmp_path / "branched.urdf"
    branched.write_text(branched_prismatic())  # its end effector moves with one joint only
    gen3 = tmp_path / "gen3.json"
    names = {
        "BRANCHED": str(branched),
        "SMALL": str(arm_files["smallarm.xml"]),
        "GEN3": _truth_file(str(arm_files["gen3like.xml"]), gen3) if "GEN3" in extra else "",
    }
    argv = ["jaxcomp", "control", "--mode", "tracking", "--trajectory", CIRCLE]
    argv += ["--duration", "0.1", "--out", str(tmp_path / "run")]
    argv += [names.get(a, a) for a in extra]
    monkeypatch.setattr("sys.argv", argv)
    monkeypatch.setenv("JAXCOMP_CACHE", "off")  # no persistent XLA cache from this process
    with pytest.raises(SystemExit) as exc:
        jaxcomp.cli.main()
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and message in err[-1]
    assert not any("Traceback" in line for line in err)


# ----------------------------------------------------------------------------- gains


@pytest.mark.parametrize("preset", ["paper", "tracking"])
def test_gen3_lite_keeps_its_presets(preset):
    """The Gen3 Lite declares its presets: exactly the figures tuned on it."""
    robot = load_robot("gen3_lite")
    gains = impedance_gains(robot, preset)
    assert gains == ImpedanceGains.preset(preset)
    k, d, d_n = {"paper": (40.0, 3.0, 0.025), "tracking": (400.0, 30.0, 0.3)}[preset]
    assert gains.stiffness == (k, k, k) and gains.damping == (d, d, d)
    assert gains.nullspace_stiffness == 0.125 and gains.nullspace_damping == d_n
    assert gains.error_clip == 0.1 and gains.current_rate_limit == 2000.0
    assert gains.max_current_step == 2000.0 * CONTROL_PERIOD
    joint = make_impedance_controller(robot, None, gains).joint
    np.testing.assert_array_equal(joint.limit, 11.0)
    np.testing.assert_array_equal(ArmLimits.from_robot(robot).current, 11.0)
    assert impedance_gains(robot, preset, stiffness=100.0).stiffness == (100.0,) * 3


def test_the_rule_reproduces_the_gen3_lite_but_for_its_light_wrist():
    """Scaled from the Gen3 Lite's apparent mass and reach, the rule gives the Gen3 Lite its own
    figures within 0.1 %, except the nullspace damping of its last joint, capped for stability
    without friction (1.3e-4 kg m^2: 0.3 N m s/rad would be D_n T / I = 2.3)."""
    robot = load_robot("gen3_lite")
    fig = arm_figures(robot)
    assert fig.apparent_mass == pytest.approx(0.1203, abs=1e-4)
    assert fig.reach == pytest.approx(0.914, abs=1e-3)
    for preset in ("paper", "tracking"):
        rule, ref = derived_preset(robot, preset), ImpedanceGains.preset(preset)
        assert rule["stiffness"] == pytest.approx(ref.stiffness[0], rel=1e-3)
        assert rule["damping"] == pytest.approx(ref.damping[0], rel=1e-3)
        assert rule["nullspace_stiffness"] == pytest.approx(ref.nullspace_stiffness, rel=1e-3)
        assert rule["error_clip"] == pytest.approx(ref.error_clip, rel=1e-3)
    d_n = np.broadcast_to(derived_preset(robot, "tracking")["nullspace_damping"], (6,))
    np.testing.assert_allclose(d_n[:5], 0.3, rtol=1e-3)
    assert d_n[5] == pytest.approx(DAMPING_NUMBER * fig.joint_inertia[5] / CONTROL_PERIOD)


def test_gains_of_other_arms_follow_the_model(arm_files, tmp_path):
    """Current limits from the efforts (nominal ratio 1 A/(N m)), rate limits scaled to them,
    Cartesian gains with the apparent mass, nullspace damping within the stability cap; a
    model that declares a preset gets exactly its figures."""
    robot = load_robot(arm_files["gen3like.xml"])
    gains = impedance_gains(robot, "tracking")
    joint = make_impedance_controller(robot, None, gains).joint
    np.testing.assert_allclose(joint.limit, [39, 39, 39, 39, 9, 9, 9])
    np.testing.assert_allclose(ArmLimits.from_robot(robot).current, joint.limit)
    np.testing.assert_allclose(gains.current_rate_limit, 2000.0 * joint.limit / 11.0)
    fig = arm_figures(robot)
    assert gains.stiffness[0] == pytest.approx(400.0 * fig.apparent_mass / 0.1203)
    assert gains.damping[0] * CONTROL_PERIOD / fig.apparent_mass == pytest.approx(0.25, rel=3e-3)
    assert fig.apparent_mass > 1.0 and gains.stiffness[0] > 3000.0  # heavy: stiffer than 400
    assert np.all(joint.damping * CONTROL_PERIOD / fig.joint_inertia <= DAMPING_NUMBER + 1e-12)

    small = load_robot(arm_files["smallarm.xml"])
    assert set(small.held_joints) == {"finger_l", "finger_r"}
    small_gains = impedance_gains(small, "tracking")
    assert small_gains.error_clip < 0.06  # a 0.47 m arm: about half the Gen3 Lite's clip
    np.testing.assert_allclose(
        make_impedance_controller(small, None, small_gains).joint.limit, [5, 5, 3, 2, 2]
    )

    declared = tmp_path / "declared.xml"
    text = small_gripper_arm().replace('model="smallarm"', 'model="declared"')
    custom = '<custom><numeric name="jaxcomp_impedance_tracking" data="150 8 0.05 0.01 0.04"/>'
    declared.write_text(text.replace("</mujoco>", custom + "</custom></mujoco>"))
    gains = impedance_gains(load_robot(declared), "tracking")
    assert gains.stiffness == (150.0,) * 3 and gains.damping == (8.0,) * 3
    assert (gains.nullspace_stiffness, gains.nullspace_damping, gains.error_clip) == (
        0.05,
        0.01,
        0.04,
    )
