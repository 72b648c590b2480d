"""The kinematic tree of a compiled MuJoCo model, as constant numpy arrays.

Everything here is read once from an ``mujoco.MjModel``; the JAX dynamics close over these
arrays as compile-time constants. Bodies are indexed 0..nb-1 without MuJoCo's world body
(MuJoCo body ``i`` is tree body ``i - 1``); parent ``-1`` is the world.
"""

from dataclasses import dataclass

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
    """Rotation matrices (..., 3, 3) from MuJoCo quaternions (..., 4) in (w, x, y, z) order."""
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
    """

    body_names: tuple[str, ...]
    parent: np.ndarray  # (nb,) int, -1 = world
    pos: np.ndarray  # (nb, 3) m
    rot: np.ndarray  # (nb, 3, 3)
    body_joints: tuple[tuple[int, ...], ...]  # joints of each body, in order
    joint_names: tuple[str, ...]
    joint_body: np.ndarray  # (nv,) int
    is_hinge: np.ndarray  # (nv,) bool; False = slide
    joint_pos: np.ndarray  # (nv, 3) m, anchor in body frame
    joint_axis: np.ndarray  # (nv, 3) unit vector in body frame
    joint_ref: np.ndarray  # (nv,) rad or m, the reference position (MuJoCo qpos0)
    joint_range: np.ndarray  # (nv, 2) rad or m; (-inf, inf) when unlimited
    armature: np.ndarray  # (nv,) kg m^2 or kg, added to the mass matrix diagonal
    moves: np.ndarray  # (nv, nb) bool: joint j moves body i
    subtree: np.ndarray  # (nb, nb) float: 1 where body i is in the subtree of body k (k, i)
    site_names: tuple[str, ...]
    site_body: np.ndarray  # (ns,) int
    site_pos: np.ndarray  # (ns, 3) m
    site_rot: np.ndarray  # (ns, 3, 3)
    nominal: InertialParams  # numpy arrays

    @property
    def nb(self) -> int:
        return len(self.body_names)

    @property
    def nv(self) -> int:
        return len(self.joint_names)


def _name(model: mujoco.MjModel, objtype: mujoco.mjtObj, i: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, objtype, i) or fallback


def tree_from_mujoco(model: mujoco.MjModel) -> KinematicTree:
    """Read the kinematic tree of ``model``; raises ModelError for unsupported models."""
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
