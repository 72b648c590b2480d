"""Sweep moments: a recording reduced to a 5 x 5 matrix per sweep, exact for the joint fit.

While joint j sweeps with the other joints held, its gravity torque is exactly
a sin(theta) + b cos(theta) + c in the swept angle theta (the carried subtree turns rigidly
about the joint axis), and so is each column of its regressor. With
psi = [sin theta, cos theta, 1, d, current] per steady sample (d the direction, current the
swept joint's, A), the sums ``sum psi psi^T`` over a sweep hold everything a least-squares fit
of Eq. (13) on that sweep needs: the fit never touches the samples again.
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
    joint's entry is irrelevant). moments (S, 5, 5): sum of psi psi^T (see the module
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
            rec.current[rows, joint],
        ]
    )
    S = used.size
    moments = np.empty((S, 5, 5))
    for a in range(5):
        for b in range(a, 5):
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
