"""The open-loop run of the MJX simulator: every world in POSITION mode through one plan.

``MjxSimulator.run`` (implemented by ``run`` here) servos each world to its initial pose, then
drives it through the shared joint-position reference ``q_ref`` (T, n) or (T, G, n) rad at
1 kHz in compiled chunks (``chunks``), and records every k-th sample as an ``MjxRecording``.
The servo is the CPU Simulator's: ``tau = clip(kp (q_ref - q) + kv (0 - dq), effort)``, the
measured current ``r tau_applied + noise``.

Agreement with the CPU ``Simulator`` (same truth, no noise, same q_ref and start, float64),
measured on the Gen3 Lite in 4 worlds of drawn truths over 4.9 s of +-20-30 deg moves at
0.3-0.5 rad/s, the servo saturating at joint 1's effort limit: max |q| error 7.6e-9 rad,
|dq| 3.1e-7 rad/s, |current| 1.4e-6 A (the solver tolerance shows at stick-slip transitions);
``AGREEMENT`` holds the tolerances the tests assert.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx.chunks import over_worlds, scan_decimated
from jaxcomp.hardware.mjx.mesh import SHARED, WORLDS, device_rows, devices, placement, world_padding
from jaxcomp.hardware.mjx.model import WORLD_MODEL_FIELDS
from jaxcomp.hardware.mjx.step import implicitfast_step
from jaxcomp.hardware.mjx.truth import BatchTruth

if TYPE_CHECKING:
    from jaxcomp.hardware.mjx.simulator import MjxSimulator

#: Tolerances of the agreement with the CPU Simulator (float64, noise 0) that the tests assert:
#: max |q| rad, |dq| rad/s, |current| A differences over a recorded plan (measured: 7.6e-9,
#: 3.1e-7, 1.4e-6).
AGREEMENT = {"q": 2e-8, "dq": 1e-6, "current": 5e-6}

#: The recorded worlds of a run's compiled program come in multiples of this (at least one
#: multiple, also when none is recorded).
RECORD_BUCKET = 4

#: Steps of the settling at the initial pose before t = 0 (the CPU Simulator's).
SETTLE_STEPS = 500

#: ``run``'s phase of a step, per reference group: the plan (faults count), settling (the
#: reference held, faults not counted), and a restart: the world set at rest at the
#: reference, then settling.
PLAN, SETTLE, RESTART = 0, 1, 2


class MjxRecording(NamedTuple):
    """What ``MjxSimulator.run`` recorded (host arrays; R recorded samples).

    Attributes:
        t: (R,) s, time of each sample (plan step i is recorded at (i + 1) ms).
        q: (W, R, n) rad; dq: (W, R, n) rad/s; current: (W, R, n) A (r tau_applied + noise),
            the state after plan steps 0, every, 2 every, ...
        q_start: (W, n) rad, each world's settled pose at t = 0.
        fault_step: (W,) first plan step after which a servoed joint was beyond
            ``following_error`` of its target, faster than ``overspeed`` or at a joint limit
            (what stops the CPU Simulator), -1 if none; the MJX worlds keep going regardless.
        every: the recording decimation k.
        reduced: the final carry of the run's ``Reduction`` (device arrays, a leading axis W:
            reduce them further there before they come to the host),
            None without one.
    """

    t: np.ndarray
    q: np.ndarray | None
    dq: np.ndarray | None
    current: np.ndarray | None
    q_start: np.ndarray
    fault_step: np.ndarray
    every: int
    reduced: Any = None


class Reduction(NamedTuple):
    """A reduction of each world's recorded samples on the device, inside the run's loop.

    ``step(carry, x, q, dq, current, valid) -> carry`` (pure JAX, one world, one recorded
    sample; vmapped over the worlds here): ``x`` the sample's row of ``xs``, q (n,) rad,
    dq (n,) rad/s, current (n,) A (noise included) the state after the plan step; ``valid``
    False for samples past the plan's end or of the settling (they must add nothing).
    ``init``: one world's initial carry (a pytree of host arrays). ``xs``: a pytree of host
    arrays (R, G, ...) with R = ceil(T / every), the rows shared by the worlds that follow
    reference g (world w reads ``xs[r, group[w]]``). ``key``: hashable, the same for the same
    ``step`` (the compiled chunk function is cached under it).
    """

    step: Callable
    init: Any
    xs: Any
    key: Hashable


def run(
    sim: MjxSimulator,
    truth: BatchTruth,
    q_ref: np.ndarray,
    initial_pose: str | Sequence[float] | np.ndarray | None = None,
    *,
    settle_steps: int = SETTLE_STEPS,
    seed: int = 0,
    every: int = 1,
    progress: Callable[[int, int], None] | None = None,
    on_chunk: Callable[[int, MjxRecording], None] | None = None,
    keep: bool = True,
    group: Sequence[int] | np.ndarray | None = None,
    reduce: Reduction | None = None,
    record: Sequence[int] | np.ndarray | None = None,
    world_ids: Sequence[int] | np.ndarray | None = None,
    phase: np.ndarray | None = None,
    noise_step: np.ndarray | None = None,
) -> MjxRecording:
    """Drive every world through the position targets ``q_ref`` at 1 kHz
    (``MjxSimulator.run``): settle, then the plan, chunk by chunk.

    Each world starts at ``initial_pose``, is servoed there for ``settle_steps`` steps (as a
    fresh CPU ``Simulator``), then follows ``q_ref``: step i commands q_ref[i] and records the
    state after it. The current noise of world w at step i is ``noise_w N(0, 1)`` from
    ``fold_in(fold_in(PRNGKey(seed), id_w), c)``, ``id_w`` = ``world_ids[w]`` and c =
    ``noise_step[i, group[w]]``, so it depends neither on chunking nor, with global ids, on how
    worlds are batched (nor, with the steps of one plan as ``noise_step``, on where a job runs).

    Args:
        sim: the simulator (``MjxSimulator``; this is its method ``run``).
        truth: the worlds' true robots (W worlds).
        q_ref: (T, n) rad, the joint-position targets of every step; or (T, G, n): G
            references side by side, world w following reference ``group[w]`` (e.g. the
            sweeps of one plan as parallel segments). Within the joint limits.
        initial_pose: a pose name, (n,) or (W, n) rad; None: ``Robot.idle_pose``.
        settle_steps: steps of the settling before t = 0 (>= 0).
        seed: of the current noise.
        every: records every ``every``-th sample (0, every, ...), >= 1.
        progress: ``progress(steps_done, steps_total)`` after each chunk.
        on_chunk: ``on_chunk(first_sample, recording_of_the_chunk)`` streams the samples.
        keep: False returns q, dq, current as None (bounded host memory; without
            ``on_chunk`` no sample leaves the device).
        group: (W,) ints in [0, G), each world's reference (default 0).
        reduce: a ``Reduction`` of every world's samples on the device, its final carry
            returned as ``reduced``.
        record: only these worlds' samples leave the device (default all; q, dq, current then
            have M = len(record) rows).
        world_ids: (W,) ints >= 0, the worlds' ids of the noise (default 0 .. W - 1).
        phase: (T, G) of ``PLAN`` (default), ``SETTLE`` (faults not counted) or ``RESTART``
            (the world set at rest at its reference, then settling): several jobs one after
            another in one world.
        noise_step: (T, G) ints, each step's noise index (default the step i).

    Returns:
        The ``MjxRecording``.

    Raises:
        InputError: an argument out of its range or shape, or a target beyond a joint limit.
    """
    plan = _checked_plan(sim, truth.worlds, q_ref, settle_steps, every, group, phase, noise_step)
    clock = sim.run_clock()
    job = _prepare(sim, truth, plan, initial_pose, seed, world_ids, record, keep, on_chunk, reduce)
    clock.mark()
    carry = _settle(sim, job, plan, reduce)
    q_start = np.asarray(carry[0])[: truth.worlds].astype(float)
    clock.mark()
    carry, out = _follow(sim, job, plan, carry, keep, on_chunk, progress)
    clock.finish()
    w, n_rec = truth.worlds, plan.noise_step.shape[0]
    t = (np.arange(n_rec) * plan.every + 1) * CONTROL_PERIOD
    return MjxRecording(
        t,
        out.get("q"),
        out.get("dq"),
        out.get("current"),
        q_start,
        np.asarray(carry[3])[:w].astype(int),
        plan.every,
        None if reduce is None else jax.tree.map(lambda a: a[:w], carry[4]),
    )


class _Plan(NamedTuple):
    """A run's checked plan (host arrays)."""

    q_ref: np.ndarray  # (T, G, n) rad
    group: np.ndarray  # (W,) each world's reference
    phase: np.ndarray  # (T, G) int8: PLAN, SETTLE or RESTART
    noise_step: np.ndarray  # (R, G) int32, the recorded samples' noise steps
    every: int
    settle_steps: int


class _Job(NamedTuple):
    """A run's compiled chunk function and what it is fed (Wp worlds, padded to the mesh)."""

    fn: Callable
    fields: dict  # per world, placed on the device(s)
    q0: np.ndarray  # (Wp, n) rad, host: the initial poses
    rows: np.ndarray  # the recorded worlds (M,), host indices
    where: np.ndarray  # their rows in a chunk's recorded output
    rows_dev: Any  # each device's recorded worlds, placed
    chunk: int
    xs: Any  # the reduction's rows (R, G, ...), host
    put: Callable
    put_shared: Callable


def _checked_plan(
    sim: MjxSimulator,
    w: int,
    q_ref: np.ndarray,
    settle_steps: int,
    every: int,
    group: Sequence[int] | np.ndarray | None,
    phase: np.ndarray | None,
    noise_step: np.ndarray | None,
) -> _Plan:
    """The run's plan, checked (InputError), with its defaults."""
    every = int(every)
    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    settle_steps = int(settle_steps)
    if settle_steps < 0:
        raise InputError("settle_steps must be >= 0")
    q_ref = _checked_reference(sim, q_ref)
    t_total, groups = q_ref.shape[0], q_ref.shape[1]
    group = np.zeros(w, np.int32) if group is None else np.asarray(group)
    if group.shape != (w,) or not ((group >= 0) & (group < groups)).all():
        raise InputError(f"group must be ({w},) ints in [0, {groups})")
    phase = np.zeros((t_total, groups), np.int8) if phase is None else np.asarray(phase, np.int8)
    if phase.shape != (t_total, groups) or not np.isin(phase, (PLAN, SETTLE, RESTART)).all():
        raise InputError(f"phase must be ({t_total}, {groups}) of PLAN, SETTLE or RESTART")
    if noise_step is None:
        noise_step = np.broadcast_to(np.arange(t_total)[:, None], (t_total, groups))
    noise_step = np.asarray(noise_step)
    if noise_step.shape != (t_total, groups) or not np.issubdtype(noise_step.dtype, np.integer):
        raise InputError(f"noise_step must be ({t_total}, {groups}) step indices")
    noise_step = noise_step[::every].astype(np.int32)  # the recorded samples' (n_rec, G)
    return _Plan(q_ref, group, phase, noise_step, every, settle_steps)


def _checked_reference(sim: MjxSimulator, q_ref: np.ndarray) -> np.ndarray:
    """``q_ref`` as (T, G, n) rad, finite and within the joint limits (InputError)."""
    hard = sim.joint_limits
    q_ref = np.asarray(q_ref, dtype=float)
    if q_ref.ndim == 2:
        q_ref = q_ref[:, None]
    if q_ref.ndim != 3 or q_ref.shape[2] != sim.n or not np.isfinite(q_ref).all():
        raise InputError(f"q_ref must be a finite (T, {sim.n}) or (T, G, {sim.n}) rad array")
    outside = (q_ref < hard[:, 0]) | (q_ref > hard[:, 1])
    if outside.any():
        i, g, j = np.argwhere(outside)[0]
        where = f"{i}, {j}" if q_ref.shape[1] == 1 else f"{i}, {g}, {j}"
        raise InputError(
            f"q_ref[{where}] = {q_ref[i, g, j]:.4g} rad is beyond joint {j}'s limits "
            f"[{hard[j, 0]:.4g}, {hard[j, 1]:.4g}] rad"
        )
    return q_ref


def _prepare(
    sim: MjxSimulator,
    truth: BatchTruth,
    plan: _Plan,
    initial_pose: str | Sequence[float] | np.ndarray | None,
    seed: int,
    world_ids: Sequence[int] | np.ndarray | None,
    record: Sequence[int] | np.ndarray | None,
    keep: bool,
    on_chunk: Callable | None,
    reduce: Reduction | None,
) -> _Job:
    """The worlds' fields and poses, the recorded rows and the compiled chunk function."""
    w, (t_total, groups) = truth.worlds, plan.q_ref.shape[:2]
    q0 = sim.initial_poses(initial_pose, w)
    fields = sim.world_fields(truth)
    pad = world_padding(sim.mesh, w)
    wp = len(pad)
    fields = {k: v[pad] for k, v in fields.items()}
    ids = np.arange(w) if world_ids is None else np.asarray(world_ids, np.int64)
    if ids.shape != (w,) or (ids < 0).any():
        raise InputError(f"world_ids must be ({w},) ints >= 0")
    rows = np.arange(w) if record is None else np.asarray(record, np.int64).reshape(-1)
    if ((rows < 0) | (rows >= w)).any():
        raise InputError(f"record must hold world indices in [0, {w})")
    if not keep and on_chunk is None:  # nobody reads the samples: none leave the device
        rows = rows[:0]
    fields["key"] = sim.world_keys(seed, ids)[pad]
    fields["group"] = plan.group.astype(np.int32)[pad]
    q0 = q0[pad]
    every = plan.every
    chunk = sim.chunk_length(wp, every, max(t_total, plan.settle_steps, 1))
    limits = (sim.following_error, sim.overspeed)
    xs = _reduction_rows(reduce, plan.noise_step.shape[0], groups)
    shape = lambda a: (np.shape(a), np.result_type(a).str)  # noqa: E731
    row = lambda a: (np.shape(a)[1:], np.result_type(a).str)  # noqa: E731  any plan length
    red_key = (
        None
        if reduce is None
        else (reduce.key, str(jax.tree.map(shape, reduce.init)), str(jax.tree.map(row, xs)))
    )
    # each device's recorded worlds, padded to a multiple of RECORD_BUCKET: runs recording a
    # few worlds (or none) share one compiled program
    local_rows, where = device_rows(rows, wp, devices(sim.mesh), RECORD_BUCKET)
    key = ("open", wp, chunk, every, groups, limits, sim.mesh, red_key, local_rows.size)
    step = None if reduce is None else reduce.step
    fn = sim.compiled_function(key, lambda: _build(sim, chunk, every, *limits, step))
    put, put_shared = placement(sim.mesh)
    fields = put(fields)
    rows_dev = put(local_rows.astype(np.int32))
    return _Job(fn, fields, q0, rows, where, rows_dev, chunk, xs, put, put_shared)


def _rows_of(job: _Job, plan: _Plan, s: int, a: np.ndarray) -> Any:
    """The rows of per-sample array ``a`` (R, ...) of the chunk from step ``s``, placed (the
    last row repeated past the end)."""
    per = job.chunk // plan.every
    return job.put_shared(a[np.minimum(s // plan.every + np.arange(per), len(a) - 1)])


def _xs_of(job: _Job, plan: _Plan, s: int) -> Any:
    """The reduction's rows of the chunk from step ``s``, placed."""
    return jax.tree.map(lambda a: _rows_of(job, plan, s, a), job.xs)


def _settle(sim: MjxSimulator, job: _Job, plan: _Plan, reduce: Reduction | None) -> tuple:
    """The carry after the settling: each world servoed to its initial pose (target q0 = 0
    reference + per-world offset q0), its fault step reset."""
    wp, n, dtype, every, chunk = len(job.q0), sim.n, sim.dtype, plan.every, job.chunk
    put, put_shared = job.put, job.put_shared
    groups, settle_steps = plan.q_ref.shape[1], plan.settle_steps
    zeros = np.zeros((wp, n), dtype)
    acc = () if reduce is None else _broadcast(reduce.init, wp, sim.mesh, put_shared)
    carry = (*put((job.q0.astype(dtype), zeros, zeros, np.full(wp, -1, np.int32))), acc)
    per = chunk // every
    settle_noise = lambda s: put_shared(  # noqa: E731  settling: its own (negative) steps
        np.repeat((s + np.arange(per) * every)[:, None], groups, 1).astype(np.int32)
    )
    settle_fields = dict(job.fields, offset=put(job.q0.astype(dtype)))
    zero_ref = put_shared(np.zeros((chunk, groups, n), dtype))
    settling = put_shared(np.full((chunk, groups), SETTLE, np.int8))
    for s in range(0, settle_steps, chunk):
        carry, _ = job.fn(
            settle_fields,
            carry,
            zero_ref,
            settling,
            _xs_of(job, plan, 0),
            settle_noise(s - settle_steps),
            job.rows_dev,
            np.int32(s - settle_steps),
            np.int32(min(chunk, settle_steps - s)),
        )
    return (*carry[:3], carry[3] * 0 - 1, carry[4])


def _follow(
    sim: MjxSimulator,
    job: _Job,
    plan: _Plan,
    carry: tuple,
    keep: bool,
    on_chunk: Callable | None,
    progress: Callable | None,
) -> tuple[tuple, dict[str, np.ndarray]]:
    """The plan, chunk by chunk: the final carry and the kept samples (q, dq, current)."""
    n, dtype, every, chunk = sim.n, sim.dtype, plan.every, job.chunk
    (t_total, groups), n_rec = plan.q_ref.shape[:2], plan.noise_step.shape[0]
    plan_fields = dict(job.fields, offset=job.put(np.zeros((len(job.q0), n), dtype)))
    out = (
        {k: np.zeros((job.rows.size, n_rec, n), dtype) for k in ("q", "dq", "current")}
        if keep
        else {}
    )

    def consume(pending: tuple) -> None:
        """Copy a chunk's samples to the host, stream them and report progress."""
        s, k, rec = pending
        nr = -(-k // every)  # samples of the chunk's valid steps
        q, dq, cur = (np.asarray(a)[job.where, :nr] for a in rec)
        first = s // every
        if out:
            out["q"][:, first : first + nr] = q
            out["dq"][:, first : first + nr] = dq
            out["current"][:, first : first + nr] = cur
        if on_chunk is not None:
            t = ((first + np.arange(nr)) * every + 1) * CONTROL_PERIOD
            empty = np.zeros((0, n))
            on_chunk(first, MjxRecording(t, q, dq, cur, empty, np.zeros(0, int), every))
        if progress is not None:
            progress(s + k, t_total)

    pending: tuple | None = None
    for s in range(0, t_total, chunk):
        ref = np.empty((chunk, groups, n), dtype)
        ph = np.zeros((chunk, groups), np.int8)
        k = min(chunk, t_total - s)
        ref[:k], ref[k:], ph[:k] = (
            plan.q_ref[s : s + k],
            plan.q_ref[s + k - 1],
            plan.phase[s : s + k],
        )
        carry, rec = job.fn(
            plan_fields,
            carry,
            job.put_shared(ref),
            job.put_shared(ph),
            _xs_of(job, plan, s),
            _rows_of(job, plan, s, plan.noise_step),
            job.rows_dev,
            np.int32(s),
            np.int32(k),
        )
        if pending is not None:  # host work overlaps the chunk just dispatched
            consume(pending)
        pending = (s, k, rec)
    if pending is not None:
        consume(pending)
    return carry, out


def _reduction_rows(reduce: Reduction | None, n_rec: int, groups: int) -> Any:
    """The reduction's rows (R, G, ...) as host arrays, checked (an empty one without it)."""
    if reduce is None:
        return np.zeros((1, groups))
    xs = jax.tree.map(np.asarray, reduce.xs)
    for a in jax.tree.leaves(xs):
        if a.shape[:2] != (n_rec, groups):
            raise InputError(f"the reduction's rows must be ({n_rec}, {groups}, ...) arrays")
    return xs


def _broadcast(init: Any, worlds: int, mesh: Any, put_shared: Callable) -> Any:
    """One world's initial carry for every world, made on the device(s), split along the
    mesh's ``"batch"`` axis (no host copy of the W worlds')."""
    one = put_shared(jax.tree.map(lambda a: np.asarray(a)[None], init))
    out = None if mesh is None else NamedSharding(mesh, P("batch"))
    repeat = lambda t: jax.tree.map(lambda a: jnp.repeat(a, worlds, axis=0), t)  # noqa: E731
    return jax.jit(repeat, out_shardings=out)(one)


def _build(
    sim: MjxSimulator,
    chunk: int,
    every: int,
    following_error: float,
    overspeed: float,
    reduce_step: Callable | None,
) -> Callable:
    """The jitted chunk function of ``run``: (fields, carry, reference rows (chunk, G, n),
    phase rows (chunk, G) (``PLAN``, ``SETTLE``, ``RESTART``), reduction rows
    (chunk // every, G, ...), the recorded samples' noise steps (chunk // every, G), recorded
    worlds (M,) (indices into the device's own, ``device_rows``), first step, valid steps) ->
    (carry, recorded (q, dq, current) (M, chunk // every, n)). Carry per world: qpos, qvel,
    qacc_warmstart, fault step (first step with a joint at its limit, beyond
    ``following_error`` rad of its target or faster than ``overspeed`` rad/s), the reduction's
    carry (``Reduction``; () without one)."""
    mx, d0, dtype, n = sim.mjx_model, sim.mjx_data, sim.dtype, sim.n
    lo = jnp.asarray(sim.joint_limits[:, 0], dtype)
    hi = jnp.asarray(sim.joint_limits[:, 1], dtype)
    groups = chunk // every
    step_fn = implicitfast_step(sim.model, dtype)

    def world_step(f, qpos, qvel, qacc, q_target):
        m = mx.tree_replace({k: f[k] for k in WORLD_MODEL_FIELDS if k in f})
        d = d0.replace(qpos=qpos, qvel=qvel, qacc_warmstart=qacc, ctrl=f["kp"] * q_target)
        out = step_fn(m, d)[:4]
        return tuple(a.astype(dtype) for a in out)

    vstep = over_worlds(world_step, sim.backend, (0, 0, 0, 0, 0))

    def step(f, carry, i, x, start, n_valid):
        qpos, qvel, qacc, fault = carry
        qr, ph = x
        target = qr[f["group"]] + f["offset"]  # each world's reference (G, n) -> (W, n)
        ph = ph[f["group"]]
        restart = (ph == RESTART)[:, None]  # at rest at the reference
        qpos = jnp.where(restart, target, qpos)
        qvel, qacc = (jnp.where(restart, 0.0, a) for a in (qvel, qacc))
        q1, dq1, acc1, tau = vstep(f, qpos, qvel, qacc, target)
        valid = i < n_valid
        t = start + i
        bad = (
            ((q1 <= lo) | (q1 >= hi)).any(axis=1)
            | (jnp.abs(dq1) > overspeed).any(axis=1)
            | (jnp.abs(q1 - target) > following_error).any(axis=1)
        )
        counted = valid & (t >= 0) & (ph == PLAN)
        fault = jnp.where((fault < 0) & bad & counted, t.astype(fault.dtype), fault)
        keep = lambda new, old: jnp.where(valid, new, old)  # noqa: E731
        carry = (keep(q1, qpos), keep(dq1, qvel), keep(acc1, qacc), fault)
        return carry, (q1, dq1, tau)

    def noise(f, t):
        """(W, n) A: each world's current noise at its noise step t (W,)."""

        def one(key, sigma, ti):
            z = jax.random.normal(jax.random.fold_in(key, ti), (n,), dtype)
            return sigma * z

        return jax.vmap(one)(f["key"], f["noise"], t)

    def reduce(f, acc, xs, q, dq, cur, valid):
        """The reduction over the chunk's recorded samples, world by world."""
        vstep = jax.vmap(reduce_step, in_axes=(0, 0, 0, 0, 0, None))

        def body(a, sample):
            x, qi, dqi, ci, vi = sample
            mine = jax.tree.map(lambda r: r[f["group"]], x)  # each world's row
            return vstep(a, mine, qi, dqi, ci, vi), None

        return jax.lax.scan(body, acc, (xs, q, dq, cur, valid))[0]

    def chunk_fn(f, carry, qr, ph, xs, ck, rows, start, n_valid):
        state, (q, dq, tau) = scan_decimated(
            lambda c, i, x: step(f, c, i, x, start, n_valid), carry[:4], (qr, ph), every
        )
        offsets = jnp.arange(groups) * every
        times = start + offsets
        cur = f["ratio"][None] * tau + jax.vmap(lambda t: noise(f, t[f["group"]]))(ck)
        acc = carry[4]
        if reduce_step is not None:
            acc = reduce(f, acc, xs, q, dq, cur, (times >= 0) & (offsets < n_valid))
        return (*state, acc), tuple(jnp.swapaxes(a, 0, 1)[rows] for a in (q, dq, cur))

    # fields, carry and the recorded worlds (each device's own, ``device_rows``): per world
    specs = (WORLDS, WORLDS, SHARED, SHARED, SHARED, SHARED, WORLDS, SHARED, SHARED)
    return sim.ahead_of_time(chunk_fn, 1, specs, WORLDS)
