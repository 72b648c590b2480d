"""Plans of the MJX simulator: the 1 kHz joint-position reference that ``Arm.move_to`` sends.

A plan is a list of moves (``Move``: target pose, speed, acceleration, settling time);
``reference_trajectory`` turns it into the position targets ``q_ref`` (T, n) rad, one row per
control period, sample by sample what successive ``Arm.move_to`` calls command
(``hardware.move_profile.move_path``). Units: rad, rad/s, rad/s^2, s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError
from jaxcomp.hardware.move_profile import move_path


class Move(NamedTuple):
    """One ``Arm.move_to``.

    Attributes:
        pose: (n,) rad (None: stay). speed: rad/s of the joint with the longest way.
        accel: rad/s^2 (None: speed / 0.1 s). settle: s held at the end.
    """

    pose: Sequence[float] | np.ndarray | None
    speed: float
    accel: float | None = None
    settle: float = 0.0


def reference_trajectory(
    moves: Sequence[Move | tuple],
    start: Sequence[float],
    *,
    limits: np.ndarray | None = None,
    max_speed: float | None = None,
) -> np.ndarray:
    """The 1 kHz position targets that ``Arm.move_to`` sends for ``moves``.

    Sample by sample what successive ``arm.move_to(pose, speed, accel=, settle=)`` calls
    command: ``hardware.move_profile.move_path`` (the path ``move_to`` follows), each move
    starting from the previous move's last target.

    Args:
        moves: the ``Move``s (or tuples of their fields).
        start: (n,) rad, the arm's current target (after a fresh ``Simulator``, its measured
            settled pose ``arm.read().q``).
        limits: (n, 2) rad, checked as ``move_to`` does, if given.
        max_speed: rad/s, checked as ``move_to`` does, if given.

    Returns:
        (T, n) rad, one row per 1 ms control period.

    Raises:
        InputError: a bad start or limits, or a move's pose, speed, accel or settle.
    """
    pos = checks.array(start, "start", unit="rad")
    n = pos.shape[0]
    if limits is not None:
        limits = np.asarray(limits, dtype=float)
        if limits.shape != (n, 2):
            raise InputError(f"limits must have shape ({n}, 2), got {limits.shape}")
    parts: list[np.ndarray] = []
    for i, mv in enumerate(moves):
        mv = mv if isinstance(mv, Move) else Move(*mv)
        target = pos if mv.pose is None else np.asarray(mv.pose, dtype=float)
        if target.shape != (n,) or not np.isfinite(target).all():
            raise InputError(f"move {i}: pose must be a finite ({n},) array of rad or None")
        if limits is not None and ((target < limits[:, 0]) | (target > limits[:, 1])).any():
            j = int(np.flatnonzero((target < limits[:, 0]) | (target > limits[:, 1]))[0])
            raise InputError(
                f"move {i}: pose {target[j]:.4g} rad of joint {j} is beyond its limits "
                f"[{limits[j, 0]:.4g}, {limits[j, 1]:.4g}] rad"
            )
        speed = float(mv.speed)
        top = math.inf if max_speed is None else float(max_speed)
        if not (math.isfinite(speed) and 0 < speed <= top):
            raise InputError(f"move {i}: speed must be in (0, {top:.3g}] rad/s, got {speed}")
        accel = speed / 0.1 if mv.accel is None else mv.accel
        accel = checks.number(accel, f"move {i}: accel", positive=True, unit="rad/s^2")
        settle = checks.number(mv.settle, f"move {i}: settle", nonneg=True, unit="s")
        path = move_path(pos, target, speed, accel, settle)
        if len(path):
            parts.append(path)
            pos = path[-1].copy()
    return np.concatenate(parts) if parts else np.zeros((0, n))
