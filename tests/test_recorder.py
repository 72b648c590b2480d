"""Calibration plans (identify/plan.py, plan_checks.py, plan_design.py) and recording them
(identify/recorder.py)."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcomp import dynamics, load_robot
from jaxcomp.errors import InputError
from jaxcomp.hardware import Simulator
from jaxcomp.identify.bins import steady
from jaxcomp.identify.plan import (
    LOWER,
    SPEED,
    UPPER,
    CalibrationPlan,
    Sweep,
    load_plan,
    plan_for_joints,
    plan_from_dict,
)
from jaxcomp.identify.plan_checks import plan_issues
from jaxcomp.identify.plan_design import PlanOptions, default_plan
from jaxcomp.identify.recorder import record
from jaxcomp.recording import load_recording, recover

ROBOT = load_robot("gen3_lite")
HOME = ROBOT.pose("home")
DEG20 = math.radians(20.0)


def short_plan(joints=(1,), settle=0.2) -> CalibrationPlan:
    """Joints swept over +-20 deg at 40 deg/s from the home pose: about 2.7 s each."""
    return plan_for_joints(ROBOT, list(joints), "home", lower=-DEG20, upper=DEG20, settle=settle)


# --------------------------------------------------------------------- plans
def test_sweep_poses_and_defaults():
    s = Sweep(2, HOME)
    assert (s.lower, s.upper, s.speed) == (LOWER, UPPER, SPEED)
    assert math.isclose(math.degrees(s.lower), -100) and math.isclose(math.degrees(s.speed), 40)
    np.testing.assert_allclose(s.start, np.r_[HOME[:2], LOWER, HOME[3:]])
    np.testing.assert_allclose(s.turn, np.r_[HOME[:2], UPPER, HOME[3:]])
    assert s.via == () and s == Sweep(2, HOME.tolist())


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"joint": 1.5}, "'joint'"),
        ({"joint": True}, "'joint'"),
        ({"hold": [0.0, np.nan, 0, 0, 0, 0]}, "'hold'"),
        ({"hold": [[0.0] * 6]}, "'hold'"),
        ({"hold": "home"}, "'hold'"),
        ({"lower": 0.5, "upper": 0.2}, "'lower'"),
        ({"upper": np.inf}, "'upper'"),
        ({"speed": 0.0}, "'speed'"),
        ({"speed": 40.0}, "deg/s"),
        ({"via": [[0.0] * 5 + [np.nan]]}, "'via'"),
        ({"via": "x"}, "'via'"),
    ],
)
def test_sweep_errors(kwargs, words):
    args = {"joint": 1, "hold": HOME} | kwargs
    with pytest.raises(InputError, match=words):
        Sweep(**args)


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"sweeps": ()}, "'sweeps' is empty"),
        ({"sweeps": ("x",)}, "sweep 0 must be a Sweep"),
        ({"move_speed": -1.0}, "'move_speed'"),
        ({"move_speed": 30.0}, "deg/s"),
        ({"settle": 0.0}, "'settle'"),
        ({"ramp": 0.0}, "'ramp'"),
    ],
)
def test_plan_errors(kwargs, words):
    args = {"sweeps": (Sweep(1, HOME),)} | kwargs
    with pytest.raises(InputError, match=words):
        CalibrationPlan(**args)


@pytest.mark.parametrize(
    "sweep, words",
    [
        (Sweep(6, HOME), "'joint' 6"),
        (Sweep(1, HOME[:5]), "'hold' must have 6"),
        (Sweep(1, np.rad2deg(HOME)), "degrees"),
        (Sweep(1, HOME, upper=math.radians(170)), "'upper' 170.0 deg of joint_1"),
        (Sweep(1, HOME, lower=-2.75), "'lower'"),
        (Sweep(1, np.r_[HOME[:3], 2.7, HOME[4:]]), "'hold' 154.7 deg of joint_3"),
        (Sweep(1, HOME, via=[np.r_[HOME[:5], 3.0]]), "'via'"),
        (Sweep(1, HOME, via=[HOME[:4]]), "'via' must have 6"),
    ],
)
def test_plan_validation_against_the_robot(sweep, words):
    plan = CalibrationPlan((Sweep(2, HOME), sweep))
    with pytest.raises(InputError, match=words) as err:
        plan.validate(ROBOT)
    assert "plan sweep 1" in str(err.value)


def test_swept_joint_entry_of_hold_is_ignored():
    hold = HOME.copy()
    hold[1] = 9.0  # beyond the limits, but it is the swept joint's entry
    plan = CalibrationPlan((Sweep(1, hold, -DEG20, DEG20),)).validate(ROBOT)
    assert plan.sweeps[0].start[1] == -DEG20


def test_plan_json_round_trip(tmp_path):
    plan = CalibrationPlan(
        (Sweep(1, HOME, -0.3, 0.4, 0.5, via=[HOME]), Sweep(3, np.zeros(6))),
        move_speed=0.6,
        settle=0.3,
        ramp=0.2,
    )
    path = plan.save(tmp_path / "plan.json")
    assert load_plan(path, ROBOT) == plan
    data = json.loads(path.read_text())
    assert data["units"]["hold"] == "rad" and data["sweeps"][0]["via"] == [HOME.tolist()]
    minimal = {"sweeps": [{"joint": 2, "hold": [0] * 6}]}
    assert plan_from_dict(minimal) == CalibrationPlan((Sweep(2, np.zeros(6)),))


@pytest.mark.parametrize(
    "data, words",
    [
        ([], "JSON object"),
        ({}, "'sweeps' is missing"),
        ({"sweeps": {}}, "list of sweeps"),
        ({"sweeps": [{"hold": [0] * 6}]}, r"sweep 0: field\(s\) \['joint'\] missing"),
        ({"sweeps": [{"joint": 1, "hold": [0] * 6, "lowr": 0}]}, "unknown field.*lowr"),
        ({"sweeps": [{"joint": 1, "hold": [0] * 6, "speed": 40}]}, "sweep 0: .*deg/s"),
        ({"sweeps": [], "extra": 1}, "unknown field.*extra"),
        ({"sweeps": [], "units": {"hold": "deg"}}, "'units'"),
        ({"format": "other", "sweeps": []}, "'format'"),
    ],
)
def test_plan_file_errors(tmp_path, data, words):
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=words) as err:
        load_plan(path)
    assert str(path) in str(err.value)


def test_plan_file_unreadable(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_plan(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(InputError, match="not a readable JSON plan"):
        load_plan(tmp_path / "bad.json")
    deg = CalibrationPlan((Sweep(1, np.full(6, 90.0), -0.1, 0.1),))
    with pytest.raises(InputError, match="degrees"):
        load_plan(deg.save(tmp_path / "deg.json"), ROBOT)


def test_plan_for_joints_and_estimates():
    plan = plan_for_joints(ROBOT, [1, 3], lower=-DEG20, upper=DEG20, settle=0.5, ramp=0.25)
    assert plan.joints == [1, 3]
    np.testing.assert_allclose(plan.sweeps[1].hold, HOME)
    # each sweep: 40 deg at 40 deg/s plus one ramp time, twice; plus settling
    per_sweep = 2 * (1.0 + 0.25)
    assert plan.sweeps[0].samples(plan.ramp) == round(per_sweep * 1000)
    # from sweep 0's start to sweep 1's: joint 3 moves 20 deg at 40 deg/s, one ramp time more
    assert plan.duration() == pytest.approx(2 * (per_sweep + 0.5) + 20 / 40 + 0.25)
    assert plan.samples(HOME) > plan.samples()  # the way from home to sweep 0 counts
    assert plan.samples(sweeps=[1]) < plan.samples()
    with pytest.raises(InputError, match="unknown pose"):
        plan_for_joints(ROBOT, 1, "nowhere")
    assert "2 sweeps" in plan.describe()


def test_plan_issues_flags_silly_plans():
    straight = CalibrationPlan((Sweep(1, np.zeros(6)),))  # the stretched arm at 100 deg
    issues = plan_issues(ROBOT, straight)
    assert issues and "joint 1 needs" in issues[0] and "effort limit" in issues[0]
    folded = np.deg2rad([0.0, 0.0, 120.0, 0.0, 0.0, 0.0])
    floor = CalibrationPlan((Sweep(1, folded, math.radians(-100), 0.0),))
    assert any("below" in i for i in plan_issues(ROBOT, floor))
    assert plan_issues(ROBOT, short_plan(), start="home") == []


@pytest.fixture(scope="module")
def plan():
    return default_plan(ROBOT)


def test_default_plan(plan):
    """Every joint swept; the four joints gravity loads three times; ~200 s at 1 kHz."""
    assert plan.joints == sorted(plan.joints)
    counts = np.bincount(plan.joints, minlength=6)
    assert counts.tolist() == [1, 3, 3, 3, 3, 1]  # 0 and 5: no gravity lever, friction only
    assert 150 < plan.duration(HOME) < 250 and plan.samples(HOME) > 150_000
    for j in range(6):  # one sweep of each loaded joint at half speed (viscous friction)
        speeds = sorted(s.speed for s in plan.sweeps if s.joint == j)
        assert speeds == pytest.approx([SPEED / 2, SPEED, SPEED] if 0 < j < 5 else [SPEED])
    for s in plan.sweeps:
        assert LOWER - 1e-9 <= s.lower < s.upper <= UPPER + 1e-9
        assert s.upper - s.lower >= math.radians(100) - 1e-9
    full = [s for s in plan.sweeps if s.joint != 1]
    assert all(np.isclose([s.lower, s.upper], [LOWER, UPPER]).all() for s in full)
    # the holds of a joint differ, and some hold a joint at 90 deg to give gravity a lever
    for j in range(1, 5):
        holds = [np.delete(s.hold, j) for s in plan.sweeps if s.joint == j]
        assert len({tuple(np.round(h, 6)) for h in holds}) == 3
    assert any(np.isclose(np.abs(s.hold), np.pi / 2).any() for s in plan.sweeps)
    assert plan_issues(ROBOT, plan, start="home") == []
    # gravity has a lever: the swept joint's gravity torque varies by N m over each sweep
    for s in plan.sweeps:
        g = np.array([ROBOT.gravity(s.pose(a))[s.joint] for a in np.linspace(s.lower, s.upper, 9)])
        assert np.ptp(g) > (0.5 if s.joint in (1, 2, 3, 4) else -1.0), s
    plan.validate(ROBOT)


def test_default_plan_is_kept_on_the_robot_per_options(plan):
    """One frozen PlanOptions is the cache key; keyword arguments build it."""
    assert default_plan(ROBOT) is plan
    assert default_plan(ROBOT, PlanOptions()) is plan
    assert default_plan(ROBOT, sweeps_per_joint=3, grid=list(PlanOptions().grid)) is plan
    assert PlanOptions(gravity=[0, 0, -9.81]) == PlanOptions(gravity=(0.0, 0.0, -9.81))
    with pytest.raises(TypeError):
        default_plan(ROBOT, sweep_per_joint=1)


# --------------------------------------------------------------------- recording
def test_record_fields_and_units(tmp_path):
    sim = Simulator("gen3_lite", seed=1)
    plan = short_plan()
    start = sim.arm.read()
    rec = record(sim.arm, plan, tmp_path / "rec.npz", model="gen3_lite", progress=True)
    assert rec.model == "gen3_lite" and rec.n_joints == 6
    assert rec.current_lag == sim.arm.current_lag == 1e-3  # the servo's current of the step before
    assert rec.n_samples == plan.samples(start.q)
    np.testing.assert_allclose(np.diff(rec.t), 1e-3, atol=1e-9)
    assert rec.t[0] == pytest.approx(start.t + 1e-3)
    swept = rec.joint == 1
    assert set(np.unique(rec.joint)) == {-1, 1}
    # the travel and settling come first (joint -1, direction 0), then up (+1), then down (-1)
    first = np.flatnonzero(swept)[0]
    assert first == plan.samples(start.q) - plan.sweeps[0].samples(plan.ramp)
    assert np.all(rec.direction[:first] == 0)
    d = rec.direction[swept]
    assert np.all(d[: len(d) // 2] == 1) and np.all(d[len(d) // 2 :] == -1)
    # directions follow the command: the first up samples barely move yet
    assert abs(rec.dq[first, 1]) < 0.05 * SPEED
    # SI units: rad, rad/s, A
    q1 = rec.q[swept, 1]
    assert q1.min() == pytest.approx(-DEG20, abs=2e-3) and q1.max() == pytest.approx(
        DEG20, abs=2e-3
    )
    fast = steady(rec)
    np.testing.assert_allclose(np.abs(rec.dq[fast, 1]), SPEED, rtol=0.02)
    held = np.delete(np.arange(6), 1)
    sag = rec.q[:, held] - HOME[held]  # the stiff servo gives a little under gravity
    assert np.abs(sag).max() < 0.01
    assert np.abs(rec.current).max() < 11.0
    assert not (tmp_path / "rec.npz.parts").exists()
    back = load_recording(tmp_path / "rec.npz")
    np.testing.assert_array_equal(back.current, rec.current)
    np.testing.assert_allclose(sim.arm.read().q, plan.sweeps[0].start, atol=0.01)


def test_recorded_currents_match_the_truth(tmp_path):
    """Steady sweep samples: c = r g(q) + l direction with the true robot's ratio r,
    friction loss l and centre-of-mass offsets (the swept joint's own speed adds no Coriolis
    torque to it; the held joints' static friction takes anything within +-l)."""
    sim = Simulator("gen3_lite", seed=2)
    truth, robot = sim.truth, sim.robot
    plan = short_plan(joints=(1, 2, 4))
    rec = record(sim.arm, plan, tmp_path / "rec.npz", model="gen3_lite", progress=False)
    params = truth.params.inertial_params(robot)
    gravity = jax.jit(jax.vmap(lambda q: dynamics.gravity(robot.tree, q, params)))
    fast = steady(rec)
    tau = np.asarray(gravity(jnp.asarray(rec.q[fast])))
    r, l, noise = truth.ratio, truth.friction, truth.current_noise
    for j in (1, 2, 4):
        sel = rec.joint[fast] == j
        model = r[j] * tau[sel, j] + l[j] * rec.direction[fast][sel]
        resid = rec.current[fast][sel, j] - model
        assert sel.sum() > 1000
        assert abs(resid.mean()) < 0.02, j  # no bias beyond the noise's
        assert resid.std() < 1.5 * noise and np.abs(resid).max() < 6 * noise, j
        for k in np.delete(np.arange(6), j):
            held = rec.current[fast][sel, k] - r[k] * tau[sel, k]
            assert np.abs(held).max() < l[k] + 6 * noise, (j, k)
    # the nominal model's gravity would not match as well: the truth has other ratios
    assert not np.allclose(r, robot.custom_numeric("jaxcomp_nominal_ratio"))


class Interrupt(Exception):
    pass


def _interrupt_after(monkeypatch, arm, calls: int, samples: int, error=KeyboardInterrupt):
    """Make ``arm.move_to`` raise ``error`` after ``samples`` states of call number
    ``calls`` (0-based); every state passed on is also returned in a list."""
    seen: list = []
    real = arm.move_to
    count = {"calls": 0}

    def move_to(pose, speed, on_state=None, **kw):
        k = count["calls"]
        count["calls"] += 1
        n = {"states": 0}

        def wrapped(state):
            if k == calls and n["states"] == samples:
                raise error("stop")
            n["states"] += 1
            seen.append(state)
            on_state(state)

        return real(pose, speed, on_state=wrapped, **kw)

    monkeypatch.setattr(arm, "move_to", move_to)
    return seen


def _rows(states) -> dict:
    return {
        "t": np.array([s.t for s in states]),
        "q": np.array([s.q for s in states]),
        "current": np.array([s.current for s in states]),
    }


def test_resume_after_an_interruption(tmp_path, monkeypatch):
    sim = Simulator("gen3_lite", seed=3)
    plan = short_plan(joints=(1, 2))
    path = tmp_path / "rec.npz"
    # sweep 0 = 3 moves (travel, up, down); interrupt sweep 1's up move after 300 samples
    first_run = _interrupt_after(monkeypatch, sim.arm, calls=4, samples=300)
    with pytest.raises(KeyboardInterrupt):
        record(sim.arm, plan, path, model="gen3_lite", progress=False)
    manifest = json.loads((tmp_path / "rec.npz.parts" / "manifest.json").read_text())
    assert manifest["completed"] == [0]
    kept = load_recording(path)  # the finished sweep, a loadable recording
    monkeypatch.undo()

    second_run = _interrupt_after(monkeypatch, sim.arm, calls=-1, samples=0)
    rec = record(sim.arm, plan, path, model="gen3_lite", progress=False, resume=True)
    assert not (tmp_path / "rec.npz.parts").exists()
    # sweep 0 kept, sweep 1 recorded once, from the second run only
    n0 = int(np.flatnonzero(rec.joint == 1)[-1]) + 1
    assert set(np.unique(rec.joint[:n0])) == {-1, 1}
    assert kept.n_samples == n0
    np.testing.assert_array_equal(kept.current, rec.current[:n0])
    assert set(np.unique(rec.joint[n0:])) == {-1, 2}
    assert not np.any(rec.joint[n0:] == 1)
    before, after = _rows(first_run[:n0]), _rows(second_run)
    union = {k: np.concatenate([before[k], after[k]]) for k in before}
    assert rec.n_samples == n0 + len(second_run)
    for k, v in union.items():
        np.testing.assert_array_equal(getattr(rec, k), v, err_msg=k)
    assert np.all(np.diff(rec.t) > 0)


def test_recover_after_an_interruption(tmp_path, monkeypatch):
    sim = Simulator("gen3_lite", seed=4)
    plan = short_plan(joints=(1, 2))
    path = tmp_path / "rec.npz"
    _interrupt_after(monkeypatch, sim.arm, calls=4, samples=1100, error=Interrupt)
    with pytest.raises(Interrupt):
        record(sim.arm, plan, path, model="gen3_lite", progress=False)
    rec = recover(path)  # sweep 0 and the 1.1 s of sweep 1 flushed on the way out
    n0 = plan.samples(HOME, [0])
    assert rec.n_samples > n0 + 1000 and set(np.unique(rec.joint)) == {-1, 1, 2}


def test_resume_on_a_restarted_arm_continues_the_clock(tmp_path, monkeypatch):
    plan = short_plan(joints=(1, 2))
    path = tmp_path / "rec.npz"
    sim = Simulator("gen3_lite", seed=5)
    _interrupt_after(monkeypatch, sim.arm, calls=5, samples=10)
    with pytest.raises(KeyboardInterrupt):
        record(sim.arm, plan, path, model="gen3_lite", progress=False)
    monkeypatch.undo()
    fresh = Simulator("gen3_lite", seed=6)  # its clock starts at 0 again
    rec = record(fresh.arm, plan, path, model="gen3_lite", progress=False, resume=True)
    n0 = plan.samples(HOME, [0])
    assert np.all(np.diff(rec.t) > 0)
    np.testing.assert_allclose(rec.t[n0] - rec.t[n0 - 1], 1e-3)


def test_resume_with_another_plan_is_refused(tmp_path, monkeypatch):
    sim = Simulator("gen3_lite", seed=7)
    path = tmp_path / "rec.npz"
    _interrupt_after(monkeypatch, sim.arm, calls=4, samples=10)
    with pytest.raises(KeyboardInterrupt):
        record(sim.arm, short_plan(joints=(1, 2)), path, model="gen3_lite", progress=False)
    monkeypatch.undo()
    with pytest.raises(InputError, match="the plan differs"):
        record(sim.arm, short_plan(joints=(1, 3)), path, model="gen3_lite", resume=True)
    # without resume it starts over
    rec = record(sim.arm, short_plan(joints=(3,)), path, model="gen3_lite", progress=False)
    assert set(np.unique(rec.joint)) == {-1, 3}


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"gravity": [0, 0, -981.0]}, "'gravity'"),
        ({"gravity": [0, -9.81]}, "'gravity'"),
        ({"payload_mass": -1.0}, "'payload_mass'"),
        ({"payload_com": [0, 0, 40.0]}, "'payload_com'"),
        ({"model": "dingo_o"}, "current-controlled joints"),
    ],
)
def test_record_checks_before_moving(tmp_path, kwargs, words):
    sim = Simulator("gen3_lite", seed=8)
    t0 = sim.t
    args = {"model": "gen3_lite", "progress": False} | kwargs
    with pytest.raises(InputError, match=words):
        record(sim.arm, short_plan(), tmp_path / "rec.npz", **args)
    assert sim.t == t0 and not (tmp_path / "rec.npz.parts").exists()


def test_record_refuses_bad_plans(tmp_path):
    sim = Simulator("gen3_lite", seed=9)
    bad = CalibrationPlan((Sweep(7, HOME),))
    with pytest.raises(InputError, match="'joint' 7"):
        record(sim.arm, bad, tmp_path / "r.npz", model="gen3_lite", progress=False)
    fast = CalibrationPlan((Sweep(1, HOME, -0.1, 0.1, speed=3.0),))
    with pytest.raises(InputError, match="speed limit"):
        record(sim.arm, fast, tmp_path / "r.npz", model="gen3_lite", progress=False)
    with pytest.raises(InputError, match="CalibrationPlan"):
        record(sim.arm, [Sweep(1, HOME)], tmp_path / "r.npz", model="gen3_lite")
    assert sim.t == 0.0


def test_record_with_metadata(tmp_path):
    sim = Simulator("gen3_lite", seed=10)
    rec = record(
        sim.arm,
        short_plan(),
        tmp_path / "rec.npz",
        model="gen3_lite",
        gravity=[0, 0, -9.81],
        payload_mass=0.0,
        payload_com=[0, 0, 0.05],
        progress=False,
    )
    np.testing.assert_allclose(rec.payload_com, [0, 0, 0.05])
    np.testing.assert_allclose(load_recording(tmp_path / "rec.npz").gravity, [0, 0, -9.81])
