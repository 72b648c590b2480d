"""3-vectors and 3x3 matrices as nested lists of scalar arrays, with constant folding.

XLA on CPU pays per operation and vectorizes poorly over tiny (3, 3) axes. Writing rigid-body
kinematics entry by entry lets zeros and ones of the model's constant frames fold away in
Python, lets XLA fuse everything into few loops, and under ``jax.vmap`` turns every entry into a
contiguous batch vector. Entries are Python floats (constants) or JAX arrays of any batch shape.
"""

import jax.numpy as jnp
import numpy as np

_EPS = 1e-15


def _const(x) -> bool:
    return isinstance(x, float)


def add(a, b):
    if _const(a) and a == 0.0:
        return b
    if _const(b) and b == 0.0:
        return a
    return a + b


def sub(a, b):
    if _const(b) and b == 0.0:
        return a
    return add(a, mul(-1.0, b))


def mul(a, b):
    if _const(a):
        if a == 0.0:
            return 0.0
        if a == 1.0:
            return b
        if _const(b):
            return a * b
        if a == -1.0:
            return -b
    if _const(b):
        return mul(b, a)
    return a * b


def total(terms):
    out = 0.0
    for t in terms:
        out = add(out, t)
    return out


def const_vec(v) -> list:
    return [0.0 if abs(x) < _EPS else float(x) for x in np.asarray(v, dtype=float)]


def const_mat(m) -> list:
    return [const_vec(row) for row in np.asarray(m, dtype=float)]


def mat_mat(a, b) -> list:
    return [[total(mul(a[i][k], b[k][j]) for k in range(3)) for j in range(3)] for i in range(3)]


def mat_vec(a, v) -> list:
    return [total(mul(a[i][k], v[k]) for k in range(3)) for i in range(3)]


def vec_add(a, b) -> list:
    return [add(x, y) for x, y in zip(a, b, strict=True)]


def vec_sub(a, b) -> list:
    return [sub(x, y) for x, y in zip(a, b, strict=True)]


def scale(s, v) -> list:
    return [mul(s, x) for x in v]


def cross(a, b) -> list:
    return [
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    ]


def dot(a, b):
    return total(mul(x, y) for x, y in zip(a, b, strict=True))


def to_array(x, like):
    """A component (constant or array) as an array broadcast to ``like``'s shape and dtype."""
    if _const(x):
        return jnp.full(jnp.shape(like), x, dtype=jnp.result_type(like))
    return jnp.broadcast_to(x, jnp.shape(like))


def pack(nested, like, shape: tuple[int, ...]):
    """One array of ``shape`` from a nested list of components, built by a single stack."""
    flat = []

    def walk(x):
        if isinstance(x, list):
            for y in x:
                walk(y)
        else:
            flat.append(to_array(x, like))

    walk(nested)
    return jnp.stack(flat, -1).reshape(jnp.shape(like) + shape)
