"""The controller's behaviour in the simulator, with the full friction of the paper's arm.

The robot is the one the session's simulated calibration recorded (``sim_calibration``: the
default truth of seed 11, i.e. the paper's ratios and full friction losses, COM offsets of a few
mm, plus a little viscous friction), the controller gets the params the joint fit identifies
from that recording with the simulator's 0.05 A current noise, and the gains are
``ImpedanceGains.tracking()`` (K_d 400 N/m, D_d 30 N s/m, Eq. 16 with the motion-torque
direction at rest, t = 0.02 rad/s; see its docstring). Pushes ramp up over 0.1 s as a hand
would. The paper's own gains are measured by ``experiments/bench_loop.py --behaviour``: with
this friction they leave the arm stalled (about 35 mm RMS on the half circle).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic import with_noise

from jaxcomp.control import ImpedanceGains, make_impedance_controller
from jaxcomp.control.loop import run_control
from jaxcomp.control.mount import ArmMount, arm_model
from jaxcomp.hardware import Simulator, TrueRobot
from jaxcomp.identify import joint_fit
from jaxcomp.robot import load_robot

MOBILE = load_robot("mobile_gen3_lite")
ARM = arm_model(MOBILE)
FORCE = 10.0  # N
GAINS = ImpedanceGains.tracking()
K = GAINS.stiffness[0]  # N/m: F / K = 25 mm, inside the 0.1 m error clip


# one worker computes the fixtures, once (session: never torn down between its tests)
pytestmark = pytest.mark.xdist_group("control-behaviour")


@pytest.fixture(scope="session")
def identified(sim_calibration):
    """(params the joint fit identifies, the calibrated truth)."""
    clean, truth = sim_calibration
    return joint_fit.fit(with_noise(clean, 0.05, seed=0)), truth


@pytest.fixture(scope="session")
def controller(identified):
    ctrl = make_impedance_controller(ARM, identified[0], GAINS)
    ctrl.compile()
    return ctrl


def _sim(robot, truth: TrueRobot) -> Simulator:
    """The calibrated robot (arm alone or on its base), with the default current noise."""
    params = dataclasses.replace(truth.params, model=robot.name)
    return Simulator(robot, TrueRobot(params, 0.05, truth.viscous, truth.seed), seed=truth.seed)


def _ramped_push(sim: Simulator, start: float, length: float, force) -> float:
    """Five pushes of force / 5, 20 ms apart: ramps over 0.1 s; returns the release (s)."""
    for k in range(5):
        sim.push(start + 0.02 * k, length, np.asarray(force, float) / 5)
    return start + 0.08 + length


def _after(t, values, release, threshold):
    """Seconds after ``release`` at which ``values`` last exceeded ``threshold``."""
    late = np.flatnonzero((t > release) & (values > threshold))
    return t[late[-1]] - release if late.size else 0.0


def test_identified_params_are_the_full_friction(identified):
    params, truth = identified
    np.testing.assert_allclose(params.friction, truth.friction, rtol=0.03)
    assert truth.friction[1] / truth.ratio[1] > 4.5  # N m: joint 1 sticks hard


def test_free_space_half_circle_tracked_within_2_mm(controller, identified, tmp_path):
    """Exp. 2 without the rope: the paper's half circle (r 0.315 m, 0.101 m/s), lead-in and
    two passes (one reversal), arm alone."""
    sim = _sim(ARM, identified[1])
    result = run_control(
        sim.arm, None, controller, "tracking", "half-circle:passes=2", None, tmp_path
    )
    assert result.kind == "completed", result.reason
    assert result.duration > 25.0
    assert result.rms_error <= 2e-3, result.summary()
    assert result.max_error <= 5e-3, result.summary()


def test_steady_push_displaces_ee_by_f_over_k(controller, identified, tmp_path):
    """Arm alone, static target: pushes of 10 N along +x, -y, +z, -x, each held 1 s."""
    sim = _sim(ARM, identified[1])
    forces = [[FORCE, 0, 0], [0, -FORCE, 0], [0, 0, FORCE], [-FORCE, 0, 0]]
    windows, start = [], 0.2
    for force in forces:
        end = _ramped_push(sim, start, 1.0, force)
        windows.append((end, np.asarray(force, float)))
        start = end + 0.8
    result = run_control(sim.arm, None, controller, "tracking", "static", start, tmp_path)
    assert result.kind == "completed", result.reason
    rec = result.recording
    t = rec.t - rec.t[0]
    d = rec.extra["ee"] - rec.extra["target"]
    for end, force in windows:
        held = d[(t > end - 0.25) & (t < end - 0.05)].mean(axis=0)
        want = force / K
        along = held @ want / np.linalg.norm(want)
        assert along == pytest.approx(np.linalg.norm(want), rel=0.1), (force, held)
        assert np.linalg.norm(held - along * want / np.linalg.norm(want)) < 0.2 * along
        back = np.linalg.norm(d[(t > end + 0.6) & (t < end + 0.8)], axis=1)
        assert back.max() < 2e-3  # released: back at the target


def test_guidance_push_moves_base_then_ee_returns_and_base_stops(controller, identified, tmp_path):
    sim = _sim(MOBILE, identified[1])
    release = _ramped_push(sim, 0.3, 0.8, [FORCE, 0.0, 0.0])
    result = run_control(sim.arm, sim.base, controller, "guidance", None, 3.5, tmp_path)
    assert result.kind == "completed", result.reason
    rec = result.recording
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    base = rec.extra["base"]
    speed = np.r_[0.0, np.linalg.norm(np.diff(base[:, :2], axis=0), axis=1) / np.diff(rec.t)]
    pushed = (t > release - 0.3) & (t < release - 0.1)
    assert err[pushed].mean() == pytest.approx(FORCE / K, rel=0.15)
    assert speed[pushed].mean() > 0.05  # m/s: the base follows the push ...
    assert base[-1, 0] > 0.05  # ... forward
    assert _after(t, err, release, 3e-3) < 2.0  # s: the end effector is back at its target
    assert _after(t, speed, release, 2e-3) < 2.0  # s: and the base has stopped
    assert err[-1] < 3e-3 and speed[-200:].max() < 2e-3
    mount = ArmMount.from_model(MOBILE)  # the target stayed fixed in the base frame
    target = rec.extra["target"]
    target_b = np.array([mount.world_to_base(p, b) for p, b in zip(target, base, strict=True)])
    assert np.abs(target_b - target_b[0]).max() < 1e-9


def test_tracking_ee_returns_to_the_moving_target_after_a_push(controller, identified, tmp_path):
    sim = _sim(MOBILE, identified[1])
    release = _ramped_push(sim, 0.6, 0.8, [FORCE, 0.0, 0.0])
    result = run_control(
        sim.arm, sim.base, controller, "tracking", "circle:r=0.05,v=0.05", 3.0, tmp_path
    )
    assert result.kind == "completed", result.reason
    rec = result.recording
    t = rec.t - rec.t[0]
    target = rec.extra["target"]
    err = np.linalg.norm(rec.extra["ee"] - target, axis=1)
    assert err[(t > 0.2) & (t < 0.6)].max() < 3e-3  # tracks before the push
    pushed = (t > release - 0.3) & (t < release - 0.1)
    assert err[pushed].mean() == pytest.approx(FORCE / K, rel=0.15)
    assert _after(t, err, release, 3e-3) < 1.0  # s: back on the moving target
    assert err[t > release + 1.0].max() < 3e-3
    assert np.linalg.norm(target[-1] - target[0]) > 0.05  # the target moved on meanwhile
    assert np.linalg.norm(rec.extra["base"][-1, :2]) > 0.01  # and the base followed
