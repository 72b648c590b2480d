"""The reference Cartesian velocity controller (non-compliant: the robot's default mode).

At joint positions q (rad), for a target position x_d (m) and velocity xd_d (m/s) of a site in
the arm's base frame:

    v  = K_p clip(x_d - x) + xd_d,  its norm limited to max_speed
    dq = dq_n + J^+ (v - J dq_n),  dq_n = k_n (q_pref - q),  J^+ = J^T (J J^T + lambda^2 I)^-1

then scaled down uniformly (direction kept) until no joint exceeds its velocity limit. The
result is a joint velocity command (rad/s) for the arm's VELOCITY mode.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import checks, dynamics
from jaxcomp.control.gains import VelocityGains
from jaxcomp.control.impedance_io import (
    packed_size,
    unpack_state,
)
from jaxcomp.control.linalg import damped_pinv
from jaxcomp.robot import Robot


class VelocityDiagnostics(NamedTuple):
    """Packed (..., 7): ee_pos (3) m | error (3) m (x_d - x, clipped) | scale (1)."""

    data: jax.Array | np.ndarray

    @property
    def ee_pos(self):
        """(3,) m, the site's position in the arm's base frame."""
        return self.data[..., 0:3]

    @property
    def error(self):
        """(3,) m, x_d - x after the norm clip."""
        return self.data[..., 3:6]

    @property
    def scale(self):
        """() factor (<= 1) the joint velocities were scaled by to respect their limits."""
        return self.data[..., 6]


def velocity_step_fn(robot: Robot, gains: VelocityGains, site: str | None = None):
    """The pure (unjitted) step function.

    Args:
        robot: the arm-alone model (arm base frame).
        gains: the ``VelocityGains``.
        site: the end-effector site; default the robot's end effector.

    Returns:
        ``step(q, target_pos, target_vel) -> (dq (n,) rad/s, VelocityDiagnostics)``, as
        ``VelocityController.step``.
    """
    tree, s = robot.tree, robot.site_index(robot.end_effector if site is None else site)
    posture, k_n, _, limit = gains.joint_arrays(robot)
    k_p, lam2 = np.asarray(gains.gain), gains.pinv_damping**2
    clip, max_speed = gains.error_clip, gains.max_speed

    def step(q, target_pos, target_vel):
        kd = dynamics.kinematics_and_dynamics(tree, q, s)  # XLA drops the unused g and M
        pos, jac = kd.position, kd.jacobian[:3]
        err = target_pos - pos
        err = err * (clip / jnp.maximum(jnp.linalg.norm(err), clip))
        v = k_p * err + target_vel
        v = v * (max_speed / jnp.maximum(jnp.linalg.norm(v), max_speed))
        dq_null = k_n * (posture - q)
        dq = dq_null + damped_pinv(jac, lam2) @ (v - jac @ dq_null)
        scale = 1.0 / jnp.maximum(jnp.max(jnp.abs(dq) / limit), 1.0)
        return dq * scale, VelocityDiagnostics(jnp.concatenate([pos, err, scale[None]]))

    return step


def velocity_packed_fn(step_fn, n: int):
    """``step_fn`` on the impedance controller's packed input (only q, pos and vel are used).

    Args:
        step_fn: a ``velocity_step_fn`` step.
        n: joints.

    Returns:
        ``packed(x) -> y``: x as ``impedance_io.packed_size(n)``, y dq (n) rad/s |
        ``VelocityDiagnostics.data`` (7).
    """

    def packed(x):
        s = unpack_state(x, n, False)
        dq, diag = step_fn(s.q, s.pos, s.vel)
        return jnp.concatenate([dq, diag.data])

    return packed


class VelocityController:
    """Reference Cartesian velocity controller (see module doc).

    Args:
        robot: the arm-alone model (arm base frame).
        gains: default ``VelocityGains()``.
        site: the end-effector site; default the robot's end effector.

    Attributes:
        robot, gains, site, n.
        step: jitted pure ``step(q, target_pos, target_vel) -> (dq (n,) rad/s,
            VelocityDiagnostics)``; q rad (n,), target_pos m (3,), target_vel m/s (3,), arm
            base frame; device arrays, no checks (``check_state`` makes checked ones).
        step_fn: the same function unjitted.
        packed_step: jitted ``packed_step(x) -> y`` for the 1 kHz loop: x packed as the
            impedance controller's (``packed_size``), y = dq (n) | diagnostics data (7).
    """

    def __init__(self, robot: Robot, gains: VelocityGains | None = None, site: str | None = None):
        site = robot.end_effector if site is None else site
        self.robot, self.site, self.n = robot, site, robot.nv
        self.gains = VelocityGains() if gains is None else gains
        self.step_fn = velocity_step_fn(robot, self.gains, site)
        self.step = jax.jit(self.step_fn)
        self.packed_size = packed_size(self.n)
        self.packed_step = jax.jit(velocity_packed_fn(self.step_fn, self.n))

    def check_state(self, q, target_pos, target_vel=None) -> tuple:
        """Validated device arrays for ``step``.

        Args:
            q: Joint angles, (n,) rad.
            target_pos: (3,) m, arm base frame.
            target_vel: (3,) m/s, arm base frame (None: zeros).

        Returns:
            The arguments of ``step``.

        Raises:
            InputError: naming a bad input.
        """
        return (
            jnp.asarray(checks.array(q, "q (rad)", n=self.n, labels=self.robot.joint_names)),
            jnp.asarray(checks.array(target_pos, "target_pos", n=3, unit="m")),
            jnp.asarray(
                np.zeros(3)
                if target_vel is None
                else checks.array(target_vel, "target_vel", n=3, unit="m/s")
            ),
        )

    def checked_step(self, q, target_pos, target_vel=None):
        """``step`` after ``check_state``.

        Args:
            q: Joint angles, (n,) rad.
            target_pos: (3,) m, arm base frame.
            target_vel: (3,) m/s, arm base frame (None: zeros).

        Returns:
            (dq (n,) rad/s, VelocityDiagnostics).

        Raises:
            InputError: naming a bad input.
        """
        return self.step(*self.check_state(q, target_pos, target_vel))


def make_velocity_controller(
    robot: Robot, gains: VelocityGains | None = None, site: str | None = None
) -> VelocityController:
    """A ``VelocityController`` for ``robot``.

    Args:
        robot: the arm's own model (arm base frame).
        gains: default ``VelocityGains()``.
        site: default the robot's end effector.

    Returns:
        The controller.
    """
    return VelocityController(robot, gains, site)
