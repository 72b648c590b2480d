"""Sharding of the MJX worlds over devices: a 1-D mesh with axis ``"batch"``.

``batch_mesh`` builds the mesh; ``world_padding`` pads the world count to a multiple of the
mesh size; ``placement`` gives the two device placements of a run: per-world arrays split
along the mesh, shared arrays replicated on every device. ``per_device`` runs a chunk
function on every device's own worlds (``jax.shard_map``: each device steps its worlds with
no collective inside the step; jitted over the mesh instead, the solver's loop over the
worlds would wait on an all-reduce of its stop test at every iteration);
``device_rows`` says which device holds a recorded world.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import jax
import numpy as np
from jax._src.config import use_shardy_partitioner
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx.chunks import PyTree

#: A function that places a pytree of host arrays on the device(s).
Put = Callable[[PyTree], PyTree]

#: ``per_device``'s specs: an argument or result split along the worlds / the same on every
#: device.
WORLDS, SHARED = P("batch"), P()


def batch_mesh(devices: int | None = None) -> Mesh:
    """A 1-D mesh with axis ``"batch"`` over this process's first ``devices`` devices (under
    ``jax.distributed`` each process shards its own worlds over its own devices).

    Args:
        devices: how many local devices (default all).

    Returns:
        The ``Mesh``.

    Raises:
        InputError: ``devices`` outside 1 .. the number of local devices.
    """
    devs = jax.local_devices()
    k = len(devs) if devices is None else int(devices)
    if not 1 <= k <= len(devs):
        raise InputError(f"devices must be in 1..{len(devs)}, got {devices}")
    return jax.make_mesh((k,), ("batch",), axis_types=(AxisType.Auto,), devices=devs[:k])


def devices(mesh: Mesh | None) -> int:
    """How many devices the worlds are split over.

    Args:
        mesh: the worlds' mesh, or None.

    Returns:
        The mesh's size (1 without a mesh).
    """
    return 1 if mesh is None else mesh.size


def world_padding(mesh: Mesh | None, worlds: int) -> np.ndarray:
    """The worlds padded to a multiple of the mesh size with copies of the last world (their
    results are dropped).

    Args:
        mesh: the worlds' mesh, or None. worlds: W, the number of worlds (>= 1).

    Returns:
        (W',) int indices into the W worlds, W' the multiple of the mesh size at or above W.
    """
    shards = devices(mesh)
    return np.minimum(np.arange(-(-worlds // shards) * shards), worlds - 1)


def placement(mesh: Mesh | None) -> tuple[Put, Put]:
    """The two device placements of a run.

    Args:
        mesh: the worlds' mesh, or None.

    Returns:
        (put per-world arrays, put shared arrays): split along ``"batch"`` / replicated on a
        mesh, else both on the default device.
    """
    if mesh is None:
        return jax.device_put, jax.device_put
    world = NamedSharding(mesh, WORLDS)
    shared = NamedSharding(mesh, SHARED)
    return (lambda x: jax.device_put(x, world)), (lambda x: jax.device_put(x, shared))


def per_device(fn: Callable, mesh: Mesh | None, in_specs: Any, out_specs: Any) -> Callable:
    """``fn`` run by every device of ``mesh`` on its own worlds (``jax.shard_map``).

    Inside, a ``WORLDS`` array holds this device's worlds only, a ``WORLDS`` result is the
    devices' results stacked. Nothing is exchanged between the devices.

    Args:
        fn: the function of one device's worlds. mesh: the worlds' mesh, or None.
        in_specs: ``WORLDS`` or ``SHARED``, pytree prefixes of ``fn``'s arguments.
        out_specs: the same of its results.

    Returns:
        The function over every device's worlds (without a mesh: ``fn``).
    """
    if mesh is None:
        return fn
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)


def partitioner(mesh: Mesh | None) -> AbstractContextManager:
    """The context to lower and compile a ``per_device`` function in: on a mesh of several
    devices, XLA's GSPMD partitioner instead of Shardy (jax 0.11.2 on two H200s: compiling the
    MJX chunk function under Shardy ends in a segmentation fault; under GSPMD it compiles and
    runs; the CPU compiles it either way).

    Args:
        mesh: the worlds' mesh, or None.

    Returns:
        The context manager (a ``nullcontext`` without a mesh of several devices).
    """
    return use_shardy_partitioner(False) if mesh is not None and mesh.size > 1 else nullcontext()


def device_rows(
    rows: np.ndarray, worlds: int, d: int, bucket: int
) -> tuple[np.ndarray, np.ndarray]:
    """Recorded worlds as each device's own.

    Args:
        rows: (r,) int, the recorded worlds, indices into the padded worlds.
        worlds: the number of padded worlds (``world_padding``), split in equal blocks over
            the devices. d: the number of devices. bucket: m is rounded up to a multiple of it.

    Returns:
        (local, where). local: (d m,) int, a ``WORLDS`` argument: device k's m indices into
        its own worlds at [k m, (k + 1) m) (m: the most any device holds, at least
        ``bucket``; the rest 0); a chunk function's per-world outputs picked at them come back
        stacked (d m, ...). where: (r,) int, where each of ``rows`` is in that stack.
    """
    rows = np.asarray(rows, np.int64)
    per = worlds // d
    owner = rows // per
    most = int(np.bincount(owner, minlength=d).max(initial=0))
    m = max(bucket, -(-most // bucket) * bucket)
    local = np.zeros((d, m), np.int64)
    where = np.zeros(rows.size, np.int64)
    for dev in range(d):
        mine = np.flatnonzero(owner == dev)
        local[dev, : mine.size] = rows[mine] - dev * per
        where[mine] = dev * m + np.arange(mine.size)
    return local.reshape(-1), where
