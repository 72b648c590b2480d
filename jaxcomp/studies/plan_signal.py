"""A calibration plan as the 1 kHz signals the simulated worlds follow and record: whole
(``plan_signal``) or cut into its sweeps, to be simulated side by side (``plan_segments``).

Plans by name come from ``identify.named_plans``. Angles in rad, one sample per 1 ms step.
"""

from typing import NamedTuple

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import PLAN, RESTART, SETTLE, SETTLE_STEPS, Move, reference_trajectory
from jaxcomp.identify.plan import CalibrationPlan, arm_pose
from jaxcomp.identify.recorder import MOVE_DIRECTION
from jaxcomp.robot import Robot


def start_pose(robot: Robot) -> np.ndarray:
    """(n,) rad: where every world starts (the "home" pose), as ``identify.plan.arm_pose``.

    Args:
        robot: the model.

    Returns:
        (n,) joint angles, rad.
    """
    return arm_pose(robot)


class PlanSignal(NamedTuple):
    """A calibration plan as the 1 kHz signals an MJX run follows and records (T steps).

    Attributes:
        q_ref: (T, n) rad, what ``Arm.move_to`` sends for the plan's moves.
        joint: (T,) the swept joint (-1 outside sweeps).
        direction: (T,) +1 / -1 (0 outside sweeps), as ``identify.recorder`` labels them.
        sweep: (T,) the index of the plan sweep (its transfer included) of each step.
    """

    q_ref: np.ndarray
    joint: np.ndarray
    direction: np.ndarray
    sweep: np.ndarray


def plan_signal(plan: CalibrationPlan, start: np.ndarray) -> PlanSignal:
    """The ``PlanSignal`` of ``plan`` from the pose ``start`` (n,) rad.

    Args:
        plan: the calibration plan.
        start: (n,) rad, the pose its first move starts from (``start_pose``).

    Returns:
        The ``PlanSignal``, one step per 1 ms of its moves.
    """
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


#: Fewest recorded samples (1 kHz / ``every``) a pass, one direction of a sweep, may have.
#: The short plan on the Gen3 Lite (shortest pass 1341 steps, one world): with 61 samples a
#: pass the fit's errors are those of 134 (``--every`` 22 against the default 10); with 39
#: (``--every`` 34) most joints' steady samples are lost and their ratios are off by 70-90 %.
MIN_PASS_SAMPLES = 50


def check_every(signal: PlanSignal, every: int) -> None:
    """InputError when recording every ``every``-th step of ``signal`` leaves fewer than
    ``MIN_PASS_SAMPLES`` samples of its shortest pass (before anything is simulated).

    Args:
        signal: the plan's signal.
        every: the recording decimation, steps.

    Raises:
        InputError: the plan has no sweep, or ``every`` is too large (the largest that does
            is named).
    """
    d = signal.direction
    starts = np.r_[0, np.flatnonzero(np.diff(d) != 0) + 1]
    lengths = np.diff(np.r_[starts, len(d)])[d[starts] != 0]
    if not len(lengths):
        raise InputError("the plan has no sweep")
    shortest = int(lengths.min())
    if every * MIN_PASS_SAMPLES > shortest:
        raise InputError(
            f"--every {every} records fewer than {MIN_PASS_SAMPLES} samples of the plan's "
            f"shortest pass ({shortest} steps at 1 kHz): use --every "
            f"{max(shortest // MIN_PASS_SAMPLES, 1)} or less"
        )


class Segments(NamedTuple):
    """A ``PlanSignal`` cut into K segments, one a plan sweep (its passes up and down, then,
    unless left out, the transfer to the next sweep's start and the settling there; segment 0
    also holds the transfer from the plan's start), to be simulated side by side as separate
    worlds (``plan_recording.simulate(parallel=True)``).

    Segment k starts at rest at ``start[k]`` (n,) rad (where segment k - 1 has settled; the
    plan's start pose for k = 0) at plan step ``first[k]``, a multiple of the recording
    decimation at or up to ``every`` - 1 steps before its sweep's first step ``begin[k]``;
    its sweep's last pass ends before step ``sweep_end[k]`` and the segment before step
    ``end[k]`` (``sweep_end[k]`` without the transfers). ``q_ref`` (L, K, n) rad: the
    references side by side, each held at its last pose up to the longest length L;
    ``signals``: each segment's ``PlanSignal`` (steps first[k] .. end[k]; the steps before
    begin[k], the end of segment k - 1, are labelled outside sweeps).
    """

    q_ref: np.ndarray
    start: np.ndarray
    first: np.ndarray
    begin: np.ndarray
    end: np.ndarray
    signals: list[PlanSignal]
    sweep_end: np.ndarray


def plan_segments(
    signal: PlanSignal, start: np.ndarray, every: int, transfers: bool = True
) -> Segments:
    """``Segments`` of ``signal`` (from the pose ``start`` (n,) rad), aligned to ``every``;
    ``transfers=False`` ends each segment with its sweep's last pass: the move to the next
    sweep's start, which a segment run on its own throws away (the next one restarts at
    rest), is not simulated (the Gen3 Lite's default plan: 177k of 233k steps).

    Args:
        signal: the whole plan's signal (``plan_signal``).
        start: (n,) rad, the pose the plan starts from.
        every: the recording decimation, steps: each segment starts at a multiple of it.
        transfers: keep the transfer to the next sweep in each segment.

    Returns:
        The ``Segments``, one per plan sweep, in plan order.

    Raises:
        InputError: a sweep does not start at rest (the plan cannot run side by side).
    """
    d = signal.direction
    cuts = (np.flatnonzero((d[1:] != 0) & (d[:-1] == 0)) + 1)[1:]  # the sweeps' first steps
    begin = np.r_[0, cuts]
    end = np.r_[cuts, len(signal.sweep)]
    last = np.flatnonzero(d != 0)
    sweep_end = last[np.searchsorted(last, end) - 1] + 1  # after each segment's last pass step
    if not transfers:
        end = sweep_end
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
    return Segments(q_ref, np.array(starts), first, begin, end, signals, sweep_end)


class Lanes(NamedTuple):
    """A plan's ``Segments`` packed into B lanes, each lane one MJX world per true robot that
    runs its segments one after another (``plan_recording.simulate(parallel=True)``).

    Segment k runs in lane ``lane[k]`` from lane step ``at[k]`` (a multiple of the recording
    decimation): the lane's first segment right after the run's settling, each later one after
    a restart at rest at its start pose and ``settle`` steps held there (phase ``SETTLE``,
    faults not counted). Faults count in a segment's sweep (``runner.PLAN``) only: a transfer
    to the next sweep that a segment holds is ``SETTLE`` too, so that a world's faults are the
    same with transfers simulated or not. ``q_ref`` (L, B, n) rad and ``phase`` (L, B)
    (``runner.PLAN``, ``SETTLE``, ``RESTART``): the lanes' references and phases, each held at
    its last pose up to the longest length L; ``plan_step`` (L, B): the plan step of each lane
    step (-1 outside segments), the steps the current noise is drawn at, so that a sample's
    noise does not depend on its lane; ``start`` (B, n) rad: each lane's first pose;
    ``signals``: each lane's ``PlanSignal`` (settling labelled outside sweeps; ``sweep`` the
    plan sweep).
    """

    q_ref: np.ndarray
    phase: np.ndarray
    plan_step: np.ndarray
    start: np.ndarray
    lane: np.ndarray
    at: np.ndarray
    signals: list[PlanSignal]


#: Longest lane ``pack_segments`` considers, as a multiple of the longest segment: longer
#: lanes pack tighter but leave fewer lanes to fill the accelerator.
LANE_STRETCH = 1.25


def pack_segments(seg: Segments, every: int, settle: int) -> Lanes:
    """``seg`` packed into lanes by first-fit decreasing, with the lane capacity (from the
    longest segment to ``LANE_STRETCH`` times it, in steps of ``every``) that needs the fewest
    lane steps in all, B (L + ``SETTLE_STEPS``) per true robot (more lanes on ties): on the
    Gen3 Lite's default plan 9 lanes of 28.4 s instead of 14 of 26 s. Depends on the plan alone
    (not on the worlds), so a world's numbers do not depend on how many run. ``settle`` steps:
    the hold after a restart (``SETTLE_STEPS`` as the run's own settling), rounded up to
    ``every``.

    Args:
        seg: the plan's segments (``plan_segments``).
        every: the recording decimation, steps.
        settle: steps held at rest after a restart.

    Returns:
        The ``Lanes`` (lane 0 starts the plan).
    """
    up = lambda x: -(-int(x) // every) * every  # noqa: E731
    length = np.array([up(e - f) for f, e in zip(seg.first, seg.end, strict=True)])
    hold = up(settle)
    longest = int(length.max())
    capacities = range(longest, int(LANE_STRETCH * longest) + 1, every)
    packs = [_first_fit(length, c, hold) for c in capacities]
    bins, used = min(packs, key=lambda p: (len(p[0]) * (max(p[1]) + SETTLE_STEPS), -len(p[0])))
    n = seg.q_ref.shape[2]
    L = max(used)
    q_ref = np.empty((L, len(bins), n))
    phase = np.full((L, len(bins)), PLAN, np.int8)
    plan_step = np.full((L, len(bins)), -1, np.int64)
    lane, at = np.zeros(len(length), int), np.zeros(len(length), int)
    signals = []
    bins = sorted(bins, key=min)  # lane 0 starts the plan
    for b, jobs in enumerate(bins):
        parts, t = [], 0
        for i, k in enumerate(sorted(jobs)):  # plan order: a lane's first fault is its earliest
            s = seg.signals[k]
            if i:
                q_ref[t : t + hold, b] = seg.start[k]
                phase[t : t + hold, b] = SETTLE
                phase[t, b] = RESTART
                parts.append(PlanSignal(np.repeat(seg.start[k][None], hold, 0), *_outside(hold)))
                t += hold
            ref = np.concatenate([s.q_ref, np.repeat(s.q_ref[-1:], length[k] - len(s.q_ref), 0)])
            q_ref[t : t + length[k], b] = ref
            plan_step[t : t + length[k], b] = seg.first[k] + np.arange(length[k])
            phase[t + seg.sweep_end[k] - seg.first[k] : t + length[k], b] = SETTLE  # a transfer
            pad = length[k] - len(s.q_ref)
            parts.append(
                PlanSignal(
                    ref,
                    np.r_[s.joint, np.full(pad, -1)],
                    np.r_[s.direction, np.zeros(pad, s.direction.dtype)],
                    np.r_[s.sweep, np.full(pad, k)],
                )
            )
            lane[k], at[k] = b, t
            t += length[k]
        q_ref[t:, b] = q_ref[t - 1, b]
        signals.append(PlanSignal(*(np.concatenate(x) for x in zip(*parts, strict=True))))
    start = seg.start[[min(jobs) for jobs in bins]]
    return Lanes(q_ref, phase, plan_step, start, lane, at, signals)


def _outside(steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joint, direction, sweep) labels of ``steps`` steps outside any sweep."""
    return np.full(steps, -1), np.zeros(steps, int), np.full(steps, -1)


def _first_fit(length: np.ndarray, capacity: int, hold: int) -> tuple[list[list[int]], list[int]]:
    """Segments (by index) of steps ``length`` into bins of ``capacity`` steps, first fit in
    decreasing length, ``hold`` steps before each but a bin's first: (bins, steps used)."""
    bins: list[list[int]] = []
    used: list[int] = []
    for k in sorted(range(len(length)), key=lambda k: (-length[k], k)):
        b = next((b for b, u in enumerate(used) if u + hold + length[k] <= capacity), None)
        if b is None:
            bins.append([k])
            used.append(int(length[k]))
        else:
            bins[b].append(k)
            used[b] += hold + int(length[k])
    return bins, used
