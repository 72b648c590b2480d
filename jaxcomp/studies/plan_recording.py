"""A calibration plan recorded in every world of a ``BatchTruth`` on MJX, each sweep reduced to
its moments on the device while the worlds run.

The simulator steps at 1 kHz and every ``every``-th state (default 10: 100 Hz) is added to its
sweep's running sums inside the compiled loop (``MjxSimulator.run(reduce=)`` with
``identify.moments.stream_add``; the steady samples are chosen from the plan's commanded speed,
``identify.moments.stream_plan``), so that only each world's small sums come back to the host:
host memory does not grow with the plan's length, and only the first ``keep`` worlds' samples
leave the device (for the scipy fit). The current noise is the simulator's, drawn on the device
from ``fold_in(fold_in(PRNGKey(seed), id), step)`` with ``id`` the world's index in the study
and ``step`` the plan step (in whichever lane a sweep runs side by side), so a world's numbers
depend neither on how worlds are batched, on the number of devices, nor on whether the
transfers between sweeps are simulated.

Units: SI (rad, rad/s, A, s).
"""

import functools
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.hardware.mjx import SETTLE_STEPS, BatchTruth, MjxSimulator, Reduction
from jaxcomp.identify.bins import STEADY_FRACTION
from jaxcomp.identify.moments import (
    StreamPlan,
    StreamSums,
    SweepMoments,
    join_sweeps,
    layout,
    stack_worlds,
    stream_add,
    stream_init,
    stream_plan,
    streamed_moments,
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


def signal_stream_plan(signal: PlanSignal, every: int) -> StreamPlan:
    """The ``StreamPlan`` of the samples of ``signal`` recorded every ``every`` steps (sample
    i: the state after plan step i every, commanded q_ref there, at the commanded velocity of
    that step)."""
    rec = np.arange(0, len(signal.joint), every)
    q = signal.q_ref
    velocity = np.diff(q, axis=0, prepend=q[:1]) / CONTROL_PERIOD
    joint = signal.joint[rec]
    speed = velocity[rec, np.maximum(joint, 0)]
    return stream_plan((rec + 1) * CONTROL_PERIOD, q[rec], speed, joint, signal.direction[rec])


def sweep_reduction(plans: list[StreamPlan], n: int, current_lag: float) -> Reduction:
    """The ``Reduction`` that sums each world's sweep moments on the device: world w follows
    ``plans[group[w]]`` (padded to the longest, with samples outside any sweep)."""
    rows = max(len(p.slot) for p in plans)
    sweeps = max(p.sweep_joint.size for p in plans)

    def padded(p: StreamPlan) -> tuple[np.ndarray, ...]:
        extra = rows - len(p.slot)
        pad = [np.full(extra, -1), *(np.zeros((extra, *a.shape[1:])) for a in p.rows()[1:])]
        return tuple(
            np.concatenate([a, b.astype(a.dtype)]) for a, b in zip(p.rows(), pad, strict=True)
        )

    xs = tuple(np.stack(a, axis=1) for a in zip(*map(padded, plans), strict=True))
    step = functools.partial(stream_add, fraction=STEADY_FRACTION, current_lag=current_lag)
    return Reduction(step, stream_init(sweeps, n), xs, ("sweep-moments", float(current_lag)))


class Simulated(NamedTuple):
    """What the simulation stage returns: ``moments`` (stacked SweepMoments, leading axis
    N), ``recordings`` of the first M worlds, ``fault_step`` (N,) (-1: none), ``timing`` s
    (wall, compilation, stepping without compilation, turning the device's sums into
    moments), ``world_steps`` simulated (settling included)."""

    moments: SweepMoments
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
    fills an accelerator that a few thousand worlds leave idle. Only batches with a world that
    keeps its recording simulate the transfers between sweeps (with faults not counted there,
    so that the other batches' worlds, which skip them, have the same numbers).
    """
    n_worlds, steps = truth.worlds, len(signal.q_ref)
    start = start_pose(sim.robot)
    keys = ("simulate", "simulate_compile", "simulate_stepping", "simulate_moments")
    timing = dict.fromkeys(keys, 0.0)
    if parallel:
        return _simulate_parallel(
            sim, truth, signal, start, seed, every, world_batch, keep, progress, timing, offset
        )
    plan = signal_stream_plan(signal, every)
    reduce = sweep_reduction([plan], sim.n, sim.current_lag)
    kept = min(max(keep - offset, 0), world_batch, n_worlds)  # the same in every run
    moments, recordings, faults = [], [], []
    rec_steps = np.arange(0, steps, every)
    for first in range(0, n_worlds, world_batch):
        rows = np.arange(first, min(first + world_batch, n_worlds))
        width = len(rows)
        record = np.arange(min(kept, width))
        rec = _run(sim, truth_rows(truth, rows), signal.q_ref, start, seed, every, progress,
                   width, steps, steps, reduce, record, offset + rows, None, timing)  # fmt: skip
        t0 = time.perf_counter()
        moments.append(streamed_moments(StreamSums(*rec.reduced), plan))
        timing["simulate_moments"] += time.perf_counter() - t0
        faults.append(rec.fault_step)
        mine = int(np.count_nonzero(offset + rows < keep))
        recordings += [
            _recording(sim, signal, rec_steps, rec.q[i], rec.dq[i], rec.current[i])
            for i in range(mine)
        ]
    return Simulated(
        stack_worlds(moments),
        recordings,
        np.concatenate(faults),
        timing,
        n_worlds * (steps + SETTLE_STEPS),
    )


def moments_like(sim: MjxSimulator, signal: PlanSignal, every: int) -> SweepMoments:
    """One true robot's sweep moments as ``simulate`` returns them (from zero sums; in turn
    or side by side, the same sweeps in plan order): their shapes and types, e.g. to compile
    the fits while the worlds still run."""
    plan = signal_stream_plan(signal, every)
    init = sweep_reduction([plan], sim.n, sim.current_lag).init
    return streamed_moments(StreamSums(*(np.asarray(a)[None] for a in init)), plan)


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
    layouts = {}  # with and without the transfers between sweeps
    n_worlds, steps = truth.worlds, len(signal.q_ref)
    kept = min(max(keep - offset, 0), world_batch, n_worlds)
    moments, recordings, faults = [], [], []
    rec_steps = np.arange(0, steps, every)
    world_steps = 0
    for first in range(0, n_worlds, world_batch):
        rows = np.arange(first, min(first + world_batch, n_worlds))
        width, nk = len(rows), min(kept, len(rows))
        mine = int(np.count_nonzero(offset + rows < keep))
        if (mine > 0) not in layouts:
            layouts[mine > 0] = _Layout.of(signal, start, every, mine > 0, sim)
        seg, lanes, _, _, reduce = layouts[mine > 0]
        length, n_lane = lanes.q_ref.shape[:2]
        record = (np.arange(n_lane)[:, None] * width + np.arange(nk)).ravel()
        rec = _run(sim, truth_rows(truth, np.tile(rows, n_lane)), lanes.q_ref,
                   np.repeat(lanes.start, width, axis=0), seed, every, progress, width, steps,
                   length, reduce, record, np.tile(offset + rows, n_lane),
                   np.repeat(np.arange(n_lane), width), timing, lanes.phase,
                   lanes.plan_step)  # fmt: skip
        world_steps += width * n_lane * (length + SETTLE_STEPS)
        t0 = time.perf_counter()
        moments.append(layouts[mine > 0].moments(StreamSums(*rec.reduced), width))
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
    return Simulated(stack_worlds(moments), recordings, np.concatenate(faults), timing, world_steps)


class _Layout(NamedTuple):
    """A plan's sweeps side by side: its segments, lanes, each lane's ``StreamPlan``, the
    order that puts the lanes' sweeps in plan order, and the sweep-moment ``Reduction``."""

    seg: Segments
    lanes: Lanes
    plans: list[StreamPlan]
    order: np.ndarray
    reduce: Reduction

    @classmethod
    def of(cls, signal: PlanSignal, start: np.ndarray, every: int, transfers: bool,
           sim: MjxSimulator) -> "_Layout":  # fmt: skip
        seg = plan_segments(signal, start, every, transfers)
        lanes = pack_segments(seg, every, SETTLE_STEPS)
        plans = [signal_stream_plan(s, every) for s in lanes.signals]
        keys = np.concatenate([_sweep_keys(s, every) for s in lanes.signals])
        reduce = sweep_reduction(plans, sim.n, sim.current_lag)
        return cls(seg, lanes, plans, np.argsort(keys, kind="stable"), reduce)

    def moments(self, sums: StreamSums, width: int) -> SweepMoments:
        """The sweep moments, in plan order, of ``width`` true robots from their lanes'
        ``sums`` (lane b's robots at rows b * width ... (b + 1) * width - 1)."""
        per_lane = [
            streamed_moments(StreamSums(*(a[b * width : (b + 1) * width] for a in sums)), p)
            for b, p in enumerate(self.plans)
        ]
        return join_sweeps(per_lane, self.order)


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
