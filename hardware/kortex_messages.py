"""The messages of the emulated kortex_api: protobuf look-alikes, enums and exceptions.

``KortexEmulator`` speaks to the Kortex adapter in these: message classes with the fields of
Kinova's ``BaseCyclic_pb2``, ``Base_pb2``, ``ActuatorConfig_pb2`` and ``Session_pb2``
messages (declared fields only, typed as protobuf types them: assigning any other field, or
assigning to a message or repeated field, raises; integers wrap to uint32, floats round to
float32), the enums (``ProtoEnum``: ``Value(name)``, ``Name(number)``) of servoing modes, arm
states, arm-level safety bits and control modes, and kortex_api's exceptions (``KException``,
``KServerException``, ``KClientException``). Units on the wire are Kortex's: positions deg,
velocities deg/s, currents A, torques N m.
"""

from __future__ import annotations

import copy
from collections.abc import ItemsView

import numpy as np


class KException(Exception):
    """kortex_api.Exceptions.KException's role: an error code and sub-code.

    Args:
        message: what went wrong.
        code: the error code. sub_code: the error sub-code.
    """

    def __init__(self, message: str, code: int = 1, sub_code: int = 0):
        super().__init__(message)
        self.code, self.sub_code = code, sub_code

    def get_error_code(self) -> int:
        """The error code.

        Returns:
            ``code``.
        """
        return self.code

    def get_error_sub_code(self) -> int:
        """The error sub-code.

        Returns:
            ``sub_code``.
        """
        return self.sub_code


class KServerException(KException):
    """Raised for a request the arm refused (kortex_api's KServerException)."""


class KClientException(KException):
    """Raised on the client side, e.g. a frame that could not be sent (kortex_api's
    KClientException; not a KServerException)."""


class ProtoEnum:
    """A protobuf enum wrapper: ``Value(name)`` and ``Name(number)``.

    Args:
        **values: each name of the enum and its number.
    """

    def __init__(self, **values: int):
        self._values = values

    def Value(self, name: str) -> int:  # noqa: N802 - protobuf's name
        """The number of a name.

        Args:
            name: a name of the enum.

        Returns:
            Its number.

        Raises:
            ValueError: the enum has no such name.
        """
        if name not in self._values:
            raise ValueError(f"enum has no value named {name!r}")
        return self._values[name]

    def Name(self, number: int) -> str:  # noqa: N802 - protobuf's name
        """The name of a number.

        Args:
            number: a number of the enum.

        Returns:
            The (first) name with that number.

        Raises:
            ValueError: no name has that number.
        """
        for k, v in self._values.items():
            if v == number:
                return k
        raise ValueError(f"enum has no value {number}")

    def items(self) -> ItemsView[str, int]:
        """The enum's values.

        Returns:
            The (name, number) pairs.
        """
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
    """A message class ``name``: each field's default (its type), a message class, or a
    1-tuple of a message class (a repeated field)."""
    return type(name, (_Message,), {"_fields": fields})


# BaseCyclic
#: One actuator's cyclic command: position deg, velocity deg/s, torque_joint N m,
#: current_motor A.
ActuatorCommand = _message(
    "ActuatorCommand",
    command_id=0,
    flags=0,
    position=0.0,
    velocity=0.0,
    torque_joint=0.0,
    current_motor=0.0,
)
#: One actuator's cyclic feedback: position deg in [0, 360), velocity deg/s, torque N m,
#: current_motor A, voltage V, temperatures deg C, fault and warning banks.
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
#: The base's cyclic feedback: arm state (Common.ArmState), voltage V, current A, fault and
#: warning banks (Base.SafetyIdentifier bits).
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
#: A cyclic command: its frame id and one ActuatorCommand per actuator.
Command = _message("Command", frame_id=0, actuators=(ActuatorCommand,))
#: A cyclic feedback: its frame id, the base's and one ActuatorFeedback per actuator.
Feedback = _message("Feedback", frame_id=0, base=BaseFeedback, actuators=(ActuatorFeedback,))
# Base, ActuatorConfig, Session
#: The base's servoing mode (Base.ServoingMode).
ServoingModeInformation = _message("ServoingModeInformation", servoing_mode=0)
#: An actuator's control mode (ActuatorConfig.ControlMode).
ControlModeInformation = _message("ControlModeInformation", control_mode=0)
#: The arm's state (Common.ArmState).
ArmStateInformation = _message("ArmStateInformation", active_state=0)
#: A session's credentials and inactivity timeouts (ms).
CreateSessionInfo = _message(
    "CreateSessionInfo",
    username="",
    password="",
    session_inactivity_timeout=0,
    connection_inactivity_timeout=0,
)

#: Base.ServoingMode.
SERVOING_MODES = ProtoEnum(
    UNSPECIFIED_SERVOING_MODE=0, SINGLE_LEVEL_SERVOING=2, LOW_LEVEL_SERVOING=3, BYPASS_SERVOING=4
)
#: Common.ArmState (the arm's state in ``Feedback.base.active_state``).
ARM_STATES = ProtoEnum(
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
SAFETY_IDENTIFIERS = ProtoEnum(
    UNSPECIFIED_BASE_SAFETY_IDENTIFIER=0, **{name: 1 << k for k, name in enumerate(_SAFETY_BITS)}
)
#: Arm-level fault bits the emulator raises itself or is asked to.
JOINT_FAULT, MAXIMUM_CURRENT, EMERGENCY_STOP_ACTIVATED = (
    SAFETY_IDENTIFIERS.Value(name)
    for name in ("JOINT_FAULT", "MAXIMUM_CURRENT", "EMERGENCY_STOP_ACTIVATED")
)
#: ActuatorConfig.ControlMode.
CONTROL_MODES = ProtoEnum(
    NONE=0, POSITION=1, VELOCITY=2, TORQUE=3, CURRENT=4, CUSTOM=5, TORQUE_HIGH_VELOCITY=6
)
