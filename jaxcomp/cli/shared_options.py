"""Option decorators of the forms several commands share: a choice among named values whose
first is the default, and the joint JAX fit's ``--com-prior``."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import click


def choice_option(*names: str, choices: Sequence[str], help: str) -> Callable:
    """An option taking one of ``choices``, the first the default (shown in --help).

    Args:
        names: the option's name and, optionally, its parameter's (as ``click.option``).
        choices: the values it takes, the default first.
        help: its help text.

    Returns:
        The ``click.option`` decorator.
    """
    return click.option(*names, type=click.Choice(list(choices)), default=choices[0],
                        show_default=True, help=help)  # fmt: skip


def com_prior_option(help: str) -> Callable:
    """``--com-prior M``: the fit's prior standard deviation of every link's COM offset per
    axis, > 0 m (default None: the command's own).

    Args:
        help: its help text (what the default is).

    Returns:
        The ``click.option`` decorator.
    """
    return click.option("--com-prior", type=click.FloatRange(min=0.0, min_open=True),
                        default=None, help=help)  # fmt: skip
