"""RobotParams: JSON round trip, atomic save, validation with one clear error per problem."""

import json

import numpy as np
import pytest

import jaxcomp
from jaxcomp.errors import InputError
from jaxcomp.robot_params import RobotParams, arm_joint_indices

JOINTS = [f"joint_{i}" for i in range(6)]


@pytest.fixture(scope="module")
def robot():
    return jaxcomp.load_robot("gen3_lite")


def _params():
    return RobotParams(
        model="gen3_lite",
        ratio=[1.03, 0.31, 1.03, 1.91, 2.04, 1.97],
        friction=[0.53, 1.48, 0.67, 0.30, 0.37, 0.59],
        com_offset={"ARM": [0.001, -0.002, 0.003], "FOREARM": [0.0, 0.004, 0.0]},
        phase_shift=[0.0, 0.01, -0.02, 0.0, 0.005, 0.0],
        std={"ratio": [0.01] * 6},
        method="lsq",
        fit_seconds=1.5,
    )


def test_json_round_trip_keeps_every_field(tmp_path, robot):
    p = _params()
    path = p.save(tmp_path / "params.json")
    q = RobotParams.load(path, robot)
    np.testing.assert_array_equal(q.ratio, p.ratio)
    np.testing.assert_array_equal(q.friction, p.friction)
    np.testing.assert_array_equal(q.com_offset["ARM"], [0.001, -0.002, 0.003])
    np.testing.assert_array_equal(q.phase_shift, p.phase_shift)
    assert q.std == {"ratio": [0.01] * 6}
    assert (q.method, q.fit_seconds, q.model) == ("lsq", 1.5, "gen3_lite")
    data = json.loads(path.read_text())
    assert set(data) == {
        "model",
        "ratio",
        "friction",
        "com_offset",
        "phase_shift",
        "std",
        "method",
        "fit_seconds",
        "diagnostics",
    }


def test_save_is_atomic(tmp_path):
    path = tmp_path / "params.json"
    _params().save(path)
    before = path.read_text()
    with pytest.raises(TypeError):  # not JSON-serialisable: the old file must survive intact
        _params().save(path, extra={"bad": object()})
    assert path.read_text() == before
    assert [f.name for f in tmp_path.iterdir()] == ["params.json"]  # no temp file left


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda d: d.pop("friction"), "missing: friction"),
        (
            lambda d: d.update(ratio=[1.0] * 5, joints=JOINTS),
            ": ratio must have 6 entries, one per joint named in joints, got 5$",
        ),
        (lambda d: d.update(friction=[0.0] * 7, joints=JOINTS), ": friction must have 6 .*got 7$"),
        (lambda d: d.update(ratio=[1.0] * 5), ": ratio has 5 entries but friction 6: both need"),
        (
            lambda d: d.update(friction=[0.1, float("nan"), 0.1, 0.1, 0.1, 0.1]),
            "friction contains NaN",
        ),
        (lambda d: d.update(ratio=[1.0, 0.0, 1.0, 1.0, 1.0, 1.0]), "ratio must be positive"),
        (lambda d: d.update(friction=[0.1, -0.1, 0.1, 0.1, 0.1, 0.1]), "friction must be >= 0"),
        (lambda d: d.update(com_offset={"ELBOW": [0, 0, 0]}), "unknown link.*'ELBOW'"),
        (lambda d: d.update(com_offset={"ARM": [0, 0]}), r"com_offset\['ARM'\] must have shape"),
        (lambda d: d.update(phase_shift=[0.0] * 4), "phase_shift must have shape"),
    ],
)
def test_load_refuses_bad_files_with_one_clear_error(tmp_path, robot, change, match):
    data = _params().to_dict()
    change(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=match):
        RobotParams.load(path, robot)


def test_wrong_joint_count_for_the_robot(robot):
    p = RobotParams("gen3_lite", [1.0] * 5, [0.0] * 5)
    with pytest.raises(InputError, match="5 entries but gen3_lite has 6"):
        p.check(robot)


def test_not_json_and_missing_file(tmp_path):
    path = tmp_path / "x.json"
    path.write_text("{ratio: ")
    with pytest.raises(InputError, match="not valid JSON"):
        RobotParams.load(path)
    with pytest.raises(InputError, match="not found"):
        RobotParams.load(tmp_path / "nope.json")


def test_nominal_reads_the_models_ratio(robot):
    p = RobotParams.nominal(robot)
    np.testing.assert_allclose(p.ratio, [0.85, 0.25, 0.85, 1.75, 1.75, 1.75])
    assert np.all(p.friction == 0) and p.com_offset == {} and p.method == "nominal"


def test_inertial_params_move_the_com_in_the_link_frame(robot):
    p = RobotParams("gen3_lite", [1.0] * 6, [0.0] * 6, {"FOREARM": [0.0, 0.01, 0.0]})
    ip = p.inertial_params(robot)
    nominal = robot.nominal_params()
    k = robot.link_index("FOREARM")
    np.testing.assert_allclose(np.asarray(ip.com[k] - nominal.com[k]), [0.0, 0.01, 0.0])
    others = np.delete(np.arange(len(robot.link_names)), k)
    np.testing.assert_array_equal(np.asarray(ip.com)[others], np.asarray(nominal.com)[others])
    # 1 cm along the forearm changes joint 2's gravity torque by m g 0.01 at most (0.059 N m)
    q = robot.pose("preferred")
    change = float(np.abs(robot.gravity(q, ip) - robot.gravity(q))[2])
    assert 0.02 < change <= 0.598 * 9.81 * 0.01 + 1e-9


def test_mobile_robot_params_cover_the_arm_joints_only():
    mobile = jaxcomp.load_robot("mobile_gen3_lite")
    assert [mobile.joint_names[j] for j in arm_joint_indices(mobile)] == [
        f"joint_{k}" for k in range(6)
    ]
    assert RobotParams.nominal(mobile).n == 6
