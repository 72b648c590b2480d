"""The calibration study: how well calibration finds thousands of simulated true robots.

N true Gen3 Lite arms are drawn from the seed (``draw_truth``: ratios 20-30 % off nominal,
friction torques 20-30 % off the paper's, COM offsets of a few mm on every moving link, current
noise, optional viscous friction); the calibration plan (default:
``identify.plan_design.default_plan``, the paper's ~230 s of sweeps; "random:K": K random
plans, ``identify.random_plans``, each recorded by a contiguous group of the worlds) is
recorded in every world at once on MJX (``MjxSimulator``, 1 kHz, float64, worlds sharded over
the accelerators), every world is fitted with the joint JAX fit in vmapped batches on the
accelerator (``batched_fit.fit_batch``) and M of them also with the paper's scipy fit
(``identify.baseline``; the first worlds of each plan's group, M spread over the plans as the
worlds are: ``baseline_worlds``). The report compares estimates with the truth.

The stages, each in its own module and composed here (``run_study``, ``chunk_results``):
``calibration_settings`` (what runs), ``truth_draw``, ``plan_signal``, ``plan_recording``
(simulate and reduce), ``batched_fit.fit_batch`` and ``baseline`` (fit), ``calibration_estimates``
and ``calibration_statistics`` (compare), ``calibration_report`` (report); the outputs written
(``calibration_figures``, ``calibration_outputs``).

Recording (``plan_recording``): the simulator steps at 1 kHz and every ``every``-th state
(default 10: 100 Hz) is added on the device, inside the simulation loop, to its sweep's
moment sums (the steady samples chosen from the plan's commanded speed): the host receives each
world's small sums, whatever the plan's length, and the samples of the M baseline worlds only.
With the sweeps side by side (``simulate(parallel=True)``, the default on an accelerator) each
MJX world holds the sums of one sweep. The current noise is drawn on the device from the
world's index in the study, so a world's numbers depend neither on how worlds are batched nor
on the number of devices. Truth draws are per world too: world w is the same for
every N > w. Worlds that fault (following error, overspeed, joint limit: what stops the CPU
simulator and the real arm) are counted and left out of the statistics.

Scale (``run_study``): the worlds run in chunks of contiguous world ids (``study_chunks``,
``chunk_results``: truth, simulation, fits and estimates of one chunk's worlds; never two
plans in a chunk), each finished chunk written to the output folder (``ChunkStore``, resumable)
and the report made from the joined per-world arrays alone (``calibration_report``), so it does
not depend on the chunking. Several processes (``processes``, ``jax.distributed``) each run
their own chunks; process 0 writes the report. The worlds whose samples leave the device are
the scipy sample's and the first ``keep_samples`` (``sampled_worlds``), those saved as
recordings.

Units: SI (rad, A, N m, m, s); COM offsets in each link's own frame; ratio A/(N m); viscous
friction of the truth N m s/rad, the fit's viscous term A s/rad (= ratio x viscous).
"""

import dataclasses
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import BatchTruth, MjxSimulator
from jaxcomp.hardware.truth import model_current_noise
from jaxcomp.identify.batched_fit import BatchFit, compile_fit_batch
from jaxcomp.identify.batched_fit import fit_batch as batch_fit
from jaxcomp.identify.evaluate import random_poses
from jaxcomp.identify.fit_model import FitModel, fit_model
from jaxcomp.identify.named_plans import named_plan, plan_count, random_count
from jaxcomp.identify.plan import CalibrationPlan
from jaxcomp.identify.random_plans import plan_seed
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot, load_robot
from jaxcomp.studies.calibration_estimates import (
    Estimates,
    jax_estimates,
    jax_parameters,
    scipy_estimates,
)
from jaxcomp.studies.calibration_report import concat_chunks, study_report
from jaxcomp.studies.calibration_settings import (
    CalibrationSettings,
    baseline_worlds,
    sampled_worlds,
    world_groups,
)
from jaxcomp.studies.plan_recording import Simulated, fit_input_like, simulate
from jaxcomp.studies.plan_signal import PlanSignal, check_every, plan_signal, start_pose
from jaxcomp.studies.processes import ONE_PROCESS, Processes, together
from jaxcomp.studies.setup import MODEL, simulator
from jaxcomp.studies.study_chunks import (
    CHUNK_WORLDS_PER_DEVICE,
    Chunk,
    ChunkStore,
    chunk_store,
    run_chunks,
    study_chunks,
)
from jaxcomp.studies.truth_draw import draw_truth

__all__ = ["FORMAT", "SAMPLES_DIR", "chunk_results", "run_study"]

#: The ``format`` of study.json.
FORMAT = "jaxcomp-study-calibration"
#: Worlds per batch of the gravity-current errors at most (``gravity_current_error_batch``).
GRAVITY_BATCH = 256
#: The folder of the kept worlds' recordings (``keep_samples``) in the output folder.
SAMPLES_DIR = "samples"


# ----------------------------------------------------------------------------- the plans
class _Group(NamedTuple):
    """The worlds ``rows`` of a study, which record ``plan`` (its ``signal``)."""

    rows: range
    plan: CalibrationPlan
    signal: PlanSignal

    def describe(self, seed: int | None) -> dict:
        """The group's part of the report: worlds [first, stop), plan seed, sweeps, swept
        joints, speeds (deg/s), 1 kHz steps, duration (s)."""
        return {
            "worlds": [self.rows.start, self.rows.stop],
            "seed": seed,
            "sweeps": len(self.plan.sweeps),
            "joints": self.plan.joints,
            "speeds_deg_s": [math.degrees(s.speed) for s in self.plan.sweeps],
            "steps": len(self.signal.q_ref),
            "duration_s": len(self.signal.q_ref) * CONTROL_PERIOD,
        }


def _plan_groups(robot: Robot, settings: CalibrationSettings) -> list[_Group]:
    """The plans' groups of worlds (``world_groups``), each plan made and its signal checked
    against the recording step."""
    plan, seed, every = settings.plan, settings.seed, settings.every
    groups = []
    for g, rows in enumerate(world_groups(settings.worlds, plan_count(plan))):
        the_plan = named_plan(robot, plan, seed=seed, group=g)
        groups.append(_Group(rows, the_plan, plan_signal(the_plan, start_pose(robot))))
        check_every(groups[-1].signal, every)
    return groups


def _plan_report(name: str, seed: int, groups: list[_Group]) -> dict:
    """The report's plan: name, sweeps, 1 kHz steps and duration (s) of the plan (of several
    plans, the means over the worlds), and each group's (``_Group.describe``)."""
    random = random_count(name) is not None
    per_group = [gr.describe(plan_seed(seed, g) if random else None) for g, gr in enumerate(groups)]
    share = np.array([len(gr.rows) for gr in groups]) / sum(len(gr.rows) for gr in groups)
    keys = ("sweeps", "steps", "duration_s")
    if len(groups) == 1:
        return {"name": name} | {k: per_group[0][k] for k in keys} | {"groups": per_group}
    mean = {k: float(share @ [d[k] for d in per_group]) for k in keys}
    return {"name": name} | mean | {"groups": per_group}


# ----------------------------------------------------------------------------- the study set up
class _Study(NamedTuple):
    """What every chunk of a study shares: its settings, robot, fit model, plan groups,
    simulator, poses of the gravity error, the worlds that send their samples to the host
    (``sampled``: the scipy sample's and the first ``keep_samples``) and the effective MJX
    batch and sweep layout."""

    settings: CalibrationSettings
    robot: Robot
    model: FitModel
    groups: list[_Group]
    sim: MjxSimulator
    poses: np.ndarray
    sample: np.ndarray
    sampled: np.ndarray
    world_batch: int
    fit_batch: int
    parallel: bool
    chunk_worlds: int

    def run_settings(self) -> dict:
        """What a resumed study must share with the run whose chunks it keeps (JSON)."""
        s = self.settings
        return {
            "model": self.robot.name,
            "joints": list(self.robot.joint_names),
            "worlds": s.worlds,
            "seed": s.seed,
            "plan": s.plan,
            "plans": [gr.plan.to_dict() for gr in self.groups],
            "every": s.every,
            "spread": dataclasses.asdict(s.spread),
            "baseline_sample": s.baseline_sample,
            "keep_samples": s.keep_samples,
            "poses": s.poses,
            "com_prior": s.fit_com_prior(),
            "parallel_sweeps": self.parallel,
            "chunk_worlds": self.chunk_worlds,
        }


def _check_baseline_fit(settings: CalibrationSettings) -> None:
    """InputError when the study asks for scipy fits and pinocchio is missing (now, not at the
    end)."""
    if settings.baseline_sample:
        try:
            import pinocchio  # noqa: F401  (the scipy fit needs it)
        except ImportError:
            raise InputError(
                "--baseline-sample needs pinocchio (pip install pin); use --baseline-sample 0 "
                "to skip the scipy fit"
            ) from None


def _setup(settings: CalibrationSettings, robot: Robot | None) -> _Study:
    """The study's shared parts (``_Study``), plans checked and the simulator made."""
    _check_baseline_fit(settings)
    robot = load_robot(MODEL) if robot is None else robot
    groups = _plan_groups(robot, settings)
    sim = simulator(settings.devices, robot)
    model = fit_model(robot, settings.fit_com_prior())
    backend = jax.default_backend()
    chunk = min(settings.chunk_worlds or CHUNK_WORLDS_PER_DEVICE * sim.mesh.size, settings.worlds)
    sample = baseline_worlds([gr.rows for gr in groups], settings.baseline_sample)
    return _Study(
        settings,
        robot,
        model,
        groups,
        sim,
        random_poses(robot, settings.poses, seed=settings.seed),
        sample,
        sampled_worlds([gr.rows for gr in groups], sample, settings.keep_samples),
        settings.world_batch or (chunk if backend != "cpu" else sim.mesh.size),
        max(2, settings.fit_batch or chunk),  # one batch shape: a world's fit the same in any
        backend != "cpu" if settings.parallel is None else bool(settings.parallel),
        chunk,
    )


# ----------------------------------------------------------------------------- one chunk
def chunk_results(
    study: _Study, chunk: Chunk, progress: bool = False
) -> tuple[dict[str, dict[str, np.ndarray]], dict[int, Recording]]:
    """One chunk of ``study``: its worlds drawn, simulated and reduced, fitted and compared.

    A world's numbers do not depend on the chunk it is in (its truth, noise and fit are its
    own; every fit batch has ``fit_batch`` worlds).

    Args:
        study: the study set up (``run_study``).
        chunk: the chunk, its global world ids all of one plan group.
        progress: show progress bars.

    Returns:
        ({"world": rows of ``WORLD_KEYS``, "scipy": the sample's worlds in the chunk
        (``SCIPY_KEYS``), "timing": s and the world-steps simulated}, {world: recording} of
        the first ``keep_samples`` worlds in it).
    """
    s, rows = study.settings, chunk.rows
    truth = draw_truth(study.robot, len(rows), s.seed, s.spread, first=rows.start)
    ids = np.arange(rows.start, rows.stop)
    recorded = int(np.isin(ids, study.sampled).sum())  # a prefix of the chunk
    simulated, fits, fit_timing = _simulate_and_fit(study, chunk, truth, recorded, progress)
    jax_est, evaluate_s = _compare(study, truth, simulated, fits)
    local = np.flatnonzero(np.isin(ids, study.sample))
    scipy_est, failed, scipy_s = _scipy_fits(study, truth, local, simulated.recordings, jax_est,
                                             progress)  # fmt: skip
    timing = dict(simulated.timing) | fit_timing | {
        "evaluate": evaluate_s, "fit_scipy": scipy_s,
        "world_steps": float(simulated.world_steps)}  # fmt: skip
    world = _world_rows(chunk, simulated, fits, jax_est)
    scipy = _scipy_rows(ids[local], scipy_est, failed, rows.start)
    kept = {int(w): simulated.recordings[i] for i, w in enumerate(ids[:recorded])
            if w < s.keep_samples}  # fmt: skip
    return {"world": world, "scipy": scipy, "timing": timing}, kept


def _gravity_batch(study: _Study) -> int:
    """Worlds per batch of the gravity-current errors: one shape in every chunk."""
    return min(study.fit_batch, GRAVITY_BATCH)


def _simulate_and_fit(
    study: _Study, chunk: Chunk, truth: BatchTruth, recorded: int, progress: bool
) -> tuple[Simulated, BatchFit, dict[str, float]]:
    """The chunk's plan recorded and reduced in its worlds (``simulate``; the first
    ``recorded`` keep their samples) while the fit compiles beside them, then the joint fits:
    (simulated, fits, the fits' timing s)."""
    gr, rows = study.groups[chunk.group], chunk.rows
    bar = tqdm(total=len(rows) * len(gr.signal.q_ref), unit="step", unit_scale=True,
               desc=f"MJX, worlds {rows.start}-{rows.stop - 1}", disable=not progress,
               leave=False)  # fmt: skip
    with ThreadPoolExecutor(1) as pool:
        compiling: list[Future] = []

        def stepped(k: int) -> None:  # the worlds step (their program is compiled): the
            if not compiling:  # fits compile beside them
                compiling.append(pool.submit(_compile_fit, study, gr.signal))
            bar.update(k)

        simulated = simulate(
            study.sim, truth, gr.signal, seed=study.settings.seed, every=study.settings.every,
            world_batch=study.world_batch, keep=rows.start + recorded,  # the chunk's first
            progress=stepped, parallel=study.parallel, offset=rows.start,
        )  # fmt: skip
        bar.close()
        t0 = time.perf_counter()
        beside = compiling[0].result() if compiling else 0.0  # s compiling, off the path
        waited = time.perf_counter() - t0
    t0 = time.perf_counter()
    fits = _fit(study, simulated.moments, simulated.transfers, len(rows))
    timing = {
        "fit_jax": waited + time.perf_counter() - t0,
        "fit_jax_compile": waited + fits.compile_seconds,  # the part not beside the worlds
        "fit_jax_compile_aside": beside,
        "fit_jax_run": fits.seconds,
    }
    return simulated, fits, timing


def _compile_fit(study: _Study, signal: PlanSignal) -> float:
    """``_fit``'s program compiled for ``signal``'s moments; the seconds it took (0 when
    compiled before)."""
    with jax.default_device(jax.local_devices(backend="cpu")[0]):  # not behind the worlds
        like, bins = fit_input_like(study.sim, signal, study.settings.every)
    return compile_fit_batch(study.model, like, study.fit_batch, study.sim.mesh, bins)


def _fit(study: _Study, moments, transfers, count: int) -> BatchFit:
    """The joint fits of a chunk's ``count`` worlds (their sweep moments and transfer bins),
    ``study.fit_batch`` at a time (a chunk of fewer worlds padded with copies of its last: one
    compiled batch for every chunk)."""
    pad = max(study.fit_batch - count, 0)
    if pad:
        idx = np.minimum(np.arange(count + pad), count - 1)
        moments, transfers = jax.tree.map(lambda a: np.asarray(a)[idx], (moments, transfers))
    fits = batch_fit(
        study.model, moments, transfers=transfers, batch=study.fit_batch, mesh=study.sim.mesh
    )
    if not pad:
        return fits
    return fits._replace(
        solution=jax.tree.map(lambda a: np.asarray(a)[:count], fits.solution),
        coef=fits.coef[:count],
        std=fits.std[:count],
    )


def _compare(
    study: _Study, truth: BatchTruth, simulated: Simulated, fits: BatchFit
) -> tuple[Estimates, float]:
    """The joint fits' estimates against the truth (``jax_estimates``) and the s it took."""
    t0 = time.perf_counter()
    jax_est = jax_estimates(study.robot, study.model, truth, simulated, fits, study.poses,
                            _gravity_batch(study))  # fmt: skip
    return jax_est, time.perf_counter() - t0


def _scipy_fits(
    study: _Study,
    truth: BatchTruth,
    local: np.ndarray,
    recordings: list[Recording],
    jax_est: Estimates,
    progress: bool,
) -> tuple[Estimates, list[dict], float]:
    """The paper's scipy fit of the chunk's sample worlds ``local`` (indices into the chunk)
    from their ``recordings`` (``scipy_estimates``): (estimates, failed fits, s)."""
    t0 = time.perf_counter()
    bar = tqdm(total=len(local), unit="fit", desc="scipy fits", leave=False,
               disable=not progress or not len(local))  # fmt: skip
    try:
        scipy_est, failed = scipy_estimates(
            study.robot, truth, local, [recordings[i] for i in local], jax_est, study.poses,
            progress=bar.update, batch=_gravity_batch(study),
        )  # fmt: skip
    finally:
        bar.close()
    return scipy_est, failed, time.perf_counter() - t0


def _world_rows(
    chunk: Chunk, simulated: Simulated, fits: BatchFit, jax_est: Estimates
) -> dict[str, np.ndarray]:
    """The chunk's rows of the per-world arrays (``WORLD_KEYS``)."""
    sol = fits.solution
    return {
        "plan_group": np.full(len(chunk.rows), chunk.group),
        "truth": jax_est.truth,
        "jax_estimate": jax_est.estimate,
        "jax_std": jax_est.std,
        "jax_identified": jax_est.identified,
        "jax_converged": np.asarray(sol.converged),
        "jax_ok": jax_est.ok,
        "jax_noise_estimate": np.asarray(sol.sigma),
        "jax_gravity_current_error": jax_est.gravity,
        "jax_gravity_current_error_pooled": jax_est.gravity_pooled,
        "swept": jax_est.swept,
        "fault_step": simulated.fault_step,
    }


def _scipy_rows(
    worlds: np.ndarray, scipy_est: Estimates, failed: list[dict], first: int
) -> dict[str, np.ndarray]:
    """The chunk's sample ``worlds`` (global ids) in the scipy arrays (``SCIPY_KEYS``); the
    failed fits' worlds are chunk indices, ``first`` the chunk's first world."""
    return {
        "scipy_worlds": worlds,
        "scipy_estimate": scipy_est.estimate,
        "scipy_std": scipy_est.std,
        "scipy_gravity_current_error": scipy_est.gravity,
        "scipy_gravity_current_error_pooled": scipy_est.gravity_pooled,
        "scipy_failed_world": np.array([f["world"] + first for f in failed], np.int64),
        "scipy_failed_error": np.array([f["error"] for f in failed], str),
    }


# ----------------------------------------------------------------------------- the study
def run_study(
    settings: CalibrationSettings,
    *,
    progress: bool = True,
    robot: Robot | None = None,
    folder: Path | None = None,
    resume: bool = False,
    processes: Processes = ONE_PROCESS,
) -> tuple[dict, dict] | None:
    """The whole study of ``settings``: set up, then each chunk simulated, reduced and fitted
    (``chunk_results``), then the report; see the module docstring.

    The worlds run in chunks (``study_chunks``: ``chunk_worlds`` contiguous worlds of one
    plan group each); the report is made from the chunks' joined per-world arrays
    (``calibration_report``), whatever the chunking. With ``plan`` "random:K" the worlds are
    cut into K contiguous groups (``world_groups``), group g recording its own random plan
    (seed ``plan_seed(seed, g)``); the truths are drawn per world (world w is the same for
    any K).

    Args:
        settings: what the study runs.
        progress: show progress bars.
        robot: the ``MODEL`` robot to study, whose simulator (``setup.simulator``) and
            compiled programs it keeps (None: freshly loaded).
        folder: the study's output folder, created and locked by the caller: each finished
            chunk is written to ``folder``/chunks (``ChunkStore``), the samples of the first
            ``keep_samples`` worlds to ``folder``/samples (None: chunks in memory).
        resume: keep the chunks in ``folder`` of an interrupted run of the same settings.
        processes: this process among several (``processes.start_processes``), each running
            its own chunks (``Processes.mine``) into the shared ``folder``.

    Returns:
        (the report for study.json, the per-world arrays for worlds.npz) on process 0; None
        on the others.

    Raises:
        InputError: ``keep_samples``, ``resume`` or several processes without a folder, a
            plan the recording step does not fit, or a scipy sample without pinocchio.
    """
    t_all = time.perf_counter()
    if folder is None and (settings.keep_samples or processes.count > 1 or resume):
        raise InputError("--keep-samples, --resume and --distributed need an output folder")
    store, settings = chunk_store(folder, settings, resume)
    study = together(processes, lambda: _setup(settings, robot), "to set the study up")
    setup_s = time.perf_counter() - t_all
    parts = _run_chunks(study, store, folder, resume, processes, progress)
    if parts is None:
        return None
    return _report(study, parts, setup_s, t_all, processes)


def _run_chunks(
    study: _Study,
    store: ChunkStore | None,
    folder: Path | None,
    resume: bool,
    processes: Processes,
    progress: bool,
) -> list[dict] | None:
    """Every chunk's parts in order (``run_chunks`` over ``chunk_results``), the kept
    worlds' recordings saved in ``folder``/samples; None on processes other than 0."""

    def compute(chunk: Chunk) -> dict:
        parts, recordings = chunk_results(study, chunk, progress)
        for w, rec in recordings.items():
            rec.save(Path(folder) / SAMPLES_DIR / f"world_{w:05d}.npz")
        return parts

    chunks = study_chunks([gr.rows for gr in study.groups], study.chunk_worlds)
    return run_chunks(processes, chunks, store, compute, settings=study.run_settings(),
                      resume=resume, progress=progress)  # fmt: skip


def _report(
    study: _Study, parts: list[dict], setup_s: float, t_all: float, processes: Processes
) -> tuple[dict, dict]:
    """(report, per-world arrays) from every chunk's ``parts``; ``setup_s`` the set-up's s,
    ``t_all`` the study's start (``time.perf_counter``)."""
    t0 = time.perf_counter()
    arrays, timing = concat_chunks(parts, *jax_parameters(study.model))
    world_steps = timing.pop("world_steps")
    timing = {"setup": setup_s} | timing | {"report": time.perf_counter() - t0}
    timing["total"] = time.perf_counter() - t_all
    return study_report(arrays, _describe(study, timing, world_steps, processes)), arrays


def _describe(study: _Study, timing: dict, world_steps: float, processes: Processes) -> dict:
    """The report's description of the run (``study_report``'s ``run``)."""
    s, sim = study.settings, study.sim
    noise = model_current_noise(study.robot) if s.spread.noise is None else s.spread.noise
    return {
        "format": FORMAT,
        "version": 1,
        "model": study.robot.name,
        "seed": s.seed,
        "worlds": s.worlds,
        "plan": _plan_report(s.plan, s.seed, study.groups),
        "record_every": s.every,
        "record_rate_hz": 1.0 / (CONTROL_PERIOD * s.every),
        "truth": dataclasses.asdict(s.spread) | {"noise": float(noise)},
        "fit_com_prior": s.fit_com_prior(),
        "backend": jax.default_backend(),
        "devices": [str(d) for d in sim.mesh.devices.flat],
        "processes": processes.count,
        "chunk_worlds": study.chunk_worlds,
        "world_batch": study.world_batch,
        "parallel_sweeps": study.parallel,
        "timing_s": timing,
        "world_steps": world_steps,
    }
