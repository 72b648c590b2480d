"""`jaxcomp study control`: tracking error and compliance of the impedance controller across
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

The controller is the wiring of ``control`` to the simulator: ``impedance_policy`` turns the
controller's step function into a per-world policy whose parameters (ratio, friction, COM of
every link) are per-world arrays, with the control loop's start (previous command = measured
current), its saturation watchdog (``max_saturated_cycles``), and the phase metrics in its
state. Units SI (m, s, N, A, rad); positions in the world (= arm base) frame.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import platform
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import numpy as np

from jaxcomp.cli.study import MODEL, check_out_dir, simulator, study
from jaxcomp.errors import InputError

if TYPE_CHECKING:  # heavy imports happen inside the functions (quick --help)
    from jaxcomp.control.trajectory import Trajectory
    from jaxcomp.hardware.mjx_sim import BatchTruth, PushSchedule
    from jaxcomp.robot import Robot

# the timeline, s from the start of the closed loop
BASELINE = (0.3, 0.5)  # static offset window
PUSH_START = 0.5  # first of the ramp's pushes
RAMP = 5  # pushes of F / RAMP, RAMP_STEP apart
RAMP_STEP = 0.02
RELEASE = 1.5  # every push ends here
HELD = (RELEASE - 0.25, RELEASE - 0.05)  # displacement window
TRACK_START = 2.0  # the half circle starts here
REFERENCE_COLUMNS = 12  # target pos (3) | vel (3) | acc (3) | w_track | w_base | w_push
POSES = 64  # random poses of the gravity-current model error

STUDY_JSON = "study.json"
FIGURES = ("tracking.png", "compliance.png")


# ----------------------------------------------------------------------------- the policy
@functools.cache
def impedance_policy(robot_name: str, gains: Any, max_saturated_cycles: int = 250) -> tuple:
    """(policy, init) of the impedance controller for ``MjxSimulator.run_closed_loop``.

    Per-world params: ``ratio`` (n,) A/(N m), ``friction`` (n,) A, ``com`` (nb, 3) m (every
    link's centre of mass, link frame) — the controller's model. The reference row is
    target pos m | vel m/s | acc m/s^2 (arm frame) | w_track | w_base | w_push (0/1 weights of
    the metric windows). State: ``prev`` (n,) A (last command; at the start the measured
    current within the arm's current limit, as ``run_control``), ``sat`` (n,) consecutive
    cycles at the controller's saturation (stop beyond ``max_saturated_cycles``, as the loop's
    watchdog), and the sums of the metrics: ``track_sq`` m^2, ``track_n``, ``track_max`` m,
    ``base_sum``/``push_sum`` (3,) m of ee - target and ``base_n``/``push_n``.
    Cached per (robot, gains): one compiled program per configuration.
    """
    import jax.numpy as jnp

    from jaxcomp.control import make_impedance_controller
    from jaxcomp.control.impedance import impedance_step_fn
    from jaxcomp.hardware import ArmLimits
    from jaxcomp.robot import load_robot
    from jaxcomp.robot_params import arm_joint_indices

    robot = load_robot(robot_name)
    controller = make_impedance_controller(robot, None, gains)
    base = controller._res  # the controller's resolved constants; params become per-world
    limit = ArmLimits.from_robot(robot, arm_joint_indices(robot)).current
    saturation = np.minimum(controller.joint.limit, limit) - 1e-9  # the watchdog's test
    n = controller.n

    def policy(p, s, obs):
        res = base._replace(
            inertial=base.inertial._replace(com=p["com"]), ratio=p["ratio"], friction=p["friction"]
        )
        ref = obs.reference
        pos = ref[0:3]
        cur, diag = impedance_step_fn(res, gains)(obs.q, obs.dq, pos, ref[3:6], ref[6:9], s["prev"])
        sat = jnp.where(jnp.abs(cur) >= saturation, s["sat"] + 1, 0)
        err = diag.ee_pos - pos
        e2 = err @ err
        w_track, w_base, w_push = ref[9], ref[10], ref[11]
        state = {
            "prev": cur,
            "sat": sat,
            "track_sq": s["track_sq"] + w_track * e2,
            "track_n": s["track_n"] + w_track,
            "track_max": jnp.maximum(s["track_max"], w_track * jnp.sqrt(e2)),
            "base_sum": s["base_sum"] + w_base * err,
            "base_n": s["base_n"] + w_base,
            "push_sum": s["push_sum"] + w_push * err,
            "push_n": s["push_n"] + w_push,
        }
        return cur, state, jnp.any(sat > max_saturated_cycles)

    def init(p, obs):
        zero = jnp.zeros((), obs.q.dtype)
        return {
            "prev": jnp.clip(obs.current, -limit, limit),
            "sat": jnp.zeros(n, jnp.int32),
            "track_sq": zero,
            "track_n": zero,
            "track_max": zero,
            "base_sum": jnp.zeros(3, obs.q.dtype),
            "base_n": zero,
            "push_sum": jnp.zeros(3, obs.q.dtype),
            "push_n": zero,
        }

    return policy, init


def controller_params(robot: Robot, ratio: Any, friction: Any, com_offset: Any) -> dict:
    """Per-world policy params: ratio (W, n) A/(N m), friction (W, n) A, and every link's COM
    (W, nb, 3) m = nominal + ``com_offset`` (W, nb, 3) m, link frame."""
    com = np.asarray(robot.nominal_params().com)[None] + np.asarray(com_offset, float)
    return {"ratio": np.asarray(ratio, float), "friction": np.asarray(friction, float), "com": com}


def reference_rows(
    trajectory: Trajectory, start: np.ndarray, steps: int, windows: dict[str, tuple[float, float]]
) -> np.ndarray:
    """(steps + 1, 12) rows of the policy's reference at t = k ms: the target (``start`` (3,) m
    before ``TRACK_START``, then ``trajectory(t - TRACK_START)``) and the window weights
    ``windows`` {"track"|"base"|"push": (from, to) s}, 1 where from <= t < to."""
    t = np.arange(steps + 1) * 1e-3
    rows = np.zeros((steps + 1, REFERENCE_COLUMNS))
    rows[:, 0:3] = start
    moving = t >= TRACK_START
    if moving.any():
        sample = trajectory.sample(t[moving] - TRACK_START)
        rows[moving, 0:3], rows[moving, 3:6], rows[moving, 6:9] = sample
    for col, name in ((9, "track"), (10, "base"), (11, "push")):
        lo, hi = windows.get(name, (math.inf, math.inf))
        rows[(t >= lo) & (t < hi), col] = 1.0
    return rows


def ramped_pushes(direction: np.ndarray, force: float) -> PushSchedule:
    """``PushSchedule`` (W, RAMP): F/RAMP along each world's unit ``direction`` (W, 3), the
    k-th from PUSH_START + k RAMP_STEP until RELEASE."""
    from jaxcomp.hardware.mjx_sim import PushSchedule

    w = len(direction)
    start = PUSH_START + RAMP_STEP * np.arange(RAMP)
    starts = np.broadcast_to(start, (w, RAMP)).copy()
    piece = force / RAMP * np.asarray(direction, float)
    return PushSchedule(starts, RELEASE - starts, np.repeat(piece[:, None], RAMP, axis=1))


# ----------------------------------------------------------------------------- the worlds
def draw_worlds(
    robot: Robot,
    worlds: int,
    seed: int,
    params_error: float,
    com_error: float,
    nominal: bool,
    noise: float,
    push: str = "horizontal",
) -> tuple[BatchTruth, dict[str, np.ndarray], np.ndarray]:
    """(truth, controller params, push directions (W, 3)) drawn from ``seed``.

    Truth per world: the paper's ratios x U(0.9, 1.1) and friction losses x U(0.8, 1.2), COM
    offsets U(+-4 mm) per axis on every moving link, current noise ``noise`` A. Controller:
    ``nominal`` -> the model's nominal ratios, no friction compensation, nominal COM; else
    "identified-like": ratio and friction x (1 + U(-params_error, params_error)), COM offsets
    + U(+-com_error) m per axis (moving links). Push directions: ``push`` "horizontal",
    uniform in the world's xy plane, or "sphere", uniform on the unit sphere (a 10 N push
    down at ``home`` plus the friction compensation asks joint 1 for more than its 14 N m).
    """
    from jaxcomp.hardware import PAPER_FRICTION, PAPER_RATIO
    from jaxcomp.hardware.mjx_sim import BatchTruth
    from jaxcomp.hardware.truth import DEFAULT_COM_OFFSET
    from jaxcomp.robot_params import RobotParams, arm_joint_indices

    rng = np.random.default_rng(seed)
    n, nb = len(arm_joint_indices(robot)), len(robot.link_names)
    moved = robot.tree.moves.any(axis=0)[None, :, None]
    ratio = np.asarray(PAPER_RATIO) * rng.uniform(0.9, 1.1, (worlds, n))
    friction = np.asarray(PAPER_FRICTION) * rng.uniform(0.8, 1.2, (worlds, n))
    com = rng.uniform(-DEFAULT_COM_OFFSET, DEFAULT_COM_OFFSET, (worlds, nb, 3)) * moved
    truth = BatchTruth.from_arrays(robot, ratio, friction, com_offset=com, current_noise=noise)
    err = rng.uniform(-1.0, 1.0, (2, worlds, n)) * params_error
    com_err = rng.uniform(-1.0, 1.0, (worlds, nb, 3)) * com_error * moved
    if push == "horizontal":
        angle = rng.uniform(0.0, 2 * np.pi, worlds)
        direction = np.stack([np.cos(angle), np.sin(angle), np.zeros(worlds)], axis=1)
    elif push == "sphere":
        direction = rng.normal(size=(worlds, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    else:
        raise InputError(f"push direction must be 'horizontal' or 'sphere', got {push!r}")
    if nominal:
        nom = RobotParams.nominal(robot)
        params = controller_params(
            robot, np.tile(nom.ratio, (worlds, 1)), np.zeros((worlds, n)), np.zeros_like(com)
        )
    else:
        params = controller_params(
            robot, ratio * (1 + err[0]), friction * (1 + err[1]), com + com_err
        )
    return truth, params, direction


def model_errors(robot: Robot, truth: BatchTruth, params: dict) -> dict[str, np.ndarray]:
    """Per-world model error of the controller's params against the truth: RMS over joints of
    the relative ratio and friction errors, RMS COM error over the moving links' axes (m), and
    the relative gravity-current error: RMS of r_c g_c(q) - r_t g_t(q) over ``POSES`` random
    poses and all joints, relative to the RMS of r_t g_t(q)."""
    import jax
    import jax.numpy as jnp

    from jaxcomp import dynamics
    from jaxcomp.identify.evaluate import random_poses

    nominal = robot.nominal_params()
    moved = robot.tree.moves.any(axis=0)
    true_com = np.asarray(nominal.com)[None] + truth.com_offset
    poses = random_poses(robot, POSES, seed=0)
    tree = robot.tree

    @jax.jit
    def gravity(com):  # (W, nb, 3) -> (W, P, n)
        def one(c, q):
            return dynamics.gravity(tree, q, nominal._replace(com=c))

        return jax.vmap(lambda c: jax.vmap(lambda q: one(c, q))(jnp.asarray(poses)))(com)

    g_true = np.asarray(gravity(jnp.asarray(true_com))) * truth.ratio[:, None]
    g_ctrl = np.asarray(gravity(jnp.asarray(params["com"]))) * params["ratio"][:, None]
    rms = lambda a, axes: np.sqrt(np.mean(a**2, axis=axes))  # noqa: E731
    return {
        "ratio_error": rms(params["ratio"] / truth.ratio - 1, 1),
        "friction_error": rms(params["friction"] / truth.friction - 1, 1),
        "com_error_m": rms((params["com"] - true_com)[:, moved], (1, 2)),
        "gravity_current_error": rms(g_ctrl - g_true, (1, 2)) / rms(g_true, (1, 2)),
    }


# ----------------------------------------------------------------------------- the study
def trajectory_for(robot: Robot, passes: int) -> tuple[np.ndarray, Trajectory]:
    """(start (3,) m, the half circle from it): the end effector at the ``home`` pose (the
    worlds settle within a fraction of a mm of it; the controller starts from where each is)."""
    from jaxcomp.control.trajectory import parse_trajectory

    start = np.asarray(robot.site_position(robot.pose("home"), "end_effector"), float)
    return start, parse_trajectory(f"half-circle:passes={passes}").build(start)


def _stats(values: np.ndarray, quantiles: tuple = (50, 95)) -> dict[str, float | None]:
    values = np.asarray(values, float)
    names = {5: "p5", 50: "median", 95: "p95"}
    if values.size == 0:
        return {names[q]: None for q in quantiles} | {"min": None, "max": None}
    out = {names[q]: float(np.percentile(values, q)) for q in quantiles}
    return out | {"min": float(values.min()), "max": float(values.max())}


def run_study(
    worlds: int,
    seed: int = 0,
    *,
    duration: float | None = None,
    passes: int = 2,
    force: float = 10.0,
    gains: Any = None,
    params_error: float = 0.05,
    com_error: float = 0.002,
    nominal: bool = False,
    noise: float = 0.05,
    push: str = "horizontal",
    devices: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """The study's numbers as a JSON-able dict (see the module doc; ``gains`` default
    ``ImpedanceGains.tracking()``); ``duration`` s of tracking (None: the whole half circle)."""
    import jax
    from tqdm.auto import tqdm

    from jaxcomp.control import ImpedanceGains
    from jaxcomp.hardware.mjx_sim import SETTLE_STEPS, fault_names
    from jaxcomp.robot import load_robot
    from jaxcomp.robot_params import json_ready

    t_begin = time.perf_counter()
    worlds, passes = int(worlds), int(passes)
    if worlds < 1:
        raise InputError(f"--worlds must be >= 1, got {worlds}")
    if passes < 1:
        raise InputError(f"--passes must be >= 1, got {passes}")
    if not (math.isfinite(force) and force > 0):
        raise InputError(f"--force must be > 0 N, got {force}")
    for name, value in (("params-error", params_error), ("com-error", com_error), ("noise", noise)):
        if not (math.isfinite(value) and value >= 0):
            raise InputError(f"--{name} must be >= 0, got {value}")
    if params_error >= 1:
        raise InputError(f"--params-error must be < 1 (relative), got {params_error}")
    gains = ImpedanceGains.tracking() if gains is None else gains
    robot = load_robot(MODEL)
    start, trajectory = trajectory_for(robot, passes)
    if duration is None:
        duration = trajectory.duration
    if not (math.isfinite(duration) and duration > 0):
        raise InputError(f"--duration must be > 0 s, got {duration}")
    steps = int(round((TRACK_START + duration) / 1e-3))
    end = TRACK_START + duration
    windows = {"track": (TRACK_START, end + 1.0), "base": BASELINE, "push": HELD}
    reference = reference_rows(trajectory, start, steps, windows)
    truth, params, direction = draw_worlds(
        robot, worlds, seed, params_error, com_error, nominal, noise, push
    )
    stiffness = np.asarray(gains.stiffness, float)
    expected = force * (direction**2 / stiffness).sum(axis=1)  # m along u: F u^T K^-1 u
    policy, init = impedance_policy(MODEL, gains)
    sim = simulator(devices)
    compiled_before = sim.compile_seconds
    bar = tqdm(total=steps, unit="step", desc=f"{worlds} worlds", disable=not progress)

    def advance(done: int, total: int) -> None:
        bar.update(done - bar.n)

    try:
        result = sim.run_closed_loop(
            truth,
            policy,
            params,
            init,
            steps,
            reference=reference,
            pushes=ramped_pushes(direction, force),
            initial_pose="home",
            seed=seed,
            progress=advance,
        )
    finally:
        bar.close()
    s = result.state
    faulted = result.fault_step >= 0
    fault_t = np.where(faulted, result.fault_step * 1e-3, np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        # a world's figure counts only when its phase ended before any fault
        rms = np.where(faulted, np.nan, np.sqrt(s["track_sq"] / s["track_n"]))
        track_max = np.where(faulted, np.nan, s["track_max"])
        offset = s["base_sum"] / s["base_n"][:, None]
        moved = s["push_sum"] / s["push_n"][:, None] - offset
        ratio = (moved * direction).sum(axis=1) / expected
    measured = fault_t >= HELD[1]
    ratio, offset = np.where(measured, ratio, np.nan), np.where(measured[:, None], offset, np.nan)
    errors = model_errors(robot, truth, params)
    ok = ~faulted
    timing = dict(sim.last_timing, compile=sim.compile_seconds - compiled_before)
    run_s = timing["settle"] + timing["plan"]
    return {
        "study": "control",
        "seed": int(seed),
        "worlds": worlds,
        "backend": jax.default_backend(),
        "devices": [str(d.device_kind) for d in (sim.mesh.devices.flat if sim.mesh else [])],
        "host": platform.node(),
        "config": {
            "model": MODEL,
            "gains": json_ready(dataclasses.asdict(gains)),
            "force_N": force,
            "push_direction": push,
            "tracking_duration_s": duration,
            "trajectory": trajectory.description,
            "passes": passes,
            "steps": steps,
            "controller": "nominal" if nominal else "identified-like",
            "params_error": params_error,
            "com_error_m": com_error,
            "current_noise_A": noise,
            "truth": "paper ratio x U(0.9, 1.1), friction x U(0.8, 1.2), COM U(+-4 mm)",
            "timeline_s": {
                "baseline": BASELINE,
                "push": [PUSH_START, RELEASE],
                "held": HELD,
                "tracking": [TRACK_START, end],
            },
        },
        "summary": {
            "tracking_rms_m": _stats(rms[ok]),
            "tracking_max_m": _stats(track_max[ok]),
            "compliance_ratio": _stats(ratio[measured], (5, 50, 95)),
            "static_offset_m": _stats(np.linalg.norm(offset[measured], axis=1)),
            "faulted": int(faulted.sum()),
            "faulted_fraction": float(faulted.mean()),
            "note": "over the worlds that did not fault before the phase ended",
        },
        "per_world": {
            "tracking_rms_m": rms.tolist(),
            "tracking_max_m": track_max.tolist(),
            "compliance_ratio": ratio.tolist(),
            "static_offset_m": np.linalg.norm(offset, axis=1).tolist(),
            "static_offset_xyz_m": offset.tolist(),
            "push_direction": direction.tolist(),
            "faulted": faulted.tolist(),
            "fault_time_s": np.where(faulted, fault_t, np.nan).tolist(),
            "fault": [", ".join(fault_names(c)) for c in result.fault_code],
            **{k: v.tolist() for k, v in errors.items()},
        },
        "timing_s": {
            "prepare": timing["prepare"],
            "compile": timing["compile"],
            "run": run_s,
            "total": time.perf_counter() - t_begin,
            "world_steps_per_s": worlds * (steps + SETTLE_STEPS) / run_s if run_s > 0 else None,
        },
    }


# ----------------------------------------------------------------------------- outputs
def write_figures(report: dict, out: Path) -> list[Path]:
    """tracking.png and compliance.png: histograms over the worlds whose phase ended before
    any fault, and scatter against the controller's model error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pw = report["per_world"]
    panels = [
        (
            FIGURES[0],
            1e3 * np.asarray(pw["tracking_rms_m"], float),
            "tracking RMS error (mm)",
            100 * np.asarray(pw["gravity_current_error"]),
            "gravity-current error of the controller's model (%)",
        ),
        (
            FIGURES[1],
            np.asarray(pw["compliance_ratio"], float),
            "compliance ratio: displacement / (F / K_d)",
            100 * np.asarray(pw["ratio_error"]),
            "ratio error of the controller's model, RMS over joints (%)",
        ),
    ]
    paths = []
    for name, values, label, error, error_label in panels:
        ok = np.isfinite(values)
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
        ax0.hist(values[ok], bins=max(5, min(50, int(ok.sum() ** 0.5) * 2)), color="C0")
        ax0.set_xlabel(label)
        ax0.set_ylabel("worlds")
        ax1.scatter(error[ok], values[ok], s=6, color="C0")
        ax1.set_xlabel(error_label)
        ax1.set_ylabel(label)
        fig.suptitle(
            f"{report['worlds']} worlds, seed {report['seed']}, {report['backend']}; "
            f"{int((~ok).sum())} faulted before the end of the phase (not shown)"
        )
        fig.tight_layout()
        path = out / name
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


def write_report(report: dict, out: Path) -> Path:
    """DIR/study.json, written atomically (NaN as null)."""
    from jaxcomp.robot_params import json_ready, write_json_atomic

    return write_json_atomic(out / STUDY_JSON, json_ready(report))


def _mm(stats: dict, key: str) -> str:
    v = stats.get(key)
    return "-" if v is None else f"{1e3 * v:.2f}"


# ----------------------------------------------------------------------------- the command
@study.command("control")
@click.option("--worlds", type=int, default=64, show_default=True, help="Simulated robots.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every draw.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="study_control")
@click.option(
    "--duration",
    type=float,
    default=None,
    help="Seconds of half-circle tracking after the 2 s compliance phase (default: the whole "
    "lead-in and passes, about 25 s for 2 passes). Short runs (e.g. 1) suit the CPU.",
)
@click.option("--passes", type=int, default=2, show_default=True, help="Half-circle passes.")
@click.option("--force", type=float, default=10.0, show_default=True, help="Push, N.")
@click.option(
    "--gains",
    "preset",
    type=click.Choice(["tracking", "paper"]),
    default="tracking",
    show_default=True,
    help="Impedance gains preset (see `jaxcomp control --help`).",
)
@click.option(
    "--controller",
    type=click.Choice(["identified", "nominal"]),
    default="identified",
    show_default=True,
    help="identified: the truth perturbed by --params-error and --com-error; nominal: the "
    "model's nominal ratios, no friction compensation, nominal COM.",
)
@click.option(
    "--params-error",
    type=float,
    default=0.05,
    show_default=True,
    help="Relative ratio and friction errors of the controller, drawn U(-E, E) per joint.",
)
@click.option(
    "--com-error",
    type=float,
    default=0.002,
    show_default=True,
    help="COM errors of the controller, m, drawn U(-D, D) per axis of every moving link.",
)
@click.option("--noise", type=float, default=0.05, show_default=True, help="Current noise, A.")
@click.option(
    "--push-direction",
    "push",
    type=click.Choice(["horizontal", "sphere"]),
    default="horizontal",
    show_default=True,
    help="Push directions, uniform in the horizontal plane or on the sphere (pushing down "
    "10 N at the home pose overloads joint 1 with the friction compensation).",
)
@click.option("--devices", type=int, default=None, help="Shard over N devices (default all).")
def control(
    worlds: int,
    seed: int,
    out_dir: str,
    duration: float | None,
    passes: int,
    force: float,
    preset: str,
    controller: str,
    params_error: float,
    com_error: float,
    noise: float,
    push: str,
    devices: int | None,
) -> None:
    """Tracking error and compliance across randomized model errors (MJX, one world each).

    Each world: a true Gen3 Lite (paper ratios x U(0.9, 1.1), friction x U(0.8, 1.2), COM
    offsets U(+-4 mm)) under the impedance controller in CURRENT mode at 1 kHz, with the
    controller's params off by --params-error / --com-error (or nominal). A push of --force N
    in a random (by default horizontal) direction measures the compliance ratio
    displacement / (F / K_d); then the paper's half circle (r 0.315 m, 0.101 m/s) measures
    the tracking error. Writes DIR/study.json and DIR/tracking.png, DIR/compliance.png.
    """
    from jaxcomp.control import ImpedanceGains

    out = check_out_dir(Path(out_dir))  # before minutes of simulation
    report = run_study(
        worlds,
        seed,
        duration=duration,
        passes=passes,
        force=force,
        gains=ImpedanceGains.preset(preset),
        params_error=params_error,
        com_error=com_error,
        nominal=controller == "nominal",
        noise=noise,
        push=push,
        devices=devices,
    )
    report["config"]["gains_preset"] = preset
    path = write_report(report, out)
    write_figures(report, out)
    sm, tm = report["summary"], report["timing_s"]
    c = sm["compliance_ratio"]
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    click.echo(
        f"{worlds} worlds on {report['backend']}: tracking RMS median "
        f"{_mm(sm['tracking_rms_m'], 'median')} mm, p95 {_mm(sm['tracking_rms_m'], 'p95')} mm, "
        f"max {_mm(sm['tracking_rms_m'], 'max')} mm; compliance ratio median "
        f"{fmt(c['median'])} (p5 {fmt(c['p5'])}, p95 {fmt(c['p95'])}); faulted {sm['faulted']}"
    )
    click.echo(
        f"compile {tm['compile']:.1f} s, run {tm['run']:.1f} s "
        f"({tm['world_steps_per_s']:.3g} world-steps/s), total {tm['total']:.1f} s -> {path}"
    )
