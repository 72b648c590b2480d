"""Plausibility: recordings, fits and params that no real arm gives are refused with one clear
error (on built-in and generated arms), before anything is fitted or commanded; a fuzz of
random corruptions of valid files ends, every time, in status 2 with one `error:` line, no
traceback and no file changed."""

import dataclasses
import hashlib
import io
import json
import zipfile

import numpy as np
import pytest
import synthetic
from click.testing import CliRunner
from odd_arms import serial_arm

import jaxcomp
from jaxcomp import plausibility
from jaxcomp.cli import main as cli_main
from jaxcomp.cli.group import cli
from jaxcomp.control import impedance, loop
from jaxcomp.control.impedance import make_impedance_controller
from jaxcomp.control.run_result import ControlResult
from jaxcomp.errors import InputError
from jaxcomp.hardware import TrueRobot
from jaxcomp.params import gyration_radii
from jaxcomp.plausibility import (
    COM_MIN,
    COM_SIZE,
    CURRENT_FACTOR,
    MIN_SAMPLES,
    RATIO_RANGE,
    SCALE_FACTOR,
    CheckedParams,
    check_params,
    checked_arm_params,
    params_problems,
    recording_problems,
    stated_scale,
)
from jaxcomp.recording import Recording, load_recording
from jaxcomp.robot_params import RobotParams, arm_joint_indices, current_limits

FIELDS = ("t", "q", "dq", "current", "joint", "direction")


def _arm(name, tmp_path_factory):
    if name.startswith("generated"):
        path = tmp_path_factory.mktemp("arm") / f"{name}.xml"
        seed = int(name[-1])
        path.write_text(serial_arm(seed, n=4 + seed, continuous=(0,) if seed % 2 else ()))
        return jaxcomp.load_robot(path)
    return jaxcomp.load_robot(name)


def _truth(robot, seed):
    """A plausible true robot: ratios 0.7-1.3 x the stated scale, friction 2-8 % of the
    current limit, COM offsets of a few mm."""
    rng = np.random.default_rng(seed)
    scale, _ = stated_scale(robot)
    n = len(scale)
    moved = robot.tree.moves[arm_joint_indices(robot)].any(axis=0)
    return RobotParams(
        robot.name,
        scale * rng.uniform(0.7, 1.3, n),
        current_limits(robot) * rng.uniform(0.02, 0.08, n),
        {k: rng.normal(0, 0.003, 3) for k, m in zip(robot.link_names, moved, strict=True) if m},
        joints=tuple(robot.joint_names[i] for i in arm_joint_indices(robot)),
    )


@pytest.mark.parametrize("name", ["gen3_lite", "wx250s", "generated1", "generated2"])
def test_each_params_bound_is_where_it_is_stated(name, tmp_path_factory):
    """Just inside each bound: plausible; just outside: one problem naming the joint or link."""
    robot = _arm(name, tmp_path_factory)
    truth = _truth(robot, 3)
    assert params_problems(truth, robot) == []
    scale, stated = stated_scale(robot)
    limits = current_limits(robot)
    joints = truth.joints
    rng = np.random.default_rng(len(name))
    j = int(rng.integers(len(joints)))

    def with_ratio(r):
        ratio = truth.ratio.copy()
        ratio[j] = r
        return params_problems(dataclasses.replace(truth, ratio=ratio), robot)

    lo, hi = RATIO_RANGE
    if stated[j]:
        lo, hi = max(lo, scale[j] / SCALE_FACTOR), min(hi, scale[j] * SCALE_FACTOR)
    assert with_ratio(lo * 1.01) == [] and with_ratio(hi * 0.99) == []
    for r in (lo * 0.98, hi * 1.02, 1e-17):
        (problem,) = with_ratio(r)
        assert f"ratio of {joints[j]} is {r:.3g} A/(N m)" in problem
    friction = truth.friction.copy()
    friction[j] = 1.01 * limits[j]
    (problem,) = params_problems(dataclasses.replace(truth, friction=friction), robot)
    assert f"friction loss of {joints[j]}" in problem and f"{limits[j]:.3g} A" in problem
    link = list(truth.com_offset)[int(rng.integers(len(truth.com_offset)))]
    size = max(COM_SIZE * gyration_radii(robot.nominal_params())[robot.link_index(link)], COM_MIN)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    for factor, count in ((0.99, 0), (1.01, 1), (500.0, 1)):
        com = dict(truth.com_offset) | {link: factor * size * direction}
        problems = params_problems(dataclasses.replace(truth, com_offset=com), robot)
        assert len(problems) == count and all(f"COM offset of {link}" in p for p in problems)


def test_the_controller_refuses_implausible_params_before_it_is_built():
    robot = jaxcomp.load_robot("gen3_lite")
    bad = dataclasses.replace(RobotParams.nominal(robot), ratio=np.full(6, 1e-17))
    with pytest.raises(InputError, match="outside the physical range 0.001-100"):
        make_impedance_controller(robot, bad)
    with pytest.raises(InputError, match=r"COM offset of ARM is 10 m"):
        check_params(
            dataclasses.replace(bad, ratio=robot_ratio(robot), com_offset={"ARM": [10, 0, 0]}),
            robot,
        )


def robot_ratio(robot):
    return RobotParams.nominal(robot).ratio


def _count_checks(monkeypatch, method: str) -> list[tuple[str, str]]:
    """The (check, model) calls of ``RobotParams.check`` ("check") and of the plausibility
    bounds ("plausibility") on params whose ``method`` is ``method``, from now on."""
    calls = []
    check, problems = RobotParams.check, plausibility.params_problems

    def counted_check(self, robot):
        if self.method == method:
            calls.append(("check", robot.name))
        return check(self, robot)

    def counted_problems(params, robot):
        if params.method == method:
            calls.append(("plausibility", robot.name))
        return problems(params, robot)

    monkeypatch.setattr(RobotParams, "check", counted_check)
    monkeypatch.setattr(plausibility, "params_problems", counted_problems)
    return calls


def test_params_are_checked_once_on_their_way_to_the_controller(tmp_path, monkeypatch):
    """`jaxcomp control --params FILE` on the simulated mobile Gen3 Lite: the file's params
    (identified on the mobile model) are renamed for the arm-alone model, checked against it
    and bounded once each, and the controller takes them as they are."""
    mobile = jaxcomp.load_robot("mobile_gen3_lite")
    params = dataclasses.replace(TrueRobot.draw(mobile, 3).params, method="under test")
    path = params.save(tmp_path / "params.json")
    calls = _count_checks(monkeypatch, "under test")
    built = []

    def no_run(arm, base, controller, *args, **kwargs):  # the controller as the loop gets it
        built.append(controller)
        return ControlResult("completed", "not run")

    monkeypatch.setattr(impedance.ImpedanceController, "compile", lambda self, step=False: 0.0)
    monkeypatch.setattr(loop, "run_control", no_run)
    args = ["control", "--params", str(path), "--out", str(tmp_path / "run")]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output + repr(out.exception)
    assert calls == [("check", "gen3_lite"), ("plausibility", "gen3_lite")]
    (controller,) = built
    assert controller.params.model == "gen3_lite" and controller.params.method == "under test"
    np.testing.assert_array_equal(controller.resolved.ratio, params.ratio)


def test_the_controller_takes_checked_params_as_they_are(monkeypatch):
    """Checked params pass the controller's own guard (model, shapes, finite numbers) without
    a second check; params it was not given checked it checks itself."""
    robot = jaxcomp.load_robot("gen3_lite")
    truth = dataclasses.replace(_truth(robot, 0), method="under test")
    checked = checked_arm_params(truth, robot)
    calls = _count_checks(monkeypatch, "under test")
    make_impedance_controller(robot, checked)
    assert calls == []
    make_impedance_controller(robot, truth)
    assert calls == [("check", "gen3_lite"), ("plausibility", "gen3_lite")]
    other = CheckedParams(dataclasses.replace(checked.params, model="wx250s"), checked.inertial)
    with pytest.raises(InputError, match="params are for model 'wx250s', the robot is 'gen3_lite'"):
        make_impedance_controller(robot, other)
    nan = checked.inertial._replace(mass=np.full_like(checked.inertial.mass, np.nan))
    with pytest.raises(InputError, match="NaN or inf"):
        make_impedance_controller(robot, checked._replace(inertial=nan))
    with pytest.raises(InputError, match="the robot is 'wx250s'"):  # the arm's own model only
        checked_arm_params(truth, jaxcomp.load_robot("wx250s"), jaxcomp.load_robot("wx250s"))


# ------------------------------------------------------------------- recordings and the fit


@pytest.fixture(scope="module")
def robot():
    return jaxcomp.load_robot("gen3_lite")


@pytest.fixture(scope="module")
def recording(robot):
    """A short plausible recording: every joint swept both ways at 2 rad/s."""
    hold = robot.pose("home")[arm_joint_indices(robot)]
    sweeps = [(j, hold, hold[j] - 0.5, hold[j] + 0.5, 2.0) for j in range(6)]
    return synthetic.recording(robot, _truth(robot, 1), sweeps, noise=0.05, seed=2)


def _cut(rec: Recording, keep: np.ndarray) -> Recording:
    return Recording(*(getattr(rec, f)[keep] for f in FIELDS), rec.model)


def test_recording_problems_name_what_no_arm_records(recording, robot):
    assert recording_problems([recording]) == []
    limits = current_limits(robot)
    over = dataclasses.replace(recording, current=recording.current * 1e3)
    (problem,) = recording_problems([over])
    assert f"exceeds {CURRENT_FACTOR:g} times the current limit" in problem and "in mA" in problem
    just = dataclasses.replace(recording, current=recording.current.copy())
    just.current[0, 2] = 0.99 * CURRENT_FACTOR * limits[2]
    assert recording_problems([just]) == []
    silent = dataclasses.replace(recording, current=recording.current.copy())
    silent.current[recording.joint == 3, 3] = 0.0
    (problem,) = recording_problems([silent])
    assert problem.startswith("the current of joint_3 is zero over its sweeps")
    one_way = _cut(recording, ~((recording.joint == 4) & (recording.direction < 0)))
    (problem,) = recording_problems([one_way])
    assert "joint_4 is swept in one direction only" in problem
    only_1 = _cut(recording, recording.joint == 1)
    problems = recording_problems([only_1])
    assert len(problems) == 5 and all("is never swept" in p for p in problems)
    # two recordings that each lack a joint's way back cover each other
    a = _cut(recording, ~((recording.joint == 4) & (recording.direction < 0)))
    b = _cut(recording, ~((recording.joint == 4) & (recording.direction > 0)))
    assert recording_problems([a, b]) == []
    few = (recording.joint == 5) & (recording.direction > 0)
    keep = ~few | (np.cumsum(few) <= MIN_SAMPLES - 1)
    assert (
        "joint_5 is swept in one direction only" in recording_problems([_cut(recording, keep)])[0]
    )


def _run(argv, monkeypatch, capsys) -> tuple[int, list[str]]:
    monkeypatch.setattr("sys.argv", ["jaxcomp", *argv])
    monkeypatch.setenv("JAXCOMP_CACHE", "off")
    with pytest.raises(SystemExit) as exc:
        cli_main()
        raise SystemExit(0)
    return exc.value.code, capsys.readouterr().err.strip().splitlines()


def _digests(folder) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def _assert_refused(status, err, folder, before, phrase=""):
    assert status == 2, err
    assert [x for x in err if x.startswith("error:")] == [err[-1]], err
    assert phrase in err[-1]
    assert not any("Traceback" in x for x in err)
    assert _digests(folder) == before


@pytest.mark.parametrize(
    "corrupt, phrase",
    [
        (lambda r: dataclasses.replace(r, current=0 * r.current), "is zero over its sweeps"),
        (lambda r: dataclasses.replace(r, current=1e3 * r.current), "a current in mA"),
        (lambda r: _cut(r, (r.joint == 2) & (r.direction > 0)), "swept in one direction only"),
        (lambda r: _cut(r, r.joint == 1), "joint_0 is never swept"),
    ],
)
@pytest.mark.parametrize("method", ["jax", "scipy"])
def test_fit_refuses_recordings_no_arm_gives(
    corrupt, phrase, method, recording, tmp_path, monkeypatch, capsys
):
    path = corrupt(recording).save(tmp_path / "rec.npz")
    (tmp_path / "p.json").write_text("{}")  # a file the failed fit must leave alone
    before = _digests(tmp_path)
    status, err = _run(
        ["fit", str(path), "--method", method, "--out", str(tmp_path / "p.json")],
        monkeypatch,
        capsys,
    )
    _assert_refused(status, err, tmp_path, before, phrase)


# ------------------------------------------------------------------- fuzz


def _recording_corruptions(rec: Recording, rng) -> list:
    """Ways to spoil a valid recording (each makes a file that must be refused), as functions
    of nothing: only the chosen one runs."""
    n, count = rec.current.shape[1], rec.n_samples
    j, i = int(rng.integers(n)), int(rng.integers(count))
    own = rec.joint == j

    def arrays(**changes):
        data = {f: getattr(rec, f) for f in FIELDS} | {"model": np.array(rec.model)}
        return data | changes

    def changed(field, index, value):
        out = getattr(rec, field).copy()
        out[index] = value
        return out

    def without(mask):
        return arrays(**{f: getattr(rec, f)[~mask] for f in FIELDS})

    k = int(rng.integers(1, count - 1))
    drop = str(rng.choice(FIELDS))
    return [
        lambda: arrays(current=rec.current * rng.uniform(50, 1e4)),  # mA
        lambda: arrays(current=changed("current", (own, j), rng.uniform(0, 1e-3))),
        lambda: arrays(current=np.zeros_like(rec.current)),
        lambda: arrays(q=np.rad2deg(rec.q)),  # degrees
        lambda: arrays(q=changed("q", (i, j), rng.choice([np.nan, np.inf, -np.inf]))),
        lambda: arrays(t=changed("t", [k - 1, k], rec.t[[k, k - 1]])),
        lambda: without(own & (rec.direction > 0)),
        lambda: without(own),
        lambda: arrays(joint=changed("joint", i, rng.choice([n, n + 3, -2]))),
        lambda: arrays(direction=changed("direction", rec.joint >= 0, rng.choice([2, 0]))),
        lambda: arrays(dq=rec.dq[:, : n - 1]),
        lambda: arrays(current=rec.current[: count // 2]),
        lambda: {f: v for f, v in arrays().items() if f != drop},
        lambda: arrays(model=np.array(rng.choice(["no_such_robot", "wx250s", ""]))),
        lambda: arrays(current=np.array([["1.5 A"] * n] * count)),
        lambda: "truncate",
        lambda: "garbage",
    ]


def _params_corruptions(params: dict, rng) -> list:
    n = len(params["ratio"])
    j = int(rng.integers(n))
    link = str(rng.choice(sorted(params["com_offset"])))
    missing = str(rng.choice(["model", "ratio", "friction"]))

    def at(field, value):
        vec = list(params[field])
        vec[j] = value
        return params | {field: vec}

    return [
        lambda: at("ratio", float(rng.choice([1e-17, 1e-5, 1e3, 1e9]))),
        lambda: at("ratio", -float(rng.uniform(0.1, 2))),
        lambda: at("ratio", float(rng.choice([np.nan, np.inf]))),
        lambda: at("friction", float(rng.uniform(20, 1e4))),
        lambda: at("friction", -float(rng.uniform(0.1, 1))),
        lambda: params | {"com_offset": params["com_offset"] | {link: list(rng.normal(0, 10, 3))}},
        lambda: params | {"com_offset": params["com_offset"] | {"NO_SUCH_LINK": [0.0, 0.0, 0.0]}},
        lambda: params | {"model": str(rng.choice(["wx250s", "no_such_robot", ""]))},
        lambda: params | {"ratio": params["ratio"][: int(rng.integers(n))]},
        lambda: params | {"ratio": "fast"},
        lambda: {k: v for k, v in params.items() if k != missing},
        lambda: params | {"joints": list(reversed(params["joints"]))},
        lambda: "truncate",
        lambda: "garbage",
    ]


def _write(path, spoiled, original: bytes, rng):
    if isinstance(spoiled, dict) and path.suffix == ".npz":
        with open(path, "wb") as fh:
            np.savez(fh, **spoiled)
    elif isinstance(spoiled, dict):
        path.write_text(json.dumps(spoiled))
    elif spoiled == "truncate":
        path.write_bytes(original[: int(rng.integers(0, len(original) - 1))])
    else:
        junk = rng.bytes(int(rng.integers(1, 200)))
        path.write_bytes(junk if rng.random() < 0.5 else b"PK\x03\x04" + junk)


def test_fuzz_a_thousand_corruptions_end_in_one_error_and_change_nothing(
    recording, robot, tmp_path, monkeypatch, capsys
):
    """1000 random corruptions of a valid recording and a valid params file, through `jaxcomp
    check` (the same loading and checks as fit and control), and a sample of them through
    `jaxcomp fit` and `jaxcomp control`: each ends in status 2 with one `error:` line, no
    traceback, and no file in the folder changed."""
    rng = np.random.default_rng(2026)
    good_rec = recording.save(tmp_path / "good.npz").read_bytes()
    params = json.loads(RobotParams.nominal(robot).to_json())
    params["com_offset"] = {k: [0.001, 0.0, -0.002] for k in ("ARM", "FOREARM", "LOWER_WRIST")}
    good_params = json.dumps(params).encode()
    (tmp_path / "good.json").write_bytes(good_params)
    status, err = _run(
        ["check", str(tmp_path / "good.npz"), str(tmp_path / "good.json")], monkeypatch, capsys
    )
    assert status == 0, err
    kinds = {}
    for case in range(1000):
        is_rec = case % 2 == 0
        options = (
            _recording_corruptions(recording, rng) if is_rec else _params_corruptions(params, rng)
        )
        k = int(rng.integers(len(options)))
        kinds[(is_rec, k)] = kinds.get((is_rec, k), 0) + 1
        path = tmp_path / ("case.npz" if is_rec else "case.json")
        _write(path, options[k](), good_rec if is_rec else good_params, rng)
        before = _digests(tmp_path)
        argv = ["check", str(path)]
        if case % 50 == 0:  # the commands that use them
            argv = (
                ["fit", str(path), "--out", str(tmp_path / "good.json")]
                if is_rec
                else ["control", "--model", "gen3_lite", "--params", str(path)]
                + ["--duration", "0.01", "--out", str(tmp_path / "run")]
            )
        status, err = _run(argv, monkeypatch, capsys)
        try:
            _assert_refused(status, err, tmp_path, before)
        except AssertionError as exc:
            raise AssertionError(
                f"case {case} ({'recording' if is_rec else 'params'} #{k})"
            ) from exc
        assert not (tmp_path / "run").exists()
    assert len(kinds) == 31  # every kind of corruption was tried
    assert (tmp_path / "good.npz").read_bytes() == good_rec
    assert isinstance(load_recording(tmp_path / "good.npz"), Recording)
    zipfile.ZipFile(io.BytesIO(good_rec)).testzip()
