"""Small dense linear algebra of the controllers, written out for XLA (no LAPACK calls).

Each function takes ``xp`` (``jax.numpy`` by default, or ``numpy`` for the pinocchio twin)
and works on Jacobians of a site's position, (3, n), in the arm's base frame.
"""

from __future__ import annotations

from types import ModuleType

import jax
import jax.numpy as jnp


def inverse3(a: jax.Array, xp: ModuleType = jnp) -> jax.Array:
    """Inverse of a 3x3 matrix by its adjugate (cross products of rows): no LAPACK call."""
    c0, c1, c2 = xp.cross(a[1], a[2]), xp.cross(a[2], a[0]), xp.cross(a[0], a[1])
    return xp.stack([c0, c1, c2], axis=1) / xp.dot(a[0], c0)


def damped_pinv(jac: jax.Array, damping: float, xp: ModuleType = jnp) -> jax.Array:
    """(n, 3) J^+ = J^T (J J^T + damping I)^-1, the damped pseudo-inverse of a (3, n) J
    (``damping`` in J's unit squared, e.g. m^2 for m/rad); J (J^+) = I when damping = 0 and
    J has rank 3. Its transpose is the pseudo-inverse of J^T, (J^T)^+ = (J^+)^T."""
    return jac.T @ inverse3(jac @ jac.T + damping * xp.eye(3), xp)


__all__ = ["damped_pinv", "inverse3"]
