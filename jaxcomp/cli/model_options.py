"""The options that name the robot model: ``--model``, ``--joints``, ``--site``."""

from __future__ import annotations

from collections.abc import Callable

import click


def model_options(default: str, what: str = "Robot model") -> Callable:
    """Decorator adding ``--model`` (default ``default``), ``--joints`` and ``--site``.

    Args:
        default: the default model, a built-in name or a model file.
        what: what the model is, starting ``--model``'s help text.

    Returns:
        The decorator adding the options.
    """

    def add(f: Callable) -> Callable:
        f = click.option(
            "--site",
            default=None,
            metavar="NAME",
            help="End-effector site when the model names none (custom text "
            "jaxcomp_end_effector) and has no site 'end_effector'; default: the origin of the "
            "last body of the chain.",
        )(f)
        f = click.option(
            "--joints",
            default=None,
            metavar="NAME,NAME,...",
            help="Current-controlled joints (default: the model's jaxcomp_joints, else every "
            "hinge joint no equality constraint couples); the others are held in position.",
        )(f)
        return click.option(
            "--model",
            default=default,
            show_default=True,
            metavar="NAME|PATH",
            help=f"{what}: a built-in name (jaxcomp models) or an MJCF (.xml) / URDF file.",
        )(f)

    return add


def joint_names(text: str | None) -> tuple[str, ...] | None:
    """``--joints`` as names (None when not given).

    Args:
        text: --joints, comma-separated names (blanks around and empty names ignored).

    Returns:
        The names in order, or None.
    """
    if text is None:
        return None
    return tuple(n.strip() for n in text.split(",") if n.strip())
