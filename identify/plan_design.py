"""Plan design: the paper's calibration plan, its held poses and speeds chosen on the model.

``default_plan(robot)`` computes the paper's calibration (paper IV-A) on the robot's model: for
each current-controlled joint it searches held poses (every other joint at -90, -45, 0, 45 or
90 deg) where gravity has a large lever on the swept joint over -100..+100 deg, rejects poses
that overload an actuator, reach the mounting surface or make the robot touch itself, and
picks about three per joint that excite every link's centre of mass in different directions
(a greedy D-optimal design). Its options are one frozen ``PlanOptions``; the plan is kept on
the robot per options (``Robot.cached``): the search takes seconds.

``plan_issues(robot, plan)`` runs the same model checks on any plan (``identify.plan``).
Units: rad, rad/s, s, m, N m.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from collections.abc import Sequence
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
        self.ignored = self._contacts(np.zeros(self.n))  # touching at q = 0: construction
        self.axes0 = self.data.xaxis[arm].copy()  # (n, 3) world joint axes at q = 0
        # COM sensitivity: g_j = -(axis_j x sum_b m_b (p_b + R_b c_b - anchor_j)) . g, so
        # d g_j / d c_b = -m_b R_b^T (g x axis_j) for every body b that hinge j moves
        self.body_ids = np.array(ids)
        self.mass = np.asarray(tree.nominal.mass)
        self.moves = tree.moves[arm] & tree.is_hinge[arm][:, None]  # (n, nb)
        self.dofs = m.jnt_dofadr[arm]
        m.opt.gravity[:] = g
        self._bias, self._accel, self._inertial = np.zeros(m.nv), np.zeros(m.nv), np.zeros(m.nv)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """(B, n) N m: gravity torques at arm poses q (B, n) rad."""
        q = np.asarray(q, float).reshape(-1, self.n)
        out = []
        for k in range(0, len(q), _CHUNK):  # a fixed batch: one compilation
            chunk = q[k : k + _CHUNK]
            pad = np.zeros((_CHUNK, self.n))
            pad[: len(chunk)] = chunk
            out.append(np.asarray(self._gravity(jnp.asarray(pad)))[: len(chunk)])
        return np.concatenate(out)

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
        deg = np.degrees(qa).round(0)
        if hit:
            names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in min(hit)]
            return f"geoms {names[0]} and {names[1]} touch at {deg} deg"
        low = min(
            d.xpos[self.moved_body, 2].min(initial=np.inf),
            d.geom_xpos[self.moved_geom, 2].min(initial=np.inf),
            d.site_xpos[self.moved_site, 2].min(initial=np.inf),
        )
        if low < self.floor:
            return f"the arm reaches z = {low:.3f} m, below {self.floor} m, at {deg} deg"
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
                f"{deg} deg"
            )
        return None

    def path_problem(self, a: np.ndarray, b: np.ndarray, speed: float, ramp: float) -> str | None:
        """None when ``Arm.move_to`` from a to b (rad) at ``speed`` rad/s with ramps of
        ``ramp`` s is admissible at every pose of its straight joint-space line (``problem``)."""
        way = b - a
        longest = np.abs(way).max()
        accel = way / longest * (_SERVO * speed / ramp) if longest > 0 else None
        return next((p for q in _path(a, b) if (p := self.problem(q, accel))), None)


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
    base frame: the mounting surface), and robot geoms closer than 5 mm to each other (pairs
    that already touch at q = 0 belong to the construction and are ignored). ``gravity``
    (3,) m/s^2 in the base frame (default: the model's).
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
def _runs(ok: np.ndarray, min_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of ok (C, S): the run of True through the middle index S // 2.

    Returns first index (C,), last index (C,) and valid (C,): the middle is True and the run
    has at least ``min_len`` steps (last - first >= min_len).
    """
    C, S = ok.shape
    mid = S // 2
    idx = np.arange(S)
    bad_left = np.where(~ok & (idx <= mid), idx, -1).max(axis=1)
    bad_right = np.where(~ok & (idx >= mid), idx, S).min(axis=1)
    first, last = bad_left + 1, bad_right - 1
    valid = ok[:, mid] & (last - first >= min_len)
    return first, last, valid


@dataclass
class _Search:
    """Candidate holds of one swept joint on the model (C candidates, S angles of the sweep).

    A candidate's sweep is its admissible stretch (``_runs``) through the middle of the range:
    ``loaded`` alone gives an upper bound of what the exact stretch (also clear) gives.
    """

    joint: int
    angles: np.ndarray  # (S,) rad
    holds: np.ndarray  # (C, n) rad
    gravity: np.ndarray  # (C, S) N m, the swept joint's
    loaded: np.ndarray  # (C, S) bool: every gravity torque within the effort fraction
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
        self.first, self.last, self.valid = _runs(self.loaded, self.min_len)
        self.checked = np.zeros(len(self.holds), bool)

    def poses(self, c: int) -> np.ndarray:
        q = np.repeat(self.holds[c][None], len(self.angles), axis=0)
        q[:, self.joint] = self.angles
        return q

    def check(self, c: int, model: _Model) -> None:
        """Make candidate c's stretch exact: also clear of the floor and of the robot."""
        if self.checked[c]:
            return
        accel = np.zeros(len(self.holds[c]))
        accel[self.joint] = self.accel
        clear = np.array([model.problem(q, accel) is None for q in self.poses(c)])
        f, la, v = _runs((self.loaded[c] & clear)[None], self.min_len)
        self.first[c], self.last[c], self.valid[c] = f[0], la[0], v[0]
        self.checked[c] = True

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
        lower, upper: rad, the swept range (default -100..+100 deg, within the joint limits).
        speed: rad/s, speed of the sweeps (default 40 deg/s).
        slow_speed: rad/s, speed of the second sweep of a joint with several (default
            20 deg/s), so that the fit can tell viscous from Coulomb friction; None: all at
            ``speed``.
        move_speed: rad/s, speed of the transfers between sweeps (default 40 deg/s).
        settle: s, hold at each sweep's start (default 0.5 s).
        ramp: s, time of every move's speed ramps (default 0.25 s).
        grid: rad, the values a held joint takes in a candidate hold (default -90, -45, 0,
            45, 90 deg).
        effort_fraction: fraction of each effort limit that gravity may take (default 0.6;
            the rest is left for friction and the ramps).
        floor: m, the lowest z (base frame) a link origin, geom centre or site may reach
            (default 0.05 m).
        min_amplitude: N m, peak-to-peak gravity torque below which gravity does not excite a
            joint (default 0.05 N m).
        amplitude_fraction: a further hold of a joint keeps at least this fraction of its
            first hold's amplitude (default 0.5).
        min_span: rad, the shortest admissible sweep (default 100 deg).
        start: where recording starts, a pose name or (n,) rad; None: "home" (else zeros).

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
    ``speed`` rad/s (default -100..+100 deg at 40 deg/s, within the joint limits) while the
    others are held; the second sweep of a joint with several runs at ``slow_speed`` (default
    20 deg/s; None: all at ``speed``), so that the fit can tell viscous from Coulomb friction.
    A candidate hold puts every other joint at a value of ``grid`` (rad;
    default -90, -45, 0, 45, 90 deg; a joint whose axis stays parallel to gravity changes no
    gravity torque and keeps its ``start`` value). Along a sweep a pose is admissible when no
    gravity torque exceeds ``effort_fraction`` of its effort limit (the rest is left for
    friction and the ramps) and the arm is clear of the floor and of itself (see
    ``plan_issues``); a candidate's sweep is its admissible stretch through the middle of the
    range, which must span at least ``min_span`` rad. Per joint:

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
    transfers from ``start`` (pose name or (n,) rad; default "home"). A transfer whose straight
    line is not admissible goes through ``via`` poses: both sweeps' middle poses, and if need
    be a third pose between them (home, zero, or another sweep's middle pose).
    ``gravity`` (3,) m/s^2 in the base frame (default: the model's).
    """
    robot = load_robot(robot)
    options = dataclasses.replace(options or PlanOptions(), **overrides)
    return robot.cached(("default_plan", options), lambda: _design(robot, options))


def _design(robot: Robot, o: PlanOptions) -> CalibrationPlan:
    """The search of ``default_plan`` (uncached)."""
    model = _Model(robot, o.gravity, o.effort_fraction, o.floor)
    n = model.n
    if int(o.sweeps_per_joint) < 1:
        raise InputError(f"sweeps_per_joint must be >= 1, got {o.sweeps_per_joint}")
    lim = robot.joint_limits[model.arm] + np.array([LIMIT_MARGIN, -LIMIT_MARGIN])
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
        lo, hi = max(o.lower, lim[j, 0]), min(o.upper, lim[j, 1])
        if not lo < hi:
            raise InputError(f"joint {j}: the range {o.lower}..{o.upper} rad is outside its limits")
        angles = np.linspace(lo, hi, int(np.ceil((hi - lo) / _STEP - 1e-9)) + 1)
        values = [
            [0.0]
            if k == j
            else [float(home[k])]
            if inert[k]
            else sorted({float(np.clip(v, *lim[k])) for v in o.grid})
            for k in range(n)
        ]
        holds = np.array(list(itertools.product(*values)))
        poses = np.repeat(holds[:, None, :], len(angles), axis=1)
        poses[:, :, j] = angles
        g = model.gravity(poses.reshape(-1, n))
        C, S = len(holds), len(angles)
        step = (hi - lo) / (S - 1)
        searches.append(
            _Search(
                joint=j,
                angles=angles,
                holds=holds,
                gravity=g[:, j].reshape(C, S),
                loaded=(model.overload(g) <= 1.0).reshape(C, S),
                min_len=int(math.ceil(min(o.min_span, hi - lo) / step - 1e-9)),
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
            for c in np.argsort(dist, kind="stable")[:50]:
                s.check(int(c), model)
                if s.valid[c] and s.last[c] - s.first[c] == full:
                    break
            span = np.where(s.valid & s.checked, s.last - s.first, -1)
            if span.max() < 0:
                raise InputError(
                    f"joint {s.joint}: no held pose gives it a sweep of "
                    f"{math.degrees(o.min_span):.0f} deg through the middle of its range, clear of "
                    "the floor, of the robot itself and of the effort limits"
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

    # transfers: straight, else through both sweeps' middle poses (and a third pose between)
    middle = {s.joint: s.angles[len(s.angles) // 2] for s in searches}
    mids = [s.pose(middle[s.joint]) for s in sweeps]
    stops = [home, np.zeros(n)] + mids
    out: list[Sweep] = []
    for s, mid in zip(sweeps, mids, strict=True):
        a = out[-1].start if out else home
        points = [a] + ([out[-1].pose(middle[out[-1].joint])] if out else []) + [mid]
        routes = [[]] + [points[1:]]
        routes += [points[1:-1] + [x, mid] for x in sorted(stops, key=lambda x: _way(points, x))]
        for via in routes:
            legs = itertools.pairwise([a] + via + [s.start])
            if not any(model.path_problem(p, q, o.move_speed, o.ramp) for p, q in legs):
                break
        else:
            via = points[1:]  # plan_issues() tells what is left
        via = [v for k, v in enumerate(via) if np.abs(v - ([a] + via)[k]).max() > 1e-12]
        out.append(Sweep(s.joint, s.hold, s.lower, s.upper, s.speed, tuple(via)))
    return CalibrationPlan(tuple(out), o.move_speed, o.settle, o.ramp).validate(robot)
