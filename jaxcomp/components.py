"""3-vectors and 3x3 matrices as nested lists of scalar arrays, with constant folding.

XLA on CPU pays per operation and vectorizes poorly over tiny (3, 3) axes. Writing rigid-body
kinematics entry by entry lets zeros and ones of the model's constant frames fold away in
Python, lets XLA fuse everything into few loops, and under ``jax.vmap`` turns every entry into a
contiguous batch vector. Entries are Python floats (constants) or JAX arrays of any batch shape;
``entry`` reads one from a parameter array (a float when the array is numpy). ``sincos`` is a
vectorisable float64 sine and cosine for batched kinematics.
"""

import jax
import jax.numpy as jnp
import numpy as np

_EPS = 1e-15


def _const(x) -> bool:
    return isinstance(x, float)


def add(a, b):
    """a + b, a constant 0 folded away.

    Args:
        a: a component (a float constant or an array).
        b: a component.

    Returns:
        The sum, a component.
    """
    if _const(a) and a == 0.0:
        return b
    if _const(b) and b == 0.0:
        return a
    return a + b


def sub(a, b):
    """a - b, a constant 0 folded away.

    Args:
        a: a component (a float constant or an array).
        b: a component.

    Returns:
        The difference, a component.
    """
    if _const(b) and b == 0.0:
        return a
    return add(a, mul(-1.0, b))


def mul(a, b):
    """a b, constant factors 0, 1 and -1 and products of constants folded away.

    Args:
        a: a component (a float constant or an array).
        b: a component.

    Returns:
        The product, a component.
    """
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
    """The sum of ``terms``, folded as ``add``.

    Args:
        terms: an iterable of components.

    Returns:
        The sum, a component (0.0 for no terms).
    """
    out = 0.0
    for t in terms:
        out = add(out, t)
    return out


def entry(array, index):
    """One entry of a parameter array: a Python float for numpy constants (folded), else the
    array's entry (traced).

    Args:
        array: a numpy array (a constant) or a JAX array.
        index: the entry's index.

    Returns:
        A float for a numpy array, else the array's entry.
    """
    if isinstance(array, np.ndarray):
        return float(array[index])
    return array[index]


def const_vec(v) -> list:
    """A constant vector as a list of floats, entries below 1e-15 in magnitude as exact zeros.

    Args:
        v: a 1-D array-like of numbers.

    Returns:
        A list of floats, one per entry.
    """
    return [0.0 if abs(x) < _EPS else float(x) for x in np.asarray(v, dtype=float)]


def const_mat(m) -> list:
    """A constant matrix as rows of ``const_vec``.

    Args:
        m: a 2-D array-like of numbers.

    Returns:
        A list of rows, each a list of floats.
    """
    return [const_vec(row) for row in np.asarray(m, dtype=float)]


def mat_mat(a, b) -> list:
    """The product a @ b.

    Args:
        a: a 3x3 matrix, a list of 3 rows of 3 components.
        b: a 3x3 matrix.

    Returns:
        a @ b, a 3x3 matrix of components.
    """
    return [[total(mul(a[i][k], b[k][j]) for k in range(3)) for j in range(3)] for i in range(3)]


def mat_vec(a, v) -> list:
    """The product a @ v.

    Args:
        a: a 3x3 matrix, a list of 3 rows of 3 components.
        v: a 3-vector, a list of 3 components.

    Returns:
        a @ v, a 3-vector of components.
    """
    return [total(mul(a[i][k], v[k]) for k in range(3)) for i in range(3)]


def vec_add(a, b) -> list:
    """a + b, entry by entry.

    Args:
        a: a vector, a list of components.
        b: a vector of the same length.

    Returns:
        The sum, a list of components.
    """
    return [add(x, y) for x, y in zip(a, b, strict=True)]


def vec_sub(a, b) -> list:
    """a - b, entry by entry.

    Args:
        a: a vector, a list of components.
        b: a vector of the same length.

    Returns:
        The difference, a list of components.
    """
    return [sub(x, y) for x, y in zip(a, b, strict=True)]


def scale(s, v) -> list:
    """s v, entry by entry.

    Args:
        s: a component (a float constant or an array).
        v: a vector, a list of components.

    Returns:
        The scaled vector, a list of components.
    """
    return [mul(s, x) for x in v]


def cross(a, b) -> list:
    """The cross product a x b.

    Args:
        a: a 3-vector, a list of 3 components.
        b: a 3-vector.

    Returns:
        a x b, a 3-vector of components.
    """
    return [
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    ]


def dot(a, b):
    """The dot product a . b.

    Args:
        a: a vector, a list of components.
        b: a vector of the same length.

    Returns:
        a . b, a component.
    """
    return total(mul(x, y) for x, y in zip(a, b, strict=True))


def to_array(x, like):
    """A component (constant or array) as an array broadcast to ``like``'s shape and dtype.

    Args:
        x: a component.
        like: an array of the batch shape and dtype wanted.

    Returns:
        An array of ``like``'s shape.
    """
    if _const(x):
        return jnp.full(jnp.shape(like), x, dtype=jnp.result_type(like))
    return jnp.broadcast_to(x, jnp.shape(like))


def pack(nested, like, shape: tuple[int, ...]):
    """One array of ``shape`` from a nested list of components, built by a single stack.

    Args:
        nested: nested lists of components, row-major (e.g. a 3x3 matrix).
        like: an array of the batch shape and dtype wanted.
        shape: the shape of one item, e.g. (3, 3).

    Returns:
        An array of ``like.shape + shape``.
    """
    flat = []

    def walk(x):
        if isinstance(x, list):
            for y in x:
                walk(y)
        else:
            flat.append(to_array(x, like))

    walk(nested)
    return jnp.stack(flat, -1).reshape(jnp.shape(like) + shape)


# fdlibm's kernel coefficients (sin and cos on [-pi/4, pi/4], < 1 ulp) and pi/2 in three parts
# of 33 bits, so that n * part is exact for |n| < 2^20 (|x| < 1.6e6 rad)
_PIO2 = (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624879595063154e-21)
_SIN = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_COS = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)


def _horner(coefs, z):
    out = coefs[-1]
    for c in coefs[-2::-1]:
        out = out * z + c
    return out


@jax.custom_jvp
def sincos(x):
    """(sin x, cos x) in float64 from one range reduction and two short polynomials.

    Within 1-2 ulp of ``jnp.sin`` / ``jnp.cos`` for |x| < 1.6e6 (rad); plain multiply-adds, so
    XLA vectorises it, unlike its float64 sine and cosine (a libm call per element).

    Args:
        x: angles, rad, any shape.

    Returns:
        (sin x, cos x), each of x's shape.
    """
    n = jnp.round(x * (2.0 / np.pi))
    r = ((x - n * _PIO2[0]) - n * _PIO2[1]) - n * _PIO2[2]
    z = r * r
    s = r + r * z * _horner(_SIN, z)
    c = 1.0 - 0.5 * z + z * z * _horner(_COS, z)
    quadrant = n - 4.0 * jnp.floor(n * 0.25)  # 0, 1, 2, 3
    odd = (quadrant == 1.0) | (quadrant == 3.0)
    sin = jnp.where(odd, c, s)
    cos = jnp.where(odd, s, c)
    sin = jnp.where(quadrant >= 2.0, -sin, sin)
    cos = jnp.where((quadrant == 1.0) | (quadrant == 2.0), -cos, cos)
    return sin, cos


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = sincos(x)
    return (s, c), (c * dx, -s * dx)
