"""The joint JAX fit: accuracy against the truth and the scipy baseline, standard errors,
identifiability handling, several recordings, failure modes."""

import dataclasses
import hashlib
import json

import numpy as np
import pytest
import synthetic
from click.testing import CliRunner

import jaxcomp
from jaxcomp.cli import cli
from jaxcomp.errors import InputError
from jaxcomp.identify import batched_fit, joint_fit
from jaxcomp.identify.baseline import fit_baseline
from jaxcomp.identify.fit_model import fit_model
from jaxcomp.identify.fit_solver import solve
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.recording import Recording
from jaxcomp.robot_params import RobotParams, arm_joint_indices

PAPER_RATIO = [1.0282, 0.3074, 1.0282, 1.9074, 2.0373, 1.9724]
PAPER_FRICTION = [0.5318, 1.4776, 0.6695, 0.3013, 0.3732, 0.5923]
LINKS = ("SHOULDER", "ARM", "FOREARM", "LOWER_WRIST", "UPPER_WRIST", "GRIPPER_FRAME")


@pytest.fixture(scope="module")
def robot():
    return jaxcomp.load_robot("gen3_lite")


@pytest.fixture(scope="module")
def truth():
    rng = np.random.default_rng(5)
    return RobotParams(
        "gen3_lite",
        PAPER_RATIO,
        PAPER_FRICTION,
        {link: rng.uniform(-0.004, 0.004, 3) for link in LINKS},
    )


@pytest.fixture(scope="module")
def sweeps(robot):
    return synthetic.plan_sweeps(default_plan(robot))


@pytest.fixture(scope="module")
def synthetic_fit(robot, truth, sweeps):
    rec = synthetic.recording(robot, truth, sweeps, noise=0.05, seed=1)
    return rec, joint_fit.fit(rec)


def test_synthetic_fit_predicts_gravity_current(robot, truth, synthetic_fit):
    rec, fitted = synthetic_fit
    poses = synthetic.random_poses(robot, 2000)
    err = synthetic.relative_gravity_error(robot, truth, fitted, poses)
    assert np.all(err[1:5] < 2e-3), err
    np.testing.assert_allclose(fitted.friction, truth.friction, rtol=0.01)
    assert fitted.method == "jax" and fitted.diagnostics["iterations"] < 50
    np.testing.assert_allclose(fitted.diagnostics["current_noise"], 0.05, rtol=0.03)


def test_one_mounting_reports_its_ratios_as_confounded_and_names_the_cure(
    robot, truth, synthetic_fit
):
    """Upright, a ratio trades with the radial COM offsets of the links it carries: the fit
    says so (and the CLI warning names the cure), its standard errors cover the truth, and an
    unexcited joint of a declared actuator type takes its type's ratio."""
    _, fitted = synthetic_fit
    d = fitted.diagnostics
    assert d["ratio_source"][0] == "mean of type M"
    types = fit_model(robot).types
    mates = [k for k in range(1, 6) if types[k] == types[0]]
    assert mates and fitted.ratio[0] == pytest.approx(
        np.exp(np.log(fitted.ratio[mates]).mean()), rel=0.01
    )
    confounded = [c["joint"] for c in d["confounded"]]
    assert len(confounded) >= 3 and not any(d["ratio_identified"][1:5])
    z = (fitted.ratio - truth.ratio) / fitted.std["ratio"]
    assert np.all(np.abs(z[1:5]) < 3), z
    lines = joint_fit.warnings_of(fitted)
    assert len(lines) == len(confounded) and all("known payload" in line for line in lines)


def test_an_unexcited_joint_without_declared_types_is_not_locked(tmp_path):
    """A model that declares no actuator types: joint 0 of an upright arm has no gravity
    signal; its ratio is the data's ratio scale with a wide standard error, never the nominal
    1 A/(N m) pinned, and the others are fitted (r > 0)."""
    from odd_arms import serial_arm

    path = tmp_path / "arm.xml"
    path.write_text(serial_arm(3, n=4))
    arm = jaxcomp.load_robot(path)
    rng = np.random.default_rng(0)
    moved = arm.tree.moves[arm_joint_indices(arm)].any(axis=0)
    truth = RobotParams(
        arm.name,
        [0.4, 1.7, 0.8, 1.3],
        [0.3, 0.5, 0.2, 0.4],
        {n: rng.normal(0, 0.003, 3) for n, m in zip(arm.link_names, moved, strict=True) if m},
    )
    hold = np.array([0.0, 0.4, -0.8, 0.5])
    sweeps = [(j, hold, -1.5, 1.5, 0.5) for j in range(4)]
    rec = synthetic.recording(arm, truth, sweeps, noise=0.02, seed=3)
    fitted = joint_fit.fit(rec)
    d = fitted.diagnostics
    assert d["ratio_source"][0] == "prior: no gravity signal" and d["excitation"][0] is None
    excited = fitted.ratio[1:]
    assert np.all(excited > 0)
    assert fitted.ratio[0] == pytest.approx(np.median(excited), rel=0.15)  # the data's scale
    assert fitted.std["ratio"][0] > 0.5 * fitted.ratio[0]
    z = (fitted.ratio - truth.ratio) / fitted.std["ratio"]
    assert np.all(np.abs(z[1:]) < 3), (z, d["ratio_source"])
    ident = np.asarray(d["ratio_identified"], bool)
    assert np.all(np.abs(fitted.ratio / truth.ratio - 1)[ident] < 0.01)
    assert any("no gravity signal" in line for line in joint_fit.warnings_of(fitted))


def test_currents_in_milliamperes_give_the_same_fit_scaled(robot, truth, sweeps, monkeypatch):
    """Every prior is scaled to the data: a recording in mA fits to the same COM offsets and
    the same identifiability, with ratio, friction and standard errors x1000 (sweeps and the
    transfers between them). (The Gen3 Lite
    states its current limit, so the fit refuses mA outright; the maths is checked with that
    check switched off, as on a model that states no current scale.)"""
    move = np.deg2rad(55.0)  # rad/s, the transfers
    in_ma = synthetic.recording(robot, truth, sweeps, seed=11, scale=1e-3, transfers=move)
    with pytest.raises(
        InputError, match=r"exceeds 2 times the current limit: joint_0 7\d\d\.\d A .*in mA"
    ):
        joint_fit.fit(in_ma)
    amps = joint_fit.fit(synthetic.recording(robot, truth, sweeps, seed=11, transfers=move))
    monkeypatch.setattr(joint_fit, "check_recordings", lambda recs: None)
    milli = joint_fit.fit(in_ma)
    np.testing.assert_allclose(milli.ratio, 1e3 * amps.ratio, rtol=1e-6)
    np.testing.assert_allclose(milli.friction, 1e3 * amps.friction, rtol=1e-6)
    np.testing.assert_allclose(milli.std["ratio"], 1e3 * amps.std["ratio"], rtol=1e-5)
    for link, off in amps.com_offset.items():
        np.testing.assert_allclose(milli.com_offset[link], off, rtol=1e-5, atol=1e-10)
    assert milli.diagnostics["ratio_source"] == amps.diagnostics["ratio_source"]
    assert milli.diagnostics["unidentified"] == amps.diagnostics["unidentified"]


def test_held_joints_that_give_way_under_load_do_not_bias_the_fit(robot, truth, sweeps):
    """Held joints deflect with their gravity torque by up to ~0.6 deg, in step with the swept
    angle: the fit takes each sample's held pose (to first order) and stays as exact as with
    rigid joints."""
    rec = synthetic.recording(robot, truth, sweeps, noise=0.05, seed=12, compliance=2e-3)
    rows = rec.joint == 1
    give = [np.ptp(rec.q[rows, k]) for k in range(6) if k != 1]
    assert max(give) > np.deg2rad(0.3), give  # the held joints do give way
    fitted = joint_fit.fit(rec)
    poses = synthetic.random_poses(robot, 2000)
    err = synthetic.relative_gravity_error(robot, truth, fitted, poses)
    assert np.all(err[1:5] < 2e-3), err
    z = (fitted.ratio - truth.ratio) / fitted.std["ratio"]
    assert np.all(np.abs(z[1:5]) < 3), z


def test_a_current_that_lags_the_pose_is_paired_with_the_pose_it_flowed_at(robot, truth, sweeps):
    """The simulators report with each pose the current their servo drove through the 1 ms
    before it (a servo bus may add more: 3 ms here). Fitted as if taken at the reported pose,
    the gravity torque's slope times the speed times the lag reads as friction (biased by
    several standard errors at low noise); with the recording's ``current_lag`` the fit pairs
    each current with its pose."""
    fast = [(j, hold, lo, hi, 3 * v) for j, hold, lo, hi, v in sweeps]  # 120 deg/s: short
    rec = synthetic.recording(robot, truth, fast, noise=0.005, seed=13, lag=3e-3)
    assert rec.current_lag == 3e-3
    paired = joint_fit.fit(rec)
    unpaired = joint_fit.fit(dataclasses.replace(rec, current_lag=0.0))
    z = lambda p: (p.friction - truth.friction) / p.std["friction"]  # noqa: E731
    assert np.abs(z(unpaired)).max() > 5, z(unpaired)
    assert np.abs(z(paired)).max() < 3.5, z(paired)


def test_standard_errors_and_identifiability_are_reported(synthetic_fit, tmp_path):
    _, fitted = synthetic_fit
    std = fitted.std
    assert np.all(np.asarray(std["friction"]) > 0) and np.all(np.asarray(std["ratio"]) > 0)
    sv = np.asarray(fitted.diagnostics["singular_values"])
    assert sv[0] > 1e3 * sv[-1]  # some directions rest on the prior only, and it says which
    assert any("SHOULDER" in name for name in fitted.diagnostics["unidentified"])
    assert not any(name.startswith("friction") for name in fitted.diagnostics["unidentified"])
    loaded = RobotParams.load(fitted.save(tmp_path / "p.json"))
    np.testing.assert_allclose(loaded.ratio, fitted.ratio)


def test_phase_shift_matches_the_truth_phase(robot, truth, synthetic_fit):
    rec, fitted = synthetic_fit
    model = fit_model(robot)
    st, coef, m = joint_fit.prepare(model, rec)
    com = np.concatenate([truth.com_offset[link] for link in model.links])
    phase, _ = joint_fit.phase_shift(model, coef, m.joint, com, np.zeros((model.K, model.K)))
    assert np.all(np.abs(fitted.phase_shift - phase)[1:5] < 3 * fitted.std["phase_shift"][1:5])
    assert np.abs(phase[1:5]).max() > np.deg2rad(0.2)  # the truth has a phase shift to find


def test_fit_models_are_kept_on_the_robot_and_equal_by_content(robot, tmp_path):
    """Equal models share compiled fits; an edited model of the same name does not."""
    assert fit_model(robot) is fit_model(robot)
    assert fit_model(robot) == fit_model("gen3_lite")
    text = robot.source.read_text()
    edited = tmp_path / "gen3_lite.xml"
    edited.write_text(text.replace('mass="', 'mass="1', 1))
    assert edited.read_text() != text
    other = jaxcomp.load_robot(edited)
    assert other.name == robot.name
    assert fit_model(other) != fit_model(robot)


def test_two_mountings_and_a_payload_identify_every_ratio(robot, truth, sweeps):
    upright = synthetic.recording(robot, truth, sweeps, seed=2)
    tilted = synthetic.recording(
        robot,
        truth,
        sweeps,
        seed=3,
        gravity=(0.0, -9.81 * np.sin(0.6), -9.81 * np.cos(0.6)),
        payload_mass=1.0,
        payload_com=(0.05, 0.0, 0.04),
    )
    fitted = joint_fit.fit([upright, tilted])
    assert fitted.diagnostics["ratio_source"][1:] == ["fit"] * 5
    np.testing.assert_allclose(fitted.ratio[1:], truth.ratio[1:], rtol=0.002)
    # joint 0, now loaded, trades only with its own link's COM (the prior's +-4 mm)
    assert abs(fitted.ratio[0] - truth.ratio[0]) < 3 * fitted.std["ratio"][0] < 0.02
    np.testing.assert_allclose(fitted.friction, truth.friction, rtol=0.01)


def test_a_known_payload_cures_the_confounded_ratios(robot, truth, sweeps):
    """One mounting: with a second recording carrying a known payload every excited joint's
    ratio is identified, within 1 % and 3 standard errors (the Cramer-Rao bound)."""
    plain = synthetic.recording(robot, truth, sweeps, seed=21)
    loaded = synthetic.recording(
        robot, truth, sweeps, seed=22, payload_mass=0.5, payload_com=(0.0, 0.0, 0.05)
    )
    alone = joint_fit.fit(plain)
    both = joint_fit.fit([plain, loaded])
    assert not any(alone.diagnostics["ratio_identified"][1:5])
    assert all(both.diagnostics["ratio_identified"][1:5]), both.diagnostics["ratio_source"]
    assert both.diagnostics["confounded"] == []
    err = both.ratio / truth.ratio - 1
    assert np.all(np.abs(err[1:5]) < 0.01), err
    z = (both.ratio - truth.ratio) / both.std["ratio"]
    assert np.all(np.abs(z[1:5]) < 3), z
    assert np.all(both.std["ratio"][1:5] < 0.3 * alone.std["ratio"][1:5])


def test_two_speeds_separate_viscous_from_coulomb_friction(robot, truth, sweeps):
    """The default plan sweeps joints 1-4 once at half speed: viscous friction is told apart."""
    viscous = np.full(6, 0.02)  # N m s/rad
    fitted = joint_fit.fit(synthetic.recording(robot, truth, sweeps, seed=4, viscous=viscous))
    np.testing.assert_allclose(fitted.friction[1:5], truth.friction[1:5], rtol=0.01)
    est = np.asarray(fitted.diagnostics["viscous"])[1:5]  # A s/rad = ratio x N m s/rad
    std = np.asarray(fitted.diagnostics["viscous_std"])[1:5]
    assert np.all(np.abs(est - truth.ratio[1:5] * viscous[1:5]) < 3 * std), (est, std)
    assert np.all(std < 0.3 * truth.ratio[1:5] * viscous[1:5])
    # at one speed it cannot be told apart: it is held at 0 and shows as friction
    plan = default_plan(robot)
    fast = synthetic.plan_sweeps(plan, lambda k, s: plan.sweeps[0].speed / s.speed)
    one_speed = joint_fit.fit(synthetic.recording(robot, truth, fast, seed=4, viscous=viscous))
    assert np.abs(one_speed.diagnostics["viscous"]).max() < 1e-9
    assert np.all(one_speed.friction > truth.friction)


def test_fit_each_equals_single_fits(robot, truth, sweeps):
    """Batches of 2 (the last one padded), one holding recordings of different layouts: the
    second sweeps joint 4 twice as fast, so the two are packed to the larger sizes. A
    recording that never sweeps a joint is refused, naming it."""
    faster = [(j, h, lo, hi, v * (2 if j == 4 else 1)) for j, h, lo, hi, v in sweeps]
    recs = [
        synthetic.recording(robot, truth, faster if s == 8 else sweeps, seed=s) for s in (7, 8, 9)
    ]
    assert recs[1].n_samples < recs[0].n_samples
    batch = batched_fit.fit_each(recs, batch=2)
    for rec, got in zip(recs, batch, strict=True):
        want = joint_fit.fit(rec)
        np.testing.assert_allclose(got.ratio, want.ratio, rtol=1e-6)
        np.testing.assert_allclose(got.friction, want.friction, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(got.phase_shift, want.phase_shift, rtol=1e-5, atol=1e-9)
    cut = int(np.flatnonzero(recs[1].joint == 4)[0])
    fields = ("t", "q", "dq", "current", "joint", "direction")
    recs[1] = Recording(*(getattr(recs[1], f)[:cut] for f in fields), recs[1].model)
    with pytest.raises(InputError, match="recording 1: joint_4 is never swept"):
        batched_fit.fit_each(recs, batch=2)


def test_a_fit_that_does_not_converge_says_so(synthetic_fit):
    rec, _ = synthetic_fit
    with pytest.raises(joint_fit.FitError, match="did not converge"):
        joint_fit.fit(rec, max_iter=1)


def test_simulator_recording_accuracy_against_truth_and_baseline(robot, sim_calibration):
    """The issue's accuracy must-show on a recording the simulator made."""
    clean, truth = sim_calibration
    rec = synthetic.with_noise(clean, 0.05, seed=0)
    fitted = joint_fit.fit(rec)
    baseline = fit_baseline(rec)
    poses = synthetic.random_poses(robot, 3000, seed=2)
    err = synthetic.relative_gravity_error(robot, truth.params, fitted, poses)[1:5]
    err_base = synthetic.relative_gravity_error(robot, truth.params, baseline, poses)[1:5]
    assert np.all(err <= 0.01), err
    assert np.all(err <= 0.5 * err_base), (err, err_base)
    np.testing.assert_allclose(fitted.friction, truth.friction, rtol=0.03)


@pytest.mark.slow
def test_spread_over_repetitions_matches_reported_standard_errors(sim_calibration):
    """Noise-only repetitions: the spread of the estimates is within 1.2x the reported std."""
    clean, _ = sim_calibration
    reps = 120
    fits = batched_fit.fit_each(
        synthetic.with_noise(clean, 0.05, seed=100 + k) for k in range(reps)
    )
    for field in ("ratio", "friction", "phase_shift"):
        values = np.array([getattr(f, field) for f in fits])
        reported = np.mean([f.std[field] for f in fits], axis=0)
        joints = slice(1, 5) if field != "friction" else slice(0, 6)
        ratio = values.std(axis=0, ddof=1)[joints] / reported[joints]
        assert np.all(ratio < 1.2), (field, ratio)
        if field != "ratio":  # ratios lean on the prior along the mass scale: spread smaller
            assert np.all(ratio > 0.8), (field, ratio)


def test_cli_fit_never_writes_over_its_inputs(synthetic_fit, tmp_path):
    """An --out or --plot that names an input (or each other) is refused; nothing changes."""
    rec, _ = synthetic_fit
    path = rec.save(tmp_path / "rec.npz")
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    runner = CliRunner()
    for args, message in [
        (["--out", str(path)], "--out"),
        (["--out", str(tmp_path / "p.json"), "--plot", str(tmp_path / "." / "rec.npz")], "--plot"),
        (["--each", "--out", str(path)], "--out"),
    ]:
        result = runner.invoke(cli, ["fit", str(path), *args])
        assert result.exit_code != 0
        assert isinstance(result.exception, InputError), result.output
        assert message in str(result.exception) and "also an input" in str(result.exception)
    same = tmp_path / "same.png"
    result = runner.invoke(cli, ["fit", str(path), "--out", str(same), "--plot", str(same)])
    assert isinstance(result.exception, InputError) and "also given as --out" in str(
        result.exception
    )
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.npz"]


def test_cli_fit_writes_params_and_refuses_bad_input(synthetic_fit, tmp_path):
    rec, _ = synthetic_fit
    path = rec.save(tmp_path / "rec.npz")
    runner = CliRunner()
    out = tmp_path / "params.json"
    result = runner.invoke(cli, ["fit", str(path), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["method"] == "jax"
    each = tmp_path / "each.json"
    result = runner.invoke(cli, ["fit", str(path), str(path), "--each", "--out", str(each)])
    assert result.exit_code == 0, result.output
    assert len(json.loads(each.read_text())) == 2
    bad = tmp_path / "bad.npz"
    data = rec.to_arrays()
    data["q"] = np.rad2deg(data["q"])
    np.savez(bad, **data)
    never = tmp_path / "never.json"
    result = runner.invoke(cli, ["fit", str(bad), "--out", str(never)])
    assert result.exit_code != 0 and "degrees" in str(result.exception)
    assert not never.exists()


def test_a_prefit_the_com_offsets_dominate_neither_slows_nor_drags_the_fit():
    """The Gen3 Lite under the any-arm protocol (``experiments/fit_any_arm.py``, seed 1: its
    last wrist's nominal torque is small against what the COM offsets add, so its prefit
    ratio is ~80x off): the ratio scale is the median of the excited joints' prefits and that
    joint starts from the prior's centre, so the fit converges in a few steps (30 when the
    scale was their geometric mean and every excited joint started from its prefit), with
    every ratio within 3 standard errors."""
    from fit_any_arm import draw_truth, user_plan

    robot = jaxcomp.load_robot("gen3_lite")
    truth, plan = draw_truth(robot, 1), user_plan(robot, 1)
    rec = synthetic.recording(
        robot, truth.params, synthetic.plan_sweeps(plan), noise=0.03, seed=1,
        transfers=plan.move_speed,
    )  # fmt: skip
    model = fit_model(robot)
    sol = solve(model.key, joint_fit.prepare(model, rec)[0])
    assert bool(sol.converged) and int(sol.iterations) <= 10, int(sol.iterations)
    std = np.sqrt(np.diag(np.asarray(sol.cov))[: model.n])
    z = (np.asarray(sol.ratio) - truth.ratio) / std
    assert np.all(np.abs(z) < 3), z
