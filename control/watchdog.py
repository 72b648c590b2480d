"""The control loop's watchdog: every state and every command is checked before it is used.

A trip raises ``WatchdogTrip`` (a ``JaxcompError``) naming what went wrong; the loop then puts
the arm in POSITION mode and stops the base before anything else (``safe_stop``). Checks:

- state: time that does not advance or data identical to the previous cycle's (stale
  feedback), NaN/inf in q, dq or current, an actuator fault reported in the state;
- odometry: NaN/inf in the base pose or twist;
- command: NaN/inf, a current beyond ``current_limit`` (A), a current held at the controller's
  saturation for more than ``max_saturated_cycles`` consecutive cycles;
- real time only: a gap of more than ``max_gap`` s between two cycles (the loop stalled);
- tracking: the end effector further than ``max_error`` m from its target for more than
  ``max_error_cycles`` consecutive cycles (it does not track: out of reach, blocked, held).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError, JaxcompError
from jaxcomp.hardware.interface import Arm, ArmState, Base, ControlMode

log = logging.getLogger(__name__)

#: Trip kinds (``WatchdogTrip.kind``).
STALE, NAN_STATE, FAULT, NAN_COMMAND, LIMIT, SATURATED, STALL, NAN_ODOMETRY, NOT_TRACKING = (
    "stale_feedback",
    "nan_state",
    "actuator_fault",
    "nan_command",
    "current_limit",
    "saturated",
    "loop_stall",
    "nan_odometry",
    "not_tracking",
)


class WatchdogTrip(JaxcompError):
    """A watchdog check failed. Attributes: kind (one of the module's trip kinds), t (s, the
    state's time, or None), joints (names of the joints concerned)."""

    def __init__(self, kind: str, message: str, t: float | None = None, joints=()):
        super().__init__(message)
        self.kind = kind
        self.t = t
        self.joints = tuple(joints)


class Watchdog:
    """State and command checks of one run (see module doc).

    Args:
        joint_names: the arm's joint names (messages).
        current_limit: (n,) A, magnitude a command may not exceed.
        saturation: (n,) A, the controller's own clip; a command at it (to 1e-9 A) for more
            than ``max_saturated_cycles`` consecutive cycles trips. None: no saturation check.
        max_saturated_cycles: cycles (1 ms each) a joint may stay saturated.
        stale_cycles: consecutive stale states tolerated (0: the first one trips).
        max_gap: s, the longest wall-clock gap between two cycles (real time only; None: off).
        unit: of the commands (messages): "A" for currents, "rad/s" for velocities.
        max_error: m, the end effector's distance from its target (``check_error``) that may
            last at most ``max_error_cycles`` consecutive cycles; None or inf: no check.
    """

    def __init__(
        self,
        joint_names,
        current_limit,
        saturation=None,
        *,
        max_saturated_cycles: int = 250,
        stale_cycles: int = 0,
        max_gap: float | None = None,
        unit: str = "A",
        max_error: float | None = None,
        max_error_cycles: int = 2000,
    ):
        self.joint_names = tuple(joint_names)
        self.n = len(self.joint_names)
        self.current_limit = np.broadcast_to(np.asarray(current_limit, float), (self.n,)).copy()
        self.saturation = (
            None
            if saturation is None
            else np.broadcast_to(np.asarray(saturation, float), (self.n,)).copy()
        )
        self.max_saturated_cycles = int(max_saturated_cycles)
        self.stale_cycles = int(stale_cycles)
        self.max_gap_ns = None if max_gap is None else int(max_gap * 1e9)
        self.unit = unit
        self._last: ArmState | None = None
        self._stale = 0
        self._saturated = np.zeros(self.n, np.int64)
        self._any_saturated = False
        self._sat_at = None if self.saturation is None else self.saturation - 1e-9
        self._last_ns: int | None = None
        self.max_error = math.inf if max_error is None else float(max_error)
        if not self.max_error > 0 or max_error_cycles < 1:
            raise InputError(
                f"max_error must be > 0 m and max_error_cycles >= 1, got {max_error}, "
                f"{max_error_cycles}"
            )
        self.max_error_cycles = int(max_error_cycles)
        self._off_target = 0  # consecutive cycles beyond max_error
        self._off_since: float | None = None
        # the same limits as floats for the per-cycle tests (``_within``)
        self._limit = self.current_limit.tolist()
        self._below_sat = None if self._sat_at is None else np.nextafter(self._sat_at, -1).tolist()

    @staticmethod
    def _within(values: list, limits: list) -> bool:
        """Every value <= its limit (False for NaN): a few floats, cheaper than numpy."""
        for x, lim in zip(values, limits, strict=True):
            if not x <= lim:
                return False
        return True

    def _names(self, mask) -> list[str]:
        return [self.joint_names[i] for i in np.flatnonzero(mask)]

    def check_state(self, state: ArmState, now_ns: int | None = None) -> None:
        """Check one measured state.

        Args:
            state: The arm's state, t s on the robot's clock.
            now_ns: ns (``perf_counter_ns``) it arrived, for the stall check (real time
                only); None: no stall check.

        Raises:
            WatchdogTrip: an actuator fault, NaN/inf, stale feedback or a loop stall.
        """
        t = state.t
        if state.faults:
            raise WatchdogTrip(FAULT, "actuator fault: " + "; ".join(state.faults), t)
        q, dq, cur = state.q, state.dq, state.current
        # one finite test for all (x @ x is inf/NaN when any entry is; dots are cheaper than sums)
        if not math.isfinite(float(q @ q) + float(dq @ dq) + float(cur @ cur) + t):
            bad = ~(np.isfinite(q) & np.isfinite(dq) & np.isfinite(cur))
            raise WatchdogTrip(
                NAN_STATE,
                f"NaN/inf in the measured state at t = {t} s (joints "
                f"{', '.join(self._names(bad)) or 'time'})",
                t,
                self._names(bad),
            )
        last = self._last
        if last is not None:
            if t <= last.t:
                why = f"time did not advance (t = {t:.4f} s, previous {last.t:.4f} s)"
            elif (
                cur.tobytes() == last.current.tobytes()
                and q.tobytes() == last.q.tobytes()
                and dq.tobytes() == last.dq.tobytes()
            ):
                why = f"q, dq and current identical to the previous cycle's at t = {t:.4f} s"
            else:
                why = None
            if why is not None:
                self._stale += 1
                if self._stale > self.stale_cycles:
                    raise WatchdogTrip(STALE, f"stale feedback: {why}", t)
            else:
                self._stale = 0
        self._last = state
        if now_ns is not None and self.max_gap_ns is not None:
            if self._last_ns is not None and now_ns - self._last_ns > self.max_gap_ns:
                gap = (now_ns - self._last_ns) / 1e6
                raise WatchdogTrip(
                    STALL,
                    f"loop stalled: {gap:.1f} ms between two cycles "
                    f"(limit {self.max_gap_ns / 1e6:.1f} ms)",
                    t,
                )
            self._last_ns = now_ns

    def check_odometry(self, pose: np.ndarray, twist: np.ndarray, t: float | None = None) -> None:
        """Check the base odometry.

        Args:
            pose: (3,) x m, y m, yaw rad, odometry (world) frame.
            twist: (3,) vx m/s, vy m/s, wz rad/s, base frame.
            t: s, the arm state's time (messages).

        Raises:
            WatchdogTrip: NaN/inf in either.
        """
        if not math.isfinite(float(pose @ pose) + float(twist @ twist)):
            raise WatchdogTrip(NAN_ODOMETRY, f"NaN/inf in the base odometry: {pose}, {twist}", t)

    def check_command(self, current: np.ndarray, t: float | None = None) -> None:
        """Check one command before it is sent.

        Args:
            current: The command, (n,) in ``unit`` (A; rad/s for the velocity controller).
            t: s, the arm state's time (messages).

        Raises:
            WatchdogTrip: NaN/inf, a command beyond ``current_limit``, or one held at the
                saturation for more than ``max_saturated_cycles``.
        """
        mag = np.abs(current)
        mags = mag.tolist()
        if not self._within(mags, self._limit):  # NaN fails the comparison too
            finite = np.isfinite(current)
            if not finite.all():
                names = self._names(~finite)
                raise WatchdogTrip(NAN_COMMAND, f"NaN/inf command for {', '.join(names)}", t, names)
            over = mag > self.current_limit
            j = int(np.flatnonzero(over)[0])
            raise WatchdogTrip(
                LIMIT,
                f"command {current[j]:.3f} {self.unit} for {self.joint_names[j]} beyond its "
                f"limit {self.current_limit[j]:.3g} {self.unit}",
                t,
                self._names(over),
            )
        if self.saturation is not None:
            if not self._within(mags, self._below_sat):  # some |current| >= _sat_at
                sat = mag >= self._sat_at
                self._saturated = np.where(sat, self._saturated + 1, 0)
                self._any_saturated = True
                long = self._saturated > self.max_saturated_cycles
                if long.any():
                    j = int(np.flatnonzero(long)[0])
                    raise WatchdogTrip(
                        SATURATED,
                        f"command of {self.joint_names[j]} saturated at "
                        f"{self.saturation[j]:.3g} {self.unit} for {self._saturated[j]} "
                        "consecutive cycles",
                        t,
                        self._names(long),
                    )
            elif self._any_saturated:
                self._saturated[:] = 0
                self._any_saturated = False

    def check_error(self, error: float, t: float | None = None) -> None:
        """Count the cycles the end effector is more than ``max_error`` m from its target.

        Args:
            error: m, this cycle's distance from the target.
            t: s from the run's start (messages).

        Raises:
            WatchdogTrip: ``not_tracking``, after more than ``max_error_cycles`` in a row.
        """
        if error <= self.max_error:
            self._off_target = 0
            return
        if self._off_target == 0:
            self._off_since = t
        self._off_target += 1
        if self._off_target > self.max_error_cycles:
            since = "" if self._off_since is None else f" from t = {self._off_since:.3f} s"
            raise WatchdogTrip(
                NOT_TRACKING,
                f"not tracking: the end effector stayed more than {1e3 * self.max_error:.0f} mm "
                f"from its target for {CONTROL_PERIOD * (self._off_target - 1):g} s{since} (now "
                f"{1e3 * error:.0f} mm): the target is out of reach or the arm is blocked or held",
                t,
            )


def safe_stop(arm: Arm | None, base: Base | None) -> list[str]:
    """Arm to POSITION mode (holding where it is) and base stopped, each tried even when the
    other fails; never raises (except Ctrl-C arriving here, after both were tried).

    Args:
        arm: The arm, or None.
        base: The mobile base, or None.

    Returns:
        The errors met, readable strings.
    """
    errors: list[str] = []
    interrupt: BaseException | None = None
    if arm is not None and not arm.closed:
        try:
            if any(m is not ControlMode.POSITION for m in arm.modes):
                arm.set_modes(ControlMode.POSITION)
        except KeyboardInterrupt as exc:  # finish the stop first
            interrupt = exc
        except Exception as exc:  # noqa: BLE001 - a stop must not stop halfway
            errors.append(f"arm to position mode failed: {exc}")
            log.error("arm to position mode failed: %r", exc)
    if base is not None:
        try:
            base.stop()
        except KeyboardInterrupt as exc:
            interrupt = exc
        except Exception as exc:  # noqa: BLE001
            errors.append(f"base stop failed: {exc}")
            log.error("base stop failed: %r", exc)
    if interrupt is not None:
        raise interrupt
    return errors


__all__ = [
    "FAULT",
    "LIMIT",
    "NAN_COMMAND",
    "NAN_ODOMETRY",
    "NAN_STATE",
    "NOT_TRACKING",
    "SATURATED",
    "STALE",
    "STALL",
    "Watchdog",
    "WatchdogTrip",
    "safe_stop",
]
