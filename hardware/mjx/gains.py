"""Position-servo gains of the MJX worlds, as the CPU ``Simulator`` computes its own.

``servo_gains`` gives each world the gains ``Simulator._gains`` would give its true robot:
from the range of every joint's effective inertia over 64 poses (the zero pose, then poses
drawn from ``default_rng(0)`` within the joint limits), with jaxcomp's mass matrix batched over
worlds and poses. The compiled inertia-range function is kept on the robot (``Robot.cached``).
Units: kg m^2, N m/rad, N m s/rad, rad/s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams
from jaxcomp.robot import Robot
from jaxcomp.robot_params import arm_joint_indices

GAIN_POSES = 64  # poses the CPU Simulator samples for its servo gains
GAIN_BATCH = 1024  # worlds per mass-matrix batch of the gain computation


def inertia_range(
    tree: KinematicTree, params: InertialParams, poses: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Each joint's effective inertia range over ``poses`` (P, n) rad, for every world of
    ``params`` (W, ...): I_min = min over poses of 1 / (M^-1)_jj and I_max = max of M_jj,
    (W, n) kg m^2 each."""
    mm = jax.vmap(
        jax.vmap(lambda p1, q1: dynamics.mass_matrix(tree, q1, p1), (None, 0)), (0, None)
    )(params, poses)
    i_min = (1.0 / jnp.diagonal(jnp.linalg.inv(mm), axis1=-2, axis2=-1)).min(axis=1)
    i_max = jnp.diagonal(mm, axis1=-2, axis2=-1).max(axis=1)
    return i_min, i_max


def servo_gains(
    robot: Robot, params: InertialParams, bandwidth: float = 500.0
) -> tuple[np.ndarray, np.ndarray]:
    """Per-world position-servo gains (W, n) as ``Simulator._gains`` computes them.

    Over the zero pose and 63 poses drawn from ``default_rng(0)`` within the joint limits
    (-pi .. pi for a continuous joint):
    I_min = min 1 / (M^-1)_jj, I_max = max M_jj; kp = I_min bandwidth^2 N m/rad,
    kv = 2 sqrt(kp sqrt(I_min I_max)) N m s/rad. ``params``: (W, ...) inertial params;
    ``bandwidth`` rad/s.
    """
    lim = np.clip(robot.joint_limits[arm_joint_indices(robot)], -np.pi, np.pi)  # continuous
    rng = np.random.default_rng(0)
    n = lim.shape[0]
    poses = np.stack(
        [np.zeros(n)] + [rng.uniform(lim[:, 0], lim[:, 1]) for _ in range(GAIN_POSES - 1)]
    )
    tree = robot.tree
    bounds = robot.cached(
        ("mjx_inertia_range",), lambda: jax.jit(lambda p, q: inertia_range(tree, p, q))
    )
    w = params.mass.shape[0]
    b = min(w, GAIN_BATCH)
    i_min, i_max = np.zeros((w, n)), np.zeros((w, n))
    for s in range(0, w, b):
        idx = np.minimum(np.arange(s, s + b), w - 1)  # last batch padded with the last world
        lo, hi = bounds(jax.tree_util.tree_map(lambda a, idx=idx: a[idx], params), poses)
        k = min(b, w - s)
        i_min[s : s + k], i_max[s : s + k] = np.asarray(lo)[:k], np.asarray(hi)[:k]
    kp = i_min * bandwidth**2
    kv = 2.0 * np.sqrt(kp * np.sqrt(i_min * i_max))
    return kp, kv
