"""The identification's entry point (``jaxcomp.identify.fit`` and ``fit_each``): either method,
the params checked against the recording's robot."""

import dataclasses

import numpy as np
import pytest
import synthetic

import jaxcomp
from jaxcomp import identify
from jaxcomp.errors import InputError
from jaxcomp.identify import batched_fit, joint_fit
from jaxcomp.identify.named_plans import named_plan
from jaxcomp.plausibility import check_params
from jaxcomp.robot_params import RobotParams

LINKS = ("SHOULDER", "ARM", "FOREARM", "LOWER_WRIST", "UPPER_WRIST", "GRIPPER_FRAME")


@pytest.fixture(scope="module")
def robot():
    return jaxcomp.load_robot("gen3_lite")


@pytest.fixture(scope="module")
def recs(robot):
    """Two noisy recordings of the short plan on a truth off the nominal model."""
    rng = np.random.default_rng(3)
    nominal = RobotParams.nominal(robot)
    truth = RobotParams(
        "gen3_lite",
        nominal.ratio * rng.uniform(0.8, 1.2, 6),
        rng.uniform(0.3, 0.6, 6),
        {link: rng.uniform(-0.003, 0.003, 3) for link in LINKS},
    )
    sweeps = synthetic.plan_sweeps(named_plan(robot, "short"))
    return [synthetic.recording(robot, truth, sweeps, noise=0.03, seed=s) for s in (1, 2)]


def test_the_jax_method_fits_the_recordings_jointly_and_checks_the_params(robot, recs):
    params = identify.fit(recs, "jax")
    want = joint_fit.fit(recs)
    assert params.method == "jax"
    np.testing.assert_array_equal(params.ratio, want.ratio)
    np.testing.assert_array_equal(params.friction, want.friction)
    assert check_params(params, robot) is params
    assert not np.allclose(params.ratio, joint_fit.fit(recs[0]).ratio, rtol=1e-9)  # both count


def test_the_scipy_method_fits_one_recording_and_refuses_several(recs):
    params = identify.fit(recs[0], "scipy")
    assert params.method == "scipy" and params.ratio.shape == (6,)
    with pytest.raises(InputError, match="--method scipy fits one recording"):
        identify.fit(recs, "scipy")
    each = identify.fit_each(recs, "scipy")
    assert len(each) == 2 and np.array_equal(each[0].ratio, params.ratio)


def test_an_unknown_method_is_refused_naming_the_methods(recs):
    for call in (identify.fit, identify.fit_each):
        with pytest.raises(InputError, match=r"unknown fit method 'pinocchio'.*'jax', 'scipy'"):
            call(recs, "pinocchio")
    with pytest.raises(InputError, match="no recording to fit"):
        identify.fit_each([], "jax")


def test_implausible_params_are_refused_never_returned(robot, recs, monkeypatch):
    """A fit whose ratios came out 1000x (a current in mA) is refused, and ``fit_each`` names
    the recording whose params are implausible."""
    good = RobotParams.nominal(robot)
    bad = dataclasses.replace(good, ratio=1e3 * good.ratio)
    monkeypatch.setattr(joint_fit, "fit", lambda recordings, **options: bad)
    with pytest.raises(InputError, match="the jax fit's params are implausible"):
        identify.fit(recs, "jax")
    monkeypatch.setattr(batched_fit, "fit_each", lambda recordings, **options: [good, bad])
    with pytest.raises(InputError, match="params of recording 1 are implausible"):
        identify.fit_each(recs, "jax")
