"""`jaxcomp control`: guidance or tracking mode on the simulator or the real robot."""

from __future__ import annotations

import math

import click

from jaxcomp import checks
from jaxcomp.cli.console_options import console_options
from jaxcomp.cli.group import cli
from jaxcomp.cli.model_options import model_options
from jaxcomp.cli.robot_options import (
    backend_option,
    gains_option,
    ip_option,
    params_option,
    rt_priority_option,
)
from jaxcomp.cli.robot_session import DEFAULT_MODEL
from jaxcomp.errors import FileError, InputError

#: What an earlier run left in --out: ``control.run_recording.RECORDING`` and its part files.
_EARLIER_RUN = ("recording.npz", "recording.npz.parts")

_TRAJ_HELP = (
    "Target path KIND[:key=value,...]; positions m, speeds m/s, accelerations m/s^2. "
    "'static' (x,y,z absolute or dx,dy,dz from the start; default: the start position), "
    "'line:dx=,dy=,dz=,v=,passes=', 'circle:r=0.1,v=0.05[,turns=,dir=,cx=,cy=,cz=]' "
    "(horizontal, in the world's x-y plane: it starts at the end effector, its centre r "
    "towards the arm's vertical axis), 'half-circle' (the paper's Exp. 2: r=0.315, "
    "v=0.101, passes=4, centred on the arm's vertical axis at the start height). "
    "Tracking mode: world frame; guidance mode: the base's frame. Default: static."
)


def parse_push(text: str) -> tuple[float, float, tuple[float, float, float]]:
    """Parse a --push.

    Args:
        text: 'START,DURATION,FX,FY,FZ' (s, s, N, N, N; world frame).

    Returns:
        (start s, duration s, force (fx, fy, fz) N, world frame).

    Raises:
        InputError: not five finite numbers, a negative start or a duration not above 0.
    """
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 5 or not all(math.isfinite(v) for v in values):
        raise InputError(
            f"--push {text!r}: expected START,DURATION,FX,FY,FZ (s, s, N, N, N), five numbers"
        )
    start, duration, fx, fy, fz = values
    if start < 0 or duration <= 0:
        raise InputError(f"--push {text!r}: START must be >= 0 s and DURATION > 0 s")
    return start, duration, (fx, fy, fz)


@cli.command()
@click.option(
    "--mode",
    type=click.Choice(["guidance", "tracking"]),
    default="guidance",
    show_default=True,
    help="guidance: target fixed to the base (push the arm, the base follows); tracking: the "
    "target follows --trajectory in the world, compliant to pushes.",
)
@backend_option(
    "sim: the MuJoCo simulator; kortex: the real Gen3 Lite (kortex_api) and, when ROS 2 is "
    "available, the Dingo-O."
)
@model_options(
    DEFAULT_MODEL,
    "Simulated robot (sim only; an arm model runs alone, a mobile model with base joints "
    "base_x, base_y, base_yaw with its base; the arm starts at the model's 'home' keyframe, "
    "else at a start pose chosen on the model)",
)
@params_option(
    "Identified params JSON (ratios A/(N m), friction A, COM offsets m); default: the model's "
    "nominal figures. The joints it lists are the current-controlled joints (--joints, if "
    "given, must agree)."
)
@click.option("--trajectory", default="static", show_default=True, help=_TRAJ_HELP)
@click.option(
    "--duration",
    type=float,
    default=None,
    help="Seconds of control; default: the trajectory's own length, or 10 s (static, endless).",
)
@click.option(
    "--push",
    "pushes",
    multiple=True,
    metavar="START,DURATION,FX,FY,FZ",
    help="Simulated push on the end effector: from START s after the start for DURATION s, "
    "force (FX, FY, FZ) N in the world frame. Repeatable. Simulator only. START must fall "
    "within the run, and the force may be at most 10 times the weight of the arm (the links "
    "its joints move, at 9.81 m/s^2; 396 N for the Gen3 Lite): beyond, the simulation breaks "
    "down.",
)
@click.option(
    "--max-error",
    type=float,
    default=None,
    help="m: a run whose end effector stays further than this from its target for more than "
    "--max-error-time s ends early (not_tracking, status 1); default: in tracking mode twice "
    "the gains' error clip (0.2 m for the Gen3 Lite), in guidance mode never (a person may hold "
    "the arm off its target); inf: never.",
)
@click.option(
    "--max-error-time",
    type=float,
    default=2.0,
    show_default=True,
    help="s, see --max-error.",
)
@click.option(
    "--controller",
    "law",
    type=click.Choice(["impedance", "velocity"]),
    default="impedance",
    show_default=True,
    help="impedance: the compliant current-based controller (CURRENT mode); velocity: the "
    "robot's stiff Cartesian velocity controller (VELOCITY mode, not compliant; the paper's "
    "reference in Exp. 2).",
)
@gains_option(
    "Impedance gains preset, figures of the Gen3 Lite. tracking: K_d 400 N/m, D_d 30 N s/m, "
    "Eq. (16) with the at-rest friction direction of the motion torque tau - g, t 0.02 rad/s, "
    "nullspace damping 0.3 (holds about 1 mm against the arm's full friction); paper: the "
    "paper's K_d 40 N/m, D_d 3 N s/m, sign(tau), t 0.3 rad/s (with full friction the arm "
    "sticks: centimetres). Other arms: the figures their model declares, else these scaled to "
    "the arm's apparent mass and reach (jaxcomp.control.presets); the run prints them."
)
@click.option(
    "--stiffness",
    type=float,
    default=None,
    help="Cartesian stiffness K_d, N/m, every axis (default: the preset's).",
)
@click.option(
    "--damping",
    type=float,
    default=None,
    help="Cartesian damping D_d, N s/m, every axis (default: the preset's).",
)
@click.option("--viewer", is_flag=True, help="Show the MuJoCo viewer (sim, needs a display).")
@click.option(
    "--realtime/--lockstep",
    default=None,
    help="Pace the loop on the wall clock at 1 kHz, or run lock step with the simulator as "
    "fast as the CPU allows. Default: lock step, real time with --viewer; kortex is always "
    "real time.",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="control_run",
    show_default=True,
    help="Directory for recording.npz (1 kHz, plus target/ee/base/command) and timing.json.",
)
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace the recording of an earlier run in --out (without it, such a folder is refused).",
)
@rt_priority_option(
    "Real time only: run the loop under SCHED_FIFO at this priority when the OS allows it "
    "(root or CAP_SYS_NICE; otherwise it runs as usual); 0: never."
)
@click.option("--seed", type=int, default=0, show_default=True, help="Simulator truth and noise.")
@ip_option
@click.option(
    "--friction-compensation/--no-friction-compensation",
    default=True,
    show_default=True,
    help="Eq. (16)'s friction compensation in the impedance controller's current (off: r tau "
    "alone; the joints then stick within their friction band).",
)
@console_options(
    "the run: the arm, the target, the force a person applies, currents, timing; "
    "stop and live gains from the page"
)
def control(**options) -> None:
    """Run the compliant arm (current-based impedance control) with the base follower.

    The controller works at 1 kHz in the arm's base frame; the base (when there is one)
    follows the end effector (paper Eq. 20). Any arm model works: its current-controlled
    joints, end effector, posture ('preferred' keyframe, else a start pose chosen on the model),
    current limits and gains come from the model; the simulated arm starts at its 'home' pose
    (same fallback), the real one where it stands. Any fault,
    stale or NaN feedback, out-of-range command or Ctrl-C ends the run with the arm in
    position mode and the base stopped. Prints the gains, how the run ended, the RMS tracking
    error (m) and the loop timing. One run at a time writes into --out (a lock file).

    Targets the arm alone must reach (guidance mode, or tracking without a base) are checked
    against its reach (the sum of its links' lengths) before the run; a run whose end
    effector stays off its target (see --max-error) ends early.

    Exit status: 0 when the run completed (or was stopped with Ctrl-C); 1 when it ran but
    ended early (a fault, a watchdog trip, not tracking, the simulator unstable: see the
    summary's 'ended:' line); 2 on bad input, with one 'error:' line (nothing was run).
    """
    from pathlib import Path

    from jaxcomp.files import check_outputs, output_folder

    out_dir = options["out_dir"]
    outputs = [("--out", str(Path(out_dir) / name)) for name in (*_EARLIER_RUN, "timing.json")]
    check_outputs(tuple(p for p in [options["params_file"]] if p), outputs)
    with output_folder(out_dir):
        _control(**options)


def _refuse_earlier_run(out_dir: str, overwrite: bool) -> None:
    """InputError when ``out_dir`` holds the recording of an earlier run, unless
    ``overwrite``."""
    from jaxcomp.files import existing

    held = existing(out_dir, _EARLIER_RUN)
    if held and not overwrite:
        raise InputError(
            f"--out {out_dir} holds the recording of an earlier run ({', '.join(held)}): "
            "--overwrite replaces it, or choose another --out"
        )


def _control(
    mode: str,
    backend: str,
    model: str,
    joints: str | None,
    site: str | None,
    params_file: str | None,
    trajectory: str,
    duration: float | None,
    pushes: tuple[str, ...],
    max_error: float | None,
    max_error_time: float,
    law: str,
    preset: str,
    stiffness: float | None,
    damping: float | None,
    viewer: bool,
    realtime: bool | None,
    out_dir: str,
    overwrite: bool,
    rt_priority: int,
    seed: int,
    ip: str,
    friction_compensation: bool,
    console: bool,
    port: int,
    host: str,
    on_disconnect: str,
) -> None:
    """``jaxcomp control`` (see ``control``) once its --out folder is locked."""
    from jaxcomp.control.timing import configure_jax_for_control, realtime_priority

    # each controller step on the calling thread, single-threaded kernels: no thread hand-off
    configure_jax_for_control()

    from jaxcomp.cli.robot_session import (
        attach_console,
        check_kortex_options,
        checked_live_gains,
        chosen_joints,
        close_robot,
        kortex_params,
        open_robot,
        target_marker,
    )
    from jaxcomp.control.loop import run_control
    from jaxcomp.control.mount import ArmMount, arm_model
    from jaxcomp.control.run_link import RunLink, Tuning
    from jaxcomp.control.trajectory import parse_trajectory
    from jaxcomp.robot_params import RobotParams

    spec = parse_trajectory(trajectory)
    push_list = [parse_push(p) for p in pushes]
    _check_run_options(duration, max_error, max_error_time)
    changes = {k: v for k, v in (("stiffness", stiffness), ("damping", damping)) if v is not None}
    if backend == "kortex":
        if push_list:
            raise InputError("--push acts on the simulator only")
        if realtime is False:
            raise InputError("the real robot runs in real time only (drop --lockstep)")
        check_kortex_options(model, joints, site)
        realtime = True
    elif realtime is None:
        realtime = viewer
    params = RobotParams.load(params_file) if params_file is not None else None
    chosen = chosen_joints(joints, params, params_file)
    _refuse_earlier_run(out_dir, overwrite)

    def make_controller(arm_robot, checked):
        return _make_controller(law, preset, changes, arm_robot, checked)

    controller = None
    if backend == "kortex":
        # the params and the controller are checked (and compiled) before the arm is
        # touched: nothing implausible reaches it, and no compile runs while it servos
        gen3, params = kortex_params(params, params_file)
        controller = make_controller(gen3, params)

    opened = None
    try:
        opened = open_robot(
            backend, model, chosen, joints, site, params, params_file, seed, viewer, ip
        )
        arm, base, sim, robot = opened.arm, opened.base, opened.sim, opened.robot
        for text, (start, length, force) in zip(pushes, push_list, strict=True):
            try:  # the simulator's clock starts with the run
                sim.push(sim.t + start, length, force)
            except InputError as exc:
                raise InputError(f"--push {text}: {exc}") from None
        arm_robot = arm_model(robot)
        if controller is None:
            controller = make_controller(arm_robot, opened.params)
        tuning = None
        if law == "impedance":
            tuning = Tuning(
                checked_live_gains(arm_robot, controller.gains, None, None, friction_compensation)
            )
        elif not friction_compensation:
            raise InputError("--no-friction-compensation: for the impedance controller only")
        link = RunLink(tuning=tuning)
        mount = ArmMount.from_model(robot) if base is not None else ArmMount()
        marker = target_marker(sim) if sim is not None else None
        page = None
        if console:
            page = attach_console(opened, controller, link, port, host, on_disconnect)
        try:
            with realtime_priority(rt_priority if realtime and rt_priority else None):
                result = run_control(
                    arm,
                    base,
                    controller,
                    mode,
                    spec,
                    duration,
                    out_dir,
                    realtime,
                    mount=mount,
                    model=robot.reference,  # the built-in name, else the model file's path
                    on_cycle=marker,
                    max_error=max_error,
                    max_error_time=max_error_time,
                    before_start=lambda length: _check_pushes(pushes, push_list, length),
                    link=link,
                )
        finally:
            if page is not None:
                page.status(state="ended", detail="the run is over", arm_modes="position")
                page.close()
    finally:
        if opened is not None:
            close_robot(opened)
    click.echo(result.summary())
    if result.file_error is not None:
        raise FileError(result.file_error)
    if not result.ok:
        raise SystemExit(1)


def _check_run_options(duration: float | None, max_error: float | None, max_error_time: float):
    """InputError for a --duration, --max-error or --max-error-time out of range."""
    if duration is not None:
        checks.number(duration, "--duration", positive=True, unit="s")
    if max_error is not None and not max_error > 0:
        raise InputError(f"--max-error must be > 0 m (inf: never), got {max_error}")
    checks.number(max_error_time, "--max-error-time", positive=True, unit="s")


def _make_controller(law: str, preset: str, changes: dict, arm_robot, checked):
    """The run's controller on the arm-alone model, compiled: the velocity controller, or the
    impedance controller with the ``preset`` gains and the option's ``changes`` (checked as
    live gains are) and the ``checked`` params (``CheckedParams``, None: nominal)."""
    from jaxcomp.control.impedance import make_impedance_controller
    from jaxcomp.control.presets import check_live_gains, impedance_gains
    from jaxcomp.control.velocity import make_velocity_controller

    if law == "velocity":
        controller = make_velocity_controller(arm_robot)
    else:
        gains = impedance_gains(arm_robot, preset, **changes)
        check_live_gains(arm_robot, gains.stiffness[0], gains.damping[0])
        controller = make_impedance_controller(arm_robot, checked, gains)
        click.echo(_describe_gains(preset, controller), err=True)
    click.echo(f"compiling the controller for {arm_robot.name} ...", err=True)
    if hasattr(controller, "compile"):
        controller.compile()
    return controller


def _check_pushes(texts, pushes, duration: float) -> None:
    """InputError for a push (``parse_push``'s, from the option ``texts``) that starts at
    or after the end of a run of ``duration`` s: it would never act."""
    for text, (start, _, _) in zip(texts, pushes, strict=True):
        if start >= duration:
            raise InputError(
                f"--push {text}: starts at {start:g} s, after the run ends at {duration:g} s "
                "(--duration, else the trajectory's length or 10 s)"
            )


def _describe_gains(preset: str, controller) -> str:
    """One line: the impedance gains of the run (per-joint figures as their range)."""
    import numpy as np

    g, j = controller.gains, controller.joint

    def span(values, fmt: str) -> str:
        lo, hi = float(min(values)), float(max(values))
        return format(lo, fmt) if lo == hi else f"{lo:{fmt}}-{hi:{fmt}}"

    rate = np.broadcast_to(g.current_rate_limit, j.limit.shape)
    return (
        f"gains ({preset}) for {controller.robot.name}: K_d {span(g.stiffness, '.4g')} N/m, "
        f"D_d {span(g.damping, '.4g')} N s/m, K_n {span(j.stiffness, '.3g')} N m/rad, "
        f"D_n {span(j.damping, '.3g')} N m s/rad, error clip {g.error_clip:.3g} m, "
        f"current limit {span(j.limit, '.3g')} A, rate limit {span(rate, '.4g')} A/s"
    )
