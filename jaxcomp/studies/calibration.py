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

The stages, each in its own module and composed here (``run_study``): ``truth_draw``,
``plan_signal``, ``plan_recording`` (simulate and reduce), ``batched_fit.fit_batch`` and
``baseline`` (fit), ``calibration_estimates`` and ``calibration_statistics`` (compare),
``calibration_figures`` and ``write_outputs`` (report).

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
import os
import shutil
import tempfile
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.files import writing
from jaxcomp.hardware.mjx import MjxSimulator
from jaxcomp.hardware.truth import model_current_noise
from jaxcomp.identify.batched_fit import BatchFit, compile_fit_batch
from jaxcomp.identify.batched_fit import fit_batch as batch_fit
from jaxcomp.identify.evaluate import random_poses
from jaxcomp.identify.fit_model import FitModel, fit_model
from jaxcomp.identify.named_plans import (
    check_plan_name,
    named_plan,
    plan_count,
    random_count,
    short_plan,
)
from jaxcomp.identify.plan import CalibrationPlan
from jaxcomp.identify.random_plans import plan_seed
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import json_ready, write_json_atomic
from jaxcomp.studies.calibration_estimates import (
    jax_estimates,
    jax_parameters,
    scipy_estimates,
)
from jaxcomp.studies.calibration_figures import plot_coverage, plot_errors
from jaxcomp.studies.calibration_report import concat_chunks, study_report
from jaxcomp.studies.plan_recording import fit_input_like, simulate
from jaxcomp.studies.plan_signal import (
    PlanSignal,
    check_every,
    plan_segments,
    plan_signal,
    start_pose,
)
from jaxcomp.studies.processes import ONE_PROCESS, Processes, together
from jaxcomp.studies.setup import MODEL, simulator
from jaxcomp.studies.study_chunks import (
    CHUNK_WORLDS_PER_DEVICE,
    CHUNKS_DIR,
    Chunk,
    ChunkStore,
    into_folder,
    run_chunks,
    study_chunks,
)
from jaxcomp.studies.truth_draw import TruthSpread, draw_truth

__all__ = [  # the study, and the stages it composes
    "FIGURES",
    "FORMAT",
    "STUDY_FILE",
    "WORLDS_FILE",
    "CalibrationSettings",
    "StudyOutputs",
    "TruthSpread",
    "draw_truth",
    "named_plan",
    "plan_segments",
    "plan_signal",
    "plot_coverage",
    "plot_errors",
    "run_study",
    "sampled_worlds",
    "short_plan",
    "simulate",
    "simulator",
    "start_pose",
    "study_into",
    "summary",
    "world_groups",
    "write_outputs",
]

STUDY_FILE = "study.json"
WORLDS_FILE = "worlds.npz"
FIGURES = ("errors.png", "coverage.png")
FORMAT = "jaxcomp-study-calibration"
#: m: the least COM prior of a study (its truths may have no COM offset at all).
MIN_COM_PRIOR = 1e-4
#: Worlds per batch of the gravity-current errors at most (``gravity_current_error_batch``).
GRAVITY_BATCH = 256
#: The folder of the kept worlds' recordings (``keep_samples``) in the output folder.
SAMPLES_DIR = "samples"


# ----------------------------------------------------------------------------- the study
@dataclasses.dataclass(frozen=True)
class CalibrationSettings:
    """What a calibration study runs, checked when made (InputError).

    Attributes:
        worlds: simulated true robots N (>= 1). seed: seed of every draw.
        plan: "default" (the paper's ~230 s of sweeps), "short", "random" or "random:K" (K
            random plans, each recorded by a group of the worlds: ``run_study``) or a plan
            JSON file.
        every: record every k-th 1 kHz state (10: 100 Hz) for the fits.
        spread: how the true robots differ from the nominal model (``TruthSpread``).
        baseline_sample: also fit M worlds with the paper's scipy fit (0: none), the first
            of each plan's group (``baseline_worlds``).
        devices: shard over the first K devices (None: all).
        world_batch: worlds per MJX run (None: all on an accelerator, one per device on the
            CPU, where MJX steps a batch of worlds slower than one world at a time).
        fit_batch: fits per vmapped batch (None: all).
        poses: random poses of the gravity-current error (drawn from ``seed``).
        parallel: the plan's sweeps side by side (``simulate``; None: on an accelerator,
            where a few thousand worlds leave it idle; on the CPU, where steps cost in
            proportion to the worlds, the sweeps run in turn).
        com_prior: m, the JAX fit's COM prior on every link (None: the spread the truths are
            drawn from, ``study_com_prior``: the fit is told the population it is tested on;
            ``jaxcomp fit`` has the model's default, ``fit_model``).
        chunk_worlds: worlds per chunk (``study_chunks``; None: ``CHUNK_WORLDS_PER_DEVICE`` per
            device, the whole study when it has fewer; a resumed study keeps its own).
        keep_samples: the recorded samples of the first K worlds are saved (``run_study``).
    """

    worlds: int
    seed: int = 0
    plan: str = "default"
    every: int = 10
    spread: TruthSpread = TruthSpread()  # frozen: one shared default is safe
    baseline_sample: int = 16
    devices: int | None = None
    world_batch: int | None = None
    fit_batch: int | None = None
    poses: int = 1000
    parallel: bool | None = None
    com_prior: float | None = None
    chunk_worlds: int | None = None
    keep_samples: int = 0

    def __post_init__(self) -> None:
        check_plan_name(self.plan)
        checks = {
            "--worlds": (self.worlds, 1),
            "--every": (self.every, 1),
            "--baseline-sample": (self.baseline_sample, 0),
            "--poses": (self.poses, 1),
            "--world-batch": (self.world_batch, 1),
            "--fit-batch": (self.fit_batch, 1),
            "--chunk-worlds": (self.chunk_worlds, 1),
            "--keep-samples": (self.keep_samples, 0),
        }
        for name, (value, low) in checks.items():
            if value is not None and (
                isinstance(value, bool) or int(value) != value or value < low
            ):
                raise InputError(f"{name} must be an integer >= {low}, got {value}")
        if plan_count(self.plan) > self.worlds:
            raise InputError(
                f"--plan {self.plan} needs at least as many --worlds ({self.worlds}) as plans"
            )


def study_com_prior(spread: TruthSpread) -> float:
    """m: the standard deviation per axis of the true COM offsets, U(-c, c): c / sqrt(3) (at
    least ``MIN_COM_PRIOR``)."""
    return max(float(spread.com_offset) / math.sqrt(3.0), MIN_COM_PRIOR)


def world_groups(worlds: int, count: int) -> list[range]:
    """The worlds 0..``worlds`` - 1 cut into ``count`` contiguous groups, as even as possible
    (the first ``worlds % count`` one world longer)."""
    size, extra = divmod(worlds, count)
    edges = np.cumsum([0] + [size + (g < extra) for g in range(count)])
    return [range(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def baseline_worlds(groups: list[range], sample: int) -> np.ndarray:
    """The worlds of the scipy sample: ``sample`` of them (at most all), cut over the plans'
    ``groups`` (``world_groups``) as ``world_groups`` cuts the worlds, the first ones of each
    group, so that every plan is in the sample."""
    shares = world_groups(min(sample, groups[-1].stop), len(groups))
    return np.concatenate(
        [
            np.arange(rows.start, rows.start + len(share))
            for rows, share in zip(groups, shares, strict=True)
        ]
    ).astype(np.int64)


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
            "com_prior": s.com_prior or study_com_prior(s.spread),
            "parallel_sweeps": self.parallel,
            "chunk_worlds": self.chunk_worlds,
        }


def sampled_worlds(groups: list[range], sample: np.ndarray, keep_samples: int) -> np.ndarray:
    """The worlds whose samples come to the host: the scipy ``sample`` (the first worlds of
    each plan group, ``baseline_worlds``) and the first ``keep_samples`` worlds, ascending.
    In each group they are its first worlds (a prefix), as ``simulate(keep=)`` takes them."""
    first = np.arange(min(keep_samples, groups[-1].stop))
    return np.union1d(sample, first).astype(np.int64)


def _setup(settings: CalibrationSettings, robot: Robot | None) -> _Study:
    """The study's shared parts (``_Study``), plans checked and the simulator made."""
    if settings.baseline_sample:
        try:
            import pinocchio  # noqa: F401  (the scipy fit needs it: fail now, not at the end)
        except ImportError:
            raise InputError(
                "--baseline-sample needs pinocchio (pip install pin); use --baseline-sample 0 "
                "to skip the scipy fit"
            ) from None
    robot = load_robot(MODEL) if robot is None else robot
    plan, seed, every = settings.plan, settings.seed, settings.every
    groups = []
    for g, rows in enumerate(world_groups(settings.worlds, plan_count(plan))):
        the_plan = named_plan(robot, plan, seed=seed, group=g)
        groups.append(_Group(rows, the_plan, plan_signal(the_plan, start_pose(robot))))
        check_every(groups[-1].signal, every)
    sim = simulator(settings.devices, robot)
    model = fit_model(robot, settings.com_prior or study_com_prior(settings.spread))
    backend = jax.default_backend()
    chunk = min(settings.chunk_worlds or CHUNK_WORLDS_PER_DEVICE * sim.mesh.size, settings.worlds)
    sample = baseline_worlds([gr.rows for gr in groups], settings.baseline_sample)
    return _Study(
        settings,
        robot,
        model,
        groups,
        sim,
        random_poses(robot, settings.poses, seed=seed),
        sample,
        sampled_worlds([gr.rows for gr in groups], sample, settings.keep_samples),
        settings.world_batch or (chunk if backend != "cpu" else sim.mesh.size),
        max(2, settings.fit_batch or chunk),  # one batch shape: a world's fit the same in any
        backend != "cpu" if settings.parallel is None else bool(settings.parallel),
        chunk,
    )


def chunk_results(
    study: _Study, chunk: Chunk, progress: bool = False
) -> tuple[dict[str, dict[str, np.ndarray]], dict[int, Recording]]:
    """One chunk of ``study``: its worlds drawn, simulated and fitted. ({"world": rows of
    ``WORLD_KEYS``, "scipy": the sample's worlds in the chunk (``SCIPY_KEYS``), "timing": s},
    {world: recording} of the first ``keep_samples`` worlds in it). A world's numbers do not
    depend on the chunk it is in (its truth, noise and fit are its own; every fit batch
    has ``fit_batch`` worlds)."""
    s, gr, rows = study.settings, study.groups[chunk.group], chunk.rows
    first, count = rows.start, len(rows)
    truth = draw_truth(study.robot, count, s.seed, s.spread, first=first)
    ids = np.arange(first, rows.stop)
    recorded = int(np.isin(ids, study.sampled).sum())  # a prefix of the chunk
    bar = tqdm(
        total=count * len(gr.signal.q_ref),
        unit="step",
        unit_scale=True,
        desc=f"MJX, worlds {first}-{rows.stop - 1}",
        disable=not progress,
        leave=False,
    )
    with ThreadPoolExecutor(1) as pool:
        compiling: list[Future] = []

        def stepped(k: int) -> None:  # the worlds step (their program is compiled): the
            if not compiling:  # fits compile beside them
                compiling.append(pool.submit(_compile_fit, study, gr.signal))
            bar.update(k)

        simulated = simulate(
            study.sim,
            truth,
            gr.signal,
            seed=s.seed,
            every=s.every,
            world_batch=study.world_batch,
            keep=first + recorded,  # global index: the chunk's first worlds
            progress=stepped,
            parallel=study.parallel,
            offset=first,
        )
        bar.close()
        t0 = time.perf_counter()
        beside = compiling[0].result() if compiling else 0.0  # s compiling, off the path
        waited = time.perf_counter() - t0
    timing = dict(simulated.timing)
    t0 = time.perf_counter()
    fits = _fit(study, simulated.moments, simulated.transfers, count)
    timing["fit_jax"] = waited + time.perf_counter() - t0
    timing["fit_jax_compile"] = waited + fits.compile_seconds  # the part not beside the worlds
    timing["fit_jax_compile_aside"] = beside
    timing["fit_jax_run"] = fits.seconds
    t0 = time.perf_counter()
    gravity_batch = min(study.fit_batch, GRAVITY_BATCH)  # one shape in every chunk
    jax_est = jax_estimates(
        study.robot, study.model, truth, simulated, fits, study.poses, gravity_batch
    )
    timing["evaluate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    local = np.flatnonzero(np.isin(ids, study.sample))
    bar = tqdm(total=len(local), unit="fit", desc="scipy fits", leave=False,
               disable=not progress or not len(local))  # fmt: skip
    recordings = simulated.recordings
    scipy_est, failed = scipy_estimates(
        study.robot, truth, local, [recordings[i] for i in local], jax_est, study.poses,
        progress=bar.update, batch=gravity_batch,
    )  # fmt: skip
    bar.close()
    timing["fit_scipy"] = time.perf_counter() - t0
    timing["world_steps"] = float(simulated.world_steps)
    sol = fits.solution
    world = {
        "plan_group": np.full(count, chunk.group),
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
    scipy = {
        "scipy_worlds": ids[local],
        "scipy_estimate": scipy_est.estimate,
        "scipy_std": scipy_est.std,
        "scipy_gravity_current_error": scipy_est.gravity,
        "scipy_gravity_current_error_pooled": scipy_est.gravity_pooled,
        "scipy_failed_world": np.array([f["world"] + first for f in failed], np.int64),
        "scipy_failed_error": np.array([f["error"] for f in failed], str),
    }
    kept = {int(w): recordings[i] for i, w in enumerate(ids[:recorded]) if w < s.keep_samples}
    return {"world": world, "scipy": scipy, "timing": timing}, kept


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


def run_study(
    settings: CalibrationSettings,
    *,
    progress: bool = True,
    robot: Robot | None = None,
    folder: Path | None = None,
    resume: bool = False,
    processes: Processes = ONE_PROCESS,
) -> tuple[dict, dict] | None:
    """The whole study of ``settings``: (report for study.json, per-world arrays for
    worlds.npz); see the module docstring. ``progress``: show progress bars; ``robot``: the
    ``MODEL`` robot to study, whose simulator (``setup.simulator``) and compiled programs it
    keeps (default: freshly loaded).

    The worlds run in chunks (``study_chunks``: ``chunk_worlds`` contiguous worlds of one
    plan group each, ``chunk_results``); the report is made from the chunks' joined per-world
    arrays (``calibration_report``), whatever the chunking. With a ``folder`` (the study's
    output folder, created and locked by the caller), each finished chunk is written to
    ``folder``/chunks (``ChunkStore``) and ``resume`` keeps those of an interrupted run of the
    same settings; the samples of the first ``keep_samples`` worlds go to ``folder``/samples.
    With several ``processes`` (``processes.start_processes``) each runs its own chunks
    (``Processes.mine``) into the shared ``folder`` and process 0 alone returns the report
    (the others None).

    With ``plan`` "random:K" the worlds are cut into K contiguous groups (``world_groups``),
    group g recording its own random plan (seed ``plan_seed(seed, g)``); the truths are drawn
    per world (world w is the same for any K).
    """
    t_all = time.perf_counter()
    if folder is None and (settings.keep_samples or processes.count > 1 or resume):
        raise InputError("--keep-samples, --resume and --distributed need an output folder")
    store = None if folder is None else ChunkStore(Path(folder) / CHUNKS_DIR)
    if resume and store is not None and settings.chunk_worlds is None:  # on any device count
        settings = dataclasses.replace(settings, chunk_worlds=store.earlier("chunk_worlds"))
    study = together(processes, lambda: _setup(settings, robot), "to set the study up")
    chunks = study_chunks([gr.rows for gr in study.groups], study.chunk_worlds)
    setup_s = time.perf_counter() - t_all

    def compute(chunk: Chunk) -> dict:
        parts, recordings = chunk_results(study, chunk, progress)
        for w, rec in recordings.items():
            rec.save(Path(folder) / SAMPLES_DIR / f"world_{w:05d}.npz")
        return parts

    parts = run_chunks(processes, chunks, store, compute, settings=study.run_settings(),
                       resume=resume, progress=progress)  # fmt: skip
    if parts is None:
        return None
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
        "fit_com_prior": s.com_prior or study_com_prior(s.spread),
        "backend": jax.default_backend(),
        "devices": [str(d) for d in sim.mesh.devices.flat],
        "processes": processes.count,
        "chunk_worlds": study.chunk_worlds,
        "world_batch": study.world_batch,
        "parallel_sweeps": study.parallel,
        "timing_s": timing,
        "world_steps": world_steps,
    }


# ----------------------------------------------------------------------------- outputs
def write_outputs(out: Path, report: dict, arrays: dict) -> list[Path]:
    """Write the figures, ``worlds.npz`` and ``study.json`` (last) into ``out``.

    Everything is written to a staging folder inside ``out`` first and moved in by
    ``os.replace`` only once all of it is written: an error leaves ``out`` as it was.
    """
    with writing(out):
        stage = Path(tempfile.mkdtemp(prefix=".study-calibration.", dir=out))
    try:
        plot_errors(report, arrays, stage / FIGURES[0])
        plot_coverage(report, arrays, stage / FIGURES[1])
        with writing(out / WORLDS_FILE):
            np.savez_compressed(stage / WORLDS_FILE, **arrays)
        with writing(out / STUDY_FILE):
            write_json_atomic(stage / STUDY_FILE, json_ready(report))
        names = [*FIGURES, WORLDS_FILE, STUDY_FILE]
        with writing(out):
            for name in names:
                os.replace(stage / name, out / name)
        return [out / name for name in names]
    finally:
        shutil.rmtree(stage, ignore_errors=True)


# ----------------------------------------------------------------------------- one call
class StudyOutputs(NamedTuple):
    """What ``study_into`` made: the report (study.json), the per-world arrays (worlds.npz)
    and the files written."""

    report: dict
    arrays: dict
    paths: list[Path]


def study_into(
    out: Path,
    settings: CalibrationSettings,
    *,
    progress: bool = True,
    robot: Robot | None = None,
    resume: bool = False,
    processes: Processes = ONE_PROCESS,
) -> StudyOutputs | None:
    """``run_study`` and ``write_outputs`` into the folder ``out``, created and locked first
    (``files.output_folder``: FileError before minutes of simulation); on error nothing is
    written but the finished chunks (``run_study``: ``resume`` keeps them), and a folder it
    created and left empty is removed. With several ``processes``, process 0 holds the folder
    and writes the report; the others write their chunks into it and return None."""

    def run(folder: Path) -> tuple[dict, dict] | None:
        shown = progress and processes.index == 0
        return run_study(settings, progress=shown, robot=robot, folder=folder, resume=resume,
                         processes=processes)  # fmt: skip

    def write(folder: Path, result: tuple[dict, dict]) -> StudyOutputs:
        report, arrays = result
        return StudyOutputs(report, arrays, write_outputs(folder, report, arrays))

    return into_folder(out, processes, run, write)


def summary(report: dict) -> str:
    """A few lines for people: per-joint errors of both fits, coverage, run times."""
    n = sum(k.startswith("ratio[") for k in report["jax"]["parameters"])
    jp, sp = report["jax"]["parameters"], report["scipy"]["parameters"]
    jg, sg = report["jax"]["gravity_current_error"], report["scipy"]["gravity_current_error"]

    def pct(v: float | None) -> str:
        return "-" if v is None or not math.isfinite(v) else f"{100 * v:.2f}%"

    head = f"{'joint':<6}" + "".join(
        f"{h:>14}"
        for h in (
            "ratio jax",
            "ratio scipy",
            "friction jax",
            "fric. scipy",
            "g-cur jax",
            "g-cur scipy",
        )
    )
    plan = report["plan"]
    plans = len(plan["groups"])
    length = (
        f"{plan['duration_s']:.0f} s"
        if plans == 1
        else f"{plans} plans, mean {plan['duration_s']:.0f} s"
    )
    lines = [
        f"{report['worlds']} worlds, plan {plan['name']} ({length}), "
        f"{report['backend']} x{len(report['devices'])}; "
        f"RMS relative errors (scipy on {report['scipy']['worlds']} of them, "
        f"{report['scipy'].get('plans', 1)} plans), "
        "gravity current: median over worlds",
        head,
    ]
    for j in range(n):
        r, f = f"ratio[{j}]", f"friction[{j}]"
        row = [
            jp[r]["relative_rmse"],
            sp.get(r, {}).get("relative_rmse"),
            jp[f]["relative_rmse"],
            sp.get(f, {}).get("relative_rmse"),
            jg["median"][j] if jg["median"] else None,
            sg["median"][j] if sg["median"] else None,
        ]
        lines.append(f"{j:<6}" + "".join(f"{pct(v):>14}" for v in row))
    pooled = report["jax"]["on_scipy_worlds"]["pooled_gravity_current_error"]
    if pooled["worlds"]:
        lines.append(
            f"gravity current pooled over the swept joints, {pooled['worlds']} worlds both fits "
            f"have: JAX worse than scipy in {pct(pooled['jax_worse_fraction'])}; median JAX "
            f"{pct(pooled['jax_median'])}, scipy {pct(pooled['scipy_median'])}"
        )
    worst = report["jax"]["largest_identified_ratio_error"]
    if worst["count"]:
        lines.append(
            f"largest ratio error the JAX fit reports identified ({worst['count']} ratios): "
            f"{pct(worst['max_abs_relative'])} (world {worst['world']}, joint {worst['joint']})"
        )
    else:
        lines.append(
            "no ratio reported identified (in one mounting each rests partly on the COM prior; "
            "a recording with a known payload identifies them)"
        )
    cov, worst = report["coverage"]["jax"]["identified"], report["coverage"]["jax"]["worst"]
    t = report["timing_s"]
    lines.append(
        f"coverage of +-1.96 std (JAX, {cov['count']} determined estimates): "
        f"{pct(cov['coverage_95'])}; z std {cov['z_std']:.2f}"
        + (
            f"; lowest of one parameter: {worst['parameter']} {pct(worst['coverage_95'])} "
            f"of {worst['count']}"
            if worst
            else ""
        )
    )
    if report["faulted_worlds"]:
        lines.append(
            f"{report['faulted_worlds']} of {report['worlds']} worlds faulted before their plan "
            "ended (following error, overspeed, a limit: a true robot that cannot follow it) "
            "and are left out; per plan: " + ", ".join(str(c) for c in report["faulted_by_plan"])
        )
    lines.append(
        f"time: simulate {t['simulate']:.1f} s (compile {t['simulate_compile']:.1f} s, "
        f"{report['throughput']['world_steps_per_s']:.3g} world-steps/s), JAX fits "
        f"{t['fit_jax']:.1f} s (compile {t['fit_jax_compile']:.1f} s, and "
        f"{t['fit_jax_compile_aside']:.1f} s beside the simulation; "
        f"{report['throughput']['jax_fits_per_min']:.3g}/min), scipy {t['fit_scipy']:.1f} s, "
        f"total {t['total']:.1f} s"
    )
    return "\n".join(lines)
