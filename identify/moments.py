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

This module holds the ``SweepMoments`` and their maths: the layout of psi (``moment_size``,
``z_index``), the per-sample features phi = [z, current] and the moments assembled from their
per-pass sums (``features``, ``assemble``), and batches of moments taken apart and joined.
They are made from a recording's samples by ``identify.sweep_reduction`` (packed by
``identify.packing``, reduced with JAX) or summed sample by sample while a simulation runs
(``identify.streaming``); the steady samples are ``identify.steady``'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.errors import InputError


class SweepMoments(NamedTuple):
    """Moments of the steady samples of each sweep of a recording (S sweeps, n joints).

    joint (S,) int: the swept joint. hold (S, n) rad: the held pose of the sweep, the mean of
    q over its steady samples (the swept joint's entry is irrelevant). moments (S, D, D),
    D = ``moment_size(n)``: sum of psi psi^T (see the module docstring). count (S,): steady
    samples. gravity (3,) m/s^2; payload_mass kg; payload_com (3,) m, end-effector frame.
    A batch of W worlds (``sweep_moments_batch``) has a leading axis W on every field.
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
        """S, the number of sweeps (of one recording)."""
        return self.joint.shape[0]

    @property
    def n_samples(self) -> int:
        """The steady samples of all sweeps."""
        return int(self.count.sum())


def moment_size(n: int) -> int:
    """The size of a sweep's moment matrix.

    Args:
        n: joints.

    Returns:
        D = 3 (n + 1) + 3, the length of psi = [z (3 (n + 1)), d, v, current].
    """
    return 3 * (n + 1) + 3


def z_index(term: int, k: int, n: int) -> int:
    """Where an entry of z lies in psi.

    Args:
        term: 0 sin theta, 1 cos theta, 2 one.
        k: the factor u_k: 0 one, 1 + i the held offset dh of joint i.
        n: joints.

    Returns:
        The index in psi of z's entry ``term`` x u_k.
    """
    return term * (n + 1) + k


def features(theta: jax.Array, dh: jax.Array, current: jax.Array) -> jax.Array:
    """The features phi = [z, current] of samples: z = [sin theta u, cos theta u, u] with
    u = [1, dh] (pure, JAX).

    Args:
        theta: (...) rad, the swept angle.
        dh: (..., n) rad, the held joints' offsets from the held pose (0 for the swept joint).
        current: (...) A, the swept joint's current.

    Returns:
        phi (..., 3 (n + 1) + 1).
    """
    u = jnp.concatenate([jnp.ones_like(dh[..., :1]), dh], axis=-1)  # (..., n + 1)
    trig = jnp.stack([jnp.sin(theta), jnp.cos(theta), jnp.ones_like(theta)], axis=-1)
    z = (trig[..., :, None] * u[..., None, :]).reshape(*theta.shape, -1)
    return jnp.concatenate([z, current[..., None]], axis=-1)


def assemble(G: jax.Array, d: jax.Array, v: jax.Array, n: int) -> jax.Array:
    """The moments of S sweeps from each pass's sums of phi phi^T (pure, JAX).

    psi = E phi with E constant over a pass (d and v are multiples of z's "one"): the
    moments are sum over passes of E G E^T.

    Args:
        G: (S, 2, Z + 1, Z + 1), Z = 3 (n + 1): each pass's sum of phi phi^T (``features``).
        d: (S, 2), each pass's direction, +1 / -1 (0: no such pass).
        v: (S, 2) rad/s, each pass's velocity.
        n: joints.

    Returns:
        (S, D, D), D = ``moment_size(n)``: the sums of psi psi^T.
    """
    S, Z = G.shape[0], G.shape[-1] - 1
    D = moment_size(n)
    one = z_index(2, 0, n)
    E = jnp.zeros((S, 2, D, Z + 1), G.dtype)
    E = E.at[:, :, jnp.arange(Z), jnp.arange(Z)].set(1.0)
    E = E.at[:, :, Z, one].set(d).at[:, :, Z + 1, one].set(v)
    E = E.at[:, :, Z + 2, Z].set(1.0)
    return jnp.einsum("skai,skij,skbj->sab", E, G, E)


def world_moments(batch: SweepMoments, w: int, keep_empty: bool = False) -> SweepMoments:
    """One world of a batch of moments as one recording's ``SweepMoments``.

    Args:
        batch: moments with a leading world axis (``sweep_moments_batch``,
            ``concat_moments``).
        w: the world.
        keep_empty: keep the sweeps without steady samples, with joint -1 (rows stay aligned
            with the batch's sweeps); else they are dropped.

    Returns:
        World ``w``'s ``SweepMoments`` (no world axis).
    """
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


#: The fields of ``SweepMoments`` with a sweep axis (axis 1 of a batch).
_PER_SWEEP = ("joint", "hold", "moments", "count")


def concat_moments(parts: Sequence[SweepMoments]) -> SweepMoments:
    """Batches of moments of consecutive stretches of the same worlds, joined.

    Args:
        parts: batches (a leading world axis W, the same in each).

    Returns:
        The batch of their sweeps joined along the sweep axis (axis 1); metadata from the
        first part.

    Raises:
        InputError: ``parts`` is empty.
    """
    if not parts:
        raise InputError("no moments to join")
    cat = [np.concatenate([getattr(p, k) for p in parts], axis=1) for k in _PER_SWEEP]
    return parts[0]._replace(**dict(zip(_PER_SWEEP, cat, strict=True)))


def join_sweeps(parts: Sequence[SweepMoments], order: np.ndarray) -> SweepMoments:
    """``concat_moments(parts)`` with its sweeps taken in an order, written once into the
    result (no joined copy).

    Args:
        parts: batches (a leading world axis W, the same in each).
        order: (S,) int, indices into the joined sweeps (axis 1).

    Returns:
        The batch of S sweeps; metadata from the first part.
    """
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
    """Batches of moments of the same sweeps in other worlds, joined.

    Args:
        parts: batches (a leading world axis each) of the same sweeps.

    Returns:
        One batch, the worlds of ``parts`` in order along the world axis.

    Raises:
        InputError: ``parts`` is empty.
    """
    if not parts:
        raise InputError("no moments to join")
    if len(parts) == 1:
        return parts[0]
    return SweepMoments(*(np.concatenate([getattr(p, f) for p in parts]) for f in parts[0]._fields))
