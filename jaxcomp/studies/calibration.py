"""The calibration study: how well calibration finds thousands of simulated true robots.

N true Gen3 Lite arms are drawn from the seed (``draw_truth``: ratios 20-30 % off nominal,
friction torques 20-30 % off the paper's, COM offsets of a few mm on every moving link, current
noise, optional viscous friction); the calibration plan (default:
``identify.plan_design.default_plan``, the paper's ~230 s of sweeps; "random:K": K random
plans, ``identify.random_plans``, each recorded by a contiguous group of the worlds) is
recorded in every world at once on MJX (``MjxSimulator``, 1 kHz, float64, worlds sharded over
the accelerators), every world is fitted with the joint JAX fit in vmapped batches on the
accelerator (``jax_fit.fit_batch``) and M of them also with the paper's scipy fit
(``identify.baseline``; the first worlds of each plan's group, M spread over the plans as the
worlds are: ``baseline_worlds``). The report compares estimates with the truth.

The stages, each in its own module and composed here (``run_study``): ``truth_draw``,
``plan_signal``, ``plan_recording`` (simulate and reduce), ``jax_fit.fit_batch`` and
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

Units: SI (rad, A, N m, m, s); COM offsets in each link's own frame; ratio A/(N m); viscous
friction of the truth N m s/rad, the fit's viscous term A s/rad (= ratio x viscous).
"""

import dataclasses
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.files import output_folder, writing
from jaxcomp.identify.evaluate import random_poses
from jaxcomp.identify.jax_fit import BatchFit, fit_model
from jaxcomp.identify.jax_fit import fit_batch as batch_fit
from jaxcomp.identify.named_plans import (
    check_plan_name,
    named_plan,
    plan_count,
    random_count,
    short_plan,
)
from jaxcomp.identify.plan import CalibrationPlan
from jaxcomp.identify.random_plans import plan_seed
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import json_ready, write_json_atomic
from jaxcomp.studies.calibration_estimates import (
    concat_estimates,
    jax_estimates,
    scipy_estimates,
)
from jaxcomp.studies.calibration_figures import plot_coverage, plot_errors
from jaxcomp.studies.calibration_statistics import (
    coverage_summary,
    cramer_rao_summary,
    gravity_comparison,
    gravity_summary,
    identified_ratio_error,
    parameter_table,
)
from jaxcomp.studies.plan_recording import Simulated, simulate
from jaxcomp.studies.plan_signal import (
    PlanSignal,
    check_every,
    plan_segments,
    plan_signal,
    start_pose,
)
from jaxcomp.studies.setup import MODEL, simulator
from jaxcomp.studies.truth_draw import TruthSpread, draw_truth, truth_rows

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

    def __post_init__(self) -> None:
        check_plan_name(self.plan)
        checks = {
            "--worlds": (self.worlds, 1),
            "--every": (self.every, 1),
            "--baseline-sample": (self.baseline_sample, 0),
            "--poses": (self.poses, 1),
            "--world-batch": (self.world_batch, 1),
            "--fit-batch": (self.fit_batch, 1),
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
    """The worlds ``rows`` of a study, which record ``plan``: its signal, the simulation, the
    joint fits and their estimates."""

    rows: range
    plan: CalibrationPlan
    signal: PlanSignal
    simulated: Simulated | None = None
    fits: BatchFit | None = None

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


def run_study(
    settings: CalibrationSettings, *, progress: bool = True, robot: Robot | None = None
) -> tuple[dict, dict]:
    """The whole study of ``settings``: (report for study.json, per-world arrays for
    worlds.npz); see the module docstring. ``progress``: show progress bars; ``robot``: the
    ``MODEL`` robot to study, whose simulator (``setup.simulator``) and compiled programs it
    keeps (default: freshly loaded).

    With ``plan`` "random:K" the worlds are cut into K contiguous groups (``world_groups``),
    group g recording its own random plan (seed ``plan_seed(seed, g)``), simulated and fitted
    on its own; the truths are drawn for all worlds at once (world w is the same for any K).
    """
    worlds, seed, plan, every = settings.worlds, settings.seed, settings.plan, settings.every
    spread, baseline_sample = settings.spread, settings.baseline_sample
    world_batch, parallel = settings.world_batch, settings.parallel
    if baseline_sample:
        try:
            import pinocchio  # noqa: F401  (the scipy fit needs it: fail now, not at the end)
        except ImportError:
            raise InputError(
                "--baseline-sample needs pinocchio (pip install pin); use --baseline-sample 0 "
                "to skip the scipy fit"
            ) from None
    t_all = time.perf_counter()
    robot = load_robot(MODEL) if robot is None else robot
    count = plan_count(plan)
    groups = []
    for g, rows in enumerate(world_groups(worlds, count)):
        the_plan = named_plan(robot, plan, seed=seed, group=g)
        groups.append(_Group(rows, the_plan, plan_signal(the_plan, start_pose(robot))))
        check_every(groups[-1].signal, every)
    sim = simulator(settings.devices, robot)
    model = fit_model(robot, settings.com_prior or study_com_prior(spread))  # m, every link
    truth = draw_truth(robot, worlds, seed, spread)
    backend, mesh = jax.default_backend(), sim.mesh
    world_batch = world_batch or (worlds if backend != "cpu" else mesh.size)
    parallel = backend != "cpu" if parallel is None else bool(parallel)
    sample = baseline_worlds([gr.rows for gr in groups], baseline_sample)
    keep = len(sample)
    timing = {"setup": time.perf_counter() - t_all}

    bar = tqdm(
        total=sum(len(gr.rows) * len(gr.signal.q_ref) for gr in groups),
        unit="step",
        unit_scale=True,
        desc=f"MJX, {worlds} worlds",
        disable=not progress,
    )
    for g, gr in enumerate(groups):
        rows = slice(gr.rows.start, gr.rows.stop)
        sampled = np.count_nonzero((sample >= rows.start) & (sample < rows.stop))
        simulated = simulate(
            sim,
            truth_rows(truth, rows),
            gr.signal,
            seed=seed,
            every=every,
            world_batch=world_batch,
            keep=rows.start + int(sampled),  # global index: the group's first worlds
            progress=bar.update,
            parallel=parallel,
            offset=gr.rows.start,
        )
        groups[g] = gr._replace(simulated=simulated)
    bar.close()
    for key in groups[0].simulated.timing:
        timing[key] = sum(gr.simulated.timing[key] for gr in groups)
    fault_step = np.concatenate([gr.simulated.fault_step for gr in groups])
    recordings = [r for gr in groups for r in gr.simulated.recordings]
    world_steps = sum(gr.simulated.world_steps for gr in groups)

    t0 = time.perf_counter()
    bar = tqdm(total=worlds, unit="fit", desc="JAX fits", disable=not progress)
    for g, gr in enumerate(groups):
        moments = gr.simulated.moments
        fits = batch_fit(model, moments, batch=settings.fit_batch, mesh=mesh, progress=bar.update)
        groups[g] = gr._replace(fits=fits)
    bar.close()
    timing["fit_jax"] = time.perf_counter() - t0
    timing["fit_jax_compile"] = sum(gr.fits.compile_seconds for gr in groups)
    timing["fit_jax_run"] = fit_seconds = sum(gr.fits.seconds for gr in groups)
    converged = np.concatenate([np.asarray(gr.fits.solution.converged) for gr in groups])
    noise_estimate = np.concatenate([np.asarray(gr.fits.solution.sigma) for gr in groups])

    t0 = time.perf_counter()
    pose_set = random_poses(robot, settings.poses, seed=seed)
    jax_est = concat_estimates(
        [
            jax_estimates(
                robot,
                model,
                truth_rows(truth, slice(gr.rows.start, gr.rows.stop)),
                gr.simulated,
                gr.fits,
                pose_set,
            )
            for gr in groups
        ]
    )
    timing["evaluate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    bar = tqdm(total=keep, unit="fit", desc="scipy fits", disable=not progress or not keep)
    scipy_est, failed = scipy_estimates(
        robot, truth, sample, recordings, jax_est, pose_set, progress=bar.update
    )
    on_m = jax_est.rows(sample)
    bar.close()
    timing["fit_scipy"] = time.perf_counter() - t0

    n = model.n
    jax_table = parameter_table(jax_est, 2 * n)
    scipy_table = parameter_table(scipy_est, 2 * n) if keep else {}
    sigma = noise_estimate[jax_est.ok]
    plan_group = np.concatenate([np.full(len(gr.rows), g) for g, gr in enumerate(groups)])
    timing["total"] = time.perf_counter() - t_all
    report = {
        "format": FORMAT,
        "version": 1,
        "model": robot.name,
        "seed": seed,
        "worlds": worlds,
        "plan": _plan_report(plan, seed, groups),
        "record_every": every,
        "record_rate_hz": 1.0 / (CONTROL_PERIOD * every),
        "truth": dataclasses.asdict(spread) | {"noise": float(truth.current_noise[0])},
        "fit_com_prior": settings.com_prior or study_com_prior(spread),
        "backend": backend,
        "devices": [str(d) for d in mesh.devices.flat],
        "world_batch": world_batch,
        "parallel_sweeps": parallel,
        "faulted_worlds": int((fault_step >= 0).sum()),
        "jax": {
            "converged": int(converged.sum()),
            "used": int(jax_est.ok.sum()),
            "noise_estimate_median": float(np.median(sigma)) if sigma.size else math.nan,
            "parameters": jax_table,
            "gravity_current_error": gravity_summary(
                np.where(jax_est.ok[:, None], jax_est.gravity, np.nan)
            ),
            "largest_identified_ratio_error": identified_ratio_error(jax_est, n),
            "on_scipy_worlds": {
                "parameters": {
                    k: {"rmse": v["rmse"], "relative_rmse": v.get("relative_rmse")}
                    for k, v in parameter_table(on_m, 2 * n).items()
                    if k in scipy_table
                },
                "gravity_current_error": gravity_summary(on_m.gravity[on_m.ok]),
                "pooled_gravity_current_error": gravity_comparison(on_m, scipy_est),
            },
        },
        "scipy": {
            "worlds": keep,
            "plans": len(np.unique(plan_group[sample])),
            "failed": failed,
            "parameters": scipy_table,
            "gravity_current_error": gravity_summary(scipy_est.gravity),
        },
        "coverage": {"jax": coverage_summary(jax_est), "scipy": coverage_summary(scipy_est)},
        "cramer_rao": cramer_rao_summary(jax_table, jax_est.names),
        "timing_s": timing,
        "throughput": {
            "world_steps_per_s": world_steps / max(timing["simulate_stepping"], 1e-9),
            "jax_fits_per_min": 60.0 * worlds / max(fit_seconds, 1e-9),
            "scipy_fits_per_min": 60.0 * keep / max(timing["fit_scipy"], 1e-9) if keep else None,
        },
    }
    arrays = {
        "parameter_names": np.array(jax_est.names),
        "plan_group": plan_group,
        "truth": jax_est.truth,
        "jax_estimate": jax_est.estimate,
        "jax_std": jax_est.std,
        "jax_identified": jax_est.identified,
        "jax_converged": converged,
        "jax_ok": jax_est.ok,
        "jax_noise_estimate": noise_estimate,
        "jax_gravity_current_error": jax_est.gravity,
        "jax_gravity_current_error_pooled": jax_est.gravity_pooled,
        "swept": jax_est.swept,
        "scipy_worlds": sample,
        "scipy_estimate": scipy_est.estimate,
        "scipy_std": scipy_est.std,
        "scipy_gravity_current_error": scipy_est.gravity,
        "scipy_gravity_current_error_pooled": scipy_est.gravity_pooled,
        "fault_step": fault_step,
    }
    return report, arrays


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
    out: Path, settings: CalibrationSettings, *, progress: bool = True, robot: Robot | None = None
) -> StudyOutputs:
    """``run_study`` and ``write_outputs`` into the folder ``out``, created and locked first
    (``files.output_folder``: FileError before minutes of simulation); nothing is written
    on error (a folder it created is removed again)."""
    with output_folder(out) as folder:
        report, arrays = run_study(settings, progress=progress, robot=robot)
        return StudyOutputs(report, arrays, write_outputs(folder, report, arrays))


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
    cov = report["coverage"]["jax"]["identified"]
    t = report["timing_s"]
    lines.append(
        f"coverage of +-1.96 std (JAX, {cov['count']} determined estimates): "
        f"{pct(cov['coverage_95'])}; z std {cov['z_std']:.2f}"
    )
    lines.append(
        f"time: simulate {t['simulate']:.1f} s (compile {t['simulate_compile']:.1f} s, "
        f"{report['throughput']['world_steps_per_s']:.3g} world-steps/s), JAX fits "
        f"{t['fit_jax']:.1f} s (compile {t['fit_jax_compile']:.1f} s, "
        f"{report['throughput']['jax_fits_per_min']:.3g}/min), scipy {t['fit_scipy']:.1f} s, "
        f"total {t['total']:.1f} s"
    )
    return "\n".join(lines)
