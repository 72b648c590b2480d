"""Chunked stepping: how a run advances its worlds in compiled calls of K steps.

A run calls one compiled chunk function per K steps (per-world state stays on the device
between calls) and keeps every k-th sample. ``scan_decimated`` is the ``lax.scan`` of such a
chunk that keeps only the recorded samples; ``chunk_length`` chooses K; ``over_worlds`` maps
one world's step over the worlds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

#: A pytree of arrays (nested tuples, lists, dicts and NamedTuples of arrays).
PyTree = Any

#: Recorded bytes per chunk and device on an accelerator (bounds the device memory of the
#: samples).
CHUNK_BYTES = 256 * 2**20


def chunk_length(
    chunk_steps: int | None,
    backend: str,
    worlds: int,
    n: int,
    itemsize: int,
    every: int,
    steps: int,
) -> int:
    """Steps per compiled call of a run that records every ``every``-th sample of
    (q, dq, current).

    Args:
        chunk_steps: the steps asked for, or None: 100 on the CPU, else as many as keep a
            chunk's samples within ``CHUNK_BYTES`` (at most 10 000), at most ``steps``.
        backend: the JAX backend (``"cpu"``, ``"gpu"``, ...).
        worlds: the worlds of one device. n: the joints. itemsize: bytes per sample value.
        every: the recording decimation (>= 1). steps: the run's length, steps.

    Returns:
        The chunk length, steps, rounded up to a multiple of ``every``.
    """
    k = chunk_steps
    if k is None:
        if backend == "cpu":
            k = 100
        else:
            per = worlds * n * 3 * itemsize / every
            k = int(max(every, min(10_000, CHUNK_BYTES // max(per, 1))))
        k = min(k, steps)
    return -(-max(int(k), 1) // every) * every


def scan_decimated(
    step: Callable[[PyTree, jax.Array, PyTree], tuple[PyTree, PyTree]],
    carry: PyTree,
    xs: PyTree,
    every: int,
) -> tuple[PyTree, PyTree | None]:
    """``lax.scan`` of ``step`` keeping the outputs of steps 0, every, 2 every, ...

    With every > 1 the group's first output rides in the carry, so the step appears once in
    the compiled graph.

    Args:
        step: ``step(carry, i, x_i) -> (carry, out)``, i the step's index.
        carry: the initial carry.
        xs: the steps' inputs along the leading axis (T, a multiple of ``every``).
        every: the decimation; 0 keeps no output.

    Returns:
        (the final carry, the kept outputs stacked (T // every, ...), or None for every = 0).
    """
    length = jax.tree_util.tree_leaves(xs)[0].shape[0]
    if every == 0:
        carry, _ = jax.lax.scan(
            lambda c, ix: (step(c, ix[0], ix[1])[0], None), carry, (jnp.arange(length), xs)
        )
        return carry, None
    groups = length // every
    xs = jax.tree_util.tree_map(lambda a: a.reshape((groups, every) + a.shape[1:]), xs)
    if every == 1:
        first = jax.tree_util.tree_map(lambda a: a[:, 0], xs)
        return jax.lax.scan(lambda c, ix: step(c, ix[0], ix[1]), carry, (jnp.arange(groups), first))
    x0 = jax.tree_util.tree_map(lambda a: a[0, 0], xs)
    shapes = jax.eval_shape(lambda c, x: step(c, 0, x)[1], carry, x0)

    def group(c, gx):
        g, xg = gx

        def inner(cc, jx):
            state, kept = cc
            j, x = jx
            state, out = step(state, g * every + j, x)
            kept = jax.tree_util.tree_map(lambda o, k: jnp.where(j == 0, o, k), out, kept)
            return (state, kept), None

        empty = jax.tree_util.tree_map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shapes)
        (c, kept), _ = jax.lax.scan(inner, (c, empty), (jnp.arange(every), xg))
        return c, kept

    return jax.lax.scan(group, carry, (jnp.arange(groups), xs))


def over_worlds(fn: Callable, backend: str, in_axes: Sequence[int | None]) -> Callable:
    """``fn`` of one world mapped over the leading world axis of its arguments.

    ``jax.vmap`` on accelerators; on the CPU a loop over the worlds (``lax.map``), where each
    world's solver loops stop when that world is done (vmapped, every world runs to the
    slowest's count and computes both branches of every ``cond``: 1.4x the time per step for
    two Gen3 Lite worlds on a 2-core CPU, 2.3x for one). Either way world w's numbers depend
    on no other world.

    Args:
        fn: the function of one world. backend: the JAX backend (``"cpu"`` loops).
        in_axes: per argument, 0 (mapped over its leading axis) or None (shared).

    Returns:
        The function of every world, its results stacked along a leading world axis.
    """
    if backend != "cpu":
        return jax.vmap(fn, in_axes=tuple(in_axes))

    def mapped(*args):
        mine = tuple(a for a, ax in zip(args, in_axes, strict=True) if ax == 0)

        def one(x):
            it = iter(x)
            return fn(*(next(it) if ax == 0 else a for a, ax in zip(args, in_axes, strict=True)))

        return jax.lax.map(one, mine)

    return mapped
