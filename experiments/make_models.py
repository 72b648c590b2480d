"""Compute the derived numbers typed into jaxcomp/models/gen3_lite.xml.

The MJCF files are written by hand; this script only does the arithmetic that is tedious by
hand and prints it, so that the figures in the XML can be re-derived and checked:

* body quaternions from the URDF joint-origin rpy angles,
* LOWER_WRIST's inertia tensor rotated from its inertial frame (rpy 0 0.785398 0) into the body
  frame,
* GRIPPER_FRAME with the four finger links (fixed joints, point masses at their frame origins)
  folded in: mass, centre of mass, inertia about the new centre of mass.

Figures are those of the paper authors' calibrated Gen3 Lite description (see
shared/reference/FIGURES.md). Run: ``python experiments/make_models.py``.
"""

from __future__ import annotations

import numpy as np


def rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(y) @ Ry(p) @ Rx(r)."""
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def rpy_quat(r: float, p: float, y: float) -> np.ndarray:
    """Same rotation as a unit quaternion (w, x, y, z), MuJoCo's convention."""
    cr, sr = np.cos(r / 2), np.sin(r / 2)
    cp, sp = np.cos(p / 2), np.sin(p / 2)
    cy, sy = np.cos(y / 2), np.sin(y / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def sym(ixx, iyy, izz, ixy, ixz, iyz) -> np.ndarray:
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def full(i: np.ndarray) -> str:
    """MJCF fullinertia order: Ixx Iyy Izz Ixy Ixz Iyz."""
    return " ".join(f"{v:.10g}" for v in (i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]))


# Joint origins (xyz, rpy) of the six revolute joints.
JOINT_ORIGINS = {
    "SHOULDER": ((0, 0, 0.12825), (0, 0, 0)),
    "ARM": ((0, -0.03, 0.115), (1.5708, 0, 0)),
    "FOREARM": ((0, 0.28, 0), (-3.1416, 0, 0)),
    "LOWER_WRIST": ((0, -0.14, 0.02), (1.5708, 0, 0)),
    "UPPER_WRIST": ((0.0285, 0, 0.105), (0, 1.5708, 0)),
    "GRIPPER_FRAME": ((-0.105, 0, 0.0285), (0, -1.5708, 0)),
}

# LOWER_WRIST inertial: tensor given in a frame rotated by rpy (0, 0.785398, 0).
LW_INERTIA = sym(0.00069098, 0.00078519, 0.00034115, -0.00000024, 0.00016483, 0.00000074)
LW_RPY = (0, 0.785398, 0)

# GRIPPER_FRAME's own inertial.
G_MASS = 0.1395
G_COM = np.array([-0.00000403, 0.0000108, 0.04139748])
G_INERTIA = sym(0.00011614, 0.00010327, 0.00009707, -0.00000001, -0.00000004, 0.0)

# Finger chain: (mass, [(xyz, rpy), ...] from GRIPPER_FRAME to the finger link frame).
FINGERS = {
    "RIGHT_FINGER_PROX": (0.018385, [((0, -0.030501, 0.070003), (0, 1.5708, 0))]),
    "RIGHT_FINGER_DIST": (
        0.010748,
        [((0, -0.030501, 0.070003), (0, 1.5708, 0)), ((-0.045636, 0.020423, 0), (0, 0, 0))],
    ),
    "LEFT_FINGER_PROX": (0.018385, [((0, 0.0305, 0.070003), (0, 1.5708, 0))]),
    "LEFT_FINGER_DIST": (
        0.010748,
        [((0, 0.0305, 0.070003), (0, 1.5708, 0)), ((-0.045636, -0.020423, 6.9901e-05), (0, 0, 0))],
    ),
}


def chain(origins) -> np.ndarray:
    """Origin of the last frame of a chain of (xyz, rpy) transforms, in the first frame."""
    pos, rot = np.zeros(3), np.eye(3)
    for xyz, rpy in origins:
        pos = pos + rot @ np.asarray(xyz, float)
        rot = rot @ rpy_matrix(*rpy)
    return pos


def fold_gripper():
    """Mass, COM and inertia about the COM of GRIPPER_FRAME plus the finger point masses."""
    masses = [G_MASS] + [m for m, _ in FINGERS.values()]
    points = [G_COM] + [chain(c) for _, c in FINGERS.values()]
    mass = float(np.sum(masses))
    com = np.sum([m * p for m, p in zip(masses, points, strict=True)], axis=0) / mass

    def shift(m, d):  # parallel-axis term of a point mass m at offset d
        return m * (np.dot(d, d) * np.eye(3) - np.outer(d, d))

    inertia = G_INERTIA + shift(G_MASS, G_COM - com)
    for (m, _), p in zip(FINGERS.values(), points[1:], strict=True):
        inertia = inertia + shift(m, p - com)
    return mass, com, inertia, dict(zip(FINGERS, points[1:], strict=True))


def main() -> None:
    np.set_printoptions(precision=10, suppress=False)
    print("body quaternions (w x y z):")
    for body, (xyz, rpy) in JOINT_ORIGINS.items():
        q = rpy_quat(*rpy)
        print(f"  {body:14s} pos={xyz} quat=" + " ".join(f"{v:.10g}" for v in q))

    r = rpy_matrix(*LW_RPY)
    lw = r @ LW_INERTIA @ r.T
    print("LOWER_WRIST fullinertia in body frame:", full(lw))

    mass, com, inertia, points = fold_gripper()
    print("finger frame origins in GRIPPER_FRAME:")
    for name, p in points.items():
        print(f"  {name:18s}", " ".join(f"{v:.8g}" for v in p))
    print(f"GRIPPER_FRAME folded: mass={mass:.10g}")
    print("  pos=" + " ".join(f"{v:.10g}" for v in com))
    print("  fullinertia=" + full(inertia))
    print("  eigenvalues:", np.linalg.eigvalsh(inertia))


if __name__ == "__main__":
    main()
