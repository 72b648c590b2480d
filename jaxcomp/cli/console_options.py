"""The options that attach the browser console: ``--console``, ``--port``, ``--host``,
``--on-disconnect`` (``jaxcomp console``, ``control --console``, ``calibrate --console``)."""

from __future__ import annotations

from collections.abc import Callable

import click

from jaxcomp.console.link import ON_LOST


def page_options(f: Callable) -> Callable:
    """``--port``, ``--host`` and ``--on-disconnect``.

    Args:
        f: the command function.

    Returns:
        ``f`` with the options.
    """
    f = click.option(
        "--on-disconnect",
        type=click.Choice(ON_LOST),
        default="continue",
        show_default=True,
        help="When the last browser disconnects or the page's server dies: continue the run, "
        "or stop it safely (arm in position mode, base stopped).",
    )(f)
    f = click.option(
        "--host",
        default="127.0.0.1",
        show_default=True,
        help="Address the page is served on: 127.0.0.1 for this computer (or an SSH tunnel: "
        "ssh -L 8080:localhost:8080 robot-pc); 0.0.0.0 for any device on the network, e.g. a "
        "phone (anyone who reaches it can drive the robot).",
    )(f)
    return click.option(
        "--port",
        type=click.IntRange(1, 65535),
        default=8080,
        show_default=True,
        help="TCP port of the page (a busy one: the next free one; the URL is printed).",
    )(f)


def console_options(what: str) -> Callable:
    """``--console`` (showing ``what``) and ``page_options``.

    Args:
        what: what the console shows, completing the flag's help text.

    Returns:
        The decorator adding the options.
    """

    def add(f: Callable) -> Callable:
        f = page_options(f)
        return click.option(
            "--console",
            is_flag=True,
            help=f"Serve the browser console (see `jaxcomp console`) showing {what}; the URL "
            "is printed.",
        )(f)

    return add
