"""load_robot, the Robot API, bad input, and the `jaxcomp info` command."""

import json

import jax
import numpy as np
import pytest
from click.testing import CliRunner

import jaxcomp
from jaxcomp.cli import cli
from jaxcomp.errors import InputError, ModelError


@pytest.fixture(scope="module")
def gen3():
    return jaxcomp.load_robot("gen3_lite")


def test_builtin_models_load_with_expected_joints():
    builtin = ["dingo_o", "gen3", "gen3_lite", "mobile_gen3_lite", "wx250s"]
    assert jaxcomp.builtin_models() == builtin
    mobile = jaxcomp.load_robot("mobile_gen3_lite")
    assert mobile.joint_names[:3] == ("base_x", "base_y", "base_yaw")
    assert mobile.nv == 9
    assert list(mobile.tree.is_hinge[:3]) == [False, False, True]


def test_a_model_in_use_is_loaded_once_and_an_edited_one_anew(gen3, tmp_path):
    """load_robot returns the robot already in use for the same model, with what it keeps."""
    again = jaxcomp.load_robot("gen3_lite")
    assert again is gen3
    assert again.cached("probe", object) is gen3.cached("probe", object)
    assert jaxcomp.load_robot(gen3.source) is gen3  # the same file by its path
    edited = tmp_path / "gen3_lite.xml"
    edited.write_text(gen3.source.read_text().replace('mass="', 'mass="1', 1))
    other = jaxcomp.load_robot(edited)
    assert other is not gen3 and other.digest != gen3.digest
    assert jaxcomp.load_robot(edited) is other
    edited.write_text(gen3.source.read_text())  # the same path, edited back: a new robot
    assert jaxcomp.load_robot(edited) is not other


def test_api_shapes_and_values(gen3):
    q = gen3.pose("preferred")
    assert gen3.joint_names == tuple(f"joint_{k}" for k in range(6))
    assert gen3.link_names[0] == "BASE" and gen3.link_names[-1] == "GRIPPER_FRAME"
    g = np.asarray(gen3.gravity(q))
    assert g.shape == (6,)
    assert abs(g[1]) == pytest.approx(1.61, abs=0.01)  # FIGURES.md: joint 1 at the preferred pose
    assert np.asarray(gen3.mass_matrix(q)).shape == (6, 6)
    assert np.asarray(gen3.jacobian(q, "end_effector")).shape == (6, 6)
    assert np.asarray(gen3.nominal_params().mass).sum() == pytest.approx(5.18674045, abs=1e-6)


def test_gravity_vector_input_rotates_the_load(gen3):
    """An arm on a wall: gravity along -x of the base frame loads joint 0, upright does not."""
    q = gen3.pose("home")
    upright = np.asarray(gen3.gravity(q))
    wall = np.asarray(gen3.gravity(q, gravity=[-9.81, 0.0, 0.0]))
    assert abs(upright[0]) < 1e-9 and abs(wall[0]) > 0.1
    np.testing.assert_allclose(gen3.gravity(q, gravity=[0, 0, -2 * 9.81]), 2 * upright)


def test_params_change_gravity_linearly_in_mass(gen3):
    q = gen3.pose("home")
    p = gen3.nominal_params()
    heavier = p._replace(mass=p.mass * 2)
    np.testing.assert_allclose(gen3.gravity(q, heavier), 2 * np.asarray(gen3.gravity(q)))


@pytest.mark.parametrize(
    ("source", "message"),
    [
        ("no_such_robot", "unknown robot 'no_such_robot'"),
        ("/nonexistent/arm.urdf", "not found"),
    ],
)
def test_bad_model_names(source, message):
    with pytest.raises(ModelError, match=message):
        jaxcomp.load_robot(source)


def test_bad_model_files(tmp_path):
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><body>")
    with pytest.raises(ModelError, match="cannot compile"):
        jaxcomp.load_robot(broken)
    still = tmp_path / "still.xml"
    still.write_text('<mujoco><worldbody><body><geom size="0.1"/></body></worldbody></mujoco>')
    with pytest.raises(ModelError, match="no joints"):
        jaxcomp.load_robot(still)
    free = tmp_path / "free.xml"
    free.write_text(
        '<mujoco><worldbody><body name="box"><freejoint name="float"/>'
        '<geom type="box" size="0.1 0.1 0.1"/></body></worldbody></mujoco>'
    )
    with pytest.raises(ModelError, match=r"float \(free\)"):
        jaxcomp.load_robot(free)


def test_bad_state_and_names(gen3):
    with pytest.raises(InputError, match=r"shape \(6,\).*got shape \(5,\)"):
        gen3.gravity(np.zeros(5))
    q = np.zeros(6)
    q[2] = np.nan
    with pytest.raises(InputError, match="NaN or inf at joint.*joint_2"):
        gen3.mass_matrix(q)
    with pytest.raises(InputError, match="unknown site 'tool'.*end_effector"):
        gen3.jacobian(np.zeros(6), "tool")
    with pytest.raises(InputError, match="unknown link 'HAND'"):
        gen3.link_index("HAND")
    with pytest.raises(InputError, match="dq"):
        gen3.bias(np.zeros(6), np.zeros(7))
    with pytest.raises(InputError, match="gravity"):
        gen3.gravity(np.zeros(6), gravity=[0, 0])


def test_values_that_are_not_numbers_or_not_physical_are_refused(gen3):
    """Strings instead of arrays, a negative link mass and NaN inertial params: InputError
    naming the argument (and the link), never a bare ValueError or NaN torques."""
    with pytest.raises(InputError, match=r"q must be an array of numbers of shape \(6,\)"):
        gen3.gravity("abcdef")
    with pytest.raises(InputError, match="gravity must be an array of numbers"):
        gen3.gravity(np.zeros(6), gravity="down")
    nominal = gen3.nominal_params()
    mass = np.array(nominal.mass)
    mass[gen3.link_index("ARM")] = -0.5
    with pytest.raises(InputError, match=r"params.mass must be >= 0 kg; negative for ARM"):
        gen3.gravity(np.zeros(6), nominal._replace(mass=mass))
    for field in ("mass", "com", "inertia"):
        bad = np.array(getattr(nominal, field))
        bad[gen3.link_index("FOREARM")] = np.nan
        with pytest.raises(InputError, match=f"params.{field} contains NaN.*FOREARM"):
            gen3.gravity(np.zeros(6), nominal._replace(**{field: bad}))
    q = np.full(6, 0.3)  # traced params (gradients) are not value-checked: still differentiable
    grad = jax.grad(lambda m: gen3.gravity(q, nominal._replace(mass=m)).sum())(nominal.mass)
    assert np.isfinite(grad).all() and np.abs(grad).max() > 0


def test_urdf_path_loads(tmp_path):
    from arms import offset_arm_7dof

    path = tmp_path / "arm.urdf"
    path.write_text(offset_arm_7dof())
    robot = jaxcomp.load_robot(path)
    assert robot.nv == 7 and robot.name == "arm"


def test_cli_info_prints_gravity_at_home(gen3):
    result = CliRunner().invoke(cli, ["info", "gen3_lite", "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)
    assert out["pose"] == "home"
    np.testing.assert_allclose(out["gravity_torque"], gen3.gravity(gen3.pose("home")), atol=1e-12)
    text = CliRunner().invoke(cli, ["info", "gen3_lite"])
    assert "GRIPPER_FRAME" in text.output and "joint_5" in text.output


def test_cli_reports_unknown_robot_as_one_line():
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-c", "from jaxcomp.cli import main; main()", "info", "nope"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert "error: unknown robot 'nope'" in proc.stderr
    assert "Traceback" not in proc.stderr
