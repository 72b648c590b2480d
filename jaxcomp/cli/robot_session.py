"""The robot a command drives: opened, its params checked once, its console, closed.

``jaxcomp control`` and ``jaxcomp console`` drive the same robots the same way: the simulated
model (``--model``, reduced to the current-controlled joints of ``--joints`` or the params
file's: ``chosen_joints``) or the real Gen3 Lite with its Dingo-O base (``--robot kortex``).
``open_robot`` opens it as an ``Opened`` (arm, base, simulator, the whole model and the params
for the arm-alone model, checked once: ``plausibility.checked_arm_params``) and
``close_robot`` closes it (arm in POSITION mode, base stopped). On the real robot the params
are checked (``kortex_params``) before the arm is touched. ``checked_live_gains`` checks live
gains as --stiffness and --damping are checked; ``attach_console`` serves a run's browser
console; ``target_marker`` draws the target in the simulator's viewer.

Heavy imports happen inside the functions: the commands' ``--help`` stays quick.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import click

from jaxcomp.cli.kortex_backend import open_kortex_arm
from jaxcomp.cli.model_options import joint_names
from jaxcomp.errors import InputError, ModelError

#: The simulated robot when --model is not given: the Gen3 Lite on its Dingo-O base.
DEFAULT_MODEL = "mobile_gen3_lite"


class Opened(NamedTuple):
    """The robot a command drives.

    Attributes:
        arm: the ``Arm``. base: the ``Base`` (None: none). sim: the ``Simulator`` (None on
            the real robot). robot: the whole model (the mobile one with a base). params: the
            ``plausibility.CheckedParams`` for the arm-alone model (None: nominal).
    """

    arm: Any
    base: Any
    sim: Any
    robot: Any
    params: Any


def check_kortex_options(model: str, joints: str | None, site: str | None) -> None:
    """Refuse the simulator's model options given with ``--robot kortex``.

    Args:
        model: --model. joints: --joints. site: --site.

    Raises:
        InputError: naming the options given.
    """
    options = (("--model", model != DEFAULT_MODEL), ("--joints", joints), ("--site", site))
    given = [name for name, value in options if value]
    if given:
        raise InputError(
            f"{', '.join(given)}: for the simulator only (--robot kortex drives the Gen3 Lite)"
        )


def chosen_joints(text: str | None, params, params_file: str | None) -> list[str] | None:
    """The current-controlled joints: --joints, else the params file's, else None.

    Args:
        text: --joints (names separated by commas), or None.
        params: the params file's ``RobotParams``, or None.
        params_file: its path, named in the error.

    Returns:
        The joint names, or None (the model's own).

    Raises:
        InputError: an empty --joints, or --joints other than the params file's.
    """
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


def kortex_params(params, params_file: str | None):
    """The Gen3 Lite's model and the params checked for it, before the real arm is touched.

    Args:
        params: the params file's ``RobotParams`` (for the Gen3 Lite or its mobile model), or
            None.
        params_file: its path, named in the errors.

    Returns:
        (the Gen3 Lite's ``Robot``, ``CheckedParams`` or None: nominal).

    Raises:
        InputError: params for another model, not fitting the arm, or implausible.
    """
    from jaxcomp.control.mount import mobile_model_name
    from jaxcomp.robot import load_robot

    gen3 = load_robot("gen3_lite")
    if params is None:
        return gen3, None
    return gen3, _checked(params, params_file, load_robot(mobile_model_name(gen3)), gen3)


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
    """Open the robot a command drives, with its params checked once.

    Args:
        backend: "sim" (the simulated ``model``, reduced to the ``chosen`` joints, its arm at
            its 'home' pose) or "kortex" (the real Gen3 Lite at ``ip``, with its Dingo-O base
            when ROS 2 is there).
        model: --model. chosen: ``chosen_joints``'. joints: --joints. site: --site.
        params: the params file's ``RobotParams`` (checked here against the model), the
            ``CheckedParams`` of ``kortex_params`` (taken as they are), or None (nominal).
        params_file: its path, named in the errors.
        seed: the simulator's truth and noise. viewer: show the simulator's viewer.
        ip: the real arm's address.

    Returns:
        The ``Opened`` robot.

    Raises:
        InputError, ModelError: params or a model that do not fit; nothing is left open.
    """
    from jaxcomp.control.mount import arm_model, mobile_model_name
    from jaxcomp.robot import load_robot
    from jaxcomp.robot_params import arm_joint_indices

    if backend == "sim":
        from jaxcomp.hardware import Simulator

        from_params = params if joints is None else None
        robot = _load_model(model, chosen, site, from_params, params_file)
        if not len(arm_joint_indices(robot)):
            raise ModelError(f"{robot.name} has no arm joints: nothing to control")
        checked = _checked(params, params_file, robot, arm_model(robot))  # before anything
        sim = Simulator(robot, seed=seed, viewer=viewer, initial_pose="home")
        return Opened(sim.arm, sim.base if sim.has_base else None, sim, robot, checked)
    from jaxcomp.hardware import DingoBase

    robot = load_robot("gen3_lite")
    checked = _checked(params, params_file, load_robot(mobile_model_name(robot)), robot)
    # the loop paces the cycles itself (absolute 1 kHz deadlines)
    arm = open_kortex_arm(ip, robot="gen3_lite", pace=False)
    try:
        base = DingoBase()
    except ImportError as exc:
        click.echo(f"no base: {exc}", err=True)
        base = None
    if base is not None:
        robot = load_robot(mobile_model_name(robot))
    return Opened(arm, base, None, robot, checked)


def close_robot(opened: Opened) -> None:
    """Arm to position mode, base stopped, connections closed (the simulator's viewer too).

    Args:
        opened: what ``open_robot`` opened.
    """
    if opened.sim is not None:
        opened.sim.close()
        return
    for part in (opened.arm, opened.base):
        if part is not None:
            part.close()


def checked_live_gains(arm_robot, gains, stiffness, damping, friction_compensation: bool):
    """The live gains of a run, within the arm's safe ranges (``presets.check_live_gains``,
    the same check for the command line and the console).

    Args:
        arm_robot: the arm-alone model.
        gains: the controller's ``ImpedanceGains``.
        stiffness: K_d, N/m, every axis (None: the gains').
        damping: D_d, N s/m, every axis (None: the gains').
        friction_compensation: on or off.

    Returns:
        (``impedance_io.LIVE_SIZE``,) the live gains (``impedance_io.live_gains``).

    Raises:
        InputError: gains outside the safe ranges.
    """
    from jaxcomp.control.impedance_io import live_gains
    from jaxcomp.control.presets import check_live_gains

    k = gains.stiffness[0] if stiffness is None else stiffness
    d = gains.damping[0] if damping is None else damping
    k, d = check_live_gains(arm_robot, k, d)
    return live_gains(k, d, bool(friction_compensation))


def attach_console(opened: Opened, controller, link, port: int, host: str, on_lost: str):
    """The browser console of a ``jaxcomp control`` run (``jaxcomp.console``): it shows the
    run and takes stop and live gains (checked as --stiffness and --damping are).

    Args:
        opened: the robot. controller: the run's controller. link: the run's ``RunLink``
            (its monitor is set to the page's feed).
        port, host: where the page is served. on_lost: what a lost page does ("continue",
            "stop").

    Returns:
        The ``console.link.ConsoleLink`` (close it after the run).
    """
    from jaxcomp.console.link import ConsoleLink
    from jaxcomp.control.mount import arm_model
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


def target_marker(sim):
    """An ``on_cycle`` hook drawing the target as a red sphere in the simulator's viewer
    (about 50 Hz). Drawing problems never stop the loop.

    Args:
        sim: the ``Simulator``.

    Returns:
        ``on_cycle(k, state, command, target)`` (target (3,) world m), or None without a
        viewer.
    """
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


def _checked(params, params_file: str | None, robot, arm_robot):
    """``params`` for the arm-alone model ``arm_robot`` of ``robot``, checked once
    (``plausibility.checked_arm_params``); already checked ones and None as they are."""
    from jaxcomp.plausibility import CheckedParams, checked_arm_params

    if params is None or isinstance(params, CheckedParams):
        return params
    return checked_arm_params(params, arm_robot, robot, params_file)


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


__all__ = [
    "DEFAULT_MODEL",
    "Opened",
    "attach_console",
    "check_kortex_options",
    "checked_live_gains",
    "chosen_joints",
    "close_robot",
    "kortex_params",
    "open_robot",
    "target_marker",
]
