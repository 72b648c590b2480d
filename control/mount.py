"""Where the arm sits on the mobile base, and which model the controllers work in.

Frames (all right-handed, z up, m):

- world: the base's odometry frame (the simulator's world); the base pose (x, y, yaw) is the
  odometry of the base's planar joints;
- base: the mobile base's own frame, moving with it (at pose 0 it coincides with the world);
- arm: the arm's base frame, where the controller works (the arm's own model, e.g.
  ``gen3_lite``); ``ArmMount`` places it in the base frame, read from the mobile model (the
  arm's root body with the base joints at zero: Gen3 Lite at (0.160, 0, 0.11) m).

``arm_model`` is the arm-alone model of a mobile one (``mobile_gen3_lite`` -> ``gen3_lite``),
``mobile_model_name`` the other way round; ``check_site_mobility`` refuses a start pose where
the joints cannot move the end effector in all three directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from jaxcomp.errors import InputError, ModelError
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import BASE_JOINTS, arm_joint_indices

#: Smallest singular value of the end effector's position Jacobian, relative to its largest,
#: that still counts as a direction the arm can move in (``check_site_mobility``).
MIN_MOBILITY = 1e-3


def rz(yaw: float) -> np.ndarray:
    """The rotation about z by ``yaw``.

    Args:
        yaw: rad.

    Returns:
        (3, 3) rotation matrix.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ArmMount:
    """Where the arm's base frame sits on the mobile base.

    Attributes:
        position: (3,) m, the arm frame's origin in the base frame.
        rotation: (3, 3), the arm frame's axes in the base frame (columns).
        pivot: (3,) m, a point on the base's yaw axis in the base frame (z = 0).

    A point p_b of the base frame is, with the base at odometry pose (x, y, yaw), at
    (x, y, 0) + pivot + Rz(yaw) (p_b - pivot) in the world. The point methods take and return
    (3,) m; ``base_pose`` is (x m, y m, yaw rad).
    """

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_model(cls, robot: Robot | str) -> ArmMount:
        """The mount of a mobile model: the pose of the arm's root body (the base body's child
        that carries the arm joints) with every joint at zero.

        Args:
            robot: a model with base joints ``base_x``, ``base_y``, ``base_yaw`` (or its name).

        Returns:
            The mount; identity (arm frame = world) for a model without base joints.

        Raises:
            ModelError: only some base joints, base joints on several bodies or of the wrong
                kind, or an arm not carried by the base body.
        """
        robot = load_robot(robot)
        names = robot.joint_names
        if not any(b in names for b in BASE_JOINTS):
            return cls()
        if not all(b in names for b in BASE_JOINTS):
            raise ModelError(f"{robot.name} has only some of the base joints {BASE_JOINTS}")
        m = robot.model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, b) for b in BASE_JOINTS]
        base_body = int(m.jnt_bodyid[jid[0]])
        if any(int(m.jnt_bodyid[j]) != base_body for j in jid):
            raise ModelError(f"{robot.name}: the base joints must all move one body")
        _check_base_joints(robot, m, d, jid)
        arm_joint = arm_joint_indices(robot)[0]
        body = int(m.jnt_bodyid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, names[arm_joint])])
        root = body
        while int(m.body_parentid[root]) != base_body:
            root = int(m.body_parentid[root])
            if root == 0:
                raise ModelError(f"{robot.name}: the arm is not carried by the base body")
        pivot = np.array([*d.xanchor[jid[2]][:2], 0.0])
        return cls(d.xpos[root].copy(), d.xmat[root].reshape(3, 3).copy(), pivot)

    def __post_init__(self) -> None:
        for name in ("position", "rotation", "pivot"):
            object.__setattr__(self, name, np.array(getattr(self, name), dtype=float))
        object.__setattr__(self, "_identity", bool(np.array_equal(self.rotation, np.eye(3))))
        object.__setattr__(self, "_no_pivot", not self.pivot.any())

    @property
    def identity_rotation(self) -> bool:
        """Whether the arm frame's axes are the base frame's."""
        return self._identity

    # ---- poses
    def arm_pose(self, base_pose) -> tuple[np.ndarray, np.ndarray]:
        """The arm frame in the world with the base at ``base_pose``.

        Args:
            base_pose: The base's odometry pose (x m, y m, yaw rad).

        Returns:
            (origin (3,) m, rotation (3, 3)), world frame.
        """
        r = rz(float(base_pose[2]))
        origin = self._base_origin(base_pose) + r @ self.position
        return origin, r @ self.rotation

    def _base_origin(self, base_pose) -> np.ndarray:
        """World position of the base frame's origin at ``base_pose``."""
        if self._no_pivot:
            return np.array([base_pose[0], base_pose[1], 0.0])
        r = rz(float(base_pose[2]))
        return np.array([base_pose[0], base_pose[1], 0.0]) + self.pivot - r @ self.pivot

    # ---- points
    def base_to_world(self, p, base_pose) -> np.ndarray:
        """A point of the base frame in the world.

        Args:
            p: (3,) m, base frame.
            base_pose: The base's odometry pose (x m, y m, yaw rad).

        Returns:
            (3,) m, world frame.
        """
        return self._base_origin(base_pose) + rz(float(base_pose[2])) @ p

    def world_to_base(self, p, base_pose) -> np.ndarray:
        """A world point ``p`` (3,) m in the base frame, (3,) m: ``base_to_world`` inverted.

        Args:
            p, base_pose: as for ``base_to_world``, ``p`` in the world frame.
        """
        return rz(float(base_pose[2])).T @ (p - self._base_origin(base_pose))

    def arm_to_base(self, p) -> np.ndarray:
        """A point of the arm frame in the base frame.

        Args:
            p: (3,) m, arm frame.

        Returns:
            (3,) m, base frame.
        """
        if self._identity:
            return self.position + p
        return self.position + self.rotation @ p

    def base_to_arm(self, p) -> np.ndarray:
        """A point ``p`` (3,) m of the base frame in the arm frame, (3,) m: ``arm_to_base``
        inverted.

        Args:
            p: (3,) m, base frame.
        """
        return self.rotation.T @ (p - self.position)

    def arm_to_world(self, p, base_pose) -> np.ndarray:
        """A point ``p`` (3,) m of the arm frame in the world, (3,) m.

        Args:
            p, base_pose: as for ``base_to_world``, ``p`` in the arm frame.
        """
        return self.base_to_world(self.arm_to_base(p), base_pose)

    def world_to_arm(self, p, base_pose) -> np.ndarray:
        """A world point ``p`` (3,) m in the arm frame, (3,) m: ``arm_to_world`` inverted.

        Args:
            p, base_pose: as for ``base_to_world``, ``p`` in the world frame.
        """
        return self.base_to_arm(self.world_to_base(p, base_pose))


def _check_base_joints(robot: Robot, m: mujoco.MjModel, d: mujoco.MjData, jid: list[int]) -> None:
    """ModelError unless the base joints are slides along world x, y and a hinge about z."""
    axes = [d.xaxis[j] for j in jid]
    types = [int(m.jnt_type[j]) for j in jid]
    slide, hinge = mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE
    expect = [(slide, [1, 0, 0]), (slide, [0, 1, 0]), (hinge, [0, 0, 1])]
    for j, (ty, ax), (want_ty, want_ax) in zip(
        jid, zip(types, axes, strict=True), expect, strict=True
    ):
        if ty != want_ty or not np.allclose(ax, want_ax, atol=1e-9):
            raise ModelError(
                f"{robot.name}: base joint {m.joint(j).name} must be a "
                f"{'slide' if want_ty == slide else 'hinge'} along world {want_ax}"
            )


def arm_model(robot: Robot | str) -> Robot:
    """The arm-alone model the controllers work in.

    Args:
        robot: a model (or its name), with or without base joints.

    Returns:
        ``robot`` itself without base joints, else the model named by its ``jaxcomp_arm_model``
        custom text (``mobile_gen3_lite`` -> ``gen3_lite``), reduced to the same
        current-controlled joints.

    Raises:
        ModelError: base joints without a ``jaxcomp_arm_model``, or an arm model that does
            not load or has other joints.
    """
    robot = load_robot(robot)
    if not any(b in robot.joint_names for b in BASE_JOINTS):
        return robot
    name = robot.custom_text("jaxcomp_arm_model")
    if name is None:
        raise ModelError(
            f"{robot.name} has base joints; name its arm-alone model in a custom text "
            "'jaxcomp_arm_model'"
        )
    want = tuple(robot.joint_names[j] for j in arm_joint_indices(robot))
    try:
        arm = load_robot(name, joints=want)
    except ModelError as exc:
        raise ModelError(f"{robot.name}'s arm model {name}: {exc}") from None
    if arm.joint_names != want:
        raise ModelError(f"{arm.name}'s joints {arm.joint_names} are not {robot.name}'s {want}")
    return arm


def mobile_model_name(robot: Robot) -> str:
    """The name of the model of the whole mobile manipulator that carries ``robot``'s arm.

    Args:
        robot: the arm's model.

    Returns:
        Its ``jaxcomp_mobile_model`` custom text (``gen3_lite`` -> ``mobile_gen3_lite``), else
        ``robot``'s own name.
    """
    return robot.custom_text("jaxcomp_mobile_model") or robot.name


def check_site_mobility(robot: Robot, q: np.ndarray, site: str) -> None:
    """Refuse a pose where the joints do not move ``site`` in all three directions: the
    position Jacobian's smallest singular value must be at least ``MIN_MOBILITY`` of its
    largest (the Cartesian controllers need a position task of rank 3).

    Args:
        robot: the arm-alone model.
        q: (n,) rad, its joint positions.
        site: the end-effector site's name.

    Raises:
        InputError: the Jacobian has rank below 3 at ``q``.
    """
    sv = np.linalg.svd(np.asarray(robot.jacobian(q, site))[:3], compute_uv=False)
    rank = int(np.sum(sv > MIN_MOBILITY * sv[0])) if sv[0] > 0 else 0
    if rank < 3:
        raise InputError(
            f"the joints of {robot.name} ({', '.join(robot.joint_names)}) move its end effector "
            f"{site!r} in only {rank} of 3 directions at the start pose (position Jacobian "
            f"singular values {', '.join(f'{v:.3g}' for v in sv)} m/rad): Cartesian control "
            "needs 3; choose another end-effector site (--site) or other joints (--joints)"
        )


__all__ = [
    "MIN_MOBILITY",
    "ArmMount",
    "arm_model",
    "check_site_mobility",
    "mobile_model_name",
    "rz",
]
