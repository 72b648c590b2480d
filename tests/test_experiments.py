"""The paper's experiments (experiments/paper_exp*.py) in their quick mode, with their checks.

The scripts are not an installed package: experiments/ goes on sys.path. One simulated
calibration (short plan) is shared by Exp. 2 and 3 through their --params / --truth options;
Exp. 1 records its own rounds.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import paper_common  # noqa: E402
import paper_exp1_calibration as exp1  # noqa: E402
import paper_exp2_rope as exp2  # noqa: E402
import paper_exp3_guidance as exp3  # noqa: E402

from jaxcomp.hardware import TrueRobot  # noqa: E402
from jaxcomp.identify import joint_fit  # noqa: E402

SEED = 3


@pytest.fixture(scope="module")
def calibration(tmp_path_factory) -> list[str]:
    """--params / --truth options of a short-plan calibration of the truth of SEED."""
    folder = tmp_path_factory.mktemp("calibration")
    truth = TrueRobot.draw(paper_common.ARM, SEED)
    rec = paper_common.record_calibration(truth, paper_common.calibration_plan(short=True))
    joint_fit.fit(rec).save(folder / "params.json")
    truth.save(folder / "truth.json")
    return ["--params", str(folder / "params.json"), "--truth", str(folder / "truth.json")]


def _outputs(out: Path, names: list[str]) -> None:
    for name in names:
        path = out / name
        assert path.is_file() and path.stat().st_size > 1000, name


def test_exp1_calibration_rounds(tmp_path):
    res = exp1.main(["--quick", "--rounds", "3", "--seed", str(SEED), "--out", str(tmp_path)])
    assert res["ok"], res["checks"]
    _outputs(tmp_path, ["exp1_ratio.png", "exp1_friction.png", "exp1_com.png", "exp1_rounds.png"])
    data = json.loads((tmp_path / "exp1_calibration.json").read_text())
    assert data["rounds"] == 3 and len(data["rounds_data"]["jax"]["ratio"]) == 3
    truth = np.array(exp1.PAPER_RATIO)
    jax_ratio = np.array(data["rounds_data"]["jax"]["ratio"])
    # every round's JAX estimate within 2 % of the truth (the short plan), rounds differ (noise)
    assert np.abs(jax_ratio / truth - 1).max() < 0.02
    assert np.ptp(jax_ratio[:, 1]) > 0
    friction = np.array(data["summary"]["jax"]["friction_mean"])
    np.testing.assert_allclose(friction, exp1.PAPER_FRICTION, rtol=0.03)
    # the JAX fit's gravity current beats the paper's scipy fit on the joints gravity loads
    g_jax = np.array(data["summary"]["jax"]["gravity_current_error"])[1:5]
    g_scipy = np.array(data["summary"]["scipy"]["gravity_current_error"])[1:5]
    assert np.all(g_jax < g_scipy)


def test_exp2_rope_compliant_against_velocity(tmp_path, calibration):
    res = exp2.main(["--quick", "--out", str(tmp_path), *calibration])
    assert res["ok"], res["checks"]
    _outputs(tmp_path, ["exp2_trajectories.png", "exp2_error.png", "exp2_rope.json"])
    imp = res["runs"]["impedance"]["0.12_N_per_mm"]
    vel = res["runs"]["velocity"]["0.12_N_per_mm"]
    # the stiff spring: the velocity controller drags the rope far out (about 0.087 m of
    # stretch, 10 N), the compliant arm gives way
    assert vel["rope_force_max_N"] > 8.0
    assert imp["rope_force_max_N"] < 0.6 * vel["rope_force_max_N"]
    assert vel["excursion_ratio"] > 0.9 and imp["excursion_ratio"] < 0.6
    # inside the free circle: velocity controller sub-millimetre, compliant within 10 mm
    assert vel["free_rms_m"] < 1e-3 and imp["free_rms_m"] < 1e-2


def test_exp3_guidance_and_tracking(tmp_path, calibration):
    res = exp3.main(["--quick", "--out", str(tmp_path), *calibration])
    assert res["ok"], res["checks"]
    _outputs(tmp_path, ["exp3_guidance.png", "exp3_tracking.png", "exp3_guidance.json"])
    push = res["guidance"]["pushes"][0]
    assert push["displacement_m"] > 0.03  # the push displaces the end effector ...
    assert push["base_travel_m"] > 0.05  # ... the base follows ...
    assert push["ee_back_s"] < 3.0 and push["base_stopped_s"] < 3.0  # ... and both settle
    assert res["guidance"]["final_error_m"] < exp3.RETURN_TOL
    hold = res["tracking"]["pushes"][0]
    assert hold["max_error_m"] > 0.03 and hold["ee_back_first_s"] < 3.0
    assert res["tracking"]["base_path_m"] > 0.2
