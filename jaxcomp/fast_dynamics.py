"""One-pass kinematics and dynamics of one pose, shaped for the latency of one XLA:CPU call.

``kinematics_and_dynamics`` returns g(q), the site Jacobian, the site pose and M(q) from one
forward kinematics (same values as ``jaxcomp.dynamics``; jit-, vmap- and grad-able). A call of
a few thousand flops costs XLA:CPU little compute but a fixed amount per kernel, per constant
array and per buffer it allocates, so the computation is cut into a few stages:

1. world rotations (3, 3, nv) and positions (3, nv) of the joint frames, one lane per joint, by
   pointer jumping (ceil(log2 depth) rounds, lane gathers by slicing);
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

import weakref
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import components as cp
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams

_STANDARD_GRAVITY = np.array([0.0, 0.0, -9.81])


class KinematicsDynamics(NamedTuple):
    """Kinematic and dynamic terms of one pose and one site, world (base) frame."""

    gravity: jax.Array  # (nv,) N m (N for slides): g(q), torque holding the arm still
    jacobian: jax.Array  # (6, nv) site Jacobian, rows vx vy vz (m/s) wx wy wz (rad/s)
    position: jax.Array  # (3,) m, site position
    rotation: jax.Array  # (3, 3) site orientation: columns are the site axes
    mass_matrix: jax.Array  # (nv, nv) kg m^2 (kg for slides), M(q), armature included


class _Plan:
    """Constant structure of a tree: one lane per joint, links attached to lanes."""

    def __init__(self, tree: KinematicTree):
        nb, nv = tree.nb, tree.nv
        frame_of: list = [None] * nb  # per link: (lane or -1 = world, 4x4 offset from it)
        self.parent = np.full(nv, -1)  # parent lane of each lane
        self.pre = pre = np.zeros((nv, 4, 4))  # parent lane frame -> joint frame (q = ref)
        for b in range(nb):
            offset = np.eye(4)
            offset[:3, :3], offset[:3, 3] = tree.rot[b], tree.pos[b]
            p = tree.parent[b]
            lane, frame = (-1, offset) if p < 0 else (frame_of[p][0], frame_of[p][1] @ offset)
            for j in tree.body_joints[b]:
                self.parent[j], pre[j] = lane, frame
                lane, frame = j, np.eye(4)
            frame_of[b] = (lane, frame)
        self.frame_of = frame_of
        # lane transform R = A0 + sin(d) A1 + (1 - cos d) A2, t = B0 + ... + d B3
        self.rot_coef = np.zeros((3, 3, 3, nv))
        self.pos_coef = np.zeros((4, 3, nv))
        for j in range(nv):
            rot, pos = pre[j][:3, :3], pre[j][:3, 3]
            self.rot_coef[0, ..., j], self.pos_coef[0, :, j] = rot, pos
            axis, anchor = tree.joint_axis[j], tree.joint_pos[j]
            if tree.is_hinge[j]:
                k1 = np.array(
                    [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]
                )
                for n, k in ((1, k1), (2, k1 @ k1)):
                    self.rot_coef[n, ..., j] = rot @ k
                    self.pos_coef[n, :, j] = -rot @ k @ anchor
            else:
                self.pos_coef[3, :, j] = rot @ axis
        self.moving = [b for b in range(nb) if frame_of[b][0] >= 0]  # links some joint moves
        self.carried: list = [[] for _ in range(nv)]  # links carried by each joint frame
        for b in self.moving:
            self.carried[frame_of[b][0]].append(b)
        self.subtree = np.eye(nv, dtype=bool)  # subtree[j, l]: lane l moves with joint j
        depth = np.ones(nv, dtype=int)
        for lane in range(nv):
            a = self.parent[lane]
            while a >= 0:
                self.subtree[a, lane] = True
                depth[lane] += 1
                a = self.parent[a]
        self.depth = int(depth.max())
        self.related = tree.moves[:, tree.joint_body]  # joint j moves the link of joint k

    def ancestors(self, k: int) -> np.ndarray:
        """Lane k steps up from each lane (-1: none)."""
        out = np.arange(len(self.parent))
        for _ in range(k):
            out = np.where(out >= 0, self.parent[np.maximum(out, 0)], -1)
        return out


_PLANS: "weakref.WeakKeyDictionary[KinematicTree, _Plan]" = weakref.WeakKeyDictionary()


def _plan(tree: KinematicTree) -> _Plan:
    if tree not in _PLANS:
        _PLANS[tree] = _Plan(tree)
    return _PLANS[tree]


def _gather(x: jax.Array, idx, fill: jax.Array) -> jax.Array:
    """x[..., idx] by concatenating slices (idx -1 -> ``fill`` of shape (..., 1))."""
    parts = [x[..., int(i) : int(i) + 1] if i >= 0 else fill for i in idx]
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=-1)


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


def _lane_frames(tree: KinematicTree, plan: _Plan, q: jax.Array):
    """World rotation (3, 3, nv) and position (3, nv) m of every joint frame."""
    d = q - tree.joint_ref
    rot = jnp.asarray(plan.rot_coef[0])
    pos = jnp.asarray(plan.pos_coef[0])
    if tree.is_hinge.any():
        s, c = jnp.sin(d), 1.0 - jnp.cos(d)
        rot = rot + s * plan.rot_coef[1] + c * plan.rot_coef[2]
        if plan.pos_coef[1:3].any():
            pos = pos + s * plan.pos_coef[1] + c * plan.pos_coef[2]
    if plan.pos_coef[3].any():
        pos = pos + d * plan.pos_coef[3]
    eye, zero = jnp.eye(3)[:, :, None], jnp.zeros((3, 1))
    span = 1
    while span < plan.depth:
        up = plan.ancestors(span)
        rot_up = _gather(rot, up, eye)
        rot, pos = _rot_mul(rot_up, rot), _rot_vec(rot_up, pos) + _gather(pos, up, zero)
        span *= 2
    return rot, pos


def _joint_axes(tree: KinematicTree, rot: jax.Array, pos: jax.Array):
    """World joint axes (3, nv) and anchors (3, nv) m."""
    axes, anchors = tree.joint_axis, tree.joint_pos
    if np.all(axes == axes[0]):  # one axis for all joints (e.g. every joint about its z)
        a = sum(float(axes[0, k]) * rot[:, k, :] for k in range(3) if axes[0, k] != 0.0)
    else:
        a = _rot_vec(rot, axes.T)
    p = pos if not anchors.any() else pos + _rot_vec(rot, anchors.T)
    return a, p


_BLOCK, _ROW = 64, 8  # entries per buffer, per row (XLA fuses concatenations of <= 8)
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _entry(array, index):
    """One entry of a parameter array: a Python float for numpy constants (folded)."""
    if isinstance(array, np.ndarray):
        return float(array[index])
    return array[index]


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


def _link_inertias(tree, plan, rot, pos, params, one, like) -> list:
    """Per joint frame: first moment m c (3) kg m and inertia about the world origin (6: xx yy
    zz xy xz yz) kg m^2 of the links it carries, world frame."""
    values = []
    for lane in range(tree.nv):
        r = [[rot[i, k, lane] for k in range(3)] for i in range(3)]
        t = [pos[i, lane] for i in range(3)]
        moment, inertia = [0.0] * 3, [0.0] * 6
        for b in plan.carried[lane]:
            offset = plan.frame_of[b][1]
            mass = _entry(params.mass, (b,))
            com = [_entry(params.com, (b, k)) for k in range(3)]
            local = [[_entry(params.inertia, (b, i, k)) for k in range(3)] for i in range(3)]
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


def _momenta(tree, plan, axes, anchors, links, params, one, like):
    """Per joint (columns), for a unit joint rate: spatial velocity v (m), w (3, nv) at the world
    origin, and linear L (kg m) and angular N (kg m^2) momentum (3, nv) of the subtree it
    moves."""
    nv = tree.nv
    cols = {"v": [], "w": [], "lin": [], "ang": []}
    for k in range(nv):
        a = [axes[i, k] for i in range(3)]
        anchor = [anchors[i, k] for i in range(3)]
        lanes = np.flatnonzero(plan.subtree[k])
        mass = cp.total(_entry(params.mass, (b,)) for lane in lanes for b in plan.carried[lane])
        h = [cp.total(links[9 * lane + i] for lane in lanes) for i in range(3)]
        e = [cp.total(links[9 * lane + 3 + i] for lane in lanes) for i in range(6)]
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

    q (nv,) rad or m; ``gravity_vector`` (3,) m/s^2 in the world frame, default (0, 0, -9.81);
    ``params`` default: the model's. Same values as ``dynamics.gravity``, ``site_jacobian``,
    ``site_pose`` and ``mass_matrix``.
    """
    p = tree.nominal if params is None else params
    gvec = _STANDARD_GRAVITY if gravity_vector is None else jnp.asarray(gravity_vector, float)
    plan = _plan(tree)
    nv = tree.nv
    like = q[0]
    one = 1.0 + 0.0 * q[0]  # a runtime 1: see the module docstring
    rot, pos = _lane_frames(tree, plan, q)
    axes, anchors = _joint_axes(tree, rot, pos)
    links = _link_inertias(tree, plan, rot, pos, p, one, like)
    v, w, lin, ang = _momenta(tree, plan, axes, anchors, links, p, one, like)
    if not tree.is_hinge.all():
        w = w * tree.is_hinge

    g = -(lin[0] * gvec[0] + lin[1] * gvec[1] + lin[2] * gvec[2])
    prod = sum(v[k][:, None] * lin[k][None, :] + w[k][:, None] * ang[k][None, :] for k in range(3))
    row = jax.lax.broadcasted_iota(jnp.int32, (nv, nv), 0)
    col = jax.lax.broadcasted_iota(jnp.int32, (nv, nv), 1)
    if plan.related.all():
        mass_matrix = jnp.where(row <= col, prod, prod.T)
    else:
        upper = plan.related & np.triu(np.ones((nv, nv), bool))
        mass_matrix = jnp.where(upper, prod, jnp.where(upper.T, prod.T, 0.0))
    if tree.armature.any():
        mass_matrix = mass_matrix + np.diag(tree.armature)

    body = int(tree.site_body[site])
    lane, offset = plan.frame_of[body] if body >= 0 else (-1, np.eye(4))
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
        if not plan.subtree[:, lane].all():
            jac = jac * plan.subtree[:, lane]
    return KinematicsDynamics(
        gravity=g, jacobian=jac, position=x, rotation=site_rot, mass_matrix=mass_matrix
    )
