"""The robot interface that identification and control drive: ``Arm`` and ``Base``.

An ``Arm`` runs at 1 kHz: each ``cycle(command)`` sends this cycle's command and returns the
next measured state (lock-step in simulation, the UDP Refresh on the real arm). Every joint is
in one of three modes (``ControlMode``): POSITION and VELOCITY use the robot's own stiff servo,
CURRENT drives the motor current directly. The base class validates every command (shape, NaN,
limits) before a backend sees it, keeps the per-joint targets, and provides ``move_to`` and a
context manager that always ends in position mode. A ``Base`` takes a body twist and reports
odometry. Units: rad, rad/s, A, s; twist m/s and rad/s in the base frame.
"""

from __future__ import annotations

import abc
import enum
import math
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError, JaxcompError
from jaxcomp.hardware.mecanum import TwistLimits
from jaxcomp.hardware.move_profile import move_path
from jaxcomp.reduction import BASE_JOINTS
from jaxcomp.robot_params import current_limits


class ControlMode(enum.Enum):
    """Per-joint control mode."""

    POSITION = "position"
    VELOCITY = "velocity"
    CURRENT = "current"


class HardwareFault(JaxcompError):
    """The robot reported a fault or broke its protocol; the arm was put in a safe state.

    Attributes: faults (readable strings), state (the last ArmState, or None).
    """

    def __init__(self, message: str, faults: Sequence[str] = (), state: ArmState | None = None):
        super().__init__(message)
        self.faults = tuple(faults)
        self.state = state


@dataclass(slots=True)
class ArmState:
    """One measurement of the arm.

    Attributes:
        t: time, s (simulation time, or the adapter's clock).
        q: (n,) joint positions, rad. dq: (n,) joint velocities, rad/s.
        current: (n,) measured motor currents, A.
        faults: readable fault descriptions; empty = healthy.
        modes: the control mode of each joint.
        jitter_us: communication jitter of this cycle, us (0 in simulation).
    """

    t: float
    q: np.ndarray
    dq: np.ndarray
    current: np.ndarray
    faults: tuple[str, ...] = ()
    modes: tuple[ControlMode, ...] = ()
    jitter_us: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.faults


_HUGE = 1e300


class ArmCommand(NamedTuple):
    """One cycle's targets; each field (n,) or None (keep the previous target).

    Each joint uses the field of its mode: ``position`` rad (POSITION), ``velocity`` rad/s
    (VELOCITY), ``current`` A (CURRENT). Entries of joints in other modes are ignored (but must
    still be finite).
    """

    position: np.ndarray | None = None
    velocity: np.ndarray | None = None
    current: np.ndarray | None = None


_FIELD_INFO = {
    ControlMode.POSITION: ("position", "rad"),
    ControlMode.VELOCITY: ("velocity", "rad/s"),
    ControlMode.CURRENT: ("current", "A"),
}


@dataclass(frozen=True)
class ArmLimits:
    """Command limits of an arm.

    Attributes:
        position: (n, 2) rad, the range position targets must stay in (joint limits less a
            margin). hard_position: (n, 2) rad, the joint limits themselves.
        velocity: (n,) rad/s, speed limit of velocity targets and ``move_to``.
        current: (n,) A, magnitude limit of current commands.
        effort: (n,) N m, actuator torque limits.
        switch_speed: rad/s, a joint moving faster may not switch to CURRENT mode.
    """

    position: np.ndarray
    hard_position: np.ndarray
    velocity: np.ndarray
    current: np.ndarray
    effort: np.ndarray
    switch_speed: float = math.radians(10.0)

    @classmethod
    def from_robot(
        cls,
        robot,
        joints: Sequence[int] | None = None,
        margin: float = math.radians(1.0),
        velocity: float = 1.0,
        switch_speed: float = math.radians(10.0),
    ) -> ArmLimits:
        """Limits from a ``jaxcomp.Robot``: joint ranges, current limits (``current_limits``),
        effort limits.

        Args:
            robot: the ``jaxcomp.Robot``.
            joints: the arm's n joints, indices into ``robot.joint_names`` (default: all).
            margin: rad off both ends of each joint range for position targets.
            velocity: rad/s, every joint's speed limit. switch_speed: rad/s (see above).

        Returns:
            The ``ArmLimits`` of the selected joints, in ``joints`` order.

        Raises:
            InputError: ``joints`` include a mobile-base joint.
        """
        idx = np.arange(robot.nv) if joints is None else np.asarray(joints, int)
        hard = robot.joint_limits[idx]
        n = len(idx)
        arm = [i for i, name in enumerate(robot.joint_names) if name not in BASE_JOINTS]
        if not set(idx.tolist()) <= set(arm):
            raise InputError(f"joints {idx.tolist()} of {robot.name} include base joints")
        cur = current_limits(robot)[[arm.index(i) for i in idx]]
        return cls(
            position=hard + np.array([margin, -margin]),
            hard_position=hard,
            velocity=np.full(n, float(velocity)),
            current=cur,
            effort=robot.effort_limits[idx].copy(),
            switch_speed=switch_speed,
        )


def _array(value, name: str, n: int, joints: Sequence[str]) -> np.ndarray:
    """``value`` as a finite (n,) array, or the InputError of ``checks.array`` (nothing sent)."""
    try:
        return checks.array(value, name, n=n, labels=joints)
    except InputError as err:
        raise InputError(f"{err}; nothing was sent") from None


def _check_range(arr, lo, hi, name: str, unit: str, joints: Sequence[str], use) -> None:
    bad = use & ((arr < lo) | (arr > hi))
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{name} {arr[j]:.4g} {unit} for {joints[j]} is beyond its limits "
            f"[{np.broadcast_to(lo, arr.shape)[j]:.4g}, {np.broadcast_to(hi, arr.shape)[j]:.4g}] "
            f"{unit}; nothing was sent"
        )


class Arm(abc.ABC):
    """A current-controllable arm at 1 kHz (simulated or real).

    Subclasses implement the backend hooks ``_exchange``, ``_switch``, ``_shutdown`` (and
    optionally ``_clear_faults``, ``_after_fault``) and call ``_start(state)`` once their first
    state is measured. Everything else (validation, targets, modes, ``move_to``, the safe exit)
    lives here, identical for every backend.
    """

    dt = CONTROL_PERIOD
    #: Consecutive cycles whose state may repeat the previous one without being stale
    #: feedback (a backend that tolerates lost replies returns the last state for them).
    stale_tolerance = 0
    #: s: how long before the reported pose the reported current flowed (a recording's
    #: ``current_lag``). 0: measured together (the real arm, whose actuators servo far
    #: faster than 1 kHz, is taken to report them so).
    current_lag = 0.0

    def __init__(self, joint_names: Sequence[str], limits: ArmLimits, poses: dict | None = None):
        self.joint_names = tuple(joint_names)
        self.n = len(self.joint_names)
        self.limits = limits
        self.poses = dict(poses or {})
        self._modes = [ControlMode.POSITION] * self.n
        self._position = np.zeros(self.n)
        self._velocity = np.zeros(self.n)
        self._current = np.zeros(self.n)
        self._state: ArmState | None = None
        self._raised: tuple[str, ...] = ()  # latched faults already raised as HardwareFault
        self._closed = False
        self._use = {m: np.zeros(self.n, bool) for m in ControlMode}
        self._update_use()

    # ----------------------------------------------------------------- backend hooks
    @abc.abstractmethod
    def _exchange(
        self,
        modes: tuple[ControlMode, ...],
        position: np.ndarray,
        velocity: np.ndarray,
        current: np.ndarray,
    ) -> ArmState:
        """Send one cycle's full targets (all (n,), validated) and return the next state."""

    @abc.abstractmethod
    def _switch(self, changes: dict[int, ControlMode]) -> None:
        """Switch the given joints' modes on the robot (already validated)."""

    @abc.abstractmethod
    def _shutdown(self) -> None:
        """Release the backend (all joints are already in position mode)."""

    def _clear_faults(self) -> None:  # noqa: B027 - optional hook
        """Clear latched faults on the robot."""

    def _after_fault(self, state: ArmState) -> None:  # noqa: B027 - optional hook
        """Called after a fault was reported and every joint was put in position mode."""

    # ----------------------------------------------------------------- state
    def _start(self, state: ArmState) -> None:
        self._state = state
        self._position = state.q.copy()
        self._current = np.zeros(self.n)
        self._velocity = np.zeros(self.n)

    def _update_use(self) -> None:
        lim = self.limits
        field_bounds = {
            ControlMode.POSITION: (lim.position[:, 0], lim.position[:, 1]),
            ControlMode.VELOCITY: (-lim.velocity, lim.velocity),
            ControlMode.CURRENT: (-lim.current, lim.current),
        }
        self._bounds = {}
        for mode, mask in self._use.items():
            mask[:] = [m is mode for m in self._modes]
            lo, hi = field_bounds[mode]
            # joints in other modes: any finite value passes (NaN and inf never do)
            self._bounds[mode] = (np.where(mask, lo, -_HUGE), np.where(mask, hi, _HUGE))
        # the same bounds as lists of floats for the per-cycle test
        self._bound_lists = {
            mode: (lo.tolist(), hi.tolist()) for mode, (lo, hi) in self._bounds.items()
        }
        self._all_position = bool(self._use[ControlMode.POSITION].all())
        self._all_current = bool(self._use[ControlMode.CURRENT].all())
        self._modes_tuple = tuple(self._modes)

    @property
    def modes(self) -> tuple[ControlMode, ...]:
        return tuple(self._modes)

    @property
    def closed(self) -> bool:
        return self._closed

    def read(self) -> ArmState:
        """The latest measured state (no command is sent)."""
        if self._state is None:
            raise HardwareFault("the arm has not been started")
        return self._state

    def _check_open(self) -> None:
        if self._closed:
            raise HardwareFault("the arm is closed; open a new one")

    # ----------------------------------------------------------------- commands
    def check_command(self, command: ArmCommand) -> ArmCommand:
        """Validate a command against shape, NaN and limits.

        Args:
            command: each field (n,) or None; limits apply to the joints in the field's mode.

        Returns:
            The command, each given field a float array (n,).

        Raises:
            InputError: a wrong shape, NaN or inf, or a target beyond the limits.
        """
        pos, vel, cur = command
        return ArmCommand(
            None if pos is None else self._check_field(pos, ControlMode.POSITION),
            None if vel is None else self._check_field(vel, ControlMode.VELOCITY),
            None if cur is None else self._check_field(cur, ControlMode.CURRENT),
        )

    def _check_field(self, value, mode: ControlMode) -> np.ndarray:
        arr = np.asarray(value, dtype=float)
        if arr.shape == (self.n,):
            # the fast path: one comparison per joint on floats catches NaN, inf and limits
            lo_list, hi_list = self._bound_lists[mode]
            values = arr.tolist()
            if all(map(operator.le, lo_list, values)) and all(map(operator.le, values, hi_list)):
                return arr
        lo, hi = self._bounds[mode]
        name, unit = _FIELD_INFO[mode]
        arr = _array(arr, f"{name} command", self.n, self.joint_names)
        _check_range(arr, lo, hi, name, unit, self.joint_names, self._use[mode])
        return arr

    def cycle(self, command: ArmCommand | None = None) -> ArmState:
        """Send this cycle's command (validated first) and return the next state (1 kHz).

        Args:
            command: this cycle's targets; None keeps every target.

        Returns:
            The next measured ``ArmState``; faults stay latched in the states (the arm in
            position mode) until ``clear_faults()``.

        Raises:
            InputError: a bad command (nothing is sent).
            HardwareFault: a new fault (every joint is then in position mode, holding), or the
                arm is closed.
        """
        if self._closed:
            self._check_open()
        if command is not None:
            pos, vel, cur = self.check_command(command)
            if pos is not None:
                if self._all_position:
                    self._position = pos.copy()
                else:
                    np.copyto(self._position, pos, where=self._use[ControlMode.POSITION])
            if vel is not None:
                np.copyto(self._velocity, vel, where=self._use[ControlMode.VELOCITY])
            if cur is not None:
                if self._all_current:
                    self._current = cur.copy()
                else:
                    np.copyto(self._current, cur, where=self._use[ControlMode.CURRENT])
        state = self._exchange(self._modes_tuple, self._position, self._velocity, self._current)
        self._state = state
        if state.faults and state.faults != self._raised:
            self._raised = state.faults
            self._fault(state)
        return state

    def _fault(self, state: ArmState) -> None:
        try:
            self._force_position()
            self._after_fault(state)
        finally:
            raise HardwareFault(
                "the arm reported fault(s): " + "; ".join(state.faults), state.faults, state
            )

    def _force_position(self) -> None:
        """Every joint to position mode holding its measured position (no checks)."""
        changes = {
            j: ControlMode.POSITION
            for j, m in enumerate(self._modes)
            if m is not ControlMode.POSITION
        }
        if self._state is not None:
            self._position = self._state.q.copy()
        self._velocity[:] = 0.0
        if changes:
            self._switch(changes)
            for j in changes:
                self._modes[j] = ControlMode.POSITION
            self._update_use()

    def _joint(self, joint: int | str) -> int:
        if isinstance(joint, str):
            if joint not in self.joint_names:
                raise InputError(f"unknown joint {joint!r}; joints: {', '.join(self.joint_names)}")
            return self.joint_names.index(joint)
        j = int(joint)
        if not 0 <= j < self.n:
            raise InputError(f"joint index {j} out of range 0..{self.n - 1}")
        return j

    def set_modes(self, modes: ControlMode | Sequence[ControlMode | None]) -> None:
        """Switch joints' control modes: one mode for all, or one per joint (None = keep).

        A joint switched to POSITION holds its measured position, to VELOCITY starts at 0
        rad/s, to CURRENT starts at its measured current (the latest measurement: a backend
        may measure while it switches).

        Args:
            modes: one ``ControlMode`` for all joints, or n entries (a ``ControlMode`` or None).

        Raises:
            InputError: not n entries, an unknown mode, leaving POSITION in fault, or CURRENT
                for a joint faster than ``limits.switch_speed`` (nothing is switched).
            HardwareFault: the arm is closed or not started.
        """
        self._check_open()
        if isinstance(modes, ControlMode):
            modes = [modes] * self.n
        modes = list(modes)
        if len(modes) != self.n:
            raise InputError(f"modes must name {self.n} joints, got {len(modes)}")
        for m in modes:
            if m is not None and not isinstance(m, ControlMode):
                raise InputError(f"unknown control mode {m!r}; use ControlMode.POSITION etc.")
        state = self.read()
        changes = {j: m for j, m in enumerate(modes) if m is not None and m is not self._modes[j]}
        if state.faults and any(m is not ControlMode.POSITION for m in changes.values()):
            raise InputError("the arm is in fault: clear_faults() before leaving position mode")
        for j, m in changes.items():
            if m is ControlMode.CURRENT and abs(state.dq[j]) > self.limits.switch_speed:
                raise InputError(
                    f"{self.joint_names[j]} moves at {state.dq[j]:.3f} rad/s, faster than "
                    f"{self.limits.switch_speed:.3f} rad/s: switching it to current mode is refused"
                )
        if not changes:
            return
        self._switch(changes)
        state = self._state  # measured during the switch, if the backend did
        for j, m in changes.items():
            self._modes[j] = m
            if m is ControlMode.POSITION:
                self._position[j] = state.q[j]
            elif m is ControlMode.VELOCITY:
                self._velocity[j] = 0.0
            else:
                self._current[j] = float(
                    np.clip(state.current[j], -self.limits.current[j], self.limits.current[j])
                )
        self._update_use()

    def set_mode(self, joint: int | str, mode: ControlMode) -> None:
        """Switch one joint; see ``set_modes`` (InputError also for an unknown joint).

        Args:
            joint: index into ``joint_names``, or the name. mode: its new ``ControlMode``.
        """
        modes: list[ControlMode | None] = [None] * self.n
        modes[self._joint(joint)] = mode
        self.set_modes(modes)

    def clear_faults(self) -> None:
        """Clear latched faults (the arm stays in position mode)."""
        self._check_open()
        self._clear_faults()
        self._raised = ()
        if self._state is not None:
            self._state = replace(self._state, faults=())

    # ----------------------------------------------------------------- motions
    def pose(self, pose: str | Sequence[float]) -> np.ndarray:
        """Joint positions of a named pose or an array, checked against the limits.

        Args:
            pose: a name in ``poses``, or (n,) rad.

        Returns:
            (n,) rad.

        Raises:
            InputError: an unknown name, a wrong shape, NaN or inf, or beyond ``limits.position``.
        """
        if isinstance(pose, str):
            if pose not in self.poses:
                raise InputError(f"unknown pose {pose!r}; known: {', '.join(self.poses)}")
            pose = self.poses[pose]
        q = _array(pose, "pose", self.n, self.joint_names)
        lim = self.limits.position
        _check_range(
            q, lim[:, 0], lim[:, 1], "pose", "rad", self.joint_names, np.ones(self.n, bool)
        )
        return q

    def move_to(
        self,
        pose: str | Sequence[float],
        speed: float,
        on_state: Callable[[ArmState], None] | None = None,
        accel: float | None = None,
        settle: float = 0.0,
    ) -> ArmState:
        """Move every joint to ``pose`` with the robot's own position servo; block until there.

        The joint with the longest way follows a trapezoidal profile (``move_path``): the others
        are scaled to arrive together, so each moves at constant speed between the ramps.

        Args:
            pose: a name in ``poses``, or (n,) rad.
            speed: rad/s of the longest way, in (0, the smallest ``limits.velocity``].
            on_state: called with every 1 kHz state (recording).
            accel: rad/s^2 of the ramps (default speed / 0.1 s). settle: s held at the end.

        Returns:
            The last ``ArmState``.

        Raises:
            InputError: a bad pose, speed or accel (nothing moves). HardwareFault: as ``cycle``.
        """
        target = self.pose(pose)
        speed = float(speed)
        if not (np.isfinite(speed) and 0 < speed <= float(self.limits.velocity.min())):
            raise InputError(
                f"speed must be in (0, {float(self.limits.velocity.min()):.3g}] rad/s, got {speed}"
            )
        accel = checks.number(
            speed / 0.1 if accel is None else accel, "accel", positive=True, unit="rad/s^2"
        )
        self.set_modes(ControlMode.POSITION)
        path = move_path(self._position.copy(), target, speed, accel, settle, self.dt)
        state = self.read()
        for ref in path:
            state = self.cycle(ArmCommand(position=ref))
            if on_state is not None:
                on_state(state)
        return state

    def hold(self, seconds: float, on_state: Callable[[ArmState], None] | None = None) -> ArmState:
        """Keep the current targets for ``seconds`` s (rounded to whole cycles).

        Args:
            seconds: s. on_state: called with every state.

        Returns:
            The last ``ArmState`` (the latest measured one for no cycle).
        """
        state = self.read()
        for _ in range(int(round(seconds / self.dt))):
            state = self.cycle()
            if on_state is not None:
                on_state(state)
        return state

    # ----------------------------------------------------------------- lifetime
    def close(self) -> None:
        """End in a safe state: every joint in position mode, then release the backend."""
        if self._closed:
            return
        try:
            self._force_position()
        finally:
            self._closed = True
            self._shutdown()

    def __enter__(self) -> Arm:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class BaseState:
    """Odometry of a mobile base.

    Attributes: t s; pose (3,) x m, y m, yaw rad in the odometry (world) frame;
    twist (3,) vx m/s, vy m/s, wz rad/s in the base frame.
    """

    t: float
    pose: np.ndarray
    twist: np.ndarray


class Base(abc.ABC):
    """A mobile base driven by a body twist, limited by ``limits`` (``TwistLimits``)."""

    def __init__(self, limits: TwistLimits):
        self.limits = limits
        self._closed = False

    @abc.abstractmethod
    def _send(self, twist: np.ndarray) -> None:
        """Forward a validated twist (3,) to the base."""

    @abc.abstractmethod
    def odometry(self) -> BaseState:
        """The latest odometry."""

    def _shutdown(self) -> None:  # noqa: B027 - optional hook
        """Release the backend (the base was told to stop)."""

    def send_twist(self, twist: Sequence[float]) -> None:
        """Command a body twist; the base keeps following it (within the acceleration limits)
        until a new command, or stops when none came for ``limits.timeout`` s.

        Args:
            twist: (3,) body twist (vx m/s, vy m/s, wz rad/s) in the base frame.

        Raises:
            InputError: a wrong shape, NaN or inf, or beyond ``limits.velocity``.
            HardwareFault: the base is closed.
        """
        if self._closed:
            raise HardwareFault("the base is closed")
        if type(twist) is np.ndarray and twist.shape == (3,) and twist.dtype == np.float64:
            # the fast path (1 kHz): within every limit, finite (NaN fails the comparison)
            vx, vy, wz = twist.tolist()
            lx, ly, lz = self.limits.velocity
            if abs(vx) <= lx + 1e-9 and abs(vy) <= ly + 1e-9 and abs(wz) <= lz + 1e-9:
                self._send(twist)
                return
        self._send(self.limits.check(twist))

    def stop(self) -> None:
        """Command zero twist (the base decelerates at its limits)."""
        self._send(np.zeros(3))

    def close(self) -> None:
        """Stop the base and release the backend."""
        if self._closed:
            return
        try:
            self.stop()
        finally:
            self._closed = True
            self._shutdown()

    def __enter__(self) -> Base:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
