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
    """A 1-D mesh with axis ``"batch"`` over this process's first ``devices`` devices (default
    all; under ``jax.distributed`` each process shards its own worlds over its own devices)."""
    devs = jax.local_devices()
    k = len(devs) if devices is None else int(devices)
    if not 1 <= k <= len(devs):
        raise InputError(f"devices must be in 1..{len(devs)}, got {devices}")
    return jax.make_mesh((k,), ("batch",), axis_types=(AxisType.Auto,), devices=devs[:k])


def devices(mesh: Mesh | None) -> int:
    """The number of devices the worlds are split over (1 without a mesh)."""
    return 1 if mesh is None else mesh.size


def world_padding(mesh: Mesh | None, worlds: int) -> np.ndarray:
    """Indices of ``worlds`` worlds padded to a multiple of the mesh size with copies of the
    last world (their results are dropped)."""
    shards = devices(mesh)
    return np.minimum(np.arange(-(-worlds // shards) * shards), worlds - 1)


def placement(mesh: Mesh | None) -> tuple[Put, Put]:
    """(put per-world arrays, put shared arrays): split along ``"batch"`` / replicated on a
    mesh, else both on the default device."""
    if mesh is None:
        return jax.device_put, jax.device_put
    world = NamedSharding(mesh, WORLDS)
    shared = NamedSharding(mesh, SHARED)
    return (lambda x: jax.device_put(x, world)), (lambda x: jax.device_put(x, shared))


def per_device(fn: Callable, mesh: Mesh | None, in_specs: Any, out_specs: Any) -> Callable:
    """``fn`` run by every device of ``mesh`` on its own worlds (``jax.shard_map``; the specs,
    ``WORLDS`` or ``SHARED``, are pytree prefixes of the arguments and results). Inside, a
    ``WORLDS`` array holds this device's worlds only, a ``WORLDS`` result is the devices'
    results stacked. Nothing is exchanged between the devices. Without a mesh: ``fn``."""
    if mesh is None:
        return fn
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)


def partitioner(mesh: Mesh | None) -> AbstractContextManager:
    """The context to lower and compile a ``per_device`` function in: on a mesh of several
    devices, XLA's GSPMD partitioner instead of Shardy (jax 0.11.2 on two H200s: compiling the
    MJX chunk function under Shardy ends in a segmentation fault; under GSPMD it compiles and
    runs; the CPU compiles it either way)."""
    return use_shardy_partitioner(False) if mesh is not None and mesh.size > 1 else nullcontext()


def device_rows(
    rows: np.ndarray, worlds: int, d: int, bucket: int
) -> tuple[np.ndarray, np.ndarray]:
    """The worlds ``rows`` (indices into ``worlds`` padded worlds, ``world_padding``, split
    in equal blocks over ``d`` devices) as each device's own: (local, where). ``local``
    (d m,): device k's m indices into its own worlds at [k m, (k + 1) m) (m: the most any
    device holds, rounded up to a multiple of ``bucket``, at least ``bucket``; the rest 0), a
    ``WORLDS`` argument; a chunk function's per-world outputs picked at them come back
    stacked (d m, ...), and ``where`` (len(rows),) says where each of ``rows`` is in that
    stack."""
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
