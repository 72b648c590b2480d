"""Streamed sweep moments: the sums of ``SweepMoments`` added sample by sample while a
simulation runs (the MJX studies, on the device).

The steady samples are chosen from the plan's commanded speed, which needs no median
(``stream_plan``, by ``identify.steady``'s rule); ``stream_add`` adds one sample of one world
(pure, jit- and vmap-able) and drops those whose measured speed is off the cruise;
``streamed_moments`` turns the sums into moments. The sums are taken about each sweep's
commanded pose and moved to the held pose at the end, exactly (u is affine in the pose; see
``identify.moments``). Units: s, rad, rad/s, A.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.identify.moments import SweepMoments, assemble, features, moment_size
from jaxcomp.identify.packing import layout
from jaxcomp.identify.steady import (
    CRUISE_TOLERANCE,
    STEADY_FRACTION,
    STEADY_SETTLE,
    STEADY_TRIM,
    at_speed,
    in_window,
)


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
    """The steady samples of a plan's passes, decided from the plan alone so that moments can
    be summed while the samples arrive: those at the pass's cruise (its largest commanded
    speed, within ``CRUISE_TOLERANCE``) in its steady window (``identify.steady.in_window``,
    from its first to its last sample at the cruise). ``stream_add`` also drops those whose
    measured speed is off the cruise by more than (1 - ``fraction``) of it (ripple,
    stick-slip), as ``identify.bins.steady``.

    Args:
        t: (R,) s, the recorded samples' times.
        q_cmd: (R, n) rad, the commanded pose.
        speed_cmd: (R,) rad/s, the swept joint's commanded velocity.
        joint: (R,) int and direction: (R,) int, the labels (as a ``Recording``'s).
        trim: s, left out before a pass's last sample at the cruise (and after its first, on
            a cruise shorter than ``SETTLE_CRUISE``).
        settle: s, left out after the first sample at the cruise of a longer one.

    Returns:
        The ``StreamPlan`` of the R samples.
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
            cruise, steady = _planned_pass(t[part], v, settle, trim)
            if steady is None:
                continue
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


def _planned_pass(
    t: np.ndarray, v: np.ndarray, settle: float, trim: float
) -> tuple[float, np.ndarray | None]:
    """(cruise rad/s, steady (m,) bool) of one pass of m samples at ``t`` (m,) s commanded at
    ``v`` (m,) rad/s along the pass; steady None when the pass never moves its way."""
    cruise = v.max()
    if cruise <= 0:
        return cruise, None
    at = v >= cruise * (1.0 - CRUISE_TOLERANCE)
    on = np.flatnonzero(at)
    return cruise, at & in_window(t, t[on[0]], t[on[-1]], settle, trim)


class StreamSums(NamedTuple):
    """Running sums over a recording's steady samples, per sweep (S) and pass (2): what
    ``stream_add`` adds to sample by sample and ``stream_moments`` turns into moments. n joints,
    P = 3 (n + 1) + 1. outer (S, 2, P, P): sum of phi phi^T, phi = ``moments.features`` with
    dh the pose less the sweep's origin (swept joint: 0); offset (S, 2, n) rad: sum of the pose
    less the origin; speed (S, 2) rad/s: sum of the swept joint's speed along the pass; count
    (S, 2)."""

    outer: jax.Array
    offset: jax.Array
    speed: jax.Array
    count: jax.Array


def stream_init(sweeps: int, n: int) -> StreamSums:
    """Zero sums to stream into.

    Args:
        sweeps: S, the sweeps (at least the plan's).
        n: joints.

    Returns:
        Zero ``StreamSums`` (host arrays, float64).
    """
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
    """``sums`` with one sample of one world added (pure, jit- and vmap-able).

    Args:
        sums: the sums so far.
        row: the sample's ``StreamPlan.rows()`` entries.
        q: (n,) rad; dq: (n,) rad/s; current: (n,) A, the sample's.
        valid: bool, False adds nothing.
        fraction: the sample counts when its swept joint's speed is within (1 - ``fraction``)
            of the planned cruise (``identify.steady.at_speed``).
        current_lag: s, the current flowed at q - lag dq.

    Returns:
        The new ``StreamSums``.
    """
    slot, passage, joint, direction, cruise, origin = row
    n = q.shape[-1]
    pose = q - current_lag * dq
    swept = jax.nn.one_hot(joint, n, dtype=q.dtype)
    speed = dq[joint] * direction
    steady = valid & (slot >= 0) & (cruise > 0) & at_speed(speed, cruise, fraction)
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
    """One world's moments from its sums (pure): the sums about each sweep's origin moved to
    its held pose (the mean over its steady samples), exactly: u = [1, dh - m] is a linear map
    of [1, dh].

    Args:
        sums: one world's ``StreamSums`` of the plan's S sweeps.
        plan: the ``StreamPlan``.

    Returns:
        (hold (S, n) rad, moments (S, D, D), count (S,)).
    """
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
    """The moments of W worlds' streamed sums.

    Args:
        sums: ``StreamSums`` with a leading world axis W (at least the plan's S sweeps).
        plan: the ``StreamPlan`` the worlds followed.
        gravity: (3,) m/s^2, base frame.

    Returns:
        ``SweepMoments`` (host arrays) with a leading world axis, as
        ``sweep_reduction.sweep_moments_batch``'s.
    """
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
