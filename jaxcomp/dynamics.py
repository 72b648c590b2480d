"""Rigid-body dynamics of a kinematic tree in JAX: pure, jit-, vmap- and grad-able.

Every function takes the constant ``KinematicTree`` first (closed over as compile-time
constants under ``jax.jit``), then joint positions ``q`` (nv,) in rad or m, and optionally
``InertialParams`` (default: the model's). Results are in the model's world frame (for a fixed
arm, its base frame). Sign conventions follow MuJoCo and pinocchio:

    M(q) ddq + C(q, dq) dq + g(q) = tau

so ``gravity`` returns g(q), the joint torque that holds the arm still against gravity.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import components as cp
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams

STANDARD_GRAVITY = (0.0, 0.0, -9.81)


class Frames(NamedTuple):
    """World poses of every body frame, and world axes and anchors of every joint."""

    rot: jax.Array  # (nb, 3, 3)
    pos: jax.Array  # (nb, 3) m
    axis: jax.Array  # (nv, 3) unit
    anchor: jax.Array  # (nv, 3) m


class OperationalSpace(NamedTuple):
    """Task-space quantities of a site's position (Eq. 2 and 5 of the paper)."""

    pos: jax.Array  # (3,) m, site position
    jac: jax.Array  # (3, nv) position Jacobian
    lam: jax.Array  # (3, 3) Cartesian inertia Lambda, kg
    mu: jax.Array  # (3, 3) Cartesian Coriolis matrix mu, kg/s
    jac_bar: jax.Array  # (nv, 3) dynamically consistent inverse M^-1 J^T Lambda
    nullspace: jax.Array  # (nv, nv) projector N = I - J^T jac_bar^T


def _skew(v: np.ndarray) -> np.ndarray:
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def _params(tree: KinematicTree, params: InertialParams | None) -> InertialParams:
    return tree.nominal if params is None else params


class _FrameComponents(NamedTuple):
    body_rot: list  # nb component matrices
    body_pos: list  # nb component vectors, m
    axis: list  # nv component vectors
    anchor: list  # nv component vectors, m


def _joint_local(tree: KinematicTree, j: int, d) -> tuple[list, list]:
    """Rotation and translation (components) that joint j applies at displacement d."""
    axis = cp.const_vec(tree.joint_axis[j])
    if not tree.is_hinge[j]:
        return cp.const_mat(np.eye(3)), cp.scale(d, axis)
    k1 = _skew(tree.joint_axis[j])
    k1c, k2c = cp.const_mat(k1), cp.const_mat(k1 @ k1)
    s, c = jnp.sin(d), 1.0 - jnp.cos(d)
    rot = [
        [
            cp.add(cp.add(float(i == k), cp.mul(k1c[i][k], s)), cp.mul(k2c[i][k], c))
            for k in range(3)
        ]
        for i in range(3)
    ]
    anchor = cp.const_vec(tree.joint_pos[j])
    return rot, cp.vec_sub(anchor, cp.mat_vec(rot, anchor))


def _frame_components(tree: KinematicTree, q: jax.Array) -> _FrameComponents:
    body_rot: list = [None] * tree.nb
    body_pos: list = [None] * tree.nb
    axis: list = [None] * tree.nv
    anchor: list = [None] * tree.nv
    for b in range(tree.nb):
        p = tree.parent[b]
        fixed_rot, fixed_pos = cp.const_mat(tree.rot[b]), cp.const_vec(tree.pos[b])
        if p < 0:
            rot, pos = fixed_rot, fixed_pos
        else:
            rot = cp.mat_mat(body_rot[p], fixed_rot)
            pos = cp.vec_add(body_pos[p], cp.mat_vec(body_rot[p], fixed_pos))
        for j in tree.body_joints[b]:
            jrot, jpos = _joint_local(tree, j, q[j] - tree.joint_ref[j])
            pos = cp.vec_add(pos, cp.mat_vec(rot, jpos))
            rot = cp.mat_mat(rot, jrot)
            axis[j] = cp.mat_vec(rot, cp.const_vec(tree.joint_axis[j]))
            anchor[j] = cp.vec_add(pos, cp.mat_vec(rot, cp.const_vec(tree.joint_pos[j])))
        body_rot[b], body_pos[b] = rot, pos
    return _FrameComponents(body_rot, body_pos, axis, anchor)


def forward_kinematics(tree: KinematicTree, q: jax.Array) -> Frames:
    """World frames of all bodies and joints at joint positions q."""
    fc = _frame_components(tree, q)
    like = q[0]
    return Frames(
        rot=jnp.stack([cp.stack_mat(r, like) for r in fc.body_rot]),
        pos=jnp.stack([cp.stack_vec(x, like) for x in fc.body_pos]),
        axis=jnp.stack([cp.stack_vec(x, like) for x in fc.axis]),
        anchor=jnp.stack([cp.stack_vec(x, like) for x in fc.anchor]),
    )


def site_pose(tree: KinematicTree, q: jax.Array, site: int) -> tuple[jax.Array, jax.Array]:
    """World position (3,) m and orientation (3, 3) of site index ``site``."""
    fc = _frame_components(tree, q)
    b = int(tree.site_body[site])
    local_rot = cp.const_mat(tree.site_rot[site])
    rot = local_rot if b < 0 else cp.mat_mat(fc.body_rot[b], local_rot)
    like = q[0]
    return cp.stack_vec(_site_point(tree, fc, site), like), cp.stack_mat(rot, like)


def _jacobian_components(tree: KinematicTree, fc: _FrameComponents, body: int, point) -> list:
    """Columns (nv of 6 components) of the Jacobian of a point fixed to ``body``."""
    cols = []
    for j in range(tree.nv):
        if body < 0 or not tree.moves[j, body]:
            cols.append([0.0] * 6)
        elif tree.is_hinge[j]:
            lin = cp.cross(fc.axis[j], cp.vec_sub(point, fc.anchor[j]))
            cols.append(lin + fc.axis[j])
        else:
            cols.append(fc.axis[j] + [0.0] * 3)
    return cols


def _site_point(tree: KinematicTree, fc: _FrameComponents, site: int) -> list:
    b = int(tree.site_body[site])
    local = cp.const_vec(tree.site_pos[site])
    if b < 0:
        return local
    return cp.vec_add(fc.body_pos[b], cp.mat_vec(fc.body_rot[b], local))


def site_jacobian(tree: KinematicTree, q: jax.Array, site: int) -> jax.Array:
    """(6, nv) Jacobian of site ``site``, world-aligned: rows vx, vy, vz, wx, wy, wz."""
    fc = _frame_components(tree, q)
    cols = _jacobian_components(tree, fc, int(tree.site_body[site]), _site_point(tree, fc, site))
    like = q[0]
    lin = jnp.stack([cp.stack_vec(col[:3], like) for col in cols], -1)
    ang = jnp.stack([cp.stack_vec(col[3:], like) for col in cols], -1)
    return jnp.concatenate([lin, ang], -2)


def body_com(tree: KinematicTree, q: jax.Array, params: InertialParams | None = None) -> jax.Array:
    """(nb, 3) world position of every body's centre of mass, m."""
    p = _params(tree, params)
    frames = forward_kinematics(tree, q)
    return frames.pos + jnp.einsum("bij,bj->bi", frames.rot, p.com)


def subtree_com(
    tree: KinematicTree, q: jax.Array, params: InertialParams | None = None
) -> tuple[jax.Array, jax.Array]:
    """Centre of mass (nb, 3) m and mass (nb,) kg of each body's subtree (itself included).

    A subtree of zero mass reports its body's origin.
    """
    p = _params(tree, params)
    frames = forward_kinematics(tree, q)
    com = frames.pos + jnp.einsum("bij,bj->bi", frames.rot, p.com)
    mass = tree.subtree @ p.mass
    weighted = tree.subtree @ (p.mass[:, None] * com)
    safe = jnp.where(mass > 0, mass, 1.0)
    return jnp.where(mass[:, None] > 0, weighted / safe[:, None], frames.pos), mass


def gravity(
    tree: KinematicTree,
    q: jax.Array,
    params: InertialParams | None = None,
    gravity_vector: jax.Array | None = None,
) -> jax.Array:
    """Generalized gravity g(q) (nv,), N m or N: the torque that holds the arm against gravity.

    ``gravity_vector`` (3,) m/s^2 in the world (base) frame; default (0, 0, -9.81).
    """
    p = _params(tree, params)
    if gravity_vector is None:
        g = cp.const_vec(STANDARD_GRAVITY)
    else:
        g = [gravity_vector[k] for k in range(3)]
    fc = _frame_components(tree, q)
    weighted: list = [None] * tree.nb  # subtree sum of m * com, kg m
    sub_mass: list = [None] * tree.nb  # subtree mass, kg
    for b in reversed(range(tree.nb)):
        m_b = _entry(p.mass, (b,))
        com_b = [_entry(p.com, (b, k)) for k in range(3)]
        c = cp.vec_add(fc.body_pos[b], cp.mat_vec(fc.body_rot[b], com_b))
        weighted[b] = cp.scale(m_b, c)
        sub_mass[b] = m_b
    for b in reversed(range(tree.nb)):
        par = tree.parent[b]
        if par >= 0:
            weighted[par] = cp.vec_add(weighted[par], weighted[b])
            sub_mass[par] = cp.add(sub_mass[par], sub_mass[b])
    out = []
    for j in range(tree.nv):
        b = tree.joint_body[j]
        if tree.is_hinge[j]:
            lever = cp.vec_sub(weighted[b], cp.scale(sub_mass[b], fc.anchor[j]))
            out.append(cp.dot(cp.cross(fc.axis[j], lever), g))
        else:
            out.append(cp.mul(sub_mass[b], cp.dot(fc.axis[j], g)))
    return -cp.pack(out, q[0], (tree.nv,))


def _entry(array, index):
    """One entry of a parameter array: a Python float for numpy constants (folded)."""
    if isinstance(array, np.ndarray):
        return float(array[index])
    return array[index]


def _world_inertia(p: InertialParams, fc: _FrameComponents, b: int) -> tuple:
    """Body b's mass m, first moment h = m c (kg m) and inertia about the world origin (kg m^2)."""
    m = _entry(p.mass, (b,))
    com = [_entry(p.com, (b, k)) for k in range(3)]
    inertia = [[_entry(p.inertia, (b, i, k)) for k in range(3)] for i in range(3)]
    rot = fc.body_rot[b]
    c = cp.vec_add(fc.body_pos[b], cp.mat_vec(rot, com))
    i_w = cp.mat_mat(cp.mat_mat(rot, inertia), [list(r) for r in zip(*rot, strict=True)])
    cc = cp.dot(c, c)
    i_o = [
        [
            cp.add(i_w[r][k], cp.mul(m, cp.sub(cc if r == k else 0.0, cp.mul(c[r], c[k]))))
            for k in range(3)
        ]
        for r in range(3)
    ]
    return m, cp.scale(m, c), i_o


def _momentum(inertia: tuple, v: list, w: list) -> tuple[list, list]:
    """Linear momentum and angular momentum about the origin of a body moving with twist (v, w)."""
    m, h, i_o = inertia
    return cp.vec_add(cp.scale(m, v), cp.cross(w, h)), cp.vec_add(
        cp.cross(h, v), cp.mat_vec(i_o, w)
    )


def _composite(tree: KinematicTree, per_body: list) -> list:
    """Subtree sums of per-body (m, h, I_O) tuples."""
    comp = list(per_body)
    for b in reversed(range(tree.nb)):
        par = tree.parent[b]
        if par >= 0:
            (m1, h1, i1), (m2, h2, i2) = comp[par], comp[b]
            summed = [
                [cp.add(x, y) for x, y in zip(r1, r2, strict=True)]
                for r1, r2 in zip(i1, i2, strict=True)
            ]
            comp[par] = (cp.add(m1, m2), cp.vec_add(h1, h2), summed)
    return comp


def _motion(tree: KinematicTree, fc: _FrameComponents, j: int) -> tuple[list, list]:
    """World twist (v_O, w) of joint j's unit motion; v_O is the velocity at the world origin."""
    if tree.is_hinge[j]:
        return cp.cross(fc.anchor[j], fc.axis[j]), fc.axis[j]
    return fc.axis[j], [0.0] * 3


def mass_matrix(
    tree: KinematicTree, q: jax.Array, params: InertialParams | None = None
) -> jax.Array:
    """Joint-space mass matrix M(q) (nv, nv), armature included.

    Composite-rigid-body algorithm in world coordinates: each subtree's mass, first moment and
    inertia about the world origin are plain sums, and M_jk = xi_j . (I_subtree(k) xi_k) for
    every joint j that moves the body of joint k (xi: the joints' unit twists).
    """
    p = _params(tree, params)
    fc = _frame_components(tree, q)
    comp = _composite(tree, [_world_inertia(p, fc, b) for b in range(tree.nb)])
    xi = [_motion(tree, fc, j) for j in range(tree.nv)]
    entries = [[0.0] * tree.nv for _ in range(tree.nv)]
    for k in range(tree.nv):
        b = tree.joint_body[k]
        lin, ang = _momentum(comp[b], *xi[k])
        for j in range(tree.nv):
            if tree.moves[j, b] and (tree.joint_body[j] != b or j <= k):
                value = cp.add(cp.dot(xi[j][0], lin), cp.dot(xi[j][1], ang))
                entries[j][k] = entries[k][j] = value
        entries[k][k] = cp.add(entries[k][k], float(tree.armature[k]))
    return cp.pack(entries, q[0], (tree.nv, tree.nv))


def _twist_cross(a: tuple, b: tuple) -> tuple[list, list]:
    """Spatial motion cross product a x b of world twists (v, w)."""
    (va, wa), (vb, wb) = a, b
    return cp.vec_add(cp.cross(wa, vb), cp.cross(va, wb)), cp.cross(wa, wb)


def coriolis(
    tree: KinematicTree, q: jax.Array, dq: jax.Array, params: InertialParams | None = None
) -> jax.Array:
    """Coriolis and centrifugal forces C(q, dq) dq (nv,), N m or N.

    Recursive Newton-Euler with zero acceleration and gravity, in world coordinates.
    """
    p = _params(tree, params)
    fc = _frame_components(tree, q)
    xi = [_motion(tree, fc, j) for j in range(tree.nv)]
    zero = ([0.0] * 3, [0.0] * 3)
    vel: list = [None] * tree.nb
    acc: list = [None] * tree.nb
    forces: list = [None] * tree.nb
    for b in range(tree.nb):
        par = tree.parent[b]
        v, a = (zero, zero) if par < 0 else (vel[par], acc[par])
        for j in tree.body_joints[b]:
            step = (cp.scale(dq[j], xi[j][0]), cp.scale(dq[j], xi[j][1]))
            v = (cp.vec_add(v[0], step[0]), cp.vec_add(v[1], step[1]))
            da = _twist_cross(v, step)  # d/dt of xi_j, times dq_j
            a = (cp.vec_add(a[0], da[0]), cp.vec_add(a[1], da[1]))
        vel[b], acc[b] = v, a
        inertia = _world_inertia(p, fc, b)
        f_a = _momentum(inertia, *a)
        lin, ang = _momentum(inertia, *v)
        (vv, vw) = v
        # f = I a + v x* (I v), with v x* (f, n) = (w x f, w x n + v x f)
        forces[b] = (
            cp.vec_add(f_a[0], cp.cross(vw, lin)),
            cp.vec_add(f_a[1], cp.vec_add(cp.cross(vw, ang), cp.cross(vv, lin))),
        )
    for b in reversed(range(tree.nb)):
        par = tree.parent[b]
        if par >= 0:
            forces[par] = (
                cp.vec_add(forces[par][0], forces[b][0]),
                cp.vec_add(forces[par][1], forces[b][1]),
            )
    out = []
    for j in range(tree.nv):
        f = forces[tree.joint_body[j]]
        out.append(cp.add(cp.dot(xi[j][0], f[0]), cp.dot(xi[j][1], f[1])))
    return cp.pack(out, q[0], (tree.nv,))


def coriolis_matrix(
    tree: KinematicTree, q: jax.Array, dq: jax.Array, params: InertialParams | None = None
) -> jax.Array:
    """Coriolis matrix C(q, dq) (nv, nv) from Christoffel symbols (M_dot - 2 C is skew)."""
    dm = jax.jacfwd(lambda qq: mass_matrix(tree, qq, params))(q)  # dm[i, j, k] = dM_ij / dq_k
    gamma = 0.5 * (dm + jnp.swapaxes(dm, 1, 2) - jnp.transpose(dm, (2, 0, 1)))
    return gamma @ dq


def bias(
    tree: KinematicTree,
    q: jax.Array,
    dq: jax.Array,
    params: InertialParams | None = None,
    gravity_vector: jax.Array | None = None,
) -> jax.Array:
    """Bias forces C(q, dq) dq + g(q) (nv,): MuJoCo's qfrc_bias, pinocchio's nonLinearEffects."""
    return coriolis(tree, q, dq, params) + gravity(tree, q, params, gravity_vector)


def operational_space(
    tree: KinematicTree,
    q: jax.Array,
    dq: jax.Array,
    site: int,
    params: InertialParams | None = None,
) -> OperationalSpace:
    """Lambda, mu (Eq. 2) and the dynamically consistent nullspace projector (Eq. 5).

    The task is the site's position x (3,) m; with J_bar = M^-1 J^T Lambda,
    Lambda = (J M^-1 J^T)^-1, mu = (J_bar^T C - Lambda J_dot) J_bar, N = I - J^T J_bar^T.
    """
    pos = site_pose(tree, q, site)[0]
    m = mass_matrix(tree, q, params)

    def jac_of(qq):
        return site_jacobian(tree, qq, site)[:3]

    jac, jac_dot = jax.jvp(jac_of, (q,), (dq,))
    minv_jt = jnp.linalg.solve(m, jac.T)
    lam = jnp.linalg.inv(jac @ minv_jt)
    lam = 0.5 * (lam + lam.T)
    jac_bar = minv_jt @ lam
    c = coriolis_matrix(tree, q, dq, params)
    mu = (jac_bar.T @ c - lam @ jac_dot) @ jac_bar
    nullspace = jnp.eye(tree.nv) - jac.T @ jac_bar.T
    return OperationalSpace(pos=pos, jac=jac, lam=lam, mu=mu, jac_bar=jac_bar, nullspace=nullspace)
