"""`jaxcomp study`: Monte-Carlo studies over thousands of simulated robots (MJX).

The subcommands live in their own modules and register on the ``study`` group defined here.
"""

import functools
import os
import tempfile
from pathlib import Path
from typing import Any

from jaxcomp.cli.group import cli
from jaxcomp.errors import InputError

#: The robot the studies simulate (a built-in model).
MODEL = "gen3_lite"


@cli.group()
def study() -> None:
    """Monte-Carlo studies on MJX: many simulated robots, each with its own hidden truth.

    Worlds are sharded over every accelerator present (GPUs of one host; CPU with small
    --worlds). A rerun with the same --seed reproduces the numbers exactly.
    """


@functools.cache
def simulator(devices: int | None) -> Any:
    """One ``MjxSimulator`` per device count per process, shared by the studies: its compiled
    programs are kept."""
    from jaxcomp.hardware.mjx_sim import MjxSimulator, batch_mesh

    return MjxSimulator(MODEL, mesh=batch_mesh(devices))


def check_out_dir(out: Path) -> Path:
    """Create ``out`` if needed and check that files can be written in it (InputError)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"cannot write to --out {out}: {exc.strerror or exc}") from None
    return out
