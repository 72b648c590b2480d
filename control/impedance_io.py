"""The impedance step's inputs and outputs: the packed input, the live gains and the
diagnostics.

The 1 kHz loop hands the controller one numpy vector (``packed_size``): q rad | dq rad/s |
previous command A | target pos m | vel m/s | acc m/s^2 (arm base frame) | measured current A
| live gains [| target orientation (3, 3) row-major] (``packed_slices``, ``unpack_state``).
The live gains (``live_gains``: K_d N/m, D_d N s/m, friction compensation on 1 / off 0) are an
input of the step, so that a running loop changes them without recompiling. The step answers
its command and one ``Diagnostics`` array (``pack_diagnostics``; the external force estimate
at ``estimate_slice``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# ----------------------------------------------------------------------------- packed input


#: Length of the live gains: K_d (3) N/m | D_d (3) N s/m | friction compensation factor (1).
LIVE_SIZE = 7


def live_gains(stiffness, damping, friction_compensation: bool | float = True) -> np.ndarray:
    """The live gains vector of a step. No checks: the gains come validated
    (``ImpedanceGains``, ``presets.check_live_gains``).

    Args:
        stiffness: K_d, N/m, (3,) or one number (every axis).
        damping: D_d, N s/m, (3,) or one number.
        friction_compensation: its factor, on (1.0) or off (0.0).

    Returns:
        (``LIVE_SIZE``,) K_d (3) | D_d (3) | compensation (1).
    """
    k = np.broadcast_to(np.asarray(stiffness, dtype=float), (3,))
    d = np.broadcast_to(np.asarray(damping, dtype=float), (3,))
    return np.concatenate([k, d, [float(friction_compensation)]])


def packed_size(n: int, orientation: bool = False) -> int:
    """Length of the packed input of ``packed_step``: q | dq | prev | pos | vel | acc |
    current | live [| target_rot row-major].

    Args:
        n: joints.
        orientation: with an orientation task.

    Returns:
        4 n + 16 (+ 9 with an orientation task).
    """
    return 4 * n + 9 + LIVE_SIZE + (9 if orientation else 0)


class PackedState(NamedTuple):
    """The parts of a packed input (see ``packed_size``): q rad, dq rad/s, prev (the last
    command) A, target pos m, vel m/s, acc m/s^2, measured current A, live gains
    (``live_gains``), rot (3, 3) or None."""

    q: Any
    dq: Any
    prev: Any
    pos: Any
    vel: Any
    acc: Any
    current: Any
    live: Any
    rot: Any


def packed_slices(n: int) -> dict[str, slice]:
    """Where each part of a packed input lies (``packed_size``).

    Args:
        n: joints.

    Returns:
        {part: slice}: q, dq, prev, pos, vel, acc, current, live, rot (only with an
        orientation task).
    """
    k = 3 * n
    live = k + 9 + n
    return {
        "q": slice(0, n),
        "dq": slice(n, 2 * n),
        "prev": slice(2 * n, k),
        "pos": slice(k, k + 3),
        "vel": slice(k + 3, k + 6),
        "acc": slice(k + 6, k + 9),
        "current": slice(k + 9, live),
        "live": slice(live, live + LIVE_SIZE),
        "rot": slice(live + LIVE_SIZE, live + LIVE_SIZE + 9),
    }


def unpack_state(x, n: int, orientation: bool) -> PackedState:
    """The parts of a packed input.

    Args:
        x: (``packed_size(n, orientation)``,) the packed input (numpy or JAX).
        n: joints.
        orientation: whether it carries a target orientation.

    Returns:
        The ``PackedState`` (views of ``x``; rot (3, 3) or None).
    """
    sl = packed_slices(n)
    rot = x[sl["rot"]].reshape(3, 3) if orientation else None
    return PackedState(*(x[sl[k]] for k in PackedState._fields[:-1]), rot)


# ----------------------------------------------------------------------------- diagnostics


class Diagnostics(NamedTuple):
    """What one control step saw and did, packed in one array (one output buffer per step).

    ``data`` is (..., 16 + 5 n): ee_pos (3) | error (3) | force (3) | tau (n) | current_raw (n)
    | rate_limited (n) | saturated (n) | clipped (1) | current_model (n) | external_force (3)
    | external_band (3). Read it through the properties; they work on JAX and numpy arrays
    and on batches. ``numpy()`` copies it to the host once.
    """

    data: jax.Array | np.ndarray

    @property
    def n(self) -> int:
        """Number of joints."""
        return (self.data.shape[-1] - 16) // 5

    def _part(self, start: int, size: int):
        return self.data[..., start : start + size]

    @property
    def ee_pos(self):
        """(3,) m, the site's position x in the arm's base frame."""
        return self._part(0, 3)

    @property
    def error(self):
        """(3,) m, the position error x_d - x acting in the spring (after deadband and clip)."""
        return self._part(3, 3)

    @property
    def force(self):
        """(3,) N, the Cartesian force F (PD part, plus feedforward when on)."""
        return self._part(6, 3)

    @property
    def tau(self):
        """(n,) N m, the joint torques of Eq. (5), gravity included."""
        return self._part(9, self.n)

    @property
    def current_raw(self):
        """(n,) A, Eq. (16) before the rate limit and the saturation."""
        return self._part(9 + self.n, self.n)

    @property
    def rate_limited(self):
        """(n,) bool, the current rate limit acted on the joint."""
        return self._part(9 + 2 * self.n, self.n) > 0.5

    @property
    def saturated(self):
        """(n,) bool, the joint's current was cut to the current limit."""
        return self._part(9 + 3 * self.n, self.n) > 0.5

    @property
    def clipped(self):
        """() bool, the Cartesian error was longer than error_clip and was clipped."""
        return self.data[..., 9 + 4 * self.n] > 0.5

    @property
    def current_model(self):
        """(n,) A, the current the identified model predicts with nothing pushing
        (``external_force.model_current``), to compare with the measured current."""
        return self._part(10 + 4 * self.n, self.n)

    @property
    def external_force(self):
        """(3,) N, the estimated force applied on the end effector (arm base frame)."""
        return self._part(10 + 5 * self.n, 3)

    @property
    def external_band(self):
        """(3,) N, per axis: the applied force lies within external_force +- this (static
        friction of joints at rest; zero when every joint moves faster than t)."""
        return self._part(13 + 5 * self.n, 3)

    def numpy(self) -> Diagnostics:
        """The same diagnostics as a host (numpy) array."""
        return Diagnostics(np.asarray(self.data))


def estimate_slice(n: int) -> slice:
    """Where the external force estimate lies in a ``Diagnostics.data``.

    Args:
        n: joints.

    Returns:
        The slice of current_model (n) A | external_force (3) N | external_band (3) N.
    """
    return slice(10 + 4 * n, 16 + 5 * n)


def pack_diagnostics(
    ee_pos, error, force, tau, current_raw, rate_limited, saturated, clipped, estimate
):
    """Diagnostics from its parts (JAX or numpy arrays).

    Args:
        ee_pos: (3,) m, arm base frame (as every Cartesian part).
        error: (3,) m, x_d - x after the deadband and clip.
        force: (3,) N, the Cartesian force F.
        tau: (n,) N m, the joint torques.
        current_raw: (n,) A, before the rate limit and the saturation.
        rate_limited: (n,) bool.
        saturated: (n,) bool.
        clipped: () bool.
        estimate: the ``external_force.ExternalForce`` (current_model A, force N, band N).

    Returns:
        The ``Diagnostics`` (one array, (16 + 5 n,)).
    """
    xp = jnp if isinstance(ee_pos, jax.Array) else np
    parts = [ee_pos, error, force, tau, current_raw]
    flags = [rate_limited, saturated, xp.reshape(clipped, (1,))]
    flags = [xp.asarray(f, dtype=float) for f in flags]
    return Diagnostics(xp.concatenate(parts + flags + list(estimate)))


__all__ = [
    "LIVE_SIZE",
    "Diagnostics",
    "PackedState",
    "estimate_slice",
    "live_gains",
    "pack_diagnostics",
    "packed_size",
    "packed_slices",
    "unpack_state",
]
