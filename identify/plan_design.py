"""Plan design: the paper's calibration plan, its held poses and speeds chosen on the model.

``default_plan(robot)`` computes the paper's calibration (paper IV-A) on the robot's model, for
any arm: for each current-controlled joint it searches held poses (every other joint at -90,
-45, 0, 45 or 90 deg, within its limits) where gravity has a large lever on the swept joint
over -100..+100 deg (within the joint's limits less a margin), rejects poses that overload an
actuator, reach the mounting surface or make the robot touch itself, and picks about three per
joint that excite every link's centre of mass in different directions (a greedy D-optimal
design). Its options are one frozen ``PlanOptions``; the plan is kept on the robot per options
(``Robot.cached``): the search takes seconds (about 15-30 s for a 7-joint arm).

``plan_issues(robot, plan)`` runs the same model checks on any plan (``identify.plan``).
Units: rad, rad/s, s, m, N m.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxcomp import dynamics
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.identify.plan import (
    LIMIT_MARGIN,
    LOWER,
    MOVE_SPEED,
    RAMP,
    SETTLE,
    SPEED,
    UPPER,
    CalibrationPlan,
    Sweep,
    arm_pose,
)
from jaxcomp.poses import LIMIT_MARGIN as POSE_MARGIN
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices

# --------------------------------------------------------------------- the model's checks
#: Design constants: current noise (A) and prior COM uncertainty (m) weighing the
#: centre-of-mass information of a sweep; the angle step of the model's checks (rad); the
#: batch of the jitted evaluations; contact distance (m) below which two geoms touch.
_NOISE = 0.05
_PRIOR_COM = 0.01
_STEP = math.radians(5.0)
_CHUNK = 4096
_CONTACT = 0.005
#: Rounding allowance: a point's floor lies this far (m) below its height at the idle pose,
#: where that is below the floor; the batched pre-check refuses only poses this far (m, and
#: fraction of a load limit) beyond a limit.
_SLACK = 1e-6
#: A position servo that lags and catches up asks up to about this times the commanded ramp
#: acceleration (the simulator's asks 1.3x): the load checks use it.
_SERVO = 1.5


class _Model:
    """The model's view of arm poses: gravity, COM sensitivity, load, floor and self-contact.

    Args:
        robot: the robot; gravity: (3,) m/s^2, base frame (None: the model's).
        effort_fraction: |g| may reach this fraction of each effort limit.
        floor: m, the lowest z (base frame) a link origin, geom centre or site may reach.
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
        g = robot.default_gravity if gravity is None else np.asarray(gravity, float)
        if g.shape != (3,) or not np.all(np.isfinite(g)) or not 1 < np.linalg.norm(g) < 30:
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
        """(B,) bool at arm poses q (B, n) rad: a watched point lies more than ``_SLACK`` m
        below its floor, or the load of gravity and ``accel`` (n,) rad/s^2 exceeds the effort
        fraction by more than ``_SLACK`` of it. ``problem`` (exact, and contacts) refuses
        these poses; the check is batched on the device, for the search to skip them."""
        below, over = self._batched(self._excess, q, jnp.asarray(accel, float))
        return (below > _SLACK) | (over > _SLACK)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """(B, n) N m: gravity torques at arm poses q (B, n) rad."""
        return self._batched(self._gravity, q)[0]

    def com_rows(self, q: np.ndarray, j: int) -> np.ndarray:
        """(B, nb * 3) N: d g_j / d COM of every link (link frame, m) at arm poses q (B, n)."""
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
        """(...,) the largest |g| / (effort_fraction * effort limit) over joints, g (..., n)."""
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
        """None when the arm pose (n,) rad is admissible, else why not.

        Admissible: no two geoms touch, nothing is below ``floor``, and for every joint
        |g| + |M accel| (accel (n,) rad/s^2: a ramp's acceleration) stays within
        ``effort_fraction`` of its effort limit.
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
        """None when ``Arm.move_to`` from a to b (rad) at ``speed`` rad/s with ramps of
        ``ramp`` s is admissible at every pose of its straight joint-space line (``problem``)."""
        way = b - a
        longest = np.abs(way).max()
        accel = way / longest * (_SERVO * speed / ramp) if longest > 0 else None
        return next((p for q in _path(a, b) if (p := self.problem(q, accel))), None)


def _deg(q: np.ndarray) -> np.ndarray:
    """A pose for messages: degrees, rounded."""
    return np.degrees(q).round(0)


def _path(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Poses every ``_STEP`` (or closer) on the straight joint-space line a -> b, both ends."""
    k = max(2, int(np.ceil(np.abs(b - a).max() / _STEP)) + 1)
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
    """What the model finds wrong with recording ``plan``: an empty list when nothing.

    Checks every sweep and every transfer (straight joint-space lines through the ``via``
    poses, from ``start``, a pose name or (n,) rad, when given) every 5 deg for: a gravity
    torque beyond ``effort_fraction`` of an actuator's effort limit (the rest is left for
    friction and acceleration), a link origin, geom centre or site below ``floor`` m (z in the
    base frame: the mounting surface; a point that the idle pose already puts lower, a part at
    the base, may not go lower than there), and robot geoms closer than 5 mm to each other
    (pairs that already touch in the zero pose, ``Robot.pose("zero")``, belong to the
    construction and are ignored). ``gravity`` (3,) m/s^2 in the base frame (default: the
    model's).
    """
    robot = load_robot(robot)
    plan.validate(robot)
    model = _Model(robot, gravity, effort_fraction, floor)
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


# --------------------------------------------------------------------- the default plan
def inner_limits(limits: np.ndarray) -> np.ndarray:
    """(n, 2) rad: joint limits (n, 2) less a margin of ``jaxcomp.poses.LIMIT_MARGIN`` of each
    range, at least ``LIMIT_MARGIN`` (1 deg, the ``Arm``'s); infinite limits stay infinite."""
    limits = np.asarray(limits, float)
    span = limits[:, 1] - limits[:, 0]
    margin = np.maximum(np.where(np.isfinite(span), POSE_MARGIN * span, 0.0), LIMIT_MARGIN)
    return limits + margin[:, None] * np.array([1.0, -1.0])


def sweep_window(lower: float, upper: float, lo: float, hi: float) -> tuple[float, float]:
    """rad: the sweep ``lower``..``upper`` within the limits ``lo``..``hi``: cut at a limit
    and moved away from it by what it lost there (as far as the other limit allows)."""
    a, b = max(lower, lo), min(upper, hi)
    if lower < lo:
        b = min(hi, lo + (upper - lower))
    if upper > hi:
        a = max(lo, hi - (upper - lower))
    return a, b


def _holds(values: list[list[float]], limit: int, seed: int) -> np.ndarray:
    """(C, n) rad: every combination of ``values`` (one list per joint), in
    ``itertools.product`` order; beyond ``limit`` combinations, ``limit`` of them drawn at random
    from ``seed`` (kept in that order)."""
    sizes = [len(v) for v in values]
    total = math.prod(sizes)
    if total <= limit:
        flat = np.arange(total)
    else:
        flat = np.sort(np.random.default_rng(seed).choice(total, limit, replace=False))
    index = np.unravel_index(flat, sizes)
    return np.stack([np.asarray(v, float)[i] for v, i in zip(values, index, strict=True)], axis=1)


def _runs(ok: np.ndarray, min_len: int, mid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of ok (C, S): the run of True through the index ``mid``.

    Returns first index (C,), last index (C,) and valid (C,): ``mid`` is True and the run
    has at least ``min_len`` steps (last - first >= min_len).
    """
    C, S = ok.shape
    idx = np.arange(S)
    bad_left = np.where(~ok & (idx <= mid), idx, -1).max(axis=1)
    bad_right = np.where(~ok & (idx >= mid), idx, S).min(axis=1)
    first, last = bad_left + 1, bad_right - 1
    valid = ok[:, mid] & (last - first >= min_len)
    return first, last, valid


@dataclass
class _Search:
    """Candidate holds of one swept joint on the model (C candidates, S angles of the sweep).

    A candidate's sweep is its admissible stretch (``_runs``) through the angle ``mid``:
    ``loaded`` alone gives an upper bound of what the exact stretch (also clear) gives.
    """

    joint: int
    angles: np.ndarray  # (S,) rad
    mid: int  # index of the angle every sweep passes: the zero pose's
    holds: np.ndarray  # (C, n) rad
    gravity: np.ndarray  # (C, S) N m, the swept joint's
    loaded: np.ndarray  # (C, S) bool: every gravity torque within the effort fraction
    possible: np.ndarray  # (C, S) bool: not refused for sure (``_Model.surely_bad``)
    min_len: int  # angle steps a sweep must span
    accel: float  # rad/s^2, the ramps' acceleration
    distance: np.ndarray  # (C,) rad, how far the hold is from the start pose (tie-breaks)
    checked: np.ndarray = field(init=False)  # (C,) bool: exact stretch known
    first: np.ndarray = field(init=False)  # (C,) angle index where the sweep starts
    last: np.ndarray = field(init=False)  # (C,) angle index where it turns
    valid: np.ndarray = field(init=False)  # (C,) bool
    chosen: list[int] = field(default_factory=list)
    best: float = 0.0  # N m, the largest exact amplitude
    rows: dict[int, np.ndarray] = field(default_factory=dict)  # c -> (S, nb * 3) N

    def __post_init__(self) -> None:
        self.first, self.last, self.valid = _runs(self.loaded, self.min_len, self.mid)
        self.checked = np.zeros(len(self.holds), bool)

    def poses(self, c: int) -> np.ndarray:
        q = np.repeat(self.holds[c][None], len(self.angles), axis=0)
        q[:, self.joint] = self.angles
        return q

    def check(self, c: int, model: _Model) -> None:
        """Make candidate c's stretch exact: also clear of the floor and of the robot."""
        if self.checked[c]:
            return
        self.checked[c] = True
        # the exact stretch lies within the stretch of the cheap checks: only that is checked
        f, la, v = _runs((self.loaded[c] & self.possible[c])[None], self.min_len, self.mid)
        if not v[0]:
            self.valid[c] = False
            return
        accel = np.zeros(len(self.holds[c]))
        accel[self.joint] = self.accel
        poses = self.poses(c)
        clear = np.zeros(len(self.angles), bool)
        clear[f[0] : la[0] + 1] = [model.problem(q, accel) is None for q in poses[f[0] : la[0] + 1]]
        f, la, v = _runs((self.loaded[c] & clear)[None], self.min_len, self.mid)
        self.first[c], self.last[c], self.valid[c] = f[0], la[0], v[0]

    def _mask(self, cands: np.ndarray) -> np.ndarray:
        idx = np.arange(len(self.angles))
        inside = (idx >= self.first[cands, None]) & (idx <= self.last[cands, None])
        return inside & self.valid[cands, None]

    def amplitude(self, cands: np.ndarray) -> np.ndarray:
        """(len(cands),) N m, peak-to-peak gravity torque of the swept joint over the sweep."""
        m = self._mask(cands)
        g = self.gravity[cands]
        amp = np.where(m, g, -np.inf).max(axis=1) - np.where(m, g, np.inf).min(axis=1)
        return np.where(m.any(axis=1), amp, 0.0)

    def information(self, cands: np.ndarray, weight: float, model: _Model) -> np.ndarray:
        """(len(cands), nb * 3, nb * 3) COM information of the sweeps, 1/m^2 (``weight``:
        1/(N m)^2 per checked angle): sum of J^T J, J = d g_swept / d COM."""
        new = [int(c) for c in cands if int(c) not in self.rows]
        if new:
            poses = np.concatenate([self.poses(c) for c in new])
            rows = model.com_rows(poses, self.joint).reshape(len(new), len(self.angles), -1)
            self.rows.update(zip(new, rows, strict=True))
        r = np.stack([self.rows[int(c)] for c in cands]) * self._mask(cands)[:, :, None]
        return weight * (r.transpose(0, 2, 1) @ r)

    def sweep(self, c: int, speed: float) -> Sweep:
        lower, upper = self.angles[self.first[c]], self.angles[self.last[c]]
        return Sweep(self.joint, self.holds[c], lower, upper, speed)


def _way(points: list[np.ndarray], x: np.ndarray) -> float:
    """rad, the longest joint way of a detour through x between the last two points."""
    return float(np.abs(x - points[-2]).max() + np.abs(points[-1] - x).max())


def _routes(
    points: list[np.ndarray], stops: list[np.ndarray], ends: list[np.ndarray]
) -> Iterator[list[np.ndarray]]:
    """The ``via`` poses to try, in order, for a transfer through ``points`` (from, the
    previous sweep's middle pose if any, the next sweep's middle pose): none; ``points[1:]``;
    with one pose of ``stops`` between the last two, then one of ``ends``, each nearest first
    (``_way``); then two of ``ends``, the shortest detour first."""
    yield []
    yield points[1:]
    for third in (stops, ends):
        for x in sorted(third, key=lambda x: _way(points, x)):
            yield points[1:-1] + [x, points[-1]]
    pairs = [(x, y) for x in ends for y in ends if x is not y]
    a, b = points[-2], points[-1]
    way = [np.abs(x - a).max() + np.abs(y - x).max() + np.abs(b - y).max() for x, y in pairs]
    for k in np.argsort(way, kind="stable"):
        yield points[1:-1] + [*pairs[k], b]


def _best(score: np.ndarray, distance: np.ndarray, tol: float) -> np.ndarray:
    """Indices by decreasing score; scores within ``tol`` count as equal, the nearer first."""
    return np.lexsort((distance, -np.round(score / tol)))


def _floats(values: Sequence[float], name: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in np.asarray(values, float).reshape(-1))
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a list of numbers, got {values!r}") from None


@dataclass(frozen=True)
class PlanOptions:
    """Options of ``default_plan`` (frozen and hashable: the key of the robot's plan cache).

    Attributes:
        gravity: (3,) m/s^2 in the base frame; None: the model's.
        sweeps_per_joint: sweeps of each joint gravity excites (>= 1).
        lower, upper: rad, the swept range (default -100..+100 deg), within each joint's
            ``inner_limits`` (``sweep_window``: cut at a limit, moved away from it).
        speed: rad/s, speed of the sweeps (default 40 deg/s).
        slow_speed: rad/s, speed of the second sweep of a joint with several (default
            20 deg/s), so that the fit can tell viscous from Coulomb friction; None: all at
            ``speed``.
        move_speed: rad/s, speed of the transfers between sweeps (default 40 deg/s).
        settle: s, hold at each sweep's start (default 0.5 s).
        ramp: s, time of every move's speed ramps (default 0.25 s).
        grid: rad, the values a held joint takes in a candidate hold (default -90, -45, 0,
            45, 90 deg; moved inside the joint's ``inner_limits``).
        effort_fraction: fraction of each effort limit that gravity may take (default 0.6;
            the rest is left for friction and the ramps).
        floor: m, the lowest z (base frame) a link origin, geom centre or site may reach
            (default 0.05 m; a point the idle pose puts lower, a part at the base, may not go
            lower than there).
        min_amplitude: N m, peak-to-peak gravity torque below which gravity does not excite a
            joint (default 0.05 N m).
        amplitude_fraction: a further hold of a joint keeps at least this fraction of its
            first hold's amplitude (default 0.5).
        min_span: rad, the shortest admissible sweep (default 100 deg; a joint whose range is
            shorter sweeps its range).
        shortest_span: rad, the shortest admissible sweep of a joint that no hold lets sweep
            ``min_span`` within the effort limits and clear of the floor (default 30 deg).
        max_holds: candidate holds per joint; beyond, a seeded random subset of the grid's
            (default 4096: the whole grid up to 6 joints).
        start: where recording starts, a pose name or (n,) rad; None: ``Robot.idle_pose``
            (the "home" keyframe, else the rest pose).

    Sequences are stored as tuples of floats.
    """

    gravity: tuple[float, ...] | None = None
    sweeps_per_joint: int = 3
    lower: float = LOWER
    upper: float = UPPER
    speed: float = SPEED
    slow_speed: float | None = SPEED / 2
    move_speed: float = MOVE_SPEED
    settle: float = SETTLE
    ramp: float = RAMP
    grid: tuple[float, ...] = tuple(float(v) for v in np.radians([-90.0, -45.0, 0.0, 45.0, 90.0]))
    effort_fraction: float = 0.6
    floor: float = 0.05
    min_amplitude: float = 0.05
    amplitude_fraction: float = 0.5
    min_span: float = math.radians(100.0)
    shortest_span: float = math.radians(30.0)
    max_holds: int = 4096
    start: str | tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.gravity is not None:
            object.__setattr__(self, "gravity", _floats(self.gravity, "gravity"))
        object.__setattr__(self, "grid", _floats(self.grid, "grid"))
        if self.start is not None and not isinstance(self.start, str):
            object.__setattr__(self, "start", _floats(self.start, "start"))


def default_plan(
    robot: Robot | str = "gen3_lite",
    options: PlanOptions | None = None,
    **overrides: float | int | str | Sequence[float] | None,
) -> CalibrationPlan:
    """The paper's calibration plan for ``robot``, held poses chosen on its model.

    ``options`` (default ``PlanOptions()``), with any of its fields replaced by
    ``overrides`` (``default_plan(robot, sweeps_per_joint=1)``). The plan is made once per
    robot and options and kept on the robot.

    Every current-controlled joint is swept from ``lower`` to ``upper`` rad and back at
    ``speed`` rad/s (default -100..+100 deg at 40 deg/s) while the others are held; a joint's
    range lies within its limits less 5 % of its range (at least 1 deg, ``inner_limits``): cut
    at a limit and moved away from it (``sweep_window``), so a joint of +-30 deg sweeps
    -27..+27 deg and a continuous joint -100..+100 deg. The second sweep of a joint with
    several runs at ``slow_speed`` (default 20 deg/s; None: all at ``speed``), so that the fit
    can tell viscous from Coulomb friction. A candidate hold puts every other joint at a value
    of ``grid`` (rad; default -90, -45, 0, 45, 90 deg, inside the joint's limits less the
    margin; a joint whose axis stays parallel to gravity changes no gravity torque and keeps
    its ``start`` value); of more than ``max_holds`` such combinations (an arm of 7 joints or
    more), a seeded random subset. Along a sweep a pose is admissible when no
    gravity torque exceeds ``effort_fraction`` of its effort limit (the rest is left for
    friction and the ramps) and the arm is clear of the floor and of itself (see
    ``plan_issues``); a candidate's sweep is its admissible stretch through the joint's angle
    in the zero pose (``Robot.pose("zero")``: zeros moved inside the limits), which must span
    at least ``min_span`` rad (or the joint's whole range, if shorter); a joint that no hold
    lets sweep that far within its effort limits and clear of the floor gets sweeps of at
    least ``shortest_span`` rad. Per joint:

    - the first hold maximizes the peak-to-peak gravity torque of the swept joint (N m);
    - up to ``sweeps_per_joint - 1`` more holds, each with at least ``amplitude_fraction`` of
      that amplitude, are chosen greedily (in turns over the joints) to maximize the
      log-determinant of the plan's centre-of-mass information (current noise 0.05 A through
      the nominal ratios, 1 cm prior): the holds vary the orientation of the links beyond the
      swept joint, so that each link's COM is excited in more than one direction;
    - a joint that gravity cannot excite (amplitude < ``min_amplitude`` N m, e.g. the vertical
      joint 0) gets one full sweep, for its friction loss, at the admissible hold nearest the
      previous sweep.

    Sweeps are grouped by joint in ascending order, within a joint ordered to shorten the
    transfers from ``start`` (pose name or (n,) rad; default ``Robot.idle_pose``). A transfer
    whose straight line is not admissible goes through ``via`` poses: both sweeps' middle poses
    (the swept joint at its zero-pose angle), and if need be a pose between them (the start,
    the zero pose, another sweep's middle pose; else a sweep's start or turn; else two of
    these).
    ``gravity`` (3,) m/s^2 in the base frame (default: the model's).
    """
    robot = load_robot(robot)
    options = dataclasses.replace(options or PlanOptions(), **overrides)

    def design() -> CalibrationPlan:
        # small batched model evaluations: on an accelerator their compiles and transfers
        # cost more than they compute (the Gen3 Lite's on an H100: 6.0 s, on its CPU 2.9 s)
        with jax.default_device(jax.local_devices(backend="cpu")[0]):
            return _design(robot, options)

    return robot.cached(("default_plan", options), design)


def _design(robot: Robot, o: PlanOptions) -> CalibrationPlan:
    """The search of ``default_plan`` (uncached)."""
    model = _Model(robot, o.gravity, o.effort_fraction, o.floor)
    n = model.n
    if int(o.sweeps_per_joint) < 1:
        raise InputError(f"sweeps_per_joint must be >= 1, got {o.sweeps_per_joint}")
    inner = inner_limits(robot.joint_limits[model.arm])
    names = [robot.joint_names[a] for a in model.arm]
    home = arm_pose(robot, o.start)
    # a joint whose axis no other arm joint turns, parallel to gravity, changes no torque
    tree = robot.tree
    axes = model.axes0
    body = tree.joint_body[model.arm]
    turns = tree.moves[model.arm][:, body] & ~np.eye(n, dtype=bool)  # (k, j): k turns j
    vertical = np.linalg.norm(np.cross(axes, model.g / np.linalg.norm(model.g)), axis=1) < 1e-9
    inert = vertical & ~turns.any(axis=0) & tree.is_hinge[model.arm]

    searches: list[_Search] = []
    for j in range(n):
        lo, hi = sweep_window(o.lower, o.upper, *inner[j])
        if not lo < hi:
            raise InputError(
                f"joint {j} ({names[j]}): its limits {np.degrees(inner[j]).round(1).tolist()} deg "
                "(less the margin) leave no range to sweep"
            )
        angles = np.linspace(lo, hi, int(np.ceil((hi - lo) / _STEP - 1e-9)) + 1)
        values = [
            [float(model.zero[k])]
            if k == j
            else [float(home[k])]
            if inert[k]
            else sorted({float(np.clip(v, *inner[k])) for v in o.grid})
            for k in range(n)
        ]
        holds = _holds(values, int(o.max_holds), seed=j)
        poses = np.repeat(holds[:, None, :], len(angles), axis=1)
        poses[:, :, j] = angles
        g = model.gravity(poses.reshape(-1, n))
        C, S = len(holds), len(angles)
        step = (hi - lo) / (S - 1)
        loaded = (model.overload(g) <= 1.0).reshape(C, S)
        accel = np.where(np.arange(n) == j, _SERVO * o.speed / o.ramp, 0.0)
        possible = ~model.surely_bad(poses.reshape(-1, n), accel).reshape(C, S)
        mid = int(np.argmin(np.abs(angles - model.zero[j])))
        min_len = int(math.ceil(min(o.min_span, hi - lo) / step - 1e-9))
        if not _runs(loaded & possible, min_len, mid)[2].any():  # too weak for min_span: shorter
            min_len = int(math.ceil(min(o.shortest_span, hi - lo) / step - 1e-9))
        searches.append(
            _Search(
                joint=j,
                angles=angles,
                mid=mid,
                holds=holds,
                gravity=g[:, j].reshape(C, S),
                loaded=loaded,
                possible=possible,
                min_len=min_len,
                accel=_SERVO * o.speed / o.ramp,
                distance=np.abs(np.delete(holds - home, j, axis=1)).max(axis=1),
            )
        )

    dim = robot.tree.nb * 3
    info = np.eye(dim) / _PRIOR_COM**2
    # per checked angle: both directions' samples times the per-sample weight
    weight = {
        s.joint: model.weight[s.joint] * 2 * _STEP / o.speed / CONTROL_PERIOD for s in searches
    }

    # the first hold: the largest exact amplitude (the load-only stretch bounds it)
    for s in searches:
        every = np.arange(len(s.holds))
        bound = s.amplitude(every)
        first = None
        for c in _best(bound, s.distance, 1e-3):
            if bound[c] < s.best + 1e-3:
                break
            s.check(int(c), model)
            amp = float(s.amplitude(np.array([c]))[0])
            if amp >= s.best + 1e-3:
                s.best, first = amp, int(c)
        if first is not None and s.best >= o.min_amplitude:
            s.chosen.append(first)
            info = info + s.information(np.array([first]), weight[s.joint], model)[0]

    # further holds: greedy D-optimal design (the load-only stretch bounds each gain)
    for _ in range(int(o.sweeps_per_joint) - 1):
        for s in searches:
            if not s.chosen:
                continue
            cands = np.setdiff1d(np.arange(len(s.holds)), s.chosen)
            cands = cands[s.amplitude(cands) >= o.amplitude_fraction * s.best]
            while len(cands):
                more = s.information(cands, weight[s.joint], model)
                gain = np.linalg.slogdet(info[None] + more)[1]
                k = int(_best(gain, s.distance[cands], 1e-3)[0])
                c = int(cands[k])
                if s.checked[c]:
                    s.chosen.append(c)
                    info = info + s.information(np.array([c]), weight[s.joint], model)[0]
                    break
                s.check(c, model)  # the gain may shrink: compare again
                keep = s.amplitude(cands) >= o.amplitude_fraction * s.best
                cands = cands[keep]

    sweeps: list[Sweep] = []
    prev = home
    for s in searches:
        if not s.chosen:  # friction only: the longest sweep at a hold near the previous one
            dist = np.abs(np.delete(s.holds - prev, s.joint, axis=1)).max(axis=1)
            full = len(s.angles) - 1
            order = np.argsort(dist, kind="stable")
            for k, c in enumerate(order):  # the 50 nearest, and on until one will do
                s.check(int(c), model)
                if s.valid[c] and (s.last[c] - s.first[c] == full or k >= 49):
                    break
            span = np.where(s.valid & s.checked, s.last - s.first, -1)
            if span.max() < 0:
                step = math.degrees(s.angles[1] - s.angles[0])
                raise InputError(
                    f"joint {s.joint} ({names[s.joint]}): no held pose gives it a sweep of "
                    f"{s.min_len * step:.0f} deg through {math.degrees(s.angles[s.mid]):.0f} deg, "
                    "clear of the floor, of the robot itself and of the effort limits"
                )
            s.chosen.append(int(_best(span.astype(float), dist, 0.5)[0]))
        speeds = [
            o.speed if k != 1 or o.slow_speed is None else o.slow_speed
            for k in range(len(s.chosen))
        ]
        todo = [s.sweep(c, v) for c, v in zip(s.chosen, speeds, strict=True)]
        while todo:  # the nearest start first
            sweep = todo.pop(int(np.argmin([np.abs(t.start - prev).max() for t in todo])))
            sweeps.append(sweep)
            prev = sweep.start

    # transfers: straight, else through both sweeps' middle poses (and one pose between:
    # home, zero, a sweep's middle pose; else a sweep's start or turn; else two of these)
    middle = {s.joint: s.angles[s.mid] for s in searches}
    mids = [s.pose(middle[s.joint]) for s in sweeps]
    stops = [home, model.zero] + mids
    ends = [x for s in sweeps for x in (s.start, s.turn)]
    out: list[Sweep] = []
    for s, mid in zip(sweeps, mids, strict=True):
        a = out[-1].start if out else home
        points = [a] + ([out[-1].pose(middle[out[-1].joint])] if out else []) + [mid]
        for via in _routes(points, stops, ends):
            legs = itertools.pairwise([a] + via + [s.start])
            if not any(model.path_problem(p, q, o.move_speed, o.ramp) for p, q in legs):
                break
        else:
            via = points[1:]  # plan_issues() tells what is left
        via = [v for k, v in enumerate(via) if np.abs(v - ([a] + via)[k]).max() > 1e-12]
        out.append(Sweep(s.joint, s.hold, s.lower, s.upper, s.speed, tuple(via)))
    return CalibrationPlan(tuple(out), o.move_speed, o.settle, o.ramp).validate(robot)
