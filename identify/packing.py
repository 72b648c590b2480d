"""Packing: the sweep samples of recordings laid out for the JAX reduction (host, pure data
movement).

``pack`` copies t, the swept joint's dq and current and every joint's q of every pass back to
back, each pass from the start of a block of ``BLOCK`` samples, so that the reduction
(``identify.sweep_reduction``) sums block by block: no gathers of samples, and passes padded
only to whole blocks. ``Layout`` says where the passes lie in a recording, from its labels
alone; the sizes of the packed form are rounded up to buckets (few compiled shapes).
``pack_worlds`` packs worlds that share one time base and labels (one plan simulated in many
worlds). Units: s, rad, rad/s, A.
"""

from __future__ import annotations

import mmap
import threading
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.recording import Recording

#: Rows of ``Packed.samples`` before the joints' angles: t, the swept joint's dq and current.
HEAD_ROWS = 3
#: Samples per block: every pass starts a block (the reduction sums block by block).
BLOCK = 512
_PASS_BUCKET = 1024  # samples: pass lengths round up to this (few compiled shapes)
_SAMPLE_BUCKET = 1 << 15
_SWEEP_BUCKET = 8


def _up(n: int, bucket: int) -> int:
    return max(bucket, -(-n // bucket) * bucket)


class Packed(NamedTuple):
    """The sweep samples of recordings, what ``sweep_reduction.reduce_packed`` reduces (host
    or device arrays; ``pack`` and ``sweep_reduction.packed_moments`` stack recordings along
    a leading axis, the shapes below are one recording's).

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
    """Where the passes of a recording lie: each contiguous run of one swept joint holds
    passes of alternating direction, two to a sweep.

    Args:
        joint: (N,) int, each sample's swept joint (-1: none), as ``Recording.joint``.
        direction: (N,) int, each sample's pass direction, +1 / -1.

    Returns:
        The ``Layout`` of the S sweeps.
    """
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
        """A view of the buffer, with arbitrary finite contents (of the array from before
        when it is large enough).

        Args:
            k: recordings; rows: rows per recording (``HEAD_ROWS`` + n); N: samples.
            touch: map fresh memory now (another thread may, ahead of the pack).

        Returns:
            (k, rows, N) float64.
        """
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
    """The pose at which each sample's current flowed.

    Args:
        q: (..., n) rad; dq: (..., n) rad/s.
        lag: s, a recording's ``current_lag``.

    Returns:
        (..., n) rad: ``q - lag dq``; ``q`` itself when ``lag`` is 0.
    """
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
            samples[..., HEAD_ROWS:, at : at + m] = np.swapaxes(q[..., part, :], -1, -2)
            at += k


def pack(recs: Sequence[Recording], buffer: PackBuffer | None = None) -> tuple[Packed, int]:
    """The sweep samples of recordings, stacked. Pure data movement.

    Args:
        recs: the recordings (n joints each).
        buffer: reuse its array for the samples (the result then aliases it: send it to the
            device before the next ``pack`` into the same buffer).

    Returns:
        The ``Packed`` recordings (a leading axis on every field; host arrays, padded to the
        largest) and L, the pass length (samples) to reduce them with.

    Raises:
        InputError: a recording has no sweep.
    """
    lays = [layout(r.joint, r.direction) for r in recs]
    for i, lay in enumerate(lays):
        if lay.joint.size == 0:
            raise InputError(f"recording {i} has no sweep (field 'joint' is -1 everywhere)")
    n = recs[0].q.shape[1]
    S, N, L = (max(dims) for dims in zip(*(lay.sizes() for lay in lays), strict=True))
    samples = (buffer or PackBuffer()).take(len(recs), HEAD_ROWS + n, N)
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


def pack_worlds(
    lay: Layout,
    t: np.ndarray,
    q: np.ndarray,
    dq: np.ndarray,
    current: np.ndarray,
    gravity: np.ndarray,
    current_lag: float = 0.0,
) -> tuple[Packed, int]:
    """The sweep samples of W worlds that share their time base and labels, stacked.

    Args:
        lay: the labels' ``Layout`` (common to every world).
        t: (T,) s, the common time base.
        q: (W, T, n) rad; dq: (W, T, n) rad/s; current: (W, T, n) A, each world's.
        gravity: (3,) m/s^2, base frame, every world's.
        current_lag: s, as a recording's.

    Returns:
        The ``Packed`` worlds (a leading axis W on every field; no payload) and L, the pass
        length (samples) to reduce them with.
    """
    w, _, n = q.shape
    S_pad, N, L = lay.sizes()
    samples = np.zeros((w, HEAD_ROWS + n, N))
    _fill(lay, t, current_pose(q, dq, current_lag), dq, current, samples)
    meta = {k: np.broadcast_to(v, (w, *v.shape[1:])) for k, v in _meta([lay], S_pad).items()}
    packed = Packed(
        samples=samples,
        **meta,
        gravity=np.broadcast_to(gravity, (w, 3)),
        payload_mass=np.zeros(w),
        payload_com=np.zeros((w, 3)),
    )
    return packed, L
