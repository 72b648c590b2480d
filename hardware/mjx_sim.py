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
from jaxcomp.hardware.interface import DT, trapezoid, trapezoid_duration
from jaxcomp.hardware.truth import DEFAULT_CURRENT_NOISE, TrueRobot
from jaxcomp.params import InertialParams
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import BASE_JOINTS, RobotParams, arm_joint_indices

#: Tolerances of the agreement with the CPU Simulator (float64, noise 0) that the tests assert:
#: max |q| rad, |dq| rad/s, |current| A differences over a recorded plan (measured: 7.6e-9,
#: 3.1e-7, 1.4e-6).
AGREEMENT = {"q": 2e-8, "dq": 1e-6, "current": 5e-6}

SETTLE_STEPS = 500  # the CPU Simulator's settling at the initial pose before t = 0
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


def _ee_body_and_point(robot: Robot) -> tuple[str, np.ndarray]:
    """Name of the end-effector site's body and the site's position in it, m."""
    name = robot.custom_text("jaxcomp_end_effector") or "end_effector"
    m = robot.model
    s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)
    if s < 0:
        raise ModelError(f"the model has no end-effector site {name!r}")
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
    ) -> MjxRecording:
        """Drive every world through the position targets ``q_ref`` (T, n) rad at 1 kHz.

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
        if q_ref.ndim != 2 or q_ref.shape[1] != self.n or not np.isfinite(q_ref).all():
            raise InputError(f"q_ref must be a finite (T, {self.n}) array of rad")
        outside = (q_ref < self._hard[:, 0]) | (q_ref > self._hard[:, 1])
        if outside.any():
            i, j = np.argwhere(outside)[0]
            raise InputError(
                f"q_ref[{i}, {j}] = {q_ref[i, j]:.4g} rad is beyond joint {j}'s limits "
                f"[{self._hard[j, 0]:.4g}, {self._hard[j, 1]:.4g}] rad"
            )
        w, n, t_total = truth.worlds, self.n, q_ref.shape[0]
        t_begin, compile_before = time.perf_counter(), self.compile_seconds
        q0 = self._initial_pose(initial_pose, w)
        fields = self.world_fields(truth)
        keys = np.asarray(
            jax.vmap(jax.random.fold_in, (None, 0))(jax.random.PRNGKey(seed), jnp.arange(w))
        )
        # pad the worlds to a multiple of the mesh size (copies of the last world, dropped)
        shards = 1 if self.mesh is None else self.mesh.size
        wp = -(-w // shards) * shards
        pad = np.minimum(np.arange(wp), w - 1)
        fields = {k: v[pad] for k, v in fields.items()}
        fields["key"] = keys[pad]
        q0 = q0[pad]
        chunk = self._chunk_steps(wp, every, max(t_total, settle_steps, 1))
        fn = self._function(wp, chunk, every)
        put, put_shared = self._placement()
        fields = put(fields)
        t_prepared = time.perf_counter()
        zeros = np.zeros((wp, n), self.dtype)
        carry = put((q0.astype(self.dtype), zeros, zeros, np.full(wp, -1, np.int32)))
        # settle: servo to q0 (target q0 = 0 reference + per-world offset q0)
        settle_fields = dict(fields, offset=put(q0.astype(self.dtype)))
        zero_ref = put_shared(np.zeros((chunk, n), self.dtype))
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
            ref = np.empty((chunk, n), self.dtype)
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

    def _function(self, worlds: int, chunk: int, every: int) -> Callable:
        key = (worlds, chunk, every)
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
            out = step_fn(m, d)
            return tuple(a.astype(dtype) for a in out)

        vstep = jax.vmap(world_step, in_axes=(0, 0, 0, 0, 0))

        def step(f, carry, i, qr, start, n_valid):
            qpos, qvel, qacc, fault = carry
            target = qr[None, :] + f["offset"]
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
            qr = qr.reshape(groups, every, -1)

            def group(carry, xs):
                g, qr_g = xs
                i0 = g * every
                if every == 1:
                    carry, (q, dq, tau) = step(f, carry, i0, qr_g[0], start, n_valid)
                else:  # one step in the graph: the group's first output rides in the carry

                    def inner(c, xs2):
                        state, kept = c
                        j, qr_j = xs2
                        state, out = step(f, state, i0 + j, qr_j, start, n_valid)
                        kept = tuple(
                            jnp.where(j == 0, o, k) for o, k in zip(out, kept, strict=True)
                        )
                        return (state, kept), None

                    empty = tuple(jnp.zeros_like(carry[0]) for _ in range(3))
                    steps = (jnp.arange(every), qr_g)
                    (carry, (q, dq, tau)), _ = jax.lax.scan(inner, (carry, empty), steps)
                cur = f["ratio"] * tau + noise(f, start + i0)
                return carry, (q, dq, cur)

            carry, rec = jax.lax.scan(group, carry, (jnp.arange(groups), qr))
            return carry, tuple(jnp.swapaxes(a, 0, 1) for a in rec)

        jitted = jax.jit(chunk_fn, donate_argnums=(1,) if self.backend != "cpu" else ())
        compiled: list[Callable] = []

        def call(*args):
            if not compiled:  # compile ahead of time on the first call's shapes, timed
                t0 = time.perf_counter()
                with self._precision():
                    compiled.append(jitted.lower(*args).compile())
                self.compile_seconds += time.perf_counter() - t0
            return compiled[0](*args)

        return call


_WORLD_MODEL_FIELDS = (
    "body_ipos",
    "body_mass",
    "dof_frictionloss",
    "dof_damping",
    "actuator_biasprm",
    "opt.gravity",
)


def _implicitfast_step(model: mujoco.MjModel, dtype: Any) -> Callable:
    """One ``mj_step`` of MuJoCo C's implicitfast integrator for hinge/slide joints driven
    by joint-transmission actuators: (m, d) -> (qpos, qvel, qacc_warmstart, qfrc_actuator).

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
        return d.qpos + dt * qvel, qvel, d.qacc, d.qfrc_actuator

    return step
