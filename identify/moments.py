"""Sweep moments: a recording reduced to a 6 x 6 matrix per sweep, exact for the joint fit.

While joint j sweeps with the other joints held, its gravity torque is exactly
a sin(theta) + b cos(theta) + c in the swept angle theta (the carried subtree turns rigidly
about the joint axis), and so is each column of its regressor. With
psi = [sin theta, cos theta, 1, d, v, current] per steady sample (d the direction, v the pass
velocity in rad/s: d times the median speed of the pass's steady samples, not the measured
velocity, whose servo ripple correlates with the current; current the swept joint's in A), the
sums ``sum psi psi^T`` over a sweep hold everything a least-squares fit of Eq. (13) (plus a
viscous term in v) on that sweep needs: the fit never touches the samples again.

Two steps: ``pack`` (host, pure data movement) copies the swept joint's t, q, dq and current
of every pass back to back, and q at every ``HOLD_STRIDE``-th sample for the held pose; the
reduction (JAX, jitted, on the default backend: a GPU reduces thousands of recordings at once)
finds the steady samples (``identify.bins.steady``'s rule) and sums the moments. Medians over a
pass (its speed, for the steady threshold and v) take every ``HOLD_STRIDE``-th sample.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.errors import InputError
from jaxcomp.identify.bins import MEDIAN_STRIDE, STEADY_FRACTION, STEADY_TRIM
from jaxcomp.recording import Recording


class SweepMoments(NamedTuple):
    """Moments of the steady samples of each sweep of a recording (S sweeps, n joints).

    joint (S,) int: the swept joint. hold (S, n) rad: the held pose of the sweep, the mean of
    q over every ``HOLD_STRIDE``-th steady sample (the swept joint's entry is irrelevant).
    moments (S, 6, 6): sum of psi psi^T (see the module docstring). count (S,): steady
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
) -> SweepMoments:
    """``sweep_moments`` of W recordings that share their time base and sweep labels.

    ``t`` (T,) s, ``joint`` (T,) and ``direction`` (T,) are common to every world (one plan
    recorded in W simulated worlds); ``q`` (W, T, n) rad, ``dq`` (W, T, n) rad/s and
    ``current`` (W, T, n) A are each world's. Returns a ``SweepMoments`` whose every field has
    a leading world axis: joint (W, S), hold (W, S, n), moments (W, S, 6, 6), count (W, S),
    gravity (W, 3), payload_mass (W,), payload_com (W, 3), with one entry per sweep of the
    labels; a sweep without steady samples in a world has zero moments, hold and count there
    (it adds nothing to a fit). ``world_moments(batch, w)`` is world w's ``sweep_moments``, to
    rounding (sums in another order).
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
    S_pad, N, H, L = lay.sizes()
    samples, hold = np.zeros((w, 4, N)), np.zeros((w, H, n))
    _fill(lay, t, q, dq, current, samples, hold)
    meta = {k: np.broadcast_to(v, (w, *v.shape[1:])) for k, v in _meta([lay], S_pad).items()}
    packed = Packed(
        samples=samples,
        hold=hold,
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


def stack_worlds(parts: Sequence[SweepMoments]) -> SweepMoments:
    """Batches of moments of the same sweeps in other worlds, joined along the world axis."""
    if not parts:
        raise InputError("no moments to join")
    return SweepMoments(*(np.concatenate([getattr(p, f) for p in parts]) for f in parts[0]._fields))


# ------------------------------------------------------------------------ packing (host)
#: The held pose of a sweep is the mean of q over every HOLD_STRIDE-th steady sample (counted
#: from the start of each pass), as the pass medians take every such sample.
HOLD_STRIDE = MEDIAN_STRIDE
_PASS_BUCKET = 1024  # samples: pass lengths round up to this (few compiled shapes)
_SAMPLE_BUCKET = 1 << 15
_SWEEP_BUCKET = 8


def _up(n: int, bucket: int) -> int:
    return max(bucket, -(-n // bucket) * bucket)


class Packed(NamedTuple):
    """The swept-joint samples of recordings, what ``reduce_packed`` reduces (host or device
    arrays; ``pack`` and ``packed_moments`` stack recordings along a leading axis, the shapes
    below are one recording's).

    S sweeps of up to two passes (slot 0 the first, slot 1 the return). samples (4, N): t s,
    the swept joint's q rad, dq rad/s and current A, the passes back to back, zero-padded.
    hold (H, n) rad: q of every HOLD_STRIDE-th sample of each pass, back to back. start,
    length, hold_start (S, 2) int: where each pass begins in samples and in hold, and its
    sample count (0: no such pass). direction (S, 2) float, +1 / -1 (0: no pass). joint (S,)
    int, the swept joint. gravity (3,) m/s^2, payload_mass kg, payload_com (3,) m.
    """

    samples: np.ndarray
    hold: np.ndarray
    start: np.ndarray
    length: np.ndarray
    hold_start: np.ndarray
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

    @property
    def held(self) -> np.ndarray:
        """(S, 2) hold rows of each pass: its every HOLD_STRIDE-th sample."""
        return -(-self.length // HOLD_STRIDE)

    def sizes(self) -> tuple[int, int, int, int]:
        """Bucketed (S sweeps, N samples, H hold rows, L pass length) of the packed form."""
        return (
            _up(self.joint.size, _SWEEP_BUCKET),
            _up(int(self.length.sum()), _SAMPLE_BUCKET),
            _up(int(self.held.sum()), _SAMPLE_BUCKET // HOLD_STRIDE),
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


class PackBuffer:
    """Host buffers that ``pack`` reuses from call to call (one per thread): writing into
    memory already mapped is several times faster than into fresh pages."""

    def __init__(self) -> None:
        self._samples = np.zeros((0, 4, 0))
        self._hold = np.zeros((0, 0, 0))

    def take(self, k: int, N: int, H: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Views (k, 4, N) and (k, H, n) with arbitrary finite contents (of the arrays from
        before when they are large enough)."""
        if any(a < b for a, b in zip(self._samples.shape, (k, 4, N), strict=True)):
            self._samples = np.zeros((k, 4, N))
        if any(a < b for a, b in zip(self._hold.shape, (k, H, n), strict=True)):
            self._hold = np.zeros((k, H, n))
        return self._samples[:k, :, :N], self._hold[:k, :H, :n]


def _meta(lays: Sequence[Layout], S: int) -> dict[str, np.ndarray]:
    """Per-pass fields of ``Packed`` for the layouts, stacked and padded to S sweeps."""
    k = len(lays)
    out = {f: np.zeros((k, S, 2), np.int64) for f in ("start", "length", "hold_start")}
    out["direction"] = np.zeros((k, S, 2))
    out["joint"] = np.zeros((k, S), np.int64)
    for i, lay in enumerate(lays):
        m = lay.joint.size
        ends = np.cumsum(lay.length.ravel()).reshape(-1, 2)
        held = np.cumsum(lay.held.ravel()).reshape(-1, 2)
        out["start"][i, :m] = ends - lay.length
        out["hold_start"][i, :m] = held - lay.held
        out["length"][i, :m] = lay.length
        out["direction"][i, :m] = lay.direction
        out["joint"][i, :m] = lay.joint
    return out


def _fill(lay: Layout, t, q, dq, current, samples: np.ndarray, hold: np.ndarray) -> None:
    """Copy the passes of ``lay`` into ``samples`` (..., 4, N) and ``hold`` (..., H, n), in
    packed order; ``q``, ``dq``, ``current`` (..., T, n) and ``t`` (T,) of one recording or of
    worlds that share the layout (a leading axis). Strided slice copies, no index arrays."""
    at = held = 0
    for j, first, length in zip(lay.joint.tolist(), lay.first, lay.length, strict=True):
        for f, m in zip(first.tolist(), length.tolist(), strict=True):
            part = slice(f, f + m)
            samples[..., 0, at : at + m] = t[part]
            samples[..., 1, at : at + m] = q[..., part, j]
            samples[..., 2, at : at + m] = dq[..., part, j]
            samples[..., 3, at : at + m] = current[..., part, j]
            h = -(-m // HOLD_STRIDE)
            hold[..., held : held + h, :] = q[..., f : f + m : HOLD_STRIDE, :]
            at, held = at + m, held + h


def pack(recs: Sequence[Recording], buffer: PackBuffer | None = None) -> tuple[Packed, int]:
    """The swept-joint samples of recordings, stacked (a leading axis on every field of the
    ``Packed``; host arrays, padded to the largest), and the pass length (samples) to reduce
    them with. Pure data movement: a strided copy of four columns and a subsample of q.

    ``buffer``: reuse its arrays for samples and hold (the result then aliases them: send it
    to the device before the next ``pack`` into the same buffer)."""
    lays = [layout(r.joint, r.direction) for r in recs]
    for i, lay in enumerate(lays):
        if lay.joint.size == 0:
            raise InputError(f"recording {i} has no sweep (field 'joint' is -1 everywhere)")
    n = recs[0].q.shape[1]
    S, N, H, L = (max(dims) for dims in zip(*(lay.sizes() for lay in lays), strict=True))
    k = len(recs)
    samples, hold = (buffer or PackBuffer()).take(k, N, H, n)
    for i, (rec, lay) in enumerate(zip(recs, lays, strict=True)):
        _fill(lay, rec.t, rec.q, rec.dq, rec.current, samples[i], hold[i])
    packed = Packed(
        samples=samples,
        hold=hold,
        **_meta(lays, S),
        gravity=np.stack([np.asarray(r.gravity, float) for r in recs]),
        payload_mass=np.array([float(r.payload_mass) for r in recs]),
        payload_com=np.stack([np.asarray(r.payload_com, float) for r in recs]),
    )
    return packed, L


# ----------------------------------------------------------------------- reduction (JAX)
def _median(x: jax.Array, keep: jax.Array, axis: int = -1) -> jax.Array:
    """Median of ``x`` over ``axis`` where ``keep``, exactly ``np.median`` of the kept values
    (the middle one, or the mean of the two); NaN where none is kept."""
    data = jnp.sort(jnp.where(keep, x, jnp.inf), axis=axis)
    c = jnp.sum(keep, axis=axis, keepdims=True)
    lo = jnp.take_along_axis(data, jnp.maximum((c - 1) // 2, 0), axis=axis)
    hi = jnp.take_along_axis(data, jnp.maximum(c // 2, 0), axis=axis)
    return jnp.squeeze(jnp.where(c > 0, 0.5 * (lo + hi), jnp.nan), axis)


def reduce_packed(p: Packed, L: int, fraction: float, trim: float) -> SweepMoments:
    """Sweep moments of one packed recording, its passes padded to ``L`` samples (pure,
    vmap-able; ``packed_moments`` runs it on a stack). ``fraction`` and ``trim``: see
    ``identify.bins.steady``."""
    off = jnp.arange(L)
    valid = off < p.length[..., None]  # (S, 2, L)
    idx = jnp.minimum(p.start[..., None] + off, p.samples.shape[-1] - 1)
    t, theta, rate, current = (p.samples[k][idx] for k in range(4))
    d = p.direction[..., None]
    speed = rate * d  # along the pass's direction
    sub = slice(None, None, HOLD_STRIDE)  # the medians are over every HOLD_STRIDE-th sample
    ref = _median(speed[..., sub], valid[..., sub])[..., None]  # (S, 2, 1) pass speed
    fast = valid & (speed >= fraction * ref) & (ref > 0)
    lo = jnp.min(jnp.where(fast, t, jnp.inf), axis=-1, keepdims=True)
    hi = jnp.max(jnp.where(fast, t, -jnp.inf), axis=-1, keepdims=True)
    steady = fast & (t > lo + trim) & (t < hi - trim)
    v = jnp.nan_to_num(d[..., 0] * _median(speed[..., sub], steady[..., sub]))[..., None]
    # psi = E [sin, cos, 1, current] with E constant over a pass (d and v are): the moments
    # are E G E^T with G the 4 x 4 moments of [sin, cos, 1, current] over the steady samples
    phi = jnp.stack([jnp.sin(theta), jnp.cos(theta), jnp.ones_like(theta), current], axis=-2)
    G = jnp.matmul(phi * steady[..., None, :], jnp.swapaxes(phi, -1, -2))  # (S, 2, 4, 4)
    E = jnp.zeros((*d.shape[:-1], 6, 4))
    E = E.at[..., 0, 0].set(1.0).at[..., 1, 1].set(1.0).at[..., 2, 2].set(1.0)
    E = E.at[..., 3, 2].set(d[..., 0]).at[..., 4, 2].set(v[..., 0]).at[..., 5, 3].set(1.0)
    moments = jnp.einsum("skai,skij,skbj->sab", E, G, E)
    hidx = jnp.minimum(p.hold_start[..., None] + jnp.arange(L // HOLD_STRIDE), p.hold.shape[0] - 1)
    S = p.joint.shape[0]
    held = p.hold[hidx].reshape(S, -1, p.hold.shape[-1])  # (S, 2 L / stride, n)
    keep = steady[..., sub].reshape(S, -1, 1).astype(held.dtype)
    hold = jnp.sum(held * keep, axis=1) / jnp.maximum(jnp.sum(keep, axis=1), 1.0)
    return SweepMoments(
        joint=p.joint,
        hold=hold,
        moments=moments,
        count=jnp.sum(steady, axis=(1, 2)),
        gravity=p.gravity,
        payload_mass=p.payload_mass,
        payload_com=p.payload_com,
    )


def reduce_batch(p: Packed, L: int, fraction: float, trim: float, sequential: bool) -> SweepMoments:
    """``reduce_packed`` over the leading axis of ``p``: vmapped, or one recording after
    another with ``sequential`` (twice as fast on a CPU, where batched gathers are slow)."""

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
    """Device ``SweepMoments`` of stacked ``pack``ed recordings (passes padded to ``length``
    samples; a leading axis on every field), on their bucketed sweeps: padding sweeps have
    zero count."""
    return _packed_moments(packed, length, fraction, trim, on_cpu())
