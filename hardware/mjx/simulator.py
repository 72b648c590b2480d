"""``MjxSimulator``: thousands of true arms in MJX, stepped side by side.

The simulator holds what every run shares: the MjModel (``model.build_model``) and its MJX
copy, the per-world model fields of a ``BatchTruth`` (``world_fields``), the initial pose, the
placement of the worlds on the devices (``mesh``), and the compiled chunk functions with their
compile time. Its two runs live in their own modules: ``run`` (POSITION mode, a shared
position reference: ``runner``) and ``run_closed_loop`` (CURRENT mode driven by a ``Policy``:
``closed_loop``). Units: rad, rad/s, A, N m, kg, m, s.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.sharding import Mesh
from mujoco import mjx

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.interface import ArmLimits
from jaxcomp.hardware.mjx import closed_loop, runner
from jaxcomp.hardware.mjx.chunks import chunk_length
from jaxcomp.hardware.mjx.gains import servo_gains
from jaxcomp.hardware.mjx.mesh import devices, partitioner, per_device
from jaxcomp.hardware.mjx.model import (
    MIN_FRICTION_LOSS,
    PAYLOAD_BODY,
    build_model,
    end_effector_site,
)
from jaxcomp.hardware.mjx.runner import SETTLE_STEPS
from jaxcomp.hardware.mjx.truth import BatchTruth, true_inertial_params
from jaxcomp.hardware.truth import TrueRobot, friction_loss_torque
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices


class MjxSimulator:
    """MJX simulation of many true arms (see the package docstring of ``hardware.mjx``).

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

    The robot, payload, dtype and model are fixed at construction; the thresholds, mesh and
    chunking may be changed between runs (they are part of the compiled functions' keys).
    """

    #: s, as ``SimArm.current_lag``: the current recorded with a state was computed at the
    #: state one step before.
    current_lag = CONTROL_PERIOD

    def __init__(
        self,
        robot: str | Path | Robot = "gen3_lite",
        *,
        payload: bool = False,
        dtype: jnp.dtype | type = jnp.float64,
        servo_bandwidth: float = 500.0,
        friction_timeconst: float = 2 * CONTROL_PERIOD,
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
        self._hard.flags.writeable = False  # public, read-only (``joint_limits``)
        self.effort = np.abs(m.jnt_actfrcrange).max(1)
        # CURRENT mode (run_closed_loop): torque limits (inf where none), the arm's current
        # limits (A, as ArmLimits), the end-effector site and its body (pushes)
        self._torque_limit = np.where(m.jnt_actfrclimited.astype(bool), self.effort, np.inf)
        self._torque_limit.flags.writeable = False  # public, read-only (``torque_limit``)
        self.current_limit = ArmLimits.from_robot(self.robot, arm_joint_indices(self.robot)).current
        site = end_effector_site(self.robot)
        self._ee_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
        self._ee_body = int(m.site_bodyid[self._ee_site])
        # this process's first device (MJX's default, jax.devices()[0], is another process's
        # under jax.distributed)
        device = jax.local_devices()[0]
        with self.precision():  # float32: the model's arrays and every traced literal
            self._mx = mjx.put_model(m, device=device)
            self._d0 = mjx.make_data(self._mx, device=device)
        self._compiled: dict[Hashable, Callable] = {}
        self.compile_seconds = 0.0  # time spent compiling chunk functions so far
        #: wall seconds of the last run: prepare (truth -> fields, gains), settle, plan
        #: (stepping and recording, compilation excluded)
        self.last_timing: dict[str, float] = {}

    # ------------------------------------------------------------------ public
    @property
    def backend(self) -> str:
        """JAX's default backend ("cpu", "gpu", ...), which the runs compile for."""
        return jax.default_backend()

    def world_fields(self, truth: BatchTruth) -> dict[str, np.ndarray]:
        """The per-world arrays a run feeds the vmapped step.

        Args:
            truth: the worlds' true robots (W worlds, this simulator's joints and links).

        Returns:
            Host arrays (W, ...) of ``dtype``: MJX model fields by their tree path
            (``WORLD_MODEL_FIELDS``; body_ipos m in the body frame, dof_frictionloss N m,
            dof_damping N m s/rad, actuator_biasprm, opt.gravity m/s^2 world frame,
            body_mass kg with a payload), plus ``kp`` (n,) N m/rad, ``ratio`` (n,) A/(N m)
            and ``noise`` () A.

        Raises:
            InputError: a truth for other joints or links, or with a payload the simulator
                was built without.
        """
        m, w, n = self.model, truth.worlds, self.n
        if truth.ratio.shape[1] != n or truth.com_offset.shape[1] != len(self._body_ids):
            raise InputError(
                f"truth is for {truth.ratio.shape[1]} joints / {truth.com_offset.shape[1]} links,"
                f" the model has {n} / {len(self._body_ids)}"
            )
        if truth.payload.any() and not self.payload:
            raise InputError("truth has a payload: build the MjxSimulator with payload=True")
        kp, kv = servo_gains(
            self.robot,
            true_inertial_params(self.robot, truth),
            truth.gravity,
            self.servo_bandwidth,
        )
        ipos = np.broadcast_to(m.body_ipos, (w,) + m.body_ipos.shape).copy()
        ipos[:, self._body_ids] += truth.com_offset
        bias = np.broadcast_to(m.actuator_biasprm, (w,) + m.actuator_biasprm.shape).copy()
        bias[:, :, :3] = np.stack([np.zeros_like(kp), -kp, -kv], axis=-1)
        fields = {
            "body_ipos": ipos,
            "dof_frictionloss": friction_loss_torque(
                truth.friction, truth.ratio, MIN_FRICTION_LOSS
            ),
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
        self,
        truth: BatchTruth,
        initial_pose: str | Sequence[float] | np.ndarray | None = None,
        settle_steps: int = SETTLE_STEPS,
    ) -> np.ndarray:
        """Each world's settled pose at t = 0 (the start a plan begins from).

        Args:
            truth: the worlds' true robots (W worlds).
            initial_pose: a pose name, (n,) or (W, n) rad; None: ``Robot.idle_pose``.
            settle_steps: steps of the settling.

        Returns:
            (W, n) rad.
        """
        rec = self.run(truth, np.zeros((0, self.n)), initial_pose, settle_steps=settle_steps)
        return rec.q_start

    #: ``run(truth, q_ref, initial_pose=None, *, settle_steps=SETTLE_STEPS, seed=0, every=1,
    #: ...) -> MjxRecording``: every world in POSITION mode through the position targets
    #: ``q_ref`` (``runner.run``, documented there).
    run = runner.run
    #: ``run_closed_loop(truth, policy, params, state, steps, *, reference=None, pushes=None,
    #: ...) -> ClosedLoopResult``: every world in CURRENT mode driven by a ``Policy``
    #: (``closed_loop.run``, documented there).
    run_closed_loop = closed_loop.run

    # ------------------------------------------------------------------ shared by the runs
    @property
    def mjx_model(self) -> mjx.Model:
        """The MJX model every world shares, on this process's first device (a run replaces
        its per-world fields, ``world_fields``, with ``tree_replace``)."""
        return self._mx

    @property
    def mjx_data(self) -> mjx.Data:
        """The MJX data a world's step starts from (``mjx.make_data``; a run replaces its
        qpos, qvel, qacc_warmstart, ctrl and applied forces)."""
        return self._d0

    @property
    def joint_limits(self) -> np.ndarray:
        """(n, 2) rad, read-only: each arm joint's hard limits [lower, upper]."""
        return self._hard

    @property
    def torque_limit(self) -> np.ndarray:
        """(n,) N m, read-only: each actuator's effort limit in CURRENT mode (inf where the
        model sets none)."""
        return self._torque_limit

    @property
    def ee_site(self) -> int:
        """The end-effector site's id in ``model`` (where pushes act)."""
        return self._ee_site

    @property
    def ee_body(self) -> int:
        """The id in ``model`` of the body that carries the end-effector site."""
        return self._ee_body

    def precision(self) -> AbstractContextManager:
        """JAX's 64-bit mode for this simulator's dtype (jaxcomp enables it).

        Returns:
            A context manager: traced literals and arrays made inside it take ``dtype``.
        """
        return jax.enable_x64(self.dtype == jnp.dtype(jnp.float64))

    def initial_poses(self, pose: str | Sequence[float] | np.ndarray | None, w: int) -> np.ndarray:
        """Each world's initial pose.

        Args:
            pose: a pose name, (n,) or (w, n) rad; None: ``Robot.idle_pose``.
            w: the number of worlds.

        Returns:
            (w, n) rad, a new array.

        Raises:
            InputError: not a pose name, or not finite of shape (n,) or (w, n).
        """
        if pose is None:
            pose = self.robot.idle_pose[arm_joint_indices(self.robot)]
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

    def world_keys(self, seed: int, worlds: int | np.ndarray) -> np.ndarray:
        """The PRNG keys of the worlds' current noise.

        Args:
            seed: the run's seed.
            worlds: the worlds' ids (W,) ints, or a count W (ids 0 .. W - 1).

        Returns:
            (W, 2) uint32 keys: world w's is ``fold_in(PRNGKey(seed), id_w)``.
        """
        ids = np.arange(worlds) if np.ndim(worlds) == 0 else np.asarray(worlds)
        fold = jax.vmap(jax.random.fold_in, (None, 0))
        return np.asarray(fold(jax.random.PRNGKey(seed), jnp.asarray(ids, jnp.int32)))

    def chunk_length(self, worlds: int, every: int, steps: int) -> int:
        """Steps per compiled call of a run of this simulator (``chunks.chunk_length`` with
        its ``chunk_steps``, backend, mesh, joints and dtype).

        Args:
            worlds: the run's worlds, padded to the mesh (``mesh.world_padding``).
            every: the recording decimation (>= 1).
            steps: the run's longest phase, steps.

        Returns:
            The chunk length, steps (a multiple of ``every``).
        """
        per_device = worlds // devices(self.mesh)
        return chunk_length(
            self.chunk_steps, self.backend, per_device, self.n, self.dtype.itemsize, every, steps
        )

    def compiled_function(self, key: Hashable, build: Callable[[], Callable]) -> Callable:
        """The chunk function of ``key``, built once per simulator.

        Args:
            key: hashable; it must hold every setting ``build`` reads that may change between
                runs (thresholds, limits, mesh, shapes), so that an entry never goes stale.
            build: makes the function (called on the first use of ``key``).

        Returns:
            The function.
        """
        if key not in self._compiled:
            self._compiled[key] = build()
        return self._compiled[key]

    @property
    def compiled_keys(self) -> tuple[Hashable, ...]:
        """The keys of the chunk functions built so far (``compiled_function``), oldest first."""
        return tuple(self._compiled)

    def ahead_of_time(
        self, fn: Callable, carry_arg: int, in_specs: Any, out_specs: Any
    ) -> Callable:
        """``fn`` on every device's worlds, jitted and compiled ahead of time.

        Args:
            fn: a chunk function of the worlds of one device.
            carry_arg: the index of its carry argument (donated on accelerators).
            in_specs, out_specs: its arguments' and outputs' partition specs
                (``mesh.per_device``; used on a mesh).

        Returns:
            The function, compiled on its first call's shapes; the compile time goes into
            ``compile_seconds``.
        """
        donate = () if self.backend == "cpu" else (carry_arg,)
        jitted = jax.jit(per_device(fn, self.mesh, in_specs, out_specs), donate_argnums=donate)
        compiled: list[Callable] = []

        def call(*args):
            if not compiled:  # compile ahead of time on the first call's shapes, timed
                t0 = time.perf_counter()
                with self.precision(), partitioner(self.mesh):
                    compiled.append(jitted.lower(*args).compile())
                self.compile_seconds += time.perf_counter() - t0
            return compiled[0](*args)

        return call

    def run_clock(self) -> RunClock:
        """A clock of the run starting now.

        Returns:
            The ``RunClock``.
        """
        return RunClock(self)


class RunClock:
    """The wall-clock phases of a run: ``mark()`` ends a phase; ``finish()`` sets
    ``sim.last_timing`` to prepare, settle and plan seconds, each without the compile time
    spent in it."""

    def __init__(self, sim: MjxSimulator):
        self.sim = sim
        self.marks = [(time.perf_counter(), sim.compile_seconds)]

    def mark(self) -> None:
        """End a phase now."""
        self.marks.append((time.perf_counter(), self.sim.compile_seconds))

    def finish(self) -> None:
        """End the last phase and set ``sim.last_timing`` (prepare, settle, plan s)."""
        self.mark()
        spans = zip(self.marks[:-1], self.marks[1:], strict=True)
        seconds = [(t1 - t0) - (c1 - c0) for (t0, c0), (t1, c1) in spans]
        self.sim.last_timing = dict(zip(("prepare", "settle", "plan"), seconds, strict=True))
