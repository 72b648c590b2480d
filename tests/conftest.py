"""Shared fixtures: one simulated calibration recording per session (it takes ~15 s).

experiments/ goes on sys.path: the tests use its arm generators (``odd_arms``). The session
keeps compiled XLA programs in one fresh folder (``$JAXCOMP_CACHE``, as the CLI does), shared
by the test processes and the subprocesses they start: a program that several tests compile
is compiled once per session, never taken from an earlier session."""

import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import jaxcomp
from jaxcomp.hardware import Simulator, TrueRobot
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.identify.recorder import record

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))


def pytest_configure(config):
    """The session's compilation cache: made by the controlling process (inherited by the
    xdist workers and every subprocess), used by each process's in-process JAX."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        where = tempfile.mkdtemp(prefix="jaxcomp-tests-xla-")
        config._jaxcomp_cache = where
        os.environ["JAXCOMP_CACHE"] = where
    import jax

    jax.config.update("jax_compilation_cache_dir", os.environ["JAXCOMP_CACHE"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


#: Modules whose tests take a minute or more each (whole studies, MJX compiles, subprocesses):
#: collected first, so that the two CI workers start on them and finish on the short tests
#: instead of one worker running a long test alone at the end.
LONG_FIRST = (
    "test_study_calibration",
    "test_study_control",
    "test_mjx_sim",
    "test_pipeline_any_arm",
)


def pytest_collection_modifyitems(config, items):
    """Long modules first (``LONG_FIRST``, in that order), the rest as collected."""

    def rank(item) -> int:
        name = item.path.stem
        return LONG_FIRST.index(name) if name in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)  # stable: each module keeps its own order


def pytest_unconfigure(config):
    where = getattr(config, "_jaxcomp_cache", None)
    if where is not None:
        shutil.rmtree(where, ignore_errors=True)


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
