"""A calibration plan recorded in every world of a ``BatchTruth`` on MJX, each sweep reduced to
its moments as soon as its samples are in.

The simulator steps at 1 kHz and every ``every``-th state (default 10: 100 Hz) is streamed to
the host (``MjxSimulator.run(every=, on_chunk=)``), where each sweep is reduced to its moments
(``identify.moments.sweep_moments_batch``): host memory stays bounded by one sweep of all
worlds; only the first ``keep`` worlds keep their whole recording. With the sweeps side by side
(``simulate(parallel=True)``) every sweep is in flight at once, so the host holds about the
whole recording of the worlds of a run. The current noise of the truth is added on the host to
the recorded samples, from a stream per world (``SeedSequence([seed, NOISE_STREAM, world])``):
the same model as the simulator's (additive Gaussian, never fed back in POSITION mode), but a
world's numbers then depend neither on how worlds are batched nor on the number of devices.

Units: SI (rad, rad/s, A, s).
"""

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import SETTLE_STEPS, BatchTruth, MjxRecording, MjxSimulator
from jaxcomp.identify.moments import (
    SweepMoments,
    concat_moments,
    stack_worlds,
    sweep_moments_batch,
)
from jaxcomp.recording import Recording
from jaxcomp.studies.plan_signal import PlanSignal, plan_segments, start_pose
from jaxcomp.studies.truth_draw import truth_rows

#: Seed stream of the current noise: SeedSequence([seed, NOISE_STREAM, world(, segment)]).
NOISE_STREAM = 2


class SweepStream:
    """``on_chunk`` of an MJX run of worlds [first, first + W): adds each world's current
    noise, reduces every sweep to moments once its samples are in, keeps the whole recording
    of the worlds below ``keep`` (global index)."""

    def __init__(
        self,
        signal: PlanSignal,
        every: int,
        first: int,
        noise: np.ndarray,
        seed: int,
        keep: int,
        segment: int | None = None,
        current_lag: float = 0.0,
    ):
        """``segment``: the plan segment k these worlds run (``plan_signal.Segments``); their
        noise then comes from ``SeedSequence([seed, NOISE_STREAM, world, k])``.
        ``current_lag``: s, the simulator's (``MjxSimulator.current_lag``)."""
        self.current_lag = float(current_lag)
        rec = np.arange(0, len(signal.joint), every)  # plan steps recorded
        self.t = (rec + 1) * CONTROL_PERIOD  # sample i is the state after plan step i
        self.joint, self.direction = signal.joint[rec], signal.direction[rec]
        sweep = signal.sweep[rec]
        self.ends = np.flatnonzero(np.r_[sweep[1:] != sweep[:-1], True]) + 1  # segment ends
        self.noise = np.asarray(noise, float)
        tail = [] if segment is None else [segment]
        self.gens = [
            np.random.default_rng([seed, NOISE_STREAM, first + i, *tail]) for i in range(len(noise))
        ]
        self.keep = max(0, min(keep - first, len(noise)))
        self.kept: list[tuple[np.ndarray, ...]] = []
        self.buffer: list[tuple[np.ndarray, ...]] = []
        self.start = 0  # recorded index of the buffer's first sample
        self.parts: list[SweepMoments] = []
        self.seconds = 0.0  # host time spent here

    def __call__(self, first: int, chunk: MjxRecording) -> None:
        t0 = time.perf_counter()
        current = np.array(chunk.current, float)
        for i, g in enumerate(self.gens):
            current[i] += self.noise[i] * g.standard_normal(current[i].shape)
        arrays = (np.asarray(chunk.q, float), np.asarray(chunk.dq, float), current)
        if self.keep:
            self.kept.append(tuple(a[: self.keep] for a in arrays))
        self.buffer.append(arrays)
        received = first + current.shape[1]
        done = len(self.parts)
        while done < len(self.ends) and self.ends[done] <= received:
            a = self.ends[done - 1] if done else 0
            b = self.ends[done]
            q, dq, cur = (np.concatenate(x, axis=1) for x in zip(*self.buffer, strict=True))
            seg = slice(a - self.start, b - self.start)
            self.parts.append(
                sweep_moments_batch(
                    self.t[a:b],
                    q[:, seg],
                    dq[:, seg],
                    cur[:, seg],
                    self.joint[a:b],
                    self.direction[a:b],
                    current_lag=self.current_lag,
                )
            )
            rest = slice(b - self.start, None)
            self.buffer, self.start = [(q[:, rest], dq[:, rest], cur[:, rest])], b
            done += 1
        self.seconds += time.perf_counter() - t0

    def kept_arrays(self) -> tuple[np.ndarray, ...]:
        """q, dq, current (M, R, n) of the kept worlds, every sample received."""
        return tuple(np.concatenate(x, axis=1) for x in zip(*self.kept, strict=True))

    def recordings(self, model: str) -> list[Recording]:
        """The kept worlds' ``Recording`` (100 Hz with the default ``every``)."""
        if not self.keep:
            return []
        q, dq, cur = self.kept_arrays()
        return [
            Recording(
                self.t,
                q[i],
                dq[i],
                cur[i],
                self.joint,
                self.direction,
                model,
                current_lag=self.current_lag,
            )
            for i in range(self.keep)
        ]


class Simulated(NamedTuple):
    """What the simulation stage returns: ``moments`` (stacked SweepMoments, leading axis
    N), ``recordings`` of the first M worlds, ``fault_step`` (N,) (-1: none), ``timing`` s
    (wall, compilation, stepping without compilation, host time reducing moments: it overlaps
    the stepping), ``world_steps`` simulated (settling included)."""

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
    plan come first): the world index of the noise streams, and of ``keep`` (the worlds
    below it keep their recordings).

    ``parallel``: run the plan's K sweeps side by side (``plan_segments``), K MJX worlds per
    true robot, each starting at rest where the sweep before it ends: K times the worlds for
    about 1/K of the steps, which fills an accelerator that a few thousand worlds leave idle.
    """
    n_worlds, steps = truth.worlds, len(signal.q_ref)
    quiet = dataclasses.replace(truth, current_noise=np.zeros(n_worlds))
    start = start_pose(sim.robot)
    moments, recordings, faults = [], [], []
    keys = ("simulate", "simulate_compile", "simulate_stepping", "simulate_moments_host")
    timing = dict.fromkeys(keys, 0.0)
    if parallel:
        return _simulate_parallel(
            sim,
            quiet,
            truth.current_noise,
            signal,
            start,
            seed,
            every,
            world_batch,
            keep,
            progress,
            timing,
            offset,
        )
    for first in range(0, n_worlds, world_batch):
        rows = slice(first, min(first + world_batch, n_worlds))
        noise = truth.current_noise[rows]
        stream = SweepStream(
            signal, every, offset + first, noise, seed, keep, current_lag=sim.current_lag
        )
        done = [0]
        width = rows.stop - rows.start

        def advance(k: int, _total: int, done=done, width=width) -> None:
            if progress is not None:
                progress((k - done[0]) * width)
            done[0] = k

        compiled = sim.compile_seconds
        t0 = time.perf_counter()
        rec = sim.run(
            truth_rows(quiet, rows),
            signal.q_ref,
            start,
            seed=seed,
            every=every,
            progress=advance,
            on_chunk=stream,
            keep=False,
        )
        _add_run_timing(timing, sim, t0, compiled, stream.seconds)
        if len(stream.parts) != len(stream.ends):
            raise InputError("the simulation stopped before the plan's last sweep")
        moments.append(concat_moments(stream.parts))
        recordings += stream.recordings(sim.robot.name)
        faults.append(rec.fault_step)
    stacked = stack_worlds(moments)
    return Simulated(
        stacked, recordings, np.concatenate(faults), timing, n_worlds * (steps + SETTLE_STEPS)
    )


def _add_run_timing(
    timing: dict[str, float], sim: MjxSimulator, t0: float, compiled: float, host: float
) -> None:
    """Add one MJX run of ``simulate`` to ``timing`` (s): wall time since ``t0``, compilation
    (``sim.compile_seconds`` was ``compiled`` before), stepping, host moment reduction."""
    timing["simulate"] += time.perf_counter() - t0
    timing["simulate_compile"] += sim.compile_seconds - compiled
    timing["simulate_stepping"] += sim.last_timing["settle"] + sim.last_timing["plan"]
    timing["simulate_moments_host"] += host


def _simulate_parallel(
    sim: MjxSimulator,
    quiet: BatchTruth,
    noise: np.ndarray,
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
    """``simulate(parallel=True)``: world w of segment k is MJX world k * B + w of a run."""
    seg = plan_segments(signal, start, every)
    n_worlds, steps, (length, n_seg, _) = quiet.worlds, len(signal.q_ref), seg.q_ref.shape
    moments, recordings, faults = [], [], []
    rec_steps = np.arange(0, steps, every)
    world_steps = 0
    for first in range(0, n_worlds, world_batch):
        rows = np.arange(first, min(first + world_batch, n_worlds))
        width = len(rows)
        streams = [
            SweepStream(
                seg.signals[k],
                every,
                offset + first,
                noise[rows],
                seed,
                keep,
                segment=k,
                current_lag=sim.current_lag,
            )
            for k in range(n_seg)
        ]
        done = [0]

        def advance(k: int, _total: int, done=done, width=width) -> None:
            if progress is not None:  # in plan steps of the worlds, as the sequential run
                now = int(k * width * steps / length)
                progress(now - done[0])
                done[0] = now

        def route(first_sample: int, chunk: MjxRecording, streams=streams, width=width) -> None:
            for k, stream in enumerate(streams):
                part = slice(k * width, (k + 1) * width)
                stream(
                    first_sample,
                    chunk._replace(q=chunk.q[part], dq=chunk.dq[part], current=chunk.current[part]),
                )

        compiled = sim.compile_seconds
        t0 = time.perf_counter()
        rec = sim.run(
            truth_rows(quiet, np.tile(rows, n_seg)),
            seg.q_ref,
            np.repeat(seg.start, width, axis=0),
            seed=seed,
            every=every,
            progress=advance,
            on_chunk=route,
            keep=False,
            group=np.repeat(np.arange(n_seg), width),
        )
        _add_run_timing(timing, sim, t0, compiled, sum(st.seconds for st in streams))
        world_steps += width * n_seg * (length + SETTLE_STEPS)
        if any(len(st.parts) != len(st.ends) for st in streams):
            raise InputError("the simulation stopped before the plan's last sweep")
        moments.append(concat_moments([p for st in streams for p in st.parts]))
        local = rec.fault_step.reshape(n_seg, width)
        at = np.where(local >= 0, local + seg.first[:, None], np.iinfo(np.int64).max)
        faults.append(np.where((local >= 0).any(axis=0), at.min(axis=0), -1))
        if streams[0].keep:  # the kept worlds' samples of each segment, in plan order
            parts = []
            for k, st in enumerate(streams):
                idx = (
                    rec_steps[(rec_steps >= seg.begin[k]) & (rec_steps < seg.end[k])] - seg.first[k]
                ) // every
                parts.append(tuple(a[:, idx] for a in st.kept_arrays()))
            q, dq, cur = (np.concatenate(x, axis=1) for x in zip(*parts, strict=True))
            recordings += [
                Recording(
                    (rec_steps + 1) * CONTROL_PERIOD,
                    q[i],
                    dq[i],
                    cur[i],
                    signal.joint[rec_steps],
                    signal.direction[rec_steps],
                    sim.robot.name,
                    current_lag=sim.current_lag,
                )
                for i in range(streams[0].keep)
            ]
    return Simulated(stack_worlds(moments), recordings, np.concatenate(faults), timing, world_steps)
