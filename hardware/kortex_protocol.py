"""The Gen3 Lite's low-level servoing rules, as the emulator enforces them (pure functions).

What the arm checks of each cyclic command (``command_refusal``: one command per actuator,
``frame_id`` advancing mod 65536, every actuator's ``command_id`` equal to it and its servoing
flag set), the hold-frame rule of a mode switch in low-level servoing (``starts_where_seen``:
the last cyclic command before the switch starts the new mode where the host last saw the
actuator), the actuators' part of a feedback (``fill_actuator_feedback``), the emulator's
actuator fault bits and ``SwitchRecord``, the log of a switch. Units on the wire are Kortex's:
positions deg in [0, 360), velocities deg/s, currents A, torques N m.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from jaxcomp.hardware.kortex_messages import CONTROL_MODES

#: Fault bits of the emulator (fault_bank_a); the adapter reports any non-zero bank.
FOLLOWING_ERROR = 1 << 4
ARM_FAULT = 1 << 7  # a fault the simulated actuator raised (limit, torque, speed)
MAX_TORQUE = 1 << 9
OVERSPEED = 1 << 11
INJECTED = 1 << 15
#: A, the motor current beyond which a CURRENT-mode command faults (MAX_TORQUE).
MAX_CURRENT = 11.0


def wrap_deg(x: np.ndarray) -> np.ndarray:
    """Angles wrapped into [0, 360) deg.

    Args:
        x: angles, deg.

    Returns:
        The same angles in [0, 360) deg.
    """
    return np.mod(x, 360.0)


def diff_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The difference of two angles, wrapped.

    Args:
        a, b: angles, deg.

    Returns:
        a - b in (-180, 180] deg.
    """
    return (np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class SwitchRecord:
    """One ``SetControlMode`` the emulator applied.

    Attributes: t (s, emulated time), device (actuator id), mode (ControlMode name),
    low_level (in LOW_LEVEL_SERVOING), frames (cyclic commands received since the previous
    switch or servoing change), held (the last of them started the new mode where the host
    last saw the actuator, see ``starts_where_seen``; None outside low-level servoing).
    """

    t: float
    device: int
    mode: str
    low_level: bool
    frames: int
    held: bool | None


def command_refusal(command, last_frame_id: int | None, device_ids: Sequence[int]) -> str | None:
    """Why the arm rejects a cyclic command, if it does.

    Args:
        command: a ``Command``.
        last_frame_id: the frame id of the last command accepted (None: none since the
            switch to LOW_LEVEL_SERVOING).
        device_ids: the actuators' device ids, in order.

    Returns:
        The refusal's message, or None for a command the arm takes.
    """
    fid = command.frame_id
    if len(command.actuators) != len(device_ids):
        return f"command for {len(command.actuators)} actuators, the arm has {len(device_ids)}"
    if last_frame_id is not None and not 0 < (fid - last_frame_id) % 65536 < 32768:
        return f"frame_id {fid} did not advance past {last_frame_id}"
    for i, a in enumerate(command.actuators):
        if a.command_id & 0xFFFF != fid:
            return (
                f"actuator {device_ids[i]}: command_id {a.command_id} does not match frame_id {fid}"
            )
        if not a.flags & 1:
            return f"actuator {device_ids[i]}: servoing flag (flags=1) not set"
    return None


def starts_where_seen(
    mode: int,
    current_mode: int,
    command: tuple[np.ndarray, np.ndarray, np.ndarray],
    i: int,
    seen,
) -> bool:
    """Whether the last cyclic command starts actuator ``i`` in ``mode`` where the host last
    saw it: CURRENT at the measured current, VELOCITY at 0, POSITION (from another mode) at
    the measured position (POSITION already: the command holds its target).

    Args:
        mode: the new mode (ActuatorConfig.ControlMode number).
        current_mode: the actuator's mode before the switch.
        command: the last command's (position deg, velocity deg/s, current A), (6,) each.
        i: the actuator's index.
        seen: the ``ActuatorFeedback`` of actuator ``i`` the host had received when it sent
            that command.

    Returns:
        True when the command is a hold frame for the switch.
    """
    position, velocity, current = command
    if mode == CONTROL_MODES.Value("CURRENT"):
        return bool(current[i] == seen.current_motor)
    if mode == CONTROL_MODES.Value("VELOCITY"):
        return bool(velocity[i] == 0.0)
    if current_mode == mode:
        return True
    return bool(position[i] == seen.position)


def fill_actuator_feedback(
    fb,
    device_ids: Sequence[int],
    q: np.ndarray,
    dq: np.ndarray,
    current: np.ndarray,
    torque: np.ndarray,
    faults: dict[int, int],
    jitter: int,
    command=None,
) -> None:
    """Add each actuator's ``ActuatorFeedback`` to a ``Feedback``.

    Args:
        fb: the ``Feedback`` (its actuators empty).
        device_ids: the actuators' device ids, in order.
        q: (6,) positions, deg in [0, 360). dq: (6,) velocities, deg/s.
        current: (6,) motor currents, A. torque: (6,) joint torques, N m.
        faults: each device id's fault bank A.
        jitter: us, each actuator's ``jitter_comm``.
        command: the ``Command`` answered (its ``command_id`` echoed), or None.
    """
    for i, d in enumerate(device_ids):
        a = fb.actuators.add()
        a.position = q[i]
        a.velocity = dq[i]
        a.current_motor = current[i]
        a.torque = torque[i]
        a.voltage = 24.0
        a.temperature_motor = a.temperature_core = 35.0
        a.fault_bank_a = faults[d]
        a.jitter_comm = jitter
        if command is not None:
            a.command_id = command.actuators[i].command_id
