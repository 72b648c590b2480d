"""A controller adapted to the 1 kHz loop: its mode, its packed input filled in place, its
command and end-effector position.

The controller runs as its ``packed_step`` on one preallocated numpy vector (q | dq |
previous command | target pos | vel | acc | measured current | live gains [| rot], see
``impedance_io.packed_slices``) that the loop fills in place: one host-to-device and one
device-to-host copy per cycle. An impedance controller also estimates the external force
(``LawAdapter.estimate``: its diagnostics' current_model, external force and band). Frames: the
arm's base frame; units A (rad/s for the velocity controller), m, N.
"""

from __future__ import annotations

import numpy as np

from jaxcomp.control.impedance import ImpedanceController
from jaxcomp.control.impedance_io import estimate_slice, packed_slices
from jaxcomp.control.velocity import VelocityController
from jaxcomp.errors import InputError
from jaxcomp.hardware.interface import Arm, ArmCommand, ArmState, ControlMode


class LawAdapter:
    """Adapter of a controller to the loop: mode, command, end-effector position (arm frame).

    Args:
        controller: an ``ImpedanceController`` (CURRENT mode) or a ``VelocityController``
            (VELOCITY mode), with as many joints as ``arm``.
        arm: the arm it drives (its current or velocity limits).

    Attributes:
        mode: the arm's ``ControlMode`` for this controller.
        limit: (n,) A or rad/s, the arm's command limits; saturation: (n,) A, the controller's
            current clip (None for the velocity controller); unit: "A" or "rad/s".
        target: (9,) view of the packed input: target pos m | vel m/s | acc m/s^2, arm frame.
        live: (7,) view of the packed input: K_d N/m | D_d N s/m | friction compensation.
        estimates: whether ``run`` estimates the external force (an impedance controller).
        estimate: after ``run``: current_model (n,) A | external force (3,) N | band (3,) N,
            arm frame.

    Raises:
        InputError: another kind of controller, or another number of joints than the arm's.
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
        self.estimates = self._current
        if self.estimates:
            self.live[:] = controller.live
        part = estimate_slice(n)  # current_model | F | band, after the command (n)
        self._estimate = slice(n + part.start, n + part.stop)
        self.estimate = np.zeros(n + 6)

    def start(self, state: ArmState) -> None:
        """Reset the command memory to what the arm applies when it switches (measured
        current, clipped to the limits; zero velocity).

        Args:
            state: the arm's state at the switch.
        """
        if self._current:
            np.clip(state.current, -self.limit, self.limit, out=self._prev)
        else:
            self._prev[:] = 0.0

    @property
    def orientation(self) -> bool:
        """Whether the controller holds an orientation (needs ``set_rot``)."""
        gains = getattr(self.controller, "gains", None)
        return bool(getattr(gains, "orientation", False))

    def set_rot(self, rot: np.ndarray) -> None:
        """Set the target orientation (orientation gains only).

        Args:
            rot: (3, 3) rotation, arm frame.
        """
        self.x[self._rot] = rot.ravel()

    def run(self, q, dq, current) -> tuple[np.ndarray, np.ndarray]:
        """One step for the target already in ``target`` (and ``set_rot``).

        Args:
            q: Joint angles, (n,) rad.
            dq: Joint velocities, (n,) rad/s.
            current: (n,) A, the measured motor currents.

        Returns:
            (command (n,) A or rad/s, end-effector position (3,) m, arm frame): read-only
            views of one output. An impedance controller's estimate is then in ``estimate``
            (a view as well).
        """
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
        """The arm command of a step's ``value``.

        Args:
            value: (n,) A (CURRENT mode) or rad/s (VELOCITY mode).

        Returns:
            The ``ArmCommand`` for ``Arm.cycle``.
        """
        if self._current:
            return ArmCommand(current=value)
        return ArmCommand(velocity=value)


__all__ = ["LawAdapter"]
