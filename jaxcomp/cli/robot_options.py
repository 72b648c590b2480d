"""The options that choose the robot and how it is driven, shared by the commands that drive
it: ``--robot``, ``--params``, ``--gains``, ``--rt-priority``, ``--ip``."""

from __future__ import annotations

from collections.abc import Callable

import click

#: ``--gains``: the impedance presets (``jaxcomp.control.gains.IMPEDANCE_PRESETS``).
PRESETS = ("tracking", "paper")


def backend_option(help: str) -> Callable:
    """``--robot sim|kortex`` (into ``backend``).

    Args:
        help: its help text.

    Returns:
        The ``click.option`` decorator.
    """
    return click.option(
        "--robot",
        "backend",
        type=click.Choice(["sim", "kortex"]),
        default="sim",
        show_default=True,
        help=help,
    )


def params_option(help: str) -> Callable:
    """``--params FILE`` (into ``params_file``).

    Args:
        help: its help text.

    Returns:
        The ``click.option`` decorator.
    """
    return click.option(
        "--params", "params_file", type=click.Path(dir_okay=False), default=None, help=help
    )


def gains_option(help: str) -> Callable:
    """``--gains tracking|paper`` (into ``preset``).

    Args:
        help: its help text.

    Returns:
        The ``click.option`` decorator.
    """
    return click.option(
        "--gains", "preset", type=click.Choice(PRESETS), default="tracking", show_default=True,
        help=help,
    )  # fmt: skip


def rt_priority_option(help: str) -> Callable:
    """``--rt-priority 0-99``.

    Args:
        help: its help text.

    Returns:
        The ``click.option`` decorator.
    """
    return click.option(
        "--rt-priority", type=click.IntRange(0, 99), default=50, show_default=True, help=help
    )


def ip_option(f: Callable) -> Callable:
    """``--ip`` of the real arm.

    Args:
        f: the command function.

    Returns:
        ``f`` with the option.
    """
    return click.option(
        "--ip", default="192.168.1.10", show_default=True, help="Arm address (kortex)."
    )(f)
