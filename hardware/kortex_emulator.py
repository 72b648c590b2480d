"""A Kinova Kortex emulator backed by the simulated arm.

``KortexEmulator().api`` has the names the Kortex adapter takes from ``kortex_api``
(transports, router, session manager, ``BaseClient``, ``BaseCyclicClient``,
``ActuatorConfigClient``, the ``*_pb2`` message modules, ``KServerException``), with the same
method names and message fields, so the adapter runs unchanged against it. Behind them a
``Simulator`` plays the Gen3 Lite and the emulator enforces the protocol of
shared/reference/FIGURES.md:

- configuration calls over TCP port 10000, ``BaseCyclic`` over UDP port 10001, both in an open
  session; actuator device ids 1, 2, 3, 4, 5 and 7;
- ``Refresh`` only in LOW_LEVEL_SERVOING; each command's ``frame_id`` must advance (mod 65536)
  and every actuator's ``command_id`` equal it, else the command is rejected;
- a commanded position further than ``following_error_deg`` from the measured one raises a
  following-error fault on that actuator (the arm then holds: it is in fault);
- ``SetControlMode(CURRENT or VELOCITY)`` before LOW_LEVEL_SERVOING is refused; leaving low-level
  servoing or closing the session with an actuator not in POSITION mode is a violation.

Every refusal is also appended to ``violations``. Units on the wire are Kortex's: positions in
deg in [0, 360), velocities deg/s, currents A, floats rounded to float32. Time is the
simulator's (lock step: 1 ms per ``Refresh``); ``clock()`` reads it. Faults can be injected:
``inject_stall`` (the caller misses cycles), ``inject_stale`` (no new feedback frames),
``inject_fault`` (an actuator fault bit).
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


class KServerException(Exception):
    """Raised for a refused request (kortex_api.Exceptions.KServerException's role)."""

    def __init__(self, message: str, code: int = 1, sub_code: int = 0):
        super().__init__(message)
        self.code, self.sub_code = code, sub_code

    def get_error_code(self) -> int:
        return self.code

    def get_error_sub_code(self) -> int:
        return self.sub_code


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
BaseFeedback = _message("BaseFeedback", active_state=0, arm_voltage=0.0, fault_bank_a=0)
Command = _message("Command", frame_id=0, actuators=(ActuatorCommand,))
Feedback = _message("Feedback", frame_id=0, base=BaseFeedback, actuators=(ActuatorFeedback,))
# Base, ActuatorConfig, Session
ServoingModeInformation = _message("ServoingModeInformation", servoing_mode=0)
ControlModeInformation = _message("ControlModeInformation", control_mode=0)
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
ARM_STATES = _Enum(ARMSTATE_UNSPECIFIED=0, ARMSTATE_IN_FAULT=4, ARMSTATE_SERVOING_READY=7)
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
    done: bool = False


# --------------------------------------------------------------------- the emulator
class KortexEmulator:
    """A Gen3 Lite behind kortex_api's interfaces (see the module docstring).

    Args:
        sim: the simulator playing the arm (default: a fresh ``Simulator("gen3_lite")``).
        following_error_deg: commanded-vs-measured position difference that faults, deg.
        username, password: the credentials ``CreateSession`` accepts.
    """

    def __init__(
        self,
        sim: Simulator | None = None,
        *,
        following_error_deg: float = 10.0,
        username: str = "admin",
        password: str = "admin",
    ):
        self.sim = sim if sim is not None else Simulator("gen3_lite")
        if self.sim.n != len(DEVICE_IDS):
            raise ValueError(f"the emulated Gen3 Lite needs 6 arm joints, got {self.sim.n}")
        self.following_error_deg = float(following_error_deg)
        self._credentials = (username, password)
        self.violations: list[str] = []
        self.servoing_mode = SERVOING_MODES.Value("SINGLE_LEVEL_SERVOING")
        self.control_modes = dict.fromkeys(DEVICE_IDS, CONTROL_MODES.Value("POSITION"))
        self.sessions_open = 0
        self.sessions_closed = 0
        self.connected: set[str] = set()
        self.fault_a = dict.fromkeys(DEVICE_IDS, 0)
        self.last_frame_id: int | None = None
        self.refresh_count = 0
        self.max_jitter_us = 0
        self._injections: list[_Injection] = []
        self._last_feedback: Feedback | None = None
        self._last_refresh_t: float | None = None
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

    def clock(self) -> float:
        """The emulated time, s (advances 1 ms per Refresh, more after a stall)."""
        return self.sim.t

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
        return any(self.fault_a.values())

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
        self.servoing_mode = mode

    def _mode_names(self) -> dict[int, str]:
        return {d: CONTROL_MODES.Name(m) for d, m in self.control_modes.items()}

    def _all_to_position(self) -> None:
        for d in DEVICE_IDS:
            self.control_modes[d] = CONTROL_MODES.Value("POSITION")
        self.sim.hold()

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
        self.control_modes[device_id] = mode
        if not self._in_fault():
            self.sim.set_modes({j: _TO_MODE[mode]})

    def clear_faults(self) -> None:
        self.fault_a = dict.fromkeys(DEVICE_IDS, 0)
        self.sim.clear_faults()
        self.sim.set_modes({j: _TO_MODE[self.control_modes[d]] for j, d in enumerate(DEVICE_IDS)})

    def close_session(self) -> None:
        if self.low_level:
            self.violations.append("session closed while in LOW_LEVEL_SERVOING")
        self.sessions_closed += 1

    def _due(self, kind: str):
        t = self.clock()
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

    def refresh(self, command) -> Feedback:
        """One cyclic exchange: apply the command for 1 ms, return the feedback."""
        if not self.low_level:
            raise self._refuse("Refresh with a command outside LOW_LEVEL_SERVOING")
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
        self._sim_faults()
        t = self.clock()
        last = self._last_refresh_t
        jitter = 0 if last is None else abs(t - last - CONTROL_PERIOD) * 1e6
        self._last_refresh_t = t
        self.max_jitter_us = max(self.max_jitter_us, int(jitter))
        if self._due("stale") is not None and self._last_feedback is not None:
            return copy.deepcopy(self._last_feedback)
        fb = self.feedback(fid, int(jitter), command)
        self._last_feedback = fb
        return fb

    def _apply(self, command) -> None:
        sim = self.sim
        q_deg = np.rad2deg(sim.data.qpos[sim._qadr])
        cmd_pos = np.array([a.position for a in command.actuators])
        err = _diff_deg(cmd_pos, q_deg)
        for i in np.flatnonzero(np.abs(err) > self.following_error_deg):
            d = DEVICE_IDS[i]
            if not self.fault_a[d] & FOLLOWING_ERROR:
                self.fault_a[d] |= FOLLOWING_ERROR
                sim.fault(f"actuator {d}: following error {err[i]:.1f} deg", int(i))
        if self._in_fault():
            return
        position = np.deg2rad(q_deg + err)
        velocity = np.deg2rad([a.velocity for a in command.actuators])
        current = np.array([a.current_motor for a in command.actuators])
        over = np.abs(current) > 11.0
        for i in np.flatnonzero(over & sim._is_cur):
            self.fault_a[DEVICE_IDS[i]] |= MAX_TORQUE
            sim.fault(f"actuator {DEVICE_IDS[i]}: current {current[i]:.2f} A beyond 11 A", int(i))
        if not self._in_fault():
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
        fb.base.active_state = ARM_STATES.Value(
            "ARMSTATE_IN_FAULT" if self._in_fault() else "ARMSTATE_SERVOING_READY"
        )
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
            def __init__(self):
                self.andForget = False
                self.delay_before_timeout = 0
                self.timeout_ms = 0

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

            def _check(self, what: str) -> None:
                emu._need(self.router.transport, "tcp", TCP_PORT, f"Base.{what}")

            def SetServoingMode(self, info) -> None:  # noqa: N802
                self._check("SetServoingMode")
                emu.set_servoing_mode(info)

            def GetServoingMode(self):  # noqa: N802
                self._check("GetServoingMode")
                return ServoingModeInformation(servoing_mode=emu.servoing_mode)

            def ClearFaults(self) -> None:  # noqa: N802
                self._check("ClearFaults")
                emu.clear_faults()

            def GetArmState(self):  # noqa: N802
                self._check("GetArmState")
                return SimpleNamespace(active_state=emu.feedback().base.active_state)

        class BaseCyclicClient:
            def __init__(self, router):
                self.router = router

            def Refresh(self, command, deviceId=0, options=None):  # noqa: N802, N803
                emu._need(self.router.transport, "udp", UDP_PORT, "BaseCyclic.Refresh")
                return emu.refresh(command)

            def RefreshFeedback(self, deviceId=0, options=None):  # noqa: N802, N803
                emu._need(self.router.transport, "udp", UDP_PORT, "BaseCyclic.RefreshFeedback")
                return emu.feedback()

        class ActuatorConfigClient:
            def __init__(self, router):
                self.router = router

            def SetControlMode(self, info, deviceId=0, options=None):  # noqa: N802, N803
                emu._need(self.router.transport, "tcp", TCP_PORT, "ActuatorConfig.SetControlMode")
                emu.set_control_mode(info, deviceId)

            def GetControlMode(self, deviceId=0, options=None):  # noqa: N802, N803
                emu._need(self.router.transport, "tcp", TCP_PORT, "ActuatorConfig.GetControlMode")
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
            Session_pb2=_module("Session_pb2", {}, CreateSessionInfo=CreateSessionInfo),
            Base_pb2=_module(
                "Base_pb2",
                {"ServoingMode": SERVOING_MODES, "ArmState": ARM_STATES},
                ServoingModeInformation=ServoingModeInformation,
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
