"""Current-based Cartesian impedance control of the arm (paper Eq. 3-5 and 16).

One control step, at joint positions q (rad) and velocities dq (rad/s), for a target position
x_d (m), velocity xd_d (m/s) and acceleration xdd_d (m/s^2) of a site (default: the end
effector), all in the arm's base frame (the arm's own model, e.g. ``gen3_lite``):

    e   = x_d - x, zeroed when |e| < deadband, its norm clipped to error_clip
    F   = K_d e + D_d (xd_d - J dq)  [+ Lambda xdd_d + mu xd_d  with gains.feedforward]
    tau = J^T F + N^T tau_2 + g(q),  tau_2 = K_n (q_pref - q) - D_n dq  [+ J_w^T m_o]
    c   = r tau + l (a (sign dq - s) + s),  a = min(|dq| / t, 1)   (Eq. 16)
          s = sign(tau) (the paper's), or with gains.friction_direction = "motion"
          s = sign(tau - g(q)), and clip(. / friction_band, -1, 1) for a band > 0;
          then at most current_rate_limit * period from the previous command, then within
          +-current_limit

J is the site's position Jacobian (3, n), g the gravity torque of the identified model
(``RobotParams.inertial_params``: nominal inertials with the calibrated COM offsets),
N^T = I - J^T J_bar^T the dynamically consistent torque projector (J_bar = M^-1 J^T Lambda,
Lambda = (J M^-1 J^T)^-1; Khatib's N = I - J_bar J), r, l the identified ratio (A/(N m)) and
friction loss (A). The optional orientation task m_o = K_o e_o - D_o omega (e_o the rotation
vector from the site's orientation to ``target_rot``, small-angle form) is a secondary task, in
the nullspace of the position task with the posture. Currents are in A.

At rest (|dq| < t) Eq. (16) adds the friction loss l along s, the direction the joint is
expected to move. The paper takes it from tau, which for a gravity-loaded joint is the gravity
torque: such a joint is pushed by l towards its gravity torque whatever the spring asks, so it
moves one way freely and the other way only under 2 l of spring torque (joint 1 of the Gen3
Lite: 2 x 4.8 N m, far beyond a 40 N/m spring). The "motion" direction uses the torque meant to
move the joint (Cartesian force, damping and nullspace torques) instead; gravity compensation
holds the joint and needs no help from it. The band makes s continuous where that torque
crosses zero, instead of flipping +-l from one cycle to the next. The current is
``jaxcomp.current.friction_current`` (Eq. 16 with that direction); g, x, J and M come from one
``jaxcomp.dynamics.kinematics_and_dynamics`` call per step.

Each step also estimates the force a person applies on the end effector from the measured
currents c (``control.external_force``: c_model = r g + a l sign(dq), F = (J^T)^+ (c_model - c)
/ r, and the static-friction band it cannot be resolved within), reported in the diagnostics.
The live gains (K_d, D_d and the friction compensation's factor, on 1 or off 0) are inputs of
the step, defaulting to the gains': a running loop changes them without recompiling.

``make_impedance_controller`` returns an ``ImpedanceController`` whose ``step`` is one pure,
jitted JAX function of device arrays (model constants and identified params folded in), and
``packed_step`` the same on one packed numpy vector (the 1 kHz loop's: ``impedance_io``);
``impedance_pinocchio.ImpedanceControllerPinocchio`` is the same law in pinocchio + numpy (the
latency baseline). Both are an ``ImpedanceLaw``: params checked by
``plausibility.checked_arm_params`` are taken as they are (a cheap guard of their model, shapes
and finiteness); any other params are checked there first.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import checks, dynamics
from jaxcomp.control.external_force import external_force
from jaxcomp.control.gains import ImpedanceGains, JointGains
from jaxcomp.control.impedance_io import (
    LIVE_SIZE,
    Diagnostics,
    live_gains,
    pack_diagnostics,
    packed_size,
    unpack_state,
)
from jaxcomp.control.impedance_terms import (
    clip_error,
    coriolis_times,
    limit_current,
    orientation_error,
)
from jaxcomp.control.linalg import cholesky_solve_lower, inverse3, spd_solve
from jaxcomp.control.presets import impedance_gains
from jaxcomp.current import friction_current
from jaxcomp.errors import InputError
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams
from jaxcomp.plausibility import CheckedParams, checked_arm_params
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams

# ----------------------------------------------------------------------------- the model


class ResolvedModel(NamedTuple):
    """The model a controller is built on, resolved to numpy constants (both implementations).

    ``inertial``: the identified inertials (nominal masses, COM offsets applied), base frame;
    ``gravity_vector`` (3,) m/s^2 in the base frame; ``ratio`` (n,) A/(N m) and ``friction``
    (n,) A of Eq. (16); ``joint``: the expanded per-joint gains. ``impedance_step_fn`` takes
    one, e.g. with other params swapped in by ``_replace``.
    """

    tree: KinematicTree
    site: int
    inertial: InertialParams  # numpy arrays
    gravity_vector: np.ndarray  # (3,) m/s^2
    ratio: np.ndarray
    friction: np.ndarray
    joint: JointGains


class ImpedanceLaw:
    """The impedance law bound to one robot, its params and gains: what both implementations
    (``ImpedanceController``, ``impedance_pinocchio.ImpedanceControllerPinocchio``) are built
    on. Each builds its step in ``_build``.

    Args:
        robot: the arm-alone model (arm base frame).
        params: identified ratio, friction and COM offsets: ``CheckedParams``
            (``plausibility.checked_arm_params``, taken as they are after a cheap guard of
            their model, shapes and finiteness), ``RobotParams`` for ``robot`` (checked here),
            or None (the model's nominal ratios, no friction, nominal COM; checked too).
        gains: default ``impedance_gains(robot, "paper")``.
        site: the end-effector site; default the robot's end effector.

    Raises:
        InputError: gains or params of the wrong type, params for another model, not fitting
            ``robot`` or implausible, or a robot with base joints.

    Attributes:
        robot, params (the checked ``RobotParams``), gains, site (name), n (joints), joint
        (``JointGains``: posture rad, K_n, D_n, current limit A).
        resolved: the ``ResolvedModel`` the step is built on.
    """

    def __init__(
        self,
        robot: Robot,
        params: RobotParams | CheckedParams | None = None,
        gains: ImpedanceGains | None = None,
        site: str | None = None,
    ):
        gains = impedance_gains(robot, "paper") if gains is None else gains
        site = robot.end_effector if site is None else site
        if not isinstance(gains, ImpedanceGains):
            raise InputError(f"gains must be an ImpedanceGains, got {type(gains).__name__}")
        joint = gains.joint_arrays(robot)  # also refuses a robot with base joints
        checked = _checked(robot, params)
        self.resolved = ResolvedModel(
            tree=robot.tree,
            site=robot.site_index(site),
            inertial=InertialParams(*(np.asarray(x, dtype=float) for x in checked.inertial)),
            gravity_vector=np.asarray(robot.default_gravity, dtype=float),
            ratio=checked.params.ratio.copy(),
            friction=checked.params.friction.copy(),
            joint=joint,
        )
        self.robot, self.params, self.gains, self.site = robot, checked.params, gains, site
        self.n = robot.nv
        self.joint = joint
        self._build()

    def _build(self) -> None:
        """Build the implementation's step (after the model is resolved)."""
        raise NotImplementedError


def _checked(robot: Robot, params: RobotParams | CheckedParams | None) -> CheckedParams:
    """``params`` known as checked for ``robot``: guarded when they are, else checked now."""
    if isinstance(params, CheckedParams):
        _guard(params, robot)
        return params
    params = RobotParams.nominal(robot) if params is None else params
    if not isinstance(params, RobotParams):
        raise InputError(
            f"params must be a RobotParams, CheckedParams or None, got {type(params).__name__}"
        )
    if params.model != robot.name:
        raise InputError(f"params are for model {params.model!r}, the robot is {robot.name!r}")
    return checked_arm_params(params, robot)  # nothing implausible reaches the arm


def _guard(checked: CheckedParams, robot: Robot) -> None:
    """InputError unless checked params are for ``robot``: model, shapes, finite numbers."""
    p, inertial, nominal = checked.params, checked.inertial, robot.tree.nominal
    if p.model != robot.name:
        raise InputError(f"params are for model {p.model!r}, the robot is {robot.name!r}")
    n = robot.nv
    shapes = [np.shape(p.ratio), np.shape(p.friction)]
    shapes += [np.shape(x) for x in inertial]
    want = [(n,), (n,)] + [np.shape(x) for x in nominal]
    if shapes != want:
        raise InputError(
            f"the checked params do not fit {robot.name}: shapes {shapes}, expected {want}"
        )
    values = (p.ratio, p.friction, *inertial)
    if not all(np.all(np.isfinite(np.asarray(x))) for x in values):
        raise InputError(f"the checked params for {robot.name} contain NaN or inf")


# ----------------------------------------------------------------------------- the step


def impedance_step_fn(
    res: ResolvedModel, gains: ImpedanceGains
) -> Callable[..., tuple[jax.Array, Diagnostics]]:
    """The pure (unjitted) step function of the controller.

    The rigid-body terms come from one call of ``dynamics.kinematics_and_dynamics`` (g, the
    site's pose and Jacobian and M in one pass); the current from ``current.friction_current``;
    the external force from ``external_force.external_force``.

    Args:
        res: the ``ResolvedModel`` (e.g. ``ImpedanceController.resolved``, or one with other
            params swapped in).
        gains: the ``ImpedanceGains``.

    Returns:
        ``step(q, dq, target_pos, target_vel, target_acc, prev_current[, target_rot]
        [, current][, live]) -> (current (n,) A, Diagnostics)``, as
        ``ImpedanceController.step``.
    """
    tree, site, inertial, grav = res.tree, res.site, res.inertial, res.gravity_vector
    k_d0, d_d0 = np.asarray(gains.stiffness), np.asarray(gains.damping)
    k_o, d_o = np.asarray(gains.orientation_stiffness), np.asarray(gains.orientation_damping)
    q_pref, k_n, d_n, limit = res.joint
    ratio, friction, threshold = res.ratio, res.friction, gains.friction_threshold
    eps = gains.singularity_damping * np.eye(3)
    max_step = gains.max_current_step
    orientation, feedforward = gains.orientation, gains.feedforward
    motion_sign, band = gains.friction_direction == "motion", gains.friction_band

    def step(
        q,
        dq,
        target_pos,
        target_vel,
        target_acc,
        prev_current,
        target_rot=None,
        current=None,
        live=None,
    ):
        kd = dynamics.kinematics_and_dynamics(tree, q, site, inertial, grav)
        jac = kd.jacobian[:3]
        if live is None:  # the gains' own, folded in
            k_d, d_d, compensate = k_d0, d_d0, 1.0
        else:
            k_d, d_d, compensate = live[0:3], live[3:6], live[6]
        error, clipped = clip_error(target_pos - kd.position, gains.deadband, gains.error_clip)
        force = k_d * error + d_d * (target_vel - jac @ dq)
        tau2 = k_n * (q_pref - q) - d_n * dq
        if orientation:
            if target_rot is None:
                raise InputError("orientation gains are set: step needs target_rot (3, 3)")
            jac_w = kd.jacobian[3:]
            moment = k_o * orientation_error(kd.rotation, target_rot) - d_o * (jac_w @ dq)
            tau2 = tau2 + jac_w.T @ moment
        # one Cholesky M = L L^T; W = L^-1 [J^T, tau_2]; W^T W = [J, tau_2]^T M^-1 [J^T, tau_2]
        w = cholesky_solve_lower(kd.mass_matrix, jnp.concatenate([jac.T, tau2[:, None]], axis=1))
        gram = w[:, :3].T @ w
        lam = inverse3(gram[:, :3] + eps)  # Lambda = (J M^-1 J^T)^-1
        # N^T tau_2 = tau_2 - J^T Lambda J M^-1 tau_2
        f_total = force - lam @ gram[:, 3]
        if feedforward:
            jac_bar = spd_solve(kd.mass_matrix, jac.T) @ lam
            jac_dot = jax.jvp(lambda qq: dynamics.site_jacobian(tree, qq, site)[:3], (q,), (dq,))[1]
            v_bar = jac_bar @ target_vel
            cor_v = coriolis_times(tree, q, dq, v_bar, inertial)
            ff = lam @ target_acc + jac_bar.T @ cor_v - lam @ (jac_dot @ v_bar)
            force = force + ff
            f_total = f_total + ff
        tau_motion = jac.T @ f_total + tau2  # everything but the gravity compensation
        tau = tau_motion + kd.gravity
        tau_rest = tau_motion if motion_sign else tau
        raw = friction_current(tau, tau_rest, dq, ratio, compensate * friction, threshold, band)
        cur, rate_limited, saturated = limit_current(raw, prev_current, max_step, limit)
        measured = prev_current if current is None else current
        estimate = external_force(jac, kd.gravity, dq, measured, ratio, friction, threshold)
        diag = pack_diagnostics(
            kd.position, error, force, tau, raw, rate_limited, saturated, clipped, estimate
        )
        return cur, diag

    return step


def impedance_packed_fn(step_fn, n: int, orientation: bool):
    """``step_fn`` on one packed input vector: one transfer each way per control cycle.

    Args:
        step_fn: an ``impedance_step_fn`` step.
        n: joints.
        orientation: with an orientation task.

    Returns:
        ``packed(x) -> y``: x the packed input (``impedance_io.packed_size``), y current (n) A
        | ``Diagnostics.data`` (16 + 5 n).
    """

    def packed(x):
        s = unpack_state(x, n, orientation)
        cur, diag = step_fn(s.q, s.dq, s.pos, s.vel, s.acc, s.prev, s.rot, s.current, s.live)
        return jnp.concatenate([cur, diag.data])

    return packed


class ImpedanceController(ImpedanceLaw):
    """Current-based impedance controller of one robot, params and gains (see module doc).

    Args:
        robot, params, gains, site: see ``ImpedanceLaw``.

    Attributes:
        robot, params, gains, site, n, joint: see ``ImpedanceLaw``.
        resolved: the ``ResolvedModel`` the step is built on (``impedance_step_fn(resolved,
            gains)`` rebuilds the step function, e.g. with per-world params swapped in).
        step: jitted pure function ``step(q, dq, target_pos, target_vel, target_acc,
            prev_current[, target_rot][, current][, live]) -> (current (n,) A, Diagnostics)``;
            q rad (n,), dq rad/s (n,), target_pos m (3,), target_vel m/s (3,), target_acc
            m/s^2 (3,), prev_current A (n,) (the last command, for the rate limit),
            target_rot (3, 3) only with orientation gains (else None), current A (n,) the
            measured motor currents for the external force estimate (None: prev_current, what
            a current-controlled motor draws), live (``LIVE_SIZE``,) the live gains
            (``live_gains``; None: the gains'); arm base frame. No input checks: pass device
            arrays (``check_state`` makes them), e.g. the previous step's current as it is.
        step_fn: the same function unjitted (to compose, vmap or jit with more).
        packed_step: jitted ``packed_step(x) -> y`` for the 1 kHz loop, the same law on one
            numpy vector x = q | dq | prev_current | target_pos | target_vel | target_acc
            | current | live [| target_rot row-major] (``packed_size``, ``packed_slices``),
            y = current (n) | Diagnostics data: one host-to-device and one device-to-host
            copy per cycle instead of eight and two (about 30 us less per call on a 2-core
            CPU). No input checks.
        live: (``LIVE_SIZE``,) the gains' own live gains (K_d, D_d, compensation on).
    """

    def _build(self) -> None:
        """The jitted step functions and the gains' live gains."""
        gains = self.gains
        self.step_fn = impedance_step_fn(self.resolved, gains)
        self.step = jax.jit(self.step_fn)
        self.packed_size = packed_size(self.n, gains.orientation)
        self.packed_step = jax.jit(impedance_packed_fn(self.step_fn, self.n, gains.orientation))
        self.live = live_gains(gains.stiffness, gains.damping, True)

    def __repr__(self) -> str:
        return (
            f"ImpedanceController({self.robot.name!r}, site={self.site!r}, "
            f"params={self.params.method!r})"
        )

    def check_state(
        self,
        q,
        dq,
        target_pos,
        target_vel=None,
        target_acc=None,
        prev_current=None,
        target_rot=None,
        current=None,
        live=None,
    ) -> tuple:
        """Validated device arrays for ``step``.

        Args:
            q: Joint angles, (n,) rad.
            dq: Joint velocities, (n,) rad/s.
            target_pos: (3,) m, arm base frame (as every Cartesian input).
            target_vel: (3,) m/s (None: zeros).
            target_acc: (3,) m/s^2 (None: zeros).
            prev_current: (n,) A, the previous command (None: zeros).
            target_rot: (3, 3), orientation gains only.
            current: (n,) A, the measured currents (None: prev_current).
            live: (``LIVE_SIZE``,) live gains (None: the gains').

        Returns:
            The arguments of ``step`` (current and live only when given, after target_rot,
            None without orientation gains).

        Raises:
            InputError: naming a bad input.
        """
        n, joints = self.n, self.robot.joint_names
        zeros = np.zeros(3)
        args = [
            checks.array(q, "q (rad)", n=n, labels=joints),
            checks.array(dq, "dq (rad/s)", n=n, labels=joints),
            checks.array(target_pos, "target_pos", n=3, unit="m"),
            zeros
            if target_vel is None
            else checks.array(target_vel, "target_vel", n=3, unit="m/s"),
            zeros
            if target_acc is None
            else checks.array(target_acc, "target_acc", n=3, unit="m/s^2"),
            np.zeros(n)
            if prev_current is None
            else checks.array(prev_current, "prev_current (A)", n=n, labels=joints),
        ]
        if self.gains.orientation:
            if target_rot is None:
                raise InputError("orientation gains are set: target_rot (3, 3) is needed")
            args.append(checks.array(target_rot, "target_rot (rotation matrix)", shape=(3, 3)))
        if current is not None or live is not None:
            if not self.gains.orientation:
                args.append(None)
            if current is not None:
                current = checks.array(current, "current (A)", n=n, labels=joints)
            if live is not None:
                live = checks.array(live, "live (live_gains)", n=LIVE_SIZE)
            args += [current, live]
        return tuple(None if a is None else jnp.asarray(a) for a in args)

    def checked_step(self, *args, **kwargs) -> tuple[jax.Array, Diagnostics]:
        """``step`` after ``check_state``: for interactive use, not the 1 kHz loop.

        Args:
            *args, **kwargs: those of ``check_state``.

        Returns:
            (current (n,) A, Diagnostics).
        """
        return self.step(*self.check_state(*args, **kwargs))

    def pack(
        self,
        q,
        dq,
        prev_current,
        target_pos,
        target_vel,
        target_acc,
        target_rot=None,
        current=None,
        live=None,
    ):
        """The packed input of ``packed_step`` (numpy, no checks).

        Args:
            q: Joint angles, (n,) rad.
            dq: Joint velocities, (n,) rad/s.
            prev_current: (n,) A, the previous command.
            target_pos: (3,) m, arm base frame (as every Cartesian input).
            target_vel: (3,) m/s.
            target_acc: (3,) m/s^2.
            target_rot: (3, 3), orientation gains only.
            current: (n,) A, the measured currents (None: prev_current).
            live: (``LIVE_SIZE``,) live gains (None: the gains').

        Returns:
            (``packed_size``,) float array.
        """
        current = prev_current if current is None else current
        live = self.live if live is None else live
        parts = [q, dq, prev_current, target_pos, target_vel, target_acc, current, live]
        if self.gains.orientation:
            parts.append(np.ravel(target_rot))
        return np.concatenate([np.asarray(p, dtype=float) for p in parts])

    def compile(self, step: bool = False) -> float:
        """Compile ``packed_step`` (the loop's) now, at the preferred pose.

        Args:
            step: compile ``step`` too.

        Returns:
            s it took.
        """
        t0 = time.perf_counter()
        q, zero3 = self.joint.posture, np.zeros(3)
        x = self.pack(q, np.zeros(self.n), np.zeros(self.n), zero3, zero3, zero3, np.eye(3))
        np.asarray(self.packed_step(x))
        if step:
            state = self.check_state(q, np.zeros(self.n), zero3, target_rot=np.eye(3))
            jax.block_until_ready(self.step(*state))
        return time.perf_counter() - t0


def make_impedance_controller(
    robot: Robot,
    params: RobotParams | CheckedParams | None = None,
    gains: ImpedanceGains | None = None,
    site: str | None = None,
) -> ImpedanceController:
    """An ``ImpedanceController`` for ``robot``.

    Args:
        robot: the arm's own model (arm base frame).
        params: identified ratio, friction and COM offsets (``CheckedParams``, or
            ``RobotParams`` checked here; None: the model's nominal ratios, no friction,
            nominal COM).
        gains: default ``impedance_gains(robot, "paper")`` (the paper's figures,
            ``ImpedanceGains()``, carried over to the arm: ``control.presets``).
        site: default the robot's end effector.

    Returns:
        The controller (compiled at its first step, or by ``compile``).
    """
    return ImpedanceController(robot, params, gains, site)


__all__ = [
    "ImpedanceController",
    "ImpedanceLaw",
    "ResolvedModel",
    "impedance_packed_fn",
    "impedance_step_fn",
    "make_impedance_controller",
]
