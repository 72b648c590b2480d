"""Plan design: the paper's calibration plan, its held poses and speeds chosen on the model.

``default_plan(robot)`` computes the paper's calibration (paper IV-A) on the robot's model, for
any arm: for each current-controlled joint it searches held poses (every other joint at -90,
-45, 0, 45 or 90 deg, within its limits) where gravity has a large lever on the swept joint
over -100..+100 deg (within the joint's limits less a margin), rejects poses that overload an
actuator, reach the mounting surface or make the robot touch itself (``identify.plan_checks``'
model), and picks about three per joint that excite every link's centre of mass in different
directions (a greedy D-optimal design). Its options are one frozen ``PlanOptions``; the plan
is kept on the robot per options (``Robot.cached``): the search takes seconds (about 15-30 s
for a 7-joint arm). ``inner_limits`` and ``sweep_window`` place a sweep within a joint's
limits (random plans use them too).
Units: rad, rad/s, s, m, N m.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import jax
import numpy as np

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
from jaxcomp.identify.plan_checks import CHECK_STEP, SERVO_RAMP_FACTOR, PlanModel
from jaxcomp.poses import LIMIT_MARGIN as POSE_MARGIN
from jaxcomp.robot import Robot, load_robot

#: m, the prior uncertainty of each link's centre of mass weighing the design's information.
_PRIOR_COM = 0.01


def inner_limits(limits: np.ndarray) -> np.ndarray:
    """Joint limits less a margin: ``jaxcomp.poses.LIMIT_MARGIN`` of each range, at least
    ``LIMIT_MARGIN`` (1 deg, the ``Arm``'s); infinite limits stay infinite.

    Args:
        limits: (n, 2) rad, lower and upper limits.

    Returns:
        (n, 2) rad, the inner limits.
    """
    limits = np.asarray(limits, float)
    span = limits[:, 1] - limits[:, 0]
    margin = np.maximum(np.where(np.isfinite(span), POSE_MARGIN * span, 0.0), LIMIT_MARGIN)
    return limits + margin[:, None] * np.array([1.0, -1.0])


def sweep_window(lower: float, upper: float, lo: float, hi: float) -> tuple[float, float]:
    """A sweep placed within a joint's limits: cut at a limit and moved away from it by what
    it lost there (as far as the other limit allows).

    Args:
        lower: rad, the sweep's wanted start.
        upper: rad, its wanted end.
        lo: rad, the joint's (inner) lower limit.
        hi: rad, its (inner) upper limit.

    Returns:
        (lower, upper) rad, the sweep within ``lo``..``hi`` (empty, lower >= upper, when the
        limits leave no range).
    """
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
    possible: np.ndarray  # (C, S) bool: not refused for sure (``PlanModel.surely_bad``)
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

    def check(self, c: int, model: PlanModel) -> None:
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

    def information(self, cands: np.ndarray, weight: float, model: PlanModel) -> np.ndarray:
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

    Args:
        robot: the robot (name, path or ``Robot``).
        options: the ``PlanOptions`` (default ``PlanOptions()``; ``gravity`` (3,) m/s^2 in
            the base frame, None: the model's).
        **overrides: fields of ``options`` replaced.

    Returns:
        The validated ``CalibrationPlan``.

    Raises:
        InputError: an option is out of range, or a joint has no admissible sweep.
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
    """The search of ``default_plan`` (uncached): the candidate holds of every joint, the
    first hold of each, further holds (D-optimal), the sweeps in order, the transfers' via
    poses."""
    model = PlanModel(robot, o.gravity, o.effort_fraction, o.floor)
    if int(o.sweeps_per_joint) < 1:
        raise InputError(f"sweeps_per_joint must be >= 1, got {o.sweeps_per_joint}")
    names = [robot.joint_names[a] for a in model.arm]
    home = arm_pose(robot, o.start)
    inner = inner_limits(robot.joint_limits[model.arm])
    inert = _inert(model)
    searches = [_search(j, model, o, home, inner, inert, names[j]) for j in range(model.n)]
    # per checked angle: both directions' samples times the per-sample weight
    weight = {
        s.joint: model.weight[s.joint] * 2 * CHECK_STEP / o.speed / CONTROL_PERIOD for s in searches
    }
    info = _first_holds(searches, model, o, weight)
    _more_holds(searches, model, o, weight, info)
    sweeps = _ordered_sweeps(searches, model, o, home, names)
    return CalibrationPlan(
        tuple(_routed(sweeps, searches, model, o, home)), o.move_speed, o.settle, o.ramp
    ).validate(robot)


def _inert(model: PlanModel) -> np.ndarray:
    """(n,) bool: the joints whose axis no other arm joint turns and lies parallel to gravity
    (they change no gravity torque)."""
    tree, n = model.robot.tree, model.n
    body = tree.joint_body[model.arm]
    turns = tree.moves[model.arm][:, body] & ~np.eye(n, dtype=bool)  # (k, j): k turns j
    axes = model.axes0
    vertical = np.linalg.norm(np.cross(axes, model.g / np.linalg.norm(model.g)), axis=1) < 1e-9
    return vertical & ~turns.any(axis=0) & tree.is_hinge[model.arm]


def _search(
    j: int,
    model: PlanModel,
    o: PlanOptions,
    home: np.ndarray,
    inner: np.ndarray,
    inert: np.ndarray,
    name: str,
) -> _Search:
    """The candidate holds of joint j (its name ``name``) and their sweeps' cheap checks
    (load, pre-checks); ``inner`` (n, 2) rad the joints' ``inner_limits``, ``inert`` (n,)
    ``_inert``'s."""
    n = model.n
    lo, hi = sweep_window(o.lower, o.upper, *inner[j])
    if not lo < hi:
        raise InputError(
            f"joint {j} ({name}): its limits {np.degrees(inner[j]).round(1).tolist()} deg "
            "(less the margin) leave no range to sweep"
        )
    angles = np.linspace(lo, hi, int(np.ceil((hi - lo) / CHECK_STEP - 1e-9)) + 1)
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
    accel = np.where(np.arange(n) == j, SERVO_RAMP_FACTOR * o.speed / o.ramp, 0.0)
    possible = ~model.surely_bad(poses.reshape(-1, n), accel).reshape(C, S)
    mid = int(np.argmin(np.abs(angles - model.zero[j])))
    min_len = int(math.ceil(min(o.min_span, hi - lo) / step - 1e-9))
    if not _runs(loaded & possible, min_len, mid)[2].any():  # too weak for min_span: shorter
        min_len = int(math.ceil(min(o.shortest_span, hi - lo) / step - 1e-9))
    return _Search(
        joint=j,
        angles=angles,
        mid=mid,
        holds=holds,
        gravity=g[:, j].reshape(C, S),
        loaded=loaded,
        possible=possible,
        min_len=min_len,
        accel=SERVO_RAMP_FACTOR * o.speed / o.ramp,
        distance=np.abs(np.delete(holds - home, j, axis=1)).max(axis=1),
    )


def _first_holds(
    searches: list[_Search], model: PlanModel, o: PlanOptions, weight: dict[int, float]
) -> np.ndarray:
    """Each joint's first hold, the largest exact amplitude (the load-only stretch bounds it),
    chosen into its search (``weight``: each joint's information weight per checked angle,
    1/(N m)^2); returns the COM information (nb * 3, nb * 3) 1/m^2: the prior's and theirs."""
    info = np.eye(model.robot.tree.nb * 3) / _PRIOR_COM**2
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
    return info


def _more_holds(
    searches: list[_Search],
    model: PlanModel,
    o: PlanOptions,
    weight: dict[int, float],
    info: np.ndarray,
) -> None:
    """Further holds, a greedy D-optimal design in turns over the joints (the load-only
    stretch bounds each gain), chosen into the searches; ``info`` the COM information of the
    holds chosen so far."""
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


def _ordered_sweeps(
    searches: list[_Search], model: PlanModel, o: PlanOptions, home: np.ndarray, names: list[str]
) -> list[Sweep]:
    """The sweeps of the chosen holds, grouped by joint, each joint's nearest start first (a
    joint without a hold gets its friction sweep, ``_friction_hold``)."""
    sweeps: list[Sweep] = []
    prev = home
    for s in searches:
        if not s.chosen:
            s.chosen.append(_friction_hold(s, model, prev, names))
        speeds = [
            o.speed if k != 1 or o.slow_speed is None else o.slow_speed
            for k in range(len(s.chosen))
        ]
        todo = [s.sweep(c, v) for c, v in zip(s.chosen, speeds, strict=True)]
        while todo:  # the nearest start first
            sweep = todo.pop(int(np.argmin([np.abs(t.start - prev).max() for t in todo])))
            sweeps.append(sweep)
            prev = sweep.start
    return sweeps


def _friction_hold(s: _Search, model: PlanModel, prev: np.ndarray, names: list[str]) -> int:
    """The hold of a joint gravity does not excite (friction only): its longest sweep at a
    hold near the previous sweep's start ``prev`` (n,) rad."""
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
    return int(_best(span.astype(float), dist, 0.5)[0])


def _routed(
    sweeps: list[Sweep],
    searches: list[_Search],
    model: PlanModel,
    o: PlanOptions,
    home: np.ndarray,
) -> list[Sweep]:
    """The sweeps with the via poses of their transfers: straight, else through both sweeps'
    middle poses (and one pose between: home, zero, a sweep's middle pose; else a sweep's
    start or turn; else two of these)."""
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
    return out
