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
    """Each joint's effective inertia range and largest gravity load over ``poses`` (P, n) rad,
    for every world of ``params`` (W, ...) under its ``gravity`` (W, 3) m/s^2:
    I_min = min over poses of 1 / (M^-1)_jj, I_max = max of M_jj (kg m^2) and max |g_j| (N m),
    (W, n) each."""

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
    """Per-world (I_min, I_max, largest gravity load) (W, n) over ``servo.gain_poses``
    (``servo_sizing``, batched and compiled once per robot). ``params``: (W, ...) inertial
    params; ``gravity`` (W, 3) m/s^2, each world's."""
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
    """Per-world position-servo gains (kp, kv) (W, n) as ``Simulator._gains`` computes them
    (``hardware.servo.pd_gains`` of ``servo_loads``); ``bandwidth`` rad/s."""
    return pd_gains(*servo_loads(robot, params, gravity), bandwidth)
