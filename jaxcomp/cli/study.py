"""`jaxcomp study`: Monte-Carlo studies over thousands of simulated robots (MJX).

The subcommands live in their own modules and register on the ``study`` group defined here,
with what every study command shares: its scale options (``scale_options``) and its run into
the report folder (``run_into``). The studies themselves are the library ``jaxcomp.studies``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from jaxcomp.cli.group import cli
from jaxcomp.cli.model_options import joint_names

if TYPE_CHECKING:
    from jaxcomp.studies.processes import Processes

R = TypeVar("R")


@cli.group()
def study() -> None:
    """Monte-Carlo studies on MJX: many simulated robots, each with its own hidden truth.

    Worlds are sharded over every accelerator present (GPUs of one host; CPU with small
    --worlds). A rerun with the same --seed reproduces the numbers exactly.
    """


def scale_options(command: Callable) -> Callable:
    """The options of a study of any size: its chunks on disk, --resume, and several
    processes (``jaxcomp.studies.processes``).

    Args:
        command: the study command.

    Returns:
        It with ``--chunk-worlds``, ``--resume``, ``--distributed``, ``--coordinator``,
        ``--num-processes`` and ``--process-id``.
    """
    options = [
        click.option(
            "--chunk-worlds",
            type=int,
            default=None,
            help="Worlds per chunk: the study runs chunk by chunk, each finished chunk saved in "
            "DIR/chunks until the report is written. Default: 4096 per device (the whole study "
            "when it has fewer; with --resume, the interrupted study's).",
        ),
        click.option(
            "--resume",
            is_flag=True,
            help="Keep the finished chunks of an interrupted study in DIR and run the others; "
            "refused when its settings (model, seed, worlds, --chunk-worlds, ...) differ.",
        ),
        click.option(
            "--distributed",
            is_flag=True,
            help="One study over several processes (jax.distributed), each running every P-th "
            "chunk on its own devices into the shared DIR, process 0 writing the report; under "
            "SLURM (srun) and Open MPI (mpirun) the processes are found, otherwise give the "
            "three options below.",
        ),
        click.option(
            "--coordinator",
            default=None,
            help="HOST:PORT of process 0's coordinator (with --distributed; default: "
            "$JAX_COORDINATOR_ADDRESS, or SLURM's / Open MPI's).",
        ),
        click.option(
            "--num-processes", type=int, default=None, help="Processes P (--distributed)."
        ),
        click.option(
            "--process-id",
            type=int,
            default=None,
            help="This process's id, 0..P-1 (--distributed).",
        ),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def run_into(
    study_into: Callable[..., R | None],
    settings: Any,
    out_dir: str,
    *,
    model: str,
    joints: str | None,
    site: str | None,
    progress: bool,
    resume: bool,
    processes: Processes,
) -> R | None:
    """The tail every study command shares: the studied robot loaded and the study run into
    its report folder.

    Args:
        study_into: the study's one call (``jaxcomp.studies.*.study_into``).
        settings: the study's settings.
        out_dir: the report folder (``--out``).
        model, joints, site: ``--model``, ``--joints``, ``--site`` (``model_options``).
        progress, resume: ``--progress``, ``--resume``.
        processes: this process among the study's (``processes.start_processes``).

    Returns:
        The study's outputs on process 0; None on the others, which say that their chunks are
        done.
    """
    from jaxcomp.robot import load_robot

    robot = load_robot(model, joints=joint_names(joints), site=site)
    result = study_into(
        Path(out_dir), settings, progress=progress, robot=robot, resume=resume,
        processes=processes,
    )  # fmt: skip
    if result is None:
        click.echo(f"process {processes.index}: its chunks are done; process 0 writes the report")
    return result
