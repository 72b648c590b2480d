"""How good is a params set: gravity-current prediction error against a known truth.

What the controller needs from identification is the current that holds the arm,
``ratio * g(q)`` per joint (Eq. 7 with the COM-corrected model); ratios and COM offsets may
trade off along directions no sweep determines, but this product may not.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxcomp import dynamics
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices


def random_poses(robot: Robot, count: int, seed: int = 0) -> np.ndarray:
    """(count, n) rad: poses drawn uniformly within the current-controlled joints' limits."""
    lo, hi = robot.joint_limits[arm_joint_indices(robot)].T
    return np.random.default_rng(seed).uniform(lo, hi, (count, len(lo)))


def gravity_current(robot: Robot, params: RobotParams, poses: np.ndarray) -> np.ndarray:
    """(count, n) A: ratio x g(q) of ``params`` at ``poses`` (arm joints, default gravity)."""
    joints = arm_joint_indices(robot)
    full = np.zeros((len(poses), robot.nv))
    full[:, joints] = poses
    inertial = params.inertial_params(robot)
    g = jax.jit(jax.vmap(lambda q: dynamics.gravity(robot.tree, q, inertial)))(full)
    return np.asarray(g)[:, joints] * params.ratio


def gravity_current_error(
    robot: Robot, truth: RobotParams, fitted: RobotParams, poses: np.ndarray
) -> np.ndarray:
    """(n,) per joint: RMS error of the predicted gravity current over ``poses``, relative to
    the RMS true gravity current (NaN for a joint gravity never loads)."""
    true = gravity_current(robot, truth, poses)
    err = gravity_current(robot, fitted, poses) - true
    scale = np.sqrt((true**2).mean(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(scale > 1e-9, np.sqrt((err**2).mean(0)) / scale, np.nan)
