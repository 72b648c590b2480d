"""Sweep moments: the packed layout, the JAX reduction against sums over the samples, and the
same sums streamed sample by sample."""

import jax
import numpy as np
import pytest
import synthetic

from jaxcomp.errors import InputError
from jaxcomp.identify.bins import steady, sweep_ids
from jaxcomp.identify.moments import moment_size
from jaxcomp.identify.packing import PackBuffer, layout, pack
from jaxcomp.identify.streaming import stream_add, stream_init, stream_plan, streamed_moments
from jaxcomp.identify.sweep_reduction import packed_moments, sweep_moments
from jaxcomp.recording import Recording


def _labels(runs):
    """joint, direction arrays from runs of (joint, direction, samples)."""
    joint = np.concatenate([np.full(n, j) for j, _, n in runs])
    direction = np.concatenate([np.full(n, d) for _, d, n in runs])
    return joint, direction


def test_layout_numbers_the_sweeps_as_sweep_ids():
    rng = np.random.default_rng(0)
    runs = []
    for _ in range(40):
        if rng.random() < 0.3:
            runs.append((-1, 0, int(rng.integers(1, 5))))
            continue
        j = int(rng.integers(0, 3))
        d = int(rng.choice([-1, 1]))
        for _ in range(int(rng.integers(1, 6))):  # 1 to 5 passes back to back
            runs.append((j, d, int(rng.integers(1, 7))))
            d = -d
    joint, direction = _labels(runs)
    lay = layout(joint, direction)
    ids = sweep_ids(joint, direction)
    seen = np.full(joint.size, -1)
    for s in range(lay.joint.size):
        for k in range(2):
            f, n = lay.first[s, k], lay.length[s, k]
            assert (n == 0) == (lay.direction[s, k] == 0)
            seen[f : f + n] = s
            assert np.all(joint[f : f + n] == lay.joint[s])
            assert np.all(direction[f : f + n] == lay.direction[s, k])
    np.testing.assert_array_equal(seen, ids)


@pytest.fixture(scope="module")
def rec(sim_calibration):
    clean, _ = sim_calibration
    return synthetic.with_noise(clean, 0.05, seed=3)


def _numpy_moments(rec: Recording):
    """The moments, counts and held poses summed sample by sample with numpy."""
    keep = steady(rec)
    ids = sweep_ids(rec.joint, rec.direction)
    n = rec.q.shape[1]
    out = []
    for s in range(ids.max() + 1):
        rows = np.flatnonzero((ids == s) & keep)
        j = rec.joint[rows[0]]
        hold = rec.q[rows].mean(axis=0)
        psi = np.empty((rows.size, moment_size(n)))
        for d in (-1, 1):
            pass_rows = np.flatnonzero((ids == s) & (rec.direction == d))
            if pass_rows.size == 0:
                continue
            mine = rec.direction[rows] == d
            v = d * np.mean(np.abs(rec.dq[rows[mine], j]))
            q = rec.q[rows[mine]]
            u = np.concatenate([np.ones((len(q), 1)), q - hold], axis=1)
            u[:, 1 + j] = 0.0
            th = q[:, j]
            z = np.concatenate([np.sin(th)[:, None] * u, np.cos(th)[:, None] * u, u], axis=1)
            tail = [np.full_like(th, d), np.full_like(th, v), rec.current[rows[mine], j]]
            psi[mine] = np.concatenate([z, np.stack(tail, axis=1)], axis=1)
        out.append((j, psi.T @ psi, rows.size, hold))
    return out


def test_moments_are_the_sums_over_the_steady_samples(rec):
    want = _numpy_moments(rec)
    got = sweep_moments(rec)
    assert got.n_sweeps == len(want) == 14
    for s, (j, moments, count, hold) in enumerate(want):
        assert got.joint[s] == j and got.count[s] == count
        scale = np.abs(moments).max()
        np.testing.assert_allclose(got.moments[s], moments, rtol=1e-9, atol=1e-12 * scale)
        np.testing.assert_allclose(got.hold[s], hold, rtol=0, atol=1e-12)


def test_a_reused_buffer_leaks_nothing_into_the_next_pack(rec):
    """Pack a long recording, then a shorter one into the same buffer: the moments of the
    shorter one are those of a fresh pack (the stale tail is never read)."""
    cut = int(np.flatnonzero(rec.joint == 3)[0])
    short = Recording(*(getattr(rec, f)[:cut] for f in ("t", "q", "dq", "current", "joint",
                      "direction")), rec.model, rec.gravity)  # fmt: skip
    buffer = PackBuffer()
    first, length = pack([rec, rec], buffer)
    packed_moments(first, length)
    packed, length = pack([short, short], buffer)
    assert np.shares_memory(packed.samples, first.samples)  # reused, stale data behind
    reused = packed_moments(packed, length)
    fresh = sweep_moments(short)
    S = fresh.n_sweeps
    np.testing.assert_array_equal(np.asarray(reused.count)[0, :S], fresh.count)
    assert not np.asarray(reused.count)[0, S:].any()
    scale = np.abs(fresh.moments).max()
    np.testing.assert_allclose(
        np.asarray(reused.moments)[1, :S], fresh.moments, rtol=1e-9, atol=1e-13 * scale
    )
    np.testing.assert_allclose(np.asarray(reused.hold)[1, :S], fresh.hold, rtol=1e-12)


def test_a_recording_without_sweeps_is_one_clear_error(rec):
    flat = Recording(
        rec.t, rec.q, rec.dq, rec.current, np.full_like(rec.joint, -1),
        np.zeros_like(rec.direction), rec.model, rec.gravity,
    )  # fmt: skip
    with pytest.raises(InputError, match="recording 0 has no sweep"):
        pack([flat])


def test_streamed_sums_are_the_packed_moments(rec):
    """``stream_add`` sample by sample, about an origin away from the held pose, then
    ``streamed_moments``: the moments of ``sweep_moments`` on the same steady samples (the
    plan's speeds stand in for the measured ones: fraction 0 keeps every planned sample)."""
    keep = steady(rec)
    dt = np.diff(rec.t, prepend=rec.t[0] - 1e-3)
    fake = stream_plan(rec.t, rec.q, np.r_[0.0, np.diff(rec.q, axis=0)[:, 0]] / dt, rec.joint,
                       rec.direction)  # fmt: skip
    lay = layout(rec.joint, rec.direction)
    assert np.array_equal(fake.sweep_joint, lay.joint) and fake.sweep_origin.shape == (14, 6)
    origin = fake.sweep_origin + 0.3  # far from the held poses: the shift must be exact
    plan = fake._replace(
        speed=np.where(keep, 1e3, 0.0),
        origin=np.where(fake.slot[:, None] >= 0, origin[np.maximum(fake.slot, 0)], 0.0),
        sweep_origin=origin,
    )
    step = jax.jit(lambda s, row, x: stream_add(s, row, *x, True, fraction=0.0))
    sums, _ = jax.lax.scan(
        lambda s, x: (step(s, x[0], x[1:]), None),
        stream_init(14, 6),
        (plan.rows(), rec.q, rec.dq, rec.current),
    )
    got = streamed_moments(jax.tree.map(lambda a: a[None], sums), plan)
    want = sweep_moments(rec)
    np.testing.assert_array_equal(got.joint[0], want.joint)
    np.testing.assert_array_equal(got.count[0], want.count)
    np.testing.assert_allclose(got.hold[0], want.hold, rtol=0, atol=1e-12)
    scale = np.abs(want.moments).max()
    np.testing.assert_allclose(got.moments[0], want.moments, rtol=1e-9, atol=1e-11 * scale)


def test_join_sweeps_is_concat_then_take():
    """``join_sweeps`` writes the joined sweeps straight in their order: equal to joining
    (``concat_moments``) and then taking the sweeps in that order, for random parts."""
    from jaxcomp.identify.moments import SweepMoments, concat_moments, join_sweeps

    rng = np.random.default_rng(7)

    def part(sweeps: int) -> SweepMoments:
        return SweepMoments(
            rng.integers(0, 6, (3, sweeps)),
            rng.random((3, sweeps, 6)),
            rng.random((3, sweeps, 4, 4)),
            rng.integers(0, 9, (3, sweeps)),
            rng.random((3, 3)),
            rng.random(3),
            rng.random((3, 3)),
        )

    parts = [part(2), part(1), part(3)]
    order = rng.permutation(6)
    joined, whole = join_sweeps(parts, order), concat_moments(parts)
    for k in ("joint", "hold", "moments", "count"):
        np.testing.assert_array_equal(getattr(joined, k), np.take(getattr(whole, k), order, 1))
    np.testing.assert_array_equal(joined.gravity, parts[0].gravity)
