"""The simulated robot: MuJoCo on the CPU at 1 kHz, standing in for the real Gen3 Lite.

``Simulator`` owns one MjModel/MjData of the *true* robot (the nominal model changed by a
``TrueRobot``): the arm alone (``gen3_lite``) or on its Dingo-O base (``mobile_gen3_lite``).
Each arm joint gets one MuJoCo actuator that is either the robot's own stiff servo (POSITION and
VELOCITY modes: a PD whose damping MuJoCo integrates implicitly) or a pure torque source
(CURRENT mode: torque = commanded current / true ratio). The measured current is the true
ratio times the torque the actuator actually applied over the step plus Gaussian noise: after
MuJoCo's effort-limit clipping, and with the servo's damping at the step's new velocity, as
the implicit integrator applies it (``qfrc_actuator`` holds it at the old velocity: the
difference, kv (dq_new - dq_old), is an inertia of 1 ms x kv that no real arm's current shows:
amperes while an arm swings). Coulomb friction is MuJoCo's ``frictionloss`` with a stiff
solver reference, so that it is delivered in full on every joint.

``Simulator.arm`` is its ``Arm`` interface (``SimArm``), ``Simulator.base`` its ``Base``
(``SimBase``). Lock-step by default (each ``cycle`` advances 1 ms, as fast as the CPU allows);
with ``realtime=True`` each step is paced to the wall clock.
"""

from __future__ import annotations

import math
import operator
import time
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from jaxcomp import checks
from jaxcomp.constants import CONTROL_PERIOD, STANDARD_GRAVITY
from jaxcomp.errors import InputError, ModelError
from jaxcomp.hardware.interaction import Interaction, Push, Rope, vec3
from jaxcomp.hardware.interface import ArmState, BaseState, ControlMode
from jaxcomp.hardware.mecanum import TwistLimiter, TwistLimits
from jaxcomp.hardware.servo import gain_poses, pd_gains
from jaxcomp.hardware.sim_model import simulation_spec
from jaxcomp.hardware.sim_viewer import open_viewer
from jaxcomp.hardware.truth import TrueRobot
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import BASE_JOINTS, arm_joint_indices

if TYPE_CHECKING:
    from jaxcomp.hardware.sim_arm import SimArm

_POS, _VEL, _CUR = 0, 1, 2
_CODE = {ControlMode.POSITION: _POS, ControlMode.VELOCITY: _VEL, ControlMode.CURRENT: _CUR}
_MODE = {v: k for k, v in _CODE.items()}
_NOISE_BLOCK = 4096
#: A push or wrench on the end effector may be at most this many times the weight of the arm
#: (the links its joints move, under standard gravity): beyond, the simulation breaks down
#: (``Simulator.max_push_force``; 396 N for the Gen3 Lite).
PUSH_LIMIT_WEIGHTS = 10.0
#: MuJoCo's warnings after which it resets the simulation (NaN, Inf or huge values).
_RESET_WARNINGS = tuple(
    int(w)
    for w in (
        mujoco.mjtWarning.mjWARN_BADQPOS,
        mujoco.mjtWarning.mjWARN_BADQVEL,
        mujoco.mjtWarning.mjWARN_BADQACC,
    )
)


def _fast_index(adr: np.ndarray) -> slice | np.ndarray:
    """A slice for contiguous addresses (views, no copies), else the index array."""
    if len(adr) and np.all(np.diff(adr) == 1):
        return slice(int(adr[0]), int(adr[-1]) + 1)
    return adr


class Simulator:
    """A MuJoCo simulation of the true robot at 1 kHz (see the module docstring).

    Args:
        robot: built-in name, model path or ``Robot`` (the nominal model).
        truth: the hidden true robot; default ``TrueRobot.draw(robot, seed)`` (None for a
            model without arm joints).
        seed: seed of the drawn truth and of the current noise.
        initial_pose: arm pose name or (n,) rad to start from (default ``Robot.idle_pose``).
        realtime: pace each step to the wall clock instead of lock step.
        viewer: open MuJoCo's passive viewer when a display exists (headless otherwise).
        servo_bandwidth: rad/s, natural frequency of the position servo at each joint's
            smallest effective inertia (stiffer where a joint's gravity load asks for it:
            ``hardware.servo``).
        following_error: rad, a servoed joint further than this from its target faults.
        overspeed: rad/s, a joint faster than this faults.
        friction_timeconst: s, solver time constant of the friction loss (default 2 x 1 ms).

    The servo (POSITION, VELOCITY) is ``kp (q_ref - q) + kv (dq_ref - dq)``, clipped by the
    effort limits; in POSITION mode ``dq_ref = 0`` (no feed-forward, so target steps cause no
    velocity spikes), in VELOCITY mode ``q_ref`` integrates ``dq_ref``. In CURRENT mode the
    torque is ``c / r``; a current whose torque exceeds the effort limit is clipped and faults.

    Pushes and wrenches beyond ``max_push_force`` are refused. Should MuJoCo still find NaN,
    Inf or huge values (it then resets the simulation to the model's reference pose), the
    interaction is removed and the arm faults with "simulator unstable", holding in position
    mode.
    """

    def __init__(
        self,
        robot: str | Path | Robot = "gen3_lite",
        truth: TrueRobot | None = None,
        *,
        seed: int = 0,
        initial_pose: str | Sequence[float] | None = None,
        realtime: bool = False,
        viewer: bool = False,
        servo_bandwidth: float = 500.0,
        following_error: float = 0.1,
        overspeed: float = 2.0,
        friction_timeconst: float = 2 * CONTROL_PERIOD,
    ):
        self.robot = load_robot(robot)
        if self.robot.source is None:
            raise ModelError("the simulator needs a robot loaded from a model file")
        self.arm_joints = arm_joint_indices(self.robot)
        names = self.robot.joint_names
        self.base_joints = [names.index(b) for b in BASE_JOINTS if b in names]
        self.arm_joint_names = tuple(names[j] for j in self.arm_joints)
        self.n = n = len(self.arm_joints)
        self.model = m = self._build()
        if n:
            self.truth = truth if truth is not None else TrueRobot.draw(self.robot, seed)
            self.truth.apply(m, self.robot, friction_timeconst)
        else:  # a bare base: nothing hidden
            self.truth = None
        self.data = mujoco.MjData(m)
        self._resets = 0  # MuJoCo's resets seen (``_check_stability``)
        self._qadr = m.jnt_qposadr[self.arm_joints]
        self._dadr = m.jnt_dofadr[self.arm_joints]
        self._qadr.flags.writeable = self._dadr.flags.writeable = False  # public, read-only
        self._qsl, self._dsl = _fast_index(self._qadr), _fast_index(self._dadr)
        self._views()
        self._badr = m.jnt_dofadr[self.base_joints]
        self._bqadr = m.jnt_qposadr[self.base_joints]
        self._bqadr.flags.writeable = False  # public, read-only
        self._base_views()
        self._ratio = self.truth.ratio.copy() if n else np.ones(0)
        limited = m.jnt_actfrclimited[self.arm_joints].astype(bool)
        self.effort = np.where(limited, np.abs(m.jnt_actfrcrange[self.arm_joints]).max(1), np.inf)
        self._effort = self.effort.tolist()
        self._hard = self.robot.joint_limits[self.arm_joints]
        self.following_error = float(following_error)
        self.overspeed = float(overspeed)
        self._rng = np.random.default_rng(self.truth.seed + 1 if n else 0)
        self._noise = np.zeros((0, n))
        self._k = 0
        self.interaction = Interaction()
        self._ee_site = self._site_id() if n else -1
        self._ee_body = int(m.site_bodyid[self._ee_site]) if n else -1
        # per-joint servo state
        self._mode = np.full(n, _POS)
        self._q_ref = np.zeros(n)
        self._dq_ref = np.zeros(n)
        self._ctrl = np.zeros(n)
        self._follow_w = np.zeros(n)
        self._over_effort = False
        self._faults: list[str] = []
        self.fault_joints: set[int] = set()
        self.current = np.zeros(n)
        self._applied = np.zeros(n)
        self._gains(servo_bandwidth)
        self.twist_limits = TwistLimits.from_robot(self.robot)
        self._limiter = TwistLimiter(self.twist_limits)
        self._realtime = realtime
        self.viewer = None
        self._last_sync = 0.0
        self._set_pose(initial_pose)
        self._wall0 = time.perf_counter()
        if viewer:
            self.viewer = open_viewer(self.model, self.data)

    def _views(self) -> None:
        """Cached numpy views into MjData (valid for its lifetime; they see every update)."""
        d, n = self.data, self.n
        self._v_ctrl = d.ctrl[:n]
        self._v_force = d.actuator_force[:n]
        self._v_q = d.qpos[self._qsl]
        self._v_dq = d.qvel[self._dsl]
        self._v_qfrc = d.qfrc_actuator[self._dsl]
        self._v_damping = self.model.actuator_biasprm[:n, 2]  # -kv of a servo, 0 in current mode
        self._dq_before = np.zeros(n)

    def _base_views(self) -> None:
        """Indices (slices when contiguous) of the base joints' qpos and qvel."""
        self._bqsl, self._bdsl = _fast_index(self._bqadr), _fast_index(self._badr)

    # ----------------------------------------------------------------- model
    def _build(self) -> mujoco.MjModel:
        spec = simulation_spec(self.robot, list(self.arm_joints) + self.base_joints)
        try:
            return spec.compile()
        except Exception as exc:
            raise ModelError(f"cannot compile the simulation model: {exc}") from None

    def _site_id(self) -> int:
        name = self.robot.end_effector
        s = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, name)
        if s < 0:
            raise ModelError(f"the model has no end-effector site {name!r}")
        return s

    def _gains(self, bandwidth: float) -> None:
        """The position servo's PD gains (``hardware.servo.pd_gains``) from each arm joint's
        effective inertia range (I_min: smallest 1 / (M^-1)_jj, I_max: largest M_jj) and its
        largest gravity torque (the model's gravity) over ``servo.gain_poses``."""
        m, d = self.model, mujoco.MjData(self.model)
        i_min = np.full(self.n, np.inf)
        i_max, load = np.zeros(self.n), np.zeros(self.n)
        full = np.zeros((m.nv, m.nv))
        for pose in gain_poses(self._hard):
            d.qpos[self._qadr] = pose
            mujoco.mj_forward(m, d)  # at rest: qfrc_bias is the gravity torque
            mujoco.mj_fullM(m, d, full)
            i_min = np.minimum(i_min, 1.0 / np.diag(np.linalg.inv(full))[self._dadr])
            i_max = np.maximum(i_max, np.diag(full)[self._dadr])
            load = np.maximum(load, np.abs(d.qfrc_bias[self._dadr]))
        self.servo_kp, self.servo_kv = pd_gains(i_min, i_max, load, bandwidth)
        if self.base_joints:
            mujoco.mj_forward(m, d)
            mujoco.mj_fullM(m, d, full)
            kv = full[self._badr, self._badr] / 0.02  # base velocity servo, 20 ms
            for i, k in enumerate(kv):
                m.actuator_gainprm[self.n + i, 0] = k
                m.actuator_biasprm[self.n + i, :3] = [0.0, 0.0, -k]

    def _set_pose(self, pose) -> None:
        if pose is None:
            pose = self.robot.idle_pose[self._qadr]
        if isinstance(pose, str):
            pose = self.robot.pose(pose)[self._qadr]
        q = checks.array(pose, "initial_pose (or a pose name)", n=self.n, unit="rad")
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qadr] = q
        mujoco.mj_forward(self.model, self.data)
        self._mode[:] = _POS
        self._apply_modes(range(self.n))
        self.step(500, pace=False)  # let the servo take up the load before t = 0
        self._faults.clear()
        self.data.time = 0.0
        self._limiter = TwistLimiter(self.twist_limits)

    # ----------------------------------------------------------------- arm (no checks here)
    @property
    def t(self) -> float:
        """Simulation time, s."""
        return float(self.data.time)

    @property
    def arm_qposadr(self) -> np.ndarray:
        """(n,) int, read-only: each arm joint's address in ``data.qpos`` (MuJoCo's
        ``jnt_qposadr``); ``data.qpos[sim.arm_qposadr]`` are the arm's angles, rad."""
        return self._qadr

    @property
    def arm_dofadr(self) -> np.ndarray:
        """(n,) int, read-only: each arm joint's address in ``data.qvel`` (MuJoCo's
        ``jnt_dofadr``); ``data.qvel[sim.arm_dofadr]`` are the arm's velocities, rad/s."""
        return self._dadr

    @property
    def base_qposadr(self) -> np.ndarray:
        """(3,) int, read-only (empty without a base): the planar base joints' addresses in
        ``data.qpos``; ``data.qpos[sim.base_qposadr]`` are the base's x m, y m, yaw rad."""
        return self._bqadr

    @property
    def modes(self) -> tuple[ControlMode, ...]:
        """Each arm joint's control mode, (n,)."""
        return self._modes

    @property
    def faults(self) -> tuple[str, ...]:
        """The latched fault messages, oldest first."""
        return tuple(self._faults)

    def set_modes(self, changes: dict[int, ControlMode]) -> None:
        """Switch arm joints' modes; servo modes start holding q.

        Args:
            changes: arm joint index -> its new mode.
        """
        for j, mode in changes.items():
            self._mode[j] = _CODE[mode]
        self._apply_modes(changes)

    def _apply_modes(self, joints) -> None:
        q = self.data.qpos[self._qadr]
        for j in joints:
            servo = self._mode[j] != _CUR
            self.model.actuator_biasprm[j, :3] = (
                [0.0, -self.servo_kp[j], -self.servo_kv[j]] if servo else [0.0, 0.0, 0.0]
            )
            self._q_ref[j] = q[j]
            self._dq_ref[j] = 0.0
        self._modes = tuple(_MODE[int(c)] for c in self._mode)
        self._is_pos = self._mode == _POS
        self._is_vel = self._mode == _VEL
        self._is_cur = self._mode == _CUR
        self._all_pos = bool(self._is_pos.all())
        self._all_cur = bool(self._is_cur.all())
        self._follow_w = np.where(self._is_cur, 0.0, 1.0 / self.following_error)
        self._ctrl = np.where(self._is_cur, 0.0, self.servo_kp * self._q_ref)
        self._over_effort = False

    def set_targets(self, position: np.ndarray, velocity: np.ndarray, current: np.ndarray) -> None:
        """This step's targets, each read in its joint's mode.

        Args:
            position: (n,) rad (POSITION). velocity: (n,) rad/s (VELOCITY).
            current: (n,) A (CURRENT: torque = current / true ratio).
        """
        if self._all_pos:
            self._q_ref = position.copy()
            self._ctrl = self.servo_kp * position
            return
        if self._all_cur:
            self._ctrl = torque = current / self._ratio
            # on floats: cheaper than three array operations
            self._over_effort = any(map(operator.gt, map(abs, torque.tolist()), self._effort))
            return
        self._dq_ref = np.where(self._is_vel, velocity, 0.0)
        self._q_ref = np.where(self._is_pos, position, self._q_ref + self._dq_ref * CONTROL_PERIOD)
        torque = current / self._ratio
        servo = self.servo_kp * self._q_ref + self.servo_kv * self._dq_ref
        self._ctrl = np.where(self._is_cur, torque, servo)
        self._over_effort = bool((self._is_cur & (np.abs(torque) > self.effort)).any())

    def hold(self) -> None:
        """Every arm joint to the position servo, holding where it is."""
        self.set_modes({j: ControlMode.POSITION for j in range(self.n)})

    def fault(self, message: str, joint: int | None = None) -> None:
        """Latch a fault and hold the arm, as the robot does.

        Args:
            message: the fault's message. joint: the arm joint index at fault, or None.
        """
        if message not in self._faults:
            self._faults.append(message)
        if joint is not None:
            self.fault_joints.add(joint)
        self.hold()

    def clear_faults(self) -> None:
        """Forget the latched faults (the modes stay as they are)."""
        self._faults.clear()
        self.fault_joints.clear()

    def arm_state(self) -> ArmState:
        """The arm's state now.

        Returns:
            ``ArmState``: time s, q (n,) rad, dq (n,) rad/s, current (n,) A, faults, modes.
        """
        return ArmState(
            self.data.time,
            self._v_q.copy(),
            self._v_dq.copy(),
            self.current,
            tuple(self._faults),
            self._modes,
        )

    @property
    def applied_torque(self) -> np.ndarray:
        """(n,) N m the arm's actuators applied during the last step (after clipping, the servo
        damping at the step's new velocity): the measured current over the true ratio."""
        return self._applied.copy()

    @property
    def friction_torque(self) -> np.ndarray:
        """(n,) N m the friction loss constraint exerted on each arm joint in the last step."""
        d = self.data
        out = np.zeros(self.n)
        for i in range(d.nefc):
            if d.efc_type[i] == mujoco.mjtConstraint.mjCNSTR_FRICTION_DOF:
                hit = np.flatnonzero(self._dadr == d.efc_id[i])
                if hit.size:
                    out[hit[0]] = d.efc_force[i]
        return out

    # ----------------------------------------------------------------- base
    @property
    def has_base(self) -> bool:
        """True when the model has the mobile base's three joints (base_x, base_y, base_yaw)."""
        return len(self.base_joints) == 3

    def command_twist(self, twist: np.ndarray) -> None:
        """Set the twist the base follows (through its ``TwistLimiter``).

        Args:
            twist: (3,) body twist (vx m/s, vy m/s, wz rad/s), validated by the caller.
        """
        self._limiter.command(twist, self.t)

    def stop_base(self) -> None:
        """Bring the base to a stop (within its limits)."""
        self._limiter.stop()

    def base_state(self) -> BaseState:
        """The base's state now.

        Returns:
            ``BaseState``: time s, pose (x m, y m, yaw rad) world frame, body twist (vx m/s,
            vy m/s, wz rad/s).
        """
        d = self.data
        x, y, yaw = d.qpos[self._bqsl].tolist()  # floats: cheaper than numpy scalars
        vxw, vyw, wz = d.qvel[self._bdsl].tolist()
        c, s = math.cos(yaw), math.sin(yaw)
        twist = np.array((c * vxw + s * vyw, -s * vxw + c * vyw, wz))
        return BaseState(float(d.time), np.array((x, y, yaw)), twist)

    # ----------------------------------------------------------------- interaction
    @cached_property
    def max_push_force(self) -> float:
        """The largest force a push or wrench may put on the end effector.

        Returns:
            N: ``PUSH_LIMIT_WEIGHTS`` times the weight (standard gravity) of the links the
            arm's joints move (0 without arm joints).
        """
        tree = self.robot.tree
        moved = tree.moves[self.arm_joints].any(axis=0) if self.n else np.zeros(tree.nb, bool)
        mass = float(np.sum(tree.nominal.mass[moved]))
        return PUSH_LIMIT_WEIGHTS * mass * float(np.linalg.norm(STANDARD_GRAVITY))

    def _check_force(self, force, what: str) -> None:
        """InputError for a force (3,) N beyond ``max_push_force`` (or not a finite vector)."""
        size = float(np.linalg.norm(vec3(force, f"{what} force")))
        if size > self.max_push_force:
            raise InputError(
                f"{what} force of {size:.4g} N is beyond {self.max_push_force:.0f} N, "
                f"{PUSH_LIMIT_WEIGHTS:g} times the weight of {self.robot.name}'s arm: the "
                "simulation would break down"
            )

    def set_wrench(self, force=(0.0, 0.0, 0.0), torque=(0.0, 0.0, 0.0)) -> None:
        """A constant wrench at the end-effector point until changed.

        Args:
            force: (3,) N, world frame, at most ``max_push_force``. torque: (3,) N m, world.

        Raises:
            InputError: a force beyond ``max_push_force`` or not a finite 3-vector.
        """
        self._check_force(force, "wrench")
        self.interaction.set_wrench(force, torque)
        self._clear_xfrc()

    def push(self, start: float, duration: float, force, torque=(0.0, 0.0, 0.0)) -> Push:
        """Push on the end effector for a while.

        Args:
            start: s, simulation time it begins. duration: s.
            force: (3,) N, world frame, at most ``max_push_force``. torque: (3,) N m, world.

        Returns:
            The ``Push`` (InputError for a force as ``set_wrench`` refuses).
        """
        self._check_force(force, "push")
        return self.interaction.add_push(start, duration, force, torque)

    def attach_rope(self, anchor, free_length: float, stiffness: float) -> Rope:
        """A rope with a spring from the end effector to a fixed point (see ``Rope``).

        Args:
            anchor: (3,) m, world frame. free_length: m, slack within this distance of it.
            stiffness: N/m of the spring.

        Returns:
            The ``Rope``.
        """
        return self.interaction.attach_rope(anchor, free_length, stiffness)

    def detach_rope(self) -> None:
        """Remove the rope, if any."""
        self.interaction.detach_rope()
        self._clear_xfrc()

    def _clear_xfrc(self) -> None:
        if self.interaction.idle:
            self.data.xfrc_applied[self._ee_body] = 0.0

    def ee_position(self) -> np.ndarray:
        """The end-effector site's position (as of the last step).

        Returns:
            (3,) m, world frame.
        """
        return self.data.site_xpos[self._ee_site].copy()

    def _apply_interaction(self) -> None:
        d = self.data
        point = d.site_xpos[self._ee_site]
        force, torque = self.interaction.wrench(d.time, point)
        # xfrc_applied acts at the body's centre of mass: move the wrench there (torque plus
        # lever x force, on floats: np.cross on 3-vectors costs tens of us)
        lx, ly, lz = (point - d.xipos[self._ee_body]).tolist()
        fx, fy, fz = force.tolist()
        tx, ty, tz = torque.tolist()
        d.xfrc_applied[self._ee_body] = (
            fx,
            fy,
            fz,
            tx + ly * fz - lz * fy,
            ty + lz * fx - lx * fz,
            tz + lx * fy - ly * fx,
        )

    # ----------------------------------------------------------------- stepping
    def step(self, n: int = 1, pace: bool = True) -> None:
        """Advance with the current targets.

        Args:
            n: steps of 1 ms. pace: with ``realtime``, keep pace with the wall clock.
        """
        m, d, na = self.model, self.data, self.n
        for _ in range(n):
            if na:
                self._v_ctrl[:] = self._ctrl
            if self.base_joints:
                self._drive_base()
            if not self.interaction.idle and na:
                self._apply_interaction()
            t0 = d.time
            if na:
                self._dq_before[:] = self._v_dq
            mujoco.mj_step(m, d)
            if d.time <= t0 or t0 == 0.0:  # after a reset MuJoCo's time starts again
                self._check_stability(t0)
            if na:
                self._measure()
            if pace and self._realtime:
                ahead = self._wall0 + d.time - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
        if self.viewer is not None:
            self._sync_viewer()

    def _drive_base(self) -> None:
        d = self.data
        vx, vy, wz = self._limiter.update(float(d.time)).tolist()
        yaw = float(d.qpos[self._bqadr[2]])
        c, s = math.cos(yaw), math.sin(yaw)
        d.ctrl[self.n :] = (c * vx - s * vy, s * vx + c * vy, wz)

    def _check_stability(self, t: float) -> None:
        """Fault the arm (\"simulator unstable\") if MuJoCo reset the simulation in the step
        from time ``t`` s (NaN, Inf or huge positions, velocities or accelerations)."""
        warnings = self.data.warning
        resets = sum(int(warnings[w].number) for w in _RESET_WARNINGS)
        if resets == self._resets:
            return
        self._resets = resets
        what = [
            mujoco.mjtWarning(w).name.removeprefix("mjWARN_BAD").lower()
            for w in _RESET_WARNINGS
            if warnings[w].number
        ]
        self.interaction.clear()  # what broke it must not act on the reset simulation
        self._clear_xfrc()
        self.fault(
            f"simulator unstable: MuJoCo found NaN, Inf or huge values ({', '.join(what)}) "
            f"at t = {t:.3f} s and reset the simulation (pushes removed)"
        )

    def _measure(self) -> None:
        """Measured current and the cheap fault tests of the step just taken."""
        k = self._k % _NOISE_BLOCK
        if k == 0:
            self._noise = self._rng.normal(0.0, self.truth.current_noise, (_NOISE_BLOCK, self.n))
        self._k += 1
        torque = self._v_qfrc  # the servo's damping at the old velocity: as applied, the new
        damped = torque + self._v_damping * (self._v_dq - self._dq_before)
        self._applied = np.where(np.abs(torque) < self.effort, damped, torque)
        current = self._ratio * self._applied
        current += self._noise[k]
        self.current = current  # a new array each step: states keep theirs
        dq = self._v_dq
        if (
            self.data.nl  # a joint-limit constraint is active
            or self._over_effort
            or np.dot(dq, dq) > self.overspeed * self.overspeed
            or (not self._all_cur and self._following_error_exceeded())
        ):
            self._record_faults()

    def _following_error_exceeded(self) -> bool:
        """Cheap test: sum((w (q - q_ref))^2) > 1 whenever a servoed joint is beyond."""
        e = (self._v_q - self._q_ref) * self._follow_w
        return float(e @ e) > 1.0

    def _record_faults(self) -> None:
        d, names = self.data, self.arm_joint_names
        q, dq = d.qpos[self._qadr], d.qvel[self._dadr]
        force = d.actuator_force[: self.n]
        found: list[tuple[str, int]] = []
        for j in range(self.n):
            lo, hi = self._hard[j]
            if not lo < q[j] < hi:
                found.append(
                    (f"{names[j]}: position {q[j]:.3f} rad at its limit [{lo:g}, {hi:g}] rad", j)
                )
            if self._is_cur[j] and abs(force[j]) > self.effort[j]:
                msg = (
                    f"{names[j]}: current {force[j] * self._ratio[j]:.2f} A asks "
                    f"{force[j]:.2f} N m, beyond the effort limit {self.effort[j]:g} N m"
                )
                found.append((msg, j))
            if abs(dq[j]) > self.overspeed:
                found.append(
                    (f"{names[j]}: speed {dq[j]:.2f} rad/s beyond {self.overspeed:g} rad/s", j)
                )
            if not self._is_cur[j] and abs(q[j] - self._q_ref[j]) > self.following_error:
                msg = (
                    f"{names[j]}: following error {q[j] - self._q_ref[j]:.3f} rad beyond "
                    f"{self.following_error:g} rad"
                )
                found.append((msg, j))
        for msg, j in found:
            self.fault(msg, j)

    # ----------------------------------------------------------------- viewer, lifetime
    def _sync_viewer(self) -> None:
        now = time.perf_counter()
        if now - self._last_sync > 1 / 60:
            self._last_sync = now
            if self.viewer.is_running():
                self.viewer.sync()

    @cached_property
    def arm(self) -> SimArm:
        """The ``Arm`` interface of this simulator.

        Returns:
            Its ``SimArm`` (one per simulator); ModelError without arm joints.
        """
        from jaxcomp.hardware.sim_arm import SimArm

        if self.n == 0:
            raise ModelError(f"{self.robot.name} has no arm joints")
        return SimArm(self)

    @cached_property
    def base(self):
        """The ``Base`` interface of this simulator (a model with base_x, base_y, base_yaw)."""
        from jaxcomp.hardware.sim_base import SimBase

        if not self.has_base:
            raise ModelError(f"{self.robot.name} has no mobile base joints {BASE_JOINTS}")
        return SimBase(self)

    def close(self) -> None:
        """Arm to position mode, base stopped, viewer closed."""
        try:
            if "arm" in self.__dict__:
                self.arm.close()
            if "base" in self.__dict__:
                self.base.close()
        finally:
            if self.viewer is not None:
                self.viewer.close()
                self.viewer = None

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
