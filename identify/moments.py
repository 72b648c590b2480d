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

from typing import NamedTuple

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.identify.bins import STEADY_FRACTION, steady, sweep_ids
from jaxcomp.recording import Recording


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
    moments = np.empty((S, 6, 6))
    for a in range(6):
        for b in range(a, 6):
            moments[:, a, b] = moments[:, b, a] = np.bincount(inverse, psi[a] * psi[b], S)
    first = np.searchsorted(inverse, np.arange(S))  # rows are in time order, ids ascending
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
