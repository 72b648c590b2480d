"""`jaxcomp control`: guidance or tracking mode on the simulator or the real robot."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import click

from jaxcomp.cli.console_options import console_options
from jaxcomp.cli.group import cli
from jaxcomp.cli.kortex_backend import open_kortex_arm
from jaxcomp.cli.model_options import joint_names, model_options
from jaxcomp.cli.robot_options import (
    backend_option,
    gains_option,
    ip_option,
    params_option,
    rt_priority_option,
)
from jaxcomp.errors import FileError, InputError, ModelError

#: The simulated robot when --model is not given: the Gen3 Lite on its Dingo-O base.
DEFAULT_MODEL = "mobile_gen3_lite"
#: What an earlier run left in --out: ``control.loop.RECORDING`` and its part files.
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
    """'START,DURATION,FX,FY,FZ' (s, s, N world) -> (start, duration, force)."""
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


def _model_name(robot) -> str:
    """The recording's ``model`` field: the built-in name, else the model file's path."""
    return robot.reference


def _target_marker(sim):
    """An ``on_cycle`` hook drawing the target as a red sphere in the simulator's viewer
    (about 50 Hz), or None without a viewer. Drawing problems never stop the loop."""
    viewer = sim.viewer
    if viewer is None:
        return None
    import mujoco
    import numpy as np

    size, rgba, eye = np.array([0.015, 0.0, 0.0]), np.array([0.9, 0.1, 0.1, 0.8]), np.eye(3)

    def on_cycle(k, state, command, target) -> None:
        if k % 20:
            return
        try:
            with viewer.lock():
                scn = viewer.user_scn
                mujoco.mjv_initGeom(
                    scn.geoms[0], mujoco.mjtGeom.mjGEOM_SPHERE, size, target, eye.ravel(), rgba
                )
                scn.ngeom = 1
        except Exception:  # noqa: BLE001, S110 - a marker must never end a run
            pass

    return on_cycle


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

    from jaxcomp.control.impedance import make_impedance_controller
    from jaxcomp.control.loop import ArmMount, arm_model, run_control
    from jaxcomp.control.presets import check_live_gains, impedance_gains
    from jaxcomp.control.run_link import RunLink, Tuning
    from jaxcomp.control.trajectory import parse_trajectory
    from jaxcomp.control.velocity import make_velocity_controller
    from jaxcomp.robot_params import RobotParams

    spec = parse_trajectory(trajectory)
    push_list = [parse_push(p) for p in pushes]
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise InputError(f"--duration must be a positive number of s, got {duration}")
    if max_error is not None and not max_error > 0:
        raise InputError(f"--max-error must be > 0 m (inf: never), got {max_error}")
    if not (math.isfinite(max_error_time) and max_error_time > 0):
        raise InputError(f"--max-error-time must be a positive number of s, got {max_error_time}")
    changes = {}
    if stiffness is not None:
        changes["stiffness"] = stiffness
    if damping is not None:
        changes["damping"] = damping

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
    chosen = _chosen_joints(joints, params, params_file)
    _refuse_earlier_run(out_dir, overwrite)

    def make_controller(arm_robot, params):
        if law == "velocity":
            controller = make_velocity_controller(arm_robot)
        else:
            gains = impedance_gains(arm_robot, preset, **changes)
            check_live_gains(arm_robot, gains.stiffness[0], gains.damping[0])
            controller = make_impedance_controller(arm_robot, params, gains)
            click.echo(_describe_gains(preset, controller), err=True)
        click.echo(f"compiling the controller for {arm_robot.name} ...", err=True)
        if hasattr(controller, "compile"):
            controller.compile()
        return controller

    controller = None
    if backend == "kortex":
        # the params and the controller are checked (and compiled) before the arm is
        # touched: nothing implausible reaches it, and no compile runs while it servos
        gen3, checked = kortex_params(params, params_file)
        controller = make_controller(gen3, checked)

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
        marker = _target_marker(sim) if sim is not None else None
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
                    model=_model_name(robot),
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


class Opened(NamedTuple):
    """The robot a command drives: ``arm``, ``base`` (None: none), ``sim`` (the
    ``Simulator``, None on the real robot), ``robot`` (the whole model: the mobile one with a
    base) and ``params`` (checked, for the arm-alone model; None: nominal)."""

    arm: Any
    base: Any
    sim: Any
    robot: Any
    params: Any


def check_kortex_options(model: str, joints, site) -> None:
    """InputError for the simulator's model options given with ``--robot kortex``."""
    options = (("--model", model != DEFAULT_MODEL), ("--joints", joints), ("--site", site))
    given = [name for name, value in options if value]
    if given:
        raise InputError(
            f"{', '.join(given)}: for the simulator only (--robot kortex drives the Gen3 Lite)"
        )


def kortex_params(params, params_file: str | None):
    """(the Gen3 Lite's model, ``params`` checked for it) before the real arm is touched."""
    from jaxcomp.control.loop import mobile_model_name
    from jaxcomp.robot import load_robot

    gen3 = load_robot("gen3_lite")
    mobile = load_robot(mobile_model_name(gen3))
    return gen3, None if params is None else _arm_params(params, params_file, mobile, gen3)


def open_robot(
    backend: str,
    model: str,
    chosen,
    joints,
    site,
    params,
    params_file,
    seed: int,
    viewer: bool,
    ip: str,
) -> Opened:
    """The simulated ``model`` (reduced to the ``chosen`` joints; its arm at its 'home'
    pose) or the real Gen3 Lite at ``ip`` with its Dingo-O base when ROS 2 is there; the
    params checked against it (``_arm_params``)."""
    from jaxcomp.control.loop import arm_model, mobile_model_name
    from jaxcomp.robot import load_robot
    from jaxcomp.robot_params import arm_joint_indices

    if backend == "sim":
        from jaxcomp.hardware import Simulator

        from_params = params if joints is None else None
        robot = _load_model(model, chosen, site, from_params, params_file)
        if not len(arm_joint_indices(robot)):
            raise ModelError(f"{robot.name} has no arm joints: nothing to control")
        if params is not None:  # checked before anything is built
            params = _arm_params(params, params_file, robot, arm_model(robot))
        sim = Simulator(robot, seed=seed, viewer=viewer, initial_pose="home")
        return Opened(sim.arm, sim.base if sim.has_base else None, sim, robot, params)
    from jaxcomp.hardware import DingoBase

    # the loop paces the cycles itself (absolute 1 kHz deadlines)
    arm = open_kortex_arm(ip, robot="gen3_lite", pace=False)
    try:
        base = DingoBase()
    except ImportError as exc:
        click.echo(f"no base: {exc}", err=True)
        base = None
    robot = load_robot("gen3_lite")
    if base is not None:
        robot = load_robot(mobile_model_name(robot))
    if params is not None:
        params = _arm_params(params, params_file, robot, arm_model(robot))
    return Opened(arm, base, None, robot, params)


def close_robot(opened: Opened) -> None:
    """Arm to position mode, base stopped, connections closed (the simulator's viewer too)."""
    if opened.sim is not None:
        opened.sim.close()
        return
    for part in (opened.arm, opened.base):
        if part is not None:
            part.close()


def checked_live_gains(arm_robot, gains, stiffness, damping, friction_compensation: bool):
    """The live gains of a run (``impedance_io.live_gains``): ``stiffness`` N/m and ``damping``
    N s/m (None: ``gains``'), within the arm's safe ranges (``presets.check_live_gains``, the
    same check for the command line and the console), friction compensation on or off."""
    from jaxcomp.control.impedance_io import live_gains
    from jaxcomp.control.presets import check_live_gains

    k = gains.stiffness[0] if stiffness is None else stiffness
    d = gains.damping[0] if damping is None else damping
    k, d = check_live_gains(arm_robot, k, d)
    return live_gains(k, d, bool(friction_compensation))


def attach_console(opened: Opened, controller, link, port: int, host: str, on_lost: str):
    """The browser console of a ``jaxcomp control`` run (``jaxcomp.console``): it shows the
    run and takes stop and live gains (checked as --stiffness and --damping are)."""
    from jaxcomp.console.link import ConsoleLink
    from jaxcomp.control.loop import arm_model
    from jaxcomp.control.presets import gain_limits
    from jaxcomp.robot_params import BASE_JOINTS

    arm_robot = arm_model(opened.robot)
    live = link.tuning.values if link.tuning is not None else None

    def handler(name: str, args: dict) -> str:
        if name == "stop":
            link.stop.set()
            return "stopping: arm in position mode, base stopped"
        if name == "gains" and link.tuning is None:
            raise InputError("the velocity controller has no impedance gains to set")
        if name == "gains":
            friction = args.get("friction", True)
            values = checked_live_gains(
                arm_robot, controller.gains, args.get("stiffness"), args.get("damping"), friction
            )
            link.tuning.set(values)
            return f"stiffness {values[0]:g} N/m, damping {values[3]:g} N s/m (now)"
        raise InputError(
            f"{name}: not while the console is attached to `jaxcomp control` (its options set "
            "the mode and trajectory; `jaxcomp console` drives the robot from the page)"
        )

    base_joints = tuple(BASE_JOINTS) if opened.base is not None else ()
    page = ConsoleLink(
        opened.robot,
        tuple(opened.arm.joint_names),
        base_joints,
        handler=handler,
        port=port,
        host=host,
        title=f"jaxcomp control: {opened.robot.name}",
        controls="control",
        gains=None
        if live is None
        else {"stiffness": live[0], "damping": live[3], "friction": bool(live[6])},
        limits=gain_limits(arm_robot)._asdict(),
        on_lost=on_lost,
        on_stop=link.stop.set,
    )
    link.monitor = page.feed
    click.echo(f"console: {page.url}", err=True)
    page.status(state="running", detail="jaxcomp control", arm_modes="switching")
    return page


def _arm_params(params, params_file: str | None, robot, arm_robot):
    """``params`` for the arm-alone model ``arm_robot`` of ``robot``, checked as the
    controller checks them (``plausibility.check_params``); InputError when they name another model
    (a fit names the model as its recording does: by name or by file) or do not fit."""
    from jaxcomp.control.loop import arm_params

    names = {r.name for r in (robot, arm_robot)} | {r.reference for r in (robot, arm_robot)}
    if params.model not in names:
        raise InputError(
            f"{params_file}: the params are for model {params.model!r}, the robot is {robot.name!r}"
        )
    from jaxcomp.plausibility import check_params

    return check_params(arm_params(params, arm_robot), arm_robot, f"the params in {params_file}")


def _check_pushes(texts, pushes, duration: float) -> None:
    """InputError for a push (``parse_push``'s, from the option ``texts``) that starts at
    or after the end of a run of ``duration`` s: it would never act."""
    for text, (start, _, _) in zip(texts, pushes, strict=True):
        if start >= duration:
            raise InputError(
                f"--push {text}: starts at {start:g} s, after the run ends at {duration:g} s "
                "(--duration, else the trajectory's length or 10 s)"
            )


def _chosen_joints(text: str | None, params, params_file: str | None) -> list[str] | None:
    """The current-controlled joints: --joints, else the params file's, else None (the
    model's own); InputError when both are given and differ."""
    listed = None if text is None else list(joint_names(text))
    if listed is not None and not listed:
        raise InputError(f"--joints {text!r}: expected joint names separated by commas")
    from_params = list(params.joints) if params is not None and params.joints else None
    if listed is not None and from_params is not None and listed != from_params:
        raise InputError(
            f"--joints {','.join(listed)} differ from the joints of {params_file}: "
            f"{','.join(from_params)}"
        )
    return listed if listed is not None else from_params


def _load_model(model: str, joints, site, from_params, params_file):
    """``load_robot(model, joints=, site=)``; joints taken from the params ``from_params``
    (None: not from a params file) that do not fit the model are reported against the file."""
    from jaxcomp.robot import load_robot

    try:
        return load_robot(model, joints=joints, site=site)
    except ModelError as exc:
        if joints is not None and from_params is not None:
            raise InputError(
                f"{params_file} is for model {from_params.model!r}, joints {', '.join(joints)}, "
                f"which do not fit {model}: {exc}"
            ) from None
        raise


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
