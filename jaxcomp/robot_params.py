"""``RobotParams``: the actuator and centre-of-mass parameters identification writes.

The params file ties the three parts of jaxcomp together: identification writes it, the
controller reads it to turn torques into currents (``c = r tau + l ...``, paper Eq. 7, 14-16),
and the simulator reads the same format as its hidden "true robot".

Units: ``ratio`` A/(N m) per current-controlled joint, ``friction`` A (friction loss expressed
as motor current), ``com_offset`` m added to a link's nominal centre of mass in the link's own
frame, ``phase_shift`` rad. The current-controlled joints are the robot's joints minus the
planar joints of a mobile base (``BASE_JOINTS``); ``joints`` names them (files without it are
taken to be for the model's default joints).

JSON layout::

    {"model": "gen3_lite", "joints": ["joint_0", ...], "ratio": [...], "friction": [...],
     "com_offset": {"ARM": [dx, dy, dz], ...}, "phase_shift": [...] | null,
     "std": {"ratio": [...], ...} | null, "method": "...", "fit_seconds": 12.3 | null,
     "diagnostics": {...} | null}

Unknown keys are ignored, so a file may carry extra fields (the simulator's truth adds its
noise level).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax.numpy as jnp
import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError
from jaxcomp.params import InertialParams
from jaxcomp.reduction import BASE_JOINTS

if TYPE_CHECKING:
    from jaxcomp.robot import Robot

#: Joints of a mobile base (not current-controlled): excluded from the params' joints.
BASE_JOINTS = BASE_JOINTS

_REQUIRED = ("model", "ratio", "friction")
#: A/(N m), the nominal current/torque ratio of a joint whose model states none.
DEFAULT_RATIO = 1.0
#: A: motor current limit of a joint whose model declares neither a current nor an effort limit.
DEFAULT_CURRENT_LIMIT = 11.0


def arm_joint_indices(robot: Robot) -> np.ndarray:
    """Indices (into ``robot.joint_names``) of the current-controlled joints, in order.

    Args:
        robot: the model.

    Returns:
        (n,) int.
    """
    return np.array([i for i, n in enumerate(robot.joint_names) if n not in BASE_JOINTS], int)


def arm_joint_names(robot: Robot) -> tuple[str, ...]:
    """Names of the current-controlled joints, in order (the params' ``joints``).

    Args:
        robot: the model.

    Returns:
        (n,) names.
    """
    return tuple(robot.joint_names[i] for i in arm_joint_indices(robot))


@dataclass
class RobotParams:
    """Per-joint current/torque ratio and friction loss, per-link COM offsets.

    Attributes:
        model: robot model name (``Robot.name``) the params belong to.
        ratio: (n,) A/(N m), current per joint torque, > 0.
        friction: (n,) A, Coulomb friction loss as motor current, >= 0.
        com_offset: {link: (3,) m}, added to the link's nominal COM, link frame.
        phase_shift: (n,) rad or None, the gravity phase shift estimated per joint.
        std: standard errors, {field: same structure as the field} or None.
        method: how the params were obtained ("nominal", "truth", a fit method ...).
        fit_seconds: wall time of the fit, s, or None.
        diagnostics: what the fit reports besides the estimates (iterations, identifiability,
            which ratios came from a prior or a type mean ...), or None.
        joints: names of the joints the entries belong to, or None (the model's default).
    """

    model: str
    ratio: np.ndarray
    friction: np.ndarray
    com_offset: dict[str, np.ndarray] = field(default_factory=dict)
    phase_shift: np.ndarray | None = None
    std: dict | None = None
    method: str = "nominal"
    fit_seconds: float | None = None
    diagnostics: dict | None = None
    joints: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.model, str) or not self.model:
            raise InputError(f"model must be a non-empty string, got {self.model!r}")
        self.ratio = checks.array(self.ratio, "ratio", unit="A/(N m)")
        n = self.ratio.shape[0]
        if n == 0:
            raise InputError("ratio is empty: the params need one ratio per joint")
        self.friction = checks.array(self.friction, "friction", unit="A")
        if self.friction.shape[0] != n:  # name the field that disagrees with the joints
            named = len(self.joints) if isinstance(self.joints, (list, tuple)) else 0
            odd = [f for f in ("ratio", "friction") if len(getattr(self, f)) != named]
            raise InputError(
                f"{odd[0]} must have {named} entries, one per joint named in joints, got "
                f"{len(getattr(self, odd[0]))}"
                if named and len(odd) == 1
                else f"ratio has {n} entries but friction {self.friction.shape[0]}: both need "
                "one entry per joint"
            )
        if np.any(self.ratio <= 0):
            bad = np.flatnonzero(self.ratio <= 0).tolist()
            raise InputError(f"ratio must be positive (A per N m); joint index(es) {bad} are not")
        if np.any(self.friction < 0):
            bad = np.flatnonzero(self.friction < 0).tolist()
            raise InputError(f"friction must be >= 0 A; joint index(es) {bad} are negative")
        if not isinstance(self.com_offset, Mapping):
            raise InputError("com_offset must be a mapping {link name: [dx, dy, dz]} in m")
        self.com_offset = {
            str(k): checks.array(v, f"com_offset[{k!r}]", n=3, unit="m")
            for k, v in self.com_offset.items()
        }
        if self.phase_shift is not None:
            self.phase_shift = checks.array(self.phase_shift, "phase_shift", n=n, unit="rad")
        if self.std is not None and not isinstance(self.std, Mapping):
            raise InputError(f"std must be a mapping of standard errors or null, got {self.std!r}")
        if self.fit_seconds is not None:
            self.fit_seconds = checks.number(self.fit_seconds, "fit_seconds", nonneg=True, unit="s")
        if self.diagnostics is not None and not isinstance(self.diagnostics, Mapping):
            raise InputError(f"diagnostics must be a mapping or null, got {self.diagnostics!r}")
        if not isinstance(self.method, str):
            raise InputError(f"method must be a string, got {self.method!r}")
        if self.joints is not None:
            if isinstance(self.joints, str) or not all(isinstance(j, str) for j in self.joints):
                raise InputError(f"joints must be a list of joint names, got {self.joints!r}")
            self.joints = tuple(self.joints)
            if len(self.joints) != n:
                raise InputError(
                    f"joints names {len(self.joints)} joints but ratio has {n} entries"
                )

    @property
    def n(self) -> int:
        """Number of current-controlled joints."""
        return self.ratio.shape[0]

    # ----------------------------------------------------------------- constructors
    @classmethod
    def nominal(cls, robot: Robot) -> RobotParams:
        """The model's own figures: ratio from ``jaxcomp_nominal_ratio`` (else
        ``DEFAULT_RATIO``, also for a joint it gives none), no friction.

        Args:
            robot: the model.

        Returns:
            Params of ratio (n,) A/(N m), friction (n,) zeros A, no COM offsets.
        """
        n = len(arm_joint_indices(robot))
        ratio = robot.joint_numeric("jaxcomp_nominal_ratio")
        ratio = np.full(n, DEFAULT_RATIO) if ratio is None else ratio
        ratio = np.where(np.isnan(ratio), DEFAULT_RATIO, ratio)
        return cls(
            model=robot.name,
            ratio=ratio,
            friction=np.zeros(n),
            method="nominal",
            joints=arm_joint_names(robot),
        )

    # ----------------------------------------------------------------- checks
    def check(self, robot: Robot) -> RobotParams:
        """Raise InputError unless the params fit ``robot`` (joint count, link names).

        Args:
            robot: the model.

        Returns:
            The params themselves.

        Raises:
            InputError: other joints, another joint count, or a COM offset of an unknown link.
        """
        names = arm_joint_names(robot)
        if self.joints is not None and self.joints != names:
            raise InputError(
                f"the params are for joints {', '.join(self.joints)} but {robot.name} "
                f"current-controls {', '.join(names)}"
            )
        n = len(names)
        if self.n != n:
            raise InputError(
                f"ratio has {self.n} entries but {robot.name} has {n} current-controlled joints"
            )
        unknown = [k for k in self.com_offset if k not in robot.link_names]
        if unknown:
            raise InputError(
                f"com_offset names unknown link(s) {', '.join(map(repr, unknown))} of "
                f"{robot.name}; links: {', '.join(robot.link_names)}"
            )
        return self

    def inertial_params(self, robot: Robot) -> InertialParams:
        """The robot's nominal inertial params with ``com_offset`` added (link frame, m).

        Args:
            robot: the model.

        Returns:
            ``InertialParams``: mass (nb,) kg, com (nb, 3) m and inertia (nb, 3, 3) kg m^2,
            link frames.

        Raises:
            InputError: the params do not fit ``robot`` (``check``).
        """
        self.check(robot)
        p = robot.nominal_params()
        com = np.array(p.com)
        for link, off in self.com_offset.items():
            com[robot.link_index(link)] += off
        return InertialParams(p.mass, jnp.asarray(com), p.inertia)

    # ----------------------------------------------------------------- JSON
    def to_dict(self) -> dict:
        """Plain JSON-ready dict (lists of floats)."""
        out = {
            "model": self.model,
            "joints": None if self.joints is None else list(self.joints),
            "ratio": self.ratio.tolist(),
            "friction": self.friction.tolist(),
            "com_offset": {k: v.tolist() for k, v in self.com_offset.items()},
            "phase_shift": None if self.phase_shift is None else self.phase_shift.tolist(),
            "std": _jsonable(self.std),
            "method": self.method,
            "fit_seconds": self.fit_seconds,
            "diagnostics": _jsonable(self.diagnostics),
        }
        if self.joints is None:
            del out["joints"]
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, data: Mapping, robot: Robot | None = None) -> RobotParams:
        """Params from a dict; InputError naming the field for anything malformed.

        Args:
            data: the JSON object (see the module docstring).
            robot: when given, the params are also checked against it (``check``).

        Returns:
            The ``RobotParams``.

        Raises:
            InputError: a missing or malformed field, or params that do not fit ``robot``.
        """
        if not isinstance(data, Mapping):
            raise InputError(f"params must be a JSON object, got {type(data).__name__}")
        missing = [k for k in _REQUIRED if k not in data]
        if missing:
            raise InputError(f"params field(s) missing: {', '.join(missing)}")
        params = cls(
            model=data["model"],
            ratio=data["ratio"],
            friction=data["friction"],
            com_offset=data.get("com_offset") or {},
            phase_shift=data.get("phase_shift"),
            std=data.get("std"),
            method=data.get("method", "unknown"),
            fit_seconds=data.get("fit_seconds"),
            diagnostics=data.get("diagnostics"),
            joints=data.get("joints"),
        )
        return params.check(robot) if robot is not None else params

    @classmethod
    def from_json(cls, text: str, robot: Robot | None = None) -> RobotParams:
        """Params from JSON text (``from_dict``).

        Args:
            text: the JSON text.
            robot: when given, the params are also checked against it (``check``).

        Returns:
            The ``RobotParams``.

        Raises:
            InputError: invalid JSON, a missing or malformed field, or params that do not fit
                ``robot``.
        """
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"params are not valid JSON: {exc}") from None
        return cls.from_dict(data, robot)

    def save(self, path: str | Path, extra: Mapping | None = None) -> Path:
        """Write the JSON atomically (temp file + rename); ``extra`` keys are added.

        Args:
            path: the file.
            extra: further top-level keys to write (numpy values as lists), or None.

        Returns:
            ``path``, as a ``Path``.

        Raises:
            FileError: ``path`` cannot be written.
        """
        data = self.to_dict()
        if extra:
            data.update(_jsonable(dict(extra)))
        return write_json_atomic(path, data)

    @classmethod
    def load(cls, path: str | Path, robot: Robot | None = None) -> RobotParams:
        """Read and validate a params file (also against ``robot`` when given).

        Args:
            path: the JSON file.
            robot: when given, the params are also checked against it (``check``).

        Returns:
            The ``RobotParams``.

        Raises:
            InputError: no such file, not UTF-8 JSON, or invalid params (naming ``path``).
        """
        path = Path(path)
        if not path.is_file():
            raise InputError(f"params file not found: {path}")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{path}: not a params file (not UTF-8 JSON text)") from None
        try:
            return cls.from_json(text, robot)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None


def current_limits(robot: Robot) -> np.ndarray:
    """(n,) A: the motor current magnitude limit of each current-controlled joint of ``robot``
    (its joints less a mobile base's): the model's ``jaxcomp_current_limit`` custom numeric (one
    value for every joint, or per joint: ``Robot.joint_numeric``), else, for a joint it gives
    none, the joint's effort limit (N m) times its nominal current/torque ratio
    (``RobotParams.nominal``: ``jaxcomp_nominal_ratio``, else 1 A/(N m)), else, for a joint with
    no effort limit either, ``DEFAULT_CURRENT_LIMIT`` (the Gen3 Lite declares 11 A).

    Args:
        robot: the model.

    Returns:
        (n,) A.

    Raises:
        InputError: a declared ``jaxcomp_current_limit`` that is not a positive, finite current.
    """
    arm = arm_joint_indices(robot)
    effort = robot.effort_limits[arm]
    derived = np.where(
        np.isfinite(effort), effort * RobotParams.nominal(robot).ratio, DEFAULT_CURRENT_LIMIT
    )
    declared = robot.joint_numeric("jaxcomp_current_limit")
    if declared is None:
        return derived
    given = ~np.isnan(declared)
    if not np.all(np.isfinite(declared[given]) & (declared[given] > 0)):
        raise InputError(
            f"{robot.name}: custom numeric jaxcomp_current_limit must hold positive currents "
            f"(A), got {declared.tolist()}"
        )
    return np.where(given, declared, derived)


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.ndarray, np.generic)) or hasattr(value, "__array__"):
        return np.asarray(value).tolist()
    return value


def json_ready(value: Any) -> Any:
    """Plain JSON data: numpy arrays and scalars as Python lists and numbers, keys as str,
    non-finite floats (NaN, inf) as None.

    Args:
        value: nested mappings, lists, tuples, arrays and scalars.

    Returns:
        The same structure as dicts, lists and plain Python values.
    """
    if isinstance(value, Mapping):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json_atomic(path: str | Path, data: Any) -> Path:
    """Write ``data`` as JSON to ``path`` via a temp file and ``os.replace`` (never partial).

    Args:
        path: the file.
        data: JSON-serialisable data (see ``json_ready``), written indented.

    Returns:
        ``path``, as a ``Path``.

    Raises:
        FileError: ``path`` cannot be written.
    """
    return write_text_atomic(path, json.dumps(data, indent=2) + "\n")


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` via a temp file and ``os.replace`` (``files.atomic_output``:
    never partial, the user's file mode; ``FileError`` naming ``path`` when it cannot).

    Args:
        path: the file.
        text: what to write.

    Returns:
        ``path``, as a ``Path``.

    Raises:
        FileError: ``path`` cannot be written.
    """
    from jaxcomp.files import atomic_output

    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(text)
    return path
