"""Sweep reduction: recordings' samples reduced to ``SweepMoments`` with JAX.

The samples are packed on the host (``identify.packing``: every pass from the start of a block
of ``BLOCK`` samples); the reduction (jitted, on the default backend: a GPU reduces thousands
of recordings at once) finds the steady samples (``identify.steady``'s rule, as
``identify.bins.steady`` applies it), their mean pose and the moments, block by block: no
gathers of samples, and passes padded only to whole blocks. The median speed of a pass takes
every ``MEDIAN_STRIDE``-th sample.

``sweep_moments`` reduces one recording, ``sweep_moments_batch`` worlds that share their time
base and labels, ``packed_moments`` a stack of packed recordings. Units: s, rad, rad/s, A.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.errors import InputError
from jaxcomp.identify.moments import SweepMoments, assemble
from jaxcomp.identify.packing import BLOCK, HEAD_ROWS, Packed, layout, pack, pack_worlds
from jaxcomp.identify.steady import MEDIAN_STRIDE, STEADY_FRACTION, STEADY_TRIM, at_speed, in_window
from jaxcomp.recording import Recording

_GROUP = 64  # blocks whose moments are formed at once


def sweep_moments(rec: Recording, fraction: float = STEADY_FRACTION) -> SweepMoments:
    """The moments of a recording's steady samples (see ``identify.bins.steady``), reduced on
    the default JAX backend.

    Args:
        rec: the recording (n joints).
        fraction: the steady fraction of the pass speed.

    Returns:
        Its ``SweepMoments``; sweeps without steady samples are left out.

    Raises:
        InputError: the recording has no sweep, or no steady sweep sample.
    """
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
    """``sweep_moments`` of W recordings that share their time base and sweep labels (one
    plan recorded in W simulated worlds).

    Args:
        t: (T,) s, the common time base.
        q: (W, T, n) rad; dq: (W, T, n) rad/s; current: (W, T, n) A, each world's.
        joint: (T,) int and direction: (T,) int, the common labels (as a ``Recording``'s).
        gravity: (3,) m/s^2, base frame.
        fraction: the steady fraction of the pass speed; trim: s (``identify.bins.steady``).
        current_lag: s, as a recording's.

    Returns:
        ``SweepMoments`` with a leading world axis on every field: joint (W, S), hold
        (W, S, n), moments (W, S, D, D), count (W, S), gravity (W, 3), payload_mass (W,),
        payload_com (W, 3), one entry per sweep of the labels; a sweep without steady samples
        in a world has zero moments, hold and count there (it adds nothing to a fit).
        ``world_moments(batch, w)`` is world w's ``sweep_moments``, to rounding (sums in
        another order).

    Raises:
        InputError: the shapes disagree.
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
    g = np.asarray(gravity, float)
    packed, L = pack_worlds(lay, t, q, dq, current, g, current_lag)
    m = jax.tree.map(np.asarray, packed_moments(packed, L, fraction, trim))
    return SweepMoments(
        joint=np.broadcast_to(lay.joint, (w, S)).astype(np.int64),
        hold=m.hold[:, :S],
        moments=m.moments[:, :S],
        count=m.count[:, :S].astype(np.int64),
        gravity=np.broadcast_to(g, (w, 3)).copy(),
        payload_mass=np.zeros(w),
        payload_com=np.zeros((w, 3)),
    )


def packed_moments(
    packed: Packed, length: int, fraction: float = STEADY_FRACTION, trim: float = STEADY_TRIM
) -> SweepMoments:
    """The moments of stacked ``pack``ed recordings, jitted on the default backend.

    Args:
        packed: recordings stacked along a leading axis (``packing.pack``).
        length: samples, the longest pass (``pack``'s L).
        fraction: the steady fraction of the pass speed; trim: s (``identify.bins.steady``).

    Returns:
        Device ``SweepMoments`` (a leading axis on every field) on the bucketed sweeps:
        padding sweeps have zero count.
    """
    return _packed_moments(packed, length, fraction, trim, on_cpu())


def on_cpu() -> bool:
    """Whether jitted work without placed inputs runs on a CPU.

    Returns:
        True when the default device (or, unset, the default backend) is a CPU.
    """
    device = jax.config.jax_default_device
    platform = getattr(device, "platform", device) if device is not None else None
    return (platform or jax.default_backend()) == "cpu"


def reduce_batch(p: Packed, L: int, fraction: float, trim: float, sequential: bool) -> SweepMoments:
    """``reduce_packed`` over the leading axis of stacked packed recordings (pure).

    Args:
        p: packed recordings, a leading axis on every field.
        L: as ``reduce_packed``'s.
        fraction: as ``reduce_packed``'s.
        trim: as ``reduce_packed``'s.
        sequential: one recording after another rather than vmapped (on a CPU: the
            temporaries of one recording rather than of the batch, whose fresh memory cost as
            much system time as the reduction took).

    Returns:
        ``SweepMoments`` with the leading axis of ``p``.
    """

    def one(x: Packed) -> SweepMoments:
        return reduce_packed(x, L, fraction, trim)

    return jax.lax.map(one, p) if sequential else jax.vmap(one)(p)


_packed_moments = jax.jit(reduce_batch, static_argnums=(1, 2, 3, 4))


def reduce_packed(p: Packed, L: int, fraction: float, trim: float) -> SweepMoments:
    """The sweep moments of one packed recording (pure, vmap-able; ``packed_moments`` runs it
    on a stack).

    Block by block (``BLOCK`` samples, each of one pass or none): per-pass sums are sums over
    blocks, and the moments are one small matrix product per block.

    Args:
        p: one packed recording (n joints, S sweeps).
        L: samples, at least its longest pass.
        fraction: the steady fraction of the pass speed; trim: s (``identify.bins.steady``,
            whose ``settle`` is ``identify.steady.STEADY_SETTLE`` here).

    Returns:
        Its ``SweepMoments`` (S sweeps, zero count where a sweep has no steady sample).
    """
    n = p.samples.shape[0] - HEAD_ROWS
    S = p.joint.shape[0]
    b = _blocks(p)
    speed, steady = _steady_samples(p, b, L, fraction, trim)
    w = steady.astype(b.t.dtype)
    v = b.sign * b.mean(speed, steady)  # (2 S,) rad/s
    count, hold = _held_poses(b, steady, w, S)
    G = _pass_sums(p, b, w, hold)  # (S, 2, Z + 1, Z + 1)
    return SweepMoments(
        joint=p.joint,
        hold=hold,
        moments=assemble(G, p.direction, v.reshape(S, 2), n),
        count=count,
        gravity=p.gravity,
        payload_mass=p.payload_mass,
        payload_com=p.payload_com,
    )


class _Blocks(NamedTuple):
    """One packed recording block by block (nb blocks of ``BLOCK`` samples, 2 S passes)."""

    t: jax.Array  # (nb, BLOCK) s
    rate: jax.Array  # (nb, BLOCK) rad/s, the swept joint's dq
    current: jax.Array  # (nb, BLOCK) A, the swept joint's
    q: list[jax.Array]  # n of (nb, BLOCK) rad, row by row (a slice of them all would be copied)
    first: jax.Array  # (2 S,) int, where each pass starts
    length: jax.Array  # (2 S,) int, its samples
    sign: jax.Array  # (2 S,) its direction
    member: jax.Array  # (nb, 2 S) bool: the block's pass
    of: jax.Array  # (nb, 2 S) float, ``member``
    k: jax.Array  # (nb,) int, the block's pass (any one for a block of none)
    valid: jax.Array  # (nb, BLOCK) bool: a sample of the block's pass

    def total(self, x: jax.Array, keep: jax.Array) -> jax.Array:
        """(2 S,) sums of ``x`` (nb, BLOCK) over each pass's samples where ``keep``."""
        return jnp.sum(jnp.where(keep, x, 0.0), axis=1) @ self.of

    def mean(self, x: jax.Array, keep: jax.Array) -> jax.Array:
        """(2 S,) means of ``x`` over each pass's samples where ``keep``; 0 where none is."""
        return self.total(x, keep) / jnp.maximum(self.total(1.0, keep), 1.0)


def _blocks(p: Packed) -> _Blocks:
    """The samples of ``p`` block by block, and each block's pass."""
    rows, N = p.samples.shape
    x = p.samples.reshape(rows, N // BLOCK, BLOCK)
    first, length, sign = (a.reshape(-1) for a in (p.start, p.length, p.direction))  # (2 S,)
    at = jnp.arange(N // BLOCK) * BLOCK
    member = (at[:, None] >= first) & (at[:, None] < first + length)  # (nb, 2 S): its pass
    k = jnp.argmax(member, axis=1)
    valid = jnp.any(member, axis=1)[:, None] & (
        (at - first[k])[:, None] + jnp.arange(BLOCK) < length[k][:, None]
    )
    return _Blocks(
        t=x[0],
        rate=x[1],
        current=x[2],
        q=[x[HEAD_ROWS + i] for i in range(rows - HEAD_ROWS)],
        first=first,
        length=length,
        sign=sign,
        member=member,
        of=member.astype(x.dtype),
        k=k,
        valid=valid,
    )


def _steady_samples(
    p: Packed, b: _Blocks, L: int, fraction: float, trim: float
) -> tuple[jax.Array, jax.Array]:
    """(speed along the pass (nb, BLOCK) rad/s, steady (nb, BLOCK) bool): ``identify.steady``'s
    rule on each pass."""
    N = p.samples.shape[1]
    k = b.k
    speed = b.rate * b.sign[k][:, None]  # along the pass's direction
    # the pass speed: the mean over the samples at >= ``fraction`` of the median speed of every
    # MEDIAN_STRIDE-th sample (the median alone may fall on a ramp when a pass has few samples)
    sub = jnp.arange(0, L, MEDIAN_STRIDE)
    strided = p.samples[1][jnp.minimum(b.first[:, None] + sub, N - 1)] * b.sign[:, None]
    median = _median(strided, sub < b.length[:, None])[k][:, None]  # (nb, 1)
    ref = b.mean(speed, b.valid & (speed >= fraction * median) & (median > 0))[k][:, None]
    fast = b.valid & at_speed(speed, ref, fraction) & (ref > 0)
    lo = jnp.min(jnp.where(fast, b.t, jnp.inf), axis=1)[:, None]  # (nb, 1), then over the pass
    hi = jnp.max(jnp.where(fast, b.t, -jnp.inf), axis=1)[:, None]
    lo = jnp.min(jnp.where(b.member, lo, jnp.inf), axis=0)[k][:, None]
    hi = jnp.max(jnp.where(b.member, hi, -jnp.inf), axis=0)[k][:, None]
    return speed, fast & in_window(b.t, lo, hi, trim=trim, xp=jnp)  # settle: the default


def _held_poses(b: _Blocks, steady: jax.Array, w: jax.Array, S: int) -> tuple[jax.Array, jax.Array]:
    """(count (S,) int, hold (S, n) rad): each sweep's steady samples (``steady`` (nb, BLOCK)
    bool; ``w`` 1 there, else 0) and their mean pose."""
    n = len(b.q)
    count = jnp.round(b.total(1.0, steady)).astype(int).reshape(S, 2).sum(axis=1)
    held = (jnp.stack([jnp.sum(qi * w, axis=1) for qi in b.q]) @ b.of).reshape(n, S, 2)
    return count, held.sum(axis=2).T / jnp.maximum(count, 1)[:, None]


def _pass_sums(p: Packed, b: _Blocks, w: jax.Array, hold: jax.Array) -> jax.Array:
    """(S, 2, Z + 1, Z + 1): each pass's sum of phi phi^T (``moments.features``) over its
    steady samples (``w`` (nb, BLOCK) 1 there), about the held poses ``hold`` (S, n) rad."""
    n, S = len(b.q), p.joint.shape[0]
    sweep = b.k // 2
    joint = p.joint[sweep]  # (nb,) the block's swept joint
    at_hold = hold[sweep]  # (nb, n)

    def moments_of(first: jax.Array) -> jax.Array:  # (_GROUP, Z + 1, Z + 1) of _GROUP blocks
        def part(x: jax.Array, axis: int = 0) -> jax.Array:
            return jax.lax.dynamic_slice_in_dim(x, first, size, axis)

        qg, wg, cg, jg, hg = (
            [part(qi) for qi in b.q],
            part(w),
            part(b.current),
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
    nb = b.t.shape[0]
    size = _GROUP if nb % _GROUP == 0 else nb
    G = jax.lax.map(moments_of, jnp.arange(0, nb, size)).reshape(nb, 3 * n + 4, 3 * n + 4)
    return jnp.einsum("np,nac->pac", b.of, G).reshape(S, 2, *G.shape[1:])


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
