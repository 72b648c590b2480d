"""Angle bins: a 1 kHz sweep recording reduced to per-angle means, per sweep and direction.

Within a sweep the swept joint moves at constant speed and the others are held, so the
measured current is a function of the swept angle and the direction only. Averaging the samples
of each (sweep, direction, angle bin) keeps all the information a least-squares fit uses (each
bin weighs as its sample count) while the fit's cost no longer grows with the sample count.
Only steady-speed samples enter (``steady``, by ``identify.steady``'s rule): the ramps at the
ends of a sweep (acceleration, inertia) are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.identify.steady import (
    MEDIAN_STRIDE,
    STEADY_FRACTION,
    STEADY_SETTLE,
    STEADY_TRIM,
    at_speed,
    in_window,
)
from jaxcomp.recording import Recording

#: Default bin width, rad (1 degree).
BIN_WIDTH = np.deg2rad(1.0)


@dataclass(frozen=True)
class SweepBins:
    """Per-bin means of a recording; B bins, n joints.

    Attributes:
        sweep: (B,) int, index of the sweep (a contiguous run of one swept joint).
        joint: (B,) int, the swept joint. direction: (B,) int, +1 or -1.
        index: (B,) int, angle bin number: floor(q[joint] / width).
        count: (B,) samples averaged.
        q: (B, n) rad, dq: (B, n) rad/s, current: (B, n) A, means over the bin.
        gravity: (3,) m/s^2, base frame. payload_mass kg, payload_com (3,) m (EE frame).
        width: bin width, rad.
    """

    sweep: np.ndarray
    joint: np.ndarray
    direction: np.ndarray
    index: np.ndarray
    count: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    current: np.ndarray
    gravity: np.ndarray
    payload_mass: float
    payload_com: np.ndarray
    width: float

    @property
    def n_bins(self) -> int:
        """B, the number of bins."""
        return self.count.shape[0]

    @property
    def swept_current(self) -> np.ndarray:
        """(B,) A, mean current of the swept joint of each bin."""
        return self.current[np.arange(self.n_bins), self.joint]


def sweep_ids(joint: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The sweep each sample belongs to.

    A sweep is a contiguous run of one swept joint holding one pass in each direction: a run
    that reverses more than once (several sweeps recorded back to back) is split.

    Args:
        joint: (N,) int, each sample's swept joint (-1: none), as ``Recording.joint``.
        direction: (N,) int, each sample's pass direction, +1 / -1, as ``Recording.direction``.

    Returns:
        (N,) int, the sweep index of each sample, from 0 in recording order (-1 outside
        sweeps).
    """
    run_start = np.r_[True, joint[1:] != joint[:-1]]
    turn = np.r_[False, direction[1:] != direction[:-1]] & ~run_start
    turns = np.cumsum(turn)
    turns_in_run = turns - np.maximum.accumulate(np.where(run_start, turns, 0))
    start = run_start | (turn & (turns_in_run % 2 == 0))
    ids = np.cumsum(start & (joint >= 0)) - 1
    return np.where(joint >= 0, ids, -1)


def steady(
    rec: Recording,
    fraction: float = STEADY_FRACTION,
    trim: float = STEADY_TRIM,
    settle: float = STEADY_SETTLE,
) -> np.ndarray:
    """The constant-speed samples of every sweep pass of a recording (``identify.steady``).

    A sample is steady when its swept joint moves in the pass's direction at a speed within
    (1 - ``fraction``) of the pass speed, either side (``at_speed``; the pass speed: the mean
    speed of the samples at >= ``fraction`` of the median speed of every ``MEDIAN_STRIDE``-th
    sample of the pass; the median alone may fall on a ramp when a pass has few samples), and
    it lies in the pass's steady window (``in_window``: more than ``settle_time`` s after the
    first such sample, the servo still rings there, and more than ``trim`` s before the last).

    Args:
        rec: the recording (N samples).
        fraction: the steady fraction of the pass speed.
        trim: s, left out before a pass's last sample at speed (and after its first, on a
            cruise shorter than ``SETTLE_CRUISE``).
        settle: s, left out after the first sample at speed of a cruise of
            ``SETTLE_CRUISE`` s or more.

    Returns:
        (N,) bool, True at the steady samples.
    """
    ids = sweep_ids(rec.joint, rec.direction)
    swept = np.flatnonzero(ids >= 0)
    keep = np.zeros(rec.n_samples, bool)
    if swept.size == 0:
        return keep
    key = ids[swept] * 2 + (rec.direction[swept] > 0)
    speed = rec.dq[swept, rec.joint[swept]] * rec.direction[swept]
    t = rec.t[swept]
    bounds = np.flatnonzero(np.diff(key)) + 1  # passes are contiguous runs of one key
    for part in np.split(np.arange(swept.size), bounds):
        median = np.median(speed[part[::MEDIAN_STRIDE]])
        if median <= 0:
            continue
        ref = speed[part][speed[part] >= fraction * median].mean()
        fast = part[at_speed(speed[part], ref, fraction)]
        if fast.size == 0:
            continue
        inside = in_window(t[fast], t[fast[0]], t[fast[-1]], settle, trim)
        keep[swept[fast[inside]]] = True
    return keep


def bin_sweeps(
    rec: Recording, width: float = BIN_WIDTH, fraction: float = STEADY_FRACTION
) -> SweepBins:
    """Average the steady samples of ``rec`` into angle bins.

    Args:
        rec: the recording.
        width: rad, the bin width (> 0).
        fraction: the steady fraction of the pass speed (``steady``).

    Returns:
        The ``SweepBins`` of its steady samples.

    Raises:
        InputError: ``width`` is not > 0, or the recording has no steady sweep sample.
    """
    if not width > 0:
        raise InputError(f"bin width must be > 0 rad, got {width}")
    keep = steady(rec, fraction)
    if not keep.any():
        raise InputError(
            "the recording has no steady sweep samples (the swept joint never moves at a "
            "constant speed in its direction)"
        )
    rows = np.flatnonzero(keep)
    ids = sweep_ids(rec.joint, rec.direction)[rows]
    joint = rec.joint[rows]
    direction = rec.direction[rows]
    index = np.floor(rec.q[rows, joint] / width).astype(np.int64)
    # dense key (sweep, direction, angle bin) -> bincount, no sort
    lo = index.min()
    span = int(index.max() - lo + 1)
    key = ((ids * 2 + (direction > 0)) * span + (index - lo)).astype(np.int64)
    count_all = np.bincount(key)
    used = np.flatnonzero(count_all)
    slot = np.zeros(count_all.shape[0], np.int64)
    slot[used] = np.arange(used.size)
    inverse = slot[key]
    count = count_all[used]
    n = rec.n_joints

    def mean(values: np.ndarray) -> np.ndarray:
        sums = [np.bincount(inverse, values[:, k], used.size) for k in range(n)]
        return np.stack(sums, axis=1) / count[:, None]

    first = np.zeros(used.size, np.int64)
    first[inverse[::-1]] = np.arange(len(rows))[::-1]
    return SweepBins(
        sweep=ids[first],
        joint=joint[first],
        direction=direction[first],
        index=index[first],
        count=count,
        q=mean(rec.q[rows]),
        dq=mean(rec.dq[rows]),
        current=mean(rec.current[rows]),
        gravity=np.asarray(rec.gravity, float),
        payload_mass=float(rec.payload_mass),
        payload_com=np.asarray(rec.payload_com, float),
        width=float(width),
    )
