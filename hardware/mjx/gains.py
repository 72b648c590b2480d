"""Position-servo gains of the MJX worlds, as the CPU ``Simulator`` computes its own.

``servo_gains`` gives each world the gains ``Simulator._gains`` would give its true robot
(``hardware.servo.pd_gains``): from every joint's effective inertia range and largest gravity
torque over ``servo.gain_poses``, with jaxcomp's mass matrix and gravity batched over worlds
and poses. The compiled function is kept on the robot (``Robot.cached``).
Units: kg m^2, N m, N m/rad, N m s/rad, rad/s, m/s^2.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.hardware.servo import gain_poses, pd_gains
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams
from jaxcomp.robot import Robot
from jaxcomp.robot_params import arm_joint_indices

GAIN_BATCH = 1024  # worlds per batch of the gain computation


def servo_sizing(
    tree: KinematicTree, params: InertialParams, gravity: jax.Array, poses: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Each joint's effective inertia range and largest gravity load over ``poses``, per world:
    I_min = min over poses of 1 / (M^-1)_jj, I_max = max of M_jj, max |g_j|.

    Args:
        tree: the robot's kinematic tree. params: the worlds' inertial params (W, ...).
        gravity: (W, 3) m/s^2, each world's, in the base (world) frame.
        poses: (P, n) rad.

    Returns:
        (I_min kg m^2, I_max kg m^2, largest gravity load N m), (W, n) each.
    """

    def world(p1, g1):
        mm = jax.vmap(lambda q1: dynamics.mass_matrix(tree, q1, p1))(poses)
        grav = jax.vmap(lambda q1: dynamics.gravity(tree, q1, p1, g1))(poses)
        i_min = (1.0 / jnp.diagonal(jnp.linalg.inv(mm), axis1=-2, axis2=-1)).min(axis=0)
        i_max = jnp.diagonal(mm, axis1=-2, axis2=-1).max(axis=0)
        return i_min, i_max, jnp.abs(grav).max(axis=0)

    return jax.vmap(world)(params, gravity)


def servo_loads(
    robot: Robot, params: InertialParams, gravity: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``servo_sizing`` over ``servo.gain_poses``, batched and compiled once per robot.

    Args:
        robot: the arm. params: the worlds' inertial params (W, ...).
        gravity: (3,) or (W, 3) m/s^2, in the base (world) frame.

    Returns:
        (I_min kg m^2, I_max kg m^2, largest gravity load N m), (W, n) each.
    """
    poses = gain_poses(robot.joint_limits[arm_joint_indices(robot)])
    tree = robot.tree
    sizing = robot.cached(
        ("mjx_servo_sizing",),
        lambda: jax.jit(lambda p, g, q: servo_sizing(tree, p, g, q)),
    )
    w, n = params.mass.shape[0], poses.shape[1]
    gravity = np.broadcast_to(np.asarray(gravity, float), (w, 3))
    b = min(w, GAIN_BATCH)
    i_min, i_max, load = np.zeros((w, n)), np.zeros((w, n)), np.zeros((w, n))
    for s in range(0, w, b):
        idx = np.minimum(np.arange(s, s + b), w - 1)  # last batch padded with the last world
        got = sizing(jax.tree_util.tree_map(lambda a, idx=idx: a[idx], params), gravity[idx], poses)
        k = min(b, w - s)
        for out, value in zip((i_min, i_max, load), got, strict=True):
            out[s : s + k] = np.asarray(value)[:k]
    return i_min, i_max, load


def servo_gains(
    robot: Robot, params: InertialParams, gravity: np.ndarray, bandwidth: float = 500.0
) -> tuple[np.ndarray, np.ndarray]:
    """Per-world position-servo gains as the CPU ``Simulator`` computes its own
    (``hardware.servo.pd_gains`` of ``servo_loads``).

    Args:
        robot: the arm. params: the worlds' inertial params (W, ...).
        gravity: (3,) or (W, 3) m/s^2, in the base (world) frame. bandwidth: rad/s.

    Returns:
        (kp N m/rad, kv N m s/rad), (W, n) each.
    """
    return pd_gains(*servo_loads(robot, params, gravity), bandwidth)
