"""Sweep moments: a recording reduced to one small matrix per sweep, exact for the joint fit.

While joint j sweeps with the others held at h, its gravity torque is exactly
a(h) sin(theta) + b(h) cos(theta) + c(h) in the swept angle theta (the carried subtree turns
rigidly about the joint axis), and so is each column of its regressor and their derivatives
with respect to h. Held joints are never quite still (servo compliance: they give way as the
load changes along the sweep), so the fit takes the torque to first order in each sample's
held pose: with dh = q - hold (the sweep's mean pose over its steady samples; 0 for the swept
joint) and u = [1, dh] (n + 1), a sample's torque is linear in
z = [sin theta u, cos theta u, u] (3 (n + 1)). With psi = [z, d, v, current] per steady sample
(d the direction, v the pass velocity in rad/s: d times the mean speed of the pass's steady
samples, not the measured velocity, whose servo ripple correlates with the current; current
the swept joint's in A), the sums ``sum psi psi^T`` over a sweep hold everything a
least-squares fit of Eq. (13) (plus a viscous term in v) on that sweep needs: the fit never
touches the samples again.

Two steps: ``pack`` (host, pure data movement) copies t, the swept joint's dq and current and
every joint's q of every pass back to back, each pass from the start of a block of ``BLOCK``
samples; the reduction (JAX, jitted, on the default backend: a GPU reduces thousands of
recordings at once) finds the steady samples (``identify.bins.steady``'s rule), their mean pose
and the moments, block by block: no gathers of samples, and passes padded only to whole blocks.
The median speed of a pass takes every ``MEDIAN_STRIDE``-th sample.

Streaming (``stream_plan``, ``stream_add``, ``streamed_moments``): the same sums added sample by
sample while a simulation runs (the MJX studies, on the device), with the steady samples chosen
from the plan's commanded speed, which needs no median; the sums are taken about each sweep's
commanded pose and moved to the held pose at the end, exactly (u is affine in the pose).
"""

from __future__ import annotations

import mmap
import threading
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.errors import InputError
from jaxcomp.identify.bins import (
    MEDIAN_STRIDE,
    STEADY_FRACTION,
    STEADY_SETTLE,
    STEADY_TRIM,
    settle_time,
)
from jaxcomp.recording import Recording


class SweepMoments(NamedTuple):
    """Moments of the steady samples of each sweep of a recording (S sweeps, n joints).

    joint (S,) int: the swept joint. hold (S, n) rad: the held pose of the sweep, the mean of
    q over its steady samples (the swept joint's entry is irrelevant). moments (S, D, D),
    D = ``moment_size(n)``: sum of psi psi^T (see the module docstring). count (S,): steady
    samples. gravity (3,) m/s^2; payload_mass kg; payload_com (3,) m, end-effector frame.
    """

    joint: np.ndarray
    hold: np.ndarray
    moments: np.ndarray
    count: np.ndarray
    gravity: np.ndarray
    payload_mass: float
    payload_com: np.ndarray

    @property
    def n_sweeps(self) -> int:
        return self.joint.shape[0]

    @property
    def n_samples(self) -> int:
        return int(self.count.sum())


def moment_size(n: int) -> int:
    """D: the size of a sweep's moment matrix for n joints, psi = [z (3 (n + 1)), d, v, current]."""
    return 3 * (n + 1) + 3


def z_index(term: int, k: int, n: int) -> int:
    """Index in psi of z's entry (``term``: 0 sin theta, 1 cos theta, 2 one) x u_k (k = 0:
    one, k = 1 + i: the held offset dh of joint i)."""
    return term * (n + 1) + k


def sweep_moments(rec: Recording, fraction: float = STEADY_FRACTION) -> SweepMoments:
    """The ``SweepMoments`` of ``rec``: its steady samples (see ``identify.bins.steady``),
    reduced on the default JAX backend; sweeps without steady samples are left out."""
    packed, length = pack([rec])
    m = jax.tree.map(lambda a: np.asarray(a)[0], packed_moments(packed, length, fraction))
    used = m.count > 0
    if not used.any():
        raise InputError(
            "the recording has no steady sweep samples (the swept joint never moves at a "
            "constant speed in its direction)"
        )
    return SweepMoments(
        joint=m.joint[used].astype(np.int64),
        hold=m.hold[used],
        moments=m.moments[used],
        count=m.count[used].astype(np.int64),
        gravity=np.asarray(rec.gravity, float),
        payload_mass=float(rec.payload_mass),
        payload_com=np.asarray(rec.payload_com, float),
    )


def sweep_moments_batch(
    t: np.ndarray,
    q: np.ndarray,
    dq: np.ndarray,
    current: np.ndarray,
    joint: np.ndarray,
    direction: np.ndarray,
    *,
    gravity: Sequence[float] = STANDARD_GRAVITY,
    fraction: float = STEADY_FRACTION,
    trim: float = STEADY_TRIM,
    current_lag: float = 0.0,
) -> SweepMoments:
    """``sweep_moments`` of W recordings that share their time base and sweep labels.

    ``t`` (T,) s, ``joint`` (T,) and ``direction`` (T,) are common to every world (one plan
    recorded in W simulated worlds); ``q`` (W, T, n) rad, ``dq`` (W, T, n) rad/s and
    ``current`` (W, T, n) A are each world's; ``current_lag`` s as a recording's. Returns a
    ``SweepMoments`` whose every field has a leading world axis: joint (W, S), hold (W, S, n),
    moments (W, S, D, D), count (W, S), gravity (W, 3), payload_mass (W,), payload_com (W, 3),
    with one entry per sweep of the labels; a sweep without steady samples in a world has zero
    moments, hold and count there (it adds nothing to a fit). ``world_moments(batch, w)`` is
    world w's ``sweep_moments``, to rounding (sums in another order).
    """
    t = np.asarray(t, float)
    joint = np.asarray(joint)
    direction = np.asarray(direction)
    q, dq, current = (np.asarray(a, float) for a in (q, dq, current))
    w, steps, n = q.shape
    if t.shape != (steps,) or joint.shape != (steps,) or direction.shape != (steps,):
        raise InputError(f"t, joint and direction must have shape ({steps},) like q's axis 1")
    if dq.shape != q.shape or current.shape != q.shape:
        raise InputError(f"q, dq and current must have the same shape (W, T, n), got {q.shape}")
    lay = layout(joint, direction)
    S = lay.joint.size
    S_pad, N, L = lay.sizes()
    samples = np.zeros((w, _ROWS + n, N))
    _fill(lay, t, current_pose(q, dq, current_lag), dq, current, samples)
    meta = {k: np.broadcast_to(v, (w, *v.shape[1:])) for k, v in _meta([lay], S_pad).items()}
    packed = Packed(
        samples=samples,
        **meta,
        gravity=np.broadcast_to(np.asarray(gravity, float), (w, 3)),
        payload_mass=np.zeros(w),
        payload_com=np.zeros((w, 3)),
    )
    m = jax.tree.map(np.asarray, packed_moments(packed, L, fraction, trim))
    return SweepMoments(
        joint=np.broadcast_to(lay.joint, (w, S)).astype(np.int64),
        hold=m.hold[:, :S],
        moments=m.moments[:, :S],
        count=m.count[:, :S].astype(np.int64),
        gravity=np.broadcast_to(np.asarray(gravity, float), (w, 3)).copy(),
        payload_mass=np.zeros(w),
        payload_com=np.zeros((w, 3)),
    )


def world_moments(batch: SweepMoments, w: int, keep_empty: bool = False) -> SweepMoments:
    """World ``w`` of a batch of moments (``sweep_moments_batch``, ``concat_moments``) as one
    recording's ``SweepMoments``; sweeps without steady samples are dropped (``keep_empty``:
    kept, with joint -1, so that rows stay aligned with the batch's sweeps)."""
    used = batch.count[w] > 0
    pick = slice(None) if keep_empty else used
    joint = np.where(used, batch.joint[w], -1) if keep_empty else batch.joint[w]
    return SweepMoments(
        joint=joint[pick],
        hold=batch.hold[w][pick],
        moments=batch.moments[w][pick],
        count=batch.count[w][pick],
        gravity=np.asarray(batch.gravity[w]),
        payload_mass=float(batch.payload_mass[w]),
        payload_com=np.asarray(batch.payload_com[w]),
    )


def concat_moments(parts: Sequence[SweepMoments]) -> SweepMoments:
    """Batches of moments of consecutive stretches of the same worlds, joined along the
    sweep axis (axis 1); metadata from the first part."""
    if not parts:
        raise InputError("no moments to join")
    cat = [np.concatenate([getattr(p, k) for p in parts], axis=1) for k in _PER_SWEEP]
    return parts[0]._replace(**dict(zip(_PER_SWEEP, cat, strict=True)))


_PER_SWEEP = ("joint", "hold", "moments", "count")


def join_sweeps(parts: Sequence[SweepMoments], order: np.ndarray) -> SweepMoments:
    """``concat_moments(parts)`` with its sweeps (axis 1) taken in ``order`` (indices into the
    joined sweeps), written once into the result (no joined copy)."""
    sizes = [p.joint.shape[1] for p in parts]
    where = np.empty(sum(sizes), np.int64)
    where[order] = np.arange(len(order))  # the result's column of each joined sweep
    out = {}
    for k in _PER_SWEEP:
        first = getattr(parts[0], k)
        out[k] = np.empty((first.shape[0], len(order), *first.shape[2:]), first.dtype)
        for p, cols in zip(parts, np.split(where, np.cumsum(sizes)[:-1]), strict=True):
            out[k][:, cols] = getattr(p, k)
    return parts[0]._replace(**out)


def stack_worlds(parts: Sequence[SweepMoments]) -> SweepMoments:
    """Batches of moments of the same sweeps in other worlds, joined along the world axis."""
    if not parts:
        raise InputError("no moments to join")
    if len(parts) == 1:
        return parts[0]
    return SweepMoments(*(np.concatenate([getattr(p, f) for p in parts]) for f in parts[0]._fields))


# ------------------------------------------------------------------------ packing (host)
#: Rows of ``Packed.samples`` before the joints' angles: t, the swept joint's dq and current.
_ROWS = 3
#: Samples per block: every pass starts a block (the reduction sums block by block).
BLOCK = 512
_GROUP = 64  # blocks whose moments are formed at once
_PASS_BUCKET = 1024  # samples: pass lengths round up to this (few compiled shapes)
_SAMPLE_BUCKET = 1 << 15
_SWEEP_BUCKET = 8


def _up(n: int, bucket: int) -> int:
    return max(bucket, -(-n // bucket) * bucket)


class Packed(NamedTuple):
    """The sweep samples of recordings, what ``reduce_packed`` reduces (host or device arrays;
    ``pack`` and ``packed_moments`` stack recordings along a leading axis, the shapes below are
    one recording's).

    S sweeps of up to two passes (slot 0 the first, slot 1 the return). samples (3 + n, N):
    t s, the swept joint's dq rad/s and current A, then q rad of every joint, the passes back to
    back, each from the start of a block of ``BLOCK`` samples (N a multiple of it); samples
    outside passes hold any finite values. start, length (S, 2) int: where each pass begins in
    samples (a multiple of ``BLOCK``), and its sample count (0: no such pass). direction (S, 2)
    float, +1 / -1 (0: no pass). joint (S,) int, the swept joint. gravity (3,) m/s^2,
    payload_mass kg, payload_com (3,) m.
    """

    samples: np.ndarray
    start: np.ndarray
    length: np.ndarray
    direction: np.ndarray
    joint: np.ndarray
    gravity: np.ndarray
    payload_mass: np.ndarray
    payload_com: np.ndarray


class Layout(NamedTuple):
    """Where the passes of each sweep lie in a recording (from its labels alone).

    joint (S,) int; first, length (S, 2) int: first sample and sample count of each pass
    (length 0: no second pass); direction (S, 2) int. Sweeps are as ``identify.bins.sweep_ids``
    numbers them.
    """

    joint: np.ndarray
    first: np.ndarray
    length: np.ndarray
    direction: np.ndarray

    def blocks(self) -> np.ndarray:
        """(S, 2) int: the samples each pass takes in the packed form, whole blocks."""
        return -(-self.length // BLOCK) * BLOCK

    def sizes(self) -> tuple[int, int, int]:
        """Bucketed (S sweeps, N samples, L pass length) of the packed form."""
        return (
            _up(self.joint.size, _SWEEP_BUCKET),
            _up(int(self.blocks().sum()), _SAMPLE_BUCKET),
            _up(int(self.length.max(initial=1)), _PASS_BUCKET),
        )


def layout(joint: np.ndarray, direction: np.ndarray) -> Layout:
    """The ``Layout`` of the labels ``joint`` (N,) and ``direction`` (N,): each contiguous run
    of one swept joint holds passes of alternating direction, two to a sweep."""
    joint = np.asarray(joint)
    direction = np.asarray(direction)
    edges = np.flatnonzero((joint[1:] != joint[:-1]) | (direction[1:] != direction[:-1])) + 1
    starts = np.r_[0, edges]
    ends = np.r_[edges, joint.size]
    sweeps: list[tuple[int, list[tuple[int, int, int]]]] = []
    previous, k = -1, 0
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        j = int(joint[s])
        if j < 0:
            previous = -1
            continue
        k = k + 1 if j == previous else 0
        if k % 2 == 0:
            sweeps.append((j, []))
        sweeps[-1][1].append((s, e - s, int(direction[s])))
        previous = j
    S = len(sweeps)
    first = np.zeros((S, 2), np.int64)
    length = np.zeros((S, 2), np.int64)
    sign = np.zeros((S, 2), np.int64)
    for i, (_, passes) in enumerate(sweeps):
        for slot, (s, n, d) in enumerate(passes):
            first[i, slot], length[i, slot], sign[i, slot] = s, n, d
    return Layout(np.array([j for j, _ in sweeps], np.int64), first, length, sign)


def _fresh_zeros(shape: tuple[int, ...]) -> np.ndarray:
    """Zeros (float64) of ``shape`` in fresh anonymous memory: page-aligned, so that XLA's CPU
    client uses it in place (it copies host memory not aligned to 64 bytes; numpy aligns to
    16), and in small pages: numpy asks Linux for huge pages for a large array, and the first
    ones cost ~0.4 s per 100 MB on the 2-core test machine (memory compacted first) against
    0.07 s here."""
    count = int(np.prod(shape))
    memory = mmap.mmap(-1, max(count * 8, 1))  # zero-filled by the kernel as it is touched
    return np.frombuffer(memory, np.float64, count).reshape(shape)


class PackBuffer:
    """A host buffer that ``pack`` reuses from call to call (one pack at a time): writing into
    memory already mapped is several times faster than into fresh pages. Aligned for XLA: on a
    CPU the device array of a pack aliases it."""

    def __init__(self) -> None:
        self._samples = np.zeros((0, 0, 0))
        self._lock = threading.Lock()

    def take(self, k: int, rows: int, N: int, touch: bool = False) -> np.ndarray:
        """A view (k, rows, N) with arbitrary finite contents (of the array from before when
        it is large enough). ``touch``: map fresh memory now (another thread may, ahead of the
        pack)."""
        with self._lock:
            if any(a < b for a, b in zip(self._samples.shape, (k, rows, N), strict=True)):
                samples = _fresh_zeros((k, rows, N))
                if touch:
                    samples.fill(0.0)
                self._samples = samples
            return self._samples[:k, :rows, :N]


def _meta(lays: Sequence[Layout], S: int) -> dict[str, np.ndarray]:
    """Per-pass fields of ``Packed`` for the layouts, stacked and padded to S sweeps."""
    k = len(lays)
    out = {f: np.zeros((k, S, 2), np.int64) for f in ("start", "length")}
    out["direction"] = np.zeros((k, S, 2))
    out["joint"] = np.zeros((k, S), np.int64)
    for i, lay in enumerate(lays):
        m = lay.joint.size
        taken = lay.blocks()
        out["start"][i, :m] = np.cumsum(taken.ravel()).reshape(-1, 2) - taken
        out["length"][i, :m] = lay.length
        out["direction"][i, :m] = lay.direction
        out["joint"][i, :m] = lay.joint
    return out


def current_pose(q: np.ndarray, dq: np.ndarray, lag: float) -> np.ndarray:
    """The pose at which each sample's current flowed, rad: ``q - lag dq`` (``lag`` s, a
    recording's ``current_lag``); ``q`` itself when ``lag`` is 0."""
    return q - lag * dq if lag else q


def _fill(lay: Layout, t, q, dq, current, samples: np.ndarray) -> None:
    """Copy the passes of ``lay`` into ``samples`` (..., 3 + n, N), in packed order (each pass
    from the start of a block); ``q``, ``dq``, ``current`` (..., T, n) and ``t`` (T,) of one
    recording or of worlds that share the layout (a leading axis). Slice copies, no index
    arrays."""
    at = 0
    taken = lay.blocks().tolist()
    for s, j in enumerate(lay.joint.tolist()):
        for f, m, k in zip(lay.first[s].tolist(), lay.length[s].tolist(), taken[s], strict=True):
            part = slice(f, f + m)
            samples[..., 0, at : at + m] = t[part]
            samples[..., 1, at : at + m] = dq[..., part, j]
            samples[..., 2, at : at + m] = current[..., part, j]
            samples[..., _ROWS:, at : at + m] = np.swapaxes(q[..., part, :], -1, -2)
            at += k


def pack(recs: Sequence[Recording], buffer: PackBuffer | None = None) -> tuple[Packed, int]:
    """The sweep samples of recordings, stacked (a leading axis on every field of the
    ``Packed``; host arrays, padded to the largest), and the pass length (samples) to reduce
    them with. Pure data movement.

    ``buffer``: reuse its array for the samples (the result then aliases it: send it to the
    device before the next ``pack`` into the same buffer)."""
    lays = [layout(r.joint, r.direction) for r in recs]
    for i, lay in enumerate(lays):
        if lay.joint.size == 0:
            raise InputError(f"recording {i} has no sweep (field 'joint' is -1 everywhere)")
    n = recs[0].q.shape[1]
    S, N, L = (max(dims) for dims in zip(*(lay.sizes() for lay in lays), strict=True))
    samples = (buffer or PackBuffer()).take(len(recs), _ROWS + n, N)
    for i, (rec, lay) in enumerate(zip(recs, lays, strict=True)):
        _fill(
            lay,
            rec.t,
            current_pose(rec.q, rec.dq, rec.current_lag),
            rec.dq,
            rec.current,
            samples[i],
        )
    packed = Packed(
        samples=samples,
        **_meta(lays, S),
        gravity=np.stack([np.asarray(r.gravity, float) for r in recs]),
        payload_mass=np.array([float(r.payload_mass) for r in recs]),
        payload_com=np.stack([np.asarray(r.payload_com, float) for r in recs]),
    )
    return packed, L


# ------------------------------------------------------------------- shared maths (JAX)
def features(theta: jax.Array, dh: jax.Array, current: jax.Array) -> jax.Array:
    """phi = [z, current] (..., 3 (n + 1) + 1) of samples: z = [sin theta u, cos theta u, u]
    with u = [1, dh]; ``theta`` (...) rad the swept angle, ``dh`` (..., n) rad, ``current``
    (...) A the swept joint's."""
    u = jnp.concatenate([jnp.ones_like(dh[..., :1]), dh], axis=-1)  # (..., n + 1)
    trig = jnp.stack([jnp.sin(theta), jnp.cos(theta), jnp.ones_like(theta)], axis=-1)
    z = (trig[..., :, None] * u[..., None, :]).reshape(*theta.shape, -1)
    return jnp.concatenate([z, current[..., None]], axis=-1)


def assemble(G: jax.Array, d: jax.Array, v: jax.Array, n: int) -> jax.Array:
    """The moments (S, D, D) of S sweeps from G (S, 2, Z + 1, Z + 1), each pass's sums of
    phi phi^T (``features``), and its direction ``d`` (S, 2) and velocity ``v`` (S, 2) rad/s.

    psi = E phi with E constant over a pass (d and v are multiples of z's "one"): the
    moments are sum over passes of E G E^T."""
    S, Z = G.shape[0], G.shape[-1] - 1
    D = moment_size(n)
    one = z_index(2, 0, n)
    E = jnp.zeros((S, 2, D, Z + 1), G.dtype)
    E = E.at[:, :, jnp.arange(Z), jnp.arange(Z)].set(1.0)
    E = E.at[:, :, Z, one].set(d).at[:, :, Z + 1, one].set(v)
    E = E.at[:, :, Z + 2, Z].set(1.0)
    return jnp.einsum("skai,skij,skbj->sab", E, G, E)


# ----------------------------------------------------------------------- reduction (JAX)
def _median(x: jax.Array, keep: jax.Array, axis: int = -1) -> jax.Array:
    """Median of ``x`` over ``axis`` where ``keep``, exactly ``np.median`` of the kept values
    (the middle one, or the mean of the two); NaN where none is kept."""
    data = jnp.sort(jnp.where(keep, x, jnp.inf), axis=axis)
    c = jnp.sum(keep, axis=axis, keepdims=True)
    lo = jnp.take_along_axis(data, jnp.maximum((c - 1) // 2, 0), axis=axis)
    hi = jnp.take_along_axis(data, jnp.maximum(c // 2, 0), axis=axis)
    return jnp.squeeze(jnp.where(c > 0, 0.5 * (lo + hi), jnp.nan), axis)


def _in_memory(x: jax.Array) -> jax.Array:
    """``x`` (2, ...), computed once into memory. XLA's CPU backend fuses a value into every
    row of a concatenation that uses it and computes it again for each: sin and cos of the swept
    angle, used by 2 (n + 1) rows of the moments' features, would cost 14 sines a sample. The
    operands of a product with the identity (a dot) are computed into memory; the product
    itself is 4 flops a sample."""
    return jnp.einsum("ij,j...->i...", jnp.eye(2, dtype=x.dtype), x)


def reduce_packed(p: Packed, L: int, fraction: float, trim: float) -> SweepMoments:
    """Sweep moments of one packed recording, its longest pass at most ``L`` samples (pure,
    vmap-able; ``packed_moments`` runs it on a stack). ``fraction`` and ``trim``: see
    ``identify.bins.steady`` (whose ``settle`` is ``STEADY_SETTLE`` here).

    Block by block (``BLOCK`` samples, each of one pass or none): per-pass sums are sums over
    blocks, and the moments are one small matrix product per block.
    """
    rows, N = p.samples.shape
    n = rows - _ROWS
    S = p.joint.shape[0]
    x = p.samples.reshape(rows, N // BLOCK, BLOCK)
    # (nb, BLOCK) each; the angles row by row (a slice of them all would be copied)
    t, rate, current, q = x[0], x[1], x[2], [x[_ROWS + i] for i in range(n)]
    first, length, sign = (a.reshape(-1) for a in (p.start, p.length, p.direction))  # (2 S,)
    at = jnp.arange(N // BLOCK) * BLOCK
    member = (at[:, None] >= first) & (at[:, None] < first + length)  # (nb, 2 S): its pass
    of = member.astype(t.dtype)
    k = jnp.argmax(member, axis=1)  # (nb,) the block's pass (any one for a block of none)
    valid = jnp.any(member, axis=1)[:, None] & (
        (at - first[k])[:, None] + jnp.arange(BLOCK) < length[k][:, None]
    )

    def total(x: jax.Array, keep: jax.Array) -> jax.Array:  # (2 S,) sums over each pass
        return jnp.sum(jnp.where(keep, x, 0.0), axis=1) @ of

    def mean(x: jax.Array, keep: jax.Array) -> jax.Array:  # (2 S,), 0 where none is kept
        return total(x, keep) / jnp.maximum(total(1.0, keep), 1.0)

    speed = rate * sign[k][:, None]  # along the pass's direction
    # the pass speed: the mean over the samples at >= ``fraction`` of the median speed of every
    # MEDIAN_STRIDE-th sample (the median alone may fall on a ramp when a pass has few samples)
    sub = jnp.arange(0, L, MEDIAN_STRIDE)
    strided = p.samples[1][jnp.minimum(first[:, None] + sub, N - 1)] * sign[:, None]
    median = _median(strided, sub < length[:, None])[k][:, None]  # (nb, 1)
    ref = mean(speed, valid & (speed >= fraction * median) & (median > 0))[k][:, None]
    fast = valid & (jnp.abs(speed - ref) <= (1.0 - fraction) * ref) & (ref > 0)
    lo = jnp.min(jnp.where(fast, t, jnp.inf), axis=1)[:, None]  # (nb, 1), then over the pass
    hi = jnp.max(jnp.where(fast, t, -jnp.inf), axis=1)[:, None]
    lo = jnp.min(jnp.where(member, lo, jnp.inf), axis=0)[k][:, None]
    hi = jnp.max(jnp.where(member, hi, -jnp.inf), axis=0)[k][:, None]
    start = settle_time(hi - lo, STEADY_SETTLE, trim, xp=jnp)
    steady = fast & (t > lo + start) & (t < hi - trim)
    v = sign * mean(speed, steady)  # (2 S,) rad/s
    w = steady.astype(t.dtype)
    count = jnp.round(total(1.0, steady)).astype(int).reshape(S, 2).sum(axis=1)
    held = (jnp.stack([jnp.sum(qi * w, axis=1) for qi in q]) @ of).reshape(n, S, 2).sum(axis=2)
    hold = held.T / jnp.maximum(count, 1)[:, None]  # (S, n)
    sweep = k // 2
    joint = p.joint[sweep]  # (nb,) the block's swept joint
    at_hold = hold[sweep]  # (nb, n)

    def moments_of(first: jax.Array) -> jax.Array:  # (_GROUP, Z + 1, Z + 1) of _GROUP blocks
        def part(x: jax.Array, axis: int = 0) -> jax.Array:
            return jax.lax.dynamic_slice_in_dim(x, first, size, axis)

        qg, wg, cg, jg, hg = (
            [part(qi) for qi in q],
            part(w),
            part(current),
            part(joint),
            part(at_hold),
        )
        theta = sum(qi * (jg == i)[:, None] for i, qi in enumerate(qg))  # the swept angle
        trig = _in_memory(jnp.stack([jnp.sin(theta), jnp.cos(theta)]))
        # u w = [1, dh] w, dh = q - hold and 0 for the swept joint; z = [sin u, cos u, u]
        uw = [wg] + [(qi - hg[:, i, None]) * ((jg != i)[:, None] * wg) for i, qi in enumerate(qg)]
        # the rows of ``features`` times w, built row by row (CPU memory); ``assemble`` forms
        # the moments from G, the sums of phi phi^T over the steady samples
        rows = [trig[0] * r for r in uw] + [trig[1] * r for r in uw] + uw + [cg * wg]
        phi = jnp.stack(rows, axis=1)  # (blocks, Z + 1, BLOCK): a matrix product per block
        return jnp.einsum("nab,ncb->nac", phi, phi)

    # a group of blocks at a time: the features of every sample never take memory at once
    nb = N // BLOCK
    size = _GROUP if nb % _GROUP == 0 else nb
    G = jax.lax.map(moments_of, jnp.arange(0, nb, size)).reshape(nb, 3 * n + 4, 3 * n + 4)
    G = jnp.einsum("np,nac->pac", of, G).reshape(S, 2, *G.shape[1:])  # (S, 2, Z + 1, Z + 1)
    moments = assemble(G, p.direction, v.reshape(S, 2), n)
    return SweepMoments(
        joint=p.joint,
        hold=hold,
        moments=moments,
        count=count,
        gravity=p.gravity,
        payload_mass=p.payload_mass,
        payload_com=p.payload_com,
    )


def reduce_batch(p: Packed, L: int, fraction: float, trim: float, sequential: bool) -> SweepMoments:
    """``reduce_packed`` over the leading axis of ``p``: vmapped, or one recording after
    another with ``sequential`` (on a CPU: the temporaries of one recording rather than of the
    batch, whose fresh memory cost as much system time as the reduction took)."""

    def one(x: Packed) -> SweepMoments:
        return reduce_packed(x, L, fraction, trim)

    return jax.lax.map(one, p) if sequential else jax.vmap(one)(p)


_packed_moments = jax.jit(reduce_batch, static_argnums=(1, 2, 3, 4))


def on_cpu() -> bool:
    """Whether jitted work without placed inputs runs on a CPU (the default device's)."""
    device = jax.config.jax_default_device
    platform = getattr(device, "platform", device) if device is not None else None
    return (platform or jax.default_backend()) == "cpu"


def packed_moments(
    packed: Packed, length: int, fraction: float = STEADY_FRACTION, trim: float = STEADY_TRIM
) -> SweepMoments:
    """Device ``SweepMoments`` of stacked ``pack``ed recordings (passes of at most ``length``
    samples; a leading axis on every field), on their bucketed sweeps: padding sweeps have
    zero count."""
    return _packed_moments(packed, length, fraction, trim, on_cpu())


# ------------------------------------------------------------ streaming (JAX, sample by sample)
#: Relative tolerance of a pass's cruise in the commanded speed (``stream_plan``).
CRUISE_TOLERANCE = 1e-6


class StreamPlan(NamedTuple):
    """What a plan tells ``stream_add`` about each recorded sample (R samples) and
    ``stream_moments`` about each of its S sweeps: host arrays shared by every world recording
    the plan (n joints).

    slot (R,) int: the sample's sweep (-1: none); passage (R,) int: 0 the first pass, 1 the
    return; joint (R,) int: the swept joint (0 outside sweeps); direction (R,) float, +1 / -1;
    speed (R,) rad/s: the commanded pass speed where the plan makes the sample steady, 0
    elsewhere; origin (R, n) rad: the commanded pose of the sample's sweep (its slot's).
    sweep_joint (S,) int, sweep_direction (S, 2) float (0: no such pass), sweep_origin (S, n)
    rad: per sweep.
    """

    slot: np.ndarray
    passage: np.ndarray
    joint: np.ndarray
    direction: np.ndarray
    speed: np.ndarray
    origin: np.ndarray
    sweep_joint: np.ndarray
    sweep_direction: np.ndarray
    sweep_origin: np.ndarray

    def rows(self) -> tuple[np.ndarray, ...]:
        """The per-sample fields (slot, passage, joint, direction, speed, origin)."""
        return self[:6]


def stream_plan(
    t: np.ndarray,
    q_cmd: np.ndarray,
    speed_cmd: np.ndarray,
    joint: np.ndarray,
    direction: np.ndarray,
    trim: float = STEADY_TRIM,
    settle: float = STEADY_SETTLE,
) -> StreamPlan:
    """The ``StreamPlan`` of R recorded samples at ``t`` (R,) s labelled ``joint`` and
    ``direction`` (R,) (as a ``Recording``), whose commanded pose is ``q_cmd`` (R, n) rad and
    the swept joint's commanded velocity ``speed_cmd`` (R,) rad/s.

    The steady samples of a pass, decided from the plan alone so that moments can be summed
    while the samples arrive: those at the pass's cruise (its largest commanded speed, within
    ``CRUISE_TOLERANCE``) more than ``settle_time`` s after its first such sample and ``trim``
    s before its last.
    ``stream_add`` also drops those whose measured speed is off the cruise by more than
    (1 - ``fraction``) of it (ripple, stick-slip), as ``identify.bins.steady``.
    """
    t, q_cmd, speed_cmd = (np.asarray(a, float) for a in (t, q_cmd, speed_cmd))
    lay = layout(joint, direction)
    R, n = q_cmd.shape
    slot = np.full(R, -1, np.int64)
    passage = np.zeros(R, np.int64)
    speed = np.zeros(R)
    sweep_origin = np.zeros((lay.joint.size, n))
    for s in range(lay.joint.size):
        first_steady = lay.first[s, 0]
        for k in (1, 0):
            f, m = int(lay.first[s, k]), int(lay.length[s, k])
            if m == 0:
                continue
            part = slice(f, f + m)
            slot[part], passage[part] = s, k
            v = speed_cmd[part] * lay.direction[s, k]
            cruise = v.max()
            at = v >= cruise * (1.0 - CRUISE_TOLERANCE)
            if cruise <= 0:
                continue
            tt = t[part]
            on = np.flatnonzero(at)
            start = settle_time(tt[on[-1]] - tt[on[0]], settle, trim)
            steady = at & (tt > tt[on[0]] + start) & (tt < tt[on[-1]] - trim)
            speed[part] = np.where(steady, cruise, 0.0)
            if steady.any():
                first_steady = f + int(np.argmax(steady))
        sweep_origin[s] = q_cmd[first_steady]
    used = slot >= 0
    origin = np.where(used[:, None], sweep_origin[np.maximum(slot, 0)], 0.0)
    return StreamPlan(
        slot,
        passage,
        np.where(used, joint, 0).astype(np.int64),
        np.where(used, direction, 0).astype(float),
        speed,
        origin,
        lay.joint,
        lay.direction.astype(float),
        sweep_origin,
    )


class StreamSums(NamedTuple):
    """Running sums over a recording's steady samples, per sweep (S) and pass (2): what
    ``stream_add`` adds to sample by sample and ``stream_moments`` turns into moments. n joints,
    P = 3 (n + 1) + 1. outer (S, 2, P, P): sum of phi phi^T, phi = ``features`` with dh the
    pose less the sweep's origin (swept joint: 0); offset (S, 2, n) rad: sum of the pose less
    the origin; speed
    (S, 2) rad/s: sum of the swept joint's speed along the pass; count (S, 2)."""

    outer: jax.Array
    offset: jax.Array
    speed: jax.Array
    count: jax.Array


def stream_init(sweeps: int, n: int) -> StreamSums:
    """Zero ``StreamSums`` of ``sweeps`` sweeps of n joints (host arrays, float64)."""
    P = moment_size(n) - 2
    return StreamSums(
        np.zeros((sweeps, 2, P, P)),
        np.zeros((sweeps, 2, n)),
        np.zeros((sweeps, 2)),
        np.zeros((sweeps, 2)),
    )


def stream_add(
    sums: StreamSums,
    row: tuple,
    q: jax.Array,
    dq: jax.Array,
    current: jax.Array,
    valid: jax.Array,
    fraction: float = STEADY_FRACTION,
    current_lag: float = 0.0,
) -> StreamSums:
    """``sums`` with one sample of one world added (pure, jit- and vmap-able): ``row`` the
    sample's ``StreamPlan.rows()`` entries, q (n,) rad, dq (n,) rad/s, current (n,) A;
    ``valid`` False adds nothing. ``current_lag`` s: the current flowed at q - lag dq."""
    slot, passage, joint, direction, cruise, origin = row
    n = q.shape[-1]
    pose = q - current_lag * dq
    swept = jax.nn.one_hot(joint, n, dtype=q.dtype)
    speed = dq[joint] * direction
    steady = (
        valid & (slot >= 0) & (cruise > 0) & (jnp.abs(speed - cruise) <= (1.0 - fraction) * cruise)
    )
    w = steady.astype(q.dtype)
    offset = pose - origin
    phi = features(pose[joint], offset * (1.0 - swept), current[joint]) * w
    at = (jnp.maximum(slot, 0), passage)
    return StreamSums(
        sums.outer.at[at].add(jnp.outer(phi, phi)),
        sums.offset.at[at].add(w * offset),
        sums.speed.at[at].add(w * speed),
        sums.count.at[at].add(w),
    )


def stream_moments(sums: StreamSums, plan: StreamPlan) -> tuple[jax.Array, ...]:
    """(hold (S, n) rad, moments (S, D, D), count (S,)) of one world's ``sums`` (pure): the
    sums about each sweep's origin moved to its held pose (the mean over its steady samples),
    exactly: u = [1, dh - m] is a linear map of [1, dh]."""
    n = sums.offset.shape[-1]
    count = sums.count.sum(axis=1)
    mean = sums.offset.sum(axis=1) / jnp.maximum(count, 1)[:, None]  # (S, n)
    swept = jax.nn.one_hot(jnp.asarray(plan.sweep_joint), n, dtype=mean.dtype)
    m = mean * (1.0 - swept)
    M = jnp.broadcast_to(jnp.eye(n + 1), (m.shape[0], n + 1, n + 1)).at[:, 1:, 0].set(-m)
    one = jnp.ones((1, 1))
    T = jax.vmap(lambda a: jax.scipy.linalg.block_diag(a, a, a, one))(M)
    G = jnp.einsum("sab,skbc,sdc->skad", T, sums.outer, T)
    d = jnp.asarray(plan.sweep_direction)
    v = d * sums.speed / jnp.maximum(sums.count, 1)
    hold = jnp.where(count[:, None] > 0, jnp.asarray(plan.sweep_origin) + mean, 0.0)
    return hold, assemble(G, d, v, n), count


@jax.jit
def _stream_moments_batch(sums: StreamSums, plan: StreamPlan) -> tuple[jax.Array, ...]:
    return jax.vmap(stream_moments, (0, None))(sums, plan)


def streamed_moments(
    sums: StreamSums, plan: StreamPlan, gravity: Sequence[float] = STANDARD_GRAVITY
) -> SweepMoments:
    """The ``SweepMoments`` (host arrays, a leading world axis as ``sweep_moments_batch``'s) of
    W worlds' ``sums`` (a leading axis W) of the plan ``plan`` (its S sweeps)."""
    S = plan.sweep_joint.size
    sums = StreamSums(*(a[:, :S] for a in sums))
    hold, moments, count = (np.asarray(a) for a in _stream_moments_batch(sums, plan))
    w = hold.shape[0]
    return SweepMoments(
        joint=np.broadcast_to(plan.sweep_joint, (w, S)).astype(np.int64),
        hold=hold,
        moments=moments,
        count=np.rint(count).astype(np.int64),
        gravity=np.broadcast_to(np.asarray(gravity, float), (w, 3)).copy(),
        payload_mass=np.zeros(w),
        payload_com=np.zeros((w, 3)),
    )
