"""The control study: tracking error and compliance of the impedance controller across
randomized model errors, one MJX world per simulated true robot.

Every world is a Gen3 Lite (arm alone, base frame = world frame) with its own hidden truth,
driven in CURRENT mode at 1 kHz by the jitted impedance controller (``control.impedance``)
whose model parameters differ from that truth. One run per world (``MjxSimulator.
run_closed_loop``), on a timeline of three phases:

1. compliance, target fixed at the end effector's start position: from 0.3 s to 0.5 s the
   static offset e0 = mean(ee - target) is measured; a push of ``force`` N along the world's
   direction u ramps up from 0.5 s (five steps of F/5, 20 ms apart, as a hand would) and is
   released at 1.5 s (u: uniform in the horizontal plane, or on the sphere); e1 = mean(ee -
   target) over 1.25-1.45 s. The compliance ratio is
   (e1 - e0) . u / (F u^T K_d^-1 u): 1 for an ideal spring K_d;
2. recovery until 2.0 s;
3. tracking from 2.0 s: the paper's half circle (r 0.315 m, 0.101 m/s, lead-in from the start
   position, ``passes`` passes) in free space for ``duration`` s (default: all of it); the
   tracking error is the RMS and max of |ee - target| over this phase.

The controller is the wiring of ``control`` to the simulator: ``control_policy.impedance_policy``
turns the controller's step function into a per-world closed-loop policy whose parameters
(ratio, friction, COM of every link) are per-world arrays, with the control loop's start
(previous command = measured current), its saturation watchdog, and the phase metrics in its
state. The timeline, each world's draws and its controller's model error (``model_errors``,
with the gravity-current error pooled over all joints) are ``control_worlds``'. Units SI (m, s,
N, A, rad); positions in the world (= arm base) frame.
"""

import dataclasses
import platform
import time
from pathlib import Path
from typing import NamedTuple, Unpack

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control import ImpedanceGains, impedance_gains
from jaxcomp.control.trajectory import Trajectory
from jaxcomp.errors import InputError
from jaxcomp.files import writing
from jaxcomp.hardware.mjx import (
    SETTLE_STEPS,
    BatchTruth,
    ClosedLoopResult,
    MjxSimulator,
    Policy,
    fault_names,
)
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import json_ready, write_json_atomic
from jaxcomp.studies.control_figures import write_figures
from jaxcomp.studies.control_policy import impedance_policy
from jaxcomp.studies.control_worlds import (
    BASELINE,
    HELD,
    PUSH_START,
    RELEASE,
    TRACK_START,
    draw_worlds,
    model_errors,
    ramped_pushes,
    reference_rows,
    trajectory_for,
)
from jaxcomp.studies.processes import ONE_PROCESS, Processes, together
from jaxcomp.studies.setup import MODEL, simulator
from jaxcomp.studies.study_chunks import (
    CHUNK_WORLDS_PER_DEVICE,
    StudyOptions,
    chunk_store,
    into_folder,
    run_chunks,
    study_chunks,
)

STUDY_JSON = "study.json"


# ----------------------------------------------------------------------------- the study
@dataclasses.dataclass(frozen=True)
class ControlSettings:
    """What a control study runs (checked by ``run_study``, InputError).

    Attributes:
        worlds: simulated true robots (>= 1). seed: seed of every draw.
        duration: s of half-circle tracking after the 2 s compliance phase (None: the whole
            lead-in and ``passes`` passes). passes: half-circle passes (>= 1).
        force: N, the push. gains: the controller's ``ImpedanceGains``, or the name of a
            preset (``impedance_gains(robot, preset)``; the report then names it).
        params_error: relative ratio and friction errors of the controller, U(-E, E) per joint
            (< 1). com_error: m, COM errors of the controller, U(-D, D) per axis of every
            moving link. nominal: the controller has the model's nominal ratios, no friction
            compensation and nominal COM instead (``draw_worlds``).
        noise: A, current noise. push: push directions, "horizontal" or "sphere".
        devices: shard over the first N devices (None: all). chunk_worlds: worlds per
            closed-loop run (``study_chunks``; None: ``CHUNK_WORLDS_PER_DEVICE`` per device; a
            resumed study keeps its own).
    """

    worlds: int = 64
    seed: int = 0
    duration: float | None = None
    passes: int = 2
    force: float = 10.0
    gains: ImpedanceGains | str = "tracking"
    params_error: float = 0.05
    com_error: float = 0.002
    nominal: bool = False
    noise: float = 0.05
    push: str = "horizontal"
    devices: int | None = None
    chunk_worlds: int | None = None


#: The per-world arrays of a chunk (``chunk_results``; ``fault_code``: ``FAULT_*`` bits).
WORLD_ARRAYS = ("tracking_rms_m", "tracking_max_m", "compliance_ratio", "static_offset_xyz_m",
                "push_direction", "faulted", "fault_time_s", "fault_code", "ratio_error",
                "friction_error", "com_error_m", "gravity_current_error_pooled")  # fmt: skip


class _Study(NamedTuple):
    """A control study set up: its checked settings and what every chunk shares."""

    settings: ControlSettings
    robot: Robot
    gains: ImpedanceGains
    duration: float
    steps: int
    trajectory: Trajectory
    reference: np.ndarray
    policy: Policy
    sim: MjxSimulator

    def run_settings(self) -> dict:
        """The settings its chunk files belong to (``ChunkStore``)."""
        kept = dataclasses.asdict(self.settings) | {"gains": dataclasses.asdict(self.gains)}
        kept.pop("devices")
        return json_ready(kept | {"model": self.robot.name, "digest": self.robot.digest})


def _setup(settings: ControlSettings, robot: Robot | None) -> _Study:
    """``settings`` checked (InputError) and the study's shared parts made."""
    _check(settings)
    duration, worlds, passes = settings.duration, int(settings.worlds), int(settings.passes)
    robot = load_robot(MODEL) if robot is None else robot
    preset = settings.gains if isinstance(settings.gains, str) else None
    gains = settings.gains if preset is None else impedance_gains(robot, preset)
    start, trajectory = trajectory_for(robot, passes)
    if duration is None:
        duration = trajectory.duration
    checks.number(duration, "--duration", positive=True, unit="s")
    steps = int(round((TRACK_START + duration) / CONTROL_PERIOD))
    windows = {"track": (TRACK_START, TRACK_START + duration + 1.0), "base": BASELINE,
               "push": HELD}  # fmt: skip
    reference = reference_rows(trajectory, start, steps, windows)
    policy = impedance_policy(robot, gains)
    sim = simulator(settings.devices, robot)
    chunk = settings.chunk_worlds
    if chunk is None:
        chunk = CHUNK_WORLDS_PER_DEVICE * sim.mesh.size
    study_chunks([range(worlds)], chunk)  # --chunk-worlds checked
    settings = dataclasses.replace(settings, chunk_worlds=chunk)
    return _Study(settings, robot, gains, duration, steps, trajectory, reference, policy, sim)


def _check(settings: ControlSettings) -> None:
    """InputError when a count, the push or an error of ``settings`` is out of range."""
    force, worlds, passes = settings.force, int(settings.worlds), int(settings.passes)
    if worlds < 1:
        raise InputError(f"--worlds must be >= 1, got {worlds}")
    if passes < 1:
        raise InputError(f"--passes must be >= 1, got {passes}")
    checks.number(force, "--force", positive=True, unit="N")
    for name in ("params_error", "com_error", "noise"):
        checks.number(getattr(settings, name), f"--{name.replace('_', '-')}", nonneg=True)
    if settings.params_error >= 1:
        raise InputError(f"--params-error must be < 1 (relative), got {settings.params_error}")


def chunk_results(study: _Study, rows: range, progress: bool = False) -> dict:
    """The worlds ``rows`` in one closed-loop run: drawn, run, measured.

    A world's numbers depend on its id alone (its draws and noise).

    Args:
        study: the study set up (``run_study``).
        rows: the chunk's global world ids.
        progress: show a progress bar.

    Returns:
        {"world": {name: (W, ...) array} of ``WORLD_ARRAYS``, "timing": {"prepare",
        "compile", "run": s}}.
    """
    st, sim = study.settings, study.sim
    truth, params, direction = draw_worlds(
        study.robot, len(rows), st.seed, st.params_error, st.com_error, st.nominal, st.noise,
        st.push, first=rows.start,
    )  # fmt: skip
    compiled_before = sim.compile_seconds
    result = _closed_loop(study, rows, truth, params, direction, progress)
    world = _phase_metrics(study, result, direction) | model_errors(study.robot, truth, params)
    timing = sim.last_timing
    return {"world": {k: np.asarray(world[k]) for k in WORLD_ARRAYS}, "timing": {
        "prepare": timing["prepare"], "compile": sim.compile_seconds - compiled_before,
        "run": timing["settle"] + timing["plan"]}}  # fmt: skip


def _closed_loop(
    study: _Study,
    rows: range,
    truth: BatchTruth,
    params: dict[str, np.ndarray],
    direction: np.ndarray,
    progress: bool,
) -> ClosedLoopResult:
    """The worlds ``rows`` under their controllers ``params``, pushed along ``direction``
    (``MjxSimulator.run_closed_loop``)."""
    st = study.settings
    desc = f"worlds {rows.start}-{rows.stop - 1}"
    bar = tqdm(total=study.steps, unit="step", desc=desc, disable=not progress, leave=False)
    try:
        return study.sim.run_closed_loop(
            truth, study.policy, params, None, study.steps, reference=study.reference,
            pushes=ramped_pushes(direction, st.force), initial_pose="home", seed=st.seed,
            progress=lambda done, _total: bar.update(done - bar.n),
            world_ids=np.arange(rows.start, rows.stop),
        )  # fmt: skip
    finally:
        bar.close()


def _phase_metrics(
    study: _Study, result: ClosedLoopResult, direction: np.ndarray
) -> dict[str, np.ndarray]:
    """Each world's tracking error, compliance ratio, static offset and fault from the
    policy's phase sums; a figure counts only when its phase ended before any fault."""
    stiffness = np.asarray(study.gains.stiffness, float)
    expected = study.settings.force * (direction**2 / stiffness).sum(axis=1)  # F u^T K^-1 u, m
    s = result.state
    faulted = result.fault_step >= 0
    fault_t = np.where(faulted, result.fault_step * CONTROL_PERIOD, np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(faulted, np.nan, np.sqrt(s["track_sq"] / s["track_n"]))
        track_max = np.where(faulted, np.nan, s["track_max"])
        offset = s["base_sum"] / s["base_n"][:, None]
        moved = s["push_sum"] / s["push_n"][:, None] - offset
        ratio = (moved * direction).sum(axis=1) / expected
    measured = fault_t >= HELD[1]
    return {
        "tracking_rms_m": rms,
        "tracking_max_m": track_max,
        "compliance_ratio": np.where(measured, ratio, np.nan),
        "static_offset_xyz_m": np.where(measured[:, None], offset, np.nan),
        "push_direction": direction,
        "faulted": faulted,
        "fault_time_s": np.where(faulted, fault_t, np.nan),
        "fault_code": np.asarray(result.fault_code),
    }


def run_study(
    settings: ControlSettings,
    *,
    progress: bool = True,
    robot: Robot | None = None,
    folder: Path | None = None,
    resume: bool = False,
    processes: Processes = ONE_PROCESS,
) -> dict | None:
    """The whole study of ``settings``: set up, every chunk run (``chunk_results``), then the
    report made from the chunks' joined per-world arrays, whatever the chunking (see the
    module doc).

    Args:
        settings: what the study runs.
        progress: show progress bars.
        robot: the ``MODEL`` robot, whose simulator and policy it keeps (None: freshly
            loaded).
        folder: the output folder, created and locked by the caller: each finished chunk is
            written to ``folder``/chunks (None: chunks in memory).
        resume: keep the chunks in ``folder`` of an interrupted run of the same settings.
        processes: this process among several, each running its own chunks into ``folder``,
            as ``studies.calibration.run_study``.

    Returns:
        The report (JSON-able but for NaN) on process 0; None on the others.

    Raises:
        InputError: settings out of range, or ``resume`` or several processes without a
            folder.
    """
    t_begin = time.perf_counter()
    if folder is None and (processes.count > 1 or resume):
        raise InputError("--resume and --distributed need an output folder")
    store, settings = chunk_store(folder, settings, resume)
    study = together(processes, lambda: _setup(settings, robot), "to set the study up")
    chunks = study_chunks([range(int(settings.worlds))], study.settings.chunk_worlds)
    parts = run_chunks(
        processes, chunks, store, lambda chunk: chunk_results(study, chunk.rows, progress),
        settings=study.run_settings(), resume=resume, progress=progress,
    )  # fmt: skip
    if parts is None:
        return None
    world, timing = _joined(parts)
    return _report(study, world, timing, time.perf_counter() - t_begin, processes.count)


def _joined(parts: list[dict]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """(per-world arrays in world order, summed run times s) of every chunk's ``parts``."""
    world = {k: np.concatenate([p["world"][k] for p in parts]) for k in WORLD_ARRAYS}
    timing = {k: float(sum(np.sum(p["timing"][k]) for p in parts))
              for k in ("prepare", "compile", "run")}  # fmt: skip
    return world, timing


def _report(study: _Study, world: dict, timing: dict, total: float, processes: int) -> dict:
    """The report of a study from its joined per-world arrays ``world`` (``WORLD_ARRAYS``),
    summed run times ``timing`` s, ``total`` s and ``processes`` count."""
    st, sim = study.settings, study.sim
    steps, run_s = study.steps, timing["run"]
    return {
        "study": "control",
        "seed": int(st.seed),
        "worlds": int(st.worlds),
        "backend": jax.default_backend(),
        "devices": [str(d.device_kind) for d in (sim.mesh.devices.flat if sim.mesh else [])],
        "host": platform.node(),
        "processes": processes,
        "chunk_worlds": st.chunk_worlds,
        "config": _config(study),
        "summary": _summary_stats(world),
        "per_world": _per_world(world),
        "timing_s": {
            **timing,
            "total": total,
            "world_steps_per_s": st.worlds * (steps + SETTLE_STEPS) / run_s if run_s > 0 else None,
        },
    }


def _config(study: _Study) -> dict:
    """The report's configuration: model, gains (and their preset), push, trajectory,
    controller, errors, truth and timeline."""
    st = study.settings
    config = {
        "model": study.robot.name,
        "gains": json_ready(dataclasses.asdict(study.gains)),
        "force_N": st.force,
        "push_direction": st.push,
        "tracking_duration_s": study.duration,
        "trajectory": study.trajectory.description,
        "passes": int(st.passes),
        "steps": study.steps,
        "controller": "nominal" if st.nominal else "identified-like",
        "params_error": st.params_error,
        "com_error_m": st.com_error,
        "current_noise_A": st.noise,
        "truth": "paper ratio x U(0.9, 1.1), friction x U(0.8, 1.2), COM U(+-4 mm)",
        "timeline_s": {
            "baseline": BASELINE,
            "push": [PUSH_START, RELEASE],
            "held": HELD,
            "tracking": [TRACK_START, TRACK_START + study.duration],
        },
    }
    if isinstance(st.gains, str):
        config["gains_preset"] = st.gains
    return config


def _summary_stats(world: dict) -> dict:
    """The statistics over the worlds that did not fault before each phase ended."""
    faulted = world["faulted"]
    ok, measured = ~faulted, np.isfinite(world["compliance_ratio"])
    static = np.linalg.norm(world["static_offset_xyz_m"], axis=1)
    return {
        "tracking_rms_m": _stats(world["tracking_rms_m"][ok]),
        "tracking_max_m": _stats(world["tracking_max_m"][ok]),
        "compliance_ratio": _stats(world["compliance_ratio"][measured], (5, 50, 95)),
        "static_offset_m": _stats(static[measured]),
        "faulted": int(faulted.sum()),
        "faulted_fraction": float(faulted.mean()),
        "note": "over the worlds that did not fault before the phase ended",
    }


def _per_world(world: dict) -> dict:
    """The per-world arrays as lists, the static offset's norm (m) and the faults' names."""
    return {
        **{k: world[k].tolist() for k in ("tracking_rms_m", "tracking_max_m", "compliance_ratio")},
        "static_offset_m": np.linalg.norm(world["static_offset_xyz_m"], axis=1).tolist(),
        "static_offset_xyz_m": world["static_offset_xyz_m"].tolist(),
        "push_direction": world["push_direction"].tolist(),
        "faulted": world["faulted"].tolist(),
        "fault_time_s": world["fault_time_s"].tolist(),
        "fault": [", ".join(fault_names(c)) for c in world["fault_code"]],
        **{k: world[k].tolist() for k in WORLD_ARRAYS[-4:]},
    }


def _stats(values: np.ndarray, quantiles: tuple = (50, 95)) -> dict[str, float | None]:
    """The ``quantiles`` (of 5, 50, 95: p5, median, p95), min and max of ``values`` (None: no
    values)."""
    values = np.asarray(values, float)
    names = {5: "p5", 50: "median", 95: "p95"}
    if values.size == 0:
        return {names[q]: None for q in quantiles} | {"min": None, "max": None}
    out = {names[q]: float(np.percentile(values, q)) for q in quantiles}
    return out | {"min": float(values.min()), "max": float(values.max())}


# ----------------------------------------------------------------------------- outputs
def write_report(report: dict, out: Path) -> Path:
    """The report written atomically (NaN as null).

    Args:
        report: the study's report (``run_study``).
        out: the report folder (it exists).

    Returns:
        The path written, ``out``/study.json.
    """
    with writing(out / STUDY_JSON):
        return write_json_atomic(out / STUDY_JSON, json_ready(report))


def _mm(stats: dict, key: str) -> str:
    """``stats[key]`` (m) in mm with two decimals ("-": none)."""
    v = stats.get(key)
    return "-" if v is None else f"{1e3 * v:.2f}"


def summary(report: dict, path: Path) -> str:
    """Two lines for people: tracking, compliance, faults; run times and the report's path.

    Args:
        report: the study's report (``run_study``).
        path: where it was written.

    Returns:
        The two lines, joined by a newline.
    """
    sm, tm = report["summary"], report["timing_s"]
    c = sm["compliance_ratio"]
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    return (
        f"{report['worlds']} worlds on {report['backend']}: tracking RMS median "
        f"{_mm(sm['tracking_rms_m'], 'median')} mm, p95 {_mm(sm['tracking_rms_m'], 'p95')} mm, "
        f"max {_mm(sm['tracking_rms_m'], 'max')} mm; compliance ratio median "
        f"{fmt(c['median'])} (p5 {fmt(c['p5'])}, p95 {fmt(c['p95'])}); faulted {sm['faulted']}"
        "\n"
        f"compile {tm['compile']:.1f} s, run {tm['run']:.1f} s "
        f"({tm['world_steps_per_s']:.3g} world-steps/s), total {tm['total']:.1f} s -> {path}"
    )


# ----------------------------------------------------------------------------- one call
class StudyOutputs(NamedTuple):
    """What ``study_into`` made: the report (study.json) and the files written (the report
    first, then the figures)."""

    report: dict
    paths: list[Path]


def study_into(
    out: Path, settings: ControlSettings, **options: Unpack[StudyOptions]
) -> StudyOutputs | None:
    """``run_study`` written into one folder (``study_chunks.into_folder``): study.json, then
    the figures (``control_figures.write_figures``).

    Args:
        out: the report folder; the finished chunks stay in ``out``/chunks until the report
            is written.
        settings: the study's settings.
        options: ``StudyOptions`` (progress, robot, resume, processes).

    Returns:
        The report and the files written (study.json first) on process 0, else None.
    """
    return into_folder(out, run_study, settings, _write, **options)


def _write(folder: Path, report: dict) -> StudyOutputs:
    """The ``report`` written into ``folder``: study.json, then the figures."""
    return StudyOutputs(report, [write_report(report, folder), *write_figures(report, folder)])
