"""The real Kinova Gen3 Lite through Kinova's ``kortex_api`` (an optional extra).

``KortexArm`` is the ``Arm`` interface on Kortex low-level servoing: configuration over TCP
(port 10000), the 1 kHz cyclic channel over UDP (port 10001). Opening it creates the sessions,
checks that neither an actuator nor the arm (``base.fault_bank_a/b``, Base.SafetyIdentifier;
ARMSTATE_IN_FAULT) is in fault, switches the base to LOW_LEVEL_SERVOING, sends hold frames
until the arm reports ARMSTATE_SERVOING_LOW_LEVEL (within ``LOW_LEVEL_WAIT`` s) and puts every
actuator (device ids 1-5 and 7) in POSITION mode. Every cycle it advances ``frame_id`` (mod
65536), sets each actuator's ``command_id`` to it, sends the joint's target in its mode
(position deg, velocity deg/s, ``current_motor`` A) and, for joints not in POSITION mode,
echoes the measured position so that no following error arises.

Mode switches go one actuator at a time, as Kinova's low-level examples do: before each
``SetControlMode`` one hold frame built from the latest feedback (the switching joints'
measured position and current, velocity 0; the other joints keep their command, position
echoed where not in POSITION mode), so a joint starts its new mode where it stands and a joint
switched just before runs on a fresh frame; one more hold frame follows the last switch. A
configuration call waits at most ``CONFIG_TIMEOUT_MS``; the ticks without a frame meanwhile are
counted in ``missed_cycles``.

A cyclic reply that does not come (``TimeoutError`` after ``CYCLIC_TIMEOUT_MS``, or
``KClientException``) is tolerated and counted (``lost_replies``): the cycle returns the last
feedback, as Kinova's examples go on; ``MAX_CONSECUTIVE_LOST`` in a row are a fault. A cycle
fails safe (state faults, then ``HardwareFault``) on that, on a cyclic command the arm rejects,
on an actuator fault bit, on an arm fault bit (named after Base.SafetyIdentifier), on an arm
state other than ARMSTATE_SERVOING_LOW_LEVEL, on a missed cycle (more than ``max_cycle_gap`` s
since the previous one) and on stale feedback (no new frame for ``stale_after`` s). A mode
switch that fails (no reply, a rejection, a fault in its hold frames) ends the session and
raises ``HardwareFault``. Every exit path (normal, exception, Ctrl-C, fault) restores POSITION
mode on every actuator (each call tried up to ``SAFE_EXIT_TRIES`` times) and
SINGLE_LEVEL_SERVOING and closes the sessions.

``kortex_api`` is not on PyPI: install Kinova's wheel without its dependencies next to
protobuf 3.20 (``pip install --no-deps kortex_api-2.6.0.post3-py3-none-any.whl
"protobuf==3.20.*"``). Without an arm, run against ``KortexEmulator`` (``KortexArm.emulated``).
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np

from jaxcomp.hardware.interface import Arm, ArmLimits, ArmState, ControlMode, HardwareFault
from jaxcomp.hardware.kortex_namespace import import_kortex_api
from jaxcomp.robot import Robot, load_robot

log = logging.getLogger(__name__)

DEVICE_IDS = (1, 2, 3, 4, 5, 7)
TCP_PORT, UDP_PORT = 10000, 10001
#: ms a cyclic ``Refresh`` waits for its reply (Kinova's low-level examples: 3 ms).
CYCLIC_TIMEOUT_MS = 3
#: ms a configuration call (servoing mode, control mode, clear faults) waits for its reply;
#: kortex_api's default is 10 s, during which no cyclic frame would go out.
CONFIG_TIMEOUT_MS = 500
#: Consecutive cyclic exchanges without a reply that end the run (about 9 ms without feedback
#: at ``CYCLIC_TIMEOUT_MS``); fewer are tolerated and counted.
MAX_CONSECUTIVE_LOST = 3
#: Tries of each configuration call on the way back to POSITION mode and single-level servoing
#: (Kinova's examples retry 3 times).
SAFE_EXIT_TRIES = 3
#: s of hold frames after ``SetServoingMode(LOW_LEVEL_SERVOING)`` for the arm to report
#: ARMSTATE_SERVOING_LOW_LEVEL.
LOW_LEVEL_WAIT = 0.5
_MODE_NAME = {
    ControlMode.POSITION: "POSITION",
    ControlMode.VELOCITY: "VELOCITY",
    ControlMode.CURRENT: "CURRENT",
}


def _wrap_rad(deg: np.ndarray) -> np.ndarray:
    """Kortex degrees (any range, usually [0, 360)) to rad in [-pi, pi)."""
    return np.deg2rad((np.asarray(deg) + 180.0) % 360.0 - 180.0)


def _bits(bank: int) -> list[int]:
    """The set bits of a fault bank, lowest first."""
    return [1 << k for k in range(32) if bank >> k & 1]


class KortexArm(Arm):
    """The ``Arm`` interface on a Gen3 Lite through Kortex low-level servoing at 1 kHz.

    Args:
        ip: the arm's address. username, password: its credentials.
        robot: the nominal model (limits, named poses), default "gen3_lite".
        api: the kortex_api namespace (default: ``import_kortex_api()``; an emulator's
            ``api`` for tests).
        clock, sleep: time source (s) and sleep function; ``pace`` waits for the next 1 ms
            tick before each send.
        max_cycle_gap: s between two cycles beyond which the session fails (missed cycle).
        stale_after: s without a new feedback frame beyond which the session fails.

    Counters: ``cycles`` (cycles exchanged), ``lost_replies`` (cyclic replies that did not
    come, hold frames included), ``lost_in_a_row`` (the current run of them),
    ``missed_cycles`` (1 kHz ticks without a frame while a joint was not in POSITION mode or
    a mode switch was under way: a gap of g s between two frames counts round(g / dt) - 1),
    ``max_jitter_us`` (the actuators' largest ``jitter_comm``).
    """

    #: A lost reply repeats the previous state; this many in a row are no stale feedback to
    #: the control loop's watchdog (the adapter ends the run at ``MAX_CONSECUTIVE_LOST``).
    stale_tolerance = MAX_CONSECUTIVE_LOST - 1

    def __init__(
        self,
        ip: str = "192.168.1.10",
        username: str = "admin",
        password: str = "admin",
        *,
        robot: str | Robot = "gen3_lite",
        api: SimpleNamespace | None = None,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
        pace: bool = True,
        max_cycle_gap: float = 0.003,
        stale_after: float = 0.010,
        limits: ArmLimits | None = None,
    ):
        self.robot = load_robot(robot)
        if self.robot.nv != len(DEVICE_IDS):
            raise HardwareFault(
                f"the Gen3 Lite has 6 actuators; {self.robot.name} has {self.robot.nv}"
            )
        super().__init__(
            self.robot.joint_names,
            limits or ArmLimits.from_robot(self.robot),
            self.robot.named_poses,
        )
        self.api = api if api is not None else import_kortex_api()
        self.ip, self._credentials = ip, (username, password)
        self._clock, self._sleep, self._pace = clock, sleep, pace
        self.max_cycle_gap, self.stale_after = float(max_cycle_gap), float(stale_after)
        self._session = self._session_rt = None
        self._tcp = self._udp = None
        self._arm_modes = [ControlMode.POSITION] * self.n  # the actuators' modes, as switched
        self._low_level = False  # the base was switched to LOW_LEVEL_SERVOING
        self._in_low_level = False  # the arm has reported ARMSTATE_SERVOING_LOW_LEVEL
        self._shut = False
        self._switching = False
        self._last_send: float | None = None
        self._last_frame_t: float | None = None
        self._last_fresh = 0.0
        self._last_frame: int | None = None
        # a reply that did not come: kortex_api's future times out, or the client failed
        self._lost_errors = (
            TimeoutError,
            concurrent.futures.TimeoutError,
            self.api.KClientException,
        )
        self.max_jitter_us = 0
        self.cycles = 0
        self.lost_replies = 0
        self.lost_in_a_row = 0
        self.missed_cycles = 0
        self._t0 = 0.0
        try:
            self._open()
        except BaseException:
            self._closed = True
            try:
                self._shutdown()
            except HardwareFault as exc:  # the opening's error is the one to report
                log.error("%s", exc)
            raise

    @classmethod
    def emulated(cls, emulator=None, **kwargs) -> KortexArm:
        """An adapter on a ``KortexEmulator`` (lock step: the emulator's clock, no sleeping).

        Args:
            emulator: the emulator (default: a fresh ``KortexEmulator()``).
            **kwargs: the adapter's other arguments (``clock`` and ``sleep`` default to the
                emulator's).

        Returns:
            The open ``KortexArm``; its ``emulator`` attribute is the emulator.
        """
        if emulator is None:
            from jaxcomp.hardware.kortex_emulator import KortexEmulator

            emulator = KortexEmulator()
        kwargs.setdefault("clock", emulator.clock)
        kwargs.setdefault("sleep", lambda s: None)
        arm = cls(api=emulator.api, **kwargs)
        arm.emulator = emulator
        return arm

    # ----------------------------------------------------------------- session
    def _send_options(self, timeout_ms: int):
        options = self.api.RouterClientSendOptions()
        options.andForget = False
        options.delay_ms = 0
        options.timeout_ms = timeout_ms
        return options

    def _open(self) -> None:
        api = self.api
        self._tcp = api.TCPTransport()
        router = api.RouterClient(self._tcp, self._router_error)
        self._tcp.connect(self.ip, TCP_PORT)
        self._udp = api.UDPTransport()
        router_rt = api.RouterClient(self._udp, self._router_error)
        self._udp.connect(self.ip, UDP_PORT)
        self._routers = (router, router_rt)
        info = api.Session_pb2.CreateSessionInfo()
        info.username, info.password = self._credentials
        info.session_inactivity_timeout = 60000  # ms
        info.connection_inactivity_timeout = 2000  # ms
        self._session = api.SessionManager(router)
        self._session.CreateSession(info)
        self._session_rt = api.SessionManager(router_rt)
        self._session_rt.CreateSession(info)
        self._base = api.BaseClient(router)
        self._cyclic = api.BaseCyclicClient(router_rt)
        self._config = api.ActuatorConfigClient(router)
        self._options = self._send_options(CYCLIC_TIMEOUT_MS)
        self._config_options = self._send_options(CONFIG_TIMEOUT_MS)
        states = api.Common_pb2.ArmState
        self._low_level_state = states.Value("ARMSTATE_SERVOING_LOW_LEVEL")
        self._fault_state = states.Value("ARMSTATE_IN_FAULT")

        fb = self._feedback()
        if len(fb.actuators) != len(DEVICE_IDS):
            raise HardwareFault(f"expected 6 actuators, the arm reports {len(fb.actuators)}")
        faults = self._fault_bits(fb) + self._arm_faults(fb, low_level=False)
        if faults:
            raise HardwareFault("the arm is in fault: " + "; ".join(faults), faults)
        mode = api.Base_pb2.ServoingModeInformation()
        mode.servoing_mode = api.Base_pb2.ServoingMode.Value("LOW_LEVEL_SERVOING")
        error = self._configure(
            self._base.SetServoingMode, mode, 0, what="SetServoingMode(LOW_LEVEL_SERVOING)"
        )
        if error is not None:
            self._single_level()  # it may have switched without a reply
            raise HardwareFault(f"cannot enter low-level servoing: {error}", (error,))
        self._low_level = True
        fb = self._feedback()
        self._command = api.BaseCyclic_pb2.Command()
        for a in fb.actuators:
            c = self._command.actuators.add()
            c.flags = 1  # servoing
            c.position = a.position
            c.current_motor = a.current_motor
        self._command.frame_id = fb.frame_id
        self._fb = fb
        self._await_low_level()
        self._send_modes(dict.fromkeys(range(self.n), ControlMode.POSITION))
        t = self._clock()
        self._t0 = t
        self._last_fresh = t
        self._last_send = self._last_frame_t = None  # the caller's first cycle may come later
        self._start(self._state_from(self._fb, t, ()))

    def _feedback(self):
        """``RefreshFeedback`` (tried ``SAFE_EXIT_TRIES`` times); HardwareFault without one."""
        error = None
        for _ in range(SAFE_EXIT_TRIES):
            try:
                return self._cyclic.RefreshFeedback(0, self._config_options)
            except (*self._lost_errors, self.api.KServerException) as exc:
                error = exc
        raise HardwareFault(f"no feedback from the arm at {self.ip}: {error!r}")

    def _await_low_level(self) -> None:
        """Hold frames until the arm reports ARMSTATE_SERVOING_LOW_LEVEL (``LOW_LEVEL_WAIT``)."""
        deadline = self._clock() + LOW_LEVEL_WAIT
        everyone = range(self.n)
        while True:
            self._hold(everyone)  # raises on no reply, a rejection or a fault
            state = self._fb.base.active_state
            if state == self._low_level_state:
                self._in_low_level = True  # from now on any other state is a fault
                return
            if self._clock() > deadline:
                why = f"arm state {self._state_name(state)} after {LOW_LEVEL_WAIT} s"
                raise HardwareFault(f"the arm did not enter low-level servoing: {why}", (why,))
            self._sleep(self.dt)

    def _router_error(self, exc) -> None:
        log.error("Kortex router error: %s", exc)

    def _configure(self, call: Callable, *args, what: str, tries: int = 1) -> str | None:
        """One configuration call (``CONFIG_TIMEOUT_MS``), up to ``tries`` times; None when it
        went through, else why not."""
        error = None
        for _ in range(tries):
            try:
                call(*args, self._config_options)
                return None
            except self._lost_errors as exc:
                error = f"{what}: no reply within {CONFIG_TIMEOUT_MS} ms ({exc!r})"
            except self.api.KServerException as exc:
                error = f"{what} refused by the arm: {exc}"
            log.warning("%s", error)
        return error

    # ----------------------------------------------------------------- frames
    def _refresh(self, now: float | None = None) -> str | None:
        """Send the command frame (next ``frame_id``, every ``command_id`` set to it). None
        when its reply came (``_fb`` is then the new feedback), else why not: a lost reply
        (counted; ``lost_in_a_row`` tells) or a rejection by the arm (``lost_in_a_row`` 0)."""
        cmd = self._command
        fid = (cmd.frame_id + 1) % 65536
        cmd.frame_id = fid
        for a in cmd.actuators:
            a.command_id = fid
        t = self._clock() if now is None else now
        if self._last_frame_t is not None and (self._switching or not self._all_position):
            ticks = round((t - self._last_frame_t) / self.dt) - 1
            if ticks > 0:
                self.missed_cycles += ticks
        self._last_frame_t = t
        try:
            fb = self._cyclic.Refresh(cmd, 0, self._options)
        except self._lost_errors as exc:
            self.lost_replies += 1
            self.lost_in_a_row = n = self.lost_in_a_row + 1
            log.warning("Kortex: no reply to cyclic frame %d (%d in a row): %r", fid, n, exc)
            if n >= MAX_CONSECUTIVE_LOST:
                return (
                    f"{n} consecutive cyclic replies lost (limit {MAX_CONSECUTIVE_LOST}), "
                    f"the last: {exc!r}"
                )
            return f"no reply to cyclic frame {fid}: {exc!r}"
        except self.api.KServerException as exc:
            self.lost_in_a_row = 0
            return f"the arm rejected cyclic frame {fid}: {exc}"
        self.lost_in_a_row = 0
        self._fb = fb
        return None

    def _hold_frame(self, switching) -> str | None:
        """One frame built from the latest feedback: every actuator keeps its command, with
        the measured position where it is not in POSITION mode (a POSITION-mode actuator keeps
        its target: it holds); the ``switching`` ones get velocity 0 and their measured
        current. A switch to CURRENT then starts at the measured current, one to POSITION at
        the measured position."""
        fb = self._fb
        modes = self._arm_modes
        for i, a in enumerate(self._command.actuators):
            measured = fb.actuators[i]
            if modes[i] is not ControlMode.POSITION:
                a.position = measured.position
            if i in switching:
                a.velocity = 0.0
                a.current_motor = measured.current_motor
        return self._refresh()

    def _hold(self, switching, safe: bool = False) -> str | None:
        """A hold frame. Not ``safe``: sent again while its reply is lost (up to
        ``MAX_CONSECUTIVE_LOST`` in a row); HardwareFault when none got through or its
        feedback shows a fault. ``safe`` (on the way out, maybe with the link down): sent
        once, faults ignored; returns why it did not get through (None if it did)."""
        error = self._hold_frame(switching)
        if safe:
            return error
        while error is not None and 0 < self.lost_in_a_row < MAX_CONSECUTIVE_LOST:
            error = self._hold_frame(switching)
        if error is not None:
            raise HardwareFault(f"no hold frame got through: {error}", (error,))
        faults = self._fault_bits(self._fb) + self._arm_faults(self._fb, self._in_low_level)
        if faults:
            raise HardwareFault("the arm reported fault(s): " + "; ".join(faults), faults)
        return None

    def _send_modes(self, changes: dict[int, ControlMode], *, safe: bool = False) -> list[str]:
        """Switch actuators one at a time, each after a hold frame; one more hold frame after
        the last. Not ``safe``: any failure raises HardwareFault. ``safe`` (the way back to
        POSITION): each ``SetControlMode`` is tried up to ``SAFE_EXIT_TRIES`` times, hold
        frames without a reply are logged, and the failed calls are returned."""
        errors: list[str] = []
        switching = set(changes)
        missed = self.missed_cycles
        self._switching = True
        try:
            for j, mode in changes.items():
                if self._low_level:
                    self._hold_logged(switching, safe)
                info = self.api.ActuatorConfig_pb2.ControlModeInformation()
                info.control_mode = self.api.ActuatorConfig_pb2.ControlMode.Value(_MODE_NAME[mode])
                error = self._configure(
                    self._config.SetControlMode,
                    info,
                    DEVICE_IDS[j],
                    what=f"SetControlMode({_MODE_NAME[mode]}) of actuator {DEVICE_IDS[j]}",
                    tries=SAFE_EXIT_TRIES if safe else 1,
                )
                if error is not None:
                    if not safe:
                        raise HardwareFault(f"mode switch aborted: {error}", (error,))
                    errors.append(error)
                else:
                    self._arm_modes[j] = mode
            if self._low_level and changes:
                self._hold_logged(switching, safe)
        finally:
            self._switching = False
        if self.missed_cycles > missed:
            log.info(
                "Kortex: %d cycle(s) without a frame while switching %d actuator(s)",
                self.missed_cycles - missed,
                len(changes),
            )
        return errors

    def _hold_logged(self, switching, safe: bool) -> None:
        error = self._hold(switching, safe)
        if error is not None:
            log.error("Kortex: hold frame on the way to POSITION mode: %s", error)

    # ----------------------------------------------------------------- Arm hooks
    def _switch(self, changes: dict[int, ControlMode]) -> None:
        safe = all(m is ControlMode.POSITION for m in changes.values())
        try:
            errors = self._send_modes(changes, safe=safe)
            if errors:
                raise HardwareFault(
                    "the arm did not return to POSITION mode: " + "; ".join(errors), errors
                )
        except HardwareFault:
            self._abort()
            raise
        self._last_send = self._last_frame_t  # the next cycle is due a tick after the last frame
        if self._low_level and not safe:  # the latest measurement: the joints start from it
            self._state = self._state_from(self._fb, self._clock(), ())

    def _abort(self) -> None:
        """End the session after a failed switch: POSITION everywhere, single-level
        servoing, sessions closed (their errors logged; the caller raises the switch's)."""
        self._closed = True
        try:
            self._shutdown()
        except HardwareFault as exc:
            log.error("%s", exc)

    def _exchange(self, modes, position, velocity, current) -> ArmState:
        now = self._clock()
        if self._pace and self._last_send is not None:
            wait = self._last_send + self.dt - now
            if wait > 0:
                self._sleep(wait)
                now = self._clock()
        faults: list[str] = []
        if self._last_send is not None and now - self._last_send > self.max_cycle_gap:
            faults.append(
                f"missed cycle: {1e3 * (now - self._last_send):.1f} ms since the last one "
                f"(limit {1e3 * self.max_cycle_gap:.1f} ms)"
            )
        self._last_send = now
        cmd, fb = self._command, self._fb
        pos_deg = np.rad2deg(position) % 360.0
        vel_deg = np.rad2deg(velocity)
        for i, a in enumerate(cmd.actuators):
            measured = fb.actuators[i]
            mode = modes[i]
            if mode is ControlMode.POSITION:
                a.position = pos_deg[i]
                a.velocity = 0.0
                a.current_motor = measured.current_motor
            else:  # echo the measured position: no following error
                a.position = measured.position
                if mode is ControlMode.VELOCITY:
                    a.velocity = vel_deg[i]
                    a.current_motor = measured.current_motor
                else:
                    a.velocity = 0.0
                    a.current_motor = current[i]
        error = self._refresh(now)
        t = self._clock()
        if error is not None:
            if self.lost_in_a_row in range(1, MAX_CONSECUTIVE_LOST):
                self._last_send = t  # tolerated: the wait for it is no stall of the host
            else:
                faults.append(error)
        fb = self._fb
        if fb.frame_id != self._last_frame:
            self._last_fresh = t
        elif t - self._last_fresh > self.stale_after:
            faults.append(
                f"stale feedback: no new frame for {1e3 * (t - self._last_fresh):.1f} ms "
                f"(limit {1e3 * self.stale_after:.1f} ms)"
            )
        self._last_frame = fb.frame_id
        self.cycles += 1
        return self._state_from(fb, t, faults + self._fault_bits(fb) + self._arm_faults(fb))

    # ----------------------------------------------------------------- faults and states
    def _fault_bits(self, fb) -> list[str]:
        out = []
        for i, a in enumerate(fb.actuators):
            if a.fault_bank_a or a.fault_bank_b:
                out.append(
                    f"actuator {DEVICE_IDS[i]} ({self.joint_names[i]}): fault bank A "
                    f"{a.fault_bank_a:#x}, bank B {a.fault_bank_b:#x}"
                )
        return out

    def _arm_faults(self, fb, low_level: bool = True) -> list[str]:
        """The arm's own faults: its fault banks (Base.SafetyIdentifier names) and its state
        (ARMSTATE_IN_FAULT; with ``low_level``, anything but ARMSTATE_SERVOING_LOW_LEVEL)."""
        base = fb.base
        bank_a, bank_b, state = base.fault_bank_a, base.fault_bank_b, base.active_state
        wrong = state == self._fault_state or (low_level and state != self._low_level_state)
        if not (bank_a or bank_b or wrong):
            return []
        out = [
            f"arm fault bank {name} {bank:#x} ({', '.join(map(self._safety_name, _bits(bank)))})"
            for name, bank in (("A", bank_a), ("B", bank_b))
            if bank
        ]
        if wrong:
            out.append(f"arm state {self._state_name(state)}")
        return out

    def _safety_name(self, bit: int) -> str:
        try:
            return str(self.api.Base_pb2.SafetyIdentifier.Name(bit))
        except ValueError:
            return f"bit {bit:#x}"

    def _state_name(self, state: int) -> str:
        try:
            return str(self.api.Common_pb2.ArmState.Name(state))
        except ValueError:
            return f"arm state {state}"

    def _state_from(self, fb, t: float, faults) -> ArmState:
        acts = fb.actuators
        jitter = max(a.jitter_comm for a in acts)
        self.max_jitter_us = max(self.max_jitter_us, jitter)
        return ArmState(
            t - self._t0,
            _wrap_rad([a.position for a in acts]),
            np.deg2rad([a.velocity for a in acts]),
            np.array([a.current_motor for a in acts]),
            tuple(faults),
            self._modes_tuple,
            float(jitter),
        )

    def _after_fault(self, state: ArmState) -> None:
        self.close()

    def _clear_faults(self) -> None:
        error = self._configure(self._base.ClearFaults, 0, what="ClearFaults")
        if error is not None:
            raise HardwareFault(error, (error,))

    # ----------------------------------------------------------------- the way out
    def _shutdown(self) -> None:
        """Every actuator to POSITION, SINGLE_LEVEL_SERVOING, sessions closed: each step is
        tried even when an earlier one fails (or is interrupted); then Ctrl-C is re-raised,
        or HardwareFault names what failed. Runs once."""
        if self._shut:
            return
        self._shut = True
        errors: list[str] = []
        interrupt: BaseException | None = None

        def attempt(what: str, step: Callable[[], object]) -> None:
            nonlocal interrupt
            try:
                result = step()
            except KeyboardInterrupt as exc:  # finish the way out first
                interrupt = exc
                result = "interrupted"
            except Exception as exc:  # noqa: BLE001 - every step must be tried
                result = repr(exc)
            for error in [result] if isinstance(result, str) else result or ():
                errors.append(f"{what}: {error}")
                log.error("Kortex shutdown, %s: %s", what, error)

        if self._low_level:
            everyone = dict.fromkeys(range(self.n), ControlMode.POSITION)
            attempt("POSITION mode", lambda: self._send_modes(everyone, safe=True))
            attempt("single-level servoing", self._single_level)
        for session in (self._session, self._session_rt):
            if session is not None:
                attempt("closing a session", session.CloseSession)
        for router in getattr(self, "_routers", ()):
            attempt("deactivating a router", lambda r=router: r.SetActivationStatus(False))
        for transport in (self._tcp, self._udp):
            if transport is not None:
                attempt("disconnecting", transport.disconnect)
        self._session = self._session_rt = None
        if interrupt is not None:
            raise interrupt
        if errors:
            raise HardwareFault("the Kortex session did not end cleanly: " + "; ".join(errors))

    def _single_level(self) -> str | None:
        mode = self.api.Base_pb2.ServoingModeInformation()
        mode.servoing_mode = self.api.Base_pb2.ServoingMode.Value("SINGLE_LEVEL_SERVOING")
        error = self._configure(
            self._base.SetServoingMode,
            mode,
            0,
            what="SetServoingMode(SINGLE_LEVEL_SERVOING)",
            tries=SAFE_EXIT_TRIES,
        )
        if error is None:
            self._low_level = False
        return error


__all__ = [
    "CONFIG_TIMEOUT_MS",
    "CYCLIC_TIMEOUT_MS",
    "DEVICE_IDS",
    "MAX_CONSECUTIVE_LOST",
    "KortexArm",
]
