"""Targets for the end effector as functions of time: static point, line, circle, half circle.

A ``Trajectory`` maps time t (s, from the start of the run) to the target position (m),
velocity (m/s) and acceleration (m/s^2), each (3,), in one fixed frame: the world (odometry)
frame in tracking mode, the mobile base's own frame in guidance mode (see ``control.loop``).
Every path is made of straight lines and circular arcs, each traversed with a trapezoidal speed
profile (ramps at ``a`` m/s^2, cruise at ``v`` m/s), so position, velocity and acceleration are
exact and continuous in position and velocity; after its end a trajectory holds its last point.

Trajectories are written as a spec string ``KIND[:key=value,...]`` (``parse_trajectory``) and
built against the start of a run (``TrajectorySpec.build``): defaults are relative to the end
effector's start position and to the arm's base frame, so each kind works out of the box.

Kinds and keys (``v`` m/s cruise speed, ``a`` m/s^2 ramps, default 0.25; ``passes`` one-way
traversals; ``turns`` full circles, default endless):

- ``static``: x, y, z (m, absolute) or dx, dy, dz (m, from the start); default: the start.
- ``line``: dx, dy, dz (m, the far end from the start; default 0.1 m along the arm's y), v
  (0.05), a, passes (2: there and back).
- ``circle``: r (0.1), v (0.05), a, turns, dir (+1: counter-clockwise seen from above), cx, cy,
  cz (m, the centre; default: r from the start towards the arm's vertical axis, so that the
  circle starts at the start position; a given centre is reached by a straight lead-in).
- ``half-circle``: the paper's Exp. 2: r (0.315), v (0.101), a, passes (4) over the half circle
  in front of the arm, centred on the arm's vertical axis (cx, cy) at the start height (z),
  reached by a straight lead-in to its nearer end.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError

DEFAULT_ACCEL = 0.25  # m/s^2, ramps of every speed profile
_EPS = 1e-12


class TargetSample(NamedTuple):
    """Target at one time: position m, velocity m/s, acceleration m/s^2, each (3,)."""

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray


# ----------------------------------------------------------------------------- speed profiles


@dataclass(frozen=True)
class Profile:
    """Trapezoidal (or triangular) speed profile over ``length`` m (``math.inf``: ramp up then
    cruise forever) at cruise speed ``speed`` m/s with ramps of ``accel`` m/s^2."""

    length: float
    speed: float
    accel: float
    # derived once (the 1 kHz loop evaluates the profile every cycle)
    _t_acc: float = field(init=False, repr=False, compare=False, default=0.0)
    _peak: float = field(init=False, repr=False, compare=False, default=0.0)
    _total: float = field(init=False, repr=False, compare=False, default=0.0)

    def __post_init__(self) -> None:
        checks.number(self.speed, "profile speed", positive=True, unit="m/s")
        checks.number(self.accel, "profile accel", positive=True, unit="m/s^2")
        if not (self.length >= 0):
            raise InputError(f"profile length must be >= 0 m, got {self.length}")
        t_acc = self.speed / self.accel
        if math.isfinite(self.length) and self.accel * t_acc**2 > self.length:
            t_acc = math.sqrt(self.length / self.accel)  # triangular
        peak = self.accel * t_acc
        if not math.isfinite(self.length):
            total = math.inf
        elif self.length <= 0:
            total = 0.0
        else:
            total = 2 * t_acc + (self.length - self.accel * t_acc**2) / peak
        object.__setattr__(self, "_t_acc", t_acc)
        object.__setattr__(self, "_peak", peak)
        object.__setattr__(self, "_total", total)

    @property
    def duration(self) -> float:
        """s (``math.inf`` for an endless profile)."""
        return self._total

    def __call__(self, t: float) -> tuple[float, float, float]:
        """(s m, ds/dt m/s, d2s/dt2 m/s^2) at time t s (clamped to [0, duration])."""
        if self.length <= 0 or t <= 0:
            return 0.0, 0.0, 0.0
        a, t_acc = self.accel, self._t_acc
        if t < t_acc:
            return 0.5 * a * t * t, a * t, a
        total = self._total
        if t >= total:
            return self.length, 0.0, 0.0
        rest = total - t
        if rest < t_acc:
            return self.length - 0.5 * a * rest * rest, a * rest, -a
        return 0.5 * a * t_acc * t_acc + self._peak * (t - t_acc), self._peak, 0.0


# ----------------------------------------------------------------------------- geometry


class Segment(ABC):
    """A path parametrised by arc length s (m): point, unit tangent, curvature vector."""

    length: float

    @abstractmethod
    def at(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The path's point and its derivatives at arc length ``s``.

        Args:
            s: Arc length, m.

        Returns:
            (p m, dp/ds, d2p/ds2 1/m), each (3,).
        """

    def sample(self, s: float, sd: float, sdd: float) -> TargetSample:
        """Position, velocity and acceleration moving along the path: p(s), p' sd,
        p'' sd^2 + p' sdd.

        Args:
            s: Arc length, m.
            sd: s', m/s.
            sdd: s'', m/s^2.

        Returns:
            The target, each field (3,).
        """
        p, dp, ddp = self.at(s)
        return TargetSample(p, dp * sd, ddp * (sd * sd) + dp * sdd)

    def farthest(self, point: np.ndarray, s_end: float) -> np.ndarray:
        """The point of the path farthest from ``point`` (here: of 1001 samples; exact in
        ``Line`` and ``Arc``).

        Args:
            point: (3,) m.
            s_end: m, the path is searched over arc lengths [0, s_end].

        Returns:
            (3,) m.
        """
        points = [self.at(s)[0] for s in np.linspace(0.0, s_end, 1001)]
        return _farthest(points, point)


def _farthest(points, point: np.ndarray) -> np.ndarray:
    """The one of ``points`` (each (3,) m) farthest from ``point``."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    return points[int(np.argmax(np.linalg.norm(points - point, axis=1)))].copy()


def _floats(v) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


@dataclass(frozen=True)
class Line(Segment):
    """Straight line from ``start`` to ``end`` (m)."""

    start: np.ndarray
    end: np.ndarray

    @property
    def length(self) -> float:  # type: ignore[override]
        return float(np.linalg.norm(self.end - self.start))

    def _unit(self) -> np.ndarray:
        d = self.end - self.start
        n = float(np.linalg.norm(d))
        return d / n if n > _EPS else np.zeros(3)

    def at(self, s: float):
        """``Segment.at``, s capped at the line's length.

        Args:
            s: Arc length, m.

        Returns:
            (p m, unit direction, zeros), each (3,).
        """
        return self.start + self._unit() * min(s, self.length), self._unit(), np.zeros(3)

    def farthest(self, point: np.ndarray, s_end: float) -> np.ndarray:
        """``Segment.farthest``, exact: one of the two ends.

        Args:
            point: (3,) m.
            s_end: m, the far end's arc length.

        Returns:
            (3,) m.
        """
        # the distance from a point is convex along a line: one of the two ends
        return _farthest([self.start, self.at(s_end)[0]], point)

    def sample(self, s: float, sd: float, sdd: float) -> TargetSample:
        """``Segment.sample``: along the line's direction, s capped at its length.

        Args:
            s: Distance from ``start``, m.
            sd: Speed along the line, m/s.
            sdd: Acceleration along it, m/s^2.

        Returns:
            Position, velocity, acceleration.
        """
        # scalar maths on cached floats: a few us per call at 1 kHz
        fast = self.__dict__.get("_fast")
        if fast is None:
            fast = (_floats(self.start), _floats(self._unit()), self.length)
            object.__setattr__(self, "_fast", fast)
        (x0, y0, z0), (ux, uy, uz), n = fast
        s = min(s, n)
        return TargetSample(
            np.array((x0 + ux * s, y0 + uy * s, z0 + uz * s)),
            np.array((ux * sd, uy * sd, uz * sd)),
            np.array((ux * sdd, uy * sdd, uz * sdd)),
        )


@dataclass(frozen=True)
class Arc(Segment):
    """Circular arc: centre (m), radius (m), in-plane orthonormal axes u, w, from angle
    ``phi0`` rad through a signed ``sweep`` rad (``math.inf`` * sign: endless); the point at
    angle phi is centre + radius (cos phi u + sin phi w)."""

    centre: np.ndarray
    radius: float
    u: np.ndarray
    w: np.ndarray
    phi0: float
    sweep: float

    @property
    def length(self) -> float:  # type: ignore[override]
        return abs(self.sweep) * self.radius

    def at(self, s: float):
        """``Segment.at``.

        Args:
            s: Arc length, m, from ``phi0`` in the sweep's direction.

        Returns:
            (p m, unit tangent, -radial / radius 1/m), each (3,).
        """
        sign = 1.0 if self.sweep >= 0 else -1.0
        phi = self.phi0 + sign * s / self.radius
        c, sn = math.cos(phi), math.sin(phi)
        radial = c * self.u + sn * self.w
        tangent = sign * (-sn * self.u + c * self.w)
        return self.centre + self.radius * radial, tangent, -radial / self.radius

    def farthest(self, point: np.ndarray, s_end: float) -> np.ndarray:
        """``Segment.farthest``, exact.

        Args:
            point: (3,) m.
            s_end: m, the arc is searched over arc lengths [0, s_end].

        Returns:
            (3,) m.
        """
        # |c + r radial(phi) - p|^2 = const + 2 r (c - p).radial(phi): largest at the ends or
        # where radial(phi) points along (c - p)'s part in the plane, if the arc gets there
        span = min(s_end, self.length) / self.radius
        sign = 1.0 if self.sweep >= 0 else -1.0
        off = self.centre - np.asarray(point, dtype=float)
        best = math.atan2(float(off @ self.w), float(off @ self.u))
        angles = [self.phi0, self.phi0 + sign * span]
        if span >= 2 * math.pi or (sign * (best - self.phi0)) % (2 * math.pi) <= span:
            angles.append(best)
        return _farthest([self.at(sign * (a - self.phi0) * self.radius)[0] for a in angles], point)

    def sample(self, s: float, sd: float, sdd: float) -> TargetSample:
        """``Segment.sample``: s'' along the tangent plus sd^2 / radius towards the centre.

        Args:
            s: Arc length from ``phi0``, m.
            sd: Speed along the arc, m/s.
            sdd: Its rate of change, m/s^2.

        Returns:
            Position, velocity (tangent), acceleration.
        """
        fast = self.__dict__.get("_fast")
        if fast is None:
            fast = (_floats(self.centre), _floats(self.u), _floats(self.w))
            object.__setattr__(self, "_fast", fast)
        (cx, cy, cz), (ux, uy, uz), (wx, wy, wz) = fast
        r = self.radius
        sign = 1.0 if self.sweep >= 0 else -1.0
        phi = self.phi0 + sign * s / r
        c, sn = math.cos(phi), math.sin(phi)
        rx, ry, rz = c * ux + sn * wx, c * uy + sn * wy, c * uz + sn * wz  # radial
        tx, ty, tz = sign * (c * wx - sn * ux), sign * (c * wy - sn * uy), sign * (c * wz - sn * uz)
        k = -sd * sd / r  # centripetal
        return TargetSample(
            np.array((cx + r * rx, cy + r * ry, cz + r * rz)),
            np.array((tx * sd, ty * sd, tz * sd)),
            np.array((k * rx + sdd * tx, k * ry + sdd * ty, k * rz + sdd * tz)),
        )


# ----------------------------------------------------------------------------- trajectories


class Trajectory(ABC):
    """Target position, velocity, acceleration as a function of time t s (see module doc)."""

    #: s, time after which the target holds still (``math.inf``: never).
    duration: float
    #: human-readable description (kind and figures).
    description: str

    @abstractmethod
    def __call__(self, t: float) -> TargetSample:
        """The target at time t s (t < 0 counts as 0)."""

    def sample(self, times) -> TargetSample:
        """The target at several times.

        Args:
            times: (N,) s.

        Returns:
            pos m, vel m/s, acc m/s^2, each (N, 3).
        """
        out = [self(float(t)) for t in np.asarray(times, dtype=float).ravel()]
        return TargetSample(*(np.array([getattr(o, f) for o in out]) for f in TargetSample._fields))

    def farthest(self, point, until: float) -> np.ndarray:
        """The target farthest from ``point`` (here: sampled every 10 ms, at most 100 000
        samples; exact in ``Static`` and ``Piecewise``).

        Args:
            point: (3,) m, the trajectory's frame.
            until: s, the target is searched over times [0, until].

        Returns:
            (3,) m, the trajectory's frame.
        """
        end = min(float(until), self.duration)
        times = np.linspace(0.0, end, int(min(end / 0.01, 1e5)) + 2)
        return _farthest(self.sample(times).pos, np.asarray(point, dtype=float))


@dataclass(frozen=True)
class Static(Trajectory):
    """A fixed target ``point`` (m)."""

    point: np.ndarray
    description: str = "static"
    duration: float = 0.0

    def __call__(self, t: float) -> TargetSample:
        return TargetSample(self.point.copy(), np.zeros(3), np.zeros(3))

    def farthest(self, point, until: float) -> np.ndarray:
        """``Trajectory.farthest``: the point itself.

        Args:
            point: (3,) m.
            until: s.

        Returns:
            (3,) m.
        """
        return self.point.copy()


@dataclass(frozen=True)
class Piecewise(Trajectory):
    """Segments traversed one after the other, each with its own ``Profile``."""

    pieces: tuple[tuple[Segment, Profile], ...]
    description: str = "path"
    _starts: tuple[float, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.pieces:
            raise InputError("a path needs at least one segment")
        starts, t = [], 0.0
        for _, prof in self.pieces:
            starts.append(t)
            t += prof.duration
        object.__setattr__(self, "_starts", tuple(starts))

    @property
    def duration(self) -> float:  # type: ignore[override]
        return self._starts[-1] + self.pieces[-1][1].duration

    def farthest(self, point, until: float) -> np.ndarray:
        """``Trajectory.farthest``, exact over the segments reached by ``until``.

        Args:
            point: (3,) m.
            until: s.

        Returns:
            (3,) m.
        """
        point = np.asarray(point, dtype=float)
        found = []
        for (seg, prof), start in zip(self.pieces, self._starts, strict=True):
            if found and start > until:
                break
            s_end = prof(min(max(until - start, 0.0), prof.duration))[0]
            found.append(seg.farthest(point, s_end))
        return _farthest(found, point)

    def __call__(self, t: float) -> TargetSample:
        t = max(float(t), 0.0)
        i = len(self.pieces) - 1
        while i > 0 and t < self._starts[i]:
            i -= 1
        seg, prof = self.pieces[i]
        return seg.sample(*prof(t - self._starts[i]))


# ----------------------------------------------------------------------------- specs


_KEYS = {
    "static": {"x", "y", "z", "dx", "dy", "dz"},
    "line": {"dx", "dy", "dz", "v", "a", "passes"},
    "circle": {"r", "v", "a", "turns", "dir", "cx", "cy", "cz"},
    "half-circle": {"r", "v", "a", "passes", "cx", "cy", "z"},
}
KINDS = tuple(_KEYS)


@dataclass(frozen=True)
class TrajectorySpec:
    """A parsed ``KIND[:key=value,...]`` spec; ``build`` resolves it against a run's start."""

    kind: str
    options: dict[str, float] = field(default_factory=dict)

    def __str__(self) -> str:
        opts = ",".join(f"{k}={v:g}" for k, v in self.options.items())
        return self.kind + (f":{opts}" if opts else "")

    def _get(self, key: str, default: float, *, positive: bool = False) -> float:
        value = float(self.options.get(key, default))
        if positive and not value > 0:
            raise InputError(f"trajectory {self.kind}: {key} must be > 0, got {value:g}")
        return value

    def _count(self, key: str, default: float) -> float:
        value = self._get(key, default, positive=True)
        if math.isfinite(value) and value != round(value):
            raise InputError(f"trajectory {self.kind}: {key} must be a whole number, got {value:g}")
        return value

    def build(
        self,
        start,
        arm_origin=None,
        arm_rotation=None,
    ) -> Trajectory:
        """The trajectory for a run whose end effector starts at ``start``.

        Args:
            start: (3,) m, the end effector at the start, in the trajectory's frame.
            arm_origin: (3,) m, the arm base frame's origin at the start, in the trajectory's
                frame (default: zeros, the arm's own frame).
            arm_rotation: (3, 3), its axes (default: identity). Both place the default circle
                and half circle (horizontal, around the arm's vertical axis).

        Returns:
            The trajectory, in the frame of ``start``.

        Raises:
            InputError: ``start`` or ``arm_origin`` not a finite (3,) vector, or an option
                the kind refuses.
        """
        start = checks.array(start, "start", n=3, unit="m")
        origin = (
            np.zeros(3)
            if arm_origin is None
            else checks.array(arm_origin, "arm_origin", n=3, unit="m")
        )
        rot = np.eye(3) if arm_rotation is None else np.asarray(arm_rotation, dtype=float)
        builder = getattr(self, "_" + self.kind.replace("-", "_"))
        return builder(start, origin, rot)

    # ---- kinds
    def _static(self, start, origin, rot) -> Trajectory:
        o = self.options
        if {"x", "y", "z"} & set(o) and {"dx", "dy", "dz"} & set(o):
            raise InputError("trajectory static: give x, y, z (absolute) or dx, dy, dz, not both")
        point = start.copy()
        for i, axis in enumerate("xyz"):
            if axis in o:
                point[i] = o[axis]
            point[i] += o.get("d" + axis, 0.0)
        return Static(point, description=f"static at {_fmt(point)} m")

    def _line(self, start, origin, rot) -> Trajectory:
        o = self.options
        if {"dx", "dy", "dz"} & set(o):
            delta = np.array([o.get("dx", 0.0), o.get("dy", 0.0), o.get("dz", 0.0)])
        else:
            delta = 0.1 * _horizontal(rot[:, 1])
        if np.linalg.norm(delta) < 1e-6:
            raise InputError("trajectory line: the offset dx, dy, dz must not be zero")
        v, a = self._get("v", 0.05, positive=True), self._get("a", DEFAULT_ACCEL, positive=True)
        passes = self._count("passes", 2)
        if not math.isfinite(passes):
            raise InputError("trajectory line: passes must be finite")
        ends = (start, start + delta)
        pieces = []
        for k in range(int(passes)):
            seg = Line(ends[k % 2], ends[(k + 1) % 2])
            pieces.append((seg, Profile(seg.length, v, a)))
        desc = f"line {_fmt(delta)} m, {v:g} m/s, {int(passes)} pass(es)"
        return Piecewise(tuple(pieces), description=desc)

    def _circle(self, start, origin, rot) -> Trajectory:
        o = self.options
        r, v = self._get("r", 0.1, positive=True), self._get("v", 0.05, positive=True)
        a = self._get("a", DEFAULT_ACCEL, positive=True)
        turns = self._count("turns", math.inf)
        direction = self._get("dir", 1.0)
        if direction not in (1.0, -1.0):
            raise InputError(f"trajectory circle: dir must be 1 or -1, got {direction:g}")
        u_axis, w_axis = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
        pieces: list[tuple[Segment, Profile]] = []
        if {"cx", "cy", "cz"} & set(o):
            centre = np.array([o.get("cx", start[0]), o.get("cy", start[1]), o.get("cz", start[2])])
            d = _horizontal(start - centre, fallback=_horizontal(rot[:, 0]))
            first = centre + r * d
            first[2] = centre[2]
            lead = Line(start, first)
            if lead.length > 1e-9:
                pieces.append((lead, Profile(lead.length, v, a)))
        else:  # the start lies on the circle, the centre r towards the arm's vertical axis
            inward = _horizontal(origin - start, fallback=-_horizontal(rot[:, 0]))
            centre = start + r * inward
            d = -inward
        phi0 = math.atan2(float(d @ w_axis), float(d @ u_axis))
        sweep = direction * 2 * math.pi * turns
        arc = Arc(centre, r, u_axis, w_axis, phi0, sweep)
        pieces.append((arc, Profile(arc.length, v, a)))
        turns_txt = "endless" if not math.isfinite(turns) else f"{int(turns)} turn(s)"
        desc = f"circle r {r:g} m about {_fmt(centre)} m, {v:g} m/s, {turns_txt}"
        return Piecewise(tuple(pieces), description=desc)

    def _half_circle(self, start, origin, rot) -> Trajectory:
        o = self.options
        r, v = self._get("r", 0.315, positive=True), self._get("v", 0.101, positive=True)
        a = self._get("a", DEFAULT_ACCEL, positive=True)
        passes = self._count("passes", 4)
        if not math.isfinite(passes):
            raise InputError("trajectory half-circle: passes must be finite")
        centre = np.array([o.get("cx", origin[0]), o.get("cy", origin[1]), o.get("z", start[2])])
        u = _horizontal(rot[:, 0])  # the arm's forward direction: the half circle's middle
        w = np.cross([0.0, 0.0, 1.0], u)
        ends = (-math.pi / 2, math.pi / 2)
        points = [centre + r * (math.cos(p) * u + math.sin(p) * w) for p in ends]
        near = int(np.argmin([np.linalg.norm(p - start) for p in points]))
        pieces: list[tuple[Segment, Profile]] = []
        lead = Line(start, points[near])
        if lead.length > 1e-9:
            pieces.append((lead, Profile(lead.length, v, a)))
        for k in range(int(passes)):
            phi = ends[(near + k) % 2]
            arc = Arc(centre, r, u, w, phi, math.pi if phi < 0 else -math.pi)
            pieces.append((arc, Profile(arc.length, v, a)))
        desc = (
            f"half circle r {r:g} m about {_fmt(centre)} m, {v:g} m/s, {int(passes)} pass(es) "
            f"after a {lead.length:.3f} m lead-in"
        )
        return Piecewise(tuple(pieces), description=desc)


def _horizontal(d, fallback=None) -> np.ndarray:
    """Unit horizontal part of ``d`` (``fallback`` or x when it has none)."""
    h = np.array([d[0], d[1], 0.0], dtype=float)
    n = float(np.linalg.norm(h))
    if n < 1e-9:
        return np.array([1.0, 0.0, 0.0]) if fallback is None else np.asarray(fallback, float)
    return h / n


def _fmt(x) -> str:
    return "(" + ", ".join(f"{v:.3f}" for v in np.asarray(x)) + ")"


def parse_trajectory(spec: str) -> TrajectorySpec:
    """Parse ``KIND[:key=value,...]`` (see the module doc).

    Args:
        spec: The spec string.

    Returns:
        The spec, its values checked by building it once.

    Raises:
        InputError: naming the problem (unknown kind or key, a value that is not a number).
    """
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(f"trajectory spec must be a non-empty string, got {spec!r}")
    kind, _, rest = spec.strip().partition(":")
    kind = kind.strip().lower().replace("_", "-")
    if kind == "halfcircle":
        kind = "half-circle"
    if kind not in _KEYS:
        raise InputError(f"unknown trajectory {kind!r}; kinds: {', '.join(KINDS)}")
    options: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip().lower()
        if not eq:
            raise InputError(f"trajectory {kind}: {item!r} is not key=value")
        if key not in _KEYS[kind]:
            raise InputError(
                f"trajectory {kind}: unknown key {key!r}; keys: {', '.join(sorted(_KEYS[kind]))}"
            )
        try:
            number = float(value)
        except ValueError:
            raise InputError(f"trajectory {kind}: {key}={value!r} is not a number") from None
        if math.isnan(number) or (math.isinf(number) and key != "turns"):
            raise InputError(f"trajectory {kind}: {key} must be finite, got {value!r}")
        if key in options:
            raise InputError(f"trajectory {kind}: {key} given twice")
        options[key] = number
    out = TrajectorySpec(kind, options)
    out.build(np.array([0.3, 0.0, 0.4]))  # validate the values now, not at the start of a run
    return out


__all__ = [
    "KINDS",
    "Arc",
    "Line",
    "Piecewise",
    "Profile",
    "Segment",
    "Static",
    "TargetSample",
    "Trajectory",
    "TrajectorySpec",
    "parse_trajectory",
]
