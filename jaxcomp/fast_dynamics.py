"""One-pass kinematics and dynamics of one pose, shaped for the latency of one XLA:CPU call.

``kinematics_and_dynamics`` returns g(q), the site Jacobian, the site pose and M(q) from one
forward kinematics (same values as ``jaxcomp.dynamics``; jit-, vmap- and grad-able): the one
call per cycle of the impedance and velocity controllers (``KinematicsDynamics``). A call of
a few thousand flops costs XLA:CPU little compute but a fixed amount per kernel, per constant
array and per buffer it allocates, so the computation is cut into a few stages:

1. world rotations (3, 3, nv) and positions (3, nv) of the joint frames, one lane per joint
   (``lane_frames``, the forward kinematics every function of ``jaxcomp.dynamics`` shares);
2. per joint frame, the first moment m c and the inertia about the world origin of the links it
   carries, entry by entry (``jaxcomp.components``, model constants folded in Python);
3. per joint, its spatial velocity (v, w) at the world origin and the momentum (L, N) of the
   subtree it moves, entry by entry;
4. M[j, k] = v_j . L_k + w_j . N_k (j moving k's link), g = -L^T gravity, J = [v + w x x; w],
   as small array expressions.

Stages 2 and 3 are materialised as small buffers multiplied by a runtime 1 (``1 + 0 q_0``):
without it XLA's algebraic simplifier dissolves a buffer of scalars back into its expressions
and the fusion pass splits the work into one kernel per shared scalar. Arrays stay <= 64
doubles for arms of up to 7 joints, which lets XLA run the kernels in sequence on the calling
thread. Special cases (joint anchors at the frame origin, one joint axis for all joints, serial
chains, sites moved by every joint) are folded at trace time, automatically and exactly.
Default (numpy) inertial parameters are folded too; passed-in ones are read entry by entry.

World (base) frame; m, rad, kg, N m.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import components as cp
from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.kinematic_tree import KinematicTree, Lanes
from jaxcomp.params import InertialParams


class KinematicsDynamics(NamedTuple):
    """Kinematic and dynamic terms of one pose and one site, world (base) frame.

    Attributes:
        gravity: (nv,) N m (N for slides), g(q): the torque holding the arm still.
        jacobian: (6, nv) site Jacobian, world-aligned: rows vx vy vz (m/s) over wx wy wz
            (rad/s) per unit joint rate.
        position: (3,) m, the site's position.
        rotation: (3, 3) the site's orientation: columns are the site's axes.
        mass_matrix: (nv, nv) kg m^2 (kg for slides), M(q), armature included.
    """

    gravity: jax.Array
    jacobian: jax.Array
    position: jax.Array
    rotation: jax.Array
    mass_matrix: jax.Array


def _rot_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Lane-wise 3x3 products (3, 3, n) @ (3, 3, n)."""
    return sum(a[:, m : m + 1, :] * b[m : m + 1, :, :] for m in range(3))


def _rot_vec(a: jax.Array, v) -> jax.Array:
    """Lane-wise (3, 3, n) @ (3, n); zero rows of a numpy ``v`` are skipped."""
    terms = [m for m in range(3) if not isinstance(v, np.ndarray) or np.any(v[m])]
    if not terms:
        return jnp.zeros(a.shape[:1] + a.shape[2:])
    return sum(a[:, m, :] * v[m : m + 1, :] for m in terms)


def _cross(a, b) -> jax.Array:
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def lane_frames(tree: KinematicTree, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World rotation (3, 3, nv) and position (3, nv) m of every lane (joint frame) at q.

    The forward kinematics of every function in ``jaxcomp.dynamics``: each lane's transform
    from its parent (``KinematicTree.lanes``), composed root to leaves with element-wise
    products (a (3, 3) dot would be a kernel of its own).

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).

    Returns:
        (rotation (3, 3, nv): lane j's axes as columns of [:, :, j], position (3, nv) m),
        world frame.
    """
    lanes = tree.lanes
    d = q - tree.joint_ref
    rot = jnp.asarray(lanes.rot_coef[0])
    pos = jnp.asarray(lanes.pos_coef[0])
    if tree.is_hinge.any():
        s, c = jnp.sin(d), 1.0 - jnp.cos(d)
        rot = rot + s * lanes.rot_coef[1] + c * lanes.rot_coef[2]
        if lanes.pos_coef[1:3].any():
            pos = pos + s * lanes.pos_coef[1] + c * lanes.pos_coef[2]
    if lanes.pos_coef[3].any():
        pos = pos + d * lanes.pos_coef[3]
    rots, poss = [], []
    for j in range(tree.nv):
        up = lanes.parent[j]
        r, t = rot[:, :, j : j + 1], pos[:, j : j + 1]
        if up >= 0:
            r, t = _rot_mul(rots[up], r), _rot_vec(rots[up], t) + poss[up]
        rots.append(r)
        poss.append(t)
    return jnp.concatenate(rots, axis=2), jnp.concatenate(poss, axis=1)


def joint_axes(tree: KinematicTree, rot: jax.Array, pos: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World joint axes (3, nv) (unit) and anchors (3, nv) m, from ``lane_frames``.

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        rot: (3, 3, nv) the lanes' world rotations (``lane_frames``).
        pos: (3, nv) m, the lanes' world positions (``lane_frames``).

    Returns:
        (axes (3, nv) unit, anchors (3, nv) m), world frame.
    """
    axes, anchors = tree.joint_axis, tree.joint_pos
    if np.all(axes == axes[0]):  # one axis for all joints (e.g. every joint about its z)
        a = sum(float(axes[0, k]) * rot[:, k, :] for k in range(3) if axes[0, k] != 0.0)
    else:
        a = _rot_vec(rot, axes.T)
    p = pos if not anchors.any() else pos + _rot_vec(rot, anchors.T)
    return a, p


_BLOCK, _ROW = 64, 8  # entries per buffer, per row (XLA fuses concatenations of <= 8)
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _materialise(values: list, one, like) -> list:
    """Scalar components -> (rows, 8) buffers of <= 64 entries (x runtime one), read back."""
    values = [cp.to_array(v, like) for v in values]
    zero = jnp.zeros_like(like)
    out = []
    for start in range(0, len(values), _BLOCK):
        chunk = values[start : start + _BLOCK]
        rows = [chunk[i : i + _ROW] for i in range(0, len(chunk), _ROW)]
        rows[-1] = rows[-1] + [zero] * (_ROW - len(rows[-1]))
        block = jnp.stack([jnp.stack(r) for r in rows]) * one
        out += [block[i // _ROW, i % _ROW] for i in range(len(chunk))]
    return out


def _rows(rows: list, one, like) -> jax.Array:
    """Rows of scalar components -> one (len(rows), n) array (x runtime one)."""
    return jnp.stack([jnp.stack([cp.to_array(v, like) for v in r]) for r in rows]) * one


def _link_inertias(
    tree: KinematicTree, lanes: Lanes, rot, pos, params: InertialParams, one, like
) -> list:
    """Per joint frame: first moment m c (3) kg m and inertia about the world origin (6: xx yy
    zz xy xz yz) kg m^2 of the links it carries, world frame."""
    values = []
    for lane in range(tree.nv):
        r = [[rot[i, k, lane] for k in range(3)] for i in range(3)]
        t = [pos[i, lane] for i in range(3)]
        moment, inertia = [0.0] * 3, [0.0] * 6
        for b in lanes.carried[lane]:
            offset = lanes.frame_of[b][1]
            mass = cp.entry(params.mass, (b,))
            com = [cp.entry(params.com, (b, k)) for k in range(3)]
            local = [[cp.entry(params.inertia, (b, i, k)) for k in range(3)] for i in range(3)]
            link_rot = cp.mat_mat(r, cp.const_mat(offset[:3, :3]))
            link_pos = cp.vec_add(t, cp.mat_vec(r, cp.const_vec(offset[:3, 3])))
            c = cp.vec_add(link_pos, cp.mat_vec(link_rot, com))
            ri = cp.mat_mat(link_rot, local)
            cc = cp.dot(c, c)
            moment = cp.vec_add(moment, cp.scale(mass, c))
            for e, (i, k) in enumerate(_PAIRS):
                rotated = cp.total(cp.mul(ri[i][n], link_rot[k][n]) for n in range(3))
                steiner = cp.mul(mass, cp.sub(cc if i == k else 0.0, cp.mul(c[i], c[k])))
                inertia[e] = cp.add(inertia[e], cp.add(rotated, steiner))
        values += moment + inertia
    return _materialise(values, one, like)


def _momenta(
    tree: KinematicTree, lanes: Lanes, axes, anchors, links, params: InertialParams, one, like
) -> list:
    """Per joint (columns), for a unit joint rate: spatial velocity v (m), w (3, nv) at the world
    origin, and linear L (kg m) and angular N (kg m^2) momentum (3, nv) of the subtree it
    moves."""
    nv = tree.nv
    cols = {"v": [], "w": [], "lin": [], "ang": []}
    for k in range(nv):
        a = [axes[i, k] for i in range(3)]
        anchor = [anchors[i, k] for i in range(3)]
        moved = np.flatnonzero(lanes.subtree[k])
        mass = cp.total(cp.entry(params.mass, (b,)) for lane in moved for b in lanes.carried[lane])
        h = [cp.total(links[9 * lane + i] for lane in moved) for i in range(3)]
        e = [cp.total(links[9 * lane + 3 + i] for lane in moved) for i in range(6)]
        io = [[e[0], e[3], e[4]], [e[3], e[1], e[5]], [e[4], e[5], e[2]]]
        if tree.is_hinge[k]:
            v, w = cp.cross(anchor, a), a
            lin = cp.cross(a, cp.vec_sub(h, cp.scale(mass, anchor)))
            ang = cp.vec_sub(cp.mat_vec(io, a), cp.cross(h, cp.cross(a, anchor)))
        else:
            v, w = a, [0.0] * 3
            lin, ang = cp.scale(mass, a), cp.cross(h, a)
        for name, val in (("v", v), ("w", w), ("lin", lin), ("ang", ang)):
            cols[name].append(val)
    return [
        _rows([[col[i] for col in cols[name]] for i in range(3)], one, like)
        for name in ("v", "w", "lin", "ang")
    ]


def kinematics_and_dynamics(
    tree: KinematicTree,
    q: jax.Array,
    site: int,
    params: InertialParams | None = None,
    gravity_vector: jax.Array | None = None,
) -> KinematicsDynamics:
    """g(q), Jacobian, position and orientation of site ``site``, and M(q), in one pass.

    Same values as ``dynamics.gravity``, ``site_jacobian``, ``site_pose`` and ``mass_matrix``.

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).
        site: site index (into ``tree.site_names``).
        params: link masses (nb,) kg, COMs (nb, 3) m and inertias (nb, 3, 3) kg m^2 in the
            link frames; default the model's.
        gravity_vector: gravity (3,) m/s^2 in the world (base) frame; default (0, 0, -9.81).

    Returns:
        ``KinematicsDynamics``: g(q) (nv,) N m, the site's Jacobian (6, nv), position (3,) m
        and orientation (3, 3), M(q) (nv, nv) kg m^2; world frame.
    """
    p = tree.nominal if params is None else params
    gvec = STANDARD_GRAVITY if gravity_vector is None else jnp.asarray(gravity_vector, float)
    lanes = tree.lanes
    nv = tree.nv
    like = q[0]
    one = 1.0 + 0.0 * q[0]  # a runtime 1: see the module docstring
    rot, pos = lane_frames(tree, q)
    axes, anchors = joint_axes(tree, rot, pos)
    links = _link_inertias(tree, lanes, rot, pos, p, one, like)
    v, w, lin, ang = _momenta(tree, lanes, axes, anchors, links, p, one, like)
    if not tree.is_hinge.all():
        w = w * tree.is_hinge

    g = -(lin[0] * gvec[0] + lin[1] * gvec[1] + lin[2] * gvec[2])
    prod = sum(v[k][:, None] * lin[k][None, :] + w[k][:, None] * ang[k][None, :] for k in range(3))
    row = jax.lax.broadcasted_iota(jnp.int32, (nv, nv), 0)
    col = jax.lax.broadcasted_iota(jnp.int32, (nv, nv), 1)
    if lanes.related.all():
        mass_matrix = jnp.where(row <= col, prod, prod.T)
    else:
        upper = lanes.related & np.triu(np.ones((nv, nv), bool))
        mass_matrix = jnp.where(upper, prod, jnp.where(upper.T, prod.T, 0.0))
    if tree.armature.any():
        mass_matrix = mass_matrix + np.diag(tree.armature)

    body = int(tree.site_body[site])
    lane, offset = lanes.frame_of[body] if body >= 0 else (-1, np.eye(4))
    local = np.eye(4)
    local[:3, :3], local[:3, 3] = tree.site_rot[site], tree.site_pos[site]
    local = offset @ local
    if lane < 0:  # a site on a link no joint moves
        x, site_rot = jnp.asarray(local[:3, 3]), jnp.asarray(local[:3, :3])
        jac = jnp.zeros((6, nv))
    else:
        r = rot[:, :, lane]
        x = pos[:, lane] + sum(float(local[k, 3]) * r[:, k] for k in range(3) if local[k, 3])
        site_rot = sum(r[:, k : k + 1] * local[k : k + 1, :3] for k in range(3))
        jac = jnp.concatenate([v + _cross(w, jnp.broadcast_to(x[:, None], (3, nv))), w], 0)
        if not lanes.subtree[:, lane].all():
            jac = jac * lanes.subtree[:, lane]
    return KinematicsDynamics(
        gravity=g, jacobian=jac, position=x, rotation=site_rot, mass_matrix=mass_matrix
    )
