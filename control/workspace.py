"""The arm's reach, from its kinematic chain, and the check that a run's targets lie within it.

The joints that move the end-effector site form a chain j_1 ... j_k from the arm's base. A
hinge turns everything after it about an axis through its anchor, so the distance from its
anchor to the next joint's anchor (or to the site) never changes; a slide changes it by at
most its travel. Their sum, ``Reach.radius``, bounds the distance from the first joint's
anchor, ``Reach.origin`` (fixed in the arm's base frame), to the site at every joint position:
a target farther than that cannot be reached (the bound is tight for the built-in arms, within
about 1 % of the farthest sampled pose). Frames: the arm's base frame (the arm model's world),
m.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from jaxcomp.control.trajectory import Trajectory
from jaxcomp.errors import InputError
from jaxcomp.robot import Robot


@dataclass(frozen=True)
class Reach:
    """Where the end effector can be: within ``radius`` m (``inf``: an unlimited slide) of
    ``origin`` (3,) m, the anchor of the first joint that moves it (arm base frame)."""

    origin: np.ndarray
    radius: float


def arm_reach(robot: Robot, site: str) -> Reach:
    """The reach of ``robot``'s site ``site`` (see the module doc).

    Args:
        robot: The arm-alone model.
        site: The end-effector site's name.

    Returns:
        Its ``Reach``, arm base frame.

    Raises:
        InputError: an unknown site.
    """
    robot.site_index(site)  # InputError for an unknown site
    m = robot.model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
    body = int(m.site_bodyid[s]) - 1  # tree bodies exclude the world
    chain = [j for j in range(robot.nv) if body >= 0 and robot.tree.moves[j, body]]
    if not chain:
        return Reach(d.site_xpos[s].copy(), 0.0)
    points = np.array([d.xanchor[j] for j in chain] + [d.site_xpos[s]])
    radius = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
    for j in chain:
        if not robot.tree.is_hinge[j]:  # a slide: plus its travel from where it was measured
            lo, hi = robot.joint_limits[j]
            q0 = float(d.qpos[m.jnt_qposadr[j]])
            radius += max(abs(hi - q0), abs(q0 - lo))
    return Reach(points[0].copy(), radius)


def check_reachable(traj: Trajectory, until: float, origin, radius: float, name: str) -> None:
    """Refuse a trajectory whose target gets beyond the arm's reach.

    Args:
        traj: The trajectory.
        until: s, the end of the run.
        origin: The ``Reach`` origin, (3,) m, in the trajectory's frame.
        radius: The ``Reach`` radius, m.
        name: The arm's model name (messages).

    Raises:
        InputError: the target over [0, until] s gets farther than ``radius`` from
            ``origin``.
    """
    origin = np.asarray(origin, dtype=float)
    far = traj.farthest(origin, until)
    distance = float(np.linalg.norm(far - origin))
    if distance > radius + 1e-9:
        where = ", ".join(f"{v:.3f}" for v in far)
        base = ", ".join(f"{v:.3f}" for v in origin)
        raise InputError(
            f"the target reaches ({where}) m, {distance:.3f} m from the base of {name}'s arm at "
            f"({base}) m: beyond its reach of {radius:.3f} m (the sum of its links' lengths); "
            "choose a smaller or nearer trajectory"
        )


__all__ = ["Reach", "arm_reach", "check_reachable"]
