"""Forces a person or the environment puts on the end effector in simulation.

All vectors are in the world frame: forces N, torques N m, points m, times s (simulation).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError


def vec3(value, name: str) -> np.ndarray:
    """A checked 3-vector.

    Args:
        value: the vector. name: what it is, for the error message.

    Returns:
        The finite (3,) float array.

    Raises:
        InputError: not a finite vector of shape (3,).
    """
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise InputError(f"{name} must be a finite vector of shape (3,), got {value!r}")
    return arr


@dataclass(frozen=True)
class Push:
    """A constant wrench on the end effector from ``start`` for ``duration`` s.

    Attributes:
        start: s, simulation time. duration: s.
        force: (3,) N. torque: (3,) N m about the end-effector point.
    """

    start: float
    duration: float
    force: np.ndarray
    torque: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def active(self, t: float) -> bool:
        """Whether the push acts at a time.

        Args:
            t: s, simulation time.

        Returns:
            start <= t < start + duration.
        """
        return self.start <= t < self.start + self.duration


@dataclass(frozen=True)
class Rope:
    """A rope with a spring between the end effector and ``anchor`` (paper, Experiment 2).

    Slack within ``free_length`` m of the anchor; beyond it pulls the end effector back with
    ``stiffness`` N/m times the stretch.

    Attributes:
        anchor: (3,) m. free_length: m (>= 0). stiffness: N/m (>= 0).

    Raises:
        InputError: a negative or non-finite free_length or stiffness.
    """

    anchor: np.ndarray
    free_length: float
    stiffness: float

    def __post_init__(self) -> None:
        checks.number(self.free_length, "rope free_length", nonneg=True, unit="m")
        checks.number(self.stiffness, "rope stiffness", nonneg=True, unit="N/m")

    def force(self, point: np.ndarray) -> np.ndarray:
        """The rope's pull on the end effector: zero while slack.

        Args:
            point: (3,) m, the end effector's position.

        Returns:
            (3,) N.
        """
        d = point - self.anchor
        dist = float(np.linalg.norm(d))
        if dist <= self.free_length or dist == 0.0:
            return np.zeros(3)
        return -self.stiffness * (dist - self.free_length) * d / dist


class Interaction:
    """The external wrench on the end effector: a constant one, scripted pushes, a rope."""

    def __init__(self) -> None:
        self.force = np.zeros(3)
        self.torque = np.zeros(3)
        self.pushes: list[Push] = []
        self.rope: Rope | None = None
        self.rope_force = np.zeros(3)
        self._idle = True

    @property
    def idle(self) -> bool:
        """True when nothing acts on the end effector (the simulator skips the wrench)."""
        return self._idle

    def _update(self) -> None:
        self._idle = not (
            self.pushes or self.rope is not None or self.force.any() or self.torque.any()
        )

    def set_wrench(self, force=(0.0, 0.0, 0.0), torque=(0.0, 0.0, 0.0)) -> None:
        """Set the constant wrench (zero: none).

        Args:
            force: (3,) N. torque: (3,) N m about the end-effector point.

        Raises:
            InputError: not a finite (3,) vector.
        """
        self.force = vec3(force, "force")
        self.torque = vec3(torque, "torque")
        self._update()

    def add_push(self, start: float, duration: float, force, torque=(0.0, 0.0, 0.0)) -> Push:
        """Add a push (see ``Push``).

        Args:
            start: s, simulation time. duration: s (> 0).
            force: (3,) N. torque: (3,) N m about the end-effector point.

        Returns:
            The ``Push``.

        Raises:
            InputError: a non-finite start, a duration <= 0 or not finite, a bad vector.
        """
        start = checks.number(start, "push start", unit="s")
        duration = checks.number(duration, "push duration", positive=True, unit="s")
        push = Push(start, duration, vec3(force, "force"), vec3(torque, "torque"))
        self.pushes.append(push)
        self._update()
        return push

    def attach_rope(self, anchor, free_length: float, stiffness: float) -> Rope:
        """Attach a rope (see ``Rope``), replacing any.

        Args:
            anchor: (3,) m. free_length: m (>= 0). stiffness: N/m (>= 0).

        Returns:
            The ``Rope``.

        Raises:
            InputError: a bad anchor, free_length or stiffness.
        """
        self.rope = Rope(vec3(anchor, "anchor"), float(free_length), float(stiffness))
        self._update()
        return self.rope

    def detach_rope(self) -> None:
        self.rope = None
        self.rope_force = np.zeros(3)
        self._update()

    def clear(self) -> None:
        """Remove everything: constant wrench, pushes, rope."""
        self.pushes.clear()
        self.set_wrench()
        self.detach_rope()

    def wrench(self, t: float, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The total wrench on the end effector; records the rope's part in ``rope_force``.

        Args:
            t: s, simulation time. point: (3,) m, the end effector's position (for the rope).

        Returns:
            (force (3,) N, torque (3,) N m about ``point``).
        """
        force, torque = self.force.copy(), self.torque.copy()
        for p in self.pushes:
            if p.active(t):
                force += p.force
                torque += p.torque
        if self.rope is not None:
            self.rope_force = self.rope.force(point)
            force += self.rope_force
        return force, torque
