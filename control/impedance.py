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
``packed_step`` the same on one packed numpy vector (the 1 kHz loop's);
``ImpedanceControllerPinocchio`` is the same law in pinocchio + numpy (the latency baseline).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.control.external_force import external_force
from jaxcomp.control.gains import ImpedanceGains, JointGains
from jaxcomp.control.linalg import inverse3
from jaxcomp.control.presets import impedance_gains
from jaxcomp.current import friction_current
from jaxcomp.errors import InputError
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams
from jaxcomp.plausibility import check_params
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams

# ----------------------------------------------------------------------------- diagnostics


class Diagnostics(NamedTuple):
    """What one control step saw and did, packed in one array (one output buffer per step).

    ``data`` is (..., 16 + 5 n): ee_pos (3) | error (3) | force (3) | tau (n) | current_raw (n)
    | rate_limited (n) | saturated (n) | clipped (1) | current_model (n) | external_force (3)
    | external_band (3). Read it through the properties; they work on JAX and numpy arrays
    and on batches. ``numpy()`` copies it to the host once.
    """

    data: jax.Array | np.ndarray

    @property
    def n(self) -> int:
        """Number of joints."""
        return (self.data.shape[-1] - 16) // 5

    def _part(self, start: int, size: int):
        return self.data[..., start : start + size]

    @property
    def ee_pos(self):
        """(3,) m, the site's position x in the arm's base frame."""
        return self._part(0, 3)

    @property
    def error(self):
        """(3,) m, the position error x_d - x acting in the spring (after deadband and clip)."""
        return self._part(3, 3)

    @property
    def force(self):
        """(3,) N, the Cartesian force F (PD part, plus feedforward when on)."""
        return self._part(6, 3)

    @property
    def tau(self):
        """(n,) N m, the joint torques of Eq. (5), gravity included."""
        return self._part(9, self.n)

    @property
    def current_raw(self):
        """(n,) A, Eq. (16) before the rate limit and the saturation."""
        return self._part(9 + self.n, self.n)

    @property
    def rate_limited(self):
        """(n,) bool, the current rate limit acted on the joint."""
        return self._part(9 + 2 * self.n, self.n) > 0.5

    @property
    def saturated(self):
        """(n,) bool, the joint's current was cut to the current limit."""
        return self._part(9 + 3 * self.n, self.n) > 0.5

    @property
    def clipped(self):
        """() bool, the Cartesian error was longer than error_clip and was clipped."""
        return self.data[..., 9 + 4 * self.n] > 0.5

    @property
    def current_model(self):
        """(n,) A, the current the identified model predicts with nothing pushing
        (``external_force.model_current``), to compare with the measured current."""
        return self._part(10 + 4 * self.n, self.n)

    @property
    def external_force(self):
        """(3,) N, the estimated force applied on the end effector (arm base frame)."""
        return self._part(10 + 5 * self.n, 3)

    @property
    def external_band(self):
        """(3,) N, per axis: the applied force lies within external_force +- this (static
        friction of joints at rest; zero when every joint moves faster than t)."""
        return self._part(13 + 5 * self.n, 3)

    def numpy(self) -> Diagnostics:
        """The same diagnostics as a host (numpy) array."""
        return Diagnostics(np.asarray(self.data))


def estimate_slice(n: int) -> slice:
    """Where current_model (n) | external_force (3) | external_band (3) lie in the
    ``Diagnostics.data`` of a robot with n joints."""
    return slice(10 + 4 * n, 16 + 5 * n)


def pack_diagnostics(
    ee_pos, error, force, tau, current_raw, rate_limited, saturated, clipped, estimate
):
    """Diagnostics from its parts (JAX or numpy arrays; flags as bool; ``estimate`` an
    ``external_force.ExternalForce``)."""
    xp = jnp if isinstance(ee_pos, jax.Array) else np
    parts = [ee_pos, error, force, tau, current_raw]
    flags = [rate_limited, saturated, xp.reshape(clipped, (1,))]
    flags = [xp.asarray(f, dtype=float) for f in flags]
    return Diagnostics(xp.concatenate(parts + flags + list(estimate)))


# ----------------------------------------------------------------------------- model terms


def cholesky_solve_lower(m: jax.Array, b: jax.Array) -> jax.Array:
    """W = L^-1 B for M = L L^T (symmetric positive definite M (n, n), B (n, k)).

    Then B^T M^-1 B = W^T W: one Cholesky factorisation and one forward substitution give
    J M^-1 J^T and J M^-1 tau with no inverse. Written out entry by entry (n is small and
    static), which XLA fuses into a few loops instead of LAPACK calls.
    """
    n = m.shape[0]
    low = [[None] * n for _ in range(n)]
    inv_diag = [None] * n
    for j in range(n):
        d = m[j, j]
        for k in range(j):
            d = d - low[j][k] * low[j][k]
        inv_diag[j] = jax.lax.rsqrt(d)
        for i in range(j + 1, n):
            s = m[i, j]
            for k in range(j):
                s = s - low[i][k] * low[j][k]
            low[i][j] = s * inv_diag[j]
    w = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - low[i][k] * w[k]
        w[i] = s * inv_diag[i]
    return jnp.stack(w)


def spd_solve(m: jax.Array, b: jax.Array) -> jax.Array:
    """X = M^-1 B for symmetric positive definite M (LAPACK Cholesky; feedforward only)."""
    low = jnp.linalg.cholesky(m)
    return jax.scipy.linalg.cho_solve((low, True), b)


def coriolis_times(
    tree: KinematicTree, q: jax.Array, dq: jax.Array, w: jax.Array, params: InertialParams
) -> jax.Array:
    """C(q, dq) w (n,) for the Christoffel Coriolis matrix C (``dynamics.coriolis_matrix``):
    0.5 (M_dot(dq) w + M_dot(w) dq - d/dq (w^T M dq)), two JVPs and one gradient of M instead
    of its full Jacobian (faster to compile and run)."""

    def mass(qq):
        return dynamics.mass_matrix(tree, qq, params)

    m_dot_dq = jax.jvp(mass, (q,), (dq,))[1]
    m_dot_w = jax.jvp(mass, (q,), (w,))[1]
    grad = jax.grad(lambda qq: w @ mass(qq) @ dq)(q)
    return 0.5 * (m_dot_dq @ w + m_dot_w @ dq - grad)


def orientation_error(rot: jax.Array, target_rot: jax.Array) -> jax.Array:
    """(3,) rad, base frame: rotation vector taking ``rot`` to ``target_rot`` (small angles;
    0.5 sum_i rot[:, i] x target_rot[:, i] = sin(angle) axis for a rotation about one axis)."""
    return 0.5 * jnp.sum(jnp.cross(rot.T, target_rot.T), axis=0)


def clip_error(err, deadband: float, clip: float, xp=jnp):
    """(error after deadband and norm clip, clipped flag): zero below ``deadband`` m, norm cut
    to ``clip`` m above it."""
    norm = xp.sqrt(xp.sum(err * err))
    scale = xp.where(norm < deadband, 0.0, clip / xp.maximum(norm, clip))
    return err * scale, norm > clip


def limit_current(raw, prev, max_step, limit, xp=jnp):
    """(current, rate_limited, saturated): ``raw`` A moved at most ``max_step`` A from ``prev``,
    then within +-``limit`` A."""
    stepped = xp.clip(raw, prev - max_step, prev + max_step)
    out = xp.clip(stepped, -limit, limit)
    return out, stepped != raw, out != stepped


# ----------------------------------------------------------------------------- controller


def check_joint_vector(x, n: int, name: str, robot: Robot) -> np.ndarray:
    """x as a finite float array (n,), or InputError naming the input and the joints."""
    arr = np.asarray(x, dtype=float)
    if arr.shape != (n,):
        raise InputError(
            f"{name} must have shape ({n},) for {robot.name} "
            f"(joints {', '.join(robot.joint_names)}), got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        bad = [robot.joint_names[i] for i in np.flatnonzero(~np.isfinite(arr))]
        raise InputError(f"{name} contains NaN or inf at joint(s) {', '.join(bad)}")
    return arr


def check_vector3(x, name: str, unit: str) -> np.ndarray:
    """x as a finite float array (3,), or InputError naming the input."""
    arr = np.asarray(x, dtype=float)
    if arr.shape != (3,):
        raise InputError(f"{name} must have shape (3,) (x, y, z in {unit}), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contains NaN or inf: {arr.tolist()}")
    return arr


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


def _resolve(
    robot: Robot, params: RobotParams | None, gains: ImpedanceGains, site: str
) -> ResolvedModel:
    if not isinstance(gains, ImpedanceGains):
        raise InputError(f"gains must be an ImpedanceGains, got {type(gains).__name__}")
    joint = gains.joint_arrays(robot)  # also refuses a robot with base joints
    params = RobotParams.nominal(robot) if params is None else params
    if not isinstance(params, RobotParams):
        raise InputError(f"params must be a RobotParams or None, got {type(params).__name__}")
    if params.model != robot.name:
        raise InputError(f"params are for model {params.model!r}, the robot is {robot.name!r}")
    check_params(params, robot)  # nothing implausible reaches the arm
    inertial = InertialParams(*(np.asarray(x, dtype=float) for x in params.inertial_params(robot)))
    return ResolvedModel(
        tree=robot.tree,
        site=robot.site_index(site),
        inertial=inertial,
        gravity_vector=np.asarray(robot.default_gravity, dtype=float),
        ratio=params.ratio.copy(),
        friction=params.friction.copy(),
        joint=joint,
    )


def impedance_step_fn(
    res: ResolvedModel, gains: ImpedanceGains
) -> Callable[..., tuple[jax.Array, Diagnostics]]:
    """The pure (unjitted) step function of the controller; see ``ImpedanceController.step``.

    The rigid-body terms come from one call of ``dynamics.kinematics_and_dynamics`` (g, the
    site's pose and Jacobian and M in one pass); the current from ``current.friction_current``;
    the external force from ``external_force.external_force``.
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


#: Length of the live gains: K_d (3) N/m | D_d (3) N s/m | friction compensation factor (1).
LIVE_SIZE = 7


def live_gains(stiffness, damping, friction_compensation: bool | float = True) -> np.ndarray:
    """The live gains vector (``LIVE_SIZE``,) of a step: K_d (3) N/m, D_d (3) N s/m (one
    number: every axis) and the friction compensation factor (1.0 on, 0.0 off). No checks:
    the gains come validated (``ImpedanceGains``, ``presets.check_live_gains``)."""
    k = np.broadcast_to(np.asarray(stiffness, dtype=float), (3,))
    d = np.broadcast_to(np.asarray(damping, dtype=float), (3,))
    return np.concatenate([k, d, [float(friction_compensation)]])


def packed_size(n: int, orientation: bool = False) -> int:
    """Length of the packed input of ``packed_step``: q | dq | prev | pos | vel | acc |
    current | live [| target_rot row-major], i.e. 4 n + 16 (+ 9 with an orientation task)."""
    return 4 * n + 9 + LIVE_SIZE + (9 if orientation else 0)


class PackedState(NamedTuple):
    """The parts of a packed input (see ``packed_size``): q rad, dq rad/s, prev (the last
    command) A, target pos m, vel m/s, acc m/s^2, measured current A, live gains
    (``live_gains``), rot (3, 3) or None."""

    q: Any
    dq: Any
    prev: Any
    pos: Any
    vel: Any
    acc: Any
    current: Any
    live: Any
    rot: Any


def packed_slices(n: int) -> dict[str, slice]:
    """Where each part of a packed input lies (``packed_size``; rot only with orientation)."""
    k = 3 * n
    live = k + 9 + n
    return {
        "q": slice(0, n),
        "dq": slice(n, 2 * n),
        "prev": slice(2 * n, k),
        "pos": slice(k, k + 3),
        "vel": slice(k + 3, k + 6),
        "acc": slice(k + 6, k + 9),
        "current": slice(k + 9, live),
        "live": slice(live, live + LIVE_SIZE),
        "rot": slice(live + LIVE_SIZE, live + LIVE_SIZE + 9),
    }


def unpack_state(x, n: int, orientation: bool) -> PackedState:
    """The ``PackedState`` of a packed input (see ``packed_size``)."""
    sl = packed_slices(n)
    rot = x[sl["rot"]].reshape(3, 3) if orientation else None
    return PackedState(*(x[sl[k]] for k in PackedState._fields[:-1]), rot)


def impedance_packed_fn(step_fn, n: int, orientation: bool):
    """``step_fn`` on one packed input vector, returning one packed output vector
    current (n) | ``Diagnostics.data`` (16 + 5 n): one transfer each way per control cycle."""

    def packed(x):
        s = unpack_state(x, n, orientation)
        cur, diag = step_fn(s.q, s.dq, s.pos, s.vel, s.acc, s.prev, s.rot, s.current, s.live)
        return jnp.concatenate([cur, diag.data])

    return packed


class ImpedanceController:
    """Current-based impedance controller of one robot, params and gains (see module doc).

    Attributes:
        robot, params (RobotParams), gains, site (name), n (joints), joint (JointGains:
        posture rad, K_n, D_n, current limit A).
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

    def __init__(
        self,
        robot: Robot,
        params: RobotParams | None = None,
        gains: ImpedanceGains | None = None,
        site: str | None = None,
    ):
        gains = impedance_gains(robot, "paper") if gains is None else gains
        site = robot.end_effector if site is None else site
        self.resolved = _resolve(robot, params, gains, site)
        self.robot = robot
        self.params = RobotParams.nominal(robot) if params is None else params
        self.gains = gains
        self.site = site
        self.n = robot.nv
        self.joint = self.resolved.joint
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
        """Validated device arrays for ``step`` (None: zeros; current and live only when
        given, after target_rot, None without orientation gains); InputError naming a bad
        input."""
        n, r = self.n, self.robot
        args = [
            check_joint_vector(q, n, "q (rad)", r),
            check_joint_vector(dq, n, "dq (rad/s)", r),
            check_vector3(target_pos, "target_pos", "m"),
            np.zeros(3) if target_vel is None else check_vector3(target_vel, "target_vel", "m/s"),
            np.zeros(3) if target_acc is None else check_vector3(target_acc, "target_acc", "m/s^2"),
            np.zeros(n)
            if prev_current is None
            else check_joint_vector(prev_current, n, "prev_current (A)", r),
        ]
        if self.gains.orientation:
            if target_rot is None:
                raise InputError("orientation gains are set: target_rot (3, 3) is needed")
            rot = np.asarray(target_rot, dtype=float)
            if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
                raise InputError(f"target_rot must be a finite (3, 3) rotation matrix, got {rot}")
            args.append(rot)
        if current is not None or live is not None:
            if not self.gains.orientation:
                args.append(None)
            if current is not None:
                current = check_joint_vector(current, n, "current (A)", r)
            if live is not None:
                live = np.asarray(live, dtype=float)
                if live.shape != (LIVE_SIZE,) or not np.all(np.isfinite(live)):
                    raise InputError(f"live must be {LIVE_SIZE} finite numbers (live_gains)")
            args += [current, live]
        return tuple(None if a is None else jnp.asarray(a) for a in args)

    def checked_step(
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
    ):
        """``step`` after ``check_state``: for interactive use, not the 1 kHz loop."""
        return self.step(
            *self.check_state(
                q, dq, target_pos, target_vel, target_acc, prev_current, target_rot, current, live
            )
        )

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
        """The packed input of ``packed_step`` (numpy, no checks; current None: prev_current,
        live None: the gains')."""
        current = prev_current if current is None else current
        live = self.live if live is None else live
        parts = [q, dq, prev_current, target_pos, target_vel, target_acc, current, live]
        if self.gains.orientation:
            parts.append(np.ravel(target_rot))
        return np.concatenate([np.asarray(p, dtype=float) for p in parts])

    def compile(self, step: bool = False) -> float:
        """Compile ``packed_step`` (the loop's), and ``step`` too when asked, now (at the
        preferred pose); returns the seconds it took."""
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
    params: RobotParams | None = None,
    gains: ImpedanceGains | None = None,
    site: str | None = None,
) -> ImpedanceController:
    """An ``ImpedanceController`` for ``robot`` (the arm's own model, base frame).

    ``params``: identified ratio, friction and COM offsets (None: the model's nominal ratios,
    no friction, nominal COM). ``gains``: default ``impedance_gains(robot, "paper")`` (the
    paper's figures, ``ImpedanceGains()``, carried over to the arm: ``control.presets``).
    ``site``: default the robot's end effector.
    """
    return ImpedanceController(robot, params, gains, site)


# ----------------------------------------------------------------------------- pinocchio


class ImpedanceControllerPinocchio:
    """The same control law in pinocchio + numpy (reference and latency baseline).

    ``step`` takes and returns numpy arrays, same arguments and results as
    ``ImpedanceController.step``. The pinocchio model is built from ``jaxcomp.urdf.to_urdf``
    of the identified (COM-corrected) inertials.
    """

    def __init__(
        self,
        robot: Robot,
        params: RobotParams | None = None,
        gains: ImpedanceGains | None = None,
        site: str | None = None,
    ):
        import pinocchio as pin

        from jaxcomp.urdf import to_urdf

        gains = impedance_gains(robot, "paper") if gains is None else gains
        site = robot.end_effector if site is None else site
        self.resolved = res = _resolve(robot, params, gains, site)
        self.robot, self.gains, self.site, self.n = robot, gains, site, robot.nv
        self._pin = pin
        self.model = pin.buildModelFromXML(to_urdf(res.tree, res.inertial, robot.name))
        self.model.gravity.linear = res.gravity_vector
        self.data = self.model.createData()
        names = list(self.model.names)[1:]
        if sorted(names) != sorted(robot.joint_names) or self.model.nq != self.n:
            raise InputError(f"pinocchio model of {robot.name} does not match its joints")
        self._perm = np.array([names.index(nm) for nm in robot.joint_names])
        self._identity = bool(np.all(self._perm == np.arange(self.n)))
        self._frame = self.model.getFrameId(site)
        self._lwa = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        self._eye = gains.singularity_damping * np.eye(3)
        self._lower = np.tril_indices(self.n, -1)

    def _to_pin(self, x: np.ndarray) -> np.ndarray:
        if self._identity:
            return x
        out = np.empty(self.n)
        out[self._perm] = x
        return out

    def _from_pin(self, x: np.ndarray) -> np.ndarray:
        return x if self._identity else x[..., self._perm]

    def step(
        self,
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
        """(current (n,) A, Diagnostics) for numpy inputs; see ``ImpedanceController.step``."""
        pin, pm, pd, g, res = self._pin, self.model, self.data, self.gains, self.resolved
        qp, vp = self._to_pin(np.asarray(q, float)), self._to_pin(np.asarray(dq, float))
        grav = self._from_pin(pin.computeGeneralizedGravity(pm, pd, qp))
        mass = pin.crba(pm, pd, qp)  # upper triangle filled
        mass[self._lower] = mass.T[self._lower]
        if not self._identity:
            mass = mass[np.ix_(self._perm, self._perm)]
        jac6 = self._from_pin(pin.computeFrameJacobian(pm, pd, qp, self._frame, self._lwa))
        frame = pd.oMf[self._frame]
        pos, jac = frame.translation.copy(), jac6[:3]
        error, clipped = clip_error(target_pos - pos, g.deadband, g.error_clip, np)
        if live is None:
            live = live_gains(g.stiffness, g.damping, True)
        k_d, d_d, compensate = live[0:3], live[3:6], live[6]
        force = k_d * error + d_d * (target_vel - jac @ dq)
        k_n, d_n = res.joint.stiffness, res.joint.damping
        tau2 = k_n * (res.joint.posture - q) - d_n * dq
        if g.orientation:
            jac_w = jac6[3:]
            e_o = 0.5 * np.sum(np.cross(frame.rotation.T, np.asarray(target_rot).T), axis=0)
            moment = np.asarray(g.orientation_stiffness) * e_o
            moment = moment - np.asarray(g.orientation_damping) * (jac_w @ dq)
            tau2 = tau2 + jac_w.T @ moment
        x = np.linalg.solve(mass, np.concatenate([jac.T, tau2[:, None]], axis=1))
        lam = np.linalg.inv(jac @ x[:, :3] + self._eye)
        f_total = force - lam @ (jac @ x[:, 3])
        if g.feedforward:
            jac_bar = x[:, :3] @ lam
            pin.computeJointJacobiansTimeVariation(pm, pd, qp, vp)
            jac_dot = self._from_pin(
                pin.getFrameJacobianTimeVariation(pm, pd, self._frame, self._lwa)[:3]
            )
            cor = pin.computeCoriolisMatrix(pm, pd, qp, vp)
            if not self._identity:
                cor = cor[np.ix_(self._perm, self._perm)]
            v_bar = jac_bar @ target_vel
            ff = lam @ target_acc + jac_bar.T @ (cor @ v_bar) - lam @ (jac_dot @ v_bar)
            force, f_total = force + ff, f_total + ff
        tau_motion = jac.T @ f_total + tau2
        tau = tau_motion + grav
        tau_rest = tau_motion if g.friction_direction == "motion" else tau
        ratio, friction, threshold = res.ratio, res.friction, g.friction_threshold
        raw = friction_current(
            tau, tau_rest, dq, ratio, compensate * friction, threshold, g.friction_band, np
        )
        prev = np.asarray(prev_current, float)
        cur, rate_limited, saturated = limit_current(
            raw, prev, g.max_current_step, res.joint.limit, np
        )
        measured = prev if current is None else np.asarray(current, float)
        estimate = external_force(jac, grav, dq, measured, ratio, friction, threshold, np)
        diag = pack_diagnostics(
            pos, error, force, tau, raw, rate_limited, saturated, clipped, estimate
        )
        return cur, diag
