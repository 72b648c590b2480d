"""A study over several processes and hosts (``jax.distributed``): who runs which chunk, and
how the processes agree on errors.

``start_processes`` joins this process to the others (``jax.distributed.initialize``, before
any JAX computation): by hand with a coordinator address, the process count and this
process's id, or as jax detects them under SLURM (``srun``) and Open MPI (``mpirun``). Each
process runs its own chunks of worlds on its local devices (``Processes.mine``: chunk k on
process k % P), so a chunk's numbers are the same however many processes there are.
``exchange`` is the processes' barrier: every process gives its error (or none) and all get
every process's, so that one process's failure stops all of them with one message instead of
leaving the others waiting.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import NamedTuple, TypeVar

import numpy as np

from jaxcomp.errors import InputError

#: Environment variables of the launchers whose processes ``jax.distributed`` finds itself
#: (SLURM's srun, Open MPI's mpirun).
CLUSTER_VARIABLES = ("SLURM_JOB_ID", "OMPI_MCA_orte_hnp_uri", "OMPI_COMM_WORLD_SIZE")
#: Bytes of an error message that ``exchange`` carries.
MESSAGE_BYTES = 2048
T = TypeVar("T")


class Processes(NamedTuple):
    """This process's ``index`` among ``count`` processes (0 of 1: no jax.distributed)."""

    index: int = 0
    count: int = 1

    def mine(self, items: Sequence[T]) -> list[T]:
        """Item k of ``items`` when k % count == index.

        Args:
            items: e.g. the study's chunks, in order.

        Returns:
            This process's items, in order.
        """
        return [x for k, x in enumerate(items) if k % self.count == self.index]


#: A study in this process alone.
ONE_PROCESS = Processes()


def start_processes(
    distributed: bool,
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> Processes:
    """Join the study's processes (``jax.distributed.initialize``) when ``distributed``;
    ``coordinator`` "HOST:PORT" of process 0 (None: ``$JAX_COORDINATOR_ADDRESS``, or SLURM's /
    Open MPI's), ``num_processes`` and ``process_id`` (None: SLURM's / Open MPI's). Several
    processes on one CPU machine talk through gloo. InputError when the options do not make a
    group of processes (no coordinator, an id out of range, JAX already started).

    Args:
        distributed: join a group of processes (else one process, and no other option).
        coordinator: "HOST:PORT" of process 0 (--coordinator).
        num_processes: the processes in all, >= 1 (--num-processes).
        process_id: this process's, 0 to ``num_processes`` - 1 (--process-id).

    Returns:
        This process's ``Processes`` (``ONE_PROCESS`` without ``distributed``).

    Raises:
        InputError: options without ``distributed``, or as above.
    """
    given = {
        "--coordinator": coordinator,
        "--num-processes": num_processes,
        "--process-id": process_id,
    }
    if not distributed:
        named = [k for k, v in given.items() if v is not None]
        if named:
            raise InputError(f"{', '.join(named)}: only with --distributed")
        return ONE_PROCESS
    address = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS")
    cluster = any(k in os.environ for k in CLUSTER_VARIABLES)
    if not cluster and (address is None or num_processes is None or process_id is None):
        raise InputError(
            "--distributed needs --coordinator HOST:PORT of process 0 (or "
            "JAX_COORDINATOR_ADDRESS), --num-processes and --process-id, unless launched by "
            "srun (SLURM) or mpirun (Open MPI)"
        )
    if address is not None and not address.rpartition(":")[2].isdigit():
        raise InputError(f"--coordinator must be HOST:PORT, got {address!r}")
    if num_processes is not None and num_processes < 1:
        raise InputError(f"--num-processes must be >= 1, got {num_processes}")
    if process_id is not None and not 0 <= process_id < (num_processes or process_id + 1):
        raise InputError(f"--process-id must be in 0..{(num_processes or 1) - 1}, got {process_id}")
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(coordinator, num_processes, process_id)
    except (ValueError, TypeError, RuntimeError) as exc:
        raise InputError(
            f"--distributed: {exc} (give --coordinator HOST:PORT of process 0 or set "
            "JAX_COORDINATOR_ADDRESS, with --num-processes and --process-id; under SLURM "
            "(srun) or Open MPI (mpirun) jax finds them itself)"
        ) from None
    return Processes(jax.process_index(), jax.process_count())


def exchange(processes: Processes, error: str | None) -> list[str | None]:
    """Every process's ``error`` (None: none), gathered on every process (a barrier: each
    process waits for all the others to call it). Messages are cut to ``MESSAGE_BYTES``.

    Args:
        processes: this process among the others.
        error: this process's error message, or None.

    Returns:
        ``count`` messages (None: no error), by process index.
    """
    if processes.count == 1:
        return [error]
    from jax.experimental import multihost_utils

    buf = np.zeros(MESSAGE_BYTES + 1, np.uint8)
    if error is not None:
        text = error.encode()[:MESSAGE_BYTES]
        buf[0], buf[1 : 1 + len(text)] = 1, np.frombuffer(text, np.uint8)
    every = np.asarray(multihost_utils.process_allgather(buf))
    return [
        bytes(row[1:]).rstrip(b"\0").decode(errors="replace") if row[0] else None
        for row in every.reshape(processes.count, -1)
    ]


def together(processes: Processes, step: Callable[[], T], where: str) -> T | None:
    """Run ``step`` on this process, then wait for every process's (``exchange``): when one
    failed, every process raises (this process's own exception, the others an InputError
    naming the process and its message). ``where``: what the step does, for the message.

    Args:
        processes: this process among the others.
        step: the work, no arguments.
        where: what it does, e.g. "to set the study up", for the message.

    Returns:
        What ``step`` returned.

    Raises:
        InputError: another process's step failed (this process's failure: its own
            exception).
    """
    error, result = None, None
    try:
        result = step()
    except BaseException as exc:
        if processes.count == 1:
            raise
        error = str(exc) or type(exc).__name__
        own = exc
    else:
        own = None
    errors = exchange(processes, error)
    if own is not None:
        raise own
    failed = [(k, e) for k, e in enumerate(errors) if e is not None]
    if failed:
        k, e = failed[0]
        raise InputError(f"process {k} of {processes.count} failed {where}: {e}")
    return result
