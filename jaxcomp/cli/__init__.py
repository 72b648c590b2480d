"""The ``jaxcomp`` command line: the one place that wires models, hardware, identify, control.

Each command is a module of this package registering itself on ``cli`` (``group.py``); importing
the package imports them all. Heavy imports happen inside the commands, so ``--help`` is quick.
"""

from jaxcomp.cli import (  # noqa: F401  (registers the commands)
    bench,
    calibrate,
    check,
    console,
    control,
    info,
    models,
    study,
    study_calibration,
    study_control,
)
from jaxcomp.cli.group import cli, main

__all__ = ["cli", "main"]
