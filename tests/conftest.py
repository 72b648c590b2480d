"""Shared fixtures: one simulated calibration recording per session (it takes ~15 s).

experiments/ goes on sys.path: the tests use its arm generators (``odd_arms``)."""

import sys
from pathlib import Path

import numpy as np
import pytest

import jaxcomp
from jaxcomp.hardware import Simulator, TrueRobot
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.identify.recorder import record

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

#: Viscous friction of the simulated truth, N m s/rad: unmodelled by the default plan's fit.
VISCOUS = 0.003


@pytest.fixture(scope="session")
def sim_calibration(tmp_path_factory):
    """(clean recording, truth): the default plan on the simulator, current noise off.

    The truth is drawn from seed 11 (paper ratios and frictions, COM offsets of a few mm) with
    a little viscous friction; tests add the sensor noise they need to the clean current.
    """
    robot = jaxcomp.load_robot("gen3_lite")
    truth = TrueRobot.draw(robot, seed=11, current_noise=0.0, viscous=np.full(6, VISCOUS))
    sim = Simulator(robot, truth, seed=11)
    path = tmp_path_factory.mktemp("calibration") / "recording.npz"
    with sim.arm as arm:
        rec = record(arm, default_plan(robot), path, model="gen3_lite", progress=False)
    return rec, truth
