"""The steady-sample rule: which samples of a sweep pass enter the joint fit.

A sweep pass ramps up, cruises at a constant speed and ramps down; only its cruise enters (the
ramps add inertia, and the servo rings after the first one). A sample is steady when

- its swept joint moves along the pass within (1 - ``STEADY_FRACTION``) of the pass's speed,
  either side (``at_speed``), and
- it lies more than ``settle_time`` s after the first such sample of its pass and more than
  ``STEADY_TRIM`` s before the last (``in_window``).

One rule for the three reductions that pick steady samples. A recording's angle bins
(``identify.bins.steady``) and the packed JAX reduction (``identify.sweep_reduction``) take the
pass's speed from the measured one (a median, then a mean) and its window from the samples at
that speed; the sums streamed from a plan (``identify.streaming``) take the pass's commanded
cruise (within ``CRUISE_TOLERANCE``) for both. The functions are pure and take numpy or JAX
arrays alike (``xp``: the array library where a branch needs one).
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np

#: A sample is steady when its swept-joint speed is within (1 - STEADY_FRACTION) of its pass's
#: speed, either side (ramps, overshoot and ringing stay out).
STEADY_FRACTION = 0.98
#: Steady samples closer than this (s) to the last of their pass are left out.
STEADY_TRIM = 0.05
#: Steady samples closer than this (s) to the first of their pass are left out: after the
#: acceleration ramp the servo rings (the Gen3's base joint at 35 deg/s: the current 40 % low
#: over the first 0.1 s, 12 % high over the next, settled after about 0.3 s).
STEADY_SETTLE = 0.3
#: Passes whose cruise is shorter than this (s) cannot spare ``STEADY_SETTLE``: they leave out
#: ``STEADY_TRIM`` at the start too (short test plans; random and default plans' passes are
#: longer).
SETTLE_CRUISE = 1.5
#: Medians over a pass (its speed) take every MEDIAN_STRIDE-th sample of it.
MEDIAN_STRIDE = 16
#: Relative tolerance of a pass's cruise in the commanded speed: a plan's samples commanded
#: within it of their pass's largest speed are at the cruise (``identify.streaming``; a
#: transfer leg's cruise likewise, ``identify.transfers``).
CRUISE_TOLERANCE = 1e-6


def settle_time(
    cruise: Any, settle: float = STEADY_SETTLE, trim: float = STEADY_TRIM, xp: ModuleType = np
) -> Any:
    """The time left out at the start of a pass's cruise.

    Args:
        cruise: s, how long the cruise lasts (from its first sample at speed to its last):
            a float or an array of any shape.
        settle: s, left out when the cruise lasts ``SETTLE_CRUISE`` or more.
        trim: s, left out when it is shorter.
        xp: ``numpy`` or ``jax.numpy``, the library of ``cruise``.

    Returns:
        s, ``cruise``'s shape: ``settle`` or ``trim``.
    """
    return xp.where(cruise >= SETTLE_CRUISE, settle, trim)


def at_speed(speed: Any, ref: Any, fraction: float = STEADY_FRACTION) -> Any:
    """Whether samples move at the speed of their pass.

    Args:
        speed: rad/s, the swept joint's speed along the pass, any shape (numpy or JAX).
        ref: rad/s, the pass's speed, broadcastable to ``speed``.
        fraction: a sample is at speed within (1 - ``fraction``) of ``ref``, either side.

    Returns:
        bool, the broadcast shape of ``speed`` and ``ref``.
    """
    return abs(speed - ref) <= (1.0 - fraction) * ref


def in_window(
    t: Any,
    first: Any,
    last: Any,
    settle: float = STEADY_SETTLE,
    trim: float = STEADY_TRIM,
    xp: ModuleType = np,
) -> Any:
    """Whether samples lie in the steady window of their pass's cruise: more than
    ``settle_time(last - first)`` after its first sample at speed, more than ``trim`` before
    its last.

    Args:
        t: s, the samples' times, any shape (numpy or JAX).
        first: s, the time of the pass's first sample at speed, broadcastable to ``t``.
        last: s, the time of its last sample at speed, broadcastable to ``t``.
        settle: s, left out at the start of a cruise of ``SETTLE_CRUISE`` or more.
        trim: s, left out at its end (and at the start of a shorter one).
        xp: ``numpy`` or ``jax.numpy``, the library of the arrays.

    Returns:
        bool, the broadcast shape of ``t``, ``first`` and ``last``.
    """
    start = settle_time(last - first, settle, trim, xp)
    return (t > first + start) & (t < last - trim)
