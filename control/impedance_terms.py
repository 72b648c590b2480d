"""The terms of the impedance law (``control.impedance``) that are more than one line: the
Coriolis product of the feedforward, the orientation error, the deadband and clip of the
position error, and the rate limit and saturation of the current.

``clip_error``, ``limit_current`` and ``orientation_error`` take ``xp`` (``jax.numpy`` by
default, or ``numpy`` for the pinocchio twin). Frames: the arm's base frame; m, rad, A.
"""

from __future__ import annotations

from types import ModuleType

import jax
import jax.numpy as jnp

from jaxcomp import dynamics
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams


def coriolis_times(
    tree: KinematicTree, q: jax.Array, dq: jax.Array, w: jax.Array, params: InertialParams
) -> jax.Array:
    """C(q, dq) w for the Christoffel Coriolis matrix C (``dynamics.coriolis_matrix``):
    0.5 (M_dot(dq) w + M_dot(w) dq - d/dq (w^T M dq)), two JVPs and one gradient of M instead
    of its full Jacobian (faster to compile and run).

    Args:
        tree: the arm's kinematic tree.
        q: Joint angles, (n,) rad.
        dq: Joint velocities, (n,) rad/s.
        w: (n,) rad/s, the velocity C multiplies.
        params: the inertials (kg, m, kg m^2; link frames).

    Returns:
        (n,) N m.
    """

    def mass(qq):
        return dynamics.mass_matrix(tree, qq, params)

    m_dot_dq = jax.jvp(mass, (q,), (dq,))[1]
    m_dot_w = jax.jvp(mass, (q,), (w,))[1]
    grad = jax.grad(lambda qq: w @ mass(qq) @ dq)(q)
    return 0.5 * (m_dot_dq @ w + m_dot_w @ dq - grad)


def orientation_error(rot: jax.Array, target_rot: jax.Array, xp: ModuleType = jnp) -> jax.Array:
    """The rotation vector taking ``rot`` to ``target_rot``, small-angle form:
    0.5 sum_i rot[:, i] x target_rot[:, i] = sin(angle) axis for a rotation about one axis.

    Args:
        rot: (3, 3) the site's orientation, arm base frame.
        target_rot: (3, 3) the target's, arm base frame.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        (3,) rad, arm base frame.
    """
    return 0.5 * xp.sum(xp.cross(rot.T, target_rot.T), axis=0)


def clip_error(err, deadband: float, clip: float, xp: ModuleType = jnp):
    """The position error after the deadband and the norm clip.

    Args:
        err: (3,) m, x_d - x.
        deadband: m, below which the error is zero.
        clip: m, the longest error kept.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        (error (3,) m, clipped: () bool, the norm was cut to ``clip``).
    """
    norm = xp.sqrt(xp.sum(err * err))
    scale = xp.where(norm < deadband, 0.0, clip / xp.maximum(norm, clip))
    return err * scale, norm > clip


def limit_current(raw, prev, max_step, limit, xp: ModuleType = jnp):
    """The current after the rate limit and the saturation.

    Args:
        raw: (n,) A, the law's current.
        prev: (n,) A, the previous command.
        max_step: A, (n,) or one number: the most a command moves in one step.
        limit: (n,) A, the current limit.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        (current (n,) A, rate_limited (n,) bool, saturated (n,) bool).
    """
    stepped = xp.clip(raw, prev - max_step, prev + max_step)
    out = xp.clip(stepped, -limit, limit)
    return out, stepped != raw, out != stepped


__all__ = ["clip_error", "coriolis_times", "limit_current", "orientation_error"]
