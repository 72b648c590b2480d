"""The kinematic tree of a compiled MuJoCo model, as constant numpy arrays.

Everything here is read once from an ``mujoco.MjModel``; the JAX dynamics close over these
arrays as compile-time constants. Bodies are indexed 0..nb-1 without MuJoCo's world body
(MuJoCo body ``i`` is tree body ``i - 1``); parent ``-1`` is the world.

``KinematicTree.lanes`` (``Lanes``) is the same tree seen from its joints, the structure every
kinematics and dynamics function of ``jaxcomp.dynamics`` walks: one frame ("lane") per joint,
each joint's transform from its parent lane as constant coefficients of sin, 1 - cos and the
displacement, and every link attached to the lane that carries it.
"""

from dataclasses import dataclass
from functools import cached_property

import mujoco
import numpy as np

from jaxcomp.errors import ModelError
from jaxcomp.params import InertialParams

_JOINT_KIND = {
    int(mujoco.mjtJoint.mjJNT_HINGE): "hinge",
    int(mujoco.mjtJoint.mjJNT_SLIDE): "slide",
    int(mujoco.mjtJoint.mjJNT_BALL): "ball",
    int(mujoco.mjtJoint.mjJNT_FREE): "free",
}


def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from MuJoCo quaternions (..., 4) in (w, x, y, z) order.

    Args:
        quat: (..., 4) quaternions (w, x, y, z), normalised here.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    quat = np.asarray(quat, dtype=float)
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(quat, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


@dataclass(frozen=True, eq=False)
class KinematicTree:
    """Constant description of a tree of rigid bodies joined by hinge and slide joints.

    Frames: each body's frame is given in its parent's frame (``pos`` m, ``rot``); joint
    anchors and axes in their body's frame; sites in their body's frame. Joint ``j`` is
    degree of freedom ``j`` (the tree has only 1-DoF joints, so nq == nv).

    Attributes:
        body_names: (nb,) body (link) names.
        parent: (nb,) int, each body's parent body, -1 = world.
        pos: (nb, 3) m, each body's origin in its parent's frame.
        rot: (nb, 3, 3) each body's orientation in its parent's frame.
        body_joints: the joints of each body, in order.
        joint_names: (nv,) joint names.
        joint_body: (nv,) int, each joint's body.
        is_hinge: (nv,) bool; False = slide.
        joint_pos: (nv, 3) m, each joint's anchor in its body's frame.
        joint_axis: (nv, 3) each joint's unit axis in its body's frame.
        joint_ref: (nv,) rad or m, the reference position (MuJoCo qpos0).
        joint_range: (nv, 2) rad or m; (-inf, inf) when unlimited.
        armature: (nv,) kg m^2 or kg, added to the mass matrix diagonal.
        moves: (nv, nb) bool: [j, i] joint j moves body i.
        subtree: (nb, nb) float: [k, i] 1 where body i is in the subtree of body k.
        site_names: (ns,) site names.
        site_body: (ns,) int, each site's body, -1 = world.
        site_pos: (ns, 3) m, each site's position in its body's frame.
        site_rot: (ns, 3, 3) each site's orientation in its body's frame.
        nominal: the model's ``InertialParams``, numpy arrays (link frames).
    """

    body_names: tuple[str, ...]
    parent: np.ndarray
    pos: np.ndarray
    rot: np.ndarray
    body_joints: tuple[tuple[int, ...], ...]
    joint_names: tuple[str, ...]
    joint_body: np.ndarray
    is_hinge: np.ndarray
    joint_pos: np.ndarray
    joint_axis: np.ndarray
    joint_ref: np.ndarray
    joint_range: np.ndarray
    armature: np.ndarray
    moves: np.ndarray
    subtree: np.ndarray
    site_names: tuple[str, ...]
    site_body: np.ndarray
    site_pos: np.ndarray
    site_rot: np.ndarray
    nominal: InertialParams

    @property
    def nb(self) -> int:
        return len(self.body_names)

    @property
    def nv(self) -> int:
        return len(self.joint_names)

    @cached_property
    def lanes(self) -> "Lanes":
        """The tree's joint frames and their constant transforms (built on first use)."""
        return Lanes.of(self)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): skew(a) @ b = a x b.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


@dataclass(frozen=True, eq=False)
class Lanes:
    """A tree's joints as lanes: one frame per joint, links attached to the lanes.

    Lane j is the frame of joint j's body after joint j moved (a body with several joints
    chains their lanes). At displacement d = q_j - ref_j (rad or m) the transform of lane j in
    its parent lane's frame (the world for -1) is

        R = rot_coef[0] + sin(d) rot_coef[1] + (1 - cos d) rot_coef[2]
        t = pos_coef[0] + sin(d) pos_coef[1] + (1 - cos d) pos_coef[2] + d pos_coef[3]  (m)

    (Rodrigues' formula about the joint's axis through its anchor, after the joint's constant
    offset from its parent lane; slides translate along their axis).

    Attributes:
        parent: (nv,) int, each lane's parent lane, -1 = world.
        frame_of: per link, (lane, offset): the lane that carries it (-1 = world) and the
            (4, 4) transform of the link's frame in the lane's (m).
        rot_coef: (3, 3, 3, nv) the coefficients of R above, rot_coef[n, :, :, j].
        pos_coef: (4, 3, nv) m, the coefficients of t above, pos_coef[n, :, j].
        moving: the links some joint moves.
        carried: per lane, the links attached to it.
        subtree: (nv, nv) bool: [j, l] lane l moves with joint j.
        related: (nv, nv) bool: [j, k] joint j moves the link of joint k.
    """

    parent: np.ndarray
    frame_of: tuple[tuple[int, np.ndarray], ...]
    rot_coef: np.ndarray
    pos_coef: np.ndarray
    moving: tuple[int, ...]
    carried: tuple[tuple[int, ...], ...]
    subtree: np.ndarray
    related: np.ndarray

    @staticmethod
    def of(tree: KinematicTree) -> "Lanes":
        """The lanes of ``tree`` (use ``tree.lanes``, built once per tree).

        Args:
            tree: the kinematic tree.

        Returns:
            Its ``Lanes``.
        """
        nb, nv = tree.nb, tree.nv
        frame_of: list = [None] * nb
        parent = np.full(nv, -1)
        pre = np.zeros((nv, 4, 4))  # parent lane frame -> joint j's frame at q = ref
        for b in range(nb):
            offset = np.eye(4)
            offset[:3, :3], offset[:3, 3] = tree.rot[b], tree.pos[b]
            p = tree.parent[b]
            lane, frame = (-1, offset) if p < 0 else (frame_of[p][0], frame_of[p][1] @ offset)
            for j in tree.body_joints[b]:
                parent[j], pre[j] = lane, frame
                lane, frame = j, np.eye(4)
            frame_of[b] = (lane, frame)
        rot_coef = np.zeros((3, 3, 3, nv))
        pos_coef = np.zeros((4, 3, nv))
        for j in range(nv):
            rot, pos = pre[j][:3, :3], pre[j][:3, 3]
            rot_coef[0, ..., j], pos_coef[0, :, j] = rot, pos
            axis, anchor = tree.joint_axis[j], tree.joint_pos[j]
            if tree.is_hinge[j]:
                k1 = skew(axis)
                for n, k in ((1, k1), (2, k1 @ k1)):
                    rot_coef[n, ..., j] = rot @ k
                    pos_coef[n, :, j] = -rot @ k @ anchor
            else:
                pos_coef[3, :, j] = rot @ axis
        moving = tuple(b for b in range(nb) if frame_of[b][0] >= 0)
        carried: list = [[] for _ in range(nv)]
        for b in moving:
            carried[frame_of[b][0]].append(b)
        subtree = np.eye(nv, dtype=bool)
        for lane in range(nv):
            a = parent[lane]
            while a >= 0:
                subtree[a, lane] = True
                a = parent[a]
        return Lanes(
            parent=parent,
            frame_of=tuple(frame_of),
            rot_coef=rot_coef,
            pos_coef=pos_coef,
            moving=moving,
            carried=tuple(tuple(c) for c in carried),
            subtree=subtree,
            related=tree.moves[:, tree.joint_body],
        )


def _name(model: mujoco.MjModel, objtype: mujoco.mjtObj, i: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, objtype, i) or fallback


def tree_from_mujoco(model: mujoco.MjModel) -> KinematicTree:
    """Read the kinematic tree of ``model``; raises ModelError for unsupported models.

    Args:
        model: a compiled ``mujoco.MjModel``.

    Returns:
        Its ``KinematicTree`` (bodies without the world body, nominal inertials).

    Raises:
        ModelError: the model has no joints, or a ball or free joint.
    """
    if model.njnt == 0:
        raise ModelError("the model has no joints: nothing to move or identify")
    kinds = [_JOINT_KIND.get(int(t), str(t)) for t in model.jnt_type]
    bad = [
        f"{_name(model, mujoco.mjtObj.mjOBJ_JOINT, j, f'joint{j}')} ({k})"
        for j, k in enumerate(kinds)
        if k not in ("hinge", "slide")
    ]
    if bad:
        raise ModelError(
            "only hinge (revolute) and slide (prismatic) joints are supported; "
            f"the model has {', '.join(bad)}"
        )
    nb = model.nbody - 1
    body_names = tuple(
        _name(model, mujoco.mjtObj.mjOBJ_BODY, i, f"body{i}") for i in range(1, model.nbody)
    )
    parent = model.body_parentid[1:].astype(int) - 1
    nv = model.njnt
    joint_body = model.jnt_bodyid.astype(int) - 1
    body_joints = tuple(tuple(int(j) for j in np.flatnonzero(joint_body == b)) for b in range(nb))
    # joint j moves body i iff j's body is i or an ancestor of i
    ancestors = np.eye(nb, dtype=bool)  # (k, i): k is i or an ancestor of i
    for i in range(nb):
        p = parent[i]
        while p >= 0:
            ancestors[p, i] = True
            p = parent[p]
    moves = ancestors[joint_body]
    limited = model.jnt_limited.astype(bool)
    joint_range = np.where(limited[:, None], model.jnt_range, [-np.inf, np.inf])
    irot = quat_to_mat(model.body_iquat[1:])
    inertia = np.einsum("bij,bj,bkj->bik", irot, model.body_inertia[1:], irot)
    nominal = InertialParams(
        mass=model.body_mass[1:].copy(), com=model.body_ipos[1:].copy(), inertia=inertia
    )
    return KinematicTree(
        body_names=body_names,
        parent=parent,
        pos=model.body_pos[1:].copy(),
        rot=quat_to_mat(model.body_quat[1:]),
        body_joints=body_joints,
        joint_names=tuple(
            _name(model, mujoco.mjtObj.mjOBJ_JOINT, j, f"joint{j}") for j in range(nv)
        ),
        joint_body=joint_body,
        is_hinge=np.array([k == "hinge" for k in kinds]),
        joint_pos=model.jnt_pos.copy(),
        joint_axis=model.jnt_axis / np.linalg.norm(model.jnt_axis, axis=1, keepdims=True),
        joint_ref=model.qpos0.copy(),
        joint_range=joint_range,
        armature=model.dof_armature.copy(),
        moves=moves,
        subtree=ancestors.astype(float),
        site_names=tuple(
            _name(model, mujoco.mjtObj.mjOBJ_SITE, s, f"site{s}") for s in range(model.nsite)
        ),
        site_body=model.site_bodyid.astype(int) - 1,
        site_pos=model.site_pos.copy(),
        site_rot=quat_to_mat(model.site_quat) if model.nsite else np.zeros((0, 3, 3)),
        nominal=nominal,
    )
