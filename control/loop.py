"""The 1 kHz control loop: guidance and tracking modes of the mobile manipulator (paper IV-B).

``run_control`` drives an ``Arm`` in CURRENT mode with an impedance controller (or in VELOCITY
mode with the reference velocity controller) and, when there is one, a ``Base`` with the base
follower of Eq. (20), for ``duration`` s, and records everything.

Frames (all right-handed, z up, m):

- world: the base's odometry frame (the simulator's world); the base pose (x, y, yaw) is the
  odometry of the base's planar joints;
- base: the mobile base's own frame, moving with it (at pose 0 it coincides with the world);
- arm: the arm's base frame, where the controller works (the arm's own model, e.g.
  ``gen3_lite``); ``ArmMount`` places it in the base frame, read from the mobile model (the
  arm's root body with the base joints at zero: Gen3 Lite at (0.160, 0, 0.11) m).

Modes:

- guidance: the target is fixed in the base frame (the trajectory is evaluated in the base
  frame; default: the end effector's start position), the base follower's p_d is the target,
  so the base follows when the end effector is pushed and stops when it is back;
- tracking: the target follows the trajectory in the world frame; p_d is the end effector's
  start position in the base frame, so the base follows the end effector around.

With orientation gains the end effector's start orientation is held, fixed in the same frame.

Each cycle: the state from the last ``arm.cycle`` is checked by the ``Watchdog``; the base
odometry turns the target into the arm frame (position; velocity relative to the moving arm
base; acceleration with the base's acceleration neglected); the controller gives the command;
the watchdog checks it; the base follower's twist goes to the base; one sample is recorded
(time, q, dq, measured current, joint -1, direction 0, plus ``target`` (3,) world m, ``ee``
(3,) world m, ``base`` (3,) x m, y m, yaw rad, ``command`` (n,) A (rad/s for the velocity
controller): the command computed from this state, sent at the next cycle; with the impedance
controller also its external force estimate (``control.external_force``): ``current_model``
(n,) A, ``wrench`` (3,) N, the force applied on the end effector, and ``wrench_band`` (3,) N,
per axis the static-friction band it lies within, both in the world frame); then the loop waits
for the next 1 kHz deadline (real time: absolute ``perf_counter_ns`` ticks, sleep then spin for
the last 200 us) or goes straight on (lock step with a simulator: deterministic, as fast as the
CPU allows) and sends it.

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
``finally``).
The recording is written incrementally (``RecordingWriter``, one part per 1000 samples, handed
over a block at a time) and joined into ``out_dir/recording.npz`` at the end;
``out_dir/timing.json`` holds the timing.

Per-cycle cost (the loop runs ~150-250 us of Python and JAX per 1 ms): the controller runs as
its ``packed_step`` (one numpy vector in, one out), frames are computed on Python floats,
samples go into preallocated blocks, and the garbage collector is off during the run (the loop
frees its objects by reference counting). For real time, call ``timing.configure_jax_for_control``
before JAX runs anything and run the loop under ``timing.realtime_priority``.
"""

from __future__ import annotations

import enum
import gc
import logging
import math
import queue
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from dataclasses import replace as dc_replace
from pathlib import Path
from typing import Any, NamedTuple

import mujoco
import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control.base_follower import BaseFollower
from jaxcomp.control.gains import BaseGains
from jaxcomp.control.impedance import ImpedanceController
from jaxcomp.control.impedance_io import estimate_slice, packed_slices
from jaxcomp.control.run_link import MonitorStart, RunLink
from jaxcomp.control.timing import CycleTimer, wait_until
from jaxcomp.control.trajectory import Static, Trajectory, TrajectorySpec, parse_trajectory
from jaxcomp.control.velocity import VelocityController
from jaxcomp.control.watchdog import FAULT, Watchdog, WatchdogTrip, safe_stop
from jaxcomp.control.workspace import arm_reach, check_reachable
from jaxcomp.errors import FileError, InputError, ModelError
from jaxcomp.files import file_problem
from jaxcomp.hardware.interface import Arm, ArmCommand, ArmState, Base, ControlMode, HardwareFault
from jaxcomp.recording import Recording, RecordingWriter
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import BASE_JOINTS, RobotParams, arm_joint_indices

log = logging.getLogger(__name__)

RECORDING = "recording.npz"
TIMING = "timing.json"
#: s, real time: the longest gap between two states before the watchdog stops a run.
STALL_LIMIT = 0.02
#: Cycles of timing stamps preallocated (10 min at 1 kHz, 19 MB): a longer run grows them.
TIMER_CAPACITY = 600_000
#: s, how long the end effector may stay beyond ``max_error`` of its target (``run_control``).
MAX_ERROR_TIME = 2.0
#: Smallest singular value of the end effector's position Jacobian, relative to its largest,
#: that still counts as a direction the arm can move in (``check_site_mobility``).
MIN_MOBILITY = 1e-3


class Mode(enum.Enum):
    """Operational mode (paper IV-B)."""

    GUIDANCE = "guidance"
    TRACKING = "tracking"


# ----------------------------------------------------------------------------- frames


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ArmMount:
    """Where the arm's base frame sits on the mobile base.

    Attributes:
        position: (3,) m, the arm frame's origin in the base frame.
        rotation: (3, 3), the arm frame's axes in the base frame (columns).
        pivot: (3,) m, a point on the base's yaw axis in the base frame (z = 0).

    A point p_b of the base frame is, with the base at odometry pose (x, y, yaw), at
    (x, y, 0) + pivot + Rz(yaw) (p_b - pivot) in the world.
    """

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_model(cls, robot: Robot | str) -> ArmMount:
        """The mount of a mobile model (base joints ``base_x``, ``base_y``, ``base_yaw``):
        the pose of the arm's root body (the base body's child that carries the arm joints)
        with every joint at zero. A model without base joints: identity (arm frame = world)."""
        robot = load_robot(robot)
        names = robot.joint_names
        if not any(b in names for b in BASE_JOINTS):
            return cls()
        if not all(b in names for b in BASE_JOINTS):
            raise ModelError(f"{robot.name} has only some of the base joints {BASE_JOINTS}")
        m = robot.model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, b) for b in BASE_JOINTS]
        base_body = int(m.jnt_bodyid[jid[0]])
        if any(int(m.jnt_bodyid[j]) != base_body for j in jid):
            raise ModelError(f"{robot.name}: the base joints must all move one body")
        axes = [d.xaxis[j] for j in jid]
        types = [int(m.jnt_type[j]) for j in jid]
        slide, hinge = mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE
        expect = [(slide, [1, 0, 0]), (slide, [0, 1, 0]), (hinge, [0, 0, 1])]
        for j, (ty, ax), (want_ty, want_ax) in zip(
            jid, zip(types, axes, strict=True), expect, strict=True
        ):
            if ty != want_ty or not np.allclose(ax, want_ax, atol=1e-9):
                raise ModelError(
                    f"{robot.name}: base joint {m.joint(j).name} must be a "
                    f"{'slide' if want_ty == slide else 'hinge'} along world {want_ax}"
                )
        arm_joint = arm_joint_indices(robot)[0]
        body = int(m.jnt_bodyid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, names[arm_joint])])
        root = body
        while int(m.body_parentid[root]) != base_body:
            root = int(m.body_parentid[root])
            if root == 0:
                raise ModelError(f"{robot.name}: the arm is not carried by the base body")
        pivot = np.array([*d.xanchor[jid[2]][:2], 0.0])
        return cls(d.xpos[root].copy(), d.xmat[root].reshape(3, 3).copy(), pivot)

    def __post_init__(self) -> None:
        for name in ("position", "rotation", "pivot"):
            object.__setattr__(self, name, np.array(getattr(self, name), dtype=float))
        object.__setattr__(self, "_identity", bool(np.array_equal(self.rotation, np.eye(3))))
        object.__setattr__(self, "_no_pivot", not self.pivot.any())

    @property
    def identity_rotation(self) -> bool:
        """Whether the arm frame's axes are the base frame's."""
        return self._identity

    # ---- poses
    def arm_pose(self, base_pose) -> tuple[np.ndarray, np.ndarray]:
        """(origin (3,) m, rotation (3, 3)) of the arm frame in the world."""
        rz = _rz(float(base_pose[2]))
        origin = self._base_origin(base_pose) + rz @ self.position
        return origin, rz @ self.rotation

    def _base_origin(self, base_pose) -> np.ndarray:
        """World position of the base frame's origin at ``base_pose``."""
        if self._no_pivot:
            return np.array([base_pose[0], base_pose[1], 0.0])
        rz = _rz(float(base_pose[2]))
        return np.array([base_pose[0], base_pose[1], 0.0]) + self.pivot - rz @ self.pivot

    # ---- points
    def base_to_world(self, p, base_pose) -> np.ndarray:
        return self._base_origin(base_pose) + _rz(float(base_pose[2])) @ p

    def world_to_base(self, p, base_pose) -> np.ndarray:
        return _rz(float(base_pose[2])).T @ (p - self._base_origin(base_pose))

    def arm_to_base(self, p) -> np.ndarray:
        if self._identity:
            return self.position + p
        return self.position + self.rotation @ p

    def base_to_arm(self, p) -> np.ndarray:
        return self.rotation.T @ (p - self.position)

    def arm_to_world(self, p, base_pose) -> np.ndarray:
        return self.base_to_world(self.arm_to_base(p), base_pose)

    def world_to_arm(self, p, base_pose) -> np.ndarray:
        return self.base_to_arm(self.world_to_base(p, base_pose))


def arm_model(robot: Robot | str) -> Robot:
    """The arm-alone model the controllers work in: ``robot`` itself without base joints, else
    the model named by its ``jaxcomp_arm_model`` custom text (``mobile_gen3_lite`` ->
    ``gen3_lite``), reduced to the same current-controlled joints."""
    robot = load_robot(robot)
    if not any(b in robot.joint_names for b in BASE_JOINTS):
        return robot
    name = robot.custom_text("jaxcomp_arm_model")
    if name is None:
        raise ModelError(
            f"{robot.name} has base joints; name its arm-alone model in a custom text "
            "'jaxcomp_arm_model'"
        )
    want = tuple(robot.joint_names[j] for j in arm_joint_indices(robot))
    try:
        arm = load_robot(name, joints=want)
    except ModelError as exc:
        raise ModelError(f"{robot.name}'s arm model {name}: {exc}") from None
    if arm.joint_names != want:
        raise ModelError(f"{arm.name}'s joints {arm.joint_names} are not {robot.name}'s {want}")
    return arm


def mobile_model_name(robot: Robot) -> str:
    """The name of the model of the whole mobile manipulator that carries ``robot``'s arm:
    its ``jaxcomp_mobile_model`` custom text (``gen3_lite`` -> ``mobile_gen3_lite``), else
    ``robot``'s own name."""
    return robot.custom_text("jaxcomp_mobile_model") or robot.name


def arm_params(params: RobotParams | None, arm: Robot) -> RobotParams | None:
    """``params`` (e.g. identified on the mobile model) re-labelled for the arm-alone model
    ``arm`` (same joints and links: checked); None stays None (nominal)."""
    if params is None or params.model == arm.name:
        return params
    return dc_replace(params, model=arm.name).check(arm)


def check_site_mobility(robot: Robot, q: np.ndarray, site: str) -> None:
    """InputError unless the joints move ``site`` in all three directions at ``q`` (rad): the
    position Jacobian's smallest singular value must be at least ``MIN_MOBILITY`` of its
    largest (the Cartesian controllers need a position task of rank 3)."""
    sv = np.linalg.svd(np.asarray(robot.jacobian(q, site))[:3], compute_uv=False)
    rank = int(np.sum(sv > MIN_MOBILITY * sv[0])) if sv[0] > 0 else 0
    if rank < 3:
        raise InputError(
            f"the joints of {robot.name} ({', '.join(robot.joint_names)}) move its end effector "
            f"{site!r} in only {rank} of 3 directions at the start pose (position Jacobian "
            f"singular values {', '.join(f'{v:.3g}' for v in sv)} m/rad): Cartesian control "
            "needs 3; choose another end-effector site (--site) or other joints (--joints)"
        )


# ----------------------------------------------------------------------------- control laws


class _Law:
    """Adapter of a controller to the loop: mode, command, end-effector position (arm frame).

    The controller runs as its ``packed_step`` on one preallocated numpy vector (q | dq |
    previous command | target pos | vel | acc | measured current | live gains [| rot], see
    ``impedance_io.packed_slices``) that the loop fills in place: one host-to-device and one
    device-to-host copy per cycle. An impedance controller also estimates the external force
    (``estimate``: its diagnostics' current_model, external force and band, after ``run``).
    """

    def __init__(self, controller, arm: Arm):
        self.controller = controller
        if isinstance(controller, ImpedanceController):
            self.mode = ControlMode.CURRENT
            self.saturation = np.minimum(controller.joint.limit, arm.limits.current)
            self.limit = arm.limits.current.copy()
            self.unit = "A"
        elif isinstance(controller, VelocityController):
            self.mode = ControlMode.VELOCITY
            self.saturation = None
            self.limit = arm.limits.velocity.copy()
            self.unit = "rad/s"
        else:
            raise InputError(
                "controller must be an ImpedanceController or a VelocityController, got "
                f"{type(controller).__name__}"
            )
        if controller.n != arm.n:
            raise InputError(f"the controller has {controller.n} joints, the arm {arm.n}")
        n = self.n = controller.n
        self.x = np.zeros(controller.packed_size)  # the packed input, filled in place
        sl = packed_slices(n)
        self.target = self.x[sl["pos"].start : sl["acc"].stop]  # pos | vel | acc, arm frame
        self._prev = self.x[sl["prev"]]
        self._measured = self.x[sl["current"]]
        self.live = self.x[sl["live"]]  # K_d | D_d | friction compensation (impedance)
        self._rot = sl["rot"]
        self._current = self.mode is ControlMode.CURRENT
        #: whether ``run`` estimates the external force (an impedance controller)
        self.estimates = self._current
        if self.estimates:
            self.live[:] = controller.live
        part = estimate_slice(n)  # current_model | F | band, after the command (n)
        self._estimate = slice(n + part.start, n + part.stop)
        self.estimate = np.zeros(n + 6)

    def start(self, state: ArmState) -> None:
        """Reset the command memory to what the arm applies when it switches (measured
        current, clipped to the limits; zero velocity)."""
        if self._current:
            np.clip(state.current, -self.limit, self.limit, out=self._prev)
        else:
            self._prev[:] = 0.0

    @property
    def orientation(self) -> bool:
        """Whether the controller holds an orientation (needs ``rot``)."""
        gains = getattr(self.controller, "gains", None)
        return bool(getattr(gains, "orientation", False))

    def set_rot(self, rot: np.ndarray) -> None:
        """The target orientation (3, 3) in the arm frame (orientation gains only)."""
        self.x[self._rot] = rot.ravel()

    def run(self, q, dq, current) -> tuple[np.ndarray, np.ndarray]:
        """(command (n,) A or rad/s, end-effector position (3,) m, arm frame) at q, dq and
        the measured ``current`` (A) for the target already in ``self.target`` (and
        ``set_rot``); read-only views of one output. An impedance controller's
        current_model (n) A | external force (3) N | band (3) N, arm frame, are then in
        ``estimate`` (a view as well)."""
        n, x = self.n, self.x
        x[:n] = q
        x[n : 2 * n] = dq
        self._measured[:] = current
        out = np.asarray(self.controller.packed_step(x))
        cmd = out[:n]
        if self._current:
            self._prev[:] = cmd
            self.estimate = out[self._estimate]
        return cmd, out[n : n + 3]

    def command(self, value: np.ndarray) -> ArmCommand:
        if self._current:
            return ArmCommand(current=value)
        return ArmCommand(velocity=value)


# ----------------------------------------------------------------------------- recording


_EXTRA = {"target": (3,), "ee": (3,), "base": (3,)}


class _BlockWriter(RecordingWriter):
    """A ``RecordingWriter`` that takes whole blocks of samples (``append_block``) instead of
    one ``append`` per sample (~20 us each: eight small array copies, then a flush that stacks
    the per-sample rows again, holding the GIL for milliseconds). The blocks go into the
    writer's field buffers as arrays, which its ``flush`` saves as they are.
    (Worth moving into ``RecordingWriter`` itself; never mix with ``append``.)"""

    def append_block(self, t, q, dq, current, **extra) -> None:
        """Add k samples: t (k,) s, q, dq, current (k, n), the extra fields (k, ...)."""
        k = len(t)
        buf = self._buf
        buf["t"].extend(t.tolist())  # a list: the parent's flush tests it for emptiness
        blocks = {"q": q, "dq": dq, "current": current, **extra}
        blocks["joint"] = np.full(k, -1)
        blocks["direction"] = np.zeros(k, np.int64)
        for name, block in blocks.items():
            old = buf[name]
            block = np.ascontiguousarray(block)
            buf[name] = block if isinstance(old, list) else np.concatenate([old, block])
        self._count += k
        self.last_t = float(t[-1])
        if len(buf["t"]) >= self.flush_every:
            self.flush()


class _Recorder:
    """Per-sample rows into preallocated blocks of ``block`` samples (one row of
    t | q | dq | current | command | target | ee | base [| current_model | wrench |
    wrench_band] per cycle, the last three with ``estimate``), each full block handed to the
    writer (which flushes it to a part file): on a writer thread in real time (the loop
    never waits for the disk), inline in lock step. ``last_row`` is the row written last."""

    def __init__(self, writer: _BlockWriter, n: int, block: int, threaded: bool, estimate: bool):
        self.writer, self.n, self.block = writer, n, block
        widths = {"t": 1, "q": n, "dq": n, "current": n, "command": n}
        widths |= {"target": 3, "ee": 3, "base": 3}
        if estimate:
            widths |= {"current_model": n, "wrench": 3, "wrench_band": 3}
        stops = np.cumsum(list(widths.values()))
        self.columns = {
            name: slice(int(stop - w), int(stop))
            for (name, w), stop in zip(widths.items(), stops, strict=True)
        }
        self._cols = dict(self.columns, t=0)
        self.width = int(stops[-1])
        self._new()
        self.last_row = self.rows[0]
        self._error: BaseException | None = None
        self._queue: queue.Queue | None = None
        self._thread = None
        if threaded:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._run, name="jaxcomp-recorder", daemon=True)
            self._thread.start()

    def _new(self) -> None:
        self.rows = np.empty((self.block, self.width))
        self.i = 0

    def add(self, t, q, dq, current, command, frames, current_model=None) -> None:
        """One sample: t s, q, dq, current, command (n,), and ``frames`` the 9 floats target
        (world m) | ee (world m) | base pose (x m, y m, yaw rad) [| wrench (world N) | band
        (world N)], with the model's current (n,) A when estimating."""
        n = self.n
        row = self.rows[self.i]
        row[0] = t
        row[1 : 1 + n] = q
        row[1 + n : 1 + 2 * n] = dq
        row[1 + 2 * n : 1 + 3 * n] = current
        row[1 + 3 * n : 1 + 4 * n] = command
        if current_model is None:
            row[1 + 4 * n :] = frames
        else:
            row[1 + 4 * n : 10 + 4 * n] = frames[:9]
            row[10 + 4 * n : 10 + 5 * n] = current_model
            row[10 + 5 * n :] = frames[9:]
        self.last_row = row
        self.i += 1
        if self.i == self.block:
            self._emit()

    def _emit(self) -> None:
        if self.i == 0:
            return
        rows = self.rows[: self.i]
        self._new()
        if self._queue is not None:
            self._queue.put(rows)
        else:
            self._write(rows)

    def _write(self, rows: np.ndarray) -> None:
        self.writer.append_block(**{name: rows[:, col] for name, col in self._cols.items()})

    def _run(self) -> None:
        while True:
            rows = self._queue.get()
            if rows is None:
                return
            try:
                self._write(rows)
            except BaseException as exc:  # noqa: BLE001 - reported by close()
                self._error = exc
                return

    def close(self) -> Recording:
        """Write what is left, wait for the writer thread, join the parts."""
        self._emit()
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
        if self._error is not None:
            raise self._error
        return self.writer.close()


# ----------------------------------------------------------------------------- result


@dataclass
class ControlResult:
    """How a run ended and what it measured.

    Attributes:
        kind: "completed", "stopped" (``RunLink.stop``), "interrupted" (Ctrl-C), a watchdog
            trip kind
            (``control.watchdog``; "not_tracking": the end effector stayed off its target),
            "hardware_fault" (a simulator's instability too), "command_refused" or "error".
        reason: one readable line.
        cycles: ``arm.cycle`` calls made (the last may be the one that tripped).
        duration: s of robot time controlled (to the last state received).
        rms_error: m, RMS of |ee - target| over the run (world frame). final_error: m, the
            last sample's. max_error: m.
        recording: the joined ``Recording`` (None if nothing was recorded).
        out_dir, recording_path, timing_path: where the files are.
        timing: ``CycleTimer.summary()``.
        stop_errors: problems met while stopping (empty when the stop was clean).
        file_error: why the recording or timing.json could not be written (read-only, full
            disk), None when they were.
    """

    kind: str
    reason: str
    cycles: int = 0
    duration: float = 0.0
    rms_error: float = math.nan
    final_error: float = math.nan
    max_error: float = math.nan
    recording: Recording | None = None
    out_dir: Path | None = None
    recording_path: Path | None = None
    timing_path: Path | None = None
    timing: dict = field(default_factory=dict)
    stop_errors: list[str] = field(default_factory=list)
    file_error: str | None = None
    trajectory: str = ""
    mode: str = ""

    @property
    def ok(self) -> bool:
        """True when the run completed, or was stopped or interrupted by the user (no
        fault)."""
        return self.kind in ("completed", "stopped", "interrupted")

    def summary(self) -> str:
        """A few readable lines: how it ended, tracking error, timing."""
        tm = self.timing
        lines = [
            f"{self.mode} mode, {self.trajectory}",
            f"ended: {self.kind} ({self.reason})",
            f"duration {self.duration:.3f} s, {self.cycles} cycles",
            f"tracking error |ee - target|: RMS {1e3 * self.rms_error:.2f} mm, "
            f"max {1e3 * self.max_error:.2f} mm, final {1e3 * self.final_error:.2f} mm",
        ]
        if tm.get("cycles"):
            c, p = tm["compute"], tm["period"]
            speed, cpu = tm.get("speed_x_realtime"), tm.get("speed_x_realtime_cpu")
            lines.append(
                f"timing ({tm['mode']}): compute median {c['median_us']:.0f} us, p99 "
                f"{c['p99_us']:.0f} us, max {c['max_us']:.0f} us; period median "
                f"{p.get('median_us', math.nan):.0f} us, p99 {p.get('p99_us', math.nan):.0f} us,"
                f" max {p.get('max_us', math.nan):.0f} us; missed deadlines "
                f"{tm['missed_deadlines']} ({100 * tm['missed_fraction']:.2f} %)"
                + (f"; {speed:.1f}x real time" if speed else "")
                + (f" ({cpu:.1f}x per CPU second)" if speed and cpu else "")
            )
        if self.recording_path is not None:
            lines.append(f"recording: {self.recording_path}")
        if self.timing_path is not None:
            lines.append(f"timing: {self.timing_path}")
        lines += [f"stop problem: {e}" for e in self.stop_errors]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- the loop


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
    on_cycle: Callable[[int, ArmState, np.ndarray, np.ndarray], None] | None = None,
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
        max_error: m, a run whose end effector stays further than this from its target for
            more than ``max_error_time`` s ends with ``not_tracking``; None: in tracking mode
            twice the controller's error clip, in guidance mode never; ``math.inf``: never
            (ignored with ``watchdog``).
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

    Returns a ``ControlResult``; raises only on setup errors (``JaxcompError``, nothing was
    switched) and on unexpected exceptions (after the safe stop and saving the recording).
    """
    mode = Mode(mode.value if isinstance(mode, Mode) else str(mode).lower())
    run = _set_up(
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
    if link.monitor is not None:
        start = MonitorStart(
            run.mode.value,
            getattr(run.work.traj, "description", ""),
            run.recorder.columns,
            run.timer,
            run.duration,
        )
        _notify(link.monitor.started, start)
    end = _loop(run, arm, base, realtime, on_cycle, link)
    result = _finish(run, end)
    if link.monitor is not None:
        _notify(link.monitor.ended, result)
    if end.unexpected is not None:
        raise end.unexpected
    if end.kind == FAULT:
        log.warning("control ended on an actuator fault: %s", end.reason)
    return result


def _notify(call: Callable[[Any], None], what: Any) -> None:
    """``call(what)``, a monitor's: its failure is logged, never raised."""
    try:
        call(what)
    except Exception as exc:  # noqa: BLE001 - a monitor never ends a run
        log.error("the run's monitor failed: %s", exc)


@dataclass
class _Run:
    """What the set-up of ``run_control`` prepared for the loop: the law and its watchdog,
    the per-cycle work, the start state (healthy and still), the number of cycles, the
    output directory, the recorder and the cycle timer."""

    mode: Mode
    law: _Law
    watchdog: Watchdog
    work: _Cycle
    state: ArmState
    n_cycles: int
    duration: float
    out: Path
    recorder: _Recorder
    timer: CycleTimer


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


def default_max_error(mode: Mode | str, controller) -> float:
    """m: how far the end effector may stay from its target (``run_control``'s ``max_error``
    when none is given): in tracking mode twice the controller's error clip; in guidance mode
    no limit (inf), as a person may hold the arm off its target at will."""
    if Mode(mode) is Mode.GUIDANCE:
        return math.inf
    return 2.0 * float(getattr(controller.gains, "error_clip", 0.1))


def _set_up(
    arm: Arm,
    base: Base | None,
    controller: ImpedanceController | VelocityController,
    mode: Mode,
    trajectory: TrajectorySpec | Trajectory | str | None,
    duration: float | None,
    out_dir: str | Path,
    realtime: bool,
    *,
    mount: ArmMount | None,
    base_gains: BaseGains | None,
    model: str | None,
    watchdog: Watchdog | None,
    max_saturated_cycles: int,
    base_velocity_compensation: bool,
    default_duration: float,
    max_error: float | None,
    max_error_time: float,
    before_start: Callable[[float], None] | None,
    stall_limit: float | None,
) -> _Run:
    """The set-up of ``run_control`` (its arguments): check that the arm is healthy and
    still, resolve the frames and the trajectory, compile and check the first command, open
    the recording; nothing is switched (a ``JaxcompError`` here leaves the robot as it was)."""
    law = _Law(controller, arm)
    robot = controller.robot
    if model is None:
        model = mobile_model_name(robot) if base is not None else robot.reference
    if mount is None:
        mount = ArmMount.from_model(model) if base is not None else ArmMount()
    out = Path(out_dir)
    if not (math.isfinite(max_error_time) and max_error_time > 0):
        raise InputError(f"max_error_time must be a positive number of s, got {max_error_time}")
    if max_error is None:
        max_error = default_max_error(mode, controller)
    wd = watchdog or Watchdog(
        arm.joint_names,
        law.limit,
        law.saturation,
        max_saturated_cycles=max_saturated_cycles,
        stale_cycles=arm.stale_tolerance,
        max_gap=stall_limit if realtime else None,
        unit=law.unit,
        max_error=max_error,
        max_error_cycles=max(int(round(max_error_time / CONTROL_PERIOD)), 1),
    )
    follower = BaseFollower(base_gains, base.limits) if base is not None else None

    # ---- the start: healthy, still
    state = arm.read()
    wd.check_state(state)
    if arm.closed:
        raise HardwareFault("the arm is closed")
    fast = np.abs(state.dq) > arm.limits.switch_speed
    if fast.any():
        j = int(np.flatnonzero(fast)[0])
        raise InputError(
            f"{arm.joint_names[j]} moves at {state.dq[j]:.3f} rad/s: the arm must be still "
            f"(below {arm.limits.switch_speed:.3f} rad/s) to start"
        )
    odom0 = base.odometry() if base is not None else None
    pose0 = np.array(odom0.pose, float) if odom0 is not None else np.zeros(3)
    if odom0 is not None:
        wd.check_odometry(odom0.pose, odom0.twist, state.t)
    check_site_mobility(robot, state.q, controller.site)
    ee0, rot0 = (np.asarray(x, dtype=float) for x in robot.site_pose(state.q, controller.site))
    guidance = mode is Mode.GUIDANCE
    if guidance:  # trajectory frame = base frame
        start, origin, rot = mount.arm_to_base(ee0), mount.position, mount.rotation
    else:
        start = mount.arm_to_world(ee0, pose0)
        origin, rot = mount.arm_pose(pose0)
    if trajectory is None:
        traj: Trajectory = Static(start, description="static at the start position")
    elif isinstance(trajectory, Trajectory):
        traj = trajectory
    else:
        spec = parse_trajectory(trajectory) if isinstance(trajectory, str) else trajectory
        traj = spec.build(start, origin, rot)
    if duration is None:
        duration = traj.duration if 0 < traj.duration < math.inf else default_duration
    duration = float(duration)
    if not (math.isfinite(duration) and duration > 0):
        raise InputError(f"duration must be a positive number of s, got {duration}")
    n_cycles = int(round(duration / CONTROL_PERIOD))
    if guidance or base is None:  # the arm alone must reach every target
        reach = arm_reach(robot, controller.site)
        o = mount.arm_to_base(reach.origin)  # in the trajectory's frame:
        o = o if guidance else mount.base_to_world(o, pose0)
        check_reachable(traj, duration, o, reach.radius, robot.name)
    if before_start is not None:
        before_start(duration)
    desired_b = mount.arm_to_base(ee0)  # tracking: the base keeps the EE where it started

    # ---- compile and check the first command before anything is switched
    work = _Cycle(
        law,
        wd,
        traj,
        state.t,
        base,
        follower,
        mount,
        guidance,
        desired_b,
        None,
        base_velocity_compensation,
    )
    if law.orientation:
        work.hold_orientation(rot0, pose0)
    law.start(state)
    wd.check_command(work.first_command(state, pose0), state.t)
    law.start(state)

    out.mkdir(parents=True, exist_ok=True)
    extra = {**_EXTRA, "command": (arm.n,)}
    if law.estimates:
        extra |= {"current_model": (arm.n,), "wrench": (3,), "wrench_band": (3,)}
    writer = _BlockWriter(
        out / RECORDING,
        model,
        arm.n,
        extra=extra,
        joints=tuple(arm.joint_names),
        flush_every=1000,
        require_sweep=False,
    )
    recorder = _Recorder(writer, arm.n, 1000, realtime, law.estimates)
    capacity = min(n_cycles + 2, TIMER_CAPACITY)  # longer runs grow it (by doubling)
    timer = CycleTimer(CONTROL_PERIOD, capacity=capacity, realtime=realtime)
    work.recorder = recorder
    return _Run(mode, law, wd, work, state, n_cycles, duration, out, recorder, timer)


def _loop(
    run: _Run,
    arm: Arm,
    base: Base | None,
    realtime: bool,
    on_cycle: Callable[[int, ArmState, np.ndarray, np.ndarray], None] | None,
    link: RunLink,
) -> _End:
    """The loop of ``run_control``: switch the arm to the law's mode, then one command per
    cycle (on 1 kHz deadlines in real time, else in lock step) until ``run.n_cycles`` cycles,
    a stop request, a watchdog trip, a hardware fault, a refused command, Ctrl-C or any
    exception; always ends with ``safe_stop`` (arm in POSITION mode, base stopped)."""
    law, wd, work, timer = run.law, run.watchdog, run.work, run.timer
    state = run.state
    stop, monitor = link.stop, link.monitor
    tuning = link.tuning if law.estimates else None
    every = max(int(monitor.every), 1) if monitor is not None else 0
    tuned = 0  # the version of the tuning applied
    kind, reason = "completed", f"ran the full {run.duration:g} s"
    stop_errors: list[str] = []
    cycles = 0
    t0 = state.t
    unexpected: BaseException | None = None
    switch_interval = sys.getswitchinterval()
    period_ns = int(CONTROL_PERIOD * 1e9)
    gc_enabled = gc.isenabled()
    try:
        if realtime:
            sys.setswitchinterval(1e-4)  # the recorder thread yields the GIL quickly
        # no collector pauses inside the loop: it frees its garbage by reference counting
        gc.disable()
        arm.set_modes(law.mode)
        law.start(state)
        if tuning is not None and tuning.version != tuned:
            tuned = tuning.version
            law.live[:] = tuning.values
            tuning.applied = tuned
        cmd = work(state)
        if on_cycle is not None:
            on_cycle(0, state, cmd, work.target_w)
        deadline = time.perf_counter_ns() + period_ns
        for k in range(1, run.n_cycles + 1):
            if realtime:
                wait_until(deadline)
            if stop is not None and stop.is_set():
                kind, reason = "stopped", "stopped on request"
                break
            cycles = k
            sent = time.perf_counter_ns()
            state = arm.cycle(law.command(cmd))
            recv = time.perf_counter_ns()
            wd.check_state(state, recv if realtime else None)
            if tuning is not None and tuning.version != tuned:  # new live gains, from now on
                tuned = tuning.version
                law.live[:] = tuning.values
                tuning.applied = tuned
            cmd = work(state)
            if on_cycle is not None:
                on_cycle(k, state, cmd, work.target_w)
            done = time.perf_counter_ns()
            deadline += period_ns  # the next send: the command must be ready by then
            timer.record(sent, recv, done, deadline if realtime else sent + period_ns)
            if realtime and done > deadline:  # a whole tick lost: skip it, keep the phase
                deadline += -(-(done - deadline) // period_ns) * period_ns
            if every and k % every == 0:
                try:
                    monitor.sample(k, run.recorder.last_row)
                except Exception as exc:  # noqa: BLE001 - a monitor never ends a run
                    log.error("the run's monitor failed and was dropped: %s", exc)
                    every = 0
    except WatchdogTrip as exc:
        kind, reason = exc.kind, str(exc)
    except HardwareFault as exc:
        kind, reason = "hardware_fault", str(exc)
    except InputError as exc:  # the arm refused a command (the watchdog should have caught it)
        kind, reason = "command_refused", str(exc)
    except KeyboardInterrupt:
        kind, reason = "interrupted", "Ctrl-C"
    except BaseException as exc:
        kind, reason = "error", f"{type(exc).__name__}: {exc}"
        unexpected = exc
    finally:
        stop_errors = safe_stop(arm, base)
        sys.setswitchinterval(switch_interval)
        if gc_enabled:
            gc.enable()
        timer.finish(state.t - t0)
    return _End(kind, reason, cycles, state.t - t0, stop_errors, unexpected)


class _Cycle:
    """The work of one cycle after its state arrived: targets, command, checks, base twist,
    one recorded sample; accumulates the tracking error |ee - target| (world, m).

    The frame maths (base odometry, mount, target) is done on Python floats and written
    straight into the controller's packed input: no small numpy arrays per cycle."""

    def __init__(
        self, law, wd, traj, t0, base, follower, mount, guidance, desired_b, recorder, compensate
    ):
        self.law, self.wd, self.traj, self.t0 = law, wd, traj, t0
        self.base, self.follower, self.mount = base, follower, mount
        self.guidance, self.desired_b = guidance, desired_b
        self.recorder, self.compensate = recorder, compensate
        self._pm = tuple(float(v) for v in mount.position)
        self._rm = tuple(float(v) for v in mount.rotation.ravel())  # row-major
        self._pivot = (float(mount.pivot[0]), float(mount.pivot[1]))
        self._desired = tuple(float(v) for v in desired_b)
        self.sq_sum, self.max_err, self.last_err, self.samples = 0.0, 0.0, math.nan, 0
        self.rot_b = None  # target orientation of the end effector in the base frame (guidance)
        self.rot_w = None  # ... in the world (tracking)
        self._target_w = (0.0, 0.0, 0.0)  # the last target, world m

    @property
    def target_w(self) -> np.ndarray:
        """(3,) m, the last target in the world."""
        return np.array(self._target_w)

    def hold_orientation(self, rot_a: np.ndarray, pose0: np.ndarray) -> None:
        """Keep the end effector's orientation ``rot_a`` (arm frame, at the start) fixed in
        the mode's frame (base frame in guidance, world in tracking)."""
        rot_b = self.mount.rotation @ rot_a
        if self.guidance:
            self.rot_b = rot_b
        else:
            self.rot_w = _rz(float(pose0[2])) @ rot_b

    def rot(self, yaw: float) -> np.ndarray | None:
        """The target orientation in the arm frame now, at base yaw ``yaw`` rad (None: no
        orientation task)."""
        rm = self.mount.rotation
        if self.rot_b is not None:
            return rm.T @ self.rot_b
        if self.rot_w is not None:
            return rm.T @ (_rz(yaw).T @ self.rot_w)
        return None

    def targets(self, t: float, px, py, yaw, vx, vy, wz, compensate: bool):
        """Write the target at time t (s from the start) into the controller's input (arm
        frame: pos m, vel m/s relative to the moving arm base when ``compensate``, acc m/s^2)
        for the base at odometry pose (px, py, yaw) moving at twist (vx, vy, wz); returns the
        target in the base frame and the world and the frame (cos yaw, sin yaw, origin)."""
        sample = self.traj(t)
        (p0, p1, p2), (v0, v1, v2), (a0, a1, a2) = (
            sample.pos.tolist(),
            sample.vel.tolist(),
            sample.acc.tolist(),
        )
        c, s = math.cos(yaw), math.sin(yaw)
        qx, qy = self._pivot  # base origin in the world: (px, py, 0) + pivot - Rz pivot
        ox, oy = px + qx - (c * qx - s * qy), py + qy - (s * qx + c * qy)
        if self.guidance:  # the trajectory is in the base frame
            tb = (p0, p1, p2)
            tw = (ox + c * p0 - s * p1, oy + s * p0 + c * p1, p2)
        else:  # in the world: to the base frame (Rz^T)
            tw = (p0, p1, p2)
            dx, dy = p0 - ox, p1 - oy
            tb = (c * dx + s * dy, -s * dx + c * dy, p2)
            v0, v1 = c * v0 + s * v1, -s * v0 + c * v1
            a0, a1 = c * a0 + s * a1, -s * a0 + c * a1
            if compensate:  # minus the base's velocity at the target point (base frame)
                v0 -= vx - wz * tb[1]
                v1 -= vy + wz * tb[0]
        m, (m0, m1, m2) = self._rm, self._pm  # arm frame: Rm^T (x_b - p_m)
        e0, e1, e2 = tb[0] - m0, tb[1] - m1, tb[2] - m2
        self.law.target[:] = (
            m[0] * e0 + m[3] * e1 + m[6] * e2,
            m[1] * e0 + m[4] * e1 + m[7] * e2,
            m[2] * e0 + m[5] * e1 + m[8] * e2,
            m[0] * v0 + m[3] * v1 + m[6] * v2,
            m[1] * v0 + m[4] * v1 + m[7] * v2,
            m[2] * v0 + m[5] * v1 + m[8] * v2,
            m[0] * a0 + m[3] * a1 + m[6] * a2,
            m[1] * a0 + m[4] * a1 + m[7] * a2,
            m[2] * a0 + m[5] * a1 + m[8] * a2,
        )
        return tb, tw, c, s, ox, oy

    def first_command(self, state: ArmState, pose0: np.ndarray) -> np.ndarray:
        """The command for ``state`` at the start (t = 0, base at rest at ``pose0``), with no
        side effect but the controller's input (the setup check)."""
        px, py, yaw = (float(v) for v in pose0)
        self.targets(0.0, px, py, yaw, 0.0, 0.0, 0.0, False)
        if self.rot_b is not None or self.rot_w is not None:
            self.law.set_rot(self.rot(yaw))
        return self.law.run(state.q, state.dq, state.current)[0]

    def wrench_world(self, c: float, s: float) -> tuple[float, ...]:
        """The law's external force estimate (arm frame) in the world at base yaw (cos c,
        sin s): force (3) N | band (3) N, the band the world-axis box around the rotated one
        (|R| b, R = Rz(yaw) Rm)."""
        f0, f1, f2, b0, b1, b2 = self.law.estimate[self.law.n :].tolist()
        m = self._rm
        r00, r01, r02 = c * m[0] - s * m[3], c * m[1] - s * m[4], c * m[2] - s * m[5]
        r10, r11, r12 = s * m[0] + c * m[3], s * m[1] + c * m[4], s * m[2] + c * m[5]
        r20, r21, r22 = m[6], m[7], m[8]
        return (
            r00 * f0 + r01 * f1 + r02 * f2,
            r10 * f0 + r11 * f1 + r12 * f2,
            r20 * f0 + r21 * f1 + r22 * f2,
            abs(r00) * b0 + abs(r01) * b1 + abs(r02) * b2,
            abs(r10) * b0 + abs(r11) * b1 + abs(r12) * b2,
            abs(r20) * b0 + abs(r21) * b1 + abs(r22) * b2,
        )

    def __call__(self, state: ArmState) -> np.ndarray:
        if self.base is not None:
            odom = self.base.odometry()
            pose, twist = odom.pose, odom.twist
            self.wd.check_odometry(pose, twist, state.t)
            px, py, yaw = pose.tolist()
            vx, vy, wz = twist.tolist()
        else:
            px = py = yaw = vx = vy = wz = 0.0
        q = state.q
        tb, tw, c, s, ox, oy = self.targets(
            state.t - self.t0, px, py, yaw, vx, vy, wz, self.compensate
        )
        if self.rot_b is not None or self.rot_w is not None:
            self.law.set_rot(self.rot(yaw))
        cmd, ee_a = self.law.run(q, state.dq, state.current)
        self.wd.check_command(cmd, state.t)
        m, (m0, m1, m2) = self._rm, self._pm  # ee in the base frame: p_m + Rm ee_a
        a0, a1, a2 = ee_a.tolist()
        eb = (
            m0 + m[0] * a0 + m[1] * a1 + m[2] * a2,
            m1 + m[3] * a0 + m[4] * a1 + m[5] * a2,
            m2 + m[6] * a0 + m[7] * a1 + m[8] * a2,
        )
        if self.follower is not None:
            p_d = tb if self.guidance else self._desired
            self.base.send_twist(self.follower.twist(eb, p_d, q))
        self._target_w = tw
        frames = (*tw, ox + c * eb[0] - s * eb[1], oy + s * eb[0] + c * eb[1], eb[2], px, py, yaw)
        if self.law.estimates:
            frames += self.wrench_world(c, s)
            model = self.law.estimate[: self.law.n]
        else:
            model = None
        self.recorder.add(state.t, q, state.dq, state.current, cmd, frames, model)
        d0, d1, d2 = eb[0] - tb[0], eb[1] - tb[1], eb[2] - tb[2]
        e2 = d0 * d0 + d1 * d1 + d2 * d2
        self.sq_sum += e2
        self.last_err = math.sqrt(e2)
        if self.last_err > self.max_err:
            self.max_err = self.last_err
        self.samples += 1
        self.wd.check_error(self.last_err, state.t - self.t0)
        return cmd


def _finish(run: _Run, end: _End) -> ControlResult:
    """Join the recording, write timing.json, fill the result; never raises."""
    work, out, recorder, timer = run.work, run.out, run.recorder, run.timer
    kind, reason, cycles = end.kind, end.reason, end.cycles
    result = ControlResult(
        kind=kind,
        reason=reason,
        cycles=cycles,
        duration=max(float(end.duration), 0.0),
        out_dir=out,
        stop_errors=list(end.stop_errors),
        trajectory=getattr(work.traj, "description", ""),
        mode=run.mode.value,
    )
    if work.samples:
        result.rms_error = math.sqrt(work.sq_sum / work.samples)
        result.final_error, result.max_error = work.last_err, work.max_err
    try:
        result.recording = recorder.close()
        result.recording_path = out / RECORDING
    except (OSError, FileError) as exc:  # read-only, full disk
        result.file_error = f"the recording was not written: {file_problem(exc)}"
        log.error(result.file_error)
    except Exception as exc:  # noqa: BLE001 - e.g. too few samples to make a recording
        result.stop_errors.append(f"recording not joined: {exc}")
        log.error("recording not joined: %s", exc)
    try:
        result.timing = timer.summary()
        run_info: dict[str, Any] = {
            "run": {
                "mode": result.mode,
                "trajectory": result.trajectory,
                "kind": kind,
                "reason": reason,
                "cycles": cycles,
                "duration_s": result.duration,
                "rms_error_m": None if math.isnan(result.rms_error) else result.rms_error,
                "max_error_m": None if math.isnan(result.max_error) else result.max_error,
            }
        }
        result.timing_path = timer.dump(out / TIMING, run_info)
    except (OSError, FileError) as exc:
        result.file_error = result.file_error or f"{TIMING} was not written: {file_problem(exc)}"
    except Exception as exc:  # noqa: BLE001
        result.stop_errors.append(f"timing.json not written: {exc}")
    return result


__all__ = [
    "ArmMount",
    "ControlResult",
    "Mode",
    "arm_model",
    "arm_params",
    "mobile_model_name",
    "run_control",
]
