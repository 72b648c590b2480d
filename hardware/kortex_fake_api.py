"""The fake kortex_api: the namespace the Kortex adapter imports, answered by an emulator.

``fake_kortex_api(emulator)`` is what ``KortexArm`` takes as ``api`` in place of Kinova's
``kortex_api`` (the names of ``kortex_namespace.KORTEX_API``): the TCP and UDP transports, the
router and its send options, the session manager, ``BaseClient``, ``BaseCyclicClient``,
``ActuatorConfigClient``, the ``*_pb2`` message modules (``kortex_messages``) and the two
exceptions, with kortex_api's method names and arguments. The classes only carry each call to
the ``KortexEmulator``: a transport belongs to one emulator (connecting it marks the emulator's
channel connected), and a session manager or a client reaches the emulator through its router's
transport. What a call does (checks, latency, refusals, replies) is the emulator's.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import TYPE_CHECKING

from jaxcomp.hardware.kortex_messages import (
    ARM_STATES,
    CONTROL_MODES,
    SAFETY_IDENTIFIERS,
    SERVOING_MODES,
    ActuatorCommand,
    ActuatorFeedback,
    ArmStateInformation,
    Command,
    ControlModeInformation,
    CreateSessionInfo,
    Feedback,
    KClientException,
    KServerException,
    ProtoEnum,
    ServoingModeInformation,
)
from jaxcomp.hardware.kortex_namespace import kortex_api_namespace

if TYPE_CHECKING:
    from jaxcomp.hardware.kortex_emulator import KortexEmulator


class Transport:
    """A kortex_api transport to one emulator (``emulator``, set by ``fake_kortex_api``).

    Attributes:
        kind: "tcp" or "udp". port: the port connected to (None before ``connect``).
        is_connected: whether it is connected.
    """

    kind = ""
    emulator: KortexEmulator

    def __init__(self):
        self.port = None
        self.is_connected = False

    def connect(self, ip: str, port: int) -> None:
        """Connect to the arm.

        Args:
            ip: the arm's address. port: its port (10000 TCP, 10001 UDP).
        """
        self.ip, self.port, self.is_connected = ip, port, True
        self.emulator.connected.add(self.kind)

    def disconnect(self) -> None:
        """Disconnect from the arm."""
        self.is_connected = False
        self.emulator.connected.discard(self.kind)


class TCPTransport(Transport):
    """The configuration channel's transport (kortex_api.TCPTransport)."""

    kind = "tcp"


class UDPTransport(Transport):
    """The cyclic channel's transport (kortex_api.UDPTransport)."""

    kind = "udp"


class RouterClient:
    """A router on a transport (kortex_api.RouterClient).

    Args:
        transport: a connected ``Transport``.
        error_callback: kortex_api's callback for router errors (kept, never called).
    """

    def __init__(self, transport: Transport, error_callback=None):
        self.transport = transport
        self.error_callback = error_callback
        self.active = True

    def SetActivationStatus(self, active: bool) -> None:  # noqa: N802
        """Activate or deactivate the router.

        Args:
            active: whether the router is active.
        """
        self.active = active


class RouterClientSendOptions:
    """kortex_api's send options: these three fields and no other (``timeout_ms`` ms)."""

    __slots__ = ("andForget", "delay_ms", "timeout_ms")

    def __init__(self):
        self.andForget = False
        self.delay_ms = 0
        self.timeout_ms = 10000

    def getTimeoutInSecond(self) -> float:  # noqa: N802
        """The reply timeout.

        Returns:
            ``timeout_ms`` in s.
        """
        return self.timeout_ms / 1000


class SessionManager:
    """A session on a router (kortex_api.SessionManager).

    Args:
        router: the ``RouterClient`` of the session's channel.
    """

    def __init__(self, router: RouterClient):
        self.router = router
        self.open = False

    def CreateSession(self, info) -> None:  # noqa: N802
        """Open the session (``KortexEmulator.create_session``).

        Args:
            info: a ``CreateSessionInfo`` (credentials).
        """
        self.router.transport.emulator.create_session(self.router.transport, info)
        self.open = True

    def CloseSession(self) -> None:  # noqa: N802
        """Close the session, if open (``KortexEmulator.close_session``)."""
        if self.open:
            self.open = False
            self.router.transport.emulator.close_session()


class _Client:
    """A service client on a router; its transport's emulator answers its calls.

    Args:
        router: the ``RouterClient`` of the service's channel.

    Every call takes kortex_api's ``deviceId`` (the actuator's device id where the call is
    for one; else unused) and ``options`` (``RouterClientSendOptions``: the reply's
    ``timeout_ms``; None: kortex_api's default 10 s).
    """

    service = ""

    def __init__(self, router: RouterClient):
        self.router = router

    def _configuration(self, what: str, options) -> KortexEmulator:
        """The emulator, after the round trip of configuration call ``what`` of this service."""
        emu = self.router.transport.emulator
        emu.configuration_call(self.router.transport, f"{self.service}.{what}", options)
        return emu

    def _cyclic(self, what: str) -> KortexEmulator:
        """The emulator, once the cyclic call ``what`` of this service may go."""
        emu = self.router.transport.emulator
        emu.cyclic_call(self.router.transport, f"{self.service}.{what}")
        return emu


class BaseClient(_Client):
    """The Base service (on the TCP router): servoing mode, faults, arm state."""

    service = "Base"

    def SetServoingMode(self, info, deviceId=0, options=None) -> None:  # noqa: N802, N803
        """Switch the base's servoing mode (``KortexEmulator.set_servoing_mode``).

        Args:
            info: a ``ServoingModeInformation``.
        """
        self._configuration("SetServoingMode", options).set_servoing_mode(info)

    def GetServoingMode(self, deviceId=0, options=None):  # noqa: N802, N803
        """The base's servoing mode, a ``ServoingModeInformation``."""
        emu = self._configuration("GetServoingMode", options)
        return ServoingModeInformation(servoing_mode=emu.servoing_mode)

    def ClearFaults(self, deviceId=0, options=None) -> None:  # noqa: N802, N803
        """Clear every actuator and arm fault (``KortexEmulator.clear_faults``)."""
        self._configuration("ClearFaults", options).clear_faults()

    def GetArmState(self, deviceId=0, options=None):  # noqa: N802, N803
        """The arm's state, an ``ArmStateInformation`` (``KortexEmulator.arm_state``)."""
        emu = self._configuration("GetArmState", options)
        return ArmStateInformation(active_state=emu.arm_state)


class BaseCyclicClient(_Client):
    """The BaseCyclic service (on the UDP router): the 1 kHz exchange."""

    service = "BaseCyclic"

    def Refresh(self, command, deviceId=0, options=None):  # noqa: N802, N803
        """One cyclic exchange (``KortexEmulator.refresh``).

        Args:
            command: a ``Command``.

        Returns:
            The ``Feedback`` after the command's 1 ms.
        """
        return self._cyclic("Refresh").refresh(command, options)

    def RefreshFeedback(self, deviceId=0, options=None):  # noqa: N802, N803
        """The current ``Feedback``, without a command (``KortexEmulator.refresh_feedback``)."""
        return self._cyclic("RefreshFeedback").refresh_feedback()


class ActuatorConfigClient(_Client):
    """The ActuatorConfig service (on the TCP router): the actuators' control modes."""

    service = "ActuatorConfig"

    def SetControlMode(self, info, deviceId=0, options=None) -> None:  # noqa: N802, N803
        """Switch one actuator's control mode (``KortexEmulator.set_control_mode``).

        Args:
            info: a ``ControlModeInformation``. deviceId: the actuator's device id.
        """
        self._configuration("SetControlMode", options).set_control_mode(info, deviceId)

    def GetControlMode(self, deviceId=0, options=None):  # noqa: N802, N803
        """Actuator ``deviceId``'s control mode, a ``ControlModeInformation``
        (``KortexEmulator.control_mode_of``)."""
        emu = self._configuration("GetControlMode", options)
        return ControlModeInformation(control_mode=emu.control_mode_of(deviceId))


def _module(name: str, enums: dict[str, ProtoEnum], **members) -> SimpleNamespace:
    """A ``*_pb2`` message module: its messages, its enums by name and their values."""
    ns = SimpleNamespace(__name__=name, **members)
    for enum_name, enum in enums.items():
        setattr(ns, enum_name, enum)
        for k, v in enum.items():
            setattr(ns, k, v)
    return ns


def _bound(cls: type[Transport], emulator: KortexEmulator) -> type[Transport]:
    """The transport class ``cls`` of one emulator (a subclass whose ``emulator`` it is)."""
    return type(cls.__name__, (cls,), {"emulator": emulator})


def fake_kortex_api(emulator: KortexEmulator) -> SimpleNamespace:
    """The kortex_api namespace of an emulated arm.

    Args:
        emulator: the ``KortexEmulator`` that answers every call.

    Returns:
        The namespace ``KortexArm`` takes as ``api`` (``kortex_namespace.kortex_api_namespace``).
    """
    base = _module(
        "Base_pb2",
        {"ServoingMode": SERVOING_MODES, "SafetyIdentifier": SAFETY_IDENTIFIERS},
        ServoingModeInformation=ServoingModeInformation,
        ArmStateInformation=ArmStateInformation,
    )
    cyclic = _module(
        "BaseCyclic_pb2",
        {},
        Command=Command,
        Feedback=Feedback,
        ActuatorCommand=ActuatorCommand,
        ActuatorFeedback=ActuatorFeedback,
    )
    config = _module(
        "ActuatorConfig_pb2",
        {"ControlMode": CONTROL_MODES},
        ControlModeInformation=ControlModeInformation,
    )
    return kortex_api_namespace(
        {
            "TCPTransport": _bound(TCPTransport, emulator),
            "UDPTransport": _bound(UDPTransport, emulator),
            "RouterClient": RouterClient,
            "RouterClientSendOptions": RouterClientSendOptions,
            "SessionManager": SessionManager,
            "BaseClient": BaseClient,
            "BaseCyclicClient": BaseCyclicClient,
            "ActuatorConfigClient": ActuatorConfigClient,
            "KServerException": KServerException,
            "KClientException": KClientException,
            "Session_pb2": _module("Session_pb2", {}, CreateSessionInfo=CreateSessionInfo),
            "Common_pb2": _module("Common_pb2", {"ArmState": ARM_STATES}),
            "Base_pb2": base,
            "BaseCyclic_pb2": cyclic,
            "ActuatorConfig_pb2": config,
        }
    )
