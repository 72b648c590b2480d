"""Transfers: the moves between sweeps, where every joint moves at once, as data for the joint fit.

Between sweeps the arm travels along straight joint-space lines (``CalibrationPlan.moves``).
At a transfer's cruise every joint moves at its own nearly constant velocity; the current of
joint k is the sweeps' model (``identify.fit_stats``) with the inertial, Coriolis and
centrifugal torques of the nominal model added:

    c_k = r_k (g_k(q) + [M(q) ddq + C(q, dq) dq]_k) + l_k sign(dq_k) + b_k dq_k

The acceleration ddq is what the recording says (``backward_acceleration``: over a run of
samples it telescopes to the run's end velocities, so velocity noise hardly enters): the
servos still ring after a cruise's start, and on a heavy arm's base joint M ddq is tens of mA.

A transfer loads the joints in poses and combinations no sweep visits (each sweep holds all but
one joint), and its samples are as many as the sweeps' on a random plan: the joint fit's error
roughly halves with them.

Which samples count, decided from the recording alone as ``identify.bins.steady`` does for a
sweep: a transfer leg is a run of samples labelled with no sweep (``joint`` -1) whose fastest
joint moves; a sample is at the leg's cruise when every joint's velocity is within
(1 - ``STEADY_FRACTION``) of the lead joint's cruise speed (the lead: the joint with the longest
way) of its own cruise velocity, more than ``STEADY_SETTLE`` s after the first such sample
(the servos ring after the ramp; a transfer's cruise is short, so this holds for every leg,
unlike a sweep's ``settle_time``) and ``STEADY_TRIM`` s before the last. Joint k counts in a
bin when it moves at >= ``MIN_SPEED`` in the leg's direction throughout the bin (slower, its
friction is not developed: stick-slip). The samples are averaged in bins of ``BIN_ANGLE`` of
the lead joint's travel; a fit evaluates its regressors at each bin's mean pose.

``TransferBins`` hold the bins of one recording (or, stacked, of many); ``transfer_bins`` makes
them from a ``Recording``, ``transfer_plan`` / ``transfer_add`` / ``transfer_finish`` from
samples streamed on the device, with the cruise decided from the plan's commanded motion (as
``streaming.stream_plan``). Units: rad, rad/s, A, s.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.identify.steady import CRUISE_TOLERANCE, STEADY_FRACTION, STEADY_SETTLE, STEADY_TRIM
from jaxcomp.recording import Recording

#: rad/s: a joint slower than this in a transfer bin is left out of it (5 deg/s).
MIN_SPEED = math.radians(5.0)
#: rad: transfer bins span this much of the lead joint's travel (1 deg).
BIN_ANGLE = math.radians(1.0)
#: Transfer bins are padded to a multiple of this (few compiled shapes).
BIN_BUCKET = 256
#: A leg's samples: those whose fastest joint moves at more than this fraction of the leg's
#: fastest (the stops at via poses and the settling split a transfer into legs).
_MOVING = 0.1


class TransferBins(NamedTuple):
    """B transfer bins of n joints (stacked: a leading axis W on every field).

    pose (B, n) rad: the bin's mean pose where the current flowed (q - current_lag dq);
    velocity (B, n) rad/s and acceleration (B, n) rad/s^2: its mean velocity and
    acceleration (every joint's, counted or not); current (B, n) A and square (B, n) A^2: sums of
    each joint's current and squared current over its counted samples; count (B, n): the
    samples each joint counts in the bin (0: it does not, a padded bin has none).
    """

    pose: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    current: np.ndarray
    square: np.ndarray
    count: np.ndarray

    @property
    def size(self) -> int:
        return int(np.shape(self.count)[-2])


def empty_bins(n: int, size: int = 0, stack: int | None = None) -> TransferBins:
    """Transfer bins that count nothing.

    Args:
        n: Joints.
        size: Bins, B.
        stack: That many such recordings, stacked (W); None: one, unstacked.

    Returns:
        Bins of zeros, each field (B, n) or (W, B, n).
    """
    shape = (size, n) if stack is None else (stack, size, n)
    return TransferBins(*(np.zeros(shape) for _ in TransferBins._fields))


def bucket(size: int) -> int:
    """A bin count rounded up to ``BIN_BUCKET`` (at least one bucket).

    Args:
        size: Bins.

    Returns:
        The padded bin count.
    """
    return max(1, -(-int(size) // BIN_BUCKET)) * BIN_BUCKET


def padded_bins(tb: TransferBins, size: int) -> TransferBins:
    """``tb`` with bins that count nothing appended.

    Args:
        tb: Bins, (..., B, n) each field.
        size: Bins wanted, >= B.

    Returns:
        Bins, (..., size, n) each field.
    """

    def pad(a):
        a = np.asarray(a, float)
        width = [(0, 0)] * a.ndim
        width[-2] = (0, size - a.shape[-2])
        return np.pad(a, width)

    return TransferBins(*(pad(a) for a in tb))


def stack_bins(parts: list[TransferBins]) -> TransferBins:
    """Stack the bins of several recordings, padded to the largest's bucket.

    Args:
        parts: One recording's bins each (W of them), fields (B_w, n).

    Returns:
        Bins, each field (W, B, n).
    """
    size = bucket(max((p.size for p in parts), default=0))
    padded = [padded_bins(p, size) for p in parts]
    return TransferBins(*(np.stack(a) for a in zip(*padded, strict=True)))


def _legs(moving: np.ndarray, dq: np.ndarray) -> list[np.ndarray]:
    """Index runs (into the recording) of the transfer legs: contiguous samples with no sweep
    whose fastest joint moves at more than ``_MOVING`` of the run's fastest."""
    idx = np.flatnonzero(moving)
    legs = []
    for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
        if run.size == 0:
            continue
        speed = np.abs(dq[run]).max(axis=1)
        on = speed > _MOVING * speed.max() if speed.max() > 0 else np.zeros(run.size, bool)
        edges = np.flatnonzero(np.diff(on.astype(np.int8))) + 1
        legs += [run[p] for p in np.split(np.arange(run.size), edges) if p.size and on[p[0]]]
    return legs


def _binned(
    lead_angle: np.ndarray,
    pose: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    current: np.ndarray,
    sign: np.ndarray,
    min_speed: float,
    width: float,
) -> TransferBins:
    """The bins of one leg's cruise samples: bins of ``width`` rad of the lead joint's travel
    ``lead_angle`` (from the first sample); ``sign`` (n,) each joint's direction in the leg."""
    k = np.floor(np.abs(lead_angle - lead_angle[0]) / width).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])  # the lead moves one way: contiguous
    per = np.diff(np.r_[starts, len(k)]).astype(float)

    def total(x: np.ndarray) -> np.ndarray:  # (m, n) -> (B, n)
        return np.add.reduceat(x, starts, axis=0)

    counts = (np.abs(dq) >= min_speed) & (np.sign(dq) == sign)  # (m, n)
    every = total(counts.astype(float)) == per[:, None]  # the joint counts throughout the bin
    use = every & (sign != 0)
    return TransferBins(
        total(pose) / per[:, None],
        total(dq) / per[:, None],
        total(ddq) / per[:, None],
        np.where(use, total(current), 0.0),
        np.where(use, total(current**2), 0.0),
        np.where(use, per[:, None], 0.0),
    )


def backward_acceleration(
    t: np.ndarray, dq: np.ndarray, at: np.ndarray | None = None
) -> np.ndarray:
    """Each sample's velocity minus the one before, over the time between them; 0 at the
    first sample.

    Args:
        t: Sample times, (R,) s.
        dq: Joint velocities, (R, n) rad/s.
        at: Only the samples of these indices, (m,); None: all.

    Returns:
        (m, n) rad/s^2 ((R, n) for all samples).
    """
    at = np.arange(len(t)) if at is None else np.asarray(at)
    ddq = np.zeros((at.size, np.shape(dq)[1]))
    later = at > 0
    i = at[later]
    ddq[later] = (dq[i] - dq[i - 1]) / (t[i] - t[i - 1])[:, None]
    return ddq


def transfer_bins(
    rec: Recording,
    fraction: float = STEADY_FRACTION,
    settle: float = STEADY_SETTLE,
    trim: float = STEADY_TRIM,
    min_speed: float = MIN_SPEED,
    width: float = BIN_ANGLE,
) -> TransferBins:
    """The transfer bins of ``rec`` (see the module docstring).

    Args:
        rec: The recording.
        fraction: ``STEADY_FRACTION``, the cruise's speed tolerance.
        settle: s left out at each leg's cruise start.
        trim: s left out at its end.
        min_speed: rad/s, the least speed of a joint counted in a bin.
        width: rad of the lead joint's travel per bin.

    Returns:
        Its bins, fields (B, n); none when it has no transfer samples (sweeps alone).
    """
    parts = []
    for leg in _legs(rec.joint < 0, rec.dq):
        dq = rec.dq[leg]
        mean = dq.mean(axis=0)
        lead = int(np.argmax(np.abs(mean)))
        speed = dq[:, lead] * np.sign(mean[lead])
        median = np.median(speed)
        if median <= 0:
            continue
        ref = speed[speed >= fraction * median].mean()
        fast = np.flatnonzero(np.abs(speed - ref) <= (1.0 - fraction) * ref)
        if fast.size == 0:
            continue
        cruise = dq[fast].mean(axis=0)  # every joint's cruise velocity
        fast = fast[np.all(np.abs(dq[fast] - cruise) <= (1.0 - fraction) * ref, axis=1)]
        if fast.size == 0:
            continue
        t = rec.t[leg[fast]]
        keep = leg[fast[(t > t[0] + settle) & (t < t[-1] - trim)]]
        if keep.size == 0:
            continue
        dq_keep = rec.dq[keep]
        pose = rec.q[keep] - rec.current_lag * dq_keep  # where the current flowed
        sign = np.sign(mean)
        parts.append(
            _binned(
                pose[:, lead],
                pose,
                dq_keep,
                backward_acceleration(rec.t, rec.dq, keep),
                rec.current[keep],
                sign,
                min_speed,
                width,
            )
        )
    if not parts:
        return empty_bins(rec.n_joints)
    return TransferBins(*(np.concatenate(a) for a in zip(*parts, strict=True)))


# ------------------------------------------------------------------------ streamed (device)
class TransferPlan(NamedTuple):
    """What a plan tells ``transfer_add`` about each of R recorded samples, and
    ``transfer_finish`` about each of B bins: host arrays shared by every world recording the
    plan (n joints).

    bin (R,) int: the sample's transfer bin (-1: none); velocity (R, n) rad/s: the commanded
    velocity there; cruise (R,) rad/s: the lead joint's commanded speed there (0 outside bins);
    rate (R,) 1/s: one over the time since the sample before (0 at the first); use (B, n)
    bool: the joints the plan moves at >= ``MIN_SPEED`` in the bin.
    """

    bin: np.ndarray
    velocity: np.ndarray
    cruise: np.ndarray
    rate: np.ndarray
    use: np.ndarray

    def rows(self) -> tuple[np.ndarray, ...]:
        """The per-sample fields (bin, velocity, cruise, rate)."""
        return self[:4]


def transfer_plan(
    t: np.ndarray,
    q_cmd: np.ndarray,
    dq_cmd: np.ndarray,
    joint: np.ndarray,
    settle: float = STEADY_SETTLE,
    trim: float = STEADY_TRIM,
    min_speed: float = MIN_SPEED,
    width: float = BIN_ANGLE,
) -> TransferPlan:
    """The ``TransferPlan`` of R recorded samples: a leg's cruise is a run of samples
    outside sweeps at one nonzero commanded velocity (within ``steady.CRUISE_TOLERANCE`` of
    its largest component), less ``settle`` at its start and ``trim`` at its end.

    Args:
        t: Sample times, (R,) s.
        q_cmd: Commanded poses, (R, n) rad.
        dq_cmd: Commanded velocities, (R, n) rad/s.
        joint: Each sample's sweep label as a ``Recording``'s, (R,) int (-1: no sweep).
        settle: s left out at each cruise's start.
        trim: s left out at its end.
        min_speed: rad/s, the least commanded speed of a joint used in a bin.
        width: rad of the lead joint's commanded travel per bin.

    Returns:
        The plan (host arrays).
    """
    t, q_cmd, dq_cmd = (np.asarray(a, float) for a in (t, q_cmd, dq_cmd))
    R, n = q_cmd.shape
    top = np.abs(dq_cmd).max(axis=1)
    same = np.zeros(R, bool)  # the sample moves at the velocity of the one before
    same[1:] = np.abs(dq_cmd[1:] - dq_cmd[:-1]).max(axis=1) <= CRUISE_TOLERANCE * top[1:]
    cruise_row = (np.asarray(joint) < 0) & (top > 0)
    bins, cruise = np.full(R, -1, np.int64), np.zeros(R)
    use: list[np.ndarray] = []
    starts = np.flatnonzero(cruise_row & ~np.r_[False, same[1:] & cruise_row[:-1]])
    for first in starts:
        last = first
        while last + 1 < R and cruise_row[last + 1] and same[last + 1]:
            last += 1
        leg = np.arange(first, last + 1)
        v = dq_cmd[first]
        lead = int(np.argmax(np.abs(v)))
        tt = t[leg]
        keep = leg[(tt > tt[0] + settle) & (tt < tt[-1] - trim)]
        if keep.size == 0:
            continue
        k = np.floor(np.abs(q_cmd[keep, lead] - q_cmd[keep[0], lead]) / width).astype(np.int64)
        _, k = np.unique(k, return_inverse=True)
        bins[keep] = len(use) + k
        cruise[keep] = abs(v[lead])
        use += [np.abs(v) >= min_speed] * (int(k.max()) + 1)
    velocity = np.where((bins >= 0)[:, None], dq_cmd, 0.0)
    rate = np.zeros(R)
    rate[1:] = 1.0 / np.diff(t)
    return TransferPlan(bins, velocity, cruise, rate, np.array(use, bool).reshape(-1, n))


class TransferSums(NamedTuple):
    """Running sums over a recording's transfer cruise samples, per bin (B): pose (B, n) rad,
    velocity (B, n) rad/s, acceleration (B, n) rad/s^2, current (B, n) A, square (B, n) A^2,
    count (B,); and ``last`` (n,) rad/s, the velocity of the sample before (whatever it was).
    """

    pose: jax.Array
    velocity: jax.Array
    acceleration: jax.Array
    current: jax.Array
    square: jax.Array
    count: jax.Array
    last: jax.Array


def transfer_init(bins: int, n: int) -> TransferSums:
    """Zero sums.

    Args:
        bins: Bins, B.
        n: Joints.

    Returns:
        ``TransferSums`` of zeros (host arrays, float64).
    """
    z = [np.zeros((bins, n)) for _ in range(5)]
    return TransferSums(*z, np.zeros(bins), np.zeros(n))


def transfer_add(
    sums: TransferSums,
    row: tuple,
    q: jax.Array,
    dq: jax.Array,
    current: jax.Array,
    valid: jax.Array,
    fraction: float = STEADY_FRACTION,
    current_lag: float = 0.0,
) -> TransferSums:
    """``sums`` with one sample of one world added (pure, jit- and vmap-able). A sample with
    a joint off its commanded velocity by more than (1 - ``fraction``) of the lead joint's
    cruise speed adds nothing (ringing, stick-slip). The acceleration is
    ``backward_acceleration``'s, from ``sums.last``.

    Args:
        sums: The sums so far.
        row: The sample's ``TransferPlan.rows()`` entries: bin (), velocity (n,) rad/s,
            cruise () rad/s, rate () 1/s.
        q: Joint angles, (n,) rad.
        dq: Joint velocities, (n,) rad/s.
        current: Motor currents, (n,) A.
        valid: () bool; False adds nothing.
        fraction: ``STEADY_FRACTION``.
        current_lag: s, the current flowed at q - current_lag dq.

    Returns:
        The new sums.
    """
    at, velocity, cruise, rate = row
    steady = valid & (at >= 0) & (cruise > 0)
    steady = steady & jnp.all(jnp.abs(dq - velocity) <= (1.0 - fraction) * cruise)
    w = steady.astype(q.dtype)
    b = jnp.maximum(at, 0)
    return TransferSums(
        sums.pose.at[b].add(w * (q - current_lag * dq)),
        sums.velocity.at[b].add(w * dq),
        sums.acceleration.at[b].add(w * (dq - sums.last) * rate),
        sums.current.at[b].add(w * current),
        sums.square.at[b].add(w * current**2),
        sums.count.at[b].add(w),
        dq,
    )


def transfer_finish(sums: TransferSums, plan: TransferPlan) -> TransferBins:
    """The bins of streamed sums.

    Args:
        sums: The sums (a leading world axis W, or none).
        plan: The plan they were streamed with (its B bins).

    Returns:
        ``TransferBins`` (host arrays), fields (..., bucket(B), n), a leading world axis as
        ``sums`` has.
    """
    B = plan.use.shape[0]
    count = np.asarray(sums.count)[..., :B, None]
    per = np.maximum(count, 1.0)
    use = plan.use & (count > 0)
    cut = [np.asarray(a)[..., :B, :] for a in sums[:5]]
    tb = TransferBins(
        cut[0] / per,
        cut[1] / per,
        cut[2] / per,
        np.where(use, cut[3], 0.0),
        np.where(use, cut[4], 0.0),
        np.where(use, count, 0.0),
    )
    return padded_bins(tb, bucket(B))
