"""The simulated position servo's tuning, shared by the CPU ``Simulator`` and the MJX worlds.

Each arm joint's PD gains follow from its effective inertia range and its largest gravity load
over the gain poses (the zero pose, then ``GAIN_POSES`` - 1 poses drawn from
``default_rng(0)`` within the limits; -pi .. pi for a continuous joint):

- kp = I_min w^2 (w: the bandwidth), raised where that leaves the joint sagging more than
  ``HOLD_SAG`` under its largest gravity load G (kp >= G / HOLD_SAG, as a real arm's servo
  holds its load: a roll joint carrying a bent wrist has a tiny I_min but a large G), but never
  above I_min (``STIFF_LIMIT`` w)^2, where the explicitly integrated stiffness stays stable;
- kv = 2 sqrt(kp sqrt(I_min I_max)) damps the whole inertia range (MuJoCo integrates the
  damping implicitly, so over-damping is harmless).

Units: kg m^2, N m, rad, rad/s, N m/rad, N m s/rad.
"""

from __future__ import annotations

import numpy as np

#: Poses the gains are sized over.
GAIN_POSES = 64
#: rad: the sag under the largest gravity load that raises kp above I_min w^2.
HOLD_SAG = 0.02
#: kp <= I_min (STIFF_LIMIT w)^2: explicit stiffness at w dt = 1 for w = 500 rad/s, 1 ms.
STIFF_LIMIT = 2.0


def gain_poses(limits: np.ndarray) -> np.ndarray:
    """The poses the gains are sized over.

    Args:
        limits: (n, 2) rad, the joint ranges; a joint with an infinite bound draws in -pi .. pi.

    Returns:
        (GAIN_POSES, n) rad: the zero pose, then poses from ``default_rng(0)`` uniform within
        ``limits``.
    """
    finite = np.isfinite(limits).all(axis=1)
    lo = np.where(finite, limits[:, 0], -np.pi)
    hi = np.where(finite, limits[:, 1], np.pi)
    rng = np.random.default_rng(0)
    n = len(limits)
    return np.stack([np.zeros(n)] + [rng.uniform(lo, hi) for _ in range(GAIN_POSES - 1)])


def pd_gains(
    i_min: np.ndarray, i_max: np.ndarray, load: np.ndarray, bandwidth: float
) -> tuple[np.ndarray, np.ndarray]:
    """The position servo's PD gains (see the module docstring).

    Args:
        i_min: (..., n) kg m^2, each joint's smallest effective inertia.
        i_max: (..., n) kg m^2, its largest.
        load: (..., n) N m, its largest gravity load (sign ignored).
        bandwidth: rad/s, w.

    Returns:
        (kp N m/rad, kv N m s/rad), (..., n) each.
    """
    i_min, i_max = np.asarray(i_min, float), np.asarray(i_max, float)
    base = i_min * bandwidth**2
    hold = np.minimum(np.abs(load) / HOLD_SAG, i_min * (STIFF_LIMIT * bandwidth) ** 2)
    kp = np.maximum(base, hold)
    return kp, 2.0 * np.sqrt(kp * np.sqrt(i_min * i_max))
