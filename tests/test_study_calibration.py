"""`jaxcomp study calibration`: truths, plan signals, batched moments and fits, the report.

MJX compiles for ~20-30 s on a 2-core CPU, once per simulator: each CLI run here loads its
robot, which keeps its own simulator (``studies.setup.simulator``); the other runs share the
module's robot. The unmarked runs use a tiny plan (joints 1-4, +-25 deg at 60 deg/s, 14 s) in 2
worlds recorded at 100 Hz, or two tiny random plans; ``--plan short`` (26 s, every joint) in 4
worlds is slow.
"""

import functools
import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import jaxcomp
from jaxcomp.cli import cli
from jaxcomp.errors import InputError
from jaxcomp.hardware import PAPER_FRICTION, PAPER_RATIO
from jaxcomp.hardware.mjx import Move, reference_trajectory
from jaxcomp.identify import batched_fit, joint_fit, named_plans
from jaxcomp.identify.evaluate import (
    error_statistics,
    gravity_current,
    gravity_current_error,
    gravity_current_error_batch,
    random_poses,
)
from jaxcomp.identify.fit_model import fit_model
from jaxcomp.identify.moments import world_moments
from jaxcomp.identify.named_plans import named_plan, short_plan
from jaxcomp.identify.plan import CalibrationPlan, Sweep
from jaxcomp.identify.random_plans import plan_seed
from jaxcomp.identify.sweep_reduction import sweep_moments
from jaxcomp.identify.transfers import transfer_bins
from jaxcomp.recording import load_recording
from jaxcomp.robot_params import RobotParams, json_ready
from jaxcomp.studies import calibration as sc
from jaxcomp.studies import calibration_outputs
from jaxcomp.studies.calibration_estimates import Estimates, jax_truth_vector
from jaxcomp.studies.calibration_outputs import (
    FIGURES,
    STUDY_FILE,
    WORLDS_FILE,
    StudyOutputs,
    study_into,
    summary,
    write_outputs,
)
from jaxcomp.studies.calibration_report import study_report
from jaxcomp.studies.calibration_settings import (
    CalibrationSettings,
    baseline_worlds,
    sampled_worlds,
    world_groups,
)
from jaxcomp.studies.calibration_statistics import worst_coverage
from jaxcomp.studies.plan_recording import signal_plans, simulate
from jaxcomp.studies.plan_signal import plan_segments, plan_signal, start_pose
from jaxcomp.studies.processes import CLUSTER_VARIABLES
from jaxcomp.studies.setup import simulator
from jaxcomp.studies.study_chunks import ChunkStore, study_chunks
from jaxcomp.studies.truth_draw import TruthSpread, draw_truth

ROOT = Path(__file__).resolve().parents[1]
SEED = 3
TIMING = ("timing_s", "throughput")  # the only keys a rerun may change
#: The tests that read the tiny study (``study``, ``whole``) run on one xdist worker, which
#: computes it once (``--dist loadgroup``).
TINY_STUDY = pytest.mark.xdist_group("tiny-study")


@pytest.fixture(scope="session")  # session: never torn down between a worker's tests
def robot():
    return jaxcomp.load_robot("gen3_lite")


@pytest.fixture(scope="session")
def tiny_plan(robot, tmp_path_factory):
    """Joints 1-4 of the short plan over +-25 deg (joint 1 from -20 deg): a 14 s plan file."""
    short = short_plan(robot, speed=math.radians(60), move_speed=math.radians(90))
    sweeps = [
        Sweep(s.joint, s.hold, max(s.lower, math.radians(-25)), math.radians(25), s.speed)
        for s in short.sweeps
        if s.joint in (1, 2, 3, 4)
    ]
    plan = CalibrationPlan(tuple(sweeps), short.move_speed, 0.2, short.ramp)
    return str(plan.save(tmp_path_factory.mktemp("plan") / "tiny.json"))


def _run(out: Path, plan: str, seed: int = SEED, *extra: str):
    args = ["study", "calibration", "--worlds", "2", "--seed", str(seed), "--plan", plan]
    args += ["--baseline-sample", "2", "--poses", "200", "--no-progress", "--out", str(out)]
    result = CliRunner().invoke(cli, [*args, *extra])
    assert result.exit_code == 0, result.output + repr(result.exception)
    report = json.loads((out / "study.json").read_text())
    with np.load(out / "worlds.npz") as data:
        arrays = {k: data[k] for k in data.files}
    return report, arrays, result.output


@pytest.fixture(scope="session")
def study(robot, tiny_plan, tmp_path_factory):
    """The tiny study from the CLI (on the module's robot: ``load_robot`` returns the robot in
    use, whose simulator the other runs here share)."""
    out = tmp_path_factory.mktemp("study") / "a"
    return (*_run(out, tiny_plan), out)


# ----------------------------------------------------------------------------- no MJX
def test_worst_coverage_names_the_parameter_whose_std_are_too_small():
    rng = np.random.default_rng(3)
    w = 400
    z = rng.standard_normal((w, 3)) * [1.0, 1.6, 9.0]  # error / std per parameter
    std = np.full((w, 3), 0.01)
    identified = np.ones((w, 3), bool)
    identified[50:, 2] = False  # the worst one is determined in 50 fits only: not counted
    est = Estimates(
        ["a", "b", "c"],
        ["A"] * 3,
        1 + z * std,
        np.ones((w, 3)),
        std,
        identified,
        np.ones(w, bool),
        np.zeros((w, 1)),
        np.zeros(w),
        np.ones((w, 1), bool),
    )
    worst = worst_coverage(est)
    inside = np.mean(np.abs(z[:, 1]) < 1.96)
    assert worst == {"parameter": "b", "coverage_95": pytest.approx(inside), "count": w}
    assert 0.7 < inside < 0.85  # std 1.6x too small
    assert worst_coverage(est, min_fits=w + 1) is None
    assert worst_coverage(est, min_fits=50)["parameter"] == "c"


def test_draw_truth_is_per_world_and_within_its_spread(robot):
    spread = TruthSpread()
    big, small = draw_truth(robot, 64, 7, spread), draw_truth(robot, 3, 7, spread)
    for f in ("ratio", "friction", "com_offset", "current_noise", "viscous"):
        np.testing.assert_array_equal(getattr(small, f), getattr(big, f)[:3])  # world w: same
    ratio0 = RobotParams.nominal(robot).ratio
    off = np.abs(big.ratio / ratio0 - 1)
    assert off.min() > 0.2 * 0.97 - 0.03 and off.max() < 0.3 * 1.03 + 0.03
    # one factor per actuator type (M L M S S S) within the 3 % type spread
    r = big.ratio / ratio0
    assert np.abs(r[:, 0] / r[:, 2] - 1).max() < 0.07 and np.abs(r[:, 3] / r[:, 5] - 1).max() < 0.07
    torque = big.friction / big.ratio
    paper = np.array(PAPER_FRICTION) / np.array(PAPER_RATIO)
    t_off = np.abs(torque / paper - 1)
    assert t_off.min() >= 0.2 - 1e-12 and t_off.max() <= 0.3 + 1e-12
    assert np.all(torque[:, 1] < paper[1])  # + would leave joint 1 under 65 % of its effort
    assert (torque[:, 2] > paper[2]).any() and (torque[:, 2] < paper[2]).any()
    assert np.abs(big.com_offset).max() <= 0.004 and np.all(big.com_offset[:, 0] == 0)  # base
    assert np.all(big.current_noise == 0.05) and np.all(big.viscous == 0)
    part = draw_truth(robot, 20, 7, spread, first=30)  # drawn without worlds 0-29
    for f in ("ratio", "friction", "com_offset", "current_noise", "viscous"):
        np.testing.assert_array_equal(getattr(part, f), getattr(big, f)[30:50])
    other = draw_truth(robot, 3, 8, spread)
    assert not np.allclose(other.ratio, small.ratio)
    with pytest.raises(InputError, match="model-error"):
        TruthSpread(model_error=(0.4, 0.2))


def test_plan_signal_is_what_the_recorder_commands(robot, tiny_plan):
    plan = named_plan(robot, tiny_plan)
    start = start_pose(robot)
    sig = plan_signal(plan, start)
    moves = [Move(t, v, a, s) for _, _, t, v, a, s in plan.moves()]
    np.testing.assert_array_equal(sig.q_ref, reference_trajectory(moves, start))
    assert len(sig.q_ref) == plan.samples(start)
    swept = sig.joint >= 0
    assert set(np.unique(sig.direction[swept])) == {-1, 1} and np.all(sig.direction[~swept] == 0)
    for i, s in enumerate(plan.sweeps):  # each sweep: its joint moves lower -> upper -> lower
        rows = (sig.sweep == i) & swept
        assert set(np.unique(sig.joint[rows])) == {s.joint}
        q = sig.q_ref[rows, s.joint]
        assert q.min() == pytest.approx(s.lower) and q.max() == pytest.approx(s.upper)


def test_batched_gravity_error_and_statistics(robot):
    """The batched gravity-current error is the per-world one; error statistics are right."""
    poses = random_poses(robot, 50, seed=1)
    truth = draw_truth(robot, 2, 1, TruthSpread())
    fit_ratio, fit_com = truth.ratio * 1.01, truth.com_offset + 0.001
    got = gravity_current_error_batch(
        robot, truth.ratio, truth.com_offset, fit_ratio, fit_com, poses
    )
    for w in range(2):
        t, f = (
            RobotParams(robot.name, r, np.zeros(6), dict(zip(robot.link_names, c, strict=True)))
            for r, c in ((truth.ratio[w], truth.com_offset[w]), (fit_ratio[w], fit_com[w]))
        )
        np.testing.assert_allclose(got[w], gravity_current_error(robot, t, f, poses), rtol=1e-9)
    rng = np.random.default_rng(0)
    err = rng.normal(0.0, 2.0, (4000, 2)) + [0.5, 0.0]
    st = error_statistics(err, np.full_like(err, 2.0))
    np.testing.assert_allclose(st["bias"], [0.5, 0.0], atol=0.1)
    np.testing.assert_allclose(st["spread_over_std"], 1.0, atol=0.05)
    assert abs(st["coverage"][1] - 0.95) < 0.015 and st["coverage"][0] < st["coverage"][1]
    st = error_statistics(err, np.full_like(err, 1.0))  # std half the truth: under-covers
    assert st["coverage"][1] < 0.7 and st["spread_over_std"][1] > 1.9


def test_pooled_gravity_error_is_one_number_over_poses_and_joints(robot):
    """The control study's gravity-current error pools the poses and joints of a world: RMS of
    the error over both, relative to the RMS true gravity current over both."""
    poses = random_poses(robot, 20, seed=2)
    truth = draw_truth(robot, 2, 2, TruthSpread())
    fit_ratio, fit_com = truth.ratio * 0.98, truth.com_offset - 0.002
    got = gravity_current_error_batch(
        robot, truth.ratio, truth.com_offset, fit_ratio, fit_com, poses, pooled=True
    )
    assert got.shape == (2,)
    for w in range(2):
        t, f = (
            RobotParams(robot.name, r, np.zeros(6), dict(zip(robot.link_names, c, strict=True)))
            for r, c in ((truth.ratio[w], truth.com_offset[w]), (fit_ratio[w], fit_com[w]))
        )
        true = gravity_current(robot, t, poses)
        err = gravity_current(robot, f, poses) - true
        want = np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(true**2))
        np.testing.assert_allclose(got[w], want, rtol=1e-9)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--worlds", "0"], "--worlds must be an integer >= 1"),
        (["--worlds", "2", "--every", "0"], "--every must be an integer >= 1"),
        (["--worlds", "2", "--baseline-sample", "-1"], "--baseline-sample must be"),
        (["--worlds", "2", "--model-error", "0.5", "0.2"], "--model-error"),
        (["--worlds", "2", "--noise", "nan"], "--noise must be"),
        (["--worlds", "2", "--plan", "nope"], "--plan must be one of"),
        (["--worlds", "2", "--plan", "random:0"], "--plan random:K needs an integer K >= 1"),
        (["--worlds", "2", "--plan", "random:3"], "needs at least as many --worlds (2)"),
        (["--worlds", "2", "--chunk-worlds", "0"], "--chunk-worlds must be an integer >= 1"),
        (["--worlds", "2", "--keep-samples", "-1"], "--keep-samples must be an integer >= 0"),
        (["--worlds", "2", "--process-id", "1"], "--process-id: only with --distributed"),
    ],
)
def test_bad_input_is_refused_before_anything_runs(args, message, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["study", "calibration", "--out", str(out), *args])
    assert isinstance(result.exception, InputError), result.output
    assert message in str(result.exception)
    assert not out.exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--distributed"], "--distributed needs --coordinator HOST:PORT"),
        (["--distributed", "--coordinator", "h:1", "--num-processes", "2"], "needs --coordinator"),
        (["--distributed", "--coordinator", "h", "--num-processes", "2", "--process-id", "0"],
         "--coordinator must be HOST:PORT"),
        (["--distributed", "--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"],
         "--process-id must be in 0..1"),
    ],
)  # fmt: skip
def test_distributed_without_its_processes_is_refused(args, message, tmp_path, monkeypatch):
    for k in ("JAX_COORDINATOR_ADDRESS", *CLUSTER_VARIABLES):
        monkeypatch.delenv(k, raising=False)
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["study", "calibration", "--worlds", "2", "--out", out, *args])
    assert isinstance(result.exception, InputError), result.output
    assert message in str(result.exception)
    assert not out.exists()


def test_unwritable_out_dir_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for out in (blocker, blocker / "sub"):
        result = CliRunner().invoke(cli, ["study", "calibration", "--worlds", "1", "--out", out])
        assert isinstance(result.exception, InputError), result.output
        assert "--out" in str(result.exception)


# ----------------------------------------------------------------------------- one study
@TINY_STUDY
def test_report_files_are_complete_and_valid(study):
    report, arrays, output, out = study
    assert report["fit_com_prior"] == pytest.approx(0.004 / np.sqrt(3))  # the truths' spread
    assert sorted(p.name for p in out.iterdir()) == sorted([*FIGURES, "study.json", "worlds.npz"])
    for name in FIGURES:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (out / name).stat().st_size > 20_000
    json.loads((out / "study.json").read_text(), parse_constant=pytest.fail)  # no NaN tokens
    assert report["format"] == sc.FORMAT and report["worlds"] == 2 and report["seed"] == SEED
    assert report["backend"] == "cpu" and report["devices"] == ["cpu:0"]
    assert report["plan"]["sweeps"] == 4 and report["record_rate_hz"] == 100.0
    assert report["jax"]["converged"] == 2 and report["faulted_worlds"] == 0
    assert report["scipy"]["worlds"] == 2 and report["scipy"]["failed"] == []
    t = report["timing_s"]
    assert t["simulate"] >= t["simulate_stepping"] > 0 and t["total"] > t["fit_jax"] > 0
    assert report["throughput"]["world_steps_per_s"] > 0
    names = list(arrays["parameter_names"])
    assert arrays["truth"].shape == arrays["jax_estimate"].shape == (2, len(names))
    assert arrays["scipy_estimate"].shape == (2, 12)
    assert set(report["jax"]["parameters"]) == set(names)
    assert "coverage of +-1.96 std" in output and "ratio jax" in output


@TINY_STUDY
def test_faulted_worlds_are_counted_per_plan_and_said(study):
    report, arrays, _, _ = study
    assert report["faulted_by_plan"] == [0] and "faulted" not in summary(report)
    changed = dict(arrays) | {"fault_step": np.array([-1, 7])}  # world 1 stopped at step 7
    again = study_report(changed, dict(report) | {"world_steps": 1.0})
    assert again["faulted_worlds"] == 1 and again["faulted_by_plan"] == [1]
    assert "1 of 2 worlds faulted before their plan ended" in summary(again)


@TINY_STUDY
def test_jax_fit_finds_the_true_robots(study, robot):
    """Ratios are drawn 20-30 % off nominal: the fit of 14 s of sweeps at 100 Hz finds them,
    the frictions and the gravity current within a few %, and the noise level."""
    report, arrays, _, _ = study
    names = [str(s) for s in arrays["parameter_names"]]
    est, truth, ident = arrays["jax_estimate"], arrays["truth"], arrays["jax_identified"]
    swept = [1, 2, 3, 4]
    ratio = est[:, swept] / truth[:, swept] - 1
    assert np.abs(ratio).max() < 0.08, ratio  # nominal would be >= 20 % off
    friction = est[:, [6 + j for j in swept]] - truth[:, [6 + j for j in swept]]
    assert np.abs(friction).max() < 0.03, friction  # A, of 0.3-1.5 A
    g = arrays["jax_gravity_current_error"][:, swept]
    assert np.all(g < 0.1), g  # joint 4, the least loaded: 7.9 % in world 0 of this draw
    poses = random_poses(robot, 200, seed=SEED)  # the study's poses
    truth_com = np.zeros((2, 7, 3))
    model = fit_model(robot)
    truth_com[:, model.link_ids] = truth[:, 18 : 18 + model.K].reshape(2, -1, 3)
    nominal = gravity_current_error_batch(
        robot,
        truth[:, :6],
        truth_com,
        np.tile(RobotParams.nominal(robot).ratio, (2, 1)),
        np.zeros((2, 7, 3)),
        poses,
    )[:, swept]
    assert np.all(nominal > 0.15) and np.all(g < 0.3 * nominal), (g, nominal)
    # per joint (unswept joints have none), from ~180 samples each: +-20 %; pooled +-10 %
    noise = arrays["jax_noise_estimate"][:, swept]
    np.testing.assert_allclose(noise, 0.05, rtol=0.2)
    np.testing.assert_allclose(np.sqrt(np.mean(noise**2, axis=1)), 0.05, rtol=0.1)
    # joints 0 and 5 are not swept: their ratios are tied; joint 0 never moves (its friction
    # is not determined), joint 5 moves in the transfers between sweeps, which determine its
    # friction; upright, the swept joints' ratios rest partly on the COM prior (confounded)
    assert not ident[:, [0, 5, 6]].any() and ident[:, [7, 8, 11]].all()
    assert np.abs(est[:, 11] - truth[:, 11]).max() < 0.03, (est[:, 11], truth[:, 11])
    assert not ident[:, :6].any()
    cov = report["coverage"]["jax"]["identified"]
    assert cov["count"] == ident.sum() >= 8 and cov["coverage_95"] >= 0.75
    table = report["jax"]["parameters"]
    np.testing.assert_allclose(
        table["ratio[1]"]["rmse"], np.sqrt(np.mean((est[:, 1] - truth[:, 1]) ** 2)), rtol=1e-12
    )
    assert names[-6:] == [f"phase_shift[{j}]" for j in range(6)]


@TINY_STUDY
def test_same_seed_reproduces_the_numbers(study, tiny_plan, tmp_path):
    first, arrays, _, _ = study
    again, arrays2, _ = _run(tmp_path / "b", tiny_plan)
    assert {k: v for k, v in again.items() if k not in TIMING} == {
        k: v for k, v in first.items() if k not in TIMING
    }
    for k, v in arrays.items():
        np.testing.assert_array_equal(arrays2[k], v, err_msg=k)
    other, arrays3, _ = _run(tmp_path / "c", tiny_plan, SEED + 1, "--baseline-sample", "0")
    assert not np.allclose(arrays3["truth"], arrays["truth"])
    assert other["jax"]["parameters"] != first["jax"]["parameters"]
    assert other["scipy"]["worlds"] == 0 and other["scipy"]["parameters"] == {}
    assert arrays3["scipy_estimate"].shape == (0, 12)


def test_streamed_moments_fit_as_the_recordings_moments(robot, tiny_plan):
    """The study's path (each sweep's moments and each transfer's bins summed on the device
    while the world runs, their steady samples chosen from the plan's commanded motion;
    vmapped fit) against the kept recording reduced on the host (``sweep_moments``,
    ``transfer_bins``: steady samples from the measured speed) and ``joint_fit.fit``: nearly the
    same samples, and fits that agree within their standard errors."""
    truth = draw_truth(robot, 1, SEED, TruthSpread())
    signal = plan_signal(named_plan(robot, tiny_plan), start_pose(robot))
    sim = simulator(None, robot)  # compiled once for the module's runs of 1 world
    res = simulate(sim, truth, signal, seed=SEED, every=10, world_batch=1, keep=1)
    rec = res.recordings[0]
    single, streamed = sweep_moments(rec), world_moments(res.moments, 0)
    np.testing.assert_array_equal(streamed.joint, single.joint)
    assert np.all(np.abs(streamed.count - single.count) <= 0.05 * single.count), (
        streamed.count,
        single.count,
    )
    held = np.ones_like(single.hold, bool)
    held[np.arange(len(single.joint)), single.joint] = False
    np.testing.assert_allclose(streamed.hold[held], single.hold[held], atol=2e-4)
    # the transfers: every joint's counted samples and summed current nearly the same
    host, device = transfer_bins(rec), res.transfers
    n_host, n_dev = host.count.sum(0), device.count[0].sum(0)
    assert n_host.sum() > 0.3 * single.count.sum(), (n_host, single.count)
    assert np.all(np.abs(n_dev - n_host) <= 0.1 * n_host.max()), (n_dev, n_host)
    mean_host = host.current.sum(0) / np.maximum(n_host, 1)
    mean_dev = device.current[0].sum(0) / np.maximum(n_dev, 1)
    np.testing.assert_allclose(mean_dev, mean_host, atol=0.05)
    # and the servo's ringing in them: the measured acceleration (RMS over counted samples,
    # rad/s^2), from the sample before on the device as on the host
    rms = [np.sqrt((b.count * b.acceleration**2).sum(-2) / np.maximum(b.count.sum(-2), 1))
           for b in (host, device.__class__(*(a[0] for a in device)))]  # fmt: skip
    assert rms[0].max() > 1e-3, rms
    np.testing.assert_allclose(rms[1], rms[0], rtol=0.05, atol=1e-5)
    model = fit_model(robot)
    fit = batched_fit.fit_batch(model, res.moments, transfers=res.transfers, mesh=sim.mesh)
    want = joint_fit.fit(rec, complete=False)  # the tiny plan sweeps joints 1-4
    swept = np.isin(np.arange(6), rec.joint)
    assert swept.sum() == 4
    for got, std, ref in (
        (fit.solution.ratio[0], fit.std[0, :6], want.ratio),
        (fit.solution.friction[0], fit.std[0, 6:12], want.friction),
    ):
        assert np.all(np.abs(got - ref)[swept] <= std[swept]), (got - ref, std)
    sigma = fit.solution.sigma[0][swept]  # the truth's noise is 0.05 A
    np.testing.assert_allclose(sigma, want.diagnostics["current_noise"][swept], rtol=0.1)
    assert np.all((0.035 < sigma) & (sigma < 0.065)), sigma


@pytest.mark.parametrize("seed", range(5))
def test_the_scipy_sample_takes_the_first_worlds_of_every_plan(seed):
    """M worlds of N in K plan groups: each group gives its first worlds, its share of M as
    even as the groups are (one more for the first M % K), all of M when M <= N."""
    rng = np.random.default_rng(seed)
    worlds = int(rng.integers(1, 300))
    count = int(rng.integers(1, worlds + 1))
    groups = world_groups(worlds, count)
    for m in (0, 1, count, int(rng.integers(0, worlds + 1)), worlds, worlds + 5):
        sample = baseline_worlds(groups, m)
        assert len(sample) == min(m, worlds) and len(set(sample)) == len(sample)
        per = [int(np.count_nonzero((sample >= r.start) & (sample < r.stop))) for r in groups]
        assert max(per) - min(per) <= 1 and per == sorted(per, reverse=True)
        for r, k in zip(groups, per, strict=True):
            np.testing.assert_array_equal(
                sample[(sample >= r.start) & (sample < r.stop)], np.arange(r.start, r.start + k)
            )


@pytest.mark.parametrize("seed", range(5))
def test_chunks_cover_the_worlds_and_never_straddle_plans(seed):
    """Chunks of at most C contiguous worlds, in order, cut where a plan group ends; the worlds
    that send samples (scipy sample, first K) are a prefix of every group, as simulate takes
    them."""
    rng = np.random.default_rng(seed)
    worlds = int(rng.integers(1, 300))
    groups = world_groups(worlds, int(rng.integers(1, worlds + 1)))
    size = int(rng.integers(1, 40))
    chunks = study_chunks(groups, size)
    assert [c.index for c in chunks] == list(range(len(chunks)))
    np.testing.assert_array_equal(np.concatenate([list(c.rows) for c in chunks]), range(worlds))
    for c in chunks:
        assert 1 <= len(c.rows) <= size and set(c.rows) <= set(groups[c.group])
        assert c.rows.start == groups[c.group].start or len(chunks[c.index - 1].rows) == size
    sample = baseline_worlds(groups, int(rng.integers(0, worlds + 1)))
    sent = sampled_worlds(groups, sample, int(rng.integers(0, worlds + 5)))
    for rows in groups:
        mine = sent[(sent >= rows.start) & (sent < rows.stop)]
        np.testing.assert_array_equal(mine, np.arange(rows.start, rows.start + len(mine)))
    for bad in (0, -3, 1.5):
        with pytest.raises(InputError, match="--chunk-worlds must be an integer >= 1"):
            study_chunks(groups, bad)


def test_resume_keeps_only_chunks_of_the_same_settings(tmp_path):
    """A chunk folder is refused without --resume, and with --resume when a setting differs
    (one InputError naming it); the same settings keep its chunk files."""
    store = ChunkStore(tmp_path / "chunks")
    settings = {"seed": 3, "worlds": 4, "plan": "short", "spread": {"com_offset": 0.004}}
    assert store.prepare(settings, resume=True) == 0  # nothing to resume: a fresh start
    chunk = study_chunks([range(4)], 2)[1]
    store.write(chunk, {"world": {"x": np.arange(2.0)}, "timing": {"t": 1.5}})
    assert store.prepare(settings, resume=True) == 1 and store.done(chunk)
    np.testing.assert_array_equal(store.read(chunk)["world"]["x"], [0.0, 1.0])
    with pytest.raises(InputError, match="--resume continues it"):
        store.prepare(settings, resume=False)
    with pytest.raises(InputError, match="seed 3 then, 4 now; the spread differs"):
        store.prepare(settings | {"seed": 4, "spread": {"com_offset": 0.0}}, resume=True)
    store.remove()
    assert not store.folder.exists()


def test_random_plans_split_the_worlds_into_groups(robot, tmp_path, monkeypatch):
    """--plan random:2: world 0 records one random plan, world 1 another (quick ones here: short
    fast sweeps near the middle of the ranges; the study's take minutes on this CPU). The truths
    are those of any plan; the report lists both plans, how often the JAX fit's pooled gravity-
    current error is worse than the scipy fit's, and the largest identified ratio error."""
    quick = functools.partial(
        named_plans.random_plan,
        speeds=(math.radians(50), math.radians(60)),
        spans=(math.radians(40), math.radians(50)),
        hold_fraction=0.3,
        move_speed=math.radians(90),
    )
    monkeypatch.setattr(named_plans, "random_plan", quick)
    settings = CalibrationSettings(2, SEED, plan="random:2", baseline_sample=2, poses=100)
    report, arrays, paths = study_into(tmp_path / "r", settings, progress=False, robot=robot)
    assert sorted(p.name for p in paths) == sorted([*FIGURES, WORLDS_FILE, STUDY_FILE])
    json.loads((tmp_path / "r" / STUDY_FILE).read_text(), parse_constant=pytest.fail)
    start, n = start_pose(robot), 6
    plans = [named_plans.named_plan(robot, "random:2", seed=SEED, group=g) for g in range(2)]
    assert plans[0] != plans[1]
    groups = report["plan"]["groups"]
    assert [d["worlds"] for d in groups] == [[0, 1], [1, 2]]
    for g, (d, plan) in enumerate(zip(groups, plans, strict=True)):
        assert d["seed"] == plan_seed(SEED, g) and d["joints"] == plan.joints
        assert d["steps"] == plan.samples(start) and d["sweeps"] == len(plan)
    assert report["plan"]["duration_s"] == pytest.approx(np.mean([d["duration_s"] for d in groups]))
    np.testing.assert_array_equal(arrays["plan_group"], [0, 1])
    assert report["jax"]["converged"] == 2 and report["faulted_worlds"] == 0
    # world w has the truth it has under any plan; it recorded its group's plan: the fit
    # determines the friction of the joints that plan sweeps or its transfers move, no other
    model = fit_model(robot)
    truth = jax_truth_vector(model, draw_truth(robot, 2, SEED, TruthSpread()))
    np.testing.assert_array_equal(arrays["truth"][:, : truth.shape[1]], truth)
    only_moved = 0
    for w, plan in enumerate(plans):
        swept = np.isin(np.arange(n), plan.joints)
        moved = signal_plans(plan_signal(plan, start), 1).transfers.use.any(0)
        np.testing.assert_array_equal(arrays["jax_identified"][w, n : 2 * n], swept | moved)
        only_moved += np.count_nonzero(moved & ~swept)
    assert only_moved > 0
    # the pooled gravity-current errors, recomputed from the estimates, and their comparison
    est = arrays["jax_estimate"]
    com = np.zeros((2, 2, len(robot.link_names), 3))
    for k, x in enumerate((truth, est)):
        com[k][:, model.link_ids] = x[:, 3 * n : 3 * n + model.K].reshape(2, -1, 3)
    poses = random_poses(robot, 100, seed=SEED)
    # pooled over the joints each world's plan sweeps
    swept = np.array([np.isin(np.arange(n), plan.joints) for plan in plans])
    np.testing.assert_array_equal(arrays["swept"], swept)
    pooled = gravity_current_error_batch(
        robot, truth[:, :n], com[0], est[:, :n], com[1], poses, pooled=True, joints=swept
    )
    np.testing.assert_allclose(arrays["jax_gravity_current_error_pooled"], pooled, rtol=1e-9)
    # the scipy sample has a world of each plan
    np.testing.assert_array_equal(arrays["scipy_worlds"], [0, 1])
    assert report["scipy"]["plans"] == 2 and report["scipy"]["failed"] == []
    sp = arrays["scipy_gravity_current_error_pooled"]
    assert np.all((0 < sp) & (sp < 1))
    cmp = report["jax"]["on_scipy_worlds"]["pooled_gravity_current_error"]
    assert cmp == {
        "worlds": 2,
        "jax_worse_fraction": float(np.mean(pooled > sp)),
        "jax_median": pytest.approx(np.median(pooled)),
        "scipy_median": pytest.approx(np.median(sp)),
    }
    ident = arrays["jax_identified"][:, :n]
    rel = np.abs(est[:, :n] / truth[:, :n] - 1)
    worst = report["jax"]["largest_identified_ratio_error"]
    assert worst["count"] == ident.sum()
    if ident.any():  # one mounting: most ratios are confounded with COM offsets
        assert worst["max_abs_relative"] == rel[ident].max()
        assert rel[worst["world"], worst["joint"]] == rel[ident].max() > 0
    else:
        assert worst["max_abs_relative"] is None or np.isnan(worst["max_abs_relative"])
    text = summary(report)
    assert "random:2 (2 plans, mean" in text and "JAX worse than scipy in" in text
    if ident.any():
        assert f"largest ratio error the JAX fit reports identified ({ident.sum()} ratios)" in text
    else:
        assert "no ratio reported identified" in text


def _tiny(plan: str, **kw) -> CalibrationSettings:
    return CalibrationSettings(2, SEED, plan=plan, baseline_sample=2, poses=200, **kw)


@pytest.fixture(scope="module")
def whole(study):
    """The tiny study in one chunk (``study``, as its files hold it)."""
    report, arrays, _, _ = study
    return StudyOutputs(report, arrays, [])


def _same(a: StudyOutputs, b: StudyOutputs, skip: tuple[str, ...] = ()) -> None:
    """The same findings (all but run times and ``skip``) and per-world arrays, bit for bit."""
    drop = (*TIMING, *skip)
    assert json_ready({k: v for k, v in a.report.items() if k not in drop}) == json_ready(
        {k: v for k, v in b.report.items() if k not in drop}
    )  # as study.json has them (NaN: null)
    assert a.arrays.keys() == b.arrays.keys()
    for k, v in a.arrays.items():
        np.testing.assert_array_equal(b.arrays[k], v, err_msg=k)


@TINY_STUDY
def test_chunked_interrupted_and_resumed_study_is_the_whole_one(
    whole, robot, tiny_plan, tmp_path, monkeypatch
):
    """One world per chunk, interrupted after the first chunk and resumed: the same per-world
    arrays and findings as the study in one chunk, bit for bit (each world's truth, noise and
    fit are its own; the fits run in batches of one shape). The finished chunk stays on disk
    until the report is written; the first --keep-samples worlds' recordings are saved. Resumed
    without a chunk size, it keeps the interrupted run's (the default, 4096 per device, would
    be the whole study of 2 here)."""
    out = tmp_path / "chunked"
    settings = _tiny(tiny_plan, chunk_worlds=1, keep_samples=1)
    real, calls = sc.chunk_results, []

    def interrupted(study, chunk, progress=False):
        calls.append(chunk.index)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(study, chunk, progress)

    monkeypatch.setattr(sc, "chunk_results", interrupted)
    with pytest.raises(KeyboardInterrupt):
        study_into(out, settings, progress=False, robot=robot)
    assert sorted(p.name for p in (out / "chunks").iterdir()) == [
        "settings.json",
        "worlds_000000000_000000001.npz",
    ]
    assert not (out / STUDY_FILE).exists()
    with pytest.raises(InputError, match="--resume continues it"):
        study_into(out, settings, progress=False, robot=robot)
    with pytest.raises(InputError, match="every 10 then, 5 now"):
        study_into(out, _tiny(tiny_plan, chunk_worlds=1, keep_samples=1, every=5),
                      robot=robot, progress=False, resume=True)  # fmt: skip
    calls.clear()
    unsized = _tiny(tiny_plan, keep_samples=1)
    resumed = study_into(out, unsized, progress=False, robot=robot, resume=True)
    assert calls == [1]  # the first chunk was kept
    assert resumed.report["chunk_worlds"] == 1 and whole.report["chunk_worlds"] == 2
    _same(whole, resumed, skip=("chunk_worlds",))
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [*FIGURES, STUDY_FILE, WORLDS_FILE, "samples"]
    )
    assert [p.name for p in (out / "samples").iterdir()] == ["world_00000.npz"]
    rec = load_recording(out / "samples" / "world_00000.npz")
    signal = plan_signal(named_plan(robot, tiny_plan), start_pose(robot))
    np.testing.assert_array_equal(rec.joint, signal.joint[::10])
    np.testing.assert_allclose(rec.q, signal.q_ref[::10], atol=0.05)  # it followed the plan


@TINY_STUDY
def test_outputs_are_all_or_nothing(study, tmp_path, monkeypatch):
    report, arrays, _, _ = study
    out = tmp_path / "out"
    out.mkdir()
    (out / "study.json").write_text("{}")  # an earlier report stays as it was

    def broken(*_args, **_kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(calibration_outputs, "plot_coverage", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        write_outputs(out, report, arrays)
    assert [p.name for p in out.iterdir()] == ["study.json"]
    assert (out / "study.json").read_text() == "{}"


# ----------------------------------------------------------------------------- slow
@pytest.mark.slow
def test_short_plan_on_four_worlds(tmp_path):
    """The documented CPU run: every joint swept once (2 worlds here, to keep CI short)."""
    out = tmp_path / "short"
    args = ["study", "calibration", "--worlds", "2", "--plan", "short", "--seed", "1"]
    result = CliRunner().invoke(cli, [*args, "--no-progress", "--out", str(out)])
    assert result.exit_code == 0, result.output + repr(result.exception)
    report = json.loads((out / "study.json").read_text())
    assert report["jax"]["converged"] == 2 and report["plan"]["sweeps"] == 6
    g = report["jax"]["gravity_current_error"]["max"]
    assert max(g[1:5]) < 0.05, g
    assert report["coverage"]["jax"]["identified"]["coverage_95"] >= 0.8


@TINY_STUDY
@pytest.mark.slow
def test_numbers_do_not_depend_on_the_device_count(tiny_plan, study, tmp_path):
    """Two forced CPU devices (worlds sharded, 2 per MJX run): the same worlds and fits (the
    JAX fits: no scipy sample here)."""
    out = tmp_path / "two"
    args = ["study", "calibration", "--worlds", "2", "--seed", str(SEED), "--plan", tiny_plan]
    args += ["--baseline-sample", "0", "--poses", "200", "--no-progress", "--out", str(out)]
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    code = "from jaxcomp.cli import main; main()"
    done = subprocess.run(
        [sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-3000:]
    two = json.loads((out / "study.json").read_text())
    assert len(two["devices"]) == 2 and two["world_batch"] == 2
    with np.load(out / "worlds.npz") as data:
        np.testing.assert_allclose(data["truth"], study[1]["truth"], rtol=1e-9, atol=1e-12)
        # the moments are XLA sums, whose order may follow the batch shape: the fits agree to
        # their convergence tolerance (COM offsets to 0.1 um, far inside their mm-scale std)
        np.testing.assert_allclose(
            data["jax_estimate"], study[1]["jax_estimate"], rtol=1e-6, atol=1e-7
        )


@pytest.fixture(scope="module")
def uneven_plan(robot):
    """Joints 1-4 of the short plan, joints 2 and 3 over +-8 deg, the others +-25: sweeps of
    uneven lengths, two of which share a lane side by side (``pack_segments``)."""
    short = short_plan(robot, speed=math.radians(60), move_speed=math.radians(90))
    span = {1: 25, 2: 8, 3: 8, 4: 25}
    sweeps = [
        Sweep(
            s.joint,
            s.hold,
            max(s.lower, -math.radians(span[s.joint])),
            math.radians(span[s.joint]),
            s.speed,
        )
        for s in short.sweeps
        if s.joint in span
    ]
    return CalibrationPlan(tuple(sweeps), short.move_speed, 0.2, short.ramp)


@pytest.mark.parametrize("arm", ["gen3_lite", "odd"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lanes_hold_every_sweep_once_in_plan_order(arm, seed, tmp_path):
    """``pack_segments`` on random plans, with and without the transfers between sweeps:
    every segment once, at its lane and step, after a restart and a settling hold unless first
    in its lane; lanes in plan order, none longer than the longest segment, fewer lanes than
    segments where two fit in one; faults counted in the sweeps only; each lane step's plan step
    (the noise's). Without transfers each segment ends with its last pass."""
    from jaxcomp.hardware.mjx import PLAN, RESTART, SETTLE
    from jaxcomp.robot import load_robot
    from jaxcomp.studies.plan_signal import LANE_STRETCH, pack_segments

    if arm == "odd":
        sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
        from odd_arms import serial_arm

        (tmp_path / "arm.xml").write_text(serial_arm(40 + seed, n=4 + seed, continuous=(0,)))
        arm = str(tmp_path / "arm.xml")
    robot = load_robot(arm)
    start = start_pose(robot)
    signal = plan_signal(named_plan(robot, "random:3", seed=seed, group=seed), start)
    every, hold = 10, 500
    transfers = seed != 1
    seg = plan_segments(signal, start, every, transfers)
    lanes = pack_segments(seg, every, hold)
    full = plan_segments(signal, start, every)
    np.testing.assert_array_equal(seg.sweep_end, full.sweep_end)
    np.testing.assert_array_equal(seg.end, full.end if transfers else full.sweep_end)
    for k, s in enumerate(full.signals):  # the last pass step, relative to the segment
        assert s.direction[seg.sweep_end[k] - 1 - seg.first[k]] != 0
        assert (s.direction[seg.sweep_end[k] - seg.first[k] :] == 0).all()
    length = seg.end - seg.first
    longest = -(-length.max() // every) * every
    K, (L, B) = len(length), lanes.phase.shape
    assert longest <= L <= LANE_STRETCH * longest + every
    assert set(lanes.lane.tolist()) == set(range(B)) and B <= K
    assert B * (L + hold) <= K * (longest + hold)  # fewer lane steps than a lane a segment
    fits = any(a + hold + b <= longest for i, a in enumerate(length) for b in length[i + 1 :])
    assert B < K or not fits
    for k in range(K):
        b, at = lanes.lane[k], lanes.at[k]
        assert at % every == 0
        np.testing.assert_array_equal(
            lanes.q_ref[at : at + length[k], b], seg.q_ref[: length[k], k]
        )
        sweep = seg.sweep_end[k] - seg.first[k]
        assert (lanes.phase[at : at + sweep, b] == PLAN).all()
        assert (lanes.phase[at + sweep : at + length[k], b] == SETTLE).all()
        np.testing.assert_array_equal(
            lanes.plan_step[at : at + length[k], b], seg.first[k] + np.arange(length[k])
        )
        mine = np.flatnonzero(lanes.lane == b)
        if k == mine.min():
            assert at == 0
            np.testing.assert_array_equal(lanes.start[b], seg.start[k])
        else:
            assert k > mine.min() and lanes.at[mine[mine < k]].max() < at
            assert lanes.phase[at - hold, b] == RESTART
            assert (lanes.phase[at - hold + 1 : at, b] == SETTLE).all()
            np.testing.assert_array_equal(
                lanes.q_ref[at - hold : at, b], seg.start[k][None].repeat(hold, 0)
            )
        sig = lanes.signals[b]
        np.testing.assert_array_equal(
            sig.joint[at : at + length[k]][: len(seg.signals[k].joint)], seg.signals[k].joint
        )


def test_sweeps_side_by_side_record_what_the_sweeps_in_turn_record(robot, uneven_plan):
    """``simulate(parallel=True)`` (each plan sweep from rest where the sweep before it ends,
    packed into lanes: two of these sweeps share one) against the plan run in turn, same
    truths and noise (drawn at each plan step): the same samples and labels; the swept
    joints' motion within 0.5 mrad; the held joints within 10 mrad (where Coulomb friction
    stops a joint under its servo depends on how it got there, and a sweep in its own world
    starts from a freshly settled rest); the fits within 5e-3 (ratio, relative) and 0.5 mA
    (friction). Without a kept recording: the same steps (the fit uses the transfers, so they
    are simulated), the same moments and transfer bins bit for bit."""
    from jaxcomp.studies.plan_signal import pack_segments

    start = start_pose(robot)
    signal = plan_signal(uneven_plan, start)
    seg = plan_segments(signal, start, every=10)
    assert len(seg.begin) == 4 and seg.end[-1] == len(signal.q_ref)
    for k, (a, b, f) in enumerate(zip(seg.begin, seg.end, seg.first, strict=True)):
        np.testing.assert_array_equal(seg.q_ref[a - f : b - f, k], signal.q_ref[a:b])
        assert f % 10 == 0 and a - 10 < f <= a
        assert k == 0 or (signal.direction[a] != 0 and signal.direction[a - 1] == 0)
        np.testing.assert_array_equal(seg.signals[k].joint[a - f :], signal.joint[a:b])
        np.testing.assert_array_equal(seg.start[k], signal.q_ref[f - 1] if f else start)
    lanes = pack_segments(seg, 10, 500)
    assert lanes.q_ref.shape[1] == 3  # two sweeps share a lane

    truth = draw_truth(robot, 1, SEED, TruthSpread())
    sim = simulator(None, robot)
    kw = dict(seed=SEED, every=10, world_batch=1)
    turn = simulate(sim, truth, signal, keep=1, **kw)
    side = simulate(sim, truth, signal, keep=1, parallel=True, **kw)
    assert side.world_steps == 3 * (len(lanes.q_ref) + 500)
    bare = simulate(sim, truth, signal, keep=0, parallel=True, **kw)
    assert bare.world_steps == side.world_steps and bare.recordings == []
    for a, b in zip(bare.moments + bare.transfers, side.moments + side.transfers, strict=True):
        np.testing.assert_array_equal(a, b)
    # the transfers' samples: as many side by side as in turn (bins in another order)
    counts = [r.transfers.count[0].sum(0) for r in (side, turn)]
    assert counts[1].sum() > 0 and np.all(np.abs(counts[0] - counts[1]) <= 0.02 * counts[1].max())
    np.testing.assert_array_equal(bare.fault_step, side.fault_step)
    np.testing.assert_array_equal(side.fault_step, turn.fault_step)
    for a, b in zip(side.recordings, turn.recordings, strict=True):
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.joint, b.joint)
        np.testing.assert_array_equal(a.direction, b.direction)
        sw = np.flatnonzero(a.joint >= 0)
        swept = np.abs(a.q[sw, a.joint[sw]] - b.q[sw, b.joint[sw]])
        assert swept.max() < 5e-4 and np.abs(a.q - b.q).max() < 1e-2
    np.testing.assert_array_equal(side.moments.joint, turn.moments.joint)
    assert np.abs(side.moments.count - turn.moments.count).max() <= 1
    model = fit_model(robot)
    fits = [batched_fit.fit_batch(model, r.moments, transfers=r.transfers) for r in (side, turn)]
    f_side, f_turn = (f.solution for f in fits)
    # held joints move a little differently (< 1e-2 rad), the fit takes each sample's held
    # pose, and a lane's transfer starts from a restart at rest: the ratios agree far inside
    # their standard errors (1-5 %), the friction losses within a third of theirs
    np.testing.assert_allclose(f_side.ratio, f_turn.ratio, rtol=5e-3)
    n = f_side.ratio.shape[1]
    friction_std = fits[1].std[:, n : 2 * n]
    assert np.all(np.abs(f_side.friction - f_turn.friction) <= friction_std / 3), (
        f_side.friction - f_turn.friction,
        friction_std,
    )


@TINY_STUDY
@pytest.mark.slow
def test_two_processes_give_the_one_process_study(whole, tiny_plan, tmp_path):
    """--distributed over two local CPU processes (gloo), one world per chunk, each process
    its own chunk: process 0's worlds.npz and study.json findings are those of the study in
    one process, bit for bit; the other process writes no report."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "two"
    args = ["study", "calibration", "--worlds", "2", "--seed", str(SEED), "--plan", tiny_plan]
    args += ["--baseline-sample", "2", "--poses", "200", "--no-progress", "--out", str(out)]
    args += ["--chunk-worlds", "1", "--distributed", "--coordinator", f"127.0.0.1:{port}"]
    args += ["--num-processes", "2"]
    code = "from jaxcomp.cli import main; main()"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", code, *args, "--process-id", str(i)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for i in range(2)
    ]
    done = [r.communicate(timeout=900) for r in runs]
    for r, (_, stderr) in zip(runs, done, strict=True):
        assert r.returncode == 0, stderr[-3000:]
    assert "process 1: its chunks are done" in done[1][0] and "wrote" in done[0][0]
    report = json.loads((out / STUDY_FILE).read_text())
    with np.load(out / WORLDS_FILE) as data:
        arrays = {k: data[k] for k in data.files}
    assert report["processes"] == 2 and whole.report["processes"] == 1
    _same(whole, StudyOutputs(report, arrays, []), skip=("processes", "chunk_worlds"))
    assert not (out / "chunks").exists()
