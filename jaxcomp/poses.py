"""Poses chosen on a model that names none: the rest pose and the controller's start pose.

Units: rad (hinge) or m (slide), one entry per joint of the (reduced) robot, world frame for
positions.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics

if TYPE_CHECKING:
    from jaxcomp.robot import Robot

#: Held and rest positions sit this fraction of a joint's range inside its limits.
LIMIT_MARGIN = 0.05
#: Start-pose candidates keep every limited joint this fraction of its range from its limits.
START_MARGIN = 0.2
#: rad: continuous joints' start-pose candidates lie within this of their rest angle.
CONTINUOUS_SPAN = np.pi / 2
#: Candidate poses the start-pose search scores.
START_CANDIDATES = 4096
#: Most of an effort limit that gravity may take at the start pose.
START_EFFORT_FRACTION = 0.5


def inside_limits(q: np.ndarray, limits: np.ndarray, margin: float = LIMIT_MARGIN) -> np.ndarray:
    """``q`` (n,) moved inside ``limits`` (n, 2) by ``margin`` of each finite range.

    Args:
        q: (n,) joint positions, rad or m.
        limits: (n, 2) lower and upper limits, rad or m (inf where unlimited).
        margin: fraction of each finite range to keep from its limits.

    Returns:
        (n,) rad or m, ``q`` clipped into the shrunk ranges.
    """
    lo, hi = limits[:, 0], limits[:, 1]
    finite = np.isfinite(lo) & np.isfinite(hi)
    span = np.where(finite, hi - lo, 0.0)
    lo_in = np.where(finite, lo + margin * span, lo)
    hi_in = np.where(finite, hi - margin * span, hi)
    return np.clip(q, lo_in, hi_in)


def rest_pose(robot: Robot) -> np.ndarray:
    """The model's ``qpos0`` (its reference pose) moved inside the joint limits, (nv,).

    Args:
        robot: the model.

    Returns:
        (nv,) rad or m.
    """
    return inside_limits(robot.tree.joint_ref.copy(), robot.joint_limits)


def _candidates(robot: Robot, count: int, rng: np.random.Generator) -> np.ndarray:
    limits, rest = robot.joint_limits, rest_pose(robot)
    finite = np.all(np.isfinite(limits), axis=1)
    span = np.where(finite, limits[:, 1] - limits[:, 0], 0.0)
    lo = np.where(finite, limits[:, 0] + START_MARGIN * span, rest - CONTINUOUS_SPAN)
    hi = np.where(finite, limits[:, 1] - START_MARGIN * span, rest + CONTINUOUS_SPAN)
    hi = np.maximum(hi, lo)
    return lo + rng.uniform(size=(count, robot.nv)) * (hi - lo)


def start_pose_scores(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Score (k,) of candidate poses ``q`` (k, nv) for the controller's start: the smallest
    singular value of the end effector's position Jacobian (m/rad, the distance from a position
    singularity) over the arm's reach, times the distance to the nearest limit (fraction of the
    range, saturating at ``START_MARGIN``). Poses with the end effector below the first joint,
    or whose gravity torque takes more than ``START_EFFORT_FRACTION`` of an effort limit,
    score -1.

    Args:
        robot: the model (its end-effector site, nominal inertials and default gravity).
        q: (k, nv) candidate poses, rad or m.

    Returns:
        (k,) scores, 1/rad (higher is better), -1 for refused poses.
    """
    tree, site = robot.tree, robot.site_index(robot.end_effector)
    params, g = robot.nominal_params(), jnp.asarray(robot.default_gravity)

    def one(qi):
        jac = dynamics.site_jacobian(tree, qi, site)[:3]
        pos = dynamics.site_pose(tree, qi, site)[0]
        return jnp.linalg.svd(jac, compute_uv=False), pos, dynamics.gravity(tree, qi, params, g)

    fn = robot.cached(("jit", "start_pose_terms"), lambda: jax.jit(jax.vmap(one)))
    sv, pos, grav = (np.asarray(x) for x in fn(jnp.asarray(q)))
    rank = min(3, robot.nv)
    # the generic rank: how many singular values are clearly nonzero somewhere
    rank = max(1, min(rank, int(np.sum(np.max(sv, axis=0) > 1e-6 * np.max(sv)))))
    reach = max(float(np.max(np.linalg.norm(pos - pos.mean(0), axis=1))), 1e-3)
    limits = robot.joint_limits
    finite = np.all(np.isfinite(limits), axis=1)
    span = np.where(finite, limits[:, 1] - limits[:, 0], 1.0)
    room = np.minimum(q - limits[:, 0], limits[:, 1] - q) / span
    room = np.where(finite, np.minimum(room, START_MARGIN) / START_MARGIN, 1.0).min(axis=1)
    score = sv[:, rank - 1] / reach * room
    floor = float(np.asarray(robot.forward_kinematics(rest_pose(robot)).anchor)[0, 2])
    effort = robot.effort_limits
    overload = np.any(np.abs(grav) > START_EFFORT_FRACTION * effort, axis=1)
    return np.where((pos[:, 2] < floor) | overload, -1.0, score)


def start_pose(robot: Robot, count: int = START_CANDIDATES, seed: int = 0) -> np.ndarray:
    """A start pose (nv,) for the controller chosen on the model: of ``count`` random poses
    away from the limits, the best by ``start_pose_scores`` (well away from singularities and
    limits, end effector above the first joint, gravity within half the effort limits).

    Args:
        robot: the model.
        count: how many random candidate poses to score.
        seed: seed of the candidates' random generator.

    Returns:
        (nv,) rad or m.
    """
    q = _candidates(robot, count, np.random.default_rng(seed))
    return q[int(np.argmax(start_pose_scores(robot, q)))].copy()
