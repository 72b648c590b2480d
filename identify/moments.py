"""Sweep moments: a recording reduced to a 5 x 5 matrix per sweep, exact for the joint fit.

While joint j sweeps with the other joints held, its gravity torque is exactly
a sin(theta) + b cos(theta) + c in the swept angle theta (the carried subtree turns rigidly
about the joint axis), and so is each column of its regressor. With
psi = [sin theta, cos theta, 1, d, v, current] per steady sample (d the direction, v the pass
velocity in rad/s: d times the median speed of the pass, not the measured velocity, whose
servo ripple correlates with the current; current the swept joint's in A), the sums
``sum psi psi^T`` over a sweep hold everything a least-squares fit of Eq. (13) (plus a
viscous term in v) on that sweep needs: the fit never touches the samples again.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.identify.bins import STEADY_FRACTION, STEADY_TRIM, steady, sweep_ids
from jaxcomp.recording import STANDARD_GRAVITY, Recording


class SweepMoments(NamedTuple):
    """Moments of the steady samples of each sweep of a recording (S sweeps, n joints).

    joint (S,) int: the swept joint. hold (S, n) rad: median pose of the sweep (the swept
    joint's entry is irrelevant). moments (S, 6, 6): sum of psi psi^T (see the module
    docstring). count (S,): steady samples. gravity (3,) m/s^2; payload_mass kg;
    payload_com (3,) m, end-effector frame.
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
    """The ``SweepMoments`` of ``rec`` (steady samples only; see ``identify.bins.steady``)."""
    keep = steady(rec, fraction)
    if not keep.any():
        raise InputError(
            "the recording has no steady sweep samples (the swept joint never moves at a "
            "constant speed in its direction)"
        )
    rows = np.flatnonzero(keep)
    ids = sweep_ids(rec.joint, rec.direction)[rows]
    used, inverse = np.unique(ids, return_inverse=True)
    joint = rec.joint[rows]
    theta = rec.q[rows, joint]
    psi = np.stack(
        [
            np.sin(theta),
            np.cos(theta),
            np.ones_like(theta),
            rec.direction[rows].astype(float),
            _pass_velocity(rec, rows, ids),
            rec.current[rows, joint],
        ]
    )
    S = used.size
    first = np.searchsorted(inverse, np.arange(S))  # rows are in time order, ids ascending
    moments = np.stack([p @ p.T for p in np.split(psi, first[1:], axis=1)])
    hold = np.stack([np.median(part, axis=0) for part in np.split(rec.q[rows], first[1:])])
    return SweepMoments(
        joint=joint[first],
        hold=hold,
        moments=moments,
        count=moments[:, 2, 2].round().astype(np.int64),
        gravity=np.asarray(rec.gravity, float),
        payload_mass=float(rec.payload_mass),
        payload_com=np.asarray(rec.payload_com, float),
    )


def _pass_velocity(rec: Recording, rows: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(len(rows),) rad/s: direction times the median swept-joint speed of each pass."""
    d = rec.direction[rows]
    speed = np.abs(rec.dq[rows, rec.joint[rows]])
    key = ids * 2 + (d > 0)
    bounds = np.flatnonzero(np.diff(key)) + 1
    out = np.empty(rows.size)
    for part in np.split(np.arange(rows.size), bounds):
        out[part] = np.median(speed[part])
    return d * out


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
    labels; a sweep without steady samples in a world has zero moments and count there (it
    adds nothing to a fit). ``world_moments(batch, w)`` is world w's ``sweep_moments``, to
    rounding (sums in another order). Vectorized over worlds, a Python loop over passes.
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
    ids = sweep_ids(joint, direction)
    swept = np.flatnonzero(ids >= 0)
    used = np.unique(ids[swept])
    S = used.size
    moments = np.zeros((w, S, 6, 6))
    hold = np.zeros((w, S, n))
    count = np.zeros((w, S), np.int64)
    key = ids[swept] * 2 + (direction[swept] > 0)
    passes = np.split(swept, np.flatnonzero(np.diff(key)) + 1) if swept.size else []
    masks: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for idx in passes:
        s = int(np.searchsorted(used, ids[idx[0]]))
        j, d = int(joint[idx[0]]), float(direction[idx[0]])
        keep = _steady_pass(t[idx], dq[:, idx, j] * d, fraction, trim)
        masks.setdefault(s, []).append((idx, keep))
        speed = np.abs(dq[:, idx, j])
        v = d * _masked_median(speed[:, :, None], keep)[:, 0]  # (W,) pass velocity, rad/s
        theta = q[:, idx, j]
        ones = np.ones_like(theta)
        psi = np.stack(
            [
                np.sin(theta),
                np.cos(theta),
                ones,
                d * ones,
                np.nan_to_num(v)[:, None] * ones,
                current[:, idx, j],
            ],
            axis=-1,
        )
        weighted = psi * keep[:, :, None]
        moments[:, s] += np.einsum("wla,wlb->wab", weighted, psi)
    for s, parts in masks.items():
        idx = np.concatenate([p[0] for p in parts])
        keep = np.concatenate([p[1] for p in parts], axis=1)
        hold[:, s] = np.nan_to_num(_masked_median(q[:, idx], keep))
        count[:, s] = keep.sum(axis=1)
    first = swept[np.searchsorted(ids[swept], used)]  # sweep ids ascend with time
    sweep_joint = joint[first]
    return SweepMoments(
        joint=np.broadcast_to(sweep_joint, (w, S)).astype(np.int64),
        hold=hold,
        moments=moments,
        count=count,
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


def _steady_pass(t: np.ndarray, speed: np.ndarray, fraction: float, trim: float) -> np.ndarray:
    """(W, L) bool: ``identify.bins.steady`` of one pass in every world; ``t`` (L,) s,
    ``speed`` (W, L) rad/s along the pass's direction."""
    ref = np.median(speed, axis=1, keepdims=True)
    fast = (speed >= fraction * ref) & (ref > 0)
    has = fast.any(axis=1)
    lo = t[np.argmax(fast, axis=1)]
    hi = t[t.size - 1 - np.argmax(fast[:, ::-1], axis=1)]
    inside = (t[None] > lo[:, None] + trim) & (t[None] < hi[:, None] - trim)
    return fast & inside & has[:, None]


def _masked_median(x: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(W, k) median over axis 1 of ``x`` (W, L, k) where ``keep`` (W, L); NaN where none.

    Exactly ``np.median`` of the kept values: the middle one, or the mean of the two."""
    data = np.where(keep[:, :, None], x, np.inf)
    data.sort(axis=1)
    c = keep.sum(axis=1)[:, None]  # (W, 1)
    lo = np.take_along_axis(data, np.maximum((c - 1) // 2, 0)[:, :, None], axis=1)[:, 0]
    hi = np.take_along_axis(data, np.maximum(c // 2, 0)[:, :, None], axis=1)[:, 0]
    hi = np.where(c > 0, hi, np.nan)
    return np.where(c > 0, (lo + hi) / 2, np.nan)
