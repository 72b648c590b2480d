"""Small dense linear algebra of the controllers, written out for XLA.

``inverse3``, ``damped_pinv`` and ``cholesky_solve_lower`` make no LAPACK call (XLA fuses
them into a few loops); ``spd_solve``, the impedance feedforward's solve, is LAPACK's Cholesky.
``inverse3`` and ``damped_pinv`` take ``xp`` (``jax.numpy`` by default, or ``numpy`` for the
pinocchio twin) and work on Jacobians of a site's position, (3, n), in the arm's base frame.
"""

from __future__ import annotations

from types import ModuleType

import jax
import jax.numpy as jnp


def inverse3(a: jax.Array, xp: ModuleType = jnp) -> jax.Array:
    """Inverse of a 3x3 matrix by its adjugate (cross products of rows): no LAPACK call.

    Args:
        a: (3, 3) invertible matrix.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        (3, 3) a^-1.
    """
    c0, c1, c2 = xp.cross(a[1], a[2]), xp.cross(a[2], a[0]), xp.cross(a[0], a[1])
    return xp.stack([c0, c1, c2], axis=1) / xp.dot(a[0], c0)


def damped_pinv(jac: jax.Array, damping: float, xp: ModuleType = jnp) -> jax.Array:
    """The damped pseudo-inverse J^+ = J^T (J J^T + damping I)^-1 of a position Jacobian.

    J (J^+) = I when damping = 0 and J has rank 3. Its transpose is the pseudo-inverse of
    J^T, (J^T)^+ = (J^+)^T.

    Args:
        jac: (3, n) J, e.g. m/rad, arm base frame.
        damping: in J's unit squared, e.g. m^2 for m/rad.
        xp: ``jax.numpy`` or ``numpy``.

    Returns:
        (n, 3) J^+.
    """
    return jac.T @ inverse3(jac @ jac.T + damping * xp.eye(3), xp)


def cholesky_solve_lower(m: jax.Array, b: jax.Array) -> jax.Array:
    """W = L^-1 B for M = L L^T.

    Then B^T M^-1 B = W^T W: one Cholesky factorisation and one forward substitution give
    J M^-1 J^T and J M^-1 tau with no inverse. Written out entry by entry (n is small and
    static), which XLA fuses into a few loops instead of LAPACK calls.

    Args:
        m: (n, n) symmetric positive definite M (e.g. the mass matrix, kg m^2).
        b: (n, k) B.

    Returns:
        (n, k) W.
    """
    n = m.shape[0]
    low = [[None] * n for _ in range(n)]
    inv_diag = [None] * n
    for j in range(n):
        d = m[j, j]
        for k in range(j):
            d = d - low[j][k] * low[j][k]
        inv_diag[j] = jax.lax.rsqrt(d)
        for i in range(j + 1, n):
            s = m[i, j]
            for k in range(j):
                s = s - low[i][k] * low[j][k]
            low[i][j] = s * inv_diag[j]
    w = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - low[i][k] * w[k]
        w[i] = s * inv_diag[i]
    return jnp.stack(w)


def spd_solve(m: jax.Array, b: jax.Array) -> jax.Array:
    """X = M^-1 B (LAPACK Cholesky; the impedance feedforward only).

    Args:
        m: (n, n) symmetric positive definite M.
        b: (n, k) B.

    Returns:
        (n, k) X.
    """
    low = jnp.linalg.cholesky(m)
    return jax.scipy.linalg.cho_solve((low, True), b)


__all__ = ["cholesky_solve_lower", "damped_pinv", "inverse3", "spd_solve"]
