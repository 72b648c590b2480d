"""Plan checks: what the robot's model finds wrong with a calibration plan.

``PlanModel`` is the model's view of arm poses: gravity torques and their sensitivity to the
links' centres of mass, the load of gravity and a ramp's acceleration against the effort
limits, the floor (the mounting surface) and self-contact. ``plan_issues(robot, plan)`` runs
its checks along every sweep and transfer of any plan (``identify.plan``); the design of the
default plan (``identify.plan_design``) searches held poses with the same model. Units: rad,
rad/s, s, m, N m.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxcomp import checks, dynamics
from jaxcomp.errors import InputError
from jaxcomp.identify.plan import CalibrationPlan, arm_pose
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices

#: rad, the angle step of the model's checks along a sweep or transfer.
CHECK_STEP = math.radians(5.0)
#: A position servo that lags and catches up asks up to about this times the commanded ramp
#: acceleration (the simulator's asks 1.3x): the load checks use it.
SERVO_RAMP_FACTOR = 1.5
#: A, the current noise that weighs the centre-of-mass information of a sample
#: (``PlanModel.weight``); the batch of the jitted evaluations; contact distance (m) below
#: which two geoms touch.
_NOISE = 0.05
_CHUNK = 4096
_CONTACT = 0.005
#: Rounding allowance: a point's floor lies this far (m) below its height at the idle pose,
#: where that is below the floor; the batched pre-check refuses only poses this far (m, and
#: fraction of a load limit) beyond a limit.
_SLACK = 1e-6


class PlanModel:
    """The model's view of arm poses: gravity, COM sensitivity, load, floor and self-contact.

    Arm poses are (n,) rad over the n current-controlled joints (``arm``).

    Args:
        robot: the robot; gravity: (3,) m/s^2, base frame (None: the model's).
        effort_fraction: |g| may reach this fraction of each effort limit.
        floor: m, the lowest z (base frame) a link origin, geom centre or site may reach.

    Attributes:
        robot: the robot. arm: (n,) int, the current-controlled joints; n: their count.
        g: (3,) m/s^2, gravity in the base frame. effort: (n,) N m, the effort limits.
        weight: (n,) 1/(N m)^2, the information of one sample of a joint's torque (its
            nominal ratio over the current noise, squared).
        zero: (n,) rad, the zero pose (``Robot.pose("zero")``). axes0: (n, 3), the joint
            axes there, world frame.

    Raises:
        InputError: ``gravity`` is not a finite (3,) vector with a norm near 9.81 m/s^2.
    """

    def __init__(
        self, robot: Robot, gravity: Sequence[float] | None, effort_fraction: float, floor: float
    ):
        self.robot = robot
        self.arm = arm = arm_joint_indices(robot)
        self.n = len(arm)
        self.effort_fraction = float(effort_fraction)
        self.floor = float(floor)
        tree = robot.tree
        g = robot.default_gravity if gravity is None else gravity
        g = checks.array(g, "gravity", n=3, unit="m/s^2")
        if not 1 < np.linalg.norm(g) < 30:
            raise InputError(f"gravity must be (3,) m/s^2 with a norm near 9.81, got {g}")
        self.g = g
        idx = jnp.asarray(arm)
        gvec = jnp.asarray(g)

        def gravity_arm(qa):
            q = jnp.zeros(tree.nv, qa.dtype).at[idx].set(qa)
            return dynamics.gravity(tree, q, None, gvec)[idx]

        self._gravity = jax.jit(jax.vmap(gravity_arm))
        self.effort = robot.effort_limits[arm]
        self.weight = (RobotParams.nominal(robot).ratio / _NOISE) ** 2  # 1/(N m)^2 per sample
        # the collision model: every geom collides, contacts reported within _CONTACT
        m = copy.deepcopy(robot.model)
        m.geom_contype[:] = 1
        m.geom_conaffinity[:] = 1
        m.geom_margin[:] = _CONTACT
        m.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        self.model, self.data = m, mujoco.MjData(m)
        self.qadr = m.jnt_qposadr[arm]
        moved = tree.moves[arm].any(axis=0)
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in tree.body_names]
        self.moved_body = np.zeros(m.nbody, bool)
        self.moved_body[[i for i, mv in zip(ids, moved, strict=True) if mv]] = True
        self.moved_geom = self.moved_body[m.geom_bodyid]
        self.moved_site = self.moved_body[m.site_bodyid]
        self.ignored: set[tuple[int, int]] = set()
        # touching at the zero pose (zeros moved inside the limits): the construction
        self.zero = arm_pose(robot, "zero")
        self.ignored = self._contacts(self.zero)
        self.axes0 = self.data.xaxis[arm].copy()  # (n, 3) world joint axes at the zero pose
        self._points(robot)
        # COM sensitivity: g_j = -(axis_j x sum_b m_b (p_b + R_b c_b - anchor_j)) . g, so
        # d g_j / d c_b = -m_b R_b^T (g x axis_j) for every body b that hinge j moves
        self.body_ids = np.array(ids)
        self.mass = np.asarray(tree.nominal.mass)
        self.moves = tree.moves[arm] & tree.is_hinge[arm][:, None]  # (n, nb)
        self.dofs = m.jnt_dofadr[arm]
        m.opt.gravity[:] = g
        self._bias, self._accel, self._inertial = np.zeros(m.nv), np.zeros(m.nv), np.zeros(m.nv)
        self._prechecks(tree)

    def _points(self, robot: Robot) -> None:
        """The points the floor check watches: origins of the moved bodies, centres of their
        geoms, their sites; each with its floor (m): ``floor``, or its height at the idle pose
        where that is lower (parts at the base that sit below the floor by construction)."""
        m, d = self.model, self.data
        body = np.flatnonzero(self.moved_body)
        geom = np.flatnonzero(self.moved_geom)
        site = np.flatnonzero(self.moved_site)
        # tree body index (MuJoCo's less the world) and position in that body's frame
        self.point_body = np.concatenate([body, m.geom_bodyid[geom], m.site_bodyid[site]]) - 1
        self.point_local = np.concatenate(
            [np.zeros((len(body), 3)), m.geom_pos[geom], m.site_pos[site]]
        ).reshape(-1, 3)
        self._point_ids = (body, geom, site)
        d.qpos[self.qadr] = arm_pose(robot)
        mujoco.mj_kinematics(m, d)
        self.point_floor = np.minimum(self.floor, self._point_z() - _SLACK)

    def _prechecks(self, tree) -> None:
        """The batched, approximate ``problem`` (no contacts): ``surely_bad``."""
        point_body, point_local = jnp.asarray(self.point_body), jnp.asarray(self.point_local)
        idx, gvec = jnp.asarray(self.arm), jnp.asarray(self.g)
        limit = jnp.asarray(self.effort_fraction * self.effort)

        def excess(qa, accel):  # m below the floors, and the load over its limit (fraction)
            q = jnp.zeros(tree.nv, qa.dtype).at[idx].set(qa)
            frames = dynamics.forward_kinematics(tree, q)
            rot, pos = frames.rot[point_body], frames.pos[point_body]
            z = pos[:, 2] + jnp.einsum("pj,pj->p", rot[:, 2], point_local)
            load = jnp.abs(dynamics.gravity(tree, q, None, gvec)[idx])
            load = load + jnp.abs(dynamics.mass_matrix(tree, q)[idx][:, idx] @ accel)
            return jnp.max(self.point_floor - z, initial=-jnp.inf), jnp.max(load / limit) - 1

        self._excess = jax.jit(jax.vmap(excess, in_axes=(0, None)))

    def _point_z(self) -> np.ndarray:
        """(P,) m: heights of the watched points in ``self.data`` (after ``mj_kinematics``)."""
        d = self.data
        body, geom, site = self._point_ids
        return np.concatenate([d.xpos[body, 2], d.geom_xpos[geom, 2], d.site_xpos[site, 2]])

    def _batched(self, fn, q: np.ndarray, *args) -> list[np.ndarray]:
        """``fn(q, *args)`` over arm poses q (B, n) rad in fixed batches (one compilation):
        its outputs, each (B, ...)."""
        q = np.asarray(q, float).reshape(-1, self.n)
        out = []
        for k in range(0, len(q), _CHUNK):
            chunk = q[k : k + _CHUNK]
            pad = np.zeros((_CHUNK, self.n))
            pad[: len(chunk)] = chunk
            res = fn(jnp.asarray(pad), *args)
            res = res if isinstance(res, tuple) else (res,)
            out.append([np.asarray(r)[: len(chunk)] for r in res])
        return [np.concatenate(parts) for parts in zip(*out, strict=True)]

    def surely_bad(self, q: np.ndarray, accel: np.ndarray) -> np.ndarray:
        """The poses that ``problem`` (exact, and contacts) surely refuses: a watched point
        lies more than ``_SLACK`` m below its floor, or the load of gravity and ``accel``
        exceeds the effort fraction by more than ``_SLACK`` of it. Batched on the device, for
        the search to skip them.

        Args:
            q: (B, n) rad, arm poses.
            accel: (n,) rad/s^2, the acceleration the load takes with gravity.

        Returns:
            (B,) bool, True where refused.
        """
        below, over = self._batched(self._excess, q, jnp.asarray(accel, float))
        return (below > _SLACK) | (over > _SLACK)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """Gravity torques of the arm joints.

        Args:
            q: (B, n) rad, arm poses.

        Returns:
            (B, n) N m.
        """
        return self._batched(self._gravity, q)[0]

    def com_rows(self, q: np.ndarray, j: int) -> np.ndarray:
        """The sensitivity of a joint's gravity torque to every link's centre of mass.

        Args:
            q: (B, n) rad, arm poses.
            j: the joint (arm index).

        Returns:
            (B, nb * 3) N: d g_j / d COM (link frame, m) of the tree's nb links.
        """
        m, d = self.model, self.data
        rot = np.empty((len(q), len(self.body_ids), 9))
        axis = np.empty((len(q), 3))
        jnt = int(self.arm[j])  # MuJoCo joint ids are the tree's joint indices
        for k, qa in enumerate(q):
            d.qpos[self.qadr] = qa
            mujoco.mj_kinematics(m, d)
            rot[k] = d.xmat[self.body_ids]
            axis[k] = d.xaxis[jnt]
        lever = np.cross(self.g, axis)  # (B, 3)
        rot = rot.reshape(len(q), -1, 3, 3)
        rows = -np.einsum("b,Bbki,Bk->Bbi", self.mass * self.moves[j], rot, lever)
        return rows.reshape(len(q), -1)

    def overload(self, g: np.ndarray) -> np.ndarray:
        """How far gravity loads the joints against their share of the effort limits.

        Args:
            g: (..., n) N m, gravity torques.

        Returns:
            (...,) the largest |g| / (effort_fraction * effort limit) over the joints.
        """
        return (np.abs(g) / (self.effort_fraction * self.effort)).max(axis=-1)

    def _contacts(self, qa: np.ndarray) -> set[tuple[int, int]]:
        m, d = self.model, self.data
        d.qpos[self.qadr] = qa
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        pairs = set()
        for g1, g2 in zip(d.contact.geom1[: d.ncon], d.contact.geom2[: d.ncon], strict=True):
            if self.moved_geom[g1] or self.moved_geom[g2]:
                pairs.add((int(min(g1, g2)), int(max(g1, g2))))
        return pairs - self.ignored

    def problem(self, qa: np.ndarray, accel: np.ndarray | None = None) -> str | None:
        """Why an arm pose is not admissible, if it is not.

        Admissible: no two geoms touch, nothing is below ``floor``, and for every joint
        |g| + |M accel| stays within ``effort_fraction`` of its effort limit.

        Args:
            qa: (n,) rad, the arm pose.
            accel: (n,) rad/s^2, a ramp's acceleration (None: gravity alone).

        Returns:
            None when admissible, else a message.
        """
        m, d = self.model, self.data
        hit = self._contacts(qa)
        if hit:
            names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in min(hit)]
            return f"geoms {names[0]} and {names[1]} touch at {_deg(qa)} deg"
        below = self._point_z() - self.point_floor
        if below.min(initial=np.inf) < 0:
            k = int(np.argmin(below))
            return (
                f"the arm reaches z = {below[k] + self.point_floor[k]:.3f} m, below "
                f"{self.point_floor[k]:.3g} m, at {_deg(qa)} deg"
            )
        mujoco.mj_comPos(m, d)
        mujoco.mj_crb(m, d)
        mujoco.mj_rne(m, d, 0, self._bias)  # g(q): qvel is 0
        load = np.abs(self._bias[self.dofs])
        if accel is not None:
            self._accel[self.dofs] = accel
            mujoco.mj_mulM(m, d, self._inertial, self._accel)
            load = load + np.abs(self._inertial[self.dofs])
        over = load / (self.effort_fraction * self.effort)
        if over.max() > 1:
            k = int(np.argmax(over))
            return (
                f"joint {k} needs {load[k]:.2f} N m (gravity and ramp), beyond "
                f"{self.effort_fraction:.0%} of its effort limit {self.effort[k]:g} N m, at "
                f"{_deg(qa)} deg"
            )
        return None

    def path_problem(self, a: np.ndarray, b: np.ndarray, speed: float, ramp: float) -> str | None:
        """Why a move is not admissible at some pose of its straight joint-space line
        (``problem``, every ``CHECK_STEP`` or closer), if it is not.

        Args:
            a, b: (n,) rad, where ``Arm.move_to`` starts and ends.
            speed: rad/s; ramp: s, its speed ramps' time.

        Returns:
            None when admissible at every pose, else the first message.
        """
        way = b - a
        longest = np.abs(way).max()
        accel = way / longest * (SERVO_RAMP_FACTOR * speed / ramp) if longest > 0 else None
        return next((p for q in _path(a, b) if (p := self.problem(q, accel))), None)


def _deg(q: np.ndarray) -> np.ndarray:
    """A pose for messages: degrees, rounded."""
    return np.degrees(q).round(0)


def _path(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Poses every ``CHECK_STEP`` (or closer) on the straight joint-space line a -> b, both ends."""
    k = max(2, int(np.ceil(np.abs(b - a).max() / CHECK_STEP)) + 1)
    return a + np.linspace(0.0, 1.0, k)[:, None] * (b - a)


def plan_issues(
    robot: Robot | str,
    plan: CalibrationPlan,
    start: str | Sequence[float] | None = None,
    *,
    gravity: Sequence[float] | None = None,
    effort_fraction: float = 0.6,
    floor: float = 0.05,
) -> list[str]:
    """What the model finds wrong with recording ``plan``.

    Checks every sweep and every transfer (straight joint-space lines through the ``via``
    poses, from ``start`` when given) every 5 deg for: a gravity torque beyond
    ``effort_fraction`` of an actuator's effort limit (the rest is left for friction and
    acceleration), a link origin, geom centre or site below ``floor`` (z in the base frame:
    the mounting surface; a point that the idle pose already puts lower, a part at the base,
    may not go lower than there), and robot geoms closer than 5 mm to each other (pairs that
    already touch in the zero pose, ``Robot.pose("zero")``, belong to the construction and
    are ignored).

    Args:
        robot: the robot (name, path or ``Robot``).
        plan: the plan (validated against the robot first).
        start: where recording starts, a pose name or (n,) rad; None: no first transfer.
        gravity: (3,) m/s^2 in the base frame (None: the model's).
        effort_fraction: the fraction of each effort limit gravity may take.
        floor: m, the lowest z a watched point may reach.

    Returns:
        One message per refused sweep or transfer; empty when nothing is wrong.

    Raises:
        InputError: the plan does not fit the robot, or ``gravity`` is not near 9.81 m/s^2.
    """
    robot = load_robot(robot)
    plan.validate(robot)
    model = PlanModel(robot, gravity, effort_fraction, floor)
    issues = []
    prev = None if start is None else arm_pose(robot, start)
    for i, s in enumerate(plan.sweeps):
        legs = [(f"sweep {i}", s.start, s.turn, s.speed)]
        points = ([] if prev is None else [prev]) + list(s.via) + [s.start]
        legs[:0] = [
            (f"transfer to sweep {i}", a, b, plan.move_speed) for a, b in itertools.pairwise(points)
        ]
        for what, a, b, speed in legs:
            problem = model.path_problem(np.asarray(a), np.asarray(b), speed, plan.ramp)
            if problem:
                issues.append(f"{what}: {problem}")
        prev = s.start
    return issues
