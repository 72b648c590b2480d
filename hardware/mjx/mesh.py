"""Sharding of the MJX worlds over devices: a 1-D mesh with axis ``"batch"``.

``batch_mesh`` builds the mesh; ``world_padding`` pads the world count to a multiple of the
mesh size; ``placement`` gives the two device placements of a run: per-world arrays split
along the mesh, shared arrays replicated on every device.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx.chunks import PyTree

#: A function that places a pytree of host arrays on the device(s).
Put = Callable[[PyTree], PyTree]


def batch_mesh(devices: int | None = None) -> Mesh:
    """A 1-D mesh with axis ``"batch"`` over this process's first ``devices`` devices (default
    all; under ``jax.distributed`` each process shards its own worlds over its own devices)."""
    devs = jax.local_devices()
    k = len(devs) if devices is None else int(devices)
    if not 1 <= k <= len(devs):
        raise InputError(f"devices must be in 1..{len(devs)}, got {devices}")
    return jax.make_mesh((k,), ("batch",), axis_types=(AxisType.Auto,), devices=devs[:k])


def world_padding(mesh: Mesh | None, worlds: int) -> np.ndarray:
    """Indices of ``worlds`` worlds padded to a multiple of the mesh size with copies of the
    last world (their results are dropped)."""
    shards = 1 if mesh is None else mesh.size
    return np.minimum(np.arange(-(-worlds // shards) * shards), worlds - 1)


def placement(mesh: Mesh | None) -> tuple[Put, Put]:
    """(put per-world arrays, put shared arrays): split along ``"batch"`` / replicated on a
    mesh, else both on the default device."""
    if mesh is None:
        return jax.device_put, jax.device_put
    world = NamedSharding(mesh, P("batch"))
    shared = NamedSharding(mesh, P())
    return (lambda x: jax.device_put(x, world)), (lambda x: jax.device_put(x, shared))
