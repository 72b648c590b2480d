"""`jaxcomp console`: the robot in the browser, and driven from it."""

from __future__ import annotations

import click

from jaxcomp.cli.console_options import page_options
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


@cli.command()
@backend_option(
    "sim: the MuJoCo simulator (calibrations run as fast as the CPU allows); kortex: the real "
    "Gen3 Lite (kortex_api) and, when ROS 2 is available, the Dingo-O."
)
@model_options(DEFAULT_MODEL, "Simulated robot (sim only; as `jaxcomp control`)")
@params_option(
    "Identified params JSON for the controller (default: the model's nominal figures; a "
    "calibration from the page replaces them)."
)
@gains_option(
    "Impedance gains preset (see `jaxcomp control --gains`): the page starts from its "
    "stiffness and damping."
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="console_runs",
    show_default=True,
    help="Folder for the runs (run-NNN/recording.npz, timing.json) and calibrations "
    "(calibration-NNN/recording.npz, params.json) started from the page.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Simulator truth and noise.")
@ip_option
@rt_priority_option(
    "Run the control thread under SCHED_FIFO at this priority when the OS allows it; 0: never."
)
@click.option(
    "--duration",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="s: close the console after this long (default: until Ctrl-C).",
)
@page_options
def console(**options) -> None:
    """Serve the operator console: see the robot and drive it from a browser.

    The page shows the arm and its base in 3D (from the model), the target and the end
    effector's trail, the force a person applies on the end effector (estimated from the
    motor currents, with the friction band it cannot be resolved within at rest) as an arrow,
    each joint's current against the model's prediction, the tracking error, the loop's
    period histogram and missed deadlines, the arm's modes, faults and identified ratios.

    From the page: start guidance or tracking along a trajectory, set the impedance gains
    within their safe ranges and friction compensation on or off (at once, in a running
    loop), calibrate (with its progress) and fit, stop (arm in position mode, base stopped)
    and clear faults. Every command is checked as the command line checks it; a refused one
    shows its error on the page. Between jobs the arm holds in position mode.

    The page is served by its own process, fed 30 times a second: the 1 kHz loop never
    waits for it. Open the printed URL (over SSH: ssh -L 8080:localhost:8080 robot-pc).
    """
    from jaxcomp.files import output_folder

    with output_folder(options["out_dir"]):
        _console(**options)


def _console(
    backend: str,
    model: str,
    joints: str | None,
    site: str | None,
    params_file: str | None,
    preset: str,
    out_dir: str,
    seed: int,
    ip: str,
    rt_priority: int,
    duration: float | None,
    port: int,
    host: str,
    on_disconnect: str,
) -> None:
    """``jaxcomp console`` once its --out folder is locked."""
    import threading
    from pathlib import Path

    from jaxcomp.control.timing import configure_jax_for_control, realtime_priority

    configure_jax_for_control()

    from jaxcomp.cli.robot_session import (
        check_kortex_options,
        chosen_joints,
        close_robot,
        kortex_params,
        open_robot,
    )
    from jaxcomp.console.operator import Operator
    from jaxcomp.control.impedance import make_impedance_controller
    from jaxcomp.control.mount import arm_model
    from jaxcomp.control.presets import impedance_gains
    from jaxcomp.robot_params import RobotParams

    params = RobotParams.load(params_file) if params_file is not None else None
    chosen = chosen_joints(joints, params, params_file)

    def make_controller(arm_robot, checked):
        controller = make_impedance_controller(
            arm_robot, checked, impedance_gains(arm_robot, preset)
        )
        click.echo(f"compiling the controller for {arm_robot.name} ...", err=True)
        controller.compile()
        return controller

    controller = None
    if backend == "kortex":
        check_kortex_options(model, joints, site)
        gen3, params = kortex_params(params, params_file)  # checked before the arm is opened
        controller = make_controller(gen3, params)
    opened = None
    link = None
    try:
        opened = open_robot(
            backend, model, chosen, joints, site, params, params_file, seed, False, ip
        )
        if controller is None:
            controller = make_controller(arm_model(opened.robot), opened.params)
        operator = Operator(
            opened.arm,
            opened.base,
            opened.sim,
            opened.robot,
            controller,
            preset,
            Path(out_dir),
            realtime=True,
        )
        if params_file is not None:
            operator.params_name = params_file
        title = f"{opened.robot.name} ({'simulator' if opened.sim is not None else ip})"
        link = operator.serve(port, host, title, on_disconnect)
        click.echo(f"console: {link.url}  (Ctrl-C ends it)", err=True)
        if duration is not None:
            timer = threading.Timer(duration, operator.close)
            timer.daemon = True
            timer.start()
        with realtime_priority(rt_priority or None):
            operator.run()
    finally:
        if link is not None:
            link.close()
        if opened is not None:
            close_robot(opened)
