"""A calibration plan recorded in every world of a ``BatchTruth`` on MJX, each sweep reduced to
its moments and each transfer's cruise to its bins on the device while the worlds run.

The simulator steps at 1 kHz and every ``every``-th state (default 10: 100 Hz) is added to its
sweep's running sums inside the compiled loop (``MjxSimulator.run(reduce=)`` with
``identify.streaming.stream_add``; the steady samples are chosen from the plan's commanded speed,
``identify.streaming.stream_plan``; the transfers' likewise, ``identify.transfers``), so that only
each world's small sums come back to the host:
host memory does not grow with the plan's length, and only the first ``keep`` worlds' samples
leave the device (for the scipy fit). The current noise is the simulator's, drawn on the device
from ``fold_in(fold_in(PRNGKey(seed), id), step)`` with ``id`` the world's index in the study
and ``step`` the plan step (in whichever lane a sweep runs side by side), so a world's numbers
depend neither on how worlds are batched nor on the number of devices.

Units: SI (rad, rad/s, A, s).
"""

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.hardware.mjx import SETTLE_STEPS, BatchTruth, MjxSimulator, Reduction
from jaxcomp.identify.moments import SweepMoments, join_sweeps, stack_worlds
from jaxcomp.identify.packing import layout
from jaxcomp.identify.steady import STEADY_FRACTION
from jaxcomp.identify.streaming import (
    StreamPlan,
    StreamSums,
    stream_add,
    stream_init,
    stream_plan,
    streamed_moments,
)
from jaxcomp.identify.transfers import (
    TransferBins,
    TransferPlan,
    TransferSums,
    padded_bins,
    transfer_add,
    transfer_finish,
    transfer_init,
    transfer_plan,
)
from jaxcomp.recording import Recording
from jaxcomp.studies.plan_signal import (
    Lanes,
    PlanSignal,
    Segments,
    pack_segments,
    plan_segments,
    start_pose,
)
from jaxcomp.studies.truth_draw import truth_rows


class SignalPlans(NamedTuple):
    """What ``stream_add`` and ``transfer_add`` are told about the recorded samples of one
    ``PlanSignal``: its sweeps' ``StreamPlan`` and its transfers' ``TransferPlan``."""

    sweeps: StreamPlan
    transfers: TransferPlan


def signal_plans(signal: PlanSignal, every: int) -> SignalPlans:
    """The ``SignalPlans`` of the samples of ``signal`` recorded every ``every`` steps (sample
    i: the state after plan step i every, commanded q_ref there, at the commanded velocity of
    that step).

    Args:
        signal: the plan's signal (T steps of 1 ms).
        every: the recording decimation, steps.

    Returns:
        The ``SignalPlans`` of its ceil(T / every) samples.
    """
    rec = np.arange(0, len(signal.joint), every)
    q = signal.q_ref
    velocity = np.diff(q, axis=0, prepend=q[:1]) / CONTROL_PERIOD
    joint = signal.joint[rec]
    speed = velocity[rec, np.maximum(joint, 0)]
    t = (rec + 1) * CONTROL_PERIOD
    return SignalPlans(
        stream_plan(t, q[rec], speed, joint, signal.direction[rec]),
        transfer_plan(t, q[rec], velocity[rec], joint),
    )


def _stacked_rows(rows: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Per-sample rows of several plans (their first field an index, -1: none) padded to
    the longest with samples that add nothing, stacked on axis 1 (R, G, ...)."""
    length = max(len(r[0]) for r in rows)

    def padded(r: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
        extra = length - len(r[0])
        pad = [np.full(extra, -1), *(np.zeros((extra, *a.shape[1:])) for a in r[1:])]
        return tuple(np.concatenate([a, b.astype(a.dtype)]) for a, b in zip(r, pad, strict=True))

    return tuple(np.stack(a, axis=1) for a in zip(*map(padded, rows), strict=True))


def plan_reduction(plans: list[SignalPlans], n: int, current_lag: float) -> Reduction:
    """The ``Reduction`` that sums each world's sweep moments and transfer bins on the device
    (carry: (``StreamSums``, ``TransferSums``)): world w follows ``plans[group[w]]``.

    Args:
        plans: the ``SignalPlans`` of each group's signal (one: every world the same).
        n: the arm's joints.
        current_lag: s, the measured current's lag behind the state (``MjxSimulator``).

    Returns:
        The ``Reduction`` for ``MjxSimulator.run(reduce=)``.
    """
    sweeps = max(p.sweeps.sweep_joint.size for p in plans)
    bins = max(p.transfers.use.shape[0] for p in plans)
    xs = (
        _stacked_rows([p.sweeps.rows() for p in plans]),
        _stacked_rows([p.transfers.rows() for p in plans]),
    )

    def step(carry, x, q, dq, current, valid):
        kw = {"fraction": STEADY_FRACTION, "current_lag": current_lag}
        return (
            stream_add(carry[0], x[0], q, dq, current, valid, **kw),
            transfer_add(carry[1], x[1], q, dq, current, valid, **kw),
        )

    init = (stream_init(sweeps, n), transfer_init(bins, n))
    return Reduction(step, init, xs, ("plan-sums", float(current_lag)))


class Simulated(NamedTuple):
    """What the simulation stage returns (N worlds).

    Attributes:
        moments: stacked ``SweepMoments``, leading axis N.
        transfers: stacked ``TransferBins``, (N, B, n).
        recordings: the ``Recording`` of each kept world (study id below ``keep``), in order.
        fault_step: (N,) the plan step of each world's first fault (-1: none).
        timing: s: wall, compilation, stepping without compilation, turning the device's
            sums into moments.
        world_steps: world-steps simulated (settling included).
    """

    moments: SweepMoments
    transfers: TransferBins
    recordings: list[Recording]
    fault_step: np.ndarray
    timing: dict[str, float]
    world_steps: int


def simulate(
    sim: MjxSimulator,
    truth: BatchTruth,
    signal: PlanSignal,
    *,
    seed: int,
    every: int,
    world_batch: int,
    keep: int,
    progress: Callable[[int], None] | None = None,
    parallel: bool = False,
    offset: int = 0,
) -> Simulated:
    """Record ``signal`` in every world of ``truth`` on the ``MjxSimulator`` ``sim``,
    ``world_batch`` worlds per run; see the module docstring for noise and streaming.

    ``offset``: the index in the study of the truth's world 0 (worlds that record another
    plan come first): the world index of the noise, and of ``keep`` (the worlds below it keep
    their recordings).

    ``parallel``: run the plan's K sweeps side by side (``plan_segments``), each starting at
    rest where the sweep before it ends, packed into B <= K lanes no longer than the longest
    sweep (``pack_segments``): B MJX worlds per true robot for about 1/B of the steps, which
    fills an accelerator that a few thousand worlds leave idle. Each segment simulates the
    transfer to its sweep too (its data count; its faults do not, as the sweep's own).

    Args:
        sim: the MJX simulator of the robot.
        truth: the W true robots.
        signal: the plan's signal (``plan_signal.plan_signal``).
        seed: the noise's seed.
        every: the recording decimation, steps (10: 100 Hz).
        world_batch: true robots per MJX run.
        keep: study world ids below which a world keeps its ``Recording``.
        progress: called with the plan steps (of all worlds) done since its last call.
        parallel: run the sweeps side by side (above).
        offset: the study world id of ``truth``'s world 0.

    Returns:
        The ``Simulated``: moments and transfer bins of all W worlds, the kept recordings.

    Raises:
        InputError: ``parallel`` and a sweep that does not start at rest.
    """
    n_worlds, steps = truth.worlds, len(signal.q_ref)
    start = start_pose(sim.robot)
    keys = ("simulate", "simulate_compile", "simulate_stepping", "simulate_moments")
    timing = dict.fromkeys(keys, 0.0)
    if parallel:
        return _simulate_parallel(
            sim, truth, signal, start, seed, every, world_batch, keep, progress, timing, offset
        )
    plans = signal_plans(signal, every)
    reduce = plan_reduction([plans], sim.n, sim.current_lag)
    kept = min(max(keep - offset, 0), world_batch, n_worlds)  # the same in every run
    moments, transfers, recordings, faults = [], [], [], []
    rec_steps = np.arange(0, steps, every)
    for first in range(0, n_worlds, world_batch):
        rows = np.arange(first, min(first + world_batch, n_worlds))
        width = len(rows)
        record = np.arange(min(kept, width))
        rec = _run(sim, truth_rows(truth, rows), signal.q_ref, start, seed, every, progress,
                   width, steps, steps, reduce, record, offset + rows, None, timing)  # fmt: skip
        t0 = time.perf_counter()
        sums, bins = rec.reduced
        moments.append(streamed_moments(StreamSums(*sums), plans.sweeps))
        transfers.append(transfer_finish(TransferSums(*bins), plans.transfers))
        timing["simulate_moments"] += time.perf_counter() - t0
        faults.append(rec.fault_step)
        mine = int(np.count_nonzero(offset + rows < keep))
        recordings += [
            _recording(sim, signal, rec_steps, rec.q[i], rec.dq[i], rec.current[i])
            for i in range(mine)
        ]
    return Simulated(
        stack_worlds(moments),
        _concat_worlds(transfers),
        recordings,
        np.concatenate(faults),
        timing,
        n_worlds * (steps + SETTLE_STEPS),
    )


def _concat_worlds(parts: list[TransferBins]) -> TransferBins:
    """Transfer bins of world batches (W_i, B_i, n) as one (W, B, n), padded to the most."""
    size = max(p.size for p in parts)
    padded = [padded_bins(p, size) for p in parts]
    return TransferBins(*(np.concatenate(a) for a in zip(*padded, strict=True)))


def fit_input_like(
    sim: MjxSimulator, signal: PlanSignal, every: int
) -> tuple[SweepMoments, TransferBins]:
    """One true robot's sweep moments and transfer bins as ``simulate`` returns them (from
    zero sums; in turn or side by side, the same sweeps in plan order and as many bins):
    their shapes and types, e.g. to compile the fits while the worlds still run.

    Args:
        sim: the MJX simulator (its joints and current lag).
        signal: the plan's signal.
        every: the recording decimation, steps.

    Returns:
        (``SweepMoments``, ``TransferBins``), with a leading world axis of 1, from zero sums.
    """
    plans = signal_plans(signal, every)
    sums, bins = plan_reduction([plans], sim.n, sim.current_lag).init
    return (
        streamed_moments(StreamSums(*(np.asarray(a)[None] for a in sums)), plans.sweeps),
        transfer_finish(TransferSums(*(np.asarray(a)[None] for a in bins)), plans.transfers),
    )


def _run(sim, truth, q_ref, start, seed, every, progress, width, steps, length, reduce, record,
         world_ids, group, timing, phase=None, noise_step=None):  # fmt: skip
    """One MJX run of ``simulate``, its timing added to ``timing`` (s: wall time,
    compilation, stepping) and its progress reported in plan steps of the worlds."""
    done = [0]

    def advance(k: int, _total: int) -> None:
        if progress is not None:
            now = int(k * width * steps / length)
            progress(now - done[0])
            done[0] = now

    compiled = sim.compile_seconds
    t0 = time.perf_counter()
    rec = sim.run(
        truth,
        q_ref,
        start,
        seed=seed,
        every=every,
        progress=advance,
        keep=len(record) > 0,
        group=group,
        reduce=reduce,
        record=record,
        world_ids=world_ids,
        phase=phase,
        noise_step=noise_step,
    )
    timing["simulate"] += time.perf_counter() - t0
    timing["simulate_compile"] += sim.compile_seconds - compiled
    timing["simulate_stepping"] += sim.last_timing["settle"] + sim.last_timing["plan"]
    return rec


def _recording(sim, signal, rec_steps, q, dq, current) -> Recording:
    """A kept world's ``Recording`` of ``signal``'s samples at ``rec_steps``."""
    return Recording(
        (rec_steps + 1) * CONTROL_PERIOD,
        q,
        dq,
        current,
        signal.joint[rec_steps],
        signal.direction[rec_steps],
        sim.robot.name,
        current_lag=sim.current_lag,
    )


def _simulate_parallel(
    sim: MjxSimulator,
    truth: BatchTruth,
    signal: PlanSignal,
    start: np.ndarray,
    seed: int,
    every: int,
    world_batch: int,
    keep: int,
    progress: Callable[[int], None] | None,
    timing: dict[str, float],
    offset: int,
) -> Simulated:
    """``simulate(parallel=True)``: world w of lane b (``pack_segments``) is MJX world
    b * B + w of a run; the sweeps come back in plan order."""
    layout = _Layout.of(signal, start, every, sim)
    seg, lanes, _, _, reduce = layout
    n_worlds, steps = truth.worlds, len(signal.q_ref)
    kept = min(max(keep - offset, 0), world_batch, n_worlds)
    moments, transfers, recordings, faults = [], [], [], []
    rec_steps = np.arange(0, steps, every)
    world_steps = 0
    for first in range(0, n_worlds, world_batch):
        rows = np.arange(first, min(first + world_batch, n_worlds))
        width, nk = len(rows), min(kept, len(rows))
        mine = int(np.count_nonzero(offset + rows < keep))
        length, n_lane = lanes.q_ref.shape[:2]
        record = (np.arange(n_lane)[:, None] * width + np.arange(nk)).ravel()
        rec = _run(sim, truth_rows(truth, np.tile(rows, n_lane)), lanes.q_ref,
                   np.repeat(lanes.start, width, axis=0), seed, every, progress, width, steps,
                   length, reduce, record, np.tile(offset + rows, n_lane),
                   np.repeat(np.arange(n_lane), width), timing, lanes.phase,
                   lanes.plan_step)  # fmt: skip
        world_steps += width * n_lane * (length + SETTLE_STEPS)
        t0 = time.perf_counter()
        m, tb = layout.sums(rec.reduced, width)
        moments.append(m)
        transfers.append(tb)
        timing["simulate_moments"] += time.perf_counter() - t0
        faults.append(_plan_fault(rec.fault_step.reshape(n_lane, width), lanes, seg.first))
        if mine:  # the kept worlds' samples of each segment, in plan order
            parts = []
            for k, b in enumerate(lanes.lane):
                plan_steps = rec_steps[(rec_steps >= seg.begin[k]) & (rec_steps < seg.end[k])]
                idx = (plan_steps - seg.first[k] + lanes.at[k]) // every
                parts.append(
                    tuple(a[b * nk : (b + 1) * nk][:, idx] for a in (rec.q, rec.dq, rec.current))
                )
            q, dq, cur = (np.concatenate(x, axis=1) for x in zip(*parts, strict=True))
            recordings += [
                _recording(sim, signal, rec_steps, q[i], dq[i], cur[i]) for i in range(mine)
            ]
    return Simulated(
        stack_worlds(moments),
        _concat_worlds(transfers),
        recordings,
        np.concatenate(faults),
        timing,
        world_steps,
    )


class _Layout(NamedTuple):
    """A plan's sweeps (each with its transfer) side by side: its segments, lanes, each lane's
    ``SignalPlans``, the order that puts the lanes' sweeps in plan order, and the
    ``Reduction``."""

    seg: Segments
    lanes: Lanes
    plans: list[SignalPlans]
    order: np.ndarray
    reduce: Reduction

    @classmethod
    def of(cls, signal: PlanSignal, start: np.ndarray, every: int, sim: MjxSimulator) -> "_Layout":
        seg = plan_segments(signal, start, every, True)
        lanes = pack_segments(seg, every, SETTLE_STEPS)
        plans = [signal_plans(s, every) for s in lanes.signals]
        keys = np.concatenate([_sweep_keys(s, every) for s in lanes.signals])
        reduce = plan_reduction(plans, sim.n, sim.current_lag)
        return cls(seg, lanes, plans, np.argsort(keys, kind="stable"), reduce)

    def sums(self, reduced: tuple, width: int) -> tuple[SweepMoments, TransferBins]:
        """The sweep moments, in plan order, and the transfer bins of ``width`` true robots
        from their lanes' sums ``reduced`` (lane b's robots at rows b * width ... (b + 1) *
        width - 1)."""
        sweeps, bins = reduced
        lane = [slice(b * width, (b + 1) * width) for b in range(len(self.plans))]
        per_lane = [
            streamed_moments(StreamSums(*(a[k] for a in sweeps)), p.sweeps)
            for k, p in zip(lane, self.plans, strict=True)
        ]
        moved = [
            transfer_finish(TransferSums(*(np.asarray(a)[k] for a in bins)), p.transfers)
            for k, p in zip(lane, self.plans, strict=True)
        ]
        return join_sweeps(per_lane, self.order), TransferBins(
            *(np.concatenate(a, axis=-2) for a in zip(*moved, strict=True))
        )


def _sweep_keys(signal: PlanSignal, every: int) -> np.ndarray:
    """The plan sweep of each sweep that ``stream_plan`` finds in ``signal`` recorded every
    ``every`` steps, in its order."""
    rec = np.arange(0, len(signal.joint), every)
    lay = layout(signal.joint[rec], signal.direction[rec])
    return signal.sweep[rec][lay.first[:, 0]]


def _plan_fault(local: np.ndarray, lanes: Lanes, first: np.ndarray) -> np.ndarray:
    """(W,) each world's first fault as a plan step (-1: none) from its lanes' first faults
    ``local`` (B, W) in lane steps; segment k runs in lane ``lanes.lane[k]`` from lane step
    ``lanes.at[k]`` as plan step ``first[k]`` (a lane's segments are in plan order)."""
    plan = np.full(local.shape, np.iinfo(np.int64).max)
    for b in range(local.shape[0]):
        ks = np.flatnonzero(lanes.lane == b)
        ks = ks[np.argsort(lanes.at[ks])]
        k = ks[np.maximum(np.searchsorted(lanes.at[ks], local[b], "right") - 1, 0)]
        plan[b] = np.where(local[b] >= 0, local[b] - lanes.at[k] + first[k], plan[b])
    at = plan.min(axis=0)
    return np.where(at < np.iinfo(np.int64).max, at, -1)
