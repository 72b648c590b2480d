"""`jaxcomp study calibration`: how well calibration finds thousands of simulated true robots.

N true Gen3 Lite arms are drawn from the seed (``draw_truth``: ratios 20-30 % off nominal,
friction torques 20-30 % off the paper's, COM offsets of a few mm on every moving link, current
noise, optional viscous friction); the calibration plan (default:
``identify.plan.default_plan``, the paper's ~230 s of sweeps) is recorded in every world at once
on MJX (``MjxSimulator``, 1 kHz, float64, worlds sharded over the accelerators), every world is
fitted with the joint JAX fit in vmapped batches on the accelerator (``jax_fit.fit_batch``) and
the first M worlds also with the paper's scipy fit (``identify.baseline``). The report compares
estimates with the truth.

Recording: the simulator steps at 1 kHz and every ``every``-th state (default 10: 100 Hz) is
streamed to the host (``MjxSimulator.run(every=, on_chunk=)``), where each sweep is reduced to
its moments (``identify.moments.sweep_moments_batch``) as soon as its samples are in: host
memory stays bounded by one sweep of all worlds; only the M baseline worlds keep their whole
recording. With the sweeps side by side (``simulate(parallel=True)``, the default on an
accelerator) every sweep is in flight at once, so the host holds about the whole recording of
the worlds of a run (4096 worlds of the default plan at 100 Hz: ~35 GB; ``--world-batch``
bounds it). The current noise of the truth is added on the host to the recorded samples, from a
stream per world (``SeedSequence([seed, 2, world])``): the same model as the simulator's
(additive Gaussian, never fed back in POSITION mode), but a world's numbers then depend neither
on how worlds are batched nor on the number of devices. Truth draws are per world too: world w
is the same for every N > w. Worlds that fault (following error, overspeed, joint limit: what
stops the CPU simulator and the real arm) are counted and left out of the statistics.

Units: SI (rad, A, N m, m, s); COM offsets in each link's own frame; ratio A/(N m); viscous
friction of the truth N m s/rad, the fit's viscous term A s/rad (= ratio x viscous).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import click
import numpy as np

from jaxcomp.cli.study import MODEL, check_out_dir, simulator, study
from jaxcomp.errors import InputError

STUDY_FILE = "study.json"
WORLDS_FILE = "worlds.npz"
FIGURES = ("errors.png", "coverage.png")
FORMAT = "jaxcomp-study-calibration"
#: Plan names of ``--plan`` (else a plan JSON file).
PLANS = ("default", "short")
#: Seed streams: SeedSequence([seed, stream, ...]).
_TRUTH_STREAM, _NOISE_STREAM = 1, 2
#: Recorded direction of each kind of move of ``CalibrationPlan.moves`` (as identify.recorder).
#: |error| < _Z95 std holds 95 % of the time when the reported std are right.
_Z95 = 1.96


# ----------------------------------------------------------------------------- truths
@dataclasses.dataclass(frozen=True)
class TruthSpread:
    """How the true robots differ from the nominal model.

    Attributes:
        model_error: (lo, hi): each actuator type's current/torque ratio is off its nominal
            (Kinova's) by a factor 1 +- U(lo, hi), random sign; each joint's Coulomb friction
            torque off the paper's (``PAPER_FRICTION / PAPER_RATIO``) by 1 +- U(lo, hi), the
            sign turned to - where + would leave less than ``headroom`` of the effort limit
            (the friction loss in A is then ratio x torque).
        type_spread: ratios of one actuator type differ by a further U(-s, s) (relative).
        com_offset: m, COM offsets U(-c, c) per axis of every moving link (link frame).
        noise: A, standard deviation of the current noise, every world.
        viscous: N m s/rad, viscous friction U(0, v) per joint (0: none).
        headroom: fraction of each joint's effort limit left free of friction: the default
            plan lets gravity use 60 % of it, and a robot whose friction takes the rest cannot
            follow its sweeps (joint 1 of the paper's arm already spends 34 % on friction).
    """

    model_error: tuple[float, float] = (0.2, 0.3)
    type_spread: float = 0.03
    com_offset: float = 0.004
    noise: float = 0.05
    viscous: float = 0.0
    headroom: float = 0.65

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.model_error)
        if not 0 <= lo <= hi < 1:
            raise InputError(f"--model-error must satisfy 0 <= LO <= HI < 1, got ({lo}, {hi})")
        for name in ("type_spread", "com_offset", "noise", "viscous", "headroom"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number >= 0")
        if self.type_spread >= 1 or self.headroom >= 1:
            raise InputError("type spread and headroom must be < 1")


def draw_truth(robot: Any, worlds: int, seed: int, spread: TruthSpread) -> Any:
    """``BatchTruth`` of ``worlds`` true robots drawn from ``seed`` (see ``TruthSpread``).

    Each quantity has its own stream and world w is row w of it, so world w is the same for
    any ``worlds`` > w. Friction torques scale the paper's for a 6-joint arm, else 0.1 N m.
    Payload 0, gravity the model's (upright).
    """
    from jaxcomp.hardware import PAPER_FRICTION, PAPER_RATIO
    from jaxcomp.hardware.mjx_sim import BatchTruth
    from jaxcomp.identify.jax_fit import fit_model
    from jaxcomp.robot_params import RobotParams

    model = fit_model(robot)
    n, nb = model.n, len(robot.link_names)
    types = sorted(set(model.types))
    type_of = np.array([types.index(t) for t in model.types])

    def rng(k: int) -> np.random.Generator:
        return np.random.default_rng([seed, _TRUTH_STREAM, k])

    def off(k: int, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:  # U(lo, hi), sign
        return rng(k).uniform(*spread.model_error, shape), np.where(
            rng(k + 1).random(shape) < 0.5, -1.0, 1.0
        )

    ratio0 = RobotParams.nominal(robot).ratio
    mag, sign = off(0, (worlds, len(types)))
    ratio = ratio0 * (1 + sign * mag)[:, type_of]
    ratio *= 1 + rng(2).uniform(-1, 1, (worlds, n)) * spread.type_spread
    paper = np.asarray(PAPER_FRICTION) / np.asarray(PAPER_RATIO)
    torque0 = paper if n == len(paper) else np.full(n, 0.1)
    mag, sign = off(3, (worlds, n))
    effort = np.abs(robot.model.jnt_actfrcrange).max(axis=1)[model.joints]  # N m
    sign = np.where(torque0 * (1 + mag) > (1 - spread.headroom) * effort, -1.0, sign)
    friction = ratio * torque0 * (1 + sign * mag)
    moved = np.zeros(nb, bool)
    moved[model.link_ids] = True
    com = rng(5).uniform(-1, 1, (worlds, nb, 3)) * spread.com_offset * moved[None, :, None]
    viscous = rng(6).uniform(0, 1, (worlds, n)) * spread.viscous
    return BatchTruth.from_arrays(
        robot, ratio, friction, com_offset=com, current_noise=spread.noise, viscous=viscous
    )


def _truth_rows(truth: Any, rows: slice | np.ndarray) -> Any:
    """The worlds ``rows`` of a ``BatchTruth``."""
    return type(truth)(**{f.name: getattr(truth, f.name)[rows] for f in dataclasses.fields(truth)})


# ----------------------------------------------------------------------------- plans
def short_plan(robot: Any) -> Any:
    """A quick plan for CPU runs and CI (~26 s instead of ~230 s for the Gen3 Lite): one sweep
    per joint over -40..+40 deg at 60 deg/s (the default plan's held-pose search), transfers
    at 90 deg/s, 0.2 s settling. One speed per joint: the fit holds viscous friction at 0."""
    from jaxcomp.identify.plan_design import default_plan

    return default_plan(
        robot,
        sweeps_per_joint=1,
        lower=math.radians(-40),
        upper=math.radians(40),
        speed=math.radians(60),
        slow_speed=None,
        move_speed=math.radians(90),
        settle=0.2,
        min_span=math.radians(60),
    )


def load_study_plan(robot: Any, plan: str) -> Any:
    """``plan``: "default" (the paper's, ``default_plan``), "short" or a plan JSON file."""
    from jaxcomp.identify.plan import load_plan
    from jaxcomp.identify.plan_design import default_plan

    if plan == "default":
        return default_plan(robot)
    if plan == "short":
        return short_plan(robot)
    return load_plan(plan, robot)


class PlanSignal(NamedTuple):
    """A calibration plan as the 1 kHz signals an MJX run follows and records (T steps).

    q_ref (T, n) rad: what ``Arm.move_to`` sends for the plan's moves; joint (T,): swept joint
    (-1 outside sweeps); direction (T,): +1 / -1 (0 outside sweeps), as ``identify.recorder``
    labels them; sweep (T,): index of the plan sweep (its transfer included) of each step.
    """

    q_ref: np.ndarray
    joint: np.ndarray
    direction: np.ndarray
    sweep: np.ndarray


def plan_signal(plan: Any, start: np.ndarray) -> PlanSignal:
    """The ``PlanSignal`` of ``plan`` from the pose ``start`` (n,) rad."""
    from jaxcomp.hardware.mjx_sim import Move, reference_trajectory
    from jaxcomp.identify.recorder import MOVE_DIRECTION

    pos = np.asarray(start, float)
    parts, labels = [], []
    for i, kind, target, speed, accel, settle in plan.moves():
        ref = reference_trajectory([Move(target, speed, accel, settle)], pos)
        if len(ref):
            pos = ref[-1].copy()
            d = MOVE_DIRECTION[kind]
            parts.append(ref)
            labels.append(np.tile([plan.sweeps[i].joint if d else -1, d, i], (len(ref), 1)))
    lab = np.concatenate(labels)
    return PlanSignal(np.concatenate(parts), lab[:, 0], lab[:, 1], lab[:, 2])


class Segments(NamedTuple):
    """A ``PlanSignal`` cut into K segments, one a plan sweep (its passes up and down, then the
    transfer to the next sweep's start and the settling there; segment 0 also holds the
    transfer from the plan's start), to be simulated side by side as separate worlds
    (``simulate(parallel=True)``).

    Segment k starts at rest at ``start[k]`` (n,) rad (where segment k - 1 has settled; the
    plan's start pose for k = 0) at plan step ``first[k]``, a multiple of the recording
    decimation at or up to ``every`` - 1 steps before its sweep's first step ``begin[k]``,
    and ends at step ``end[k]``. ``q_ref`` (L, K, n) rad: the references side by side, each
    held at its last pose up to the longest length L; ``signals``: each segment's
    ``PlanSignal`` (steps first[k] .. end[k]; the steps before begin[k], the end of segment
    k - 1, are labelled outside sweeps).
    """

    q_ref: np.ndarray
    start: np.ndarray
    first: np.ndarray
    begin: np.ndarray
    end: np.ndarray
    signals: list[PlanSignal]


def plan_segments(signal: PlanSignal, start: np.ndarray, every: int) -> Segments:
    """``Segments`` of ``signal`` (from the pose ``start`` (n,) rad), aligned to ``every``."""
    d = signal.direction
    cuts = (np.flatnonzero((d[1:] != 0) & (d[:-1] == 0)) + 1)[1:]  # the sweeps' first steps
    begin = np.r_[0, cuts]
    end = np.r_[cuts, len(signal.sweep)]
    first = begin - begin % every
    for f, a in zip(first[1:], begin[1:], strict=True):
        if np.ptp(signal.q_ref[f - 1 : a], axis=0).max() > 0:
            raise InputError("a plan sweep does not start at rest: sweeps cannot run in parallel")
    length = int((end - first).max())
    q_ref = np.empty((length, len(begin), signal.q_ref.shape[1]))
    starts, signals = [], []
    for k, (a, b, f) in enumerate(zip(begin, end, first, strict=True)):
        ref = signal.q_ref[f:b]
        q_ref[:, k] = np.concatenate([ref, np.repeat(ref[-1:], length - len(ref), axis=0)])
        starts.append(np.asarray(start, float) if f == 0 else signal.q_ref[f - 1])
        outside = np.arange(f, b) < a  # the tail of segment k - 1
        signals.append(
            PlanSignal(
                ref,
                np.where(outside, -1, signal.joint[f:b]),
                np.where(outside, 0, signal.direction[f:b]),
                np.full(b - f, k),
            )
        )
    return Segments(q_ref, np.array(starts), first, begin, end, signals)


# ----------------------------------------------------------------------------- recording
class _Stream:
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
    ):
        """``segment``: the plan segment k these worlds run (``Segments``); their noise then
        comes from ``SeedSequence([seed, stream, world, k])``."""
        from jaxcomp.hardware.interface import DT

        rec = np.arange(0, len(signal.joint), every)  # plan steps recorded
        self.t = (rec + 1) * DT  # sample i is the state after plan step i
        self.joint, self.direction = signal.joint[rec], signal.direction[rec]
        sweep = signal.sweep[rec]
        self.ends = np.flatnonzero(np.r_[sweep[1:] != sweep[:-1], True]) + 1  # segment ends
        self.noise = np.asarray(noise, float)
        tail = [] if segment is None else [segment]
        self.gens = [
            np.random.default_rng([seed, _NOISE_STREAM, first + i, *tail])
            for i in range(len(noise))
        ]
        self.keep = max(0, min(keep - first, len(noise)))
        self.kept: list[tuple[np.ndarray, ...]] = []
        self.buffer: list[tuple[np.ndarray, ...]] = []
        self.start = 0  # recorded index of the buffer's first sample
        self.parts: list[Any] = []
        self.seconds = 0.0  # host time spent here

    def __call__(self, first: int, chunk: Any) -> None:
        from jaxcomp.identify.moments import sweep_moments_batch

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
                )
            )
            rest = slice(b - self.start, None)
            self.buffer, self.start = [(q[:, rest], dq[:, rest], cur[:, rest])], b
            done += 1
        self.seconds += time.perf_counter() - t0

    def kept_arrays(self) -> tuple[np.ndarray, ...]:
        """q, dq, current (M, R, n) of the kept worlds, every sample received."""
        return tuple(np.concatenate(x, axis=1) for x in zip(*self.kept, strict=True))

    def recordings(self, model: str) -> list[Any]:
        """The kept worlds' ``Recording`` (100 Hz with the default ``every``)."""
        from jaxcomp.recording import Recording

        if not self.keep:
            return []
        q, dq, cur = self.kept_arrays()
        return [
            Recording(self.t, q[i], dq[i], cur[i], self.joint, self.direction, model)
            for i in range(self.keep)
        ]


class Simulated(NamedTuple):
    """What the simulation stage returns: ``moments`` (stacked SweepMoments, leading axis
    N), ``recordings`` of the first M worlds, ``fault_step`` (N,) (-1: none), ``timing`` s
    (wall, compilation, stepping without compilation, host time reducing moments: it overlaps
    the stepping), ``world_steps`` simulated (settling included)."""

    moments: Any
    recordings: list
    fault_step: np.ndarray
    timing: dict[str, float]
    world_steps: int


def simulate(
    sim: Any,
    truth: Any,
    signal: PlanSignal,
    *,
    seed: int,
    every: int,
    world_batch: int,
    keep: int,
    progress: Callable[[int], None] | None = None,
    parallel: bool = False,
) -> Simulated:
    """Record ``signal`` in every world of ``truth`` on the ``MjxSimulator`` ``sim``,
    ``world_batch`` worlds per run; see the module docstring for noise and streaming.

    ``parallel``: run the plan's K sweeps side by side (``plan_segments``), K MJX worlds per
    true robot, each starting at rest where the sweep before it ends: K times the worlds for
    about 1/K of the steps, which fills an accelerator that a few thousand worlds leave idle.
    """
    from jaxcomp.hardware.mjx_sim import SETTLE_STEPS
    from jaxcomp.identify.moments import concat_moments, stack_worlds

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
        )
    for first in range(0, n_worlds, world_batch):
        rows = slice(first, min(first + world_batch, n_worlds))
        stream = _Stream(signal, every, first, truth.current_noise[rows], seed, keep)
        done = [0]
        width = rows.stop - rows.start

        def advance(k: int, _total: int, done=done, width=width) -> None:
            if progress is not None:
                progress((k - done[0]) * width)
            done[0] = k

        compiled = sim.compile_seconds
        t0 = time.perf_counter()
        rec = sim.run(
            _truth_rows(quiet, rows),
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


def _add_run_timing(timing: dict, sim: Any, t0: float, compiled: float, host: float) -> None:
    """Add one MJX run of ``simulate`` to ``timing`` (s): wall time since ``t0``, compilation
    (``sim.compile_seconds`` was ``compiled`` before), stepping, host moment reduction."""
    timing["simulate"] += time.perf_counter() - t0
    timing["simulate_compile"] += sim.compile_seconds - compiled
    timing["simulate_stepping"] += sim.last_timing["settle"] + sim.last_timing["plan"]
    timing["simulate_moments_host"] += host


def _simulate_parallel(
    sim, quiet, noise, signal, start, seed, every, world_batch, keep, progress, timing
) -> Simulated:
    """``simulate(parallel=True)``: world w of segment k is MJX world k * B + w of a run."""
    from jaxcomp.hardware.interface import DT
    from jaxcomp.hardware.mjx_sim import SETTLE_STEPS
    from jaxcomp.identify.moments import concat_moments, stack_worlds
    from jaxcomp.recording import Recording

    seg = plan_segments(signal, start, every)
    n_worlds, steps, (length, n_seg, _) = quiet.worlds, len(signal.q_ref), seg.q_ref.shape
    moments, recordings, faults = [], [], []
    rec_steps = np.arange(0, steps, every)
    world_steps = 0
    for first in range(0, n_worlds, world_batch):
        rows = np.arange(first, min(first + world_batch, n_worlds))
        width = len(rows)
        streams = [
            _Stream(seg.signals[k], every, first, noise[rows], seed, keep, segment=k)
            for k in range(n_seg)
        ]
        done = [0]

        def advance(k: int, _total: int, done=done, width=width) -> None:
            if progress is not None:  # in plan steps of the worlds, as the sequential run
                now = int(k * width * steps / length)
                progress(now - done[0])
                done[0] = now

        def route(first_sample: int, chunk: Any, streams=streams, width=width) -> None:
            for k, stream in enumerate(streams):
                part = slice(k * width, (k + 1) * width)
                stream(
                    first_sample,
                    chunk._replace(q=chunk.q[part], dq=chunk.dq[part], current=chunk.current[part]),
                )

        compiled = sim.compile_seconds
        t0 = time.perf_counter()
        rec = sim.run(
            _truth_rows(quiet, np.tile(rows, n_seg)),
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
                    (rec_steps + 1) * DT,
                    q[i],
                    dq[i],
                    cur[i],
                    signal.joint[rec_steps],
                    signal.direction[rec_steps],
                    sim.robot.name,
                )
                for i in range(streams[0].keep)
            ]
    return Simulated(stack_worlds(moments), recordings, np.concatenate(faults), timing, world_steps)


def start_pose(robot: Any) -> np.ndarray:
    """(n,) rad: where every world starts (the "home" pose), as ``identify.plan.arm_pose``."""
    from jaxcomp.identify.plan import arm_pose

    return arm_pose(robot)


# ----------------------------------------------------------------------------- the fits
class Estimates(NamedTuple):
    """One method's estimates of W worlds against their truth (P parameters).

    names (P,), units (P,); estimate, truth, std (W, P) (std NaN where none was reported);
    identified (W, P) bool: the data determine the parameter (``jax_fit.identified``); ok (W,)
    bool: the fit converged / did not fail; gravity (W, n): relative RMS gravity-current error
    at random poses (``evaluate.gravity_current_error``).
    """

    names: list[str]
    units: list[str]
    estimate: np.ndarray
    truth: np.ndarray
    std: np.ndarray
    identified: np.ndarray
    ok: np.ndarray
    gravity: np.ndarray

    @property
    def error(self) -> np.ndarray:
        """(W, P) estimate - truth, NaN for failed fits."""
        return np.where(self.ok[:, None], self.estimate - self.truth, np.nan)


def jax_truth_vector(model: Any, truth: Any) -> np.ndarray:
    """(W, 3n + K) the truth in the joint fit's parameter order [ratio, friction, viscous
    (A s/rad: ratio x viscous), com (the fitted links, m)]."""
    return np.concatenate(
        [
            truth.ratio,
            truth.friction,
            truth.ratio * truth.viscous,
            truth.com_offset[:, model.link_ids].reshape(truth.worlds, -1),
        ],
        axis=1,
    )


def jax_estimates(
    robot: Any, model: Any, truth: Any, simulated: Simulated, fits: Any, poses: np.ndarray
) -> Estimates:
    """The joint fit's ``BatchFit`` of every world as ``Estimates``: ratio, friction, viscous,
    COM offsets and the phase shifts of each joint's first sweep (rad; the truth's from the
    true COM offsets through the same sweep coefficients). ``ok``: converged, and the world
    ran the plan without a fault (a real arm would have stopped)."""
    from jaxcomp.identify.evaluate import gravity_current_error_batch
    from jaxcomp.identify.jax_fit import identified, phase_shift

    sol, n, w = fits.solution, model.n, truth.worlds
    lin = 3 * n
    true = jax_truth_vector(model, truth)
    joint = np.where(simulated.moments.count > 0, simulated.moments.joint, -1)  # -1: empty
    phases = []
    for i in range(w):
        cov = sol.cov[i, lin:, lin:]
        fit_phase = phase_shift(model, fits.coef[i], joint[i], sol.com[i], cov)
        true_phase, _ = phase_shift(model, fits.coef[i], joint[i], true[i, lin:], cov)
        phases.append((fit_phase[0], fit_phase[1], true_phase))
    phase, phase_std, true_phase = (np.array(x) for x in zip(*phases, strict=True))
    ident = identified(model, sol.excited, fits.std)
    nb = len(robot.link_names)
    fit_com = np.zeros((w, nb, 3))
    fit_com[:, model.link_ids] = sol.com.reshape(w, -1, 3)
    return Estimates(
        names=model.parameter_names() + [f"phase_shift[{j}]" for j in range(n)],
        units=["A/(N m)"] * n + ["A"] * n + ["A s/rad"] * n + ["m"] * model.K + ["rad"] * n,
        estimate=np.concatenate([sol.ratio, sol.friction, sol.viscous, sol.com, phase], axis=1),
        truth=np.concatenate([true, true_phase], axis=1),
        std=np.concatenate([fits.std, np.where(phase_std > 0, phase_std, np.nan)], axis=1),
        identified=np.concatenate([ident, ident[:, :n] & (phase_std > 0)], axis=1),
        ok=np.asarray(sol.converged, bool) & (simulated.fault_step < 0),
        gravity=gravity_current_error_batch(
            robot, truth.ratio, truth.com_offset, sol.ratio, fit_com, poses
        ),
    )


def scipy_estimates(
    robot: Any,
    truth: Any,
    recordings: Sequence[Any],
    jax: Estimates,
    poses: np.ndarray,
    progress: Callable[[], None] | None = None,
) -> tuple[Estimates, list[dict]]:
    """The paper's scipy fit of the first M = len(recordings) worlds: ratio and friction as
    ``Estimates`` (identified where the joint fit's are), and the fits that failed."""
    from jaxcomp.identify.evaluate import gravity_current_error_batch

    if recordings:  # pinocchio: only when there is something to fit
        from jaxcomp.identify.baseline import fit_baseline
    m, n, nb = len(recordings), truth.ratio.shape[1], len(robot.link_names)
    est, std = np.full((m, 2 * n), np.nan), np.full((m, 2 * n), np.nan)
    com = np.zeros((m, nb, 3))
    failed = []
    for w, rec in enumerate(recordings):
        try:
            p = fit_baseline(rec, robot=robot)
        except (ValueError, np.linalg.LinAlgError) as exc:  # the paper's fit gives up
            failed.append({"world": w, "error": str(exc)})
        else:
            est[w] = np.r_[p.ratio, p.friction]
            std[w] = np.r_[_std(p, "ratio", n), _std(p, "friction", n)]
            for link, off in p.com_offset.items():
                com[w, robot.link_index(link)] = off
        if progress is not None:
            progress()
    ok = np.isfinite(est).all(axis=1) & jax.ok[:m]  # faulted worlds left out, as for JAX
    gravity = gravity_current_error_batch(
        robot,
        truth.ratio[:m],
        truth.com_offset[:m],
        np.where(ok[:, None], est[:, :n], 1.0),
        com,
        poses,
    )
    gravity[~ok] = np.nan
    cut = slice(0, 2 * n)
    return (
        Estimates(
            names=jax.names[cut],
            units=jax.units[cut],
            estimate=est,
            truth=jax.truth[:m, cut],
            std=std,
            identified=jax.identified[:m, cut] & ok[:, None],
            ok=ok,
            gravity=gravity,
        ),
        failed,
    )


def _std(params: Any, key: str, n: int) -> np.ndarray:
    """(n,) a scipy fit's std of ``key`` (NaN where it reported none)."""
    values = (params.std or {}).get(key)
    if values is None:
        return np.full(n, np.nan)
    return np.array([np.nan if v is None else float(v) for v in values])


# ----------------------------------------------------------------------------- statistics
def parameter_table(est: Estimates, relative: int) -> dict:
    """{parameter: {unit, identified, bias, rmse, spread, ..., coverage, spread_over_std}}
    over the worlds (``evaluate.error_statistics``); the first ``relative`` parameters
    (ratio and friction) also relative to the truth (``relative_bias``, ``relative_rmse``,
    ``relative_p95_abs``). ``identified``: fraction of the fits where the data determine it."""
    from jaxcomp.identify.evaluate import error_statistics

    err = est.error
    stats = error_statistics(err, est.std)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = error_statistics(err[:, :relative] / est.truth[:, :relative])
    share = est.identified[est.ok].mean(axis=0) if est.ok.any() else np.zeros(len(est.names))
    table = {}
    for p, name in enumerate(est.names):
        row = {"unit": est.units[p], "identified": float(share[p])}
        row |= {k: float(v[p]) for k, v in stats.items()}
        if p < relative:
            row |= {f"relative_{k}": float(rel[k][p]) for k in ("bias", "rmse", "p95_abs")}
        table[name] = row
    return table


def groups(names: Sequence[str]) -> dict[str, np.ndarray]:
    """Parameter indices by kind: ratio, friction, viscous, com_offset, phase_shift."""
    kinds = ("ratio", "friction", "viscous", "com_offset", "phase_shift")
    return {
        k: np.array([i for i, s in enumerate(names) if s.startswith(k + "[")], int)
        for k in kinds
        if any(s.startswith(k + "[") for s in names)
    }


def coverage_summary(est: Estimates) -> dict:
    """Coverage of +-1.96 std and moments of the z-scores error / std, pooled over the fits
    and the parameters the data determine: all of them and per kind."""

    def pooled(cols: np.ndarray | slice) -> dict:
        with np.errstate(invalid="ignore", divide="ignore"):
            z = est.error[:, cols] / est.std[:, cols]
        z = z[est.identified[:, cols] & np.isfinite(z)]
        return {
            "count": int(z.size),
            "coverage_95": float(np.mean(np.abs(z) < _Z95)) if z.size else math.nan,
            "z_mean": float(np.mean(z)) if z.size else math.nan,
            "z_std": float(np.std(z, ddof=1)) if z.size > 1 else math.nan,
        }

    return {"identified": pooled(slice(None))} | {
        k: pooled(idx) for k, idx in groups(est.names).items()
    }


def cramer_rao_summary(table: dict, names: Sequence[str]) -> dict:
    """Per kind: median over the determined parameters of (empirical spread of the errors) /
    (RMS of the std the fit reported, its Cramer-Rao bound); 1 when they agree."""
    out = {}
    for kind, idx in groups(names).items():
        rows = [table[names[i]] for i in idx if table[names[i]]["identified"] > 0.5]
        ratios = np.array([r["spread_over_std"] for r in rows], float)
        ratios = ratios[np.isfinite(ratios)]
        out[kind] = {
            "parameters": len(rows),
            "median_spread_over_std": float(np.median(ratios)) if ratios.size else math.nan,
            "min": float(ratios.min()) if ratios.size else math.nan,
            "max": float(ratios.max()) if ratios.size else math.nan,
        }
    return out


def gravity_summary(errors: np.ndarray) -> dict:
    """Per joint median, 95th percentile and max over the worlds of the relative gravity-
    current error (NaN: the joint carries no gravity)."""
    e = np.asarray(errors, float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN joints: NaN is the answer
        if not len(e):
            return {"median": [], "p95": [], "max": []}
        return {
            "median": np.nanmedian(e, axis=0).tolist(),
            "p95": np.nanpercentile(e, 95, axis=0).tolist(),
            "max": np.nanmax(e, axis=0).tolist(),
        }


# ----------------------------------------------------------------------------- the study
def run_study(
    worlds: int,
    seed: int = 0,
    *,
    plan: str = "default",
    every: int = 10,
    spread: TruthSpread = TruthSpread(),  # noqa: B008  (frozen)
    baseline_sample: int = 16,
    devices: int | None = None,
    world_batch: int | None = None,
    fit_batch: int | None = None,
    poses: int = 1000,
    progress: bool = True,
    parallel: bool | None = None,
) -> tuple[dict, dict]:
    """The whole study: (report for study.json, per-world arrays for worlds.npz).

    See the module docstring; ``devices``: shard over the first K devices (default all);
    ``world_batch``: worlds per MJX run (default: all on an accelerator, one per device on
    the CPU, where MJX steps a batch of worlds slower than one world at a time);
    ``fit_batch``: fits per vmapped batch (default all); ``poses``: random poses of the
    gravity-current error (drawn from ``seed``); ``parallel``: the plan's sweeps side by side
    (``simulate``; default: on an accelerator, where a few thousand worlds leave it idle; on
    the CPU, where steps cost in proportion to the worlds, the sweeps run in turn).
    """
    from tqdm.auto import tqdm

    _check_counts(worlds, every, baseline_sample, poses, world_batch, fit_batch)
    if baseline_sample:
        try:
            import pinocchio  # noqa: F401  (the scipy fit needs it: fail now, not at the end)
        except ImportError:
            raise InputError(
                "--baseline-sample needs pinocchio (pip install pin); use --baseline-sample 0 "
                "to skip the scipy fit"
            ) from None
    import jax

    from jaxcomp.hardware.interface import DT
    from jaxcomp.identify.evaluate import random_poses
    from jaxcomp.identify.jax_fit import fit_batch as batch_fit
    from jaxcomp.identify.jax_fit import fit_model
    from jaxcomp.robot import load_robot

    t_all = time.perf_counter()
    robot = load_robot(MODEL)
    the_plan = load_study_plan(robot, plan)
    signal = plan_signal(the_plan, start_pose(robot))
    sim = simulator(devices)
    model = fit_model(robot)
    truth = draw_truth(robot, worlds, seed, spread)
    backend, mesh = jax.default_backend(), sim.mesh
    world_batch = world_batch or (worlds if backend != "cpu" else mesh.size)
    parallel = backend != "cpu" if parallel is None else bool(parallel)
    keep = min(baseline_sample, worlds)
    timing = {"setup": time.perf_counter() - t_all}

    bar = tqdm(
        total=worlds * len(signal.q_ref),
        unit="step",
        unit_scale=True,
        desc=f"MJX, {worlds} worlds",
        disable=not progress,
    )
    simulated = simulate(
        sim,
        truth,
        signal,
        seed=seed,
        every=every,
        world_batch=world_batch,
        keep=keep,
        progress=bar.update,
        parallel=parallel,
    )
    bar.close()
    timing |= simulated.timing

    t0 = time.perf_counter()
    bar = tqdm(total=worlds, unit="fit", desc="JAX fits", disable=not progress)
    fits = batch_fit(model, simulated.moments, batch=fit_batch, mesh=mesh, progress=bar.update)
    bar.close()
    timing |= {"fit_jax": time.perf_counter() - t0, "fit_jax_compile": fits.compile_seconds}
    timing["fit_jax_run"] = fits.seconds

    t0 = time.perf_counter()
    pose_set = random_poses(robot, poses, seed=seed)
    jax_est = jax_estimates(robot, model, truth, simulated, fits, pose_set)
    timing["evaluate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    bar = tqdm(total=keep, unit="fit", desc="scipy fits", disable=not progress or not keep)
    scipy_est, failed = scipy_estimates(
        robot, truth, simulated.recordings, jax_est, pose_set, progress=bar.update
    )
    bar.close()
    timing["fit_scipy"] = time.perf_counter() - t0

    n = model.n
    jax_table = parameter_table(jax_est, 2 * n)
    scipy_table = parameter_table(scipy_est, 2 * n) if keep else {}
    on_m = Estimates(*(x[:keep] if isinstance(x, np.ndarray) else x for x in jax_est))
    sigma = fits.solution.sigma[jax_est.ok]
    timing["total"] = time.perf_counter() - t_all
    report = {
        "format": FORMAT,
        "version": 1,
        "model": robot.name,
        "seed": seed,
        "worlds": worlds,
        "plan": {
            "name": plan,
            "sweeps": len(the_plan.sweeps),
            "steps": len(signal.q_ref),
            "duration_s": len(signal.q_ref) * DT,
        },
        "record_every": every,
        "record_rate_hz": 1.0 / (DT * every),
        "truth": dataclasses.asdict(spread),
        "backend": backend,
        "devices": [str(d) for d in mesh.devices.flat],
        "world_batch": world_batch,
        "parallel_sweeps": parallel,
        "faulted_worlds": int((simulated.fault_step >= 0).sum()),
        "jax": {
            "converged": int(fits.solution.converged.sum()),
            "used": int(jax_est.ok.sum()),
            "noise_estimate_median": float(np.median(sigma)) if sigma.size else math.nan,
            "parameters": jax_table,
            "gravity_current_error": gravity_summary(
                np.where(jax_est.ok[:, None], jax_est.gravity, np.nan)
            ),
            "on_scipy_worlds": {
                "parameters": {
                    k: {"rmse": v["rmse"], "relative_rmse": v.get("relative_rmse")}
                    for k, v in parameter_table(on_m, 2 * n).items()
                    if k in scipy_table
                },
                "gravity_current_error": gravity_summary(on_m.gravity[on_m.ok]),
            },
        },
        "scipy": {
            "worlds": keep,
            "failed": failed,
            "parameters": scipy_table,
            "gravity_current_error": gravity_summary(scipy_est.gravity),
        },
        "coverage": {"jax": coverage_summary(jax_est), "scipy": coverage_summary(scipy_est)},
        "cramer_rao": cramer_rao_summary(jax_table, jax_est.names),
        "timing_s": timing,
        "throughput": {
            "world_steps_per_s": simulated.world_steps / max(timing["simulate_stepping"], 1e-9),
            "jax_fits_per_min": 60.0 * worlds / max(fits.seconds, 1e-9),
            "scipy_fits_per_min": 60.0 * keep / max(timing["fit_scipy"], 1e-9) if keep else None,
        },
    }
    arrays = {
        "parameter_names": np.array(jax_est.names),
        "truth": jax_est.truth,
        "jax_estimate": jax_est.estimate,
        "jax_std": jax_est.std,
        "jax_identified": jax_est.identified,
        "jax_converged": fits.solution.converged,
        "jax_ok": jax_est.ok,
        "jax_noise_estimate": fits.solution.sigma,
        "jax_gravity_current_error": jax_est.gravity,
        "scipy_estimate": scipy_est.estimate,
        "scipy_std": scipy_est.std,
        "scipy_gravity_current_error": scipy_est.gravity,
        "fault_step": simulated.fault_step,
    }
    return report, arrays


def _check_counts(worlds, every, baseline_sample, poses, world_batch, fit_batch) -> None:
    checks = {
        "--worlds": (worlds, 1),
        "--every": (every, 1),
        "--baseline-sample": (baseline_sample, 0),
        "--poses": (poses, 1),
        "--world-batch": (world_batch, 1),
        "--fit-batch": (fit_batch, 1),
    }
    for name, (value, low) in checks.items():
        if value is not None and (isinstance(value, bool) or int(value) != value or value < low):
            raise InputError(f"{name} must be an integer >= {low}, got {value}")


# ----------------------------------------------------------------------------- outputs
def write_outputs(out: Path, report: dict, arrays: dict) -> list[Path]:
    """Write the figures, ``worlds.npz`` and ``study.json`` (last) into ``out``.

    Everything is written to a staging folder inside ``out`` first and moved in by
    ``os.replace`` only once all of it is written: an error leaves ``out`` as it was.
    """
    from jaxcomp.robot_params import json_ready, write_json_atomic

    stage = Path(tempfile.mkdtemp(prefix=".study-calibration.", dir=out))
    try:
        plot_errors(report, arrays, stage / FIGURES[0])
        plot_coverage(report, arrays, stage / FIGURES[1])
        np.savez_compressed(stage / WORLDS_FILE, **arrays)
        write_json_atomic(stage / STUDY_FILE, json_ready(report))
        names = [*FIGURES, WORLDS_FILE, STUDY_FILE]
        for name in names:
            os.replace(stage / name, out / name)
        return [out / name for name in names]
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def plot_errors(report: dict, arrays: dict, path: Path) -> Path:
    """Estimate errors against the truth per joint, JAX fit (all worlds) beside the scipy
    fit (its M worlds): ratio and friction (relative, %), gravity current (relative RMS, %),
    and the JAX fit's COM offset errors (mm) per link axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [str(s) for s in arrays["parameter_names"]]
    n = sum(s.startswith("ratio[") for s in names)
    truth = arrays["truth"]
    ok = arrays["jax_ok"]
    # a JAX friction the data do not determine (joint never swept) is left out
    shown = np.where(arrays["jax_identified"][:, n : 2 * n], 1.0, np.nan)
    jax_rel = 100 * (arrays["jax_estimate"][ok, : 2 * n] / truth[ok, : 2 * n] - 1)
    jax_rel[:, n:] *= shown[ok]
    m = arrays["scipy_estimate"].shape[0]
    sci_rel = 100 * (arrays["scipy_estimate"] / truth[:m, : 2 * n] - 1)
    panels = [
        ("ratio error (%)", jax_rel[:, :n], sci_rel[:, :n]),
        ("friction loss error (%)", jax_rel[:, n:], sci_rel[:, n:]),
        (
            "gravity-current error, RMS / RMS true (%)",
            100 * arrays["jax_gravity_current_error"][ok],
            100 * arrays["scipy_gravity_current_error"],
        ),
    ]
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    for ax, (label, a, b) in zip(axes.flat, panels, strict=False):
        _paired_boxes(ax, a, b, [f"j{j}" for j in range(a.shape[1])])
        ax.set_ylabel(label)
        ax.axhline(0, color="k", lw=0.5)
    axes.flat[2].set_yscale("log")
    com = [i for i, s in enumerate(names) if s.startswith("com_offset[")]
    ax = axes.flat[3]
    err = 1e3 * (arrays["jax_estimate"][ok][:, com] - truth[ok][:, com])
    ident = arrays["jax_identified"][ok][:, com].mean(axis=0) > 0.5
    box = ax.boxplot(_columns(err), showfliers=False, patch_artist=True)
    for patch, good in zip(box["boxes"], ident, strict=True):
        patch.set_facecolor("C0" if good else "0.85")
    labels = [names[i].replace("com_offset[", "").replace("]", "") for i in com]
    ax.set_xticks(range(1, len(com) + 1), labels, rotation=90, fontsize=7)
    ax.set_ylabel("JAX COM offset error (mm)")
    ax.set_title("grey: prior-dominated (not determined by the sweeps)", fontsize=8)
    fig.suptitle(
        f"{report['worlds']} worlds (scipy: first {m}), seed {report['seed']}, plan "
        f"{report['plan']['name']}, {report['record_rate_hz']:g} Hz, {report['backend']}"
    )
    fig.tight_layout()
    return _save(fig, path)


def plot_coverage(report: dict, arrays: dict, path: Path) -> Path:
    """Coverage of the reported standard errors per parameter (fraction of |error| < 1.96
    std; 0.95 expected), the Cramer-Rao comparison (empirical spread against the reported
    std, JAX fit), and the z-scores error / std of the determined parameters against N(0, 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = report["jax"]["parameters"]
    names = [k for k, v in table.items() if v["identified"] > 0.5]
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(16, 4.5), gridspec_kw={"width_ratios": [3, 2, 2]})
    cov = [table[k]["coverage"] for k in names]
    a.bar(range(len(names)), cov, color="C0", label="JAX")
    sci = report["scipy"]["parameters"]
    s_cov = [sci[k]["coverage"] if k in sci else np.nan for k in names]
    a.plot(range(len(names)), s_cov, "s", color="C1", ms=4, label="scipy")
    a.axhline(0.95, color="k", lw=0.8, ls="--")
    a.set_xticks(range(len(names)), names, rotation=90, fontsize=6)
    a.set_ylim(0, 1.05)
    a.set_ylabel("coverage of +-1.96 std")
    a.legend(fontsize=7)
    spread = np.array([table[k]["spread"] for k in names], float)
    std = np.array([table[k]["std_rms"] for k in names], float)
    groups = ("ratio", "friction", "viscous", "com", "phase")
    for g, color in zip(groups, ("C0", "C1", "C2", "C3", "C4"), strict=True):
        sel = np.array([k.startswith(g) for k in names])
        b.loglog(std[sel], spread[sel], "o", color=color, ms=4, label=g)
    good = np.isfinite(spread) & np.isfinite(std) & (spread > 0) & (std > 0)
    if good.any():
        lim = [min(std[good].min(), spread[good].min()), max(std[good].max(), spread[good].max())]
        b.loglog(lim, lim, "k--", lw=0.8)
    b.set_xlabel("reported std (RMS over worlds)")
    b.set_ylabel("empirical spread of the errors")
    b.set_title("Cramer-Rao comparison (JAX fit)", fontsize=9)
    b.legend(fontsize=7)
    mask = arrays["jax_identified"] & arrays["jax_ok"][:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (arrays["jax_estimate"] - arrays["truth"]) / arrays["jax_std"]
    z = z[mask & np.isfinite(z)]
    if z.size:
        c.hist(np.clip(z, -6, 6), bins=60, range=(-6, 6), density=True, color="C0")
    x = np.linspace(-6, 6, 200)
    c.plot(x, np.exp(-0.5 * x**2) / math.sqrt(2 * math.pi), "k", lw=1, label="N(0, 1)")
    c.set_xlabel("error / reported std (determined parameters, JAX)")
    c.legend(fontsize=7)
    fig.suptitle(f"Reported standard errors against the truth, {report['worlds']} worlds")
    fig.tight_layout()
    return _save(fig, path)


def _paired_boxes(ax: Any, a: np.ndarray, b: np.ndarray, labels: list[str]) -> None:
    """Per column, a box of ``a`` (JAX) and one of ``b`` (scipy) side by side."""
    k = a.shape[1]
    pos = np.arange(k) * 3.0
    for data, shift, color, name in ((a, -0.5, "C0", "JAX"), (b, 0.5, "C1", "scipy")):
        if len(data):
            box = ax.boxplot(
                _columns(data),
                positions=pos + shift,
                widths=0.8,
                patch_artist=True,
                showfliers=False,
            )
            for patch in box["boxes"]:
                patch.set_facecolor(color)
            ax.plot([], [], "s", color=color, label=name)
    ax.set_xticks(pos, labels)
    ax.legend(fontsize=7)


def _columns(values: np.ndarray) -> list[np.ndarray]:
    """The finite values of each column (boxplot input)."""
    return [c[np.isfinite(c)] for c in np.asarray(values, float).T]


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- the command
@study.command("calibration")
@click.option("--worlds", type=int, required=True, help="Simulated true robots N (>= 1).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every draw.")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(),
    default="study_calibration",
    show_default=True,
    help="Report folder: study.json, worlds.npz, errors.png, coverage.png.",
)
@click.option("--devices", type=int, default=None, help="Shard over K devices (default all).")
@click.option(
    "--baseline-sample",
    type=int,
    default=16,
    show_default=True,
    help="Also fit the first M worlds with the paper's scipy fit (0: none).",
)
@click.option(
    "--plan",
    default="default",
    show_default=True,
    help="default: the paper's plan (~230 s of sweeps); short: one +-40 deg sweep per joint "
    "(~26 s, for CPU runs and CI); or a plan JSON file.",
)
@click.option(
    "--every",
    type=int,
    default=10,
    show_default=True,
    help="Record every k-th 1 kHz state (10: 100 Hz) for the fits.",
)
@click.option(
    "--com-offset",
    type=float,
    default=0.004,
    show_default=True,
    help="True COM offsets U(-c, c) m per axis of every moving link.",
)
@click.option(
    "--model-error",
    type=(float, float),
    default=(0.2, 0.3),
    show_default=True,
    help="True ratios (per actuator type) off nominal, friction torques off the paper's, "
    "by 1 +- U(LO, HI) (friction: - where + would take over 35 % of the effort limit).",
)
@click.option(
    "--noise", type=float, default=0.05, show_default=True, help="True current noise (std), A."
)
@click.option(
    "--viscous",
    type=float,
    default=0.0,
    show_default=True,
    help="True viscous friction U(0, v) N m s/rad per joint.",
)
@click.option(
    "--poses", type=int, default=1000, show_default=True, help="Poses of the gravity error."
)
@click.option(
    "--world-batch",
    type=int,
    default=None,
    help="Worlds per MJX run (default: all on an accelerator, one per device on the CPU).",
)
@click.option("--fit-batch", type=int, default=None, help="Fits per vmapped batch (default all).")
@click.option(
    "--parallel-sweeps/--sequential-sweeps",
    "parallel",
    default=None,
    help="Simulate the plan's sweeps side by side (K worlds per robot, each from rest where "
    "the sweep before it ends) or in turn. Default: side by side on an accelerator.",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
def calibration(
    worlds: int,
    seed: int,
    out_dir: str,
    devices: int | None,
    baseline_sample: int,
    plan: str,
    every: int,
    noise: float,
    com_offset: float,
    model_error: tuple[float, float],
    viscous: float,
    poses: int,
    world_batch: int | None,
    fit_batch: int | None,
    progress: bool,
    parallel: bool | None,
) -> None:
    """Calibrate N simulated true robots at once and compare with their truth (MJX).

    Each world: a Gen3 Lite whose ratios and friction losses are off nominal by 20-30 % and
    whose links' COM are off by a few mm, with current noise. The calibration plan is recorded
    in all worlds at once on MJX (1 kHz, recorded at 1 kHz / --every), every world is fitted
    with the joint JAX fit (batched on the accelerator) and the first M with the paper's scipy
    fit. DIR/study.json: per-parameter errors against the truth, gravity-current error at
    random poses, coverage of the reported standard errors, Cramer-Rao comparison, run times;
    DIR/errors.png, DIR/coverage.png; DIR/worlds.npz: per-world truth and estimates. Nothing
    is written on error. The same --seed reproduces the numbers (timings aside).
    """
    if plan not in PLANS and not Path(plan).is_file():
        raise InputError(f"--plan must be one of {', '.join(PLANS)} or a plan JSON file: {plan}")
    spread = TruthSpread(model_error, com_offset=com_offset, noise=noise, viscous=viscous)
    _check_counts(worlds, every, baseline_sample, poses, world_batch, fit_batch)
    out = check_out_dir(Path(out_dir))
    report, arrays = run_study(
        worlds,
        seed,
        plan=plan,
        every=every,
        spread=spread,
        baseline_sample=baseline_sample,
        devices=devices,
        world_batch=world_batch,
        fit_batch=fit_batch,
        poses=poses,
        progress=progress,
        parallel=parallel,
    )
    paths = write_outputs(out, report, arrays)
    click.echo(summary(report))
    click.echo("wrote " + ", ".join(str(p) for p in paths))


def summary(report: dict) -> str:
    """A few lines for people: per-joint errors of both fits, coverage, run times."""
    n = sum(k.startswith("ratio[") for k in report["jax"]["parameters"])
    jp, sp = report["jax"]["parameters"], report["scipy"]["parameters"]
    jg, sg = report["jax"]["gravity_current_error"], report["scipy"]["gravity_current_error"]

    def pct(v: Any) -> str:
        return "-" if v is None or not math.isfinite(v) else f"{100 * v:.2f}%"

    head = f"{'joint':<6}" + "".join(
        f"{h:>14}"
        for h in (
            "ratio jax",
            "ratio scipy",
            "friction jax",
            "fric. scipy",
            "g-cur jax",
            "g-cur scipy",
        )
    )
    lines = [
        f"{report['worlds']} worlds, plan {report['plan']['name']} "
        f"({report['plan']['duration_s']:.0f} s), {report['backend']} x{len(report['devices'])}; "
        f"RMS relative errors (scipy on the first {report['scipy']['worlds']}), "
        "gravity current: median over worlds",
        head,
    ]
    for j in range(n):
        r, f = f"ratio[{j}]", f"friction[{j}]"
        row = [
            jp[r]["relative_rmse"],
            sp.get(r, {}).get("relative_rmse"),
            jp[f]["relative_rmse"],
            sp.get(f, {}).get("relative_rmse"),
            jg["median"][j] if jg["median"] else None,
            sg["median"][j] if sg["median"] else None,
        ]
        lines.append(f"{j:<6}" + "".join(f"{pct(v):>14}" for v in row))
    cov = report["coverage"]["jax"]["identified"]
    t = report["timing_s"]
    lines.append(
        f"coverage of +-1.96 std (JAX, {cov['count']} determined estimates): "
        f"{pct(cov['coverage_95'])}; z std {cov['z_std']:.2f}"
    )
    lines.append(
        f"time: simulate {t['simulate']:.1f} s (compile {t['simulate_compile']:.1f} s, "
        f"{report['throughput']['world_steps_per_s']:.3g} world-steps/s), JAX fits "
        f"{t['fit_jax']:.1f} s (compile {t['fit_jax_compile']:.1f} s, "
        f"{report['throughput']['jax_fits_per_min']:.3g}/min), scipy {t['fit_scipy']:.1f} s, "
        f"total {t['total']:.1f} s"
    )
    return "\n".join(lines)
