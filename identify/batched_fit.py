"""The joint fit of many recordings, each on its own, in vmapped batches on the default backend.

``fit_each`` fits recordings (read, checked and packed on the host while the device fits the
batches before: moments, statistics and solve of a batch in one traced program kept between
processes, ``identify.traced``) into one params set each, as ``joint_fit.fit`` would.
``fit_batch`` fits stacked sweep moments and transfer bins (the studies' simulated worlds),
``compile_fit_batch`` compiles its program ahead of the data; ``BatchFit`` holds the results.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from jaxcomp.errors import InputError
from jaxcomp.identify import traced
from jaxcomp.identify.fit_model import FitModel, fit_model
from jaxcomp.identify.fit_solver import Solution, solve
from jaxcomp.identify.fit_stats import padded_sweeps, sweep_bucket, sweep_stats, transfer_stats
from jaxcomp.identify.joint_fit import FitError, solution_params
from jaxcomp.identify.moments import SweepMoments
from jaxcomp.identify.packing import PackBuffer, Packed, pack
from jaxcomp.identify.steady import STEADY_FRACTION, STEADY_TRIM
from jaxcomp.identify.sweep_reduction import on_cpu, reduce_batch
from jaxcomp.identify.transfers import (
    TransferBins,
    bucket,
    empty_bins,
    padded_bins,
    stack_bins,
    transfer_bins,
)
from jaxcomp.plausibility import recording_problems
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams


@partial(jax.jit, static_argnums=(0, 2, 3))
def _fit_packed(model: FitModel, data: tuple[Packed, TransferBins], length: int, sequential: bool):
    """Stacked packed recordings and their transfer bins (leading batch axis) -> (Solution,
    coef, joint, count) of each: moments, statistics and fit in one computation on the device
    (``sequential``: the moments one recording after another, see
    ``sweep_reduction.reduce_batch``)."""
    p, tb = data
    m = reduce_batch(p, length, STEADY_FRACTION, STEADY_TRIM, sequential)
    sol, coef = _fit_moments.__wrapped__(model, m, tb)
    return sol, coef, m.joint, m.count


def _join(parts: list[tuple[Packed, int]], size: int) -> tuple[Packed, int]:
    """Groups of packed recordings on the device as one batch of ``size``: padded to the
    largest sizes, the last recording repeated to fill the batch."""
    length = max(n for _, n in parts)
    leaves = [p for p, _ in parts]
    shapes = jax.tree.map(
        lambda *a: tuple(max(dims) for dims in zip(*(x.shape[1:] for x in a), strict=True)),
        *leaves,
    )

    def fit(a, shape):
        if a.shape[1:] == shape:
            return a
        return jnp.pad(a, [(0, 0)] + [(0, s - d) for s, d in zip(shape, a.shape[1:], strict=True)])

    def join(*a):
        a = a[0] if len(a) == 1 else jnp.concatenate(a)
        fill = size - a.shape[0]  # no copy of a full batch in one group (the CPU's case)
        return a if fill == 0 else jnp.concatenate([a, jnp.repeat(a[-1:], fill, axis=0)])

    padded = [jax.tree.map(fit, p, shapes) for p in leaves]
    return jax.tree.map(join, *padded), length


#: Recordings per host-to-device transfer in ``fit_each`` (a worker's reused buffer).
_GROUP = 16


def fit_each(
    recordings: Iterable[Recording],
    batch: int | None = None,
    progress: bool = False,
    workers: int | None = None,
    com_prior: float | None = None,
    transfers: bool = True,
) -> list[RobotParams]:
    """Fit every recording on its own, ``batch`` at a time in one vmapped computation on the
    default backend (a GPU when present): moments, statistics and fit of a batch in one call
    (each as ``fit``, its transfers too unless ``transfers`` is False).

    The host reads (``recordings`` may be a generator that loads them), checks and packs a
    batch while the device fits the two before; the device's program is loaded (or traced and
    compiled) for a batch like the first recording while the rest of the first batch is read,
    and a recording is let go once packed.

    Args:
        recordings: The recordings, of one robot model (a generator may load them).
        batch: Recordings per call (default 256 on an accelerator; 4 on a CPU, where a
            smaller batch maps less fresh memory and starts the device sooner).
        progress: Show a progress bar.
        workers: Host threads that pack the recordings (``_GROUP`` to a transfer) and send
            them to the device (default: up to 8 on an accelerator, where more only contend
            for host memory bandwidth; 1 on a CPU).
        com_prior: m, as ``fit``'s.
        transfers: Fit the transfers' samples too.

    Returns:
        One params set per recording, in order.

    Raises:
        InputError: no recording, recordings of several models, or one that fails the
            plausibility checks.
        FitError: naming the recordings whose fit did not converge (no result then).
    """
    accelerated = not on_cpu()
    batch = int(batch or (256 if accelerated else 4))
    workers = max(1, int(workers or (min(8, os.cpu_count() or 1) if accelerated else 1)))
    group = min(_GROUP, batch)
    local = threading.local()
    out: list[RobotParams] = []
    failed: list[int] = []
    model: FitModel | None = None
    name = None  # the recordings' model
    robots: dict[tuple, Robot] = {}  # each recording's robot, by its model and joints
    buffers: dict[tuple[int, int], PackBuffer] = {}  # a CPU's, by batch parity and group
    bar = tqdm(desc="fitting", unit="rec", disable=not progress)

    def send(item: tuple[tuple[int, int], list[Recording]]) -> tuple[Packed, int]:
        which, recs = item
        if accelerated:  # copied to the device: each thread packs into its own buffer again
            buffer = local.__dict__.setdefault("buffer", PackBuffer())
        else:  # the device array aliases the buffer: packed into again two batches later, once
            # the batch that used it is fitted (fresh memory costs a page fault per 4 kB)
            buffer = buffers.setdefault(which, PackBuffer())
        packed, length = pack(recs, buffer)
        return jax.block_until_ready(jax.device_put((packed, _bins_of(recs, transfers)))), length

    def finish(names: list[str], result: Future, start: float) -> None:
        sols, coef, joint, count = jax.tree.map(np.asarray, result.result())
        joint = np.where(count > 0, joint, -1)
        seconds = (time.perf_counter() - start) / len(names)
        for i, recorded in enumerate(names):
            sol = jax.tree.map(lambda a, i=i: a[i], sols)
            try:
                out.append(solution_params(model, recorded, sol, coef[i], joint[i], seconds))
            except FitError:
                failed.append(len(out) + len(failed))
        bar.update(len(names))

    def program(packed, length: int) -> Callable:
        return traced.program(
            "fit_packed",
            repr((model.identity, length, not accelerated)),
            partial(_fit_packed, model, length=length, sequential=not accelerated),
            (packed,),
            (Packed, TransferBins, Solution),
        )

    def load(rec: Recording) -> None:  # the program for a batch of recordings like ``rec``
        packed, length = pack([rec])
        packed = (packed, _bins_of([rec], transfers))
        if not accelerated:  # and the pack buffers' memory, mapped ahead of the first packs
            for which in itertools.product((0, 1), range(-(-batch // group))):
                shape = packed[0].samples.shape[1:]
                buffers.setdefault(which, PackBuffer()).take(group, *shape, True)
        like = jax.tree.map(lambda a: jax.ShapeDtypeStruct((batch, *a.shape[1:]), a.dtype), packed)
        program(like, length)

    def run(packed, length: int):  # the batch's results, asynchronously
        return program(packed, length)(packed)

    pending: deque = deque()  # (names, result, start) of the batches not finished yet
    seen = 0
    stream = iter(recordings)
    first = next(stream, None)
    # the device thread loads the kept program and starts each batch's fit (asynchronous)
    # while this one reads (``recordings`` may be a generator), checks and packs the next ones
    with ThreadPoolExecutor(workers) as pool, ThreadPoolExecutor(1) as device:
        if first is not None:
            name = first.model
            model = fit_model(name, com_prior)
            device.submit(load, first)  # while the rest of the first batch is read
            stream = itertools.chain([first], stream)
            del first
        for k, chunk in enumerate(_chunks(stream, batch)):
            if any(r.model != name for r in chunk):
                raise InputError("fit_each needs recordings of one robot model")
            for i, rec in enumerate(chunk):
                if (rec.model, rec.joints) not in robots:
                    robots[rec.model, rec.joints] = rec.robot()
                if problems := recording_problems([rec], robots[rec.model, rec.joints]):
                    raise InputError(f"recording {seen + i}: {'; '.join(problems)}")
            seen += len(chunk)
            while len(pending) > 1 or (pending and pending[0][1].done()):
                finish(*pending.popleft())  # the batch two before: its pack buffer is free
            start = time.perf_counter()
            groups = [((k % 2, i), chunk[i : i + group]) for i in range(0, len(chunk), group)]
            packed, length = _join(list(pool.map(send, groups)), batch)
            result = device.submit(run, packed, length)
            pending.append(([r.model for r in chunk], result, start))
            del chunk, groups  # the samples are packed: the recordings can go
        while pending:
            finish(*pending.popleft())
    bar.close()
    if model is None:
        raise InputError("no recording to fit")
    if failed:
        raise FitError(f"the fit of recording(s) {failed} did not converge; nothing was written")
    return out


def _bins_of(recs: list[Recording], transfers: bool) -> TransferBins:
    """The recordings' transfer bins, stacked (none with ``transfers`` False)."""
    if not transfers:
        return empty_bins(recs[0].n_joints, stack=len(recs))
    return stack_bins([transfer_bins(r) for r in recs])


def _chunks(items: Iterable, size: int) -> Iterable[list]:
    chunk: list = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class BatchFit(NamedTuple):
    """Result of ``fit_batch`` (host arrays, leading axis W = recordings).

    Attributes:
        solution: the ``Solution`` of every recording (ratio (W, n) A/(N m), friction (W, n)
            A, viscous (W, n) A s/rad, com (W, K) m, cov (W, P, P), ...).
        coef: (W, S, 1 + K, 3) torque coefficients of each sweep (see ``phase_shift``).
        std: (W, P) standard errors of [ratio, friction, viscous, com], sqrt(diag cov).
        compile_seconds: s spent compiling (0 when the batch shape was compiled before).
        seconds: s of the fits proper (compilation excluded, device sync included).
    """

    solution: Solution
    coef: np.ndarray
    std: np.ndarray
    compile_seconds: float
    seconds: float


@partial(jax.jit, static_argnums=0)
def _fit_moments(model: FitModel, m: SweepMoments, tb: TransferBins) -> tuple[Solution, jax.Array]:
    """Stacked moments and transfer bins (leading batch axis) -> (Solution, coef) of every
    recording."""
    st, coef = jax.vmap(sweep_stats.__wrapped__, in_axes=(None, 0))(model, m)
    moving = jax.vmap(transfer_stats.__wrapped__, in_axes=(None, 0, 0, 0, 0))(
        model, tb, m.gravity, m.payload_mass, m.payload_com
    )
    return jax.vmap(solve.__wrapped__, in_axes=(None, 0))(model.key, st + moving), coef


def _compiled_fit(
    model: FitModel,
    chunk: tuple[SweepMoments, TransferBins],
    shape: tuple,
    options: dict | None = None,
) -> tuple[Callable, float]:
    """``_fit_moments`` compiled ahead of time for ``chunk`` (so that its time is known),
    kept on the robot per model and ``shape`` = (batch, sweeps, mesh); and the seconds spent
    compiling it now (0 when it was compiled before). ``options``: XLA compiler options."""
    seconds = 0.0

    def build() -> Callable:
        nonlocal seconds
        t0 = time.perf_counter()
        compiled = _fit_moments.lower(model, *chunk).compile(options)
        seconds = time.perf_counter() - t0
        return compiled

    types = tuple(str(a.dtype) for a in jax.tree.leaves(chunk))
    return model.robot.cached(("batched_fit.fit_batch", model, *shape, types), build), seconds


def _batch_input(
    moments: SweepMoments, transfers: TransferBins | None, batch: int, mesh: Mesh | None
) -> tuple[tuple[SweepMoments, TransferBins], int, tuple[int, int], Callable]:
    """``fit_batch``'s input: ((the moments with their sweeps padded to the bucket size and
    float gravity and payload, the transfer bins padded to theirs: none when ``transfers`` is
    None), rows per batch (``batch`` rounded up to the mesh), the padded sweep and bin counts,
    the function that places a batch on the mesh)."""
    shards = 1 if mesh is None else mesh.size
    b = -(-max(1, int(batch)) // shards) * shards
    size = sweep_bucket(moments.moments.shape[1])
    padded = padded_sweeps(moments, size, axis=1)
    padded = padded._replace(
        payload_mass=np.asarray(padded.payload_mass, float),
        gravity=np.asarray(padded.gravity, float),
        payload_com=np.asarray(padded.payload_com, float),
    )
    w, n = moments.hold.shape[0], moments.hold.shape[-1]
    if transfers is None:
        tb = empty_bins(n, stack=w)
    else:
        tb = padded_bins(transfers, bucket(transfers.size))
    place = (
        (lambda x: x)
        if mesh is None
        else partial(jax.device_put, device=NamedSharding(mesh, PartitionSpec("batch")))
    )
    return (padded, tb), b, (size, tb.size), place


def compile_fit_batch(
    model: FitModel,
    like: SweepMoments,
    batch: int,
    mesh: Mesh | None = None,
    transfers: TransferBins | None = None,
) -> float:
    """Compile ``fit_batch``'s program for batches of ``batch`` recordings with moments and
    transfer bins like ``like`` and ``transfers`` (stacked; any number of rows) ahead of the
    data themselves, e.g. while the simulation that makes them runs on the same device:
    without autotuning, which would time its candidate kernels behind that work.

    Args:
        model: The fit model.
        like: Stacked moments shaped like the data's (any number of rows).
        batch: Recordings per batch.
        mesh: As ``fit_batch``'s.
        transfers: Stacked transfer bins shaped like the data's; None: sweeps alone.

    Returns:
        s spent compiling (0 when compiled before).
    """
    padded, b, size, _ = _batch_input(like, transfers, batch, mesh)
    sharding = None if mesh is None else NamedSharding(mesh, PartitionSpec("batch"))
    shaped = jax.tree.map(
        lambda a: jax.ShapeDtypeStruct(
            (b, *np.shape(a)[1:]), np.asarray(a).dtype, sharding=sharding
        ),
        padded,
    )
    return _compiled_fit(model, shaped, (b, size, mesh), {"xla_gpu_autotune_level": 0})[1]


def fit_batch(
    model: FitModel,
    moments: SweepMoments,
    *,
    transfers: TransferBins | None = None,
    batch: int | None = None,
    mesh: Mesh | None = None,
    progress: Callable[[int], None] | None = None,
) -> BatchFit:
    """Fit W recordings each on its own from their stacked sweep moments, on the default
    backend (a GPU when present), ``batch`` at a time in one vmapped computation.

    The results are those of ``solve`` per recording; non-converged fits are reported in
    ``solution.converged``, not raised.

    Args:
        model: The fit model.
        moments: A ``SweepMoments`` with a leading axis W on every field (joint (W, S), hold
            (W, S, n) rad, moments (W, S, D, D) with D = ``moments.moment_size(n)``, count
            (W, S), gravity (W, 3) m/s^2, payload_mass (W,) kg, payload_com (W, 3) m), e.g.
            ``identify.sweep_reduction.sweep_moments_batch``; a sweep of zero moments adds
            nothing.
        transfers: The recordings' stacked ``TransferBins`` (W, B, n); None: sweeps alone.
        batch: Recordings per computation (default: all W).
        mesh: A ``jax.sharding.Mesh`` with the single axis "batch" to shard each batch over
            (its devices); the batch is rounded up to a multiple of the mesh size and the
            last batch padded with copies of the last recording (dropped).
        progress: Called as ``progress(k)`` after each batch of k recordings.

    Returns:
        The fits, host arrays with a leading axis W.

    Raises:
        InputError: moments not stacked.
    """
    w = int(moments.moments.shape[0])
    if w < 1 or moments.moments.ndim != 4:
        raise InputError("moments must be stacked: moments (W, S, D, D) with W >= 1")
    rows = w if batch is None else max(1, min(int(batch), w))
    padded, b, size, place = _batch_input(moments, transfers, rows, mesh)
    compile_seconds, seconds = 0.0, 0.0
    sols, coefs = [], []
    for start in range(0, w, b):
        idx = np.minimum(np.arange(start, start + b), w - 1)
        chunk = place(jax.tree.map(lambda a, idx=idx: np.asarray(a)[idx], padded))
        compiled, compiling = _compiled_fit(model, chunk, (b, size, mesh))
        compile_seconds += compiling
        t0 = time.perf_counter()
        sol, coef = jax.block_until_ready(compiled(*chunk))
        k = min(b, w - start)
        sols.append(jax.tree.map(lambda a, k=k: np.asarray(a)[:k], sol))
        coefs.append(np.asarray(coef)[:k])
        seconds += time.perf_counter() - t0
        if progress is not None:
            progress(k)
    solution = jax.tree.map(lambda *a: np.concatenate(a), *sols)
    std = np.sqrt(np.clip(np.diagonal(solution.cov, axis1=-2, axis2=-1), 0.0, None))
    return BatchFit(solution, np.concatenate(coefs), std, compile_seconds, seconds)


def identified(sol: Solution) -> np.ndarray:
    """Which of [ratio, friction, viscous, com] the data determine in a fit.

    Args:
        sol: A solution (or a batch of them).

    Returns:
        (..., P) bool (``Solution.identified``; ratios also to ``RATIO_IDENTIFIED``).
    """
    return np.asarray(sol.identified, bool)
