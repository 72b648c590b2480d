"""A Kinova Kortex emulator backed by the simulated arm.

``KortexEmulator().api`` has the names the Kortex adapter takes from ``kortex_api``
(``kortex_fake_api``, with the messages of ``kortex_messages``), with the same method names and
message fields, so the adapter runs unchanged against it; each of their calls comes to one of
the emulator's services here. Behind them a ``Simulator`` plays the Gen3 Lite and the emulator
enforces the protocol of shared/reference/FIGURES.md:

- configuration calls over TCP port 10000, ``BaseCyclic`` over UDP port 10001, both in an open
  session; actuator device ids 1, 2, 3, 4, 5 and 7;
- ``Refresh`` only in LOW_LEVEL_SERVOING, with a command the arm takes (``kortex_protocol``:
  ``frame_id`` advancing mod 65536, every actuator's ``command_id`` equal to it);
- a commanded position further than ``following_error_deg`` from the measured one raises a
  following-error fault on that actuator (the arm then holds: it is in fault);
- ``SetControlMode(CURRENT or VELOCITY)`` before LOW_LEVEL_SERVOING is refused; leaving low-level
  servoing or closing the session with an actuator not in POSITION mode is a violation, and so
  is a switch to CURRENT or VELOCITY in low-level servoing that no hold frame precedes (the last
  cyclic command before it, received after the previous switch, must start the new mode where
  the last feedback the host received left the actuator: ``starts_where_seen``). Every switch
  is logged in ``switches`` (``SwitchRecord``).

It produces what the arm produces: the arm state in ``Feedback.base.active_state`` and
``GetArmState`` (ARMSTATE_SERVOING_READY, ARMSTATE_SERVOING_LOW_LEVEL once in low-level
servoing, ARMSTATE_IN_FAULT on any fault), arm-level fault bits (``Base.SafetyIdentifier``) in
``base.fault_bank_a`` (JOINT_FAULT while an actuator is in fault), configuration calls that
take ``config_latency`` s (the arm runs on the last cyclic command meanwhile), replies that
never come (the caller waits its ``timeout_ms`` and gets ``TimeoutError``, as kortex_api's
future does) and the host's jitter (each send late by up to ``jitter`` s, seen in ``clock()``
and in the actuators' ``jitter_comm``). Every refusal is also appended to ``violations``.

Units on the wire are Kortex's: positions in deg in [0, 360), velocities deg/s, currents A,
floats rounded to float32. Time is the simulator's (lock step: 1 ms per ``Refresh``);
``clock()`` reads it (plus the host's lateness). Injections (``kortex_injections``):
``inject_stall``, ``inject_stale``, ``inject_fault``, ``inject_arm_fault``, ``inject_lost``,
``inject_config_timeout``; constructor options draw lost replies at random
(``lost_reply_rate``) and the jitter (``jitter``, ``seed``).
"""

from __future__ import annotations

import copy

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.hardware.interface import ControlMode
from jaxcomp.hardware.kortex import DEVICE_IDS, TCP_PORT, UDP_PORT
from jaxcomp.hardware.kortex_fake_api import Transport, fake_kortex_api
from jaxcomp.hardware.kortex_injections import LOST_KINDS, Injection, InjectionSchedule
from jaxcomp.hardware.kortex_messages import (
    ARM_STATES,
    CONTROL_MODES,
    EMERGENCY_STOP_ACTIVATED,
    JOINT_FAULT,
    SERVOING_MODES,
    Feedback,
    KClientException,
    KServerException,
)
from jaxcomp.hardware.kortex_protocol import (
    ARM_FAULT,
    FOLLOWING_ERROR,
    INJECTED,
    MAX_CURRENT,
    MAX_TORQUE,
    SwitchRecord,
    command_refusal,
    diff_deg,
    fill_actuator_feedback,
    starts_where_seen,
    wrap_deg,
)
from jaxcomp.hardware.simulator import Simulator

#: ActuatorConfig.ControlMode numbers the Gen3 Lite has, as the simulator's modes.
_TO_MODE = {1: ControlMode.POSITION, 2: ControlMode.VELOCITY, 4: ControlMode.CURRENT}


def _check_settings(
    sim: Simulator,
    config_latency: float,
    servoing_delay: float,
    jitter: float,
    lost_reply_rate: float,
) -> None:
    """ValueError unless the simulator has the Gen3 Lite's 6 joints and the times (s) are
    >= 0 and the loss rate in [0, 1)."""
    if sim.n != len(DEVICE_IDS):
        raise ValueError(f"the emulated Gen3 Lite needs 6 arm joints, got {sim.n}")
    for name, value in (
        ("config_latency", config_latency),
        ("servoing_delay", servoing_delay),
        ("jitter", jitter),
    ):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a number of s >= 0, got {value}")
    if not 0 <= lost_reply_rate < 1:
        raise ValueError(f"lost_reply_rate must be in [0, 1), got {lost_reply_rate}")


class KortexEmulator:
    """A Gen3 Lite behind kortex_api's interfaces (see the module docstring).

    Args:
        sim: the simulator playing the arm (default: a fresh ``Simulator("gen3_lite")``).
        following_error_deg: commanded-vs-measured position difference that faults, deg.
        username, password: the credentials ``CreateSession`` accepts.
        config_latency: s each configuration call (``SetControlMode``, ``SetServoingMode``)
            takes; the arm runs on the last cyclic command meanwhile. Longer than the caller's
            ``timeout_ms``: the call times out.
        servoing_delay: s after ``SetServoingMode(LOW_LEVEL_SERVOING)`` before the arm state
            reads ARMSTATE_SERVOING_LOW_LEVEL (ARMSTATE_SERVOING_READY until then).
        jitter: s, each cyclic command reaches the arm up to this late after its 1 ms tick
            (uniform), as a host's 1 kHz loop does.
        lost_reply_rate: probability that a ``Refresh``'s reply is lost (the command was
            applied; the caller waits its timeout).
        seed: of the jitter and the random losses.

    Raises:
        ValueError: a simulator without 6 arm joints, a negative time, a rate outside [0, 1).
    """

    def __init__(
        self,
        sim: Simulator | None = None,
        *,
        following_error_deg: float = 10.0,
        username: str = "admin",
        password: str = "admin",
        config_latency: float = 0.0,
        servoing_delay: float = 0.0,
        jitter: float = 0.0,
        lost_reply_rate: float = 0.0,
        seed: int | None = 0,
    ):
        self.sim = sim if sim is not None else Simulator("gen3_lite")
        _check_settings(self.sim, config_latency, servoing_delay, jitter, lost_reply_rate)
        self.following_error_deg = float(following_error_deg)
        self.config_latency = float(config_latency)
        self.servoing_delay = float(servoing_delay)
        self.jitter = float(jitter)
        self.lost_reply_rate = float(lost_reply_rate)
        self._rng = np.random.default_rng(seed)
        self._credentials = (username, password)
        self._start_arm()
        self._start_records()
        self._start_exchange()
        self.api = fake_kortex_api(self)

    def _start_arm(self) -> None:
        """The arm's own state: modes, sessions, connections, faults, frames."""
        self.servoing_mode = SERVOING_MODES.Value("SINGLE_LEVEL_SERVOING")
        self.control_modes = dict.fromkeys(DEVICE_IDS, CONTROL_MODES.Value("POSITION"))
        self.sessions_open = 0
        self.sessions_closed = 0
        self.connected: set[str] = set()
        self.fault_a = dict.fromkeys(DEVICE_IDS, 0)
        self.arm_fault_a = 0
        self.last_frame_id: int | None = None
        self._frame = 0

    def _start_records(self) -> None:
        """What the emulator records for inspection: violations, counters, switches."""
        self.violations: list[str] = []
        self.refresh_count = 0
        self.lost = dict.fromkeys(LOST_KINDS, 0)
        self.config_timeouts = 0
        self.max_jitter_us = 0
        self.switches: list[SwitchRecord] = []
        self._injections = InjectionSchedule()

    def _start_exchange(self) -> None:
        """The state of the cyclic exchange with the host."""
        self._last_feedback: Feedback | None = None
        self._delivered: Feedback | None = None  # the last feedback the host received
        self._last_arrival: float | None = None
        self._late = 0.0  # s the host's next send comes after its tick
        self._low_level_since = 0.0
        self._frames_since_switch = 0
        self._last_command: tuple[np.ndarray, ...] | None = None  # position, velocity, current
        self._basis: Feedback | None = None  # what the host had received when it sent it
        self._targets: tuple[np.ndarray, ...] | None = None  # the sim's last targets

    # ----------------------------------------------------------------- inspection
    @property
    def session_open(self) -> bool:
        """True while more sessions were opened than closed."""
        return self.sessions_open > self.sessions_closed

    @property
    def all_position(self) -> bool:
        """True when every actuator is in POSITION mode."""
        return all(m == CONTROL_MODES.Value("POSITION") for m in self.control_modes.values())

    @property
    def low_level(self) -> bool:
        """True in LOW_LEVEL_SERVOING."""
        return self.servoing_mode == SERVOING_MODES.Value("LOW_LEVEL_SERVOING")

    @property
    def arm_state(self) -> int:
        """The arm's state (Common.ArmState number; ``ARM_STATES.Name`` gives its name)."""
        if self._in_fault():
            return ARM_STATES.Value("ARMSTATE_IN_FAULT")
        if self.low_level and self.sim.t >= self._low_level_since + self.servoing_delay - 1e-9:
            return ARM_STATES.Value("ARMSTATE_SERVOING_LOW_LEVEL")
        return ARM_STATES.Value("ARMSTATE_SERVOING_READY")

    def clock(self) -> float:
        """The host's time, s: the emulated time (1 ms per Refresh, more after a stall, a
        configuration call or a timeout) plus how late the host's next send comes (jitter).

        Returns:
            The host's time, s.
        """
        return self.sim.t + self._late

    # ----------------------------------------------------------------- injections
    def inject_stall(self, at: float, seconds: float) -> None:
        """The caller stalls (missed cycles).

        Args:
            at: s, when. seconds: s, how long.
        """
        self._injections.add(Injection(at, "stall", seconds=seconds))

    def inject_stale(self, at: float, seconds: float) -> None:
        """Feedback frames stop coming for a while (the old feedback repeats).

        Args:
            at: s, from when. seconds: s, how long.
        """
        self._injections.add(Injection(at, "stale", seconds=seconds))

    def inject_fault(self, at: float, device: int, bits: int = INJECTED) -> None:
        """An actuator raises fault bits in its fault_bank_a.

        Args:
            at: s, when. device: the actuator's device id. bits: the fault bits.
        """
        self._injections.add(Injection(at, "fault", device=device, bits=bits))

    def inject_arm_fault(self, at: float, bits: int = EMERGENCY_STOP_ACTIVATED) -> None:
        """The arm raises arm-level fault bits in ``base.fault_bank_a``: ARMSTATE_IN_FAULT,
        every actuator holds.

        Args:
            at: s, when. bits: the fault bits (Base.SafetyIdentifier).
        """
        self._injections.add(Injection(at, "arm_fault", bits=bits))

    def inject_lost(self, at: float, count: int = 1, what: str = "reply") -> None:
        """The next ``count`` ``Refresh`` calls at or after ``at`` s fail: ``what`` = "reply"
        (the command is applied, its reply lost), "command" (the command never arrives) or
        "client" (``KClientException`` at once, nothing sent). A lost reply or command costs
        the caller its ``timeout_ms`` and raises ``TimeoutError``.

        Args:
            at: s, from when. count: how many calls. what: one of ``LOST_KINDS``.

        Raises:
            ValueError: ``what`` is not one of ``LOST_KINDS``.
        """
        if what not in LOST_KINDS:
            raise ValueError(f"what must be one of {LOST_KINDS}, got {what!r}")
        self._injections.add(Injection(at, "lost", count=int(count), what=what))

    def inject_config_timeout(self, at: float, count: int = 1) -> None:
        """The next ``count`` configuration calls at or after ``at`` s get no reply (not
        applied): the caller waits its ``timeout_ms`` and gets ``TimeoutError``.

        Args:
            at: s, from when. count: how many calls.
        """
        self._injections.add(Injection(at, "config_timeout", count=int(count)))

    # ----------------------------------------------------------------- channels and sessions
    def configuration_call(self, transport: Transport, what: str, options) -> None:
        """A configuration call's way to the arm: over TCP port 10000 in an open session, then
        its round trip (``config_latency`` s, or no reply).

        Args:
            transport: the caller's router's transport. what: the call, e.g. "Base.GetArmState".
            options: the caller's ``RouterClientSendOptions`` (``timeout_ms``), or None.

        Raises:
            KServerException: not on a connected TCP transport, or outside a session.
            TimeoutError: the reply did not come within ``timeout_ms`` (the caller waited).
        """
        self._need(transport, "tcp", TCP_PORT, what)
        self._configure(what, options)

    def cyclic_call(self, transport: Transport, what: str) -> None:
        """A cyclic call's way to the arm: over UDP port 10001 in an open session.

        Args:
            transport: the caller's router's transport. what: the call, e.g. "BaseCyclic.Refresh".

        Raises:
            KServerException: not on a connected UDP transport, or outside a session.
        """
        self._need(transport, "udp", UDP_PORT, what)

    def create_session(self, transport: Transport, info) -> None:
        """Open a session (``SessionManager.CreateSession``).

        Args:
            transport: the session's transport. info: a ``CreateSessionInfo``.

        Raises:
            KServerException: the transport is not connected, or the credentials are wrong.
        """
        if not transport.is_connected:
            raise self._refuse("CreateSession on a transport that is not connected")
        if (info.username, info.password) != self._credentials:
            raise KServerException("wrong username or password")
        self.sessions_open += 1

    def close_session(self) -> None:
        """Close a session (a violation while in LOW_LEVEL_SERVOING)."""
        if self.low_level:
            self.violations.append("session closed while in LOW_LEVEL_SERVOING")
        self.sessions_closed += 1

    # ----------------------------------------------------------------- protocol helpers
    def _refuse(self, message: str) -> KServerException:
        self.violations.append(message)
        return KServerException(message)

    def _need(self, transport: Transport, kind: str, port: int, what: str) -> None:
        if transport.kind != kind or transport.port != port or not transport.is_connected:
            raise self._refuse(f"{what} needs a {kind.upper()} connection on port {port}")
        if not self.session_open:
            raise self._refuse(f"{what} without an open session")

    def _device(self, device_id: int) -> int:
        if device_id not in DEVICE_IDS:
            raise self._refuse(f"no actuator with device id {device_id} (ids {DEVICE_IDS})")
        return DEVICE_IDS.index(device_id)

    def _in_fault(self) -> bool:
        return bool(self.arm_fault_a) or any(self.fault_a.values())

    def _wait(self, seconds: float) -> None:
        """The arm runs ``seconds`` s on its last targets (no new command arrives)."""
        steps = int(round(seconds / CONTROL_PERIOD))
        if steps > 0:
            self.sim.step(steps)
            self._sim_faults()

    @staticmethod
    def _timeout_s(options) -> float:
        return (10000 if options is None else options.timeout_ms) / 1000.0

    def _take(self, kind: str) -> Injection | None:
        """A due counted injection of ``kind`` (one of its counts used up), or None."""
        return self._injections.take(kind, self.sim.t)

    def _configure(self, what: str, options) -> None:
        """A configuration call's round trip: ``config_latency`` s, or a timeout."""
        timeout = self._timeout_s(options)
        if self._take("config_timeout") is not None or self.config_latency > timeout:
            self._wait(timeout)
            self.config_timeouts += 1
            raise TimeoutError(f"{what}: no reply within {1e3 * timeout:.0f} ms")
        self._wait(self.config_latency)

    # ----------------------------------------------------------------- configuration services
    def set_servoing_mode(self, info) -> None:
        """``Base.SetServoingMode``: SINGLE_LEVEL_SERVOING (2) or LOW_LEVEL_SERVOING (3).

        Args:
            info: a ``ServoingModeInformation``.

        Raises:
            KServerException: another servoing mode.
        """
        mode = info.servoing_mode
        if mode not in (2, 3):
            raise self._refuse(f"servoing mode {mode} is not supported by the emulator")
        if mode == 2 and self.low_level and not self.all_position:
            self.violations.append(
                f"left low-level servoing with actuators not in POSITION mode: {self._mode_names()}"
            )
            self._all_to_position()
        if mode == 3 and not self.low_level:
            self.last_frame_id = None
            self._low_level_since = self.sim.t
            self._last_command = self._basis = None
        self._frames_since_switch = 0
        self.servoing_mode = mode

    def _mode_names(self) -> dict[int, str]:
        return {d: CONTROL_MODES.Name(m) for d, m in self.control_modes.items()}

    def _all_to_position(self) -> None:
        for d in DEVICE_IDS:
            self.control_modes[d] = CONTROL_MODES.Value("POSITION")
        self.sim.hold()

    def control_mode_of(self, device_id: int) -> int:
        """``ActuatorConfig.GetControlMode``.

        Args:
            device_id: the actuator's device id.

        Returns:
            Its control mode (ActuatorConfig.ControlMode number).

        Raises:
            KServerException: no actuator has that id.
        """
        self._device(device_id)
        return self.control_modes[device_id]

    def set_control_mode(self, info, device_id: int) -> None:
        """``ActuatorConfig.SetControlMode`` of one actuator, recorded in ``switches``.

        Args:
            info: a ``ControlModeInformation``. device_id: the actuator's device id.

        Raises:
            KServerException: no such actuator, a mode the Gen3 Lite lacks, or CURRENT or
                VELOCITY outside LOW_LEVEL_SERVOING.
        """
        j = self._device(device_id)
        mode = info.control_mode
        self._check_mode(device_id, mode)
        self._record_switch(j, device_id, mode)
        self._frames_since_switch = 0
        self.control_modes[device_id] = mode
        if not self._in_fault():
            self.sim.set_modes({j: _TO_MODE[mode]})
            if self._targets is not None:  # the actuator goes on with the last command
                self.sim.set_targets(*self._targets)

    def _check_mode(self, device_id: int, mode: int) -> None:
        """Refuse a mode the Gen3 Lite lacks, or CURRENT or VELOCITY before low-level servoing."""
        if mode not in _TO_MODE:
            raise self._refuse(
                f"control mode {CONTROL_MODES.Name(mode)} is not available on the Gen3 Lite"
            )
        if mode != CONTROL_MODES.Value("POSITION") and not self.low_level:
            raise self._refuse(
                f"{CONTROL_MODES.Name(mode)} mode for actuator {device_id} needs "
                "LOW_LEVEL_SERVOING first"
            )

    def _record_switch(self, i: int, device: int, mode: int) -> None:
        """Log the switch (``SwitchRecord``); one to CURRENT or VELOCITY without a hold frame
        is a violation."""
        held = self._held(i, device, mode) if self.low_level else None
        self.switches.append(
            SwitchRecord(
                self.sim.t,
                device,
                CONTROL_MODES.Name(mode),
                self.low_level,
                self._frames_since_switch,
                held,
            )
        )
        if held is False and mode != CONTROL_MODES.Value("POSITION"):
            self.violations.append(
                f"SetControlMode({CONTROL_MODES.Name(mode)}) for actuator {device} without a "
                "hold frame built from the feedback before it"
            )

    def _held(self, i: int, device: int, mode: int) -> bool:
        """A hold frame came since the last switch and starts actuator index ``i`` in
        ``mode`` where the host last saw it (``starts_where_seen``)."""
        if self._frames_since_switch < 1 or self._last_command is None or self._basis is None:
            return False
        seen = self._basis.actuators[i]
        return starts_where_seen(mode, self.control_modes[device], self._last_command, i, seen)

    def clear_faults(self) -> None:
        """``Base.ClearFaults``: every actuator and arm fault cleared, the modes restored."""
        self.fault_a = dict.fromkeys(DEVICE_IDS, 0)
        self.arm_fault_a = 0
        self.sim.clear_faults()
        self.sim.set_modes({j: _TO_MODE[self.control_modes[d]] for j, d in enumerate(DEVICE_IDS)})

    # ----------------------------------------------------------------- the cyclic exchange
    def refresh(self, command, options=None) -> Feedback:
        """One cyclic exchange (``BaseCyclic.Refresh``): apply the command for 1 ms, return
        the feedback (or lose it: see ``inject_lost``).

        Args:
            command: a ``Command`` (positions deg, velocities deg/s, currents A).
            options: the caller's ``RouterClientSendOptions`` (``timeout_ms``), or None.

        Returns:
            The ``Feedback`` after the step.

        Raises:
            KServerException: outside LOW_LEVEL_SERVOING, or a command the arm rejects.
            KClientException: an injected client error (nothing sent).
            TimeoutError: a lost command or reply (the caller waited its timeout).
        """
        if not self.low_level:
            raise self._refuse("Refresh with a command outside LOW_LEVEL_SERVOING")
        loss = self._loss()
        if loss == "client":
            self.lost["client"] += 1
            raise KClientException("Couldn't send message frame (injected)")
        timeout = self._timeout_s(options)
        if loss == "command":
            raise self._lost("command", timeout, timeout)
        self._check_command(command)
        jitter = self._receive(command.frame_id)
        self._apply(command)
        self._run_cycle()
        fb = self._reply(command, jitter)
        if loss == "reply":
            raise self._lost("reply", timeout - CONTROL_PERIOD, timeout)
        self._draw_late()
        self._delivered = fb
        return fb

    def refresh_feedback(self) -> Feedback:
        """``BaseCyclic.RefreshFeedback``: the current feedback, no command.

        Returns:
            The ``Feedback`` (what the host now has received).
        """
        self._delivered = fb = self.feedback()
        return fb

    def _due(self, kind: str) -> Injection | None:
        """A due one-shot injection of ``kind`` (stale feedback: while it lasts), or None."""
        return self._injections.due(kind, self.sim.t)

    def _loss(self) -> str | None:
        """How this Refresh fails: an injected loss, a random lost reply, or None."""
        inj = self._take("lost")
        if inj is not None:
            return inj.what
        if self.lost_reply_rate and self._rng.random() < self.lost_reply_rate:
            return "reply"
        return None

    def _lost(self, what: str, wait: float, timeout: float) -> TimeoutError:
        """A lost command or reply, counted: the caller waits ``wait`` s of its ``timeout``."""
        self.lost[what] += 1
        self._wait(wait)
        self._draw_late()
        return TimeoutError(f"Refresh: no reply within {1e3 * timeout:.0f} ms ({what} lost)")

    def _check_command(self, command) -> None:
        """Refuse a command the arm rejects (``command_refusal``)."""
        refusal = command_refusal(command, self.last_frame_id, DEVICE_IDS)
        if refusal is not None:
            raise self._refuse(refusal)

    def _receive(self, frame_id: int) -> int:
        """Count an accepted command; its arrival's jitter (us) against the last one's."""
        self.last_frame_id = frame_id
        self.refresh_count += 1
        self._frames_since_switch += 1
        arrival = self.sim.t + self._late
        last = self._last_arrival
        jitter = 0 if last is None else int(abs(arrival - last - CONTROL_PERIOD) * 1e6)
        self._last_arrival = arrival
        self.max_jitter_us = max(self.max_jitter_us, jitter)
        return jitter

    def _run_cycle(self) -> None:
        """The arm's 1 ms (more after an injected stall), then the faults that came in it."""
        steps = 1
        stall = self._due("stall")
        if stall is not None:
            steps += int(round(stall.seconds / CONTROL_PERIOD))
        self.sim.step(steps)
        fault = self._due("fault")
        if fault is not None:
            self.fault_a[fault.device] |= fault.bits
            self.sim.hold()
        arm_fault = self._due("arm_fault")
        if arm_fault is not None:
            self.arm_fault_a |= arm_fault.bits
            self.sim.hold()
        self._sim_faults()

    def _reply(self, command, jitter: int) -> Feedback:
        """The reply: the old feedback again while stale (injected), else a fresh one."""
        if self._due("stale") is not None and self._last_feedback is not None:
            return copy.deepcopy(self._last_feedback)
        fb = self.feedback(command.frame_id, jitter, command)
        self._last_feedback = fb
        return fb

    def _draw_late(self) -> None:
        if self.jitter:
            self._late = float(self._rng.uniform(0.0, self.jitter))

    def _apply(self, command) -> None:
        """The command's targets to the simulator, unless a following error or a current
        beyond ``MAX_CURRENT`` faults."""
        cmd_pos = np.array([a.position for a in command.actuators])
        velocity_deg = np.array([a.velocity for a in command.actuators])
        current = np.array([a.current_motor for a in command.actuators])
        self._last_command = (cmd_pos, velocity_deg, current)
        self._basis = self._delivered
        q_deg = np.rad2deg(self.sim.data.qpos[self.sim.arm_qposadr])
        err = diff_deg(cmd_pos, q_deg)
        self._following_faults(err)
        if self._in_fault():
            return
        self._current_faults(current)
        if not self._in_fault():
            position = np.deg2rad(q_deg + err)
            velocity = np.deg2rad(velocity_deg)
            self._targets = (position, velocity, current)
            self.sim.set_targets(position, velocity, current)

    def _following_faults(self, err: np.ndarray) -> None:
        """FOLLOWING_ERROR on each actuator commanded further than ``following_error_deg``
        (``err`` (6,) deg, commanded - measured)."""
        for i in np.flatnonzero(np.abs(err) > self.following_error_deg):
            d = DEVICE_IDS[i]
            if not self.fault_a[d] & FOLLOWING_ERROR:
                self.fault_a[d] |= FOLLOWING_ERROR
                self.sim.fault(f"actuator {d}: following error {err[i]:.1f} deg", int(i))

    def _current_faults(self, current: np.ndarray) -> None:
        """MAX_TORQUE on each CURRENT-mode actuator commanded beyond ``MAX_CURRENT``
        (``current`` (6,) A)."""
        in_current = np.array([m is ControlMode.CURRENT for m in self.sim.modes])
        for i in np.flatnonzero((np.abs(current) > MAX_CURRENT) & in_current):
            self.fault_a[DEVICE_IDS[i]] |= MAX_TORQUE
            self.sim.fault(
                f"actuator {DEVICE_IDS[i]}: current {current[i]:.2f} A beyond 11 A", int(i)
            )

    def _sim_faults(self) -> None:
        if not self.sim.fault_joints:
            return
        for j in self.sim.fault_joints:
            d = DEVICE_IDS[j]
            if not self.fault_a[d]:
                self.fault_a[d] |= ARM_FAULT
        self.sim.hold()

    def feedback(self, frame_id: int | None = None, jitter: int = 0, command=None) -> Feedback:
        """The current Feedback message (what RefreshFeedback returns).

        Args:
            frame_id: its frame id (None: the next of the emulator's own).
            jitter: us, each actuator's ``jitter_comm``.
            command: the ``Command`` it answers (its actuators' ``command_id`` echoed), or None.

        Returns:
            The ``Feedback``: arm state and fault banks, each actuator's position deg in
            [0, 360), velocity deg/s, current A and torque N m.
        """
        self._frame = (self._frame + 1) % 65536 if frame_id is None else frame_id
        fb = Feedback(frame_id=self._frame)
        fb.base.active_state = self.arm_state
        joint_fault = JOINT_FAULT if any(self.fault_a.values()) else 0
        fb.base.fault_bank_a = self.arm_fault_a | joint_fault
        fb.base.arm_voltage = 24.0
        self._actuator_feedback(fb, jitter, command)
        return fb

    def _actuator_feedback(self, fb: Feedback, jitter: int, command) -> None:
        """Each actuator's feedback, added to ``fb``."""
        sim = self.sim
        q = wrap_deg(np.rad2deg(sim.data.qpos[sim.arm_qposadr]))
        dq = np.rad2deg(sim.data.qvel[sim.arm_dofadr])
        torque = sim.applied_torque
        fill_actuator_feedback(
            fb, DEVICE_IDS, q, dq, sim.current, torque, self.fault_a, jitter, command
        )
