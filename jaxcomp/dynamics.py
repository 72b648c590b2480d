"""Rigid-body dynamics of a kinematic tree in JAX: pure, jit-, vmap- and grad-able.

Every function takes the constant ``KinematicTree`` first (closed over as compile-time
constants under ``jax.jit``), then joint positions ``q`` (nv,) in rad or m, and optionally
``InertialParams`` (default: the model's). Results are in the model's world frame (for a fixed
arm, its base frame). Sign conventions follow MuJoCo and pinocchio:

    M(q) ddq + C(q, dq) dq + g(q) = tau

so ``gravity`` returns g(q), the joint torque that holds the arm still against gravity.

One kinematics: every function walks the tree's joint frames (``KinematicTree.lanes``), and the
world frames come from one forward kinematics, ``fast_dynamics.lane_frames``. On top of it:

- ``kinematics_and_dynamics`` (``jaxcomp.fast_dynamics``): g(q), a site's pose and Jacobian
  and M(q) of one pose in one pass (``KinematicsDynamics``), the call both controllers make
  once per cycle;
- ``gravity``: g(q) alone, by a recursion in the lanes' own frames, entry by entry: the fewest
  flops per pose, for identification's batches and gradients;
- ``mass_matrix``: M(q) alone, from the bodies' Jacobians as batched array operations: what
  automatic differentiation (``coriolis_matrix``, ``operational_space``) and batched callers
  use, as it compiles several times faster under jvp and grad than the one pass;
- ``inverse_dynamics``: M(q) ddq + C(q, dq) dq + g(q) by Newton-Euler on the same Jacobians
  and their time derivatives, without automatic differentiation (``coriolis`` and ``bias``
  are its special cases): ~15 times faster than differentiating M under ``jax.vmap``;
- ``forward_kinematics``, ``site_pose``, ``site_jacobian``, ``body_com``, ``subtree_com``.

The one pass and the separate functions agree to rounding (tests: against MuJoCo and pinocchio
to 1e-9).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import components as cp
from jaxcomp import fast_dynamics
from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.fast_dynamics import KinematicsDynamics, kinematics_and_dynamics
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams

__all__ = [
    "Frames",
    "KinematicsDynamics",
    "OperationalSpace",
    "bias",
    "body_com",
    "coriolis",
    "coriolis_matrix",
    "forward_kinematics",
    "gravity",
    "inverse_dynamics",
    "kinematics_and_dynamics",
    "mass_matrix",
    "operational_space",
    "site_jacobian",
    "site_pose",
    "subtree_com",
]


class Frames(NamedTuple):
    """World poses of every body frame, and world axes and anchors of every joint.

    Attributes:
        rot: (nb, 3, 3) each body's orientation: columns are its axes in the world frame.
        pos: (nb, 3) m, each body frame's origin in the world frame.
        axis: (nv, 3) each joint's unit axis in the world frame.
        anchor: (nv, 3) m, each joint's anchor point in the world frame.
    """

    rot: jax.Array
    pos: jax.Array
    axis: jax.Array
    anchor: jax.Array


class OperationalSpace(NamedTuple):
    """Task-space quantities of a site's position (Eq. 2 and 5 of the paper).

    Attributes:
        pos: (3,) m, the site's position x, world frame.
        jac: (3, nv) position Jacobian J, world-aligned, m/rad (1 for a slide).
        lam: (3, 3) kg, Cartesian inertia Lambda = (J M^-1 J^T)^-1.
        mu: (3, 3) kg/s, Cartesian Coriolis matrix mu.
        jac_bar: (nv, 3) dynamically consistent inverse J_bar = M^-1 J^T Lambda.
        nullspace: (nv, nv) nullspace projector N = I - J^T J_bar^T.
    """

    pos: jax.Array
    jac: jax.Array
    lam: jax.Array
    mu: jax.Array
    jac_bar: jax.Array
    nullspace: jax.Array


def _params(tree: KinematicTree, params: InertialParams | None) -> InertialParams:
    return tree.nominal if params is None else params


def forward_kinematics(tree: KinematicTree, q: jax.Array) -> Frames:
    """World frames of all bodies, and world axes and anchors of all joints, at q.

    From the lane frames of ``fast_dynamics.lane_frames``: a body's frame is its lane's frame
    times the body's constant offset in it (the world, for a body no joint moves).

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).

    Returns:
        ``Frames``: body orientations (nb, 3, 3) and origins (nb, 3) m, joint axes (nv, 3)
        and anchors (nv, 3) m, world frame.
    """
    lanes = tree.lanes
    rot, pos = fast_dynamics.lane_frames(tree, q)
    axis, anchor = fast_dynamics.joint_axes(tree, rot, pos)
    # lane index nv: the world frame, for bodies no joint moves
    rot = jnp.concatenate([rot, jnp.eye(3)[:, :, None]], axis=2)
    pos = jnp.concatenate([pos, jnp.zeros((3, 1))], axis=1)
    lane = np.array([ln if ln >= 0 else tree.nv for ln, _ in lanes.frame_of])
    offset = np.stack([off for _, off in lanes.frame_of])  # (nb, 4, 4)
    lane_rot = jnp.moveaxis(rot[:, :, lane], 2, 0)  # (nb, 3, 3)
    body_rot = jnp.einsum("bij,bjk->bik", lane_rot, offset[:, :3, :3])
    body_pos = pos[:, lane].T + jnp.einsum("bij,bj->bi", lane_rot, offset[:, :3, 3])
    return Frames(rot=body_rot, pos=body_pos, axis=axis.T, anchor=anchor.T)


def _point_on_body(frames: Frames, body: int, local: np.ndarray) -> jax.Array:
    if body < 0:
        return jnp.asarray(local, dtype=float)
    return frames.pos[body] + frames.rot[body] @ local


def site_pose(tree: KinematicTree, q: jax.Array, site: int) -> tuple[jax.Array, jax.Array]:
    """World position (3,) m and orientation (3, 3) of site index ``site``.

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).
        site: site index (into ``tree.site_names``).

    Returns:
        (position (3,) m, rotation (3, 3): columns are the site's axes), world frame.
    """
    frames = forward_kinematics(tree, q)
    b = int(tree.site_body[site])
    if b < 0:
        return jnp.asarray(tree.site_pos[site]), jnp.asarray(tree.site_rot[site])
    return _point_on_body(frames, b, tree.site_pos[site]), frames.rot[b] @ tree.site_rot[site]


def site_jacobian(tree: KinematicTree, q: jax.Array, site: int) -> jax.Array:
    """(6, nv) Jacobian of site ``site``, world-aligned: rows vx, vy, vz, wx, wy, wz.

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).
        site: site index (into ``tree.site_names``).

    Returns:
        (6, nv): the site origin's linear velocity per joint rate, m/rad (1 for a slide),
        over its angular velocity, rad/rad (0 for a slide); zero columns for joints that do
        not move the site.
    """
    frames = forward_kinematics(tree, q)
    body = int(tree.site_body[site])
    if body < 0:
        return jnp.zeros((6, tree.nv))
    point = _point_on_body(frames, body, tree.site_pos[site])
    mask = tree.moves[:, body].astype(float)[:, None]
    lin = jnp.where(
        tree.is_hinge[:, None], jnp.cross(frames.axis, point - frames.anchor), frames.axis
    )
    ang = frames.axis * tree.is_hinge[:, None]
    return jnp.concatenate([lin * mask, ang * mask], 1).T


def body_com(tree: KinematicTree, q: jax.Array, params: InertialParams | None = None) -> jax.Array:
    """(nb, 3) world position of every body's centre of mass, m.

    Args:
        tree, q, params: as for ``gravity``.

    Returns:
        (nb, 3) m, world frame.
    """
    p = _params(tree, params)
    frames = forward_kinematics(tree, q)
    return frames.pos + jnp.einsum("bij,bj->bi", frames.rot, p.com)


def subtree_com(
    tree: KinematicTree, q: jax.Array, params: InertialParams | None = None
) -> tuple[jax.Array, jax.Array]:
    """Centre of mass (nb, 3) m and mass (nb,) kg of each body's subtree (itself included).

    A subtree of zero mass reports its body's origin.

    Args:
        tree, q, params: as for ``gravity``.

    Returns:
        (centre of mass (nb, 3) m in the world frame, mass (nb,) kg).
    """
    p = _params(tree, params)
    com = body_com(tree, q, p)
    mass = tree.subtree @ p.mass
    weighted = tree.subtree @ (p.mass[:, None] * com)
    safe = jnp.where(mass > 0, mass, 1.0)
    origin = forward_kinematics(tree, q).pos
    return jnp.where(mass[:, None] > 0, weighted / safe[:, None], origin), mass


def _joint_trig(tree: KinematicTree, q: jax.Array) -> dict:
    """sin and cos of every hinge displacement, as (1,) components, computed once.

    The vector of sines and cosines goes through an identity matrix product: a dot is a kernel
    XLA never fuses into its consumers, so under ``jax.vmap`` they are computed once per pose
    rather than once per output joint.
    """
    hinges = [j for j in range(tree.nv) if tree.is_hinge[j]]
    if not hinges:
        return {}
    d = jnp.stack([q[j] - tree.joint_ref[j] for j in hinges])
    trig = jnp.concatenate(cp.sincos(d))[None, :] @ np.eye(2 * len(hinges))
    n = len(hinges)
    return {j: (trig[0, i : i + 1], trig[0, n + i : n + i + 1]) for i, j in enumerate(hinges)}


def gravity(
    tree: KinematicTree,
    q: jax.Array,
    params: InertialParams | None = None,
    gravity_vector: jax.Array | None = None,
) -> jax.Array:
    """Generalized gravity g(q) (nv,), N m or N: the torque that holds the arm against gravity.

    Recursive, in joint frames (entry by entry, model constants folded): the gravity vector is
    carried out to every joint frame and each subtree's mass and first moment back in, so a
    pose costs a few hundred flops and one sine and cosine per hinge.

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).
        params: link masses (nb,) kg, COMs (nb, 3) m and inertias (nb, 3, 3) kg m^2 in the
            link frames; default the model's.
        gravity_vector: gravity (3,) m/s^2 in the world (base) frame; default (0, 0, -9.81).

    Returns:
        g(q) (nv,), N m (N for a slide).
    """
    p = _params(tree, params)
    if gravity_vector is None:
        g = cp.const_vec(STANDARD_GRAVITY)
    else:
        gravity_vector = jnp.asarray(gravity_vector, dtype=float)
        g = [gravity_vector[k : k + 1] for k in range(3)]
    lanes = tree.lanes
    trig = _joint_trig(tree, q)
    nv = tree.nv
    rots, trans = [], []  # each lane's rotation and position (m) in its parent lane's frame
    for j in range(nv):
        coef = [cp.const_mat(lanes.rot_coef[n, ..., j]) for n in range(3)]
        pos_coef = [cp.const_vec(lanes.pos_coef[n, :, j]) for n in range(4)]
        rot, pos = coef[0], pos_coef[0]
        if tree.is_hinge[j]:
            s, c = trig[j]
            c = 1.0 - c
            rot = [
                [
                    cp.add(cp.add(rot[i][k], cp.mul(coef[1][i][k], s)), cp.mul(coef[2][i][k], c))
                    for k in range(3)
                ]
                for i in range(3)
            ]
            pos = cp.vec_add(pos, cp.vec_add(cp.scale(s, pos_coef[1]), cp.scale(c, pos_coef[2])))
        else:
            pos = cp.vec_add(pos, cp.scale(q[j : j + 1] - tree.joint_ref[j], pos_coef[3]))
        rots.append(rot)
        trans.append(pos)
    # gravity (m/s^2) in every joint frame, root to leaves
    grav: list = [None] * nv
    for j in range(nv):
        up = g if lanes.parent[j] < 0 else grav[lanes.parent[j]]
        grav[j] = [cp.total(cp.mul(rots[j][k][i], up[k]) for k in range(3)) for i in range(3)]
    # mass (kg) and first moment (kg m) of each joint's subtree in its frame, leaves to root
    mass: list = [0.0] * nv
    moment: list = [[0.0, 0.0, 0.0] for _ in range(nv)]
    for b in lanes.moving:
        lane, offset = lanes.frame_of[b]
        m_b = cp.entry(p.mass, (b,))
        com = [cp.entry(p.com, (b, k)) for k in range(3)]
        c = cp.vec_add(cp.const_vec(offset[:3, 3]), cp.mat_vec(cp.const_mat(offset[:3, :3]), com))
        mass[lane] = cp.add(mass[lane], m_b)
        moment[lane] = cp.vec_add(moment[lane], cp.scale(m_b, c))
    for j in reversed(range(nv)):
        up = lanes.parent[j]
        if up >= 0:
            mass[up] = cp.add(mass[up], mass[j])
            carried = cp.vec_add(cp.scale(mass[j], trans[j]), cp.mat_vec(rots[j], moment[j]))
            moment[up] = cp.vec_add(moment[up], carried)
    out = []
    for j in range(nv):
        axis = cp.const_vec(tree.joint_axis[j])
        if tree.is_hinge[j]:
            lever = cp.vec_sub(moment[j], cp.scale(mass[j], cp.const_vec(tree.joint_pos[j])))
            out.append(cp.mul(-1.0, cp.dot(axis, cp.cross(lever, grav[j]))))
        else:
            out.append(cp.mul(-1.0, cp.mul(mass[j], cp.dot(axis, grav[j]))))
    like = q[:1]
    return jnp.concatenate([cp.to_array(v, like) for v in out])


def _com_jacobians(
    tree: KinematicTree, frames: Frames, p: InertialParams
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """World centre of mass (nb, 3) m of every body, and the Jacobians of its velocity
    (nb, nv, 3) and of its angular velocity (nb, nv, 3): column j is zero where joint j does
    not move the body."""
    com = frames.pos + jnp.einsum("bij,bj->bi", frames.rot, p.com)
    mask = tree.moves.T.astype(float)[:, :, None]  # (nb, nv, 1)
    hinge = tree.is_hinge[None, :, None]
    lin = jnp.where(
        hinge,
        jnp.cross(frames.axis[None, :, :], com[:, None, :] - frames.anchor[None, :, :]),
        frames.axis[None, :, :],
    )
    return com, lin * mask, frames.axis[None, :, :] * (mask * hinge)


def _world_inertia(frames: Frames, p: InertialParams) -> jax.Array:
    """(nb, 3, 3) kg m^2: every body's rotational inertia about its COM, world axes."""
    return jnp.einsum("bij,bjk,blk->bil", frames.rot, p.inertia, frames.rot)


def mass_matrix(
    tree: KinematicTree, q: jax.Array, params: InertialParams | None = None
) -> jax.Array:
    """Joint-space mass matrix M(q) (nv, nv), armature included.

    M = sum_i m_i Jc_i^T Jc_i + Jw_i^T I_i Jw_i over bodies i, from the Jacobians of every
    body's centre of mass (Jc) and angular velocity (Jw), as a few batched array operations.

    Args:
        tree, q, params: as for ``gravity``.

    Returns:
        M(q) (nv, nv): kg m^2 between hinges, kg between slides, kg m across.
    """
    p = _params(tree, params)
    frames = forward_kinematics(tree, q)
    _, lin, ang = _com_jacobians(tree, frames, p)
    m = jnp.einsum("bja,b,bka->jk", lin, p.mass, lin)
    m = m + jnp.einsum("bja,bac,bkc->jk", ang, _world_inertia(frames, p), ang)
    return m + jnp.diag(tree.armature)


def inverse_dynamics(
    tree: KinematicTree,
    q: jax.Array,
    dq: jax.Array,
    ddq: jax.Array,
    params: InertialParams | None = None,
    gravity_vector: jax.Array | None = None,
) -> jax.Array:
    """Joint force tau = M(q) ddq + C(q, dq) dq + g(q) (nv,), N m or N, armature included
    (MuJoCo's qfrc_inverse without damping; pinocchio's rnea).

    Newton-Euler on every body's centre of mass, in the world frame: the body's COM
    acceleration a and angular acceleration alpha from its Jacobians Jc, Jw and their time
    derivatives, then tau = sum_b Jc_b^T m_b (a_b - g) + Jw_b^T (I_b alpha_b + w_b x I_b w_b).
    No automatic differentiation: a few batched array operations, as ``mass_matrix``.

    Args:
        tree: the kinematic tree (constant; ``Robot.tree``).
        q: joint positions (nv,), rad (slides: m).
        dq: joint velocities (nv,), rad/s (slides: m/s).
        ddq: joint accelerations (nv,), rad/s^2 (slides: m/s^2).
        params: link masses (nb,) kg, COMs (nb, 3) m and inertias (nb, 3, 3) kg m^2 in the
            link frames; default the model's.
        gravity_vector: gravity (3,) m/s^2 in the world (base) frame; default (0, 0, -9.81).

    Returns:
        tau (nv,), N m (N for a slide).
    """
    p = _params(tree, params)
    g = jnp.asarray(STANDARD_GRAVITY if gravity_vector is None else gravity_vector, float)
    frames = forward_kinematics(tree, q)
    com, lin, ang = _com_jacobians(tree, frames, p)
    hinge = tree.is_hinge
    # before[j, k]: joint k moves joint j's axis and anchor (k outward of j moves j's body)
    before = (tree.moves[:, tree.joint_body].T & np.tri(tree.nv, k=-1, dtype=bool)).astype(float)
    # each joint's axis and anchor move with the joints before it
    turn = jnp.cross(frames.axis[None, :, :], frames.anchor[:, None, :] - frames.anchor[None])
    lin_at = jnp.where(hinge[None, :, None], turn, frames.axis[None, :, :])  # (j, k, 3)
    anchor_dot = jnp.einsum("jk,jka->ja", before * dq[None, :], lin_at)
    axis_dot = jnp.cross((before * (hinge * dq)[None, :]) @ frames.axis, frames.axis)
    omega = jnp.einsum("bja,j->ba", ang, dq)
    v_com = jnp.einsum("bja,j->ba", lin, dq)
    mask = tree.moves.T.astype(float)[:, :, None]
    lin_dot = (
        jnp.where(
            hinge[None, :, None],
            jnp.cross(axis_dot[None], com[:, None, :] - frames.anchor[None])
            + jnp.cross(frames.axis[None], v_com[:, None, :] - anchor_dot[None]),
            axis_dot[None],
        )
        * mask
    )
    ang_dot = axis_dot[None] * (mask * hinge[None, :, None])
    acc = jnp.einsum("bja,j->ba", lin, ddq) + jnp.einsum("bja,j->ba", lin_dot, dq)
    alpha = jnp.einsum("bja,j->ba", ang, ddq) + jnp.einsum("bja,j->ba", ang_dot, dq)
    inertia = _world_inertia(frames, p)
    spin = jnp.einsum("bac,bc->ba", inertia, omega)
    force = p.mass[:, None] * (acc - g)
    torque = jnp.einsum("bac,bc->ba", inertia, alpha) + jnp.cross(omega, spin)
    tau = jnp.einsum("bja,ba->j", lin, force) + jnp.einsum("bja,ba->j", ang, torque)
    return tau + tree.armature * ddq


def coriolis(
    tree: KinematicTree, q: jax.Array, dq: jax.Array, params: InertialParams | None = None
) -> jax.Array:
    """Coriolis and centrifugal forces C(q, dq) dq (nv,), N m or N: ``inverse_dynamics``
    without acceleration and gravity.

    Args:
        tree, q, dq, params: as for ``inverse_dynamics``.

    Returns:
        C(q, dq) dq (nv,), N m (N for a slide).
    """
    zero = jnp.zeros_like(dq)
    return inverse_dynamics(tree, q, dq, zero, params, jnp.zeros(3))


def coriolis_matrix(
    tree: KinematicTree, q: jax.Array, dq: jax.Array, params: InertialParams | None = None
) -> jax.Array:
    """Coriolis matrix C(q, dq) (nv, nv) from Christoffel symbols (M_dot - 2 C is skew).

    Args:
        tree, q, dq, params: as for ``inverse_dynamics``.

    Returns:
        C(q, dq) (nv, nv), such that C dq is in N m (N for a slide).
    """
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
    """Bias forces C(q, dq) dq + g(q) (nv,): MuJoCo's qfrc_bias, pinocchio's nonLinearEffects
    (``inverse_dynamics`` without acceleration).

    Args:
        tree, q, dq, params: as for ``inverse_dynamics``.
        gravity_vector: gravity (3,) m/s^2 in the world (base) frame; default (0, 0, -9.81).

    Returns:
        C(q, dq) dq + g(q) (nv,), N m (N for a slide).
    """
    return inverse_dynamics(tree, q, dq, jnp.zeros_like(dq), params, gravity_vector)


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

    Args:
        tree, q, dq, params: as for ``inverse_dynamics``.
        site: site index (into ``tree.site_names``).

    Returns:
        ``OperationalSpace``: x (3,) m, J (3, nv), Lambda (3, 3) kg, mu (3, 3) kg/s, J_bar
        (nv, 3) and N (nv, nv), world frame.
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
