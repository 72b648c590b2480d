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
from jaxcomp.hardware.mjx.chunks import PyTree
from jaxcomp.hardware.mjx.closed_loop import ClosedLoopResult, Policy, PushSchedule
from jaxcomp.hardware.mjx.gains import servo_gains
from jaxcomp.hardware.mjx.mesh import partitioner, per_device
from jaxcomp.hardware.mjx.model import (
    MIN_FRICTION_LOSS,
    PAYLOAD_BODY,
    build_model,
    end_effector_site,
)
from jaxcomp.hardware.mjx.runner import MjxRecording
from jaxcomp.hardware.mjx.truth import BatchTruth, true_inertial_params
from jaxcomp.hardware.truth import TrueRobot, friction_loss_torque
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices

SETTLE_STEPS = 500  # the CPU Simulator's settling at the initial pose before t = 0


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
        self.effort = np.abs(m.jnt_actfrcrange).max(1)
        # CURRENT mode (run_closed_loop): torque limits (inf where none), the arm's current
        # limits (A, as ArmLimits), the end-effector site and its body (pushes)
        self._torque_limit = np.where(m.jnt_actfrclimited.astype(bool), self.effort, np.inf)
        self.current_limit = ArmLimits.from_robot(self.robot, arm_joint_indices(self.robot)).current
        site = end_effector_site(self.robot)
        self._ee_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
        self._ee_body = int(m.site_bodyid[self._ee_site])
        # this process's first device (MJX's default, jax.devices()[0], is another process's
        # under jax.distributed)
        device = jax.local_devices()[0]
        with self._precision():  # float32: the model's arrays and every traced literal
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
        return jax.default_backend()

    def world_fields(self, truth: BatchTruth) -> dict[str, np.ndarray]:
        """The per-world arrays (W, ...) a run feeds the vmapped step (host, self.dtype):
        MJX model fields by their tree path (``WORLD_MODEL_FIELDS``), plus ``kp`` N m/rad,
        ``ratio`` A/(N m) and ``noise`` A."""
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
        """Each world's settled pose (W, n) rad at t = 0 (the start a plan begins from)."""
        rec = self.run(truth, np.zeros((0, self.n)), initial_pose, settle_steps=settle_steps)
        return rec.q_start

    def run(
        self,
        truth: BatchTruth,
        q_ref: np.ndarray,
        initial_pose: str | Sequence[float] | np.ndarray | None = None,
        *,
        settle_steps: int = SETTLE_STEPS,
        seed: int = 0,
        every: int = 1,
        progress: Callable[[int, int], None] | None = None,
        on_chunk: Callable[[int, MjxRecording], None] | None = None,
        keep: bool = True,
        group: Sequence[int] | np.ndarray | None = None,
        reduce: runner.Reduction | None = None,
        record: Sequence[int] | np.ndarray | None = None,
        world_ids: Sequence[int] | np.ndarray | None = None,
        phase: np.ndarray | None = None,
        noise_step: np.ndarray | None = None,
    ) -> MjxRecording:
        """Drive every world through the position targets ``q_ref`` (T, n) rad at 1 kHz.

        ``q_ref`` may also be (T, G, n): G references run side by side, world w following
        reference ``group[w]`` ((W,) ints in [0, G); e.g. the sweeps of one plan as parallel
        segments).

        Each world starts at ``initial_pose`` (name, (n,) or (W, n) rad; default "home"),
        is servoed there for ``settle_steps`` steps (as a fresh CPU ``Simulator``), then
        follows ``q_ref``: step i commands q_ref[i] and records the state after it. Records
        every ``every``-th sample (0, every, ...); the current noise of world w at step i is
        ``noise_w N(0, 1)`` from ``fold_in(fold_in(PRNGKey(seed), id_w), c)``, ``id_w`` =
        ``world_ids[w]`` (default w) and c = ``noise_step[i, group[w]]`` ((T, G) ints, default i),
        so it depends neither on chunking nor, with global ids, on how worlds are batched
        (nor, with the steps of one plan as ``noise_step``, on where a job runs).
        ``progress(steps_done, steps_total)`` after each chunk;
        ``on_chunk(first_sample, recording_of_the_chunk)`` streams samples; ``keep=False``
        returns q, dq, current as None (bounded host memory; without ``on_chunk`` no sample
        leaves the device). ``record``: only these worlds' samples leave the device (default
        all; q, dq, current then have M = len(record) rows).
        ``reduce``: a ``runner.Reduction`` of every world's samples on the device, its final
        carry returned as ``reduced``. ``phase`` (T, G) of ``runner.PLAN`` (default),
        ``SETTLE`` (faults not counted) or ``RESTART`` (the world set at rest at its reference,
        then settling): several jobs one after another in one world. See ``runner``.
        """
        return runner.run(
            self,
            truth,
            q_ref,
            initial_pose,
            settle_steps=settle_steps,
            seed=seed,
            every=every,
            progress=progress,
            on_chunk=on_chunk,
            keep=keep,
            group=group,
            reduce=reduce,
            record=record,
            world_ids=world_ids,
            phase=phase,
            noise_step=noise_step,
        )

    def run_closed_loop(
        self,
        truth: BatchTruth,
        policy: Policy,
        params: PyTree,
        state: PyTree | None,
        steps: int,
        *,
        reference: np.ndarray | None = None,
        pushes: PushSchedule | None = None,
        initial_pose: str | Sequence[float] | np.ndarray | None = None,
        settle_steps: int = SETTLE_STEPS,
        seed: int = 0,
        every: int = 0,
        progress: Callable[[int, int], None] | None = None,
        world_ids: Sequence[int] | np.ndarray | None = None,
    ) -> ClosedLoopResult:
        """Drive every world in CURRENT mode with ``policy`` for ``steps`` steps of 1 ms.

        Each world settles at ``initial_pose`` under the position servo for ``settle_steps``
        (>= 1) steps, as in ``run``; from t = 0 the policy maps each sample k (``Observation``
        at t = k CONTROL_PERIOD, k = 0 .. steps) to the motor currents (n,) A of step k (the
        last sample's are not applied): torque = current / true ratio, clamped at the effort
        limit, as the CPU Simulator's CURRENT mode (the sample before a step, the command
        after it: ``control.loop.run_control`` in lock step, with ``steps`` cycles). The
        measured current is ratio x applied torque + noise; world w's noise at sample k comes
        from ``fold_in(fold_in(PRNGKey(seed), id_w), k)``, ``id_w`` = ``world_ids[w]``
        (default w): with global ids it does not depend on how the worlds are chunked.

        ``policy`` is a ``Policy(init, step)`` of pure JAX functions of one world, vmapped
        over worlds here; ``params`` is a pytree of (W, ...) arrays; ``state`` the initial
        policy state, a pytree of (W, ...) arrays, or None when ``policy.init`` makes it from
        sample 0. ``reference`` (steps + 1, m), shared by the worlds, gives row k to the
        policy with sample k (None: an empty row). ``pushes`` act on the end effectors (world
        frame).

        A world goes to POSITION mode, holding its measured position, for the rest of the run
        (``fault_step``, ``fault_code``) when, as on the CPU Simulator and the ``Arm``, a joint
        reaches its limit, a torque exceeds the effort limit or a joint ``overspeed`` (the
        sample after the step shows the fault), or at a sample whose command is refused (NaN/inf
        or beyond ``current_limit`` A, never sent) or where the policy returns ``stop``; the
        policy state stays as after the last sample whose command was sent (``run_control``:
        a tripped sample is not counted). Records every ``every``-th step (0: only the final
        state); ``progress(steps_done, steps_total)`` after each chunk. See ``closed_loop``.
        """
        return closed_loop.run(
            self,
            truth,
            policy,
            params,
            state,
            steps,
            reference=reference,
            pushes=pushes,
            initial_pose=initial_pose,
            settle_steps=settle_steps,
            seed=seed,
            every=every,
            progress=progress,
            world_ids=world_ids,
        )

    # ------------------------------------------------------------------ shared by the runs
    def _precision(self) -> AbstractContextManager:
        """Context of JAX's 64-bit mode for this simulator's dtype (jaxcomp enables it)."""
        return jax.enable_x64(self.dtype == jnp.dtype(jnp.float64))

    def _initial_pose(self, pose: str | Sequence[float] | np.ndarray | None, w: int) -> np.ndarray:
        """(w, n) rad: a pose name, (n,) or (w, n) rad; None: ``Robot.idle_pose``."""
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

    def _world_keys(self, seed: int, worlds: int | np.ndarray) -> np.ndarray:
        """(W, 2) PRNG keys of the current noise: world w's is ``fold_in(PRNGKey(seed), w)``
        for w in ``worlds`` (ids, or a count: 0 .. worlds - 1)."""
        ids = np.arange(worlds) if np.ndim(worlds) == 0 else np.asarray(worlds)
        fold = jax.vmap(jax.random.fold_in, (None, 0))
        return np.asarray(fold(jax.random.PRNGKey(seed), jnp.asarray(ids, jnp.int32)))

    def _compiled_function(self, key: Hashable, build: Callable[[], Callable]) -> Callable:
        """The chunk function of ``key``, built once per simulator. ``key`` must hold every
        setting ``build`` reads that may change between runs (thresholds, limits, mesh,
        shapes), so that an entry never goes stale."""
        if key not in self._compiled:
            self._compiled[key] = build()
        return self._compiled[key]

    def _ahead_of_time(
        self, fn: Callable, carry_arg: int, in_specs: Any, out_specs: Any
    ) -> Callable:
        """``fn`` run on every device's worlds (``mesh.per_device`` with these specs; on a
        mesh), jitted (argument ``carry_arg``, the carry, donated on accelerators) and
        compiled ahead of time on its first call's shapes, timed into ``compile_seconds``."""
        donate = () if self.backend == "cpu" else (carry_arg,)
        jitted = jax.jit(per_device(fn, self.mesh, in_specs, out_specs), donate_argnums=donate)
        compiled: list[Callable] = []

        def call(*args):
            if not compiled:  # compile ahead of time on the first call's shapes, timed
                t0 = time.perf_counter()
                with self._precision(), partitioner(self.mesh):
                    compiled.append(jitted.lower(*args).compile())
                self.compile_seconds += time.perf_counter() - t0
            return compiled[0](*args)

        return call

    def _clock(self) -> RunClock:
        """A clock of the run starting now (``RunClock``)."""
        return RunClock(self)


class RunClock:
    """The wall-clock phases of a run: ``mark()`` ends a phase; ``finish()`` sets
    ``sim.last_timing`` to prepare, settle and plan seconds, each without the compile time
    spent in it."""

    def __init__(self, sim: MjxSimulator):
        self.sim = sim
        self.marks = [(time.perf_counter(), sim.compile_seconds)]

    def mark(self) -> None:
        self.marks.append((time.perf_counter(), self.sim.compile_seconds))

    def finish(self) -> None:
        self.mark()
        spans = zip(self.marks[:-1], self.marks[1:], strict=True)
        seconds = [(t1 - t0) - (c1 - c0) for (t0, c0), (t1, c1) in spans]
        self.sim.last_timing = dict(zip(("prepare", "settle", "plan"), seconds, strict=True))
