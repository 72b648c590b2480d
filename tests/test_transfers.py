"""The transfers between sweeps as data for the joint fit (``identify.transfers``), on generated
arms with continuous joints, random plans and random truths."""

import math

import jax
import numpy as np
import pytest
import synthetic
from odd_arms import serial_arm

import jaxcomp
from jaxcomp import dynamics
from jaxcomp.identify import joint_fit
from jaxcomp.identify.evaluate import gravity_current_error_batch, random_poses
from jaxcomp.identify.fit_model import fit_model
from jaxcomp.identify.fit_solver import joint_rss
from jaxcomp.identify.fit_stats import Stats, transfer_stats
from jaxcomp.identify.random_plans import MOVE_SPEED, random_plan
from jaxcomp.identify.steady import STEADY_SETTLE, STEADY_TRIM
from jaxcomp.identify.transfers import BIN_ANGLE, MIN_SPEED, bucket, padded_bins, transfer_bins
from jaxcomp.studies.truth_draw import TruthSpread, draw_truth

SPREAD = TruthSpread(com_offset=0.004)


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    path = tmp_path_factory.mktemp("arm") / "arm.xml"
    path.write_text(serial_arm(41, n=5, scale=0.8, continuous=(0, 3)))
    return jaxcomp.load_robot(path)


@pytest.fixture(scope="module")
def truths(arm):
    return draw_truth(arm, 3, 41, SPREAD)


def _coms(robot, params) -> np.ndarray:
    c = np.zeros((len(robot.link_names), 3))
    for link, off in params.com_offset.items():
        c[robot.link_index(link)] = off
    return c


def _recording(arm, truths, w: int, noise: float, transfers: float = MOVE_SPEED):
    plan = random_plan(arm, 100 + w)
    truth = truths.true_robot(arm, w)
    sweeps = synthetic.plan_sweeps(plan)
    return synthetic.recording(arm, truth.params, sweeps, noise=noise, seed=w, transfers=transfers)


def test_transfer_bins_keep_every_cruise_sample_of_the_moving_joints(arm, truths):
    """Noise-free straight moves at constant velocity: every sample of a leg counts, less the
    settling and trim at its ends; a joint slower than MIN_SPEED counts nowhere; bins span at
    most BIN_ANGLE of the lead joint; and the bin means are the samples' means."""
    rec = _recording(arm, truths, 0, noise=0.0)
    tb = transfer_bins(rec)
    legs = np.flatnonzero(np.diff(np.r_[0, (rec.joint < 0).astype(int), 0]))
    expected = np.zeros(rec.n_joints)
    for a, b in zip(legs[::2], legs[1::2], strict=True):
        t = rec.t[a:b]
        kept = np.count_nonzero((t > t[0] + STEADY_SETTLE) & (t < t[-1] - STEADY_TRIM))
        expected += kept * (np.abs(rec.dq[a]) >= MIN_SPEED)
    assert expected.sum() > 1000
    np.testing.assert_allclose(tb.count.sum(0), expected, atol=2 * len(legs))
    lead = np.argmax(np.abs(tb.velocity), axis=1)
    assert np.all(tb.count.sum(1) > 0)
    per = tb.count.max(1)
    step = np.abs(tb.velocity[np.arange(tb.size), lead]) * 1e-3  # rad a sample moves
    assert np.all((per - 1) * step <= BIN_ANGLE + 1e-9), ((per - 1) * step).max()
    moving = tb.count > 0
    assert np.all(np.abs(tb.velocity[moving]) >= MIN_SPEED)


def test_the_transfer_model_holds_exactly_at_the_truth(arm, truths):
    """Noise-free transfers of a true robot (COM offsets of a few mm): each bin's mean current
    is r (g + C(q, dq) dq) + l sign(dq) of the true robot at the bin's mean pose and velocity
    to 1e-4 of the current; and the fit's transfer statistics at the true parameters leave 100
    times less (beyond the current's spread within the bins) than at the nominal COM (gravity
    is linear in the offsets, the Coriolis torque nearly so, and both are modelled)."""
    truth = truths.true_robot(arm, 1)
    rec = _recording(arm, truths, 1, noise=0.0)
    tb = transfer_bins(rec)
    params = truth.params.inertial_params(arm)
    torque = jax.vmap(lambda q, v: dynamics.bias(arm.tree, q, v, params))(tb.pose, tb.velocity)
    model = truth.ratio * np.asarray(torque) + truth.friction * np.sign(tb.velocity)
    counted = tb.count > 0
    measured = tb.current[counted] / tb.count[counted]
    scale = np.sqrt(np.mean(measured**2))
    assert np.abs(measured - model[counted]).max() < 1e-4 * scale  # the curvature in a bin

    the_model = fit_model(arm)
    st = joint_fit.prepare(the_model, rec)[0] + Stats(
        *(-a for a in joint_fit.prepare(the_model, rec, transfers=False)[0])
    )  # the transfers' statistics alone
    com = _coms(arm, truth.params)[[arm.link_index(link) for link in the_model.links]].ravel()
    n, K = the_model.n, the_model.K

    def rss(delta):
        theta = np.r_[truth.ratio, truth.friction, np.zeros(n), delta]
        return np.asarray(joint_rss(jax.numpy.asarray(theta), st, n, K))

    # what no parameter explains: the current's spread about its mean within each bin
    within = (tb.square - np.where(counted, tb.current**2 / np.maximum(tb.count, 1), 0)).sum(0)
    moving = np.asarray(st.samples) > 0
    assert moving.sum() >= n - 1
    at_truth, nominal = rss(com) - within, rss(np.zeros(K)) - within
    assert np.all(at_truth[moving] * 100 < nominal[moving]), (at_truth, nominal)


def test_transfers_shrink_the_gravity_current_error(arm, truths):
    """The same noisy recordings (0.05 A) fitted with and without their transfers: with them
    the gravity-current error over random poses (the swept joints) is smaller in every world,
    by a third at least in the median, and the ratios stay within 4 standard errors."""
    poses = random_poses(arm, 300, seed=1)
    errors = []
    for w in range(3):
        rec = _recording(arm, truths, w, noise=0.05)
        truth = truths.true_robot(arm, w)
        swept = np.isin(np.arange(rec.n_joints), rec.joint)[None]
        row = []
        for transfers in (False, True):
            fit = joint_fit.fit(rec, com_prior=SPREAD.com_offset / math.sqrt(3), complete=False,
                              transfers=transfers)  # fmt: skip
            row.append(
                gravity_current_error_batch(
                    arm,
                    truth.ratio[None],
                    _coms(arm, truth.params)[None],
                    fit.ratio[None],
                    _coms(arm, fit)[None],
                    poses,
                    batch=1,
                    pooled=True,
                    joints=swept,
                )[0]  # fmt: skip
            )
            z = (fit.ratio - truth.ratio) / fit.std["ratio"]
            assert np.all(np.abs(z[swept[0]]) < 4), (transfers, z)
        errors.append(row)
    errors = np.array(errors)
    assert np.all(errors[:, 1] < errors[:, 0]), errors
    assert np.median(errors[:, 1] / errors[:, 0]) < 2 / 3, errors


def test_a_recording_without_transfers_fits_as_before(arm, truths):
    """Sweeps alone (each starting where the one before ends): no transfer bins, and the fit
    with transfers is the fit without them."""
    rec = _recording(arm, truths, 2, noise=0.05, transfers=0.0)
    assert transfer_bins(rec).size == 0
    a = joint_fit.fit(rec, complete=False)
    b = joint_fit.fit(rec, complete=False, transfers=False)
    np.testing.assert_array_equal(a.ratio, b.ratio)
    np.testing.assert_array_equal(a.friction, b.friction)


RING = (0.015, 6.0, 0.4)  # the velocity rings by 1.5 % at 6 Hz, decaying in 0.4 s


def test_a_ringing_servo_is_modelled_by_the_measured_acceleration(arm, truths):
    """Transfers whose velocity rings after the ramp (``RING``: inside the steady band, so the
    samples count), the current holding M(q) ddq: each bin's mean current is the true robot's
    r (M(q) ddq + C dq + g) + l sign(dq) with the bin's measured mean acceleration, many times
    nearer than without it; and at the true parameters the fit's transfer statistics leave
    many times less than with the acceleration hidden from them."""
    truth = truths.true_robot(arm, 1)
    plan = random_plan(arm, 101)
    rec = synthetic.recording(arm, truth.params, synthetic.plan_sweeps(plan), noise=0.0,
                              seed=1, transfers=MOVE_SPEED, ring=RING)  # fmt: skip
    tb = transfer_bins(rec)
    counted = tb.count > 0
    assert counted.sum() > 200
    params = truth.params.inertial_params(arm)

    def torque(q, v, a):
        return dynamics.mass_matrix(arm.tree, q, params) @ a + dynamics.bias(arm.tree, q, v, params)

    full = np.asarray(jax.vmap(torque)(tb.pose, tb.velocity, tb.acceleration))
    still = np.asarray(jax.vmap(torque)(tb.pose, tb.velocity, 0 * tb.acceleration))
    measured = tb.current[counted] / tb.count[counted]
    off = [np.abs(measured - (truth.ratio * t + truth.friction * np.sign(tb.velocity))[counted])
           for t in (full, still)]  # fmt: skip
    scale = np.sqrt(np.mean(measured**2))
    assert off[0].max() < 2e-3 * scale, (off[0].max(), scale)
    assert off[1].max() > 10 * off[0].max(), (off[1].max(), off[0].max())

    model = fit_model(arm)
    com = _coms(arm, truth.params)[[arm.link_index(link) for link in model.links]].ravel()
    n, K = model.n, model.K
    theta = jax.numpy.asarray(np.r_[truth.ratio, truth.friction, np.zeros(n), com])
    left = []
    for acc in (tb.acceleration, 0 * tb.acceleration):
        bins = tb._replace(acceleration=acc)
        bins = padded_bins(bins, bucket(bins.size))
        st = transfer_stats(model, bins, rec.gravity, 0.0, np.zeros(3))
        within = (tb.square - np.where(counted, tb.current**2 / np.maximum(tb.count, 1), 0)).sum(0)
        left.append(np.asarray(joint_rss(theta, st, n, K)) - within)
    moving = tb.count.sum(0) > 0
    assert np.all(left[0][moving] * 10 < left[1][moving]), left
