"""The 1 kHz control loop: guidance and tracking modes of the mobile manipulator (paper IV-B).

``run_control`` drives an ``Arm`` in CURRENT mode with an impedance controller (or in VELOCITY
mode with the reference velocity controller) and, when there is one, a ``Base`` with the base
follower of Eq. (20), for ``duration`` s, and records everything. Frames: world, base and arm
(``control.mount``; the controller works in the arm's base frame); SI units (m, rad, s, N, A).

Modes:

- guidance: the target is fixed in the base frame (the trajectory is evaluated in the base
  frame; default: the end effector's start position), the base follower's p_d is the target,
  so the base follows when the end effector is pushed and stops when it is back;
- tracking: the target follows the trajectory in the world frame; p_d is the end effector's
  start position in the base frame, so the base follows the end effector around.

With orientation gains the end effector's start orientation is held, fixed in the same frame.

A run has three stages: the set-up (nothing switched: the arm healthy and still, the frames and
the trajectory, the reach, the first command compiled and checked, the recording opened), the
loop, and the finish (the recording joined, timing.json written, the ``ControlResult``). Each
cycle of the loop: the state from the last ``arm.cycle`` is checked by the ``Watchdog``; the
cycle's work (``control.cycle.Cycle``: targets in the arm frame, the command, its check, the
base twist, one recorded sample: ``control.run_recording``) gives the command computed from
this state, sent at the next cycle; then the loop waits for the next 1 kHz deadline (real time:
absolute ``perf_counter_ns`` ticks, sleep then spin for the last 200 us) or goes straight on
(lock step with a simulator: deterministic, as fast as the CPU allows) and sends it.

Before anything is switched, the targets are checked against the arm's reach
(``workspace.arm_reach``: guidance mode, or tracking without a base, whose targets the arm alone
must reach); during the run the watchdog also ends a run whose end effector stays more than
``max_error`` m (default in tracking mode twice the controller's error clip: 0.2 m on the Gen3
Lite; in guidance mode none, where a person may hold the arm off its target) from its target for
more than ``max_error_time`` s (default 2 s) with ``not_tracking``.

A ``RunLink`` (``control.run_link``) connects the run to an operator on another thread: a
stop request, live gains (K_d, D_d, friction compensation, taken up at the next cycle without
recompiling) and a monitor fed with every 33rd recorded sample (the browser console's feed).

Any stop request, watchdog trip, hardware fault, Ctrl-C or exception ends the run with the arm
in POSITION mode and the base stopped, before anything else is done (``safe_stop`` in a
``finally``). The recording is written incrementally (one part per 1000 samples, handed over a
block at a time) and joined into ``out_dir/recording.npz`` at the end; ``out_dir/timing.json``
holds the timing.

Per-cycle cost (the loop runs ~150-250 us of Python and JAX per 1 ms): the controller runs as
its ``packed_step`` (one numpy vector in, one out, ``control.law_adapter``), frames are
computed on Python floats, samples go into preallocated blocks, and the garbage collector is
off during the run (the loop frees its objects by reference counting). For real time, call
``timing.configure_jax_for_control`` before JAX runs anything and run the loop under
``timing.realtime_priority``.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control.gains import BaseGains
from jaxcomp.control.impedance import ImpedanceController
from jaxcomp.control.law_adapter import LawAdapter
from jaxcomp.control.mount import ArmMount
from jaxcomp.control.run_link import MonitorStart, RunLink, Tuning
from jaxcomp.control.run_recording import RECORDING, TIMING, Recorder
from jaxcomp.control.run_result import ControlResult
from jaxcomp.control.run_setup import Mode, PreparedRun, set_up_run
from jaxcomp.control.timing import CycleTimer, wait_until
from jaxcomp.control.trajectory import Trajectory, TrajectorySpec
from jaxcomp.control.velocity import VelocityController
from jaxcomp.control.watchdog import FAULT, Watchdog, WatchdogTrip, safe_stop
from jaxcomp.errors import FileError, InputError
from jaxcomp.files import file_problem
from jaxcomp.hardware.interface import Arm, ArmState, Base, HardwareFault

log = logging.getLogger(__name__)

#: s, real time: the longest gap between two states before the watchdog stops a run.
STALL_LIMIT = 0.02
#: s, how long the end effector may stay beyond ``max_error`` of its target (``run_control``).
MAX_ERROR_TIME = 2.0

#: ``on_cycle(k, state, command, target)``: cycle k, its state, the command (n,) computed from
#: it (A or rad/s), the target (3,) world m.
OnCycle = Callable[[int, ArmState, np.ndarray, np.ndarray], None]


def run_control(
    arm: Arm,
    base: Base | None,
    controller: ImpedanceController | VelocityController,
    mode: Mode | str = Mode.GUIDANCE,
    trajectory: TrajectorySpec | Trajectory | str | None = None,
    duration: float | None = None,
    out_dir: str | Path = "control_run",
    realtime: bool = False,
    *,
    mount: ArmMount | None = None,
    base_gains: BaseGains | None = None,
    model: str | None = None,
    watchdog: Watchdog | None = None,
    max_saturated_cycles: int = 250,
    base_velocity_compensation: bool = True,
    on_cycle: OnCycle | None = None,
    default_duration: float = 10.0,
    max_error: float | None = None,
    max_error_time: float = MAX_ERROR_TIME,
    before_start: Callable[[float], None] | None = None,
    link: RunLink | None = None,
    stall_limit: float | None = STALL_LIMIT,
) -> ControlResult:
    """Run guidance or tracking mode for ``duration`` s (see the module doc).

    Args:
        arm: the arm (its state must be healthy and still; it is switched to the controller's
            mode here and always ends in POSITION mode).
        base: the mobile base, or None (arm alone: base frame = world frame).
        controller: ``make_impedance_controller(arm_model, ...)`` (CURRENT mode) or
            ``make_velocity_controller`` (VELOCITY mode), on the arm-alone model.
        mode: "guidance" (target fixed in the base frame) or "tracking" (world frame).
        trajectory: spec string, ``TrajectorySpec`` (resolved at the start), a built
            ``Trajectory`` (in the mode's frame), or None (``static``: hold the start).
        duration: s of control; None: the trajectory's duration, or ``default_duration`` s
            when it has none (static, endless circle).
        out_dir: directory for ``recording.npz`` and ``timing.json`` (created).
        realtime: pace on absolute 1 kHz wall-clock deadlines; False: lock step, as fast as
            possible (for a simulator).
        mount: the arm's mount on the base; default ``ArmMount.from_model(model)`` when there
            is a base, identity otherwise.
        base_gains: base follower gains (default the paper's ``BaseGains()``).
        model: the recording's ``model`` field and the model the mount is read from; default
            the controller's robot (``Robot.reference``: built-in name or file path); with a
            base, the mobile model it names (``mobile_model_name``: "mobile_gen3_lite" for
            "gen3_lite"). The recording's ``joints`` are the arm's.
        watchdog: default: current limit = the arm's limits, saturation at the controller's
            limit for ``max_saturated_cycles`` cycles, the arm's ``stale_tolerance`` (repeated
            states of lost replies the arm tolerates; 0 for the simulator), loop-stall limit
            ``stall_limit`` (20 ms) in real time.
        base_velocity_compensation: give the controller the target's velocity relative to
            the moving arm base (from the odometry twist); False: the target's own velocity.
        on_cycle: called each cycle as ``on_cycle(k, state, command, target)`` (target: (3,)
            world m) after the command is computed and checked and before it is sent (for
            viewers and tests; keep it short: it runs inside the 1 ms budget).
        default_duration: s, see ``duration``.
        max_error: m, a run whose end effector stays further than this from its target for
            more than ``max_error_time`` s ends with ``not_tracking``; None: in tracking mode
            twice the controller's error clip, in guidance mode never; ``math.inf``: never
            (ignored with ``watchdog``).
        max_error_time: s, see ``max_error``.
        before_start: called with the run's duration (s) once it is resolved, before anything
            is switched or written (e.g. to refuse events outside the run by raising
            ``InputError``).
        link: a ``RunLink`` from outside the loop's thread: a stop request (ends the run,
            kind "stopped"), live gains, a monitor fed every ``monitor.every`` cycles.
        stall_limit: s, real time only: the longest the loop may go without a new state
            before the watchdog ends the run (a stalled loop leaves a real arm on its last
            command); None: no limit (a lock-step simulator waits for the loop). Ignored with
            ``watchdog``.

    Targets the arm alone must reach (guidance mode, or tracking without a base) that get
    farther from its base than its reach (``workspace.arm_reach``) are refused (InputError).

    Returns:
        A ``ControlResult``.

    Raises:
        JaxcompError: on setup errors (nothing was switched).
        Exception: an unexpected exception of the loop, after the safe stop and saving the
            recording.
    """
    mode = Mode(mode.value if isinstance(mode, Mode) else str(mode).lower())
    run = set_up_run(
        arm,
        base,
        controller,
        mode,
        trajectory,
        duration,
        out_dir,
        realtime,
        mount=mount,
        base_gains=base_gains,
        model=model,
        watchdog=watchdog,
        max_saturated_cycles=max_saturated_cycles,
        base_velocity_compensation=base_velocity_compensation,
        default_duration=default_duration,
        max_error=max_error,
        max_error_time=max_error_time,
        before_start=before_start,
        stall_limit=stall_limit,
    )
    link = RunLink() if link is None else link
    _announce(run, link)
    end = _loop(run, arm, base, realtime, on_cycle, link)
    result = _finish(run, end)
    _conclude(result, end, link)
    return result


# ----------------------------------------------------------------------------- the run


class _End(NamedTuple):
    """How the loop of ``run_control`` ended: the ``ControlResult.kind`` and reason, cycles
    made, s of robot time controlled, stop errors, and an unexpected exception to re-raise
    after the result is written (None if none)."""

    kind: str
    reason: str
    cycles: int
    duration: float
    stop_errors: list[str]
    unexpected: BaseException | None


def _announce(run: PreparedRun, link: RunLink) -> None:
    """Tell the link's monitor (if any) that the run is set up and about to switch the arm."""
    if link.monitor is None:
        return
    start = MonitorStart(
        run.mode.value,
        getattr(run.work.traj, "description", ""),
        run.recorder.columns,
        run.timer,
        run.duration,
    )
    _notify(link.monitor.started, start)


def _conclude(result: ControlResult, end: _End, link: RunLink) -> None:
    """Tell the monitor the run ended, re-raise an unexpected exception, log an actuator
    fault."""
    if link.monitor is not None:
        _notify(link.monitor.ended, result)
    if end.unexpected is not None:
        raise end.unexpected
    if end.kind == FAULT:
        log.warning("control ended on an actuator fault: %s", end.reason)


def _notify(call: Callable[[Any], None], what: Any) -> None:
    """``call(what)``, a monitor's: its failure is logged, never raised."""
    try:
        call(what)
    except Exception as exc:  # noqa: BLE001 - a monitor never ends a run
        log.error("the run's monitor failed: %s", exc)


# ----------------------------------------------------------------------------- the loop


class _Progress:
    """How far the loop got: cycles made and the last state received."""

    def __init__(self, state: ArmState):
        self.cycles = 0
        self.state = state


def _loop(
    run: PreparedRun,
    arm: Arm,
    base: Base | None,
    realtime: bool,
    on_cycle: OnCycle | None,
    link: RunLink,
) -> _End:
    """The loop of ``run_control``: switch the arm to the law's mode, then one command per
    cycle (on 1 kHz deadlines in real time, else in lock step) until ``run.n_cycles`` cycles,
    a stop request, a watchdog trip, a hardware fault, a refused command, Ctrl-C or any
    exception; always ends with ``safe_stop`` (arm in POSITION mode, base stopped)."""
    progress = _Progress(run.state)
    t0 = run.state.t
    unexpected: BaseException | None = None
    with _quiet_interpreter(realtime):
        try:
            arm.set_modes(run.law.mode)
            kind, reason = _cycles(run, arm, realtime, on_cycle, link, progress)
        except BaseException as exc:  # noqa: BLE001 - every end is a ControlResult.kind
            kind, reason, unexpected = _ending(exc)
        finally:
            stop_errors = safe_stop(arm, base)
            run.timer.finish(progress.state.t - t0)
    duration = progress.state.t - t0
    return _End(kind, reason, progress.cycles, duration, stop_errors, unexpected)


@contextlib.contextmanager
def _quiet_interpreter(realtime: bool) -> Iterator[None]:
    """No collector pauses inside the loop (it frees its garbage by reference counting) and,
    in real time, a short thread switch interval (the recorder thread yields the GIL
    quickly); both restored after."""
    switch_interval = sys.getswitchinterval()
    gc_enabled = gc.isenabled()
    try:
        if realtime:
            sys.setswitchinterval(1e-4)
        gc.disable()
        yield
    finally:
        sys.setswitchinterval(switch_interval)
        if gc_enabled:
            gc.enable()


def _ending(exc: BaseException) -> tuple[str, str, BaseException | None]:
    """(``ControlResult.kind``, reason, the exception to re-raise or None) of a loop that
    ended on ``exc``."""
    if isinstance(exc, WatchdogTrip):
        return exc.kind, str(exc), None
    if isinstance(exc, HardwareFault):
        return "hardware_fault", str(exc), None
    if isinstance(exc, InputError):  # the arm refused a command (the watchdog should have)
        return "command_refused", str(exc), None
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted", "Ctrl-C", None
    return "error", f"{type(exc).__name__}: {exc}", exc


def _cycles(
    run: PreparedRun,
    arm: Arm,
    realtime: bool,
    on_cycle: OnCycle | None,
    link: RunLink,
    progress: _Progress,
) -> tuple[str, str]:
    """The cycles of the loop once the arm is switched; returns (kind, reason) of a run that
    completed or was stopped (anything else raises)."""
    law, wd, work, timer = run.law, run.watchdog, run.work, run.timer
    state = run.state
    stop, monitor = link.stop, link.monitor
    tuning = link.tuning if law.estimates else None
    every = max(int(monitor.every), 1) if monitor is not None else 0
    period_ns = int(CONTROL_PERIOD * 1e9)
    law.start(state)
    tuned = _take_tuning(tuning, law, 0)
    cmd = work(state)
    if on_cycle is not None:
        on_cycle(0, state, cmd, work.target_w)
    deadline = time.perf_counter_ns() + period_ns
    for k in range(1, run.n_cycles + 1):
        if realtime:
            wait_until(deadline)
        if stop is not None and stop.is_set():
            return "stopped", "stopped on request"
        progress.cycles = k
        sent = time.perf_counter_ns()
        state = arm.cycle(law.command(cmd))
        recv = time.perf_counter_ns()
        progress.state = state
        wd.check_state(state, recv if realtime else None)
        if tuning is not None and tuning.version != tuned:  # new live gains, from now on
            tuned = _take_tuning(tuning, law, tuned)
        cmd = work(state)
        if on_cycle is not None:
            on_cycle(k, state, cmd, work.target_w)
        done = time.perf_counter_ns()
        deadline += period_ns  # the next send: the command must be ready by then
        timer.record(sent, recv, done, deadline if realtime else sent + period_ns)
        if realtime and done > deadline:  # a whole tick lost: skip it, keep the phase
            deadline += -(-(done - deadline) // period_ns) * period_ns
        if every and k % every == 0:
            every = _sample(monitor, k, run.recorder.last_row, every)
    return "completed", f"ran the full {run.duration:g} s"


def _take_tuning(tuning: Tuning | None, law: LawAdapter, tuned: int) -> int:
    """Apply the link's live gains to the law when they are newer than version ``tuned``;
    returns the version applied."""
    if tuning is None or tuning.version == tuned:
        return tuned
    version = tuning.version
    law.live[:] = tuning.values
    tuning.applied = version
    return version


def _sample(monitor, k: int, row: np.ndarray, every: int) -> int:
    """Feed the monitor cycle ``k``'s row; returns ``every``, or 0 when the monitor failed
    (it is dropped: a monitor never ends a run)."""
    try:
        monitor.sample(k, row)
    except Exception as exc:  # noqa: BLE001 - a monitor never ends a run
        log.error("the run's monitor failed and was dropped: %s", exc)
        return 0
    return every


# ----------------------------------------------------------------------------- finish


def _finish(run: PreparedRun, end: _End) -> ControlResult:
    """Join the recording, write timing.json, fill the result; never raises."""
    work = run.work
    result = ControlResult(
        kind=end.kind,
        reason=end.reason,
        cycles=end.cycles,
        duration=max(float(end.duration), 0.0),
        out_dir=run.out,
        stop_errors=list(end.stop_errors),
        trajectory=getattr(work.traj, "description", ""),
        mode=run.mode.value,
    )
    if work.samples:
        result.rms_error = math.sqrt(work.sq_sum / work.samples)
        result.final_error, result.max_error = work.last_err, work.max_err
    _join_recording(result, run.recorder, run.out)
    _write_timing(result, run.timer, run.out)
    return result


def _join_recording(result: ControlResult, recorder: Recorder, out: Path) -> None:
    """The recording joined into ``out / RECORDING``, or why not (in ``result``)."""
    try:
        result.recording = recorder.close()
        result.recording_path = out / RECORDING
    except (OSError, FileError) as exc:  # read-only, full disk
        result.file_error = f"the recording was not written: {file_problem(exc)}"
        log.error(result.file_error)
    except Exception as exc:  # noqa: BLE001 - e.g. too few samples to make a recording
        result.stop_errors.append(f"recording not joined: {exc}")
        log.error("recording not joined: %s", exc)


def _write_timing(result: ControlResult, timer: CycleTimer, out: Path) -> None:
    """The timing summary into ``result`` and ``out / TIMING``, or why not."""
    try:
        result.timing = timer.summary()
        result.timing_path = timer.dump(out / TIMING, result.run_info())
    except (OSError, FileError) as exc:
        result.file_error = result.file_error or f"{TIMING} was not written: {file_problem(exc)}"
    except Exception as exc:  # noqa: BLE001
        result.stop_errors.append(f"timing.json not written: {exc}")


__all__ = [
    "MAX_ERROR_TIME",
    "STALL_LIMIT",
    "OnCycle",
    "run_control",
]
