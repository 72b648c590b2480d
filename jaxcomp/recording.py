"""Recordings: the ``.npz`` format that calibration writes and identification reads.

One ``.npz``, SI units, n = the robot's current-controlled joints:

- ``t`` (N,) s, increasing; ``q`` (N, n) rad; ``dq`` (N, n) rad/s; ``current`` (N, n) A;
- ``joint`` (N,) int, index of the swept joint (-1 outside sweeps);
- ``direction`` (N,) int, +1 or -1 (0 outside sweeps);
- ``model`` str, a built-in robot name or a path to an MJCF or URDF file;
- optional ``joints`` (n,) str, the current-controlled joints' names (``load_robot(model,
  joints=...)``; without it, the model's default joints);
- optional ``gravity`` (3,) m/s^2 in the base frame (default (0, 0, -9.81));
- optional ``payload_mass`` kg and ``payload_com`` (3,) m in the end-effector frame;
- optional ``current_lag`` s (default 0): the current of a sample flowed at the pose of
  ``current_lag`` earlier (q - current_lag dq); the simulators record the current their servo
  computed one 1 kHz cycle before the pose they report, 1 ms.

Any further array whose first axis has length N (the controller adds ``target``, ``ee``,
``base``, ``command``, and the impedance controller its external force estimate
``current_model``, ``wrench``, ``wrench_band``: ``jaxcomp.control.run_recording``) is kept in
``Recording.extra``. Loading validates everything and raises
one ``InputError`` naming the field; nothing is silently dropped.

``RecordingWriter`` writes a recording incrementally: samples go to numbered part files in
``<path>.parts/`` (each written atomically, at least every ``flush_every`` samples), grouped
into segments; ``close()`` joins them into ``<path>`` atomically. After an interruption,
``save_completed()`` joins the completed segments into ``<path>`` (the parts stay),
``RecordingWriter(path, ..., resume=True)`` keeps every completed segment, and
``recover(path)`` joins whatever was written. Every file is written atomically
(``jaxcomp.files``); one that cannot be written raises one ``FileError``.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jaxcomp import checks
from jaxcomp.constants import STANDARD_GRAVITY
from jaxcomp.errors import InputError, JaxcompError, ModelError
from jaxcomp.files import atomic_output, reading, writing
from jaxcomp.npz import read_npz
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import arm_joint_indices, write_json_atomic

_ARRAYS = ("t", "q", "dq", "current", "joint", "direction")
_OPTIONAL = ("gravity", "payload_mass", "payload_com", "joints", "current_lag")
#: s: the largest ``current_lag`` accepted.
MAX_CURRENT_LAG = 0.1
#: |q| beyond this (rad) cannot be an angle in radians of a revolute arm joint.
_MAX_ANGLE = 2 * np.pi + 0.5


@dataclass(frozen=True, eq=False)
class Recording:
    """A validated recording (see the module docstring for the format).

    Attributes:
        t: (N,) s, increasing.
        q: (N, n) rad (slides: m), the current-controlled joints' positions.
        dq: (N, n) rad/s (slides: m/s).
        current: (N, n) A, the motor currents.
        joint: (N,) int, the swept joint's index, -1 outside sweeps.
        direction: (N,) int, +1 or -1 in a sweep, 0 outside.
        model: a built-in robot name or a path to an MJCF or URDF file.
        gravity: (3,) m/s^2 in the base frame.
        payload_mass: kg.
        payload_com: (3,) m, the payload's centre of mass in the end-effector frame.
        extra: {name: (N, ...) array} of further per-sample fields.
        joints: the current-controlled joints' names, or None (the model's default joints).
        current_lag: s, how long before its pose a sample's current flowed.
    """

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    current: np.ndarray
    joint: np.ndarray
    direction: np.ndarray
    model: str
    gravity: np.ndarray = field(default_factory=lambda: np.array(STANDARD_GRAVITY))
    payload_mass: float = 0.0
    payload_com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    joints: tuple[str, ...] | None = None
    current_lag: float = 0.0

    @property
    def n_samples(self) -> int:
        return self.t.shape[0]

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    def robot(self) -> Robot:
        """The robot model named by ``model``, reduced to ``joints``."""
        return load_robot(self.model, joints=self.joints)

    def to_arrays(self) -> dict[str, Any]:
        """The ``.npz`` contents (all fields, extras included)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in _ARRAYS}
        out.update(
            model=np.array(self.model),
            gravity=self.gravity,
            payload_mass=np.array(self.payload_mass),
            payload_com=self.payload_com,
            current_lag=np.array(self.current_lag),
        )
        if self.joints is not None:
            out["joints"] = np.array(self.joints)
        out.update(self.extra)
        return out

    def save(self, path: str | Path) -> Path:
        """Write the ``.npz`` atomically (temp file + rename).

        Args:
            path: the file (written as given: no ``.npz`` appended).

        Returns:
            ``path``, as a ``Path``.

        Raises:
            FileError: ``path`` cannot be written.
        """
        return _save_npz(path, self.to_arrays())

    def select(self, mask: np.ndarray) -> Recording:
        """The samples where ``mask`` (N,) is true, same metadata.

        Args:
            mask: (N,) bool (or indices into the samples).

        Returns:
            The ``Recording`` of those samples.
        """
        pick = {k: getattr(self, k)[mask] for k in _ARRAYS}
        extra = {k: v[mask] for k, v in self.extra.items()}
        return Recording(
            **pick,
            model=self.model,
            gravity=self.gravity,
            payload_mass=self.payload_mass,
            payload_com=self.payload_com,
            extra=extra,
            joints=self.joints,
            current_lag=self.current_lag,
        )


def _save_npz(path: str | Path, arrays: Mapping[str, Any]) -> Path:
    path = Path(path)
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)  # to the file itself: no ".npz" appended to other names
    return path


def setting_differences(earlier: Mapping[str, Any], now: Mapping[str, Any]) -> str:
    """What differs between two settings mappings, for people: "seed 0 then, 7 now; the
    truth differs" (a scalar setting: both values; a list or mapping: that it differs).

    Args:
        earlier: the settings then.
        now: the settings now.

    Returns:
        The differences joined by "; ", empty when there are none.
    """
    said = []
    for key in sorted(set(earlier) | set(now), key=str):
        a, b = earlier.get(key), now.get(key)
        if a == b:
            continue
        scalar = all(v is None or isinstance(v, str | int | float | bool) for v in (a, b))
        verb = "differ" if str(key).endswith("s") else "differs"
        said.append(f"{key} {a!r} then, {b!r} now" if scalar else f"the {key} {verb}")
    return "; ".join(said)


def _numeric(data: Mapping, name: str, shape: tuple, kind: str = "float") -> np.ndarray:
    """Field ``name`` as an array of ``shape`` (None = any length), finite."""
    try:
        arr = np.asarray(data[name])
    except KeyError:
        raise InputError(f"recording field {name!r} is missing") from None
    if arr.dtype.kind not in "biuf":
        raise InputError(f"recording field {name!r} must be numeric, got dtype {arr.dtype}")
    if kind == "float":
        return checks.array(arr, f"recording field {name!r}", shape=shape)  # float64
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr) & (arr == np.round(arr))):
        raise InputError(f"recording field {name!r} must hold integers")
    checks.array(arr, f"recording field {name!r}", shape=shape)  # the shape
    return arr.astype(np.int64, copy=False)


def _degrees_hint(name: str, arr: np.ndarray, limit: float, unit: str) -> None:
    peak = max(float(arr.max()), -float(arr.min())) if arr.size else 0.0
    if peak > limit:
        raise InputError(
            f"recording field {name!r} reaches {peak:.4g}, beyond {limit:.3g} {unit}: it looks "
            f"like degrees; the format wants {unit}"
        )


def validate(
    data: Mapping[str, Any],
    source: str = "recording",
    require_sweep: bool = True,
    robots: dict[tuple, Robot] | None = None,
) -> Recording:
    """A ``Recording`` from a mapping of fields (e.g. an opened ``.npz``), fully checked; an
    array already of its field's dtype (float64, int64) is kept, not copied.

    Args:
        data: the fields by name (see the module docstring).
        source: what messages name the recording by (e.g. its path).
        require_sweep: refuse a recording without any swept sample (what identification
            needs); a controller's log has none.
        robots: the robots of recordings checked before, by (model, joints), kept and reused
            (``load_recordings``); None: none kept.

    Returns:
        The ``Recording``.

    Raises:
        InputError: a missing, malformed or implausible field (degrees, millimetres, an
            unknown model ...), the message starting with ``source``.
    """
    try:
        return _validate(data, require_sweep, {} if robots is None else robots)
    except JaxcompError as exc:
        raise type(exc)(f"{source}: {exc}") from None


def _validate(data: Mapping[str, Any], require_sweep: bool, robots: dict) -> Recording:
    if "model" not in data:
        raise InputError("recording field 'model' is missing")
    model = np.asarray(data["model"])
    if model.dtype.kind == "S" and model.ndim == 0:
        model = np.asarray(model.item().decode("utf-8", "replace"))
    if model.dtype.kind != "U" or model.ndim != 0 or not str(model):
        raise InputError("recording field 'model' must be a non-empty string")
    model = str(model)
    joints = _joint_names(data)
    if (model, joints) not in robots:
        try:
            robots[model, joints] = load_robot(model, joints=joints)
        except ModelError as exc:
            fields = "field 'model'" if joints is None else "field 'model' (with 'joints')"
            raise InputError(f"recording {fields}: {exc}") from None
    robot = robots[model, joints]
    n = len(arm_joint_indices(robot))
    t = _numeric(data, "t", (None,))
    N = t.shape[0]
    if N < 2:
        raise InputError(f"recording field 't' has {N} sample(s): the recording is empty")
    q = _numeric(data, "q", (N, n))
    dq = _numeric(data, "dq", (N, n))
    current = _numeric(data, "current", (N, n))
    joint = _numeric(data, "joint", (N,), "int")
    direction = _numeric(data, "direction", (N,), "int")
    if np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(f"recording field 't' must increase; it does not at index {i + 1}")
    hinge = np.asarray(robot.tree.is_hinge)[arm_joint_indices(robot)]
    qh, dqh = (q, dq) if hinge.all() else (q[:, hinge], dq[:, hinge])  # no copy for an arm
    _degrees_hint("q", qh, _MAX_ANGLE, "rad")
    steps = np.diff(qh, axis=0)  # in place from here: these are the large arrays
    moved = np.abs(steps, out=steps).sum()
    if moved > 0:
        # dq in deg/s shows as |dq| ~57x the finite-difference velocity of q
        fd = np.divide(steps, np.diff(t)[:, None], out=steps).sum()
        mean = np.add(dqh[1:], dqh[:-1])
        ratio = 0.5 * np.abs(mean, out=mean).sum() / max(fd, 1e-300)
        if 20 < ratio < 200:
            raise InputError(
                f"recording field 'dq' is {ratio:.0f}x the rate of change of q: it looks like "
                "degrees per second; the format wants rad/s"
            )
    bad = (joint < -1) | (joint >= n)
    if bad.any():
        raise InputError(
            f"recording field 'joint' must be -1 or a joint index 0..{n - 1}; "
            f"found {int(joint[bad][0])} at index {int(np.flatnonzero(bad)[0])}"
        )
    if np.any(~np.isin(direction, (-1, 0, 1))):
        raise InputError("recording field 'direction' must hold only +1, -1 or 0")
    mismatch = (joint >= 0) != (direction != 0)
    if mismatch.any():
        raise InputError(
            "recording fields 'joint' and 'direction' disagree at index "
            f"{int(np.flatnonzero(mismatch)[0])}: a swept sample (joint >= 0) needs direction "
            "+1 or -1, a sample outside sweeps (joint -1) direction 0"
        )
    if require_sweep and not np.any(joint >= 0):
        raise InputError("recording has no sweep: field 'joint' is -1 everywhere")
    gravity = _numeric(data, "gravity", (3,)) if "gravity" in data else np.array(STANDARD_GRAVITY)
    g = float(np.linalg.norm(gravity))
    if not 1.0 < g < 30.0:
        raise InputError(f"recording field 'gravity' has norm {g:.4g} m/s^2; expected about 9.81")
    payload_mass = float(_numeric(data, "payload_mass", ())) if "payload_mass" in data else 0.0
    if payload_mass < 0:
        raise InputError(f"recording field 'payload_mass' must be >= 0 kg, got {payload_mass}")
    payload_com = _numeric(data, "payload_com", (3,)) if "payload_com" in data else np.zeros(3)
    if np.abs(payload_com).max() > 2.0:
        raise InputError(
            f"recording field 'payload_com' is {payload_com.tolist()} m; beyond 2 m from the "
            "end effector (millimetres?)"
        )
    lag = float(_numeric(data, "current_lag", ())) if "current_lag" in data else 0.0
    if not 0.0 <= lag <= MAX_CURRENT_LAG:
        raise InputError(
            f"recording field 'current_lag' must be within 0-{MAX_CURRENT_LAG:g} s, got {lag:g}"
        )
    extra = {}
    for key in data:
        if key in _ARRAYS or key in _OPTIONAL or key == "model":
            continue
        arr = np.asarray(data[key])
        if arr.ndim == 0 or arr.shape[0] != N:
            raise InputError(
                f"recording field {key!r} is not part of the format and is not per sample "
                f"(shape {arr.shape}, expected first axis {N})"
            )
        if arr.dtype.kind in "f" and not np.all(np.isfinite(arr)):
            raise InputError(f"recording field {key!r} has NaN/inf values")
        extra[key] = arr
    return Recording(
        t=t,
        q=q,
        dq=dq,
        current=current,
        joint=joint,
        direction=direction,
        model=model,
        gravity=gravity,
        payload_mass=payload_mass,
        payload_com=payload_com,
        extra=extra,
        joints=joints,
        current_lag=lag,
    )


def _joint_names(data: Mapping[str, Any]) -> tuple[str, ...] | None:
    if "joints" not in data:
        return None
    names = np.asarray(data["joints"])
    if names.dtype.kind == "S":
        names = np.char.decode(names, "utf-8", "replace")
    if names.dtype.kind != "U" or names.ndim != 1 or names.size == 0:
        raise InputError("recording field 'joints' must be a non-empty list of joint names")
    return tuple(str(x) for x in names)


def load_recordings(paths: Iterable[str | Path], require_sweep: bool = True) -> Iterator[Recording]:
    """``load_recording`` of each path in turn, as the caller asks for them; recordings of one
    model (and joints) share one robot, looked up once.

    Args:
        paths: the ``.npz`` files.
        require_sweep: refuse recordings without a sweep (``validate``).

    Returns:
        An iterator of the ``Recording`` of each path, in order.

    Raises:
        InputError: a recording that is missing, unreadable or invalid, when it is reached.
    """
    robots: dict[tuple, Robot] = {}
    for path in paths:
        yield load_recording(path, require_sweep, robots)


def load_recording(
    path: str | Path, require_sweep: bool = True, robots: dict[tuple, Robot] | None = None
) -> Recording:
    """Read and validate a recording ``.npz``; ``InputError`` naming the problem otherwise.

    Args:
        path: the ``.npz`` file.
        require_sweep: False also accepts recordings without sweeps (controller logs).
        robots: robots kept between calls, see ``validate``.

    Returns:
        The ``Recording``.

    Raises:
        InputError: no such file, not a readable ``.npz``, or an invalid recording.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"recording not found: {path}")
    try:
        data = read_npz(path)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npz recording ({exc})") from None
    except Exception as exc:  # zipfile.BadZipFile and friends from a truncated file
        raise InputError(f"{path}: not a readable .npz recording ({exc})") from None
    return validate(data, str(path), require_sweep, robots)


# --------------------------------------------------------------------- incremental writing
class RecordingWriter:
    """Write a recording incrementally (see the module docstring).

    Args:
        path: the final ``.npz``.
        model: ``model`` field; n: current-controlled joints.
        joints: ``joints`` field, their names (None: not written).
        gravity, payload_mass, payload_com, current_lag: optional metadata (format units).
        extra: {name: per-sample shape} of additional arrays (e.g. ``{"ee": (3,)}``).
        flush_every: samples per part file (1000 = one second at 1 kHz).
        resume: keep the completed segments of an earlier, interrupted writer of ``path``;
            otherwise existing parts are discarded.
        require_sweep: the joined recording must contain a sweep (False for controller logs).
    """

    def __init__(
        self,
        path: str | Path,
        model: str,
        n: int,
        *,
        gravity=None,
        payload_mass: float | None = None,
        payload_com=None,
        current_lag: float | None = None,
        extra: Mapping[str, tuple] | None = None,
        joints: tuple[str, ...] | None = None,
        flush_every: int = 1000,
        resume: bool = False,
        require_sweep: bool = True,
    ):
        self.path = Path(path)
        self.parts = self.path.with_name(self.path.name + ".parts")
        self.meta = {"model": str(model), "n": int(n), "extra": {}}
        if gravity is not None:
            self.meta["gravity"] = np.asarray(gravity, float).tolist()
        if payload_mass is not None:
            self.meta["payload_mass"] = float(payload_mass)
        if payload_com is not None:
            self.meta["payload_com"] = np.asarray(payload_com, float).tolist()
        if joints is not None:
            self.meta["joints"] = [str(x) for x in joints]
        if current_lag:
            self.meta["current_lag"] = float(current_lag)
        self.meta["extra"] = {k: list(v) for k, v in (extra or {}).items()}
        self.meta["require_sweep"] = bool(require_sweep)
        self.flush_every = int(flush_every)
        self.completed: list[Any] = []
        self._files: list[str] = []  # part files of completed segments
        self._open: list[str] = []  # part files of the open segment
        self._segment: Any = None
        self._buf: dict[str, list] = {k: [] for k in self._fields()}
        self._count = 0
        #: time (s) of the last sample written or buffered; None before the first
        self.last_t: float | None = None
        manifest = read_manifest(self.path) if resume else None
        if manifest is not None:
            differ = setting_differences(manifest["meta"], json.loads(json.dumps(self.meta)))
            if differ:
                raise InputError(f"cannot resume {self.path}: {differ}")
            self.completed = manifest["completed"]
            self._files = manifest["files"]
            with reading(self.parts):
                for name in self._files:
                    with np.load(self.parts / name) as part:
                        self._count += int(part["t"].shape[0])
                        self.last_t = float(part["t"][-1])
                for f in self.parts.glob("part-*.npz"):
                    if f.name not in self._files:
                        f.unlink()  # samples of an unfinished segment
        else:
            shutil.rmtree(self.parts, ignore_errors=True)
        with writing(self.parts):
            self.parts.mkdir(parents=True, exist_ok=True)
        try:
            self._write_manifest()
        except BaseException:
            if not self._files:  # nothing kept: leave no empty parts folder behind
                shutil.rmtree(self.parts, ignore_errors=True)
            raise

    def _fields(self) -> list[str]:
        return list(_ARRAYS) + list(self.meta["extra"])

    @property
    def samples(self) -> int:
        """Samples written or buffered so far (completed segments and the open one)."""
        return self._count

    def begin(self, segment: Any = None) -> None:
        """Start a segment (e.g. one sweep of a plan); ``segment`` is a JSON-able label.

        Args:
            segment: the segment's label, kept in the manifest when it ends; None: none.
        """
        self._segment = segment

    def append(
        self, t: float, q, dq, current, joint: int = -1, direction: int = 0, **extra
    ) -> None:
        """Add one sample (format units).

        Args:
            t: s.
            q: (n,) rad (slides: m).
            dq: (n,) rad/s (slides: m/s).
            current: (n,) A.
            joint: the swept joint's index, -1 outside sweeps.
            direction: +1 or -1 in a sweep, 0 outside.
            **extra: the declared extra fields, each of its per-sample shape.

        Raises:
            InputError: a declared extra field missing or an undeclared one given.
            FileError: a part file (written every ``flush_every`` samples) cannot be written.
        """
        buf = self._buf
        missing = [k for k in self.meta["extra"] if k not in extra]
        unknown = [k for k in extra if k not in self.meta["extra"]]
        if missing or unknown:
            raise InputError(
                f"recording sample: extra field(s) missing {missing} / not declared {unknown}"
            )
        self.last_t = float(t)
        buf["t"].append(float(t))
        buf["q"].append(np.array(q, float))
        buf["dq"].append(np.array(dq, float))
        buf["current"].append(np.array(current, float))
        buf["joint"].append(int(joint))
        buf["direction"].append(int(direction))
        for k in self.meta["extra"]:
            buf[k].append(np.array(extra[k], float))
        self._count += 1
        if len(buf["t"]) >= self.flush_every:
            self.flush()

    def append_block(self, t, q, dq, current, **extra) -> None:
        """Add k samples of no sweep (joint -1, direction 0) at once.

        For loops that log every cycle: ``append`` costs ~20 us a sample (small array copies,
        then a flush that stacks the rows again); the blocks go into the field buffers as
        arrays, which ``flush`` saves as they are. Never mix with ``append`` on one writer.

        Args:
            t: (k,) s.
            q: (k, n) rad.
            dq: (k, n) rad/s.
            current: (k, n) A.
            **extra: the declared extra fields, (k, ...) each.
        """
        k = len(t)
        buf = self._buf
        buf["t"].extend(t.tolist())  # a list: ``flush`` tests it for emptiness
        blocks = {"q": q, "dq": dq, "current": current, **extra}
        blocks["joint"] = np.full(k, -1)
        blocks["direction"] = np.zeros(k, np.int64)
        for name, block in blocks.items():
            old = buf[name]
            block = np.ascontiguousarray(block)
            buf[name] = block if isinstance(old, list) else np.concatenate([old, block])
        self._count += k
        self.last_t = float(t[-1])
        if len(buf["t"]) >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        """Write buffered samples to a new part file (atomically)."""
        if not self._buf["t"]:
            return
        name = f"part-{len(self._files) + len(self._open):06d}.npz"
        _save_npz(self.parts / name, {k: np.asarray(v) for k, v in self._buf.items()})
        self._open.append(name)
        self._buf = {k: [] for k in self._fields()}
        self._write_manifest()

    def end(self) -> None:
        """Finish the open segment: its samples survive a crash and count on resume."""
        self.flush()
        self._files.extend(self._open)
        self._open = []
        if self._segment is not None:
            self.completed.append(self._segment)
        self._segment = None
        self._write_manifest()

    def _write_manifest(self) -> None:
        where = self.parts / "manifest.json"
        with writing(where):
            write_json_atomic(
                where,
                {
                    "meta": self.meta,
                    "completed": self.completed,
                    "files": self._files,
                    "open": self._open,
                },
            )

    def close(self) -> Recording:
        """End the open segment, join every part into ``path`` (validated), remove the parts."""
        self.end()
        rec = _join(self.parts, self._files, self.meta)
        rec.save(self.path)
        shutil.rmtree(self.parts, ignore_errors=True)
        return rec

    def save_completed(self) -> Recording | None:
        """Join the completed segments into ``path`` (validated) and keep the parts, so that
        a resume still goes on; None (nothing written) before the first segment ends. For an
        interrupted writer: ``path`` then loads like any recording."""
        if not self._files:
            return None
        rec = _join(self.parts, self._files, self.meta)
        rec.save(self.path)
        return rec


def _join(parts: Path, files: list[str], meta: Mapping) -> Recording:
    chunks = []
    with reading(parts):
        for name in files:
            with np.load(parts / name) as npz:
                chunks.append({k: npz[k] for k in npz.files})
    if not chunks:
        raise InputError(f"{parts}: nothing was recorded")
    data: dict[str, Any] = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    data["model"] = np.array(meta["model"])
    for key in _OPTIONAL:
        if key in meta:
            data[key] = np.asarray(meta[key])
    return validate(data, str(parts), meta.get("require_sweep", True))


def recover(path: str | Path) -> Recording:
    """Join every part file left by an interrupted ``RecordingWriter`` of ``path``.

    Includes the samples of an unfinished segment (up to its last flush); writes ``path`` and
    keeps the parts, so a later ``RecordingWriter(..., resume=True)`` can still go on.

    Args:
        path: the final ``.npz`` the writer was writing.

    Returns:
        The joined ``Recording`` (validated), also saved to ``path``.

    Raises:
        InputError: nothing to recover, or the joined samples are not a valid recording.
        FileError: a part cannot be read or ``path`` cannot be written.
    """
    path = Path(path)
    parts = path.with_name(path.name + ".parts")
    manifest = read_manifest(path)
    if manifest is None:
        raise InputError(f"no interrupted recording to recover at {parts}")
    rec = _join(parts, manifest["files"] + manifest["open"], manifest["meta"])
    rec.save(path)
    return rec


def read_manifest(path: str | Path) -> dict | None:
    """The manifest of an interrupted ``RecordingWriter`` of ``path`` (its ``meta``,
    ``completed`` segments, their part ``files`` and the ``open`` segment's); None when
    there is none.

    Args:
        path: the final ``.npz`` of the writer.

    Returns:
        The manifest, a dict, or None.

    Raises:
        InputError: a manifest that is not one.
        FileError: a manifest that cannot be read.
    """
    path = Path(path)
    where = path.with_name(path.name + ".parts") / "manifest.json"
    if not where.is_file():
        return None
    with reading(where):
        text = where.read_text()
    try:
        manifest = json.loads(text)
        keys = ("meta", "completed", "files", "open")
        if not isinstance(manifest, dict) or any(k not in manifest for k in keys):
            raise ValueError("fields missing")
    except ValueError as exc:
        raise InputError(f"{where}: not a recording manifest ({exc})") from None
    return manifest
