"""A Kinova Kortex emulator backed by the simulated arm.

``KortexEmulator().api`` has the names the Kortex adapter takes from ``kortex_api``
(transports, router and its send options, session manager, ``BaseClient``,
``BaseCyclicClient``, ``ActuatorConfigClient``, the ``*_pb2`` message modules,
``KServerException``, ``KClientException``), with the same method names and message fields
(assigning any other field raises, as protobuf does), so the adapter runs unchanged against it.
Behind them a ``Simulator`` plays the Gen3 Lite and the emulator enforces the protocol of
shared/reference/FIGURES.md:

- configuration calls over TCP port 10000, ``BaseCyclic`` over UDP port 10001, both in an open
  session; actuator device ids 1, 2, 3, 4, 5 and 7;
- ``Refresh`` only in LOW_LEVEL_SERVOING; each command's ``frame_id`` must advance (mod 65536)
  and every actuator's ``command_id`` equal it, else the command is rejected;
- a commanded position further than ``following_error_deg`` from the measured one raises a
  following-error fault on that actuator (the arm then holds: it is in fault);
- ``SetControlMode(CURRENT or VELOCITY)`` before LOW_LEVEL_SERVOING is refused; leaving low-level
  servoing or closing the session with an actuator not in POSITION mode is a violation, and so
  is a switch to CURRENT or VELOCITY in low-level servoing that no hold frame precedes: the
  last cyclic command before it, received after the previous switch, must start the new mode
  exactly where the last feedback the host received left the actuator (its measured current,
  for CURRENT; velocity 0, for VELOCITY; its measured position, for POSITION from another
  mode). Every switch is logged in ``switches`` (``SwitchRecord``).

It produces what the arm produces: the arm state in ``Feedback.base.active_state`` and
``GetArmState`` (ARMSTATE_SERVOING_READY, ARMSTATE_SERVOING_LOW_LEVEL once in low-level
servoing, ARMSTATE_IN_FAULT on any fault), arm-level fault bits (``Base.SafetyIdentifier``) in
``base.fault_bank_a`` (JOINT_FAULT while an actuator is in fault), configuration calls that
take ``config_latency`` s (the arm runs on the last cyclic command meanwhile), replies that
never come (the caller waits its ``timeout_ms`` and gets ``TimeoutError``, as kortex_api's
future does) and the host's jitter (each send late by up to ``jitter`` s, seen in ``clock()``
and in the actuators' ``jitter_comm``).

Every refusal is also appended to ``violations``. Units on the wire are Kortex's: positions in
deg in [0, 360), velocities deg/s, currents A, floats rounded to float32. Time is the
simulator's (lock step: 1 ms per ``Refresh``); ``clock()`` reads it (plus the host's lateness).
Injections: ``inject_stall`` (the caller misses cycles), ``inject_stale`` (no new feedback
frames), ``inject_fault`` (an actuator fault bit), ``inject_arm_fault`` (an arm-level fault),
``inject_lost`` (lost replies, lost commands, client errors), ``inject_config_timeout``
(configuration calls without a reply); constructor options draw lost replies at random
(``lost_reply_rate``) and the jitter (``jitter``, ``seed``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.hardware.interface import ControlMode
from jaxcomp.hardware.sim_arm import Simulator

DEVICE_IDS = (1, 2, 3, 4, 5, 7)
TCP_PORT, UDP_PORT = 10000, 10001
#: Fault bits of the emulator (fault_bank_a); the adapter reports any non-zero bank.
FOLLOWING_ERROR = 1 << 4
ARM_FAULT = 1 << 7  # a fault the simulated actuator raised (limit, torque, speed)
MAX_TORQUE = 1 << 9
OVERSPEED = 1 << 11
INJECTED = 1 << 15


class KException(Exception):
    """kortex_api.Exceptions.KException's role: an error code and sub-code."""

    def __init__(self, message: str, code: int = 1, sub_code: int = 0):
        super().__init__(message)
        self.code, self.sub_code = code, sub_code

    def get_error_code(self) -> int:
        return self.code

    def get_error_sub_code(self) -> int:
        return self.sub_code


class KServerException(KException):
    """Raised for a request the arm refused (kortex_api's KServerException)."""


class KClientException(KException):
    """Raised on the client side, e.g. a frame that could not be sent (kortex_api's
    KClientException; not a KServerException)."""


# --------------------------------------------------------------------- protobuf look-alikes
class _Enum:
    """A protobuf enum wrapper: ``Value(name)`` and ``Name(number)``."""

    def __init__(self, **values: int):
        self._values = values

    def Value(self, name: str) -> int:  # noqa: N802 - protobuf's name
        if name not in self._values:
            raise ValueError(f"enum has no value named {name!r}")
        return self._values[name]

    def Name(self, number: int) -> str:  # noqa: N802 - protobuf's name
        for k, v in self._values.items():
            if v == number:
                return k
        raise ValueError(f"enum has no value {number}")

    def items(self):
        return self._values.items()


class _Repeated:
    """A repeated message field: ``add()``, ``extend()``, indexing, ``len``."""

    def __init__(self, kind: type):
        self._kind = kind
        self._items: list = []

    def add(self, **kw):
        item = self._kind(**kw)
        self._items.append(item)
        return item

    def extend(self, items) -> None:
        for it in items:
            self.add().CopyFrom(it)

    def __getitem__(self, i):
        return self._items[i]

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self):
        return iter(self._items)


class _Message:
    """A protobuf message look-alike: declared fields only, typed, ``CopyFrom``."""

    _fields: dict[str, object] = {}

    def __init__(self, **kw):
        for name, kind in self._fields.items():
            if isinstance(kind, tuple):  # repeated message
                value = _Repeated(kind[0])
            elif isinstance(kind, type) and issubclass(kind, _Message):
                value = kind()
            else:
                value = kind
            object.__setattr__(self, name, value)
        for k, v in kw.items():
            setattr(self, k, v)

    def __setattr__(self, name: str, value) -> None:
        if name not in self._fields:
            raise AttributeError(f"{type(self).__name__} has no field {name!r}")
        default = self._fields[name]
        if isinstance(default, tuple) or (
            isinstance(default, type) and issubclass(default, _Message)
        ):
            raise AttributeError(
                f"assignment not allowed to message or repeated field {name!r} (use CopyFrom / add)"
            )
        if isinstance(default, bool) or isinstance(default, str):
            pass
        elif isinstance(default, int):
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool):
                raise TypeError(f"{type(self).__name__}.{name} is an integer field, got {value!r}")
            value = int(value) & 0xFFFFFFFF
        elif isinstance(default, float):
            if not isinstance(value, (int, float, np.floating, np.integer)):
                raise TypeError(f"{type(self).__name__}.{name} is a float field, got {value!r}")
            value = float(np.float32(value))
        object.__setattr__(self, name, value)

    def CopyFrom(self, other: _Message) -> None:  # noqa: N802 - protobuf's name
        for name in self._fields:
            object.__setattr__(self, name, copy.deepcopy(getattr(other, name)))


def _message(name: str, **fields) -> type:
    return type(name, (_Message,), {"_fields": fields})


# BaseCyclic
ActuatorCommand = _message(
    "ActuatorCommand",
    command_id=0,
    flags=0,
    position=0.0,
    velocity=0.0,
    torque_joint=0.0,
    current_motor=0.0,
)
ActuatorFeedback = _message(
    "ActuatorFeedback",
    command_id=0,
    status_flags=0,
    jitter_comm=0,
    position=0.0,
    velocity=0.0,
    torque=0.0,
    current_motor=0.0,
    voltage=0.0,
    temperature_motor=0.0,
    temperature_core=0.0,
    fault_bank_a=0,
    fault_bank_b=0,
    warning_bank_a=0,
    warning_bank_b=0,
)
BaseFeedback = _message(
    "BaseFeedback",
    active_state=0,
    arm_voltage=0.0,
    arm_current=0.0,
    fault_bank_a=0,
    fault_bank_b=0,
    warning_bank_a=0,
    warning_bank_b=0,
)
Command = _message("Command", frame_id=0, actuators=(ActuatorCommand,))
Feedback = _message("Feedback", frame_id=0, base=BaseFeedback, actuators=(ActuatorFeedback,))
# Base, ActuatorConfig, Session
ServoingModeInformation = _message("ServoingModeInformation", servoing_mode=0)
ControlModeInformation = _message("ControlModeInformation", control_mode=0)
ArmStateInformation = _message("ArmStateInformation", active_state=0)
CreateSessionInfo = _message(
    "CreateSessionInfo",
    username="",
    password="",
    session_inactivity_timeout=0,
    connection_inactivity_timeout=0,
)

SERVOING_MODES = _Enum(
    UNSPECIFIED_SERVOING_MODE=0, SINGLE_LEVEL_SERVOING=2, LOW_LEVEL_SERVOING=3, BYPASS_SERVOING=4
)
#: Common.ArmState (the arm's state in ``Feedback.base.active_state``).
ARM_STATES = _Enum(
    ARMSTATE_UNSPECIFIED=0,
    ARMSTATE_BASE_INITIALIZATION=1,
    ARMSTATE_IDLE=2,
    ARMSTATE_INITIALIZATION=3,
    ARMSTATE_IN_FAULT=4,
    ARMSTATE_MAINTENANCE=5,
    ARMSTATE_SERVOING_LOW_LEVEL=6,
    ARMSTATE_SERVOING_READY=7,
    ARMSTATE_SERVOING_PLAYING_SEQUENCE=8,
    ARMSTATE_SERVOING_MANUALLY_CONTROLLED=9,
    ARMSTATE_RESERVED=255,
)
#: Base.SafetyIdentifier: the bits of the arm-level fault and warning banks, bit k = 1 << k.
_SAFETY_BITS = (
    "FIRMWARE_UPDATE_FAILURE",
    "EXTERNAL_COMMUNICATION_ERROR",
    "MAXIMUM_AMBIENT_TEMPERATURE",
    "MAXIMUM_CORE_TEMPERATURE",
    "JOINT_FAULT",
    "CYCLIC_DATA_JITTER",
    "REACHED_MAXIMUM_EVENT_LOGS",
    "NO_KINEMATICS_SUPPORT",
    "BRAKE_REMOVAL_FAILURE",
    "NETWORK_ERROR",
    "UNABLE_TO_REACH_POSE",
    "JOINT_DETECTION_ERROR",
    "NETWORK_INITIALIZATION_ERROR",
    "MAXIMUM_CURRENT",
    "MAXIMUM_VOLTAGE",
    "MINIMUM_VOLTAGE",
    "MAXIMUM_END_EFFECTOR_TRANSLATION_VELOCITY",
    "MAXIMUM_END_EFFECTOR_ORIENTATION_VELOCITY",
    "MAXIMUM_END_EFFECTOR_TRANSLATION_ACCELERATION",
    "MAXIMUM_END_EFFECTOR_ORIENTATION_ACCELERATION",
    "MAXIMUM_END_EFFECTOR_TRANSLATION_FORCE",
    "MAXIMUM_END_EFFECTOR_ORIENTATION_FORCE",
    "MAXIMUM_END_EFFECTOR_PAYLOAD",
    "EMERGENCY_STOP_ACTIVATED",
    "EMERGENCY_LINE_ACTIVATED",
    "INRUSH_CURRENT_LIMITER_FAULT",
    "NVRAM_CORRUPTED",
    "INCOMPATIBLE_FIRMWARE_VERSION",
    "POWERON_SELF_TEST_FAILURE",
    "DISCRETE_INPUT_STUCK_ACTIVE",
    "ARM_INTO_ILLEGAL_POSITION",
)
SAFETY_IDENTIFIERS = _Enum(
    UNSPECIFIED_BASE_SAFETY_IDENTIFIER=0, **{name: 1 << k for k, name in enumerate(_SAFETY_BITS)}
)
#: Arm-level fault bits the emulator raises itself or is asked to.
JOINT_FAULT, MAXIMUM_CURRENT, EMERGENCY_STOP_ACTIVATED = (
    SAFETY_IDENTIFIERS.Value(name)
    for name in ("JOINT_FAULT", "MAXIMUM_CURRENT", "EMERGENCY_STOP_ACTIVATED")
)
CONTROL_MODES = _Enum(
    NONE=0, POSITION=1, VELOCITY=2, TORQUE=3, CURRENT=4, CUSTOM=5, TORQUE_HIGH_VELOCITY=6
)
_TO_MODE = {1: ControlMode.POSITION, 2: ControlMode.VELOCITY, 4: ControlMode.CURRENT}


def _module(name: str, enums: dict[str, _Enum], **members) -> SimpleNamespace:
    ns = SimpleNamespace(__name__=name, **members)
    for enum_name, enum in enums.items():
        setattr(ns, enum_name, enum)
        for k, v in enum.items():
            setattr(ns, k, v)
    return ns


def _wrap_deg(x):
    """Degrees into [0, 360)."""
    return np.mod(x, 360.0)


def _diff_deg(a, b):
    """a - b in (-180, 180] degrees."""
    return (np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0


@dataclass
class _Injection:
    at: float
    kind: str
    seconds: float = 0.0
    device: int = 0
    bits: int = 0
    count: int = 1
    what: str = ""
    done: bool = False


#: What ``inject_lost`` loses: the reply (the command was applied), the command (it never
#: arrived) or the send itself (a client error at once, nothing sent).
LOST_KINDS = ("reply", "command", "client")


@dataclass(frozen=True)
class SwitchRecord:
    """One ``SetControlMode`` the emulator applied.

    Attributes: t (s, emulated time), device (actuator id), mode (ControlMode name),
    low_level (in LOW_LEVEL_SERVOING), frames (cyclic commands received since the previous
    switch or servoing change), held (the last of them started the new mode where the host
    last saw the actuator, see the module docstring; None outside low-level servoing).
    """

    t: float
    device: int
    mode: str
    low_level: bool
    frames: int
    held: bool | None


# --------------------------------------------------------------------- the emulator
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
        if self.sim.n != len(DEVICE_IDS):
            raise ValueError(f"the emulated Gen3 Lite needs 6 arm joints, got {self.sim.n}")
        for name, value in (
            ("config_latency", config_latency),
            ("servoing_delay", servoing_delay),
            ("jitter", jitter),
        ):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a number of s >= 0, got {value}")
        if not 0 <= lost_reply_rate < 1:
            raise ValueError(f"lost_reply_rate must be in [0, 1), got {lost_reply_rate}")
        self.following_error_deg = float(following_error_deg)
        self.config_latency = float(config_latency)
        self.servoing_delay = float(servoing_delay)
        self.jitter = float(jitter)
        self.lost_reply_rate = float(lost_reply_rate)
        self._rng = np.random.default_rng(seed)
        self._credentials = (username, password)
        self.violations: list[str] = []
        self.servoing_mode = SERVOING_MODES.Value("SINGLE_LEVEL_SERVOING")
        self.control_modes = dict.fromkeys(DEVICE_IDS, CONTROL_MODES.Value("POSITION"))
        self.sessions_open = 0
        self.sessions_closed = 0
        self.connected: set[str] = set()
        self.fault_a = dict.fromkeys(DEVICE_IDS, 0)
        self.arm_fault_a = 0
        self.last_frame_id: int | None = None
        self.refresh_count = 0
        self.lost = dict.fromkeys(LOST_KINDS, 0)
        self.config_timeouts = 0
        self.max_jitter_us = 0
        self.switches: list[SwitchRecord] = []
        self._injections: list[_Injection] = []
        self._last_feedback: Feedback | None = None
        self._delivered: Feedback | None = None  # the last feedback the host received
        self._last_arrival: float | None = None
        self._late = 0.0  # s the host's next send comes after its tick
        self._low_level_since = 0.0
        self._frames_since_switch = 0
        self._last_command: tuple[np.ndarray, ...] | None = None  # position, velocity, current
        self._basis: Feedback | None = None  # what the host had received when it sent it
        self._targets: tuple[np.ndarray, ...] | None = None  # the sim's last targets
        self._frame = 0
        self.api = self._make_api()

    # ----------------------------------------------------------------- inspection
    @property
    def session_open(self) -> bool:
        return self.sessions_open > self.sessions_closed

    @property
    def all_position(self) -> bool:
        """True when every actuator is in POSITION mode."""
        return all(m == CONTROL_MODES.Value("POSITION") for m in self.control_modes.values())

    @property
    def low_level(self) -> bool:
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
        configuration call or a timeout) plus how late the host's next send comes (jitter)."""
        return self.sim.t + self._late

    # ----------------------------------------------------------------- injections
    def inject_stall(self, at: float, seconds: float) -> None:
        """At time ``at`` s the caller stalls for ``seconds`` s (missed cycles)."""
        self._injections.append(_Injection(at, "stall", seconds=seconds))

    def inject_stale(self, at: float, seconds: float) -> None:
        """From ``at`` s, for ``seconds`` s, feedback frames stop coming (old feedback)."""
        self._injections.append(_Injection(at, "stale", seconds=seconds))

    def inject_fault(self, at: float, device: int, bits: int = INJECTED) -> None:
        """At ``at`` s actuator ``device`` raises fault bits ``bits`` in fault_bank_a."""
        self._injections.append(_Injection(at, "fault", device=device, bits=bits))

    def inject_arm_fault(self, at: float, bits: int = EMERGENCY_STOP_ACTIVATED) -> None:
        """At ``at`` s the arm raises the arm-level fault bits ``bits`` (Base.SafetyIdentifier)
        in ``base.fault_bank_a``: ARMSTATE_IN_FAULT, every actuator holds."""
        self._injections.append(_Injection(at, "arm_fault", bits=bits))

    def inject_lost(self, at: float, count: int = 1, what: str = "reply") -> None:
        """The next ``count`` ``Refresh`` calls at or after ``at`` s fail: ``what`` = "reply"
        (the command is applied, its reply lost), "command" (the command never arrives) or
        "client" (``KClientException`` at once, nothing sent). A lost reply or command costs
        the caller its ``timeout_ms`` and raises ``TimeoutError``."""
        if what not in LOST_KINDS:
            raise ValueError(f"what must be one of {LOST_KINDS}, got {what!r}")
        self._injections.append(_Injection(at, "lost", count=int(count), what=what))

    def inject_config_timeout(self, at: float, count: int = 1) -> None:
        """The next ``count`` configuration calls at or after ``at`` s get no reply (not
        applied): the caller waits its ``timeout_ms`` and gets ``TimeoutError``."""
        self._injections.append(_Injection(at, "config_timeout", count=int(count)))

    # ----------------------------------------------------------------- protocol helpers
    def _refuse(self, message: str) -> KServerException:
        self.violations.append(message)
        return KServerException(message)

    def _need(self, transport, kind: str, port: int, what: str) -> None:
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

    def _take(self, kind: str) -> _Injection | None:
        """A due count injection of ``kind`` (one of its counts used up), or None."""
        t = self.sim.t
        for inj in self._injections:
            if inj.kind == kind and not inj.done and t >= inj.at - 1e-9:
                inj.count -= 1
                inj.done = inj.count <= 0
                return inj
        return None

    def _configure(self, what: str, options) -> None:
        """A configuration call's round trip: ``config_latency`` s, or a timeout."""
        timeout = self._timeout_s(options)
        if self._take("config_timeout") is not None or self.config_latency > timeout:
            self._wait(timeout)
            self.config_timeouts += 1
            raise TimeoutError(f"{what}: no reply within {1e3 * timeout:.0f} ms")
        self._wait(self.config_latency)

    # ----------------------------------------------------------------- services
    def set_servoing_mode(self, info) -> None:
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

    def _held(self, i: int, device: int, mode: int) -> bool:
        """A hold frame came since the last switch and its command for actuator index ``i``
        starts ``mode`` where the host last saw the actuator: CURRENT at the measured current,
        VELOCITY at 0, POSITION (from another mode) at the measured position."""
        if self._frames_since_switch < 1 or self._last_command is None or self._basis is None:
            return False
        position, velocity, current = self._last_command
        seen = self._basis.actuators[i]
        if mode == CONTROL_MODES.Value("CURRENT"):
            return bool(current[i] == seen.current_motor)
        if mode == CONTROL_MODES.Value("VELOCITY"):
            return bool(velocity[i] == 0.0)
        if self.control_modes[device] == mode:  # POSITION already: the frame holds its target
            return True
        return bool(position[i] == seen.position)

    def set_control_mode(self, info, device_id: int) -> None:
        j = self._device(device_id)
        mode = info.control_mode
        if mode not in _TO_MODE:
            raise self._refuse(
                f"control mode {CONTROL_MODES.Name(mode)} is not available on the Gen3 Lite"
            )
        if mode != CONTROL_MODES.Value("POSITION") and not self.low_level:
            raise self._refuse(
                f"{CONTROL_MODES.Name(mode)} mode for actuator {device_id} needs "
                "LOW_LEVEL_SERVOING first"
            )
        held = self._held(j, device_id, mode) if self.low_level else None
        self.switches.append(
            SwitchRecord(
                self.sim.t,
                device_id,
                CONTROL_MODES.Name(mode),
                self.low_level,
                self._frames_since_switch,
                held,
            )
        )
        if held is False and mode != CONTROL_MODES.Value("POSITION"):
            self.violations.append(
                f"SetControlMode({CONTROL_MODES.Name(mode)}) for actuator {device_id} without a "
                "hold frame built from the feedback before it"
            )
        self._frames_since_switch = 0
        self.control_modes[device_id] = mode
        if not self._in_fault():
            self.sim.set_modes({j: _TO_MODE[mode]})
            if self._targets is not None:  # the actuator goes on with the last command
                self.sim.set_targets(*self._targets)

    def clear_faults(self) -> None:
        self.fault_a = dict.fromkeys(DEVICE_IDS, 0)
        self.arm_fault_a = 0
        self.sim.clear_faults()
        self.sim.set_modes({j: _TO_MODE[self.control_modes[d]] for j, d in enumerate(DEVICE_IDS)})

    def close_session(self) -> None:
        if self.low_level:
            self.violations.append("session closed while in LOW_LEVEL_SERVOING")
        self.sessions_closed += 1

    def _due(self, kind: str):
        t = self.sim.t
        for inj in self._injections:
            if inj.kind == kind and not inj.done and t >= inj.at:
                if kind == "stale":
                    if t < inj.at + inj.seconds:
                        return inj
                    inj.done = True
                    continue
                inj.done = True
                return inj
        return None

    def _loss(self) -> str | None:
        """How this Refresh fails: an injected loss, a random lost reply, or None."""
        inj = self._take("lost")
        if inj is not None:
            return inj.what
        if self.lost_reply_rate and self._rng.random() < self.lost_reply_rate:
            return "reply"
        return None

    def refresh(self, command, options=None) -> Feedback:
        """One cyclic exchange: apply the command for 1 ms, return the feedback (or lose it:
        see ``inject_lost``)."""
        if not self.low_level:
            raise self._refuse("Refresh with a command outside LOW_LEVEL_SERVOING")
        loss = self._loss()
        if loss == "client":
            self.lost["client"] += 1
            raise KClientException("Couldn't send message frame (injected)")
        timeout = self._timeout_s(options)
        if loss == "command":
            self.lost["command"] += 1
            self._wait(timeout)
            self._draw_late()
            raise TimeoutError(f"Refresh: no reply within {1e3 * timeout:.0f} ms (command lost)")
        fid = command.frame_id
        if len(command.actuators) != len(DEVICE_IDS):
            raise self._refuse(
                f"command for {len(command.actuators)} actuators, the arm has {len(DEVICE_IDS)}"
            )
        if self.last_frame_id is not None and not 0 < (fid - self.last_frame_id) % 65536 < 32768:
            raise self._refuse(f"frame_id {fid} did not advance past {self.last_frame_id}")
        for i, a in enumerate(command.actuators):
            if a.command_id & 0xFFFF != fid:
                raise self._refuse(
                    f"actuator {DEVICE_IDS[i]}: command_id {a.command_id} does not match "
                    f"frame_id {fid}"
                )
            if not a.flags & 1:
                raise self._refuse(f"actuator {DEVICE_IDS[i]}: servoing flag (flags=1) not set")
        self.last_frame_id = fid
        self.refresh_count += 1
        self._frames_since_switch += 1
        arrival = self.sim.t + self._late
        last = self._last_arrival
        jitter = 0 if last is None else int(abs(arrival - last - CONTROL_PERIOD) * 1e6)
        self._last_arrival = arrival
        self.max_jitter_us = max(self.max_jitter_us, jitter)
        self._apply(command)
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
        if self._due("stale") is not None and self._last_feedback is not None:
            fb = copy.deepcopy(self._last_feedback)
        else:
            fb = self.feedback(fid, jitter, command)
            self._last_feedback = fb
        if loss == "reply":
            self.lost["reply"] += 1
            self._wait(timeout - CONTROL_PERIOD)
            self._draw_late()
            raise TimeoutError(f"Refresh: no reply within {1e3 * timeout:.0f} ms (reply lost)")
        self._draw_late()
        self._delivered = fb
        return fb

    def _draw_late(self) -> None:
        if self.jitter:
            self._late = float(self._rng.uniform(0.0, self.jitter))

    def _apply(self, command) -> None:
        sim = self.sim
        cmd_pos = np.array([a.position for a in command.actuators])
        velocity_deg = np.array([a.velocity for a in command.actuators])
        current = np.array([a.current_motor for a in command.actuators])
        self._last_command = (cmd_pos, velocity_deg, current)
        self._basis = self._delivered
        q_deg = np.rad2deg(sim.data.qpos[sim._qadr])
        err = _diff_deg(cmd_pos, q_deg)
        for i in np.flatnonzero(np.abs(err) > self.following_error_deg):
            d = DEVICE_IDS[i]
            if not self.fault_a[d] & FOLLOWING_ERROR:
                self.fault_a[d] |= FOLLOWING_ERROR
                sim.fault(f"actuator {d}: following error {err[i]:.1f} deg", int(i))
        if self._in_fault():
            return
        position = np.deg2rad(q_deg + err)
        velocity = np.deg2rad(velocity_deg)
        over = np.abs(current) > 11.0
        for i in np.flatnonzero(over & sim._is_cur):
            self.fault_a[DEVICE_IDS[i]] |= MAX_TORQUE
            sim.fault(f"actuator {DEVICE_IDS[i]}: current {current[i]:.2f} A beyond 11 A", int(i))
        if not self._in_fault():
            self._targets = (position, velocity, current)
            sim.set_targets(position, velocity, current)

    def _sim_faults(self) -> None:
        if not self.sim.fault_joints:
            return
        for j in self.sim.fault_joints:
            d = DEVICE_IDS[j]
            if not self.fault_a[d]:
                self.fault_a[d] |= ARM_FAULT
        self.sim.hold()

    def feedback(self, frame_id: int | None = None, jitter: int = 0, command=None) -> Feedback:
        """The current Feedback message (what RefreshFeedback returns)."""
        sim = self.sim
        self._frame = (self._frame + 1) % 65536 if frame_id is None else frame_id
        fb = Feedback(frame_id=self._frame)
        fb.base.active_state = self.arm_state
        joint_fault = JOINT_FAULT if any(self.fault_a.values()) else 0
        fb.base.fault_bank_a = self.arm_fault_a | joint_fault
        fb.base.arm_voltage = 24.0
        q = _wrap_deg(np.rad2deg(sim.data.qpos[sim._qadr]))
        dq = np.rad2deg(sim.data.qvel[sim._dadr])
        torque = sim.applied_torque
        for i, d in enumerate(DEVICE_IDS):
            a = fb.actuators.add()
            a.position = q[i]
            a.velocity = dq[i]
            a.current_motor = sim.current[i]
            a.torque = torque[i]
            a.voltage = 24.0
            a.temperature_motor = a.temperature_core = 35.0
            a.fault_bank_a = self.fault_a[d]
            a.jitter_comm = jitter
            if command is not None:
                a.command_id = command.actuators[i].command_id
        return fb

    # ----------------------------------------------------------------- the fake kortex_api
    def _make_api(self) -> SimpleNamespace:
        emu = self

        class _Transport:
            kind = ""

            def __init__(self):
                self.port = None
                self.is_connected = False

            def connect(self, ip: str, port: int) -> None:
                self.ip, self.port, self.is_connected = ip, port, True
                emu.connected.add(self.kind)

            def disconnect(self) -> None:
                self.is_connected = False
                emu.connected.discard(self.kind)

        class TCPTransport(_Transport):
            kind = "tcp"

        class UDPTransport(_Transport):
            kind = "udp"

        class RouterClient:
            def __init__(self, transport, error_callback=None):
                self.transport = transport
                self.error_callback = error_callback
                self.active = True

            def SetActivationStatus(self, active: bool) -> None:  # noqa: N802
                self.active = active

        class RouterClientSendOptions:
            """kortex_api's send options: these three fields and no other."""

            __slots__ = ("andForget", "delay_ms", "timeout_ms")

            def __init__(self):
                self.andForget = False
                self.delay_ms = 0
                self.timeout_ms = 10000

            def getTimeoutInSecond(self) -> float:  # noqa: N802
                return self.timeout_ms / 1000

        class SessionManager:
            def __init__(self, router):
                self.router = router
                self.open = False

            def CreateSession(self, info) -> None:  # noqa: N802
                if not self.router.transport.is_connected:
                    raise emu._refuse("CreateSession on a transport that is not connected")
                if (info.username, info.password) != emu._credentials:
                    raise KServerException("wrong username or password")
                self.open = True
                emu.sessions_open += 1

            def CloseSession(self) -> None:  # noqa: N802
                if self.open:
                    self.open = False
                    emu.close_session()

        class BaseClient:
            def __init__(self, router):
                self.router = router

            def _call(self, what: str, options) -> None:
                emu._need(self.router.transport, "tcp", TCP_PORT, f"Base.{what}")
                emu._configure(f"Base.{what}", options)

            def SetServoingMode(self, info, deviceId=0, options=None):  # noqa: N802, N803
                self._call("SetServoingMode", options)
                emu.set_servoing_mode(info)

            def GetServoingMode(self, deviceId=0, options=None):  # noqa: N802, N803
                self._call("GetServoingMode", options)
                return ServoingModeInformation(servoing_mode=emu.servoing_mode)

            def ClearFaults(self, deviceId=0, options=None) -> None:  # noqa: N802, N803
                self._call("ClearFaults", options)
                emu.clear_faults()

            def GetArmState(self, deviceId=0, options=None):  # noqa: N802, N803
                self._call("GetArmState", options)
                return ArmStateInformation(active_state=emu.arm_state)

        class BaseCyclicClient:
            def __init__(self, router):
                self.router = router

            def Refresh(self, command, deviceId=0, options=None):  # noqa: N802, N803
                emu._need(self.router.transport, "udp", UDP_PORT, "BaseCyclic.Refresh")
                return emu.refresh(command, options)

            def RefreshFeedback(self, deviceId=0, options=None):  # noqa: N802, N803
                emu._need(self.router.transport, "udp", UDP_PORT, "BaseCyclic.RefreshFeedback")
                emu._delivered = fb = emu.feedback()
                return fb

        class ActuatorConfigClient:
            def __init__(self, router):
                self.router = router

            def _call(self, what: str, options) -> None:
                emu._need(self.router.transport, "tcp", TCP_PORT, f"ActuatorConfig.{what}")
                emu._configure(f"ActuatorConfig.{what}", options)

            def SetControlMode(self, info, deviceId=0, options=None):  # noqa: N802, N803
                self._call("SetControlMode", options)
                emu.set_control_mode(info, deviceId)

            def GetControlMode(self, deviceId=0, options=None):  # noqa: N802, N803
                self._call("GetControlMode", options)
                emu._device(deviceId)
                return ControlModeInformation(control_mode=emu.control_modes[deviceId])

        return SimpleNamespace(
            TCPTransport=TCPTransport,
            UDPTransport=UDPTransport,
            RouterClient=RouterClient,
            RouterClientSendOptions=RouterClientSendOptions,
            SessionManager=SessionManager,
            BaseClient=BaseClient,
            BaseCyclicClient=BaseCyclicClient,
            ActuatorConfigClient=ActuatorConfigClient,
            KServerException=KServerException,
            KClientException=KClientException,
            Session_pb2=_module("Session_pb2", {}, CreateSessionInfo=CreateSessionInfo),
            Common_pb2=_module("Common_pb2", {"ArmState": ARM_STATES}),
            Base_pb2=_module(
                "Base_pb2",
                {"ServoingMode": SERVOING_MODES, "SafetyIdentifier": SAFETY_IDENTIFIERS},
                ServoingModeInformation=ServoingModeInformation,
                ArmStateInformation=ArmStateInformation,
            ),
            BaseCyclic_pb2=_module(
                "BaseCyclic_pb2",
                {},
                Command=Command,
                Feedback=Feedback,
                ActuatorCommand=ActuatorCommand,
                ActuatorFeedback=ActuatorFeedback,
            ),
            ActuatorConfig_pb2=_module(
                "ActuatorConfig_pb2",
                {"ControlMode": CONTROL_MODES},
                ControlModeInformation=ControlModeInformation,
            ),
        )
