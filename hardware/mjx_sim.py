"""The simulated arm on MJX: thousands of true robots driven by one plan at once.

``MjxSimulator`` is the CPU ``Simulator`` (hardware/sim_arm.py) of an arm-only model in POSITION
mode, batched over worlds with ``jax.vmap(mjx.step)``: the same MuJoCo model (actuators, 1 ms
implicitfast step, stiff friction-loss solver reference), the same servo
``tau = clip(kp (q_ref - q) + kv (0 - dq), effort)`` with the same per-joint gains (computed as
the CPU simulator does, from each world's true inertia), the same settling of 500 steps at the
initial pose before t = 0, and the same measured current ``r tau_applied + noise``. Each world
has its own truth (``BatchTruth``: ratio, friction loss, COM offsets, viscous friction,
current noise, and two things the CPU simulator lacks: a point payload at the end-effector site
and the gravity vector of the mounting). The per-world model fields (``body_ipos``,
``body_mass``, ``dof_frictionloss``, ``dof_damping``, ``actuator_biasprm``, ``opt.gravity``) go
in through ``tree_replace`` with vmap axis 0; the shared model is closed over (axis None).

A plan is a joint-position reference ``q_ref (T, n)`` at 1 kHz (``reference_trajectory`` builds
it from moves exactly as ``Arm.move_to`` does). ``run`` advances every world through it in
compiled chunks of K steps (``lax.scan`` over the vmapped step; per-world state stays on the
device between chunks), records every k-th sample and calls ``progress`` per chunk. The world
axis can be sharded over a ``jax.sharding.Mesh`` with axis ``"batch"`` (``batch_mesh``).

Agreement with the CPU ``Simulator`` (same truth, no noise, same q_ref and start, float64),
measured on the Gen3 Lite in 4 worlds of drawn truths over 4.9 s of +-20-30 deg moves at
0.3-0.5 rad/s, the servo saturating at joint 1's effort limit: max |q| error 7.6e-9 rad,
|dq| 3.1e-7 rad/s, |current| 1.4e-6 A (the solver tolerance shows at stick-slip transitions);
``AGREEMENT`` holds the tolerances the tests assert. For that, the step integrates as MuJoCo C
does when an effort limit clamps the servo (see ``_implicitfast_step``), not as ``mjx.step``.

``run_closed_loop`` drives the worlds in CURRENT mode instead, closed loop at 1 kHz: a policy
(a pure JAX function of per-world parameters and state, vmapped here, knowing nothing of the
simulator) maps each measured sample (t, q, dq, current, a row of a shared reference) to motor
currents; the torque is current / true ratio (effort-clamped), pushes act on the end effector
(``PushSchedule``), and the faults of the CPU Simulator and the ``Arm`` (joint limit, effort,
overspeed, refused command) or the policy's own stop put a world in POSITION mode, holding.
The same chunked scan and sharding as ``run``; only the final policy state need leave the
device. Agreement with ``control.loop.run_control`` in lock step on the CPU Simulator (same
truth and impedance controller, no noise, 1.5 s of tracking with a push and an effort fault):
max |q| 7.6e-10 rad, |dq| 5.7e-9 rad/s, |current| 3.9e-7 A, tracking RMS to 1e-11 m
(``CLOSED_LOOP_AGREEMENT``).

Units: rad, rad/s, A, N m, kg, m, s; gravity and COM offsets as in ``BatchTruth``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from mujoco import mjx

from jaxcomp import dynamics
from jaxcomp.errors import InputError, ModelError
from jaxcomp.hardware.interface import DT, ArmLimits, trapezoid, trapezoid_duration
from jaxcomp.hardware.truth import DEFAULT_CURRENT_NOISE, TrueRobot
from jaxcomp.params import InertialParams
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import BASE_JOINTS, RobotParams, arm_joint_indices

#: Tolerances of the agreement with the CPU Simulator (float64, noise 0) that the tests assert:
#: max |q| rad, |dq| rad/s, |current| A differences over a recorded plan (measured: 7.6e-9,
#: 3.1e-7, 1.4e-6).
AGREEMENT = {"q": 2e-8, "dq": 1e-6, "current": 5e-6}

#: The same for ``run_closed_loop`` against the CPU Simulator + ``run_control`` (measured over
#: 1.5 s: 7.6e-10 rad, 5.7e-9 rad/s, 3.9e-7 A, command 3.9e-7 A, tracking RMS 4.5e-11 m).
CLOSED_LOOP_AGREEMENT = {"q": 1e-8, "dq": 1e-7, "current": 5e-6, "rms": 1e-9}

SETTLE_STEPS = 500  # the CPU Simulator's settling at the initial pose before t = 0
#: Line-search steps per Newton iteration of the constraint solver (MuJoCo's default: 50).
#: MuJoCo C leaves the line search once it converges; MJX, vmapped, runs every step of it,
#: so the cap is paid each iteration. The Newton loop's own tolerance still decides when the
#: solution is found (a capped line search only costs an extra iteration), and the agreement
#: with the CPU simulator is the same to the last digit; 1.9x the world-steps/s of 50 on an
#: H100 (65 536 worlds: 9.5e6 against 4.9e6).
LS_ITERATIONS = 12
PAYLOAD_BODY = "jaxcomp_payload"
_GAIN_POSES = 64  # poses the CPU Simulator samples for its servo gains
_GAIN_BATCH = 1024  # worlds per mass-matrix batch of the gain computation
_CHUNK_BYTES = 256 * 2**20  # recorded bytes per chunk on an accelerator
_MIN_FRICTION = 1e-9  # N m, the friction loss of a friction-free joint (MJX needs > 0)


# ----------------------------------------------------------------------------- plans
class Move(NamedTuple):
    """One ``Arm.move_to``: ``pose`` (n,) rad (None: stay), ``speed`` rad/s of the joint with
    the longest way, ``accel`` rad/s^2 (None: speed / 0.1 s), ``settle`` s held at the end."""

    pose: Any
    speed: float
    accel: float | None = None
    settle: float = 0.0


def reference_trajectory(
    moves: Sequence[Move | tuple],
    start: Sequence[float],
    *,
    limits: np.ndarray | None = None,
    max_speed: float | None = None,
) -> np.ndarray:
    """The 1 kHz position targets (T, n) rad that ``Arm.move_to`` sends for ``moves``.

    Sample by sample what successive ``arm.move_to(pose, speed, accel=, settle=)`` calls
    command from the target ``start`` (n,) rad (the arm's current target: after a fresh
    ``Simulator``, its measured settled pose ``arm.read().q``): a trapezoidal profile in
    ``hardware.interface.trapezoid``, each move starting from the previous move's last target.
    ``limits`` (n, 2) rad and ``max_speed`` rad/s, if given, are checked as ``move_to`` does.
    """
    pos = np.asarray(start, dtype=float)
    if pos.ndim != 1 or not np.isfinite(pos).all():
        raise InputError(f"start must be a finite (n,) array of rad, got shape {pos.shape}")
    n = pos.shape[0]
    if limits is not None:
        limits = np.asarray(limits, dtype=float)
        if limits.shape != (n, 2):
            raise InputError(f"limits must have shape ({n}, 2), got {limits.shape}")
    parts: list[np.ndarray] = []
    for i, mv in enumerate(moves):
        mv = mv if isinstance(mv, Move) else Move(*mv)
        target = pos if mv.pose is None else np.asarray(mv.pose, dtype=float)
        if target.shape != (n,) or not np.isfinite(target).all():
            raise InputError(f"move {i}: pose must be a finite ({n},) array of rad or None")
        if limits is not None and ((target < limits[:, 0]) | (target > limits[:, 1])).any():
            j = int(np.flatnonzero((target < limits[:, 0]) | (target > limits[:, 1]))[0])
            raise InputError(
                f"move {i}: pose {target[j]:.4g} rad of joint {j} is beyond its limits "
                f"[{limits[j, 0]:.4g}, {limits[j, 1]:.4g}] rad"
            )
        speed = float(mv.speed)
        top = math.inf if max_speed is None else float(max_speed)
        if not (math.isfinite(speed) and 0 < speed <= top):
            raise InputError(f"move {i}: speed must be in (0, {top:.3g}] rad/s, got {speed}")
        accel = speed / 0.1 if mv.accel is None else float(mv.accel)
        if not (math.isfinite(accel) and accel > 0):
            raise InputError(f"move {i}: accel must be a positive number of rad/s^2")
        settle = float(mv.settle)
        if not (math.isfinite(settle) and settle >= 0):
            raise InputError(f"move {i}: settle must be >= 0 s, got {settle}")
        # the arithmetic of Arm.move_to, operation for operation
        delta = target - pos
        dist = float(np.abs(delta).max())
        steps = math.ceil(trapezoid_duration(dist, speed, accel) / DT - 1e-9)
        steps += int(round(settle / DT))
        times = np.arange(1, steps + 1) * DT
        frac = trapezoid(dist, speed, accel, times) / dist if dist > 0 else np.ones(steps)
        path = pos + frac[:, None] * delta
        if steps:
            parts.append(path)
            pos = path[-1].copy()
    return np.concatenate(parts) if parts else np.zeros((0, n))


# ----------------------------------------------------------------------------- truths
@dataclass(frozen=True)
class BatchTruth:
    """The hidden true robot of every world (W worlds, n arm joints, nb links).

    Attributes:
        ratio: (W, n) A/(N m), current per joint torque.
        friction: (W, n) A, Coulomb friction loss as current (torque friction / ratio N m).
        com_offset: (W, nb, 3) m, added to each link's COM in the link's own frame; rows in
            ``robot.link_names`` order.
        current_noise: (W,) A, standard deviation of the measured current's noise.
        viscous: (W, n) N m s/rad, viscous friction.
        payload: (W,) kg, point mass at the end-effector site (needs ``payload=True`` sims).
        gravity: (W, 3) m/s^2, gravity in the robot's base (world) frame: the mounting.
    """

    ratio: np.ndarray
    friction: np.ndarray
    com_offset: np.ndarray
    current_noise: np.ndarray
    viscous: np.ndarray
    payload: np.ndarray
    gravity: np.ndarray

    def __post_init__(self) -> None:
        w, n = np.shape(self.ratio)[:2] if np.ndim(self.ratio) == 2 else (-1, -1)
        if w < 1 or n < 1:
            raise InputError(f"ratio must have shape (W, n), got {np.shape(self.ratio)}")
        want = {
            "ratio": (w, n),
            "friction": (w, n),
            "current_noise": (w,),
            "viscous": (w, n),
            "payload": (w,),
            "gravity": (w, 3),
        }
        for name, shape in want.items():
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != shape or not np.isfinite(arr).all():
                raise InputError(f"{name} must be a finite array of shape {shape}")
            object.__setattr__(self, name, arr)
        off = np.asarray(self.com_offset, dtype=float)
        if off.ndim != 3 or off.shape[0] != w or off.shape[2] != 3 or not np.isfinite(off).all():
            raise InputError(f"com_offset must be a finite (W={w}, nb, 3) array of m")
        object.__setattr__(self, "com_offset", off)
        for name in ("friction", "current_noise", "viscous", "payload"):
            if (getattr(self, name) < 0).any():
                raise InputError(f"{name} must be >= 0")
        if (self.ratio <= 0).any():
            raise InputError("ratio must be > 0 A/(N m)")

    @property
    def worlds(self) -> int:
        return self.ratio.shape[0]

    @classmethod
    def from_arrays(
        cls,
        robot: Robot,
        ratio: Any,
        friction: Any,
        *,
        com_offset: Any = None,
        current_noise: Any = DEFAULT_CURRENT_NOISE,
        viscous: Any = None,
        payload: Any = 0.0,
        gravity: Any = None,
        worlds: int | None = None,
    ) -> BatchTruth:
        """Broadcast per-joint (n,) or per-world (W, n) figures to a ``BatchTruth``.

        ``com_offset`` (nb, 3) or (W, nb, 3) m (default 0); ``gravity`` (3,) or (W, 3) m/s^2
        (default the model's); scalars broadcast to every world. ``worlds`` sets W when no
        argument has a world axis.
        """
        n, nb = len(arm_joint_indices(robot)), len(robot.link_names)
        # W: the leading axis of any per-world argument (else ``worlds``, else 1)
        per_world = [(ratio, 2), (friction, 2), (viscous, 2), (com_offset, 3), (gravity, 2)]
        per_world += [(payload, 1), (current_noise, 1)]
        sizes = [np.shape(v)[0] for v, nd in per_world if v is not None and np.ndim(v) == nd]
        w = worlds or max(sizes + [1])

        def bcast(val, shape, name):
            try:
                return np.broadcast_to(np.asarray(val, dtype=float), shape).copy()
            except ValueError:
                raise InputError(f"{name} of shape {np.shape(val)} does not fit {shape}") from None

        g = robot.model.opt.gravity if gravity is None else gravity
        return cls(
            ratio=bcast(ratio, (w, n), "ratio"),
            friction=bcast(friction, (w, n), "friction"),
            com_offset=bcast(0.0 if com_offset is None else com_offset, (w, nb, 3), "com_offset"),
            current_noise=bcast(current_noise, (w,), "current_noise"),
            viscous=bcast(0.0 if viscous is None else viscous, (w, n), "viscous"),
            payload=bcast(payload, (w,), "payload"),
            gravity=bcast(g, (w, 3), "gravity"),
        )

    @classmethod
    def from_truths(
        cls,
        robot: Robot,
        truths: Sequence[TrueRobot],
        *,
        payload: Any = 0.0,
        gravity: Any = None,
    ) -> BatchTruth:
        """One world per ``TrueRobot`` (as the CPU ``Simulator`` would use it), plus optional
        payload (W,) kg and gravity (3,) or (W, 3) m/s^2."""
        if not truths:
            raise InputError("truths is empty: give one TrueRobot per world")
        links = list(robot.link_names)
        off = np.zeros((len(truths), len(links), 3))
        for w, t in enumerate(truths):
            t.params.check(robot)
            for link, d in t.params.com_offset.items():
                off[w, robot.link_index(link)] = d
        n = len(arm_joint_indices(robot))
        return cls.from_arrays(
            robot,
            np.stack([t.ratio for t in truths]),
            np.stack([t.friction for t in truths]),
            com_offset=off,
            current_noise=np.array([t.current_noise for t in truths]),
            viscous=np.stack([np.zeros(n) if t.viscous is None else t.viscous for t in truths]),
            payload=payload,
            gravity=gravity,
        )

    def true_robot(self, robot: Robot, w: int) -> TrueRobot:
        """World ``w`` as a ``TrueRobot`` for the CPU ``Simulator`` (payload, gravity dropped)."""
        offsets = {
            name: self.com_offset[w, i]
            for i, name in enumerate(robot.link_names)
            if np.any(self.com_offset[w, i])
        }
        params = RobotParams(robot.name, self.ratio[w], self.friction[w], offsets, method="truth")
        viscous = self.viscous[w] if np.any(self.viscous[w]) else None
        return TrueRobot(params, float(self.current_noise[w]), viscous)


# ----------------------------------------------------------------------------- model
def build_model(robot: Robot, payload: bool = False) -> mujoco.MjModel:
    """The CPU Simulator's MjModel of ``robot`` (an arm-only model): 1 ms implicitfast, one
    servo actuator (gain 1, affine bias) per arm joint; with ``payload`` a massless body
    ``jaxcomp_payload`` at the end-effector site (its mass is set per world)."""
    if robot.source is None:
        raise ModelError("the MJX simulator needs a robot loaded from a model file")
    names = robot.joint_names
    if any(b in names for b in BASE_JOINTS):
        raise ModelError(f"{robot.name} has mobile-base joints: the MJX simulator is arm-only")
    spec = mujoco.MjSpec.from_file(str(robot.source))
    spec.option.timestep = DT
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.ls_iterations = LS_ITERATIONS
    for j in arm_joint_indices(robot):  # as Simulator._build
        act = spec.add_actuator(
            name=f"jaxcomp_drive_{names[j]}",
            target=names[j],
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            gaintype=mujoco.mjtGain.mjGAIN_FIXED,
            biastype=mujoco.mjtBias.mjBIAS_AFFINE,
        )
        act.gainprm[0] = 1.0
    if payload:
        body, pos = _ee_body_and_point(robot)
        spec.body(body).add_body(
            name=PAYLOAD_BODY,
            pos=pos,
            ipos=[0.0, 0.0, 0.0],
            iquat=[1.0, 0.0, 0.0, 0.0],
            mass=0.0,
            inertia=[0.0, 0.0, 0.0],
            explicitinertial=True,
        )
    try:
        model = spec.compile()
    except Exception as exc:
        raise ModelError(f"cannot compile the simulation model: {exc}") from None
    if model.nq != model.nv or model.nv != model.nu:
        raise ModelError(f"{robot.name}: the MJX simulator needs hinge/slide arm joints only")
    return model


def _ee_site_name(robot: Robot) -> str:
    """The end-effector site's name (``Robot.end_effector``), checked to exist."""
    name = robot.end_effector
    if mujoco.mj_name2id(robot.model, mujoco.mjtObj.mjOBJ_SITE, name) < 0:
        raise ModelError(f"the model has no end-effector site {name!r}")
    return name


def _ee_body_and_point(robot: Robot) -> tuple[str, np.ndarray]:
    """Name of the end-effector site's body and the site's position in it, m."""
    name = _ee_site_name(robot)
    m = robot.model
    s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)
    b = int(m.site_bodyid[s])
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b), m.site_pos[s].copy()


def true_inertial_params(robot: Robot, truth: BatchTruth) -> InertialParams:
    """Per-world inertial params (W, nb, ...): nominal + COM offsets, payload folded into the
    end-effector body (mass, COM and inertia about the COM, link frame)."""
    p = robot.nominal_params()
    w = truth.worlds
    mass = np.broadcast_to(np.asarray(p.mass), (w,) + np.shape(p.mass)).copy()
    com = np.asarray(p.com)[None] + truth.com_offset
    inertia = np.broadcast_to(np.asarray(p.inertia), (w,) + np.shape(p.inertia)).copy()
    if truth.payload.any():
        body, point = _ee_body_and_point(robot)
        b = robot.link_index(body)
        mb, cb, mp = mass[:, b], com[:, b], truth.payload
        total = mb + mp
        c = (mb[:, None] * cb + mp[:, None] * point) / total[:, None]

        def shift(mm, d):  # parallel-axis term of mass mm at offset d (W, 3)
            dd = np.einsum("wi,wi->w", d, d)
            return mm[:, None, None] * (dd[:, None, None] * np.eye(3) - d[:, :, None] * d[:, None])

        inertia[:, b] += shift(mb, cb - c) + shift(mp, point - c)
        mass[:, b], com[:, b] = total, c
    return InertialParams(jnp.asarray(mass), jnp.asarray(com), jnp.asarray(inertia))


_GAIN_FUNCTIONS: dict[int, tuple[Robot, Callable]] = {}


def _gain_function(robot: Robot) -> Callable:
    """Jitted (params (W, ...), poses (P, n)) -> I_min, I_max (W, n), cached per robot."""
    if id(robot) not in _GAIN_FUNCTIONS:
        tree = robot.tree

        @jax.jit
        def gains(p: InertialParams, q: jax.Array) -> tuple[jax.Array, jax.Array]:
            mm = jax.vmap(
                jax.vmap(lambda p1, q1: dynamics.mass_matrix(tree, q1, p1), (None, 0)), (0, None)
            )(p, q)
            i_min = (1.0 / jnp.diagonal(jnp.linalg.inv(mm), axis1=-2, axis2=-1)).min(axis=1)
            i_max = jnp.diagonal(mm, axis1=-2, axis2=-1).max(axis=1)
            return i_min, i_max

        _GAIN_FUNCTIONS[id(robot)] = (robot, gains)  # the robot stays alive with its entry
    return _GAIN_FUNCTIONS[id(robot)][1]


def servo_gains(
    robot: Robot, params: InertialParams, bandwidth: float = 500.0
) -> tuple[np.ndarray, np.ndarray]:
    """Per-world position-servo gains (W, n) as ``Simulator._gains`` computes them.

    Over the zero pose and 63 poses drawn from ``default_rng(0)`` within the joint limits:
    I_min = min 1 / (M^-1)_jj, I_max = max M_jj; kp = I_min bandwidth^2 N m/rad,
    kv = 2 sqrt(kp sqrt(I_min I_max)) N m s/rad. ``params``: (W, ...) inertial params.
    """
    lim = robot.joint_limits[arm_joint_indices(robot)]
    rng = np.random.default_rng(0)
    n = lim.shape[0]
    poses = np.stack(
        [np.zeros(n)] + [rng.uniform(lim[:, 0], lim[:, 1]) for _ in range(_GAIN_POSES - 1)]
    )
    gains = _gain_function(robot)
    w = params.mass.shape[0]
    b = min(w, _GAIN_BATCH)
    i_min, i_max = np.zeros((w, n)), np.zeros((w, n))
    for s in range(0, w, b):
        idx = np.minimum(np.arange(s, s + b), w - 1)  # last batch padded with the last world
        lo, hi = gains(jax.tree_util.tree_map(lambda a, idx=idx: a[idx], params), poses)
        k = min(b, w - s)
        i_min[s : s + k], i_max[s : s + k] = np.asarray(lo)[:k], np.asarray(hi)[:k]
    kp = i_min * bandwidth**2
    kv = 2.0 * np.sqrt(kp * np.sqrt(i_min * i_max))
    return kp, kv


def batch_mesh(devices: int | None = None) -> Mesh:
    """A 1-D mesh with axis ``"batch"`` over the first ``devices`` devices (default all)."""
    devs = jax.devices()
    k = len(devs) if devices is None else int(devices)
    if not 1 <= k <= len(devs):
        raise InputError(f"devices must be in 1..{len(devs)}, got {devices}")
    return jax.make_mesh((k,), ("batch",), axis_types=(AxisType.Auto,), devices=devs[:k])


# ----------------------------------------------------------------------------- recordings
class MjxRecording(NamedTuple):
    """What ``MjxSimulator.run`` recorded (host arrays; R recorded samples).

    Attributes:
        t: (R,) s, time of each sample (plan step i is recorded at (i + 1) ms).
        q: (W, R, n) rad; dq: (W, R, n) rad/s; current: (W, R, n) A (r tau_applied + noise),
            the state after plan steps 0, every, 2 every, ...
        q_start: (W, n) rad, each world's settled pose at t = 0.
        fault_step: (W,) first plan step after which a servoed joint was beyond
            ``following_error`` of its target, faster than ``overspeed`` or at a joint limit
            (what stops the CPU Simulator), -1 if none; the MJX worlds keep going regardless.
        every: the recording decimation k.
    """

    t: np.ndarray
    q: np.ndarray | None
    dq: np.ndarray | None
    current: np.ndarray | None
    q_start: np.ndarray
    fault_step: np.ndarray
    every: int


# ----------------------------------------------------------------------------- closed loop
#: Bits of ``ClosedLoopResult.fault_code``: what put a world in POSITION mode (as the CPU
#: Simulator and the Arm interface would): a joint at its limit, a current whose torque is
#: beyond the effort limit, a joint faster than ``overspeed``, a command refused before it is
#: sent (NaN/inf or beyond the arm's current limit), the policy asking to stop (a watchdog).
FAULT_LIMIT, FAULT_EFFORT, FAULT_OVERSPEED, FAULT_REFUSED, FAULT_STOPPED = 1, 2, 4, 8, 16
FAULT_NAMES = {
    FAULT_LIMIT: "joint limit",
    FAULT_EFFORT: "effort limit",
    FAULT_OVERSPEED: "overspeed",
    FAULT_REFUSED: "command refused",
    FAULT_STOPPED: "stopped by the policy",
}


def fault_names(code: int) -> list[str]:
    """The readable names of the bits set in a ``fault_code``."""
    return [name for bit, name in FAULT_NAMES.items() if int(code) & bit]


class Observation(NamedTuple):
    """What a closed-loop policy sees of one world at time t (one 1 kHz sample).

    Attributes:
        t: () s since the start of the closed loop (sample k is at k DT).
        q: (n,) rad; dq: (n,) rad/s; current: (n,) A, measured (r tau_applied + noise).
        reference: (m,) row k of the run's shared ``reference`` (e.g. a target trajectory).
    """

    t: jax.Array
    q: jax.Array
    dq: jax.Array
    current: jax.Array
    reference: jax.Array


#: A closed-loop policy, per world: (params, state, Observation) -> (command (n,) A, new state,
#: stop ()); pure JAX, vmapped over worlds by the simulator.
Policy = Callable[[Any, Any, Observation], tuple[jax.Array, Any, jax.Array]]


class PushSchedule(NamedTuple):
    """Forces on each world's end effector (``hardware.interaction.Push``, force only).

    Push p of world w acts with ``force[w, p]`` (3,) N, world frame, at the end-effector
    site while ``start[w, p] <= t < start[w, p] + duration[w, p]`` (s since the start of the
    closed loop); active pushes add up.
    """

    start: np.ndarray  # (W, P) s
    duration: np.ndarray  # (W, P) s
    force: np.ndarray  # (W, P, 3) N

    @classmethod
    def from_pushes(cls, pushes: Sequence[Sequence[Any]]) -> PushSchedule:
        """One list of ``Push`` per world (padded with zero forces to the longest list)."""
        if not pushes:
            raise InputError("pushes is empty: give one list of Push per world")
        width = max(1, max(len(p) for p in pushes))
        start, dur = np.zeros((len(pushes), width)), np.ones((len(pushes), width))
        force = np.zeros((len(pushes), width, 3))
        for w, world in enumerate(pushes):
            for k, push in enumerate(world):
                if np.any(getattr(push, "torque", np.zeros(3))):
                    raise InputError("the MJX simulator applies push forces only (torque = 0)")
                start[w, k], dur[w, k], force[w, k] = push.start, push.duration, push.force
        return cls(start, dur, force)

    def checked(self, worlds: int) -> PushSchedule:
        """Float arrays of the right shapes, finite, start >= 0, duration > 0 (InputError)."""
        start, dur, force = (np.asarray(a, dtype=float) for a in self)
        if start.ndim != 2 or start.shape[0] != worlds or dur.shape != start.shape:
            raise InputError(
                f"push start and duration must have shape ({worlds}, P), got {start.shape} "
                f"and {dur.shape}"
            )
        if force.shape != start.shape + (3,):
            raise InputError(f"push force must have shape {start.shape + (3,)}, got {force.shape}")
        if not (np.isfinite(start).all() and np.isfinite(dur).all() and np.isfinite(force).all()):
            raise InputError("pushes must be finite")
        if (start < 0).any() or (dur <= 0).any():
            raise InputError("pushes need start >= 0 s and duration > 0 s")
        return PushSchedule(start, dur, force)


class ClosedLoopResult(NamedTuple):
    """What ``MjxSimulator.run_closed_loop`` returns (host arrays; R recorded samples).

    Attributes:
        t: (R,) s, time of each recorded sample (step i's state, at (i + 1) DT).
        q: (W, R, n) rad; dq: (W, R, n) rad/s; current: (W, R, n) A measured, the state after
            steps 0, every, ...; command: (W, R, n) A, the policy's command applied in those
            steps (its last one once the world is in POSITION mode). None when not recorded.
        state: the policy state of every world at the end (pytree of (W, ...) arrays; frozen
            after the last sample whose command was sent).
        q_start: (W, n) rad, each world's settled pose at t = 0.
        fault_step: (W,) the sample at which each world went to POSITION mode after a fault,
            a refused command or a stop (t = fault_step DT; it holds from step fault_step on),
            -1 if none.
        fault_code: (W,) bits ``FAULT_*`` of that event (0 if none).
        every: the recording decimation (0: nothing recorded).
    """

    t: np.ndarray
    q: np.ndarray | None
    dq: np.ndarray | None
    current: np.ndarray | None
    command: np.ndarray | None
    state: Any
    q_start: np.ndarray
    fault_step: np.ndarray
    fault_code: np.ndarray
    every: int


# ----------------------------------------------------------------------------- simulator
class MjxSimulator:
    """MJX simulation of many true arms in POSITION mode (see the module docstring).

    Args:
        robot: built-in name, model path or ``Robot`` (arm-only).
        payload: add the end-effector payload body (needed for ``BatchTruth.payload`` > 0).
        dtype: jnp.float64 (default; agrees with the CPU simulator) or jnp.float32.
        servo_bandwidth: rad/s, as ``Simulator``.
        friction_timeconst: s, friction-loss solver time constant, as ``Simulator``.
        following_error: rad, overspeed: rad/s, fault thresholds (reported, see MjxRecording).
        mesh: a ``Mesh`` with axis "batch" to shard the worlds over (``batch_mesh``); None:
            the default device.
        chunk_steps: steps per compiled call (default: 100 on CPU, else as many as keep the
            recorded output of a chunk within 256 MiB); rounded up to a multiple of ``every``.
    """

    def __init__(
        self,
        robot: str | Path | Robot = "gen3_lite",
        *,
        payload: bool = False,
        dtype: Any = jnp.float64,
        servo_bandwidth: float = 500.0,
        friction_timeconst: float = 2 * DT,
        following_error: float = 0.1,
        overspeed: float = 2.0,
        mesh: Mesh | None = None,
        chunk_steps: int | None = None,
    ):
        self.robot = load_robot(robot)
        self.dtype = jnp.dtype(dtype)
        if self.dtype not in (jnp.dtype(jnp.float64), jnp.dtype(jnp.float32)):
            raise InputError(f"dtype must be float64 or float32, got {self.dtype}")
        self.payload = bool(payload)
        self.servo_bandwidth = float(servo_bandwidth)
        self.following_error = float(following_error)
        self.overspeed = float(overspeed)
        self.mesh = mesh
        if mesh is not None and tuple(mesh.axis_names) != ("batch",):
            raise InputError(f"mesh must have the single axis 'batch', got {mesh.axis_names}")
        self.chunk_steps = chunk_steps
        self.model = m = build_model(self.robot, self.payload)
        n = m.nu
        self.n = n
        # the CPU Simulator's friction-loss solver settings (TrueRobot.apply), friction > 0 so
        # that MJX builds the friction rows (their values are set per world)
        dummy = RobotParams(self.robot.name, np.ones(n), np.ones(n))
        TrueRobot(dummy, current_noise=0.0).apply(m, self.robot, friction_timeconst)
        self._body_ids = np.array(
            [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in self.robot.link_names]
        )
        self._payload_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, PAYLOAD_BODY)
        self._hard = self.robot.joint_limits[arm_joint_indices(self.robot)]
        self.effort = np.abs(m.jnt_actfrcrange).max(1)
        # CURRENT mode (run_closed_loop): torque limits (inf where none), the arm's current
        # limits (A, as ArmLimits), the end-effector site and its body (pushes)
        self._torque_limit = np.where(m.jnt_actfrclimited.astype(bool), self.effort, np.inf)
        self.current_limit = ArmLimits.from_robot(self.robot, arm_joint_indices(self.robot)).current
        site = _ee_site_name(self.robot)
        self._ee_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
        self._ee_body = int(m.site_bodyid[self._ee_site])
        with self._precision():  # float32: the model's arrays and every traced literal
            self._mx = mjx.put_model(m)
            self._d0 = mjx.make_data(self._mx)
        self._compiled: dict[tuple, Callable] = {}
        self.compile_seconds = 0.0  # time spent compiling chunk functions so far
        #: wall seconds of the last run: prepare (truth -> fields, gains), settle, plan
        #: (stepping and recording, compilation excluded)
        self.last_timing: dict[str, float] = {}

    # ------------------------------------------------------------------ public
    def _precision(self):
        """Context of JAX's 64-bit mode for this simulator's dtype (jaxcomp enables it)."""
        return jax.enable_x64(self.dtype == jnp.dtype(jnp.float64))

    @property
    def backend(self) -> str:
        return jax.default_backend()

    def world_fields(self, truth: BatchTruth) -> dict[str, np.ndarray]:
        """The per-world arrays (W, ...) a run feeds the vmapped step (host, self.dtype):
        MJX model fields by their tree path, plus ``kp`` N m/rad, ``ratio`` A/(N m) and
        ``noise`` A."""
        m, w, n = self.model, truth.worlds, self.n
        if truth.ratio.shape[1] != n or truth.com_offset.shape[1] != len(self._body_ids):
            raise InputError(
                f"truth is for {truth.ratio.shape[1]} joints / {truth.com_offset.shape[1]} links,"
                f" the model has {n} / {len(self._body_ids)}"
            )
        if truth.payload.any() and not self.payload:
            raise InputError("truth has a payload: build the MjxSimulator with payload=True")
        kp, kv = servo_gains(
            self.robot, true_inertial_params(self.robot, truth), self.servo_bandwidth
        )
        ipos = np.broadcast_to(m.body_ipos, (w,) + m.body_ipos.shape).copy()
        ipos[:, self._body_ids] += truth.com_offset
        bias = np.broadcast_to(m.actuator_biasprm, (w,) + m.actuator_biasprm.shape).copy()
        bias[:, :, :3] = np.stack([np.zeros_like(kp), -kp, -kv], axis=-1)
        fields = {
            "body_ipos": ipos,
            # MJX treats a friction row of zero loss as a locked joint (its force is only
            # bounded by the loss when the loss is > 0): a negligible floor instead
            "dof_frictionloss": np.maximum(truth.friction / truth.ratio, _MIN_FRICTION),
            "dof_damping": truth.viscous.copy(),
            "actuator_biasprm": bias,
            "opt.gravity": truth.gravity.copy(),
            "kp": kp,
            "ratio": truth.ratio.copy(),
            "noise": truth.current_noise.copy(),
        }
        if self.payload:
            mass = np.broadcast_to(m.body_mass, (w, m.nbody)).copy()
            mass[:, self._payload_id] = truth.payload
            fields["body_mass"] = mass
        return {k: v.astype(self.dtype) for k, v in fields.items()}

    def settle(
        self, truth: BatchTruth, initial_pose: Any = None, settle_steps: int = SETTLE_STEPS
    ) -> np.ndarray:
        """Each world's settled pose (W, n) rad at t = 0 (the start a plan begins from)."""
        rec = self.run(truth, np.zeros((0, self.n)), initial_pose, settle_steps=settle_steps)
        return rec.q_start

    def run(
        self,
        truth: BatchTruth,
        q_ref: np.ndarray,
        initial_pose: Any = None,
        *,
        settle_steps: int = SETTLE_STEPS,
        seed: int = 0,
        every: int = 1,
        progress: Callable[[int, int], None] | None = None,
        on_chunk: Callable[[int, MjxRecording], None] | None = None,
        keep: bool = True,
        group: Any = None,
    ) -> MjxRecording:
        """Drive every world through the position targets ``q_ref`` (T, n) rad at 1 kHz.

        ``q_ref`` may also be (T, G, n): G references run side by side, world w following
        reference ``group[w]`` ((W,) ints in [0, G); e.g. the sweeps of one plan as parallel
        segments).

        Each world starts at ``initial_pose`` (name, (n,) or (W, n) rad; default "home"),
        is servoed there for ``settle_steps`` steps (as a fresh CPU ``Simulator``), then
        follows ``q_ref``: step i commands q_ref[i] and records the state after it. Records
        every ``every``-th sample (0, every, ...); the current noise of world w at step i is
        ``noise_w N(0, 1)`` from ``fold_in(fold_in(PRNGKey(seed), w), i)``, so it does not
        depend on chunking. ``progress(steps_done, steps_total)`` after each chunk;
        ``on_chunk(first_sample, recording_of_the_chunk)`` streams samples; ``keep=False``
        returns q, dq, current as None (bounded host memory).
        """
        every = int(every)
        if every < 1:
            raise InputError(f"every must be >= 1, got {every}")
        settle_steps = int(settle_steps)
        if settle_steps < 0:
            raise InputError("settle_steps must be >= 0")
        q_ref = np.asarray(q_ref, dtype=float)
        if q_ref.ndim == 2:
            q_ref = q_ref[:, None]
        if q_ref.ndim != 3 or q_ref.shape[2] != self.n or not np.isfinite(q_ref).all():
            raise InputError(f"q_ref must be a finite (T, {self.n}) or (T, G, {self.n}) rad array")
        outside = (q_ref < self._hard[:, 0]) | (q_ref > self._hard[:, 1])
        if outside.any():
            i, g, j = np.argwhere(outside)[0]
            where = f"{i}, {j}" if q_ref.shape[1] == 1 else f"{i}, {g}, {j}"
            raise InputError(
                f"q_ref[{where}] = {q_ref[i, g, j]:.4g} rad is beyond joint {j}'s limits "
                f"[{self._hard[j, 0]:.4g}, {self._hard[j, 1]:.4g}] rad"
            )
        w, n, t_total, groups = truth.worlds, self.n, q_ref.shape[0], q_ref.shape[1]
        group = np.zeros(w, np.int32) if group is None else np.asarray(group)
        if group.shape != (w,) or not ((group >= 0) & (group < groups)).all():
            raise InputError(f"group must be ({w},) ints in [0, {groups})")
        t_begin, compile_before = time.perf_counter(), self.compile_seconds
        q0 = self._initial_pose(initial_pose, w)
        fields = self.world_fields(truth)
        pad = self._world_padding(w)
        wp = len(pad)
        fields = {k: v[pad] for k, v in fields.items()}
        fields["key"] = _world_keys(seed, w)[pad]
        fields["group"] = group.astype(np.int32)[pad]
        q0 = q0[pad]
        chunk = self._chunk_steps(wp, every, max(t_total, settle_steps, 1))
        fn = self._function(wp, chunk, every, groups)
        put, put_shared = self._placement()
        fields = put(fields)
        t_prepared = time.perf_counter()
        zeros = np.zeros((wp, n), self.dtype)
        carry = put((q0.astype(self.dtype), zeros, zeros, np.full(wp, -1, np.int32)))
        # settle: servo to q0 (target q0 = 0 reference + per-world offset q0)
        settle_fields = dict(fields, offset=put(q0.astype(self.dtype)))
        zero_ref = put_shared(np.zeros((chunk, groups, n), self.dtype))
        for s in range(0, settle_steps, chunk):
            carry, _ = fn(
                settle_fields,
                carry,
                zero_ref,
                np.int32(s - settle_steps),
                np.int32(min(chunk, settle_steps - s)),
            )
        carry = carry[:3] + (carry[3] * 0 - 1,)
        q_start = np.asarray(carry[0])[:w].astype(float)
        t_settled, compile_settled = time.perf_counter(), self.compile_seconds
        plan_fields = dict(fields, offset=put(zeros))
        n_rec = -(-t_total // every)
        out = (
            {k: np.zeros((w, n_rec, n), self.dtype) for k in ("q", "dq", "current")} if keep else {}
        )
        pending: tuple | None = None
        for s in range(0, t_total, chunk):
            ref = np.empty((chunk, groups, n), self.dtype)
            k = min(chunk, t_total - s)
            ref[:k], ref[k:] = q_ref[s : s + k], q_ref[s + k - 1]
            carry, rec = fn(plan_fields, carry, put_shared(ref), np.int32(s), np.int32(k))
            if pending is not None:  # host work overlaps the chunk just dispatched
                self._consume(pending, w, every, out, on_chunk, progress, t_total)
            pending = (s, k, rec)
        if pending is not None:
            self._consume(pending, w, every, out, on_chunk, progress, t_total)
        t_end = time.perf_counter()
        self.last_timing = {
            "prepare": t_prepared - t_begin,
            "settle": t_settled - t_prepared - (compile_settled - compile_before),
            "plan": t_end - t_settled - (self.compile_seconds - compile_settled),
        }
        t = (np.arange(n_rec) * every + 1) * DT
        return MjxRecording(
            t,
            out.get("q"),
            out.get("dq"),
            out.get("current"),
            q_start,
            np.asarray(carry[3])[:w].astype(int),
            every,
        )

    def run_closed_loop(
        self,
        truth: BatchTruth,
        policy: Policy,
        params: Any,
        state: Any,
        steps: int,
        *,
        reference: Any = None,
        pushes: PushSchedule | None = None,
        initial_pose: Any = None,
        settle_steps: int = SETTLE_STEPS,
        seed: int = 0,
        every: int = 0,
        progress: Callable[[int, int], None] | None = None,
    ) -> ClosedLoopResult:
        """Drive every world in CURRENT mode with ``policy`` for ``steps`` steps of 1 ms.

        Each world settles at ``initial_pose`` under the position servo for ``settle_steps``
        (>= 1) steps, as in ``run``; from t = 0 the policy maps each sample k (``Observation``
        at t = k DT, k = 0 .. steps) to the motor currents (n,) A of step k (the last sample's
        are not applied): torque = current / true ratio, clamped at the effort limit, as the
        CPU Simulator's CURRENT mode (the sample before a step, the command after it:
        ``control.loop.run_control`` in lock step, with ``steps`` cycles). The measured
        current is ratio x applied torque + noise; world w's noise at sample k comes from
        ``fold_in(fold_in(PRNGKey(seed), w), k)``.

        ``policy(params_w, state_w, obs) -> (current (n,) A, new state_w, stop ())`` is pure
        JAX, vmapped over worlds here; ``params`` and ``state`` are pytrees of (W, ...) arrays,
        or ``state`` is a function ``init(params_w, obs_0) -> state_w`` applied to sample 0.
        ``reference`` (steps + 1, m), shared by the worlds, gives row k to the policy with
        sample k (None: an empty row). ``pushes`` act on the end effectors (world frame).

        A world goes to POSITION mode, holding its measured position, for the rest of the run
        (``fault_step``, ``fault_code``) when, as on the CPU Simulator and the ``Arm``, a joint
        reaches its limit, a torque exceeds the effort limit or a joint ``overspeed`` (the
        sample after the step shows the fault), or at a sample whose command is refused (NaN/inf
        or beyond ``current_limit`` A, never sent) or where the policy returns ``stop``; the
        policy state stays as after the last sample whose command was sent (``run_control``:
        a tripped sample is not counted). Records every ``every``-th step (0: only the final
        state); ``progress(steps_done, steps_total)`` after each chunk.
        """
        steps, settle_steps, every = int(steps), int(settle_steps), int(every)
        if steps < 1:
            raise InputError(f"steps must be >= 1, got {steps}")
        if settle_steps < 1:
            raise InputError("settle_steps must be >= 1: sample 0 is the settled state")
        if every < 0:
            raise InputError(f"every must be >= 0 (0: no recording), got {every}")
        if not callable(policy):
            raise InputError("policy must be a function (params, state, Observation) -> ...")
        w, n = truth.worlds, self.n
        ref = np.zeros((steps + 1, 0)) if reference is None else np.asarray(reference, float)
        if ref.ndim != 2 or ref.shape[0] != steps + 1 or not np.isfinite(ref).all():
            raise InputError(
                f"reference must be a finite (steps + 1 = {steps + 1}, m) array, got shape "
                f"{ref.shape}"
            )
        if pushes is None:
            pushes = PushSchedule(np.zeros((w, 1)), np.ones((w, 1)), np.zeros((w, 1, 3)))
        pushes = pushes.checked(w)
        init = state if callable(state) else None
        params = _per_world(params, w, "params")
        t_begin, compile_before = time.perf_counter(), self.compile_seconds
        q0 = self._initial_pose(initial_pose, w)
        fields = self.world_fields(truth)
        fields.update(
            push_start=pushes.start.astype(self.dtype),
            push_duration=pushes.duration.astype(self.dtype),
            push_force=pushes.force.astype(self.dtype),
            key=_world_keys(seed, w),
        )
        pad = self._world_padding(w)
        wp = len(pad)
        padded = lambda tree: jax.tree_util.tree_map(lambda a: a[pad], tree)  # noqa: E731
        fields, params, q0 = padded(fields), padded(params), q0[pad].astype(self.dtype)
        zeros = np.zeros((wp, n), self.dtype)
        if init is None:
            pstate = padded(_per_world(state, w, "state"))
        else:  # zeros of init's structure until sample 0 replaces them
            obs = Observation(np.zeros(wp), zeros, zeros, zeros, np.zeros((wp, ref.shape[1])))
            with self._precision():
                shapes = jax.eval_shape(jax.vmap(init), params, obs)
            pstate = jax.tree_util.tree_map(lambda sd: np.zeros(sd.shape, sd.dtype), shapes)
        if every:
            chunk = self._chunk_steps(wp, every, max(steps, settle_steps))
        else:
            chunk = self.chunk_steps or (100 if self.backend == "cpu" else 1000)
            chunk = min(int(chunk), max(steps, settle_steps))
        put, put_shared = self._placement()
        fields, params = put(fields), put(params)
        no_fault = np.full(wp, -1, np.int32)
        carry = (q0, zeros, zeros, np.zeros((wp, 3), self.dtype), zeros, pstate, q0)
        carry = put(carry + (no_fault, np.zeros(wp, np.int32)))
        # the compiled step sees (chunk, m) rows of the reference, never its length
        key = ("closed", policy, init, chunk, every, _signature(fields, params, carry, ref[0]))
        if key not in self._compiled:
            self._compiled[key] = self._build_closed_loop(policy, init, every)
        fn = self._compiled[key]
        t_prepared = time.perf_counter()

        def rows(first: int) -> jax.Array:  # reference rows of samples first .. first+chunk-1
            return put_shared(ref[np.clip(np.arange(first, first + chunk), 0, steps)])

        for s in range(-settle_steps, 0, chunk):
            carry, _, _ = fn(
                fields, params, carry, rows(s + 1), np.int32(s), np.int32(min(chunk, -s))
            )
        q_start = np.asarray(carry[0])[:w].astype(float)
        t_settled, compile_settled = time.perf_counter(), self.compile_seconds
        n_rec = -(-steps // every) if every else 0
        names = ("q", "dq", "current", "command")
        out = {k: np.zeros((w, n_rec, n), self.dtype) for k in names} if every else {}
        pending: tuple | None = None
        for s in range(0, steps, chunk):
            k = min(chunk, steps - s)
            carry, rec, faulted = fn(fields, params, carry, rows(s + 1), np.int32(s), np.int32(k))
            if pending is not None:  # host work overlaps the chunk just dispatched
                self._collect(pending, w, every, out, progress, steps)
            pending = (s, k, rec, faulted)
        if pending is not None:
            self._collect(pending, w, every, out, progress, steps)
        final = jax.tree_util.tree_map(lambda a: np.asarray(a)[:w], carry)
        t_end = time.perf_counter()
        self.last_timing = {
            "prepare": t_prepared - t_begin,
            "settle": t_settled - t_prepared - (compile_settled - compile_before),
            "plan": t_end - t_settled - (self.compile_seconds - compile_settled),
        }
        return ClosedLoopResult(
            (np.arange(n_rec) * every + 1) * DT if every else np.zeros(0),
            *(out.get(k) for k in names),
            state=final[5],
            q_start=q_start,
            fault_step=final[7].astype(int),
            fault_code=final[8].astype(int),
            every=every,
        )

    # ------------------------------------------------------------------ internals
    def _initial_pose(self, pose: Any, w: int) -> np.ndarray:
        if pose is None:
            pose = "home" if "home" in self.robot.named_poses else np.zeros(self.n)
        if isinstance(pose, str):
            pose = self.robot.pose(pose)[arm_joint_indices(self.robot)]
        q = np.asarray(pose, dtype=float)
        if q.shape == (self.n,):
            q = np.broadcast_to(q, (w, self.n))
        if q.shape != (w, self.n) or not np.isfinite(q).all():
            raise InputError(
                f"initial_pose must be a pose name or finite ({self.n},) or ({w}, {self.n}) rad"
            )
        return np.array(q)

    def _world_padding(self, w: int) -> np.ndarray:
        """Indices of ``w`` worlds padded to a multiple of the mesh size with copies of the
        last world (their results are dropped)."""
        shards = 1 if self.mesh is None else self.mesh.size
        return np.minimum(np.arange(-(-w // shards) * shards), w - 1)

    def _chunk_steps(self, worlds: int, every: int, steps: int) -> int:
        k = self.chunk_steps
        if k is None:
            if self.backend == "cpu":
                k = 100
            else:
                per = worlds * self.n * 3 * self.dtype.itemsize / every
                k = int(max(every, min(10_000, _CHUNK_BYTES // max(per, 1))))
            k = min(k, steps)
        return -(-max(int(k), 1) // every) * every

    def _placement(self) -> tuple[Callable, Callable]:
        if self.mesh is None:
            return (lambda x: jax.device_put(x)), (lambda x: jax.device_put(x))
        world = NamedSharding(self.mesh, P("batch"))
        shared = NamedSharding(self.mesh, P())
        return (lambda x: jax.device_put(x, world)), (lambda x: jax.device_put(x, shared))

    def _consume(self, pending, w, every, out, on_chunk, progress, t_total) -> None:
        s, k, rec = pending
        nr = -(-k // every)  # samples of the chunk's valid steps
        q, dq, cur = (np.asarray(a)[:w, :nr] for a in rec)
        first = s // every
        if out:
            out["q"][:, first : first + nr] = q
            out["dq"][:, first : first + nr] = dq
            out["current"][:, first : first + nr] = cur
        if on_chunk is not None:
            t = ((first + np.arange(nr)) * every + 1) * DT
            empty = np.zeros((0, self.n))
            on_chunk(first, MjxRecording(t, q, dq, cur, empty, np.zeros(0, int), every))
        if progress is not None:
            progress(s + k, t_total)

    def _collect(self, pending, w, every, out, progress, t_total) -> None:
        """Copy a closed-loop chunk's samples to the host and report progress."""
        s, k, rec, faulted = pending
        np.asarray(faulted)  # waits for the chunk
        if out:
            nr, first = -(-k // every), s // every
            for name, a in zip(out, rec, strict=True):
                out[name][:, first : first + nr] = np.asarray(a)[:w, :nr]
        if progress is not None:
            progress(s + k, t_total)

    def _build_closed_loop(self, policy: Policy, init: Callable | None, every: int) -> Callable:
        """The jitted chunk function of ``run_closed_loop``: (fields, params, carry, reference
        rows (chunk, m), first step, valid steps) -> (carry, recorded samples or None, number
        of worlds in fault). Carry per world: qpos, qvel, qacc_warmstart, lever of the push
        (site - body COM, m, from the previous step's kinematics, as the CPU Simulator uses
        it), command, policy state, held position, fault step, fault code."""
        mx, d0, dtype, n = self._mx, self._d0, self.dtype, self.n
        lo = jnp.asarray(self._hard[:, 0], dtype)
        hi = jnp.asarray(self._hard[:, 1], dtype)
        torque_limit = jnp.asarray(self._torque_limit, dtype)
        current_limit = jnp.asarray(self.current_limit, dtype)
        over, site, body, nbody = self.overspeed, self._ee_site, self._ee_body, self.model.nbody
        step_fn = _implicitfast_step(self.model, dtype)

        def select(cond, new, old):
            return jax.tree_util.tree_map(lambda a, b: jnp.where(cond, a, b), new, old)

        def world(f, p, carry, k, ref, valid):
            qpos, qvel, qacc, lever, cmd, state, hold, fault_step, code = carry
            run = (k >= 0) & (fault_step < 0)  # CURRENT mode (settling, k < 0: held)
            torque = cmd / f["ratio"]
            over_effort = run & jnp.any(jnp.abs(torque) > torque_limit)
            t0 = k * DT
            on = (f["push_start"] <= t0) & (t0 < f["push_start"] + f["push_duration"])
            force = jnp.where(on[:, None], f["push_force"], 0.0).sum(axis=0)
            wrench = jnp.concatenate([force, jnp.cross(lever, force)])
            model = {key: f[key] for key in _WORLD_MODEL_FIELDS if key in f}
            model["actuator_biasprm"] = jnp.where(run, 0.0, f["actuator_biasprm"])
            d = d0.replace(
                qpos=qpos,
                qvel=qvel,
                qacc_warmstart=qacc,
                ctrl=jnp.where(run, torque, f["kp"] * hold),
                xfrc_applied=jnp.zeros((nbody, 6), dtype).at[body].set(wrench),
            )
            *physics, fwd = step_fn(mx.tree_replace(model), d)
            q1, dq1, acc1, tau = (a.astype(dtype) for a in physics)
            lever1 = (fwd.site_xpos[site] - fwd.xipos[body]).astype(dtype)
            z = jax.random.normal(jax.random.fold_in(f["key"], jnp.maximum(k + 1, 0)), (n,), dtype)
            cur1 = f["ratio"] * tau + f["noise"] * z
            at_limit = jnp.any((q1 <= lo) | (q1 >= hi))
            fast = jnp.any(jnp.abs(dq1) > over)
            fault = run & (at_limit | over_effort | fast)
            # the next command, from the state just measured (sample k + 1)
            obs = Observation((k + 1) * DT, q1, dq1, cur1, ref)
            state_in = state if init is None else select(k + 1 == 0, init(p, obs), state)
            cmd1, state1, stop = policy(p, state_in, obs)
            cmd1 = cmd1.astype(dtype)
            live = (k + 1 >= 0) & (fault_step < 0) & ~fault
            refused = live & ~jnp.all(jnp.abs(cmd1) <= current_limit)  # NaN fails too
            stop = live & ~refused & jnp.asarray(stop, bool)
            accept = live & ~refused & ~stop
            event = fault | refused | stop
            bits = (
                FAULT_LIMIT * (fault & at_limit)
                + FAULT_EFFORT * (fault & over_effort)
                + FAULT_OVERSPEED * (fault & fast)
                + FAULT_REFUSED * refused
                + FAULT_STOPPED * stop
            ).astype(jnp.int32)
            new = (
                q1,
                dq1,
                acc1,
                lever1,
                jnp.where(accept, cmd1, cmd),
                select(accept, state1, state_in),
                jnp.where(event, q1, hold),
                jnp.where(event, k + 1, fault_step),
                jnp.where(event, bits, code),
            )
            return select(valid, new, carry), (q1, dq1, cur1, cmd)

        vworld = jax.vmap(world, in_axes=(0, 0, 0, None, None, None))

        def chunk_fn(f, p, carry, refs, start, n_valid):
            def step(c, i, ref):
                return vworld(f, p, c, (start + i).astype(jnp.int32), ref, i < n_valid)

            carry, rec = _scan_decimated(step, carry, refs, every)
            if rec is not None:
                rec = tuple(jnp.swapaxes(a, 0, 1) for a in rec)
            return carry, rec, jnp.sum(carry[7] >= 0)

        return self._ahead_of_time(chunk_fn, carry_arg=2)

    def _function(self, worlds: int, chunk: int, every: int, groups: int) -> Callable:
        key = (worlds, chunk, every, groups)
        if key not in self._compiled:
            self._compiled[key] = self._build_function(chunk, every)
        return self._compiled[key]

    def _build_function(self, chunk: int, every: int) -> Callable:
        mx, d0, dtype = self._mx, self._d0, self.dtype
        model_keys = _WORLD_MODEL_FIELDS
        lo = jnp.asarray(self._hard[:, 0], dtype)
        hi = jnp.asarray(self._hard[:, 1], dtype)
        follow, over = self.following_error, self.overspeed
        groups = chunk // every
        step_fn = _implicitfast_step(self.model, dtype)

        def world_step(f, qpos, qvel, qacc, q_target):
            m = mx.tree_replace({k: f[k] for k in model_keys if k in f})
            d = d0.replace(qpos=qpos, qvel=qvel, qacc_warmstart=qacc, ctrl=f["kp"] * q_target)
            out = step_fn(m, d)[:4]
            return tuple(a.astype(dtype) for a in out)

        vstep = jax.vmap(world_step, in_axes=(0, 0, 0, 0, 0))

        def step(f, carry, i, qr, start, n_valid):
            qpos, qvel, qacc, fault = carry
            target = qr[f["group"]] + f["offset"]  # each world's reference (G, n) -> (W, n)
            q1, dq1, acc1, tau = vstep(f, qpos, qvel, qacc, target)
            valid = i < n_valid
            t = start + i
            bad = (
                ((q1 <= lo) | (q1 >= hi)).any(axis=1)
                | (jnp.abs(dq1) > over).any(axis=1)
                | (jnp.abs(q1 - target) > follow).any(axis=1)
            )
            fault = jnp.where((fault < 0) & bad & valid & (t >= 0), t.astype(fault.dtype), fault)
            keep = lambda new, old: jnp.where(valid, new, old)  # noqa: E731
            carry = (keep(q1, qpos), keep(dq1, qvel), keep(acc1, qacc), fault)
            return carry, (q1, dq1, tau)

        def noise(f, t):
            def one(key, sigma):
                z = jax.random.normal(jax.random.fold_in(key, t), (self.n,), dtype)
                return sigma * z

            return jax.vmap(one)(f["key"], f["noise"])

        def chunk_fn(f, carry, qr, start, n_valid):
            carry, (q, dq, tau) = _scan_decimated(
                lambda c, i, qr_i: step(f, c, i, qr_i, start, n_valid), carry, qr, every
            )
            times = start + jnp.arange(groups) * every
            cur = f["ratio"][None] * tau + jax.vmap(lambda t: noise(f, t))(times)
            return carry, tuple(jnp.swapaxes(a, 0, 1) for a in (q, dq, cur))

        return self._ahead_of_time(chunk_fn, carry_arg=1)

    def _ahead_of_time(self, fn: Callable, carry_arg: int) -> Callable:
        """``fn`` jitted (argument ``carry_arg``, the carry, donated on accelerators) and
        compiled ahead of time on its first call's shapes, timed into ``compile_seconds``."""
        donate = () if self.backend == "cpu" else (carry_arg,)
        jitted = jax.jit(fn, donate_argnums=donate)
        compiled: list[Callable] = []

        def call(*args):
            if not compiled:  # compile ahead of time on the first call's shapes, timed
                t0 = time.perf_counter()
                with self._precision():
                    compiled.append(jitted.lower(*args).compile())
                self.compile_seconds += time.perf_counter() - t0
            return compiled[0](*args)

        return call


def _world_keys(seed: int, worlds: int) -> np.ndarray:
    """(worlds, 2) PRNG keys: world w's is ``fold_in(PRNGKey(seed), w)``."""
    fold = jax.vmap(jax.random.fold_in, (None, 0))
    return np.asarray(fold(jax.random.PRNGKey(seed), jnp.arange(worlds)))


def _per_world(tree: Any, worlds: int, name: str) -> Any:
    """``tree`` with numpy leaves, each with a leading world axis of ``worlds`` (InputError)."""
    tree = jax.tree_util.tree_map(np.asarray, tree)
    for leaf in jax.tree_util.tree_leaves(tree):
        if leaf.ndim < 1 or leaf.shape[0] != worlds:
            raise InputError(f"every array of {name} needs a leading axis of {worlds} worlds")
    return tree


def _signature(*trees: Any) -> tuple:
    """Structure, shapes and dtypes of pytrees (a key of compiled functions)."""
    leaves, struct = jax.tree_util.tree_flatten(trees)
    return (str(struct),) + tuple((tuple(a.shape), str(a.dtype)) for a in leaves)


_WORLD_MODEL_FIELDS = (
    "body_ipos",
    "body_mass",
    "dof_frictionloss",
    "dof_damping",
    "actuator_biasprm",
    "opt.gravity",
)


def _scan_decimated(step: Callable, carry: Any, xs: Any, every: int) -> tuple[Any, Any]:
    """``lax.scan`` of ``step(carry, i, x_i) -> (carry, out)`` over the leading axis of ``xs``
    (a multiple of ``every``), keeping the outputs of steps 0, every, 2 every, ... stacked
    (steps // every, ...); ``every`` = 0 keeps none (returns None). With every > 1 the group's
    first output rides in the carry, so the step appears once in the compiled graph."""
    length = jax.tree_util.tree_leaves(xs)[0].shape[0]
    if every == 0:
        carry, _ = jax.lax.scan(
            lambda c, ix: (step(c, ix[0], ix[1])[0], None), carry, (jnp.arange(length), xs)
        )
        return carry, None
    groups = length // every
    xs = jax.tree_util.tree_map(lambda a: a.reshape((groups, every) + a.shape[1:]), xs)
    if every == 1:
        first = jax.tree_util.tree_map(lambda a: a[:, 0], xs)
        return jax.lax.scan(lambda c, ix: step(c, ix[0], ix[1]), carry, (jnp.arange(groups), first))
    x0 = jax.tree_util.tree_map(lambda a: a[0, 0], xs)
    shapes = jax.eval_shape(lambda c, x: step(c, 0, x)[1], carry, x0)

    def group(c, gx):
        g, xg = gx

        def inner(cc, jx):
            state, kept = cc
            j, x = jx
            state, out = step(state, g * every + j, x)
            kept = jax.tree_util.tree_map(lambda o, k: jnp.where(j == 0, o, k), out, kept)
            return (state, kept), None

        empty = jax.tree_util.tree_map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shapes)
        (c, kept), _ = jax.lax.scan(inner, (c, empty), (jnp.arange(every), xg))
        return c, kept

    return jax.lax.scan(group, carry, (jnp.arange(groups), xs))


def _implicitfast_step(model: mujoco.MjModel, dtype: Any) -> Callable:
    """One ``mj_step`` of MuJoCo C's implicitfast integrator for hinge/slide joints driven
    by joint-transmission actuators: (m, d) -> (qpos, qvel, qacc_warmstart, qfrc_actuator,
    d_forward), the last the data after ``mjx.forward`` at the step's start (kinematics).

    ``mjx.step`` keeps a servo's velocity derivative (-kv) in the implicit matrix even when its
    joint torque is clamped at the effort limit (``jnt_actfrcrange``); MuJoCo C (4.0) leaves it
    out, as the clamped torque no longer depends on the velocity. This step does as C does:
    M_hat = M + dt (diag(dof_damping) - sum over unclamped actuators of gear^2 biasprm[2]),
    qacc = M_hat^-1 (qfrc_smooth + qfrc_constraint), qvel += dt qacc, qpos += dt qvel.
    """
    if not (model.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT).all():
        raise ModelError("the MJX simulator drives joints only")
    if model.actuator_forcelimited.any() or (model.actuator_gaintype != 0).any():
        raise ModelError("the MJX simulator's actuators have fixed gain and no force range")
    jnt = model.actuator_trnid[:, 0]
    dof = model.jnt_dofadr[jnt]
    gear_np = model.actuator_gear[:, 0]
    limited = model.jnt_actfrclimited[jnt].astype(bool)
    lo_np = np.where(limited, model.jnt_actfrcrange[jnt, 0], -np.inf)
    hi_np = np.where(limited, model.jnt_actfrcrange[jnt, 1], np.inf)
    nv, dt = model.nv, float(model.opt.timestep)

    def step(m: mjx.Model, d: mjx.Data) -> tuple[jax.Array, ...]:
        gear, lo, hi = (jnp.asarray(a, dtype) for a in (gear_np, lo_np, hi_np))
        d = mjx.forward(m, d)
        raw = jnp.zeros(nv, dtype).at[dof].add(gear * d.actuator_force)
        clamped = (raw[dof] <= lo) | (raw[dof] >= hi)
        bias_vel = jnp.where(clamped, 0.0, gear * gear * m.actuator_biasprm[:, 2])
        deriv = jnp.zeros(nv, dtype).at[dof].add(bias_vel) - m.dof_damping
        m_hat = mjx.full_m(m, d) - dt * jnp.diag(deriv)
        factor = jax.scipy.linalg.cho_factor(m_hat)
        qacc = jax.scipy.linalg.cho_solve(factor, d.qfrc_smooth + d.qfrc_constraint)
        qvel = d.qvel + dt * qacc
        return d.qpos + dt * qvel, qvel, d.qacc, d.qfrc_actuator, d

    return step
