"""The recording format (jaxcomp.recording): validation, files, incremental writing; and the
angle bins of identify/bins.py on a synthetic recording."""

import json

import numpy as np
import pytest

from jaxcomp import recording
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import FileError, InputError, JaxcompError
from jaxcomp.identify.bins import bin_sweeps, steady
from jaxcomp.identify.steady import SETTLE_CRUISE, STEADY_SETTLE, STEADY_TRIM
from jaxcomp.recording import (
    Recording,
    RecordingWriter,
    load_recording,
    recover,
    validate,
)

N_JOINTS = 6
HOLD = np.deg2rad([0.0, -16.0, 75.0, 0.0, -60.0, 0.0])  # gen3_lite "home"
SPEED = np.deg2rad(40.0)  # rad/s
RATIO, FRICTION = 0.3, 1.5  # A/(N m), A: the synthetic current model of the swept joint


def _profile(distance: float, ramp: int) -> np.ndarray:
    """Velocities (samples of 1 ms), rad/s: a ramp up, constant SPEED, a ramp down."""
    up = SPEED * np.arange(1, ramp + 1) / ramp
    flat = int(round((distance - SPEED * ramp * CONTROL_PERIOD) / (SPEED * CONTROL_PERIOD)))
    return np.r_[up, np.full(flat, SPEED), up[::-1]]


def synthetic(joint: int = 1, lower: float = -0.4, upper: float = 0.4, *, sweeps: int = 1):
    """Recording fields of ``sweeps`` sweeps of ``joint`` (lower -> upper -> lower), each
    after 50 idle samples, at 1 kHz with 100 ms ramps. The swept joint's current is
    RATIO * 5 sin(q) + FRICTION * direction; the others draw 0.1 A."""
    v = _profile(upper - lower, 100)
    q0 = HOLD.copy()
    q0[joint] = lower
    parts = []
    for _ in range(sweeps):
        idle = np.zeros(50)
        vel = np.r_[idle, v, -v]
        direction = np.r_[np.zeros(50, int), np.ones(len(v), int), -np.ones(len(v), int)]
        parts.append((vel, direction))
    vel = np.concatenate([p[0] for p in parts])
    direction = np.concatenate([p[1] for p in parts])
    N = len(vel)
    dq = np.zeros((N, N_JOINTS))
    dq[:, joint] = vel
    q = q0 + np.cumsum(dq, axis=0) * CONTROL_PERIOD
    current = np.full((N, N_JOINTS), 0.1)
    current[:, joint] = RATIO * 5.0 * np.sin(q[:, joint]) + FRICTION * direction
    return {
        "model": np.array("gen3_lite"),
        "t": np.arange(1, N + 1) * CONTROL_PERIOD,
        "q": q,
        "dq": dq,
        "current": current,
        "joint": np.where(direction != 0, joint, -1),
        "direction": direction,
    }


def _fails(data, *words, kind=InputError):
    with pytest.raises(kind) as err:
        validate(data)
    for w in words:
        assert w in str(err.value), (w, str(err.value))
    return str(err.value)


# --------------------------------------------------------------------- validation
def test_valid_recording_fields_and_units():
    rec = validate(synthetic())
    assert isinstance(rec, Recording)
    assert rec.n_joints == N_JOINTS and rec.n_samples == len(rec.t)
    assert rec.q.dtype == np.float64 and rec.joint.dtype == np.int64
    np.testing.assert_allclose(rec.gravity, [0, 0, -9.81])
    assert rec.payload_mass == 0.0 and np.all(rec.payload_com == 0)
    assert rec.model == "gen3_lite" and rec.robot().name == "gen3_lite"
    assert set(np.unique(rec.direction)) == {-1, 0, 1}


@pytest.mark.parametrize("name", ["t", "q", "dq", "current", "joint", "direction", "model"])
def test_missing_field(name):
    data = synthetic()
    del data[name]
    _fails(data, f"'{name}'", "missing")


@pytest.mark.parametrize("name", ["q", "dq", "current"])
def test_swapped_axes(name):
    data = synthetic()
    data[name] = data[name].T.copy()
    _fails(data, f"'{name}'", "shape")


@pytest.mark.parametrize("name", ["t", "q", "dq", "current"])
def test_nan_in_float_arrays(name):
    data = synthetic()
    data[name] = data[name].astype(float)
    data[name].flat[7] = np.nan
    _fails(data, f"'{name}'", "NaN")


@pytest.mark.parametrize("name", ["joint", "direction"])
def test_nan_in_integer_arrays(name):
    data = synthetic()
    data[name] = data[name].astype(float)
    data[name][7] = np.nan
    _fails(data, f"'{name}'", "integers")


def test_degrees_in_q():
    data = synthetic()
    data["q"] = np.rad2deg(data["q"])
    data["dq"] = np.rad2deg(data["dq"])
    _fails(data, "'q'", "degrees")


def test_degrees_per_second_in_dq():
    data = synthetic()
    data["dq"] = np.rad2deg(data["dq"])
    _fails(data, "'dq'", "degrees per second")


def test_empty_recording():
    data = synthetic()
    for k in ("t", "q", "dq", "current", "joint", "direction"):
        data[k] = data[k][:0]
    _fails(data, "'t'", "empty")


def test_no_sweep():
    data = synthetic()
    data["joint"][:] = -1
    data["direction"][:] = 0
    _fails(data, "'joint'", "no sweep")


def test_unknown_model():
    data = synthetic()
    data["model"] = np.array("nosuchbot")
    msg = _fails(data, "nosuchbot")
    assert "field 'model'" in msg


@pytest.mark.parametrize("model", [np.array(3.0), np.array(["a", "b"]), np.array("")])
def test_model_not_a_string(model):
    data = synthetic()
    data["model"] = model
    _fails(data, "'model'")


def test_time_must_increase():
    data = synthetic()
    data["t"][10] = data["t"][9]
    _fails(data, "'t'", "increase")


def test_joint_and_direction_values():
    data = synthetic()
    data["joint"][data["joint"] == 1] = 6
    _fails(data, "'joint'", "0..5")
    data = synthetic()
    data["direction"][data["direction"] == 1] = 2
    _fails(data, "'direction'")
    data = synthetic()
    data["direction"][0] = 1  # an idle sample with a direction
    _fails(data, "'joint'", "'direction'", "index 0")


@pytest.mark.parametrize(
    "gravity, words",
    [
        ([0.0, -9.81], "shape"),
        ([0.0, 0.0, np.nan], "NaN"),
        ([0.0, 0.0, -9810.0], "norm"),
        ([0.0, 0.0, 0.0], "norm"),
    ],
)
def test_bad_gravity(gravity, words):
    data = synthetic()
    data["gravity"] = np.array(gravity)
    _fails(data, "'gravity'", words)


def test_tilted_gravity_is_kept():
    data = synthetic()
    data["gravity"] = np.array([-9.81, 0.0, 0.0])
    np.testing.assert_allclose(validate(data).gravity, [-9.81, 0, 0])


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("payload_mass", -0.2, ">= 0"),
        ("payload_mass", np.nan, "not a finite number"),
        ("payload_mass", [0.1, 0.2], "shape"),
        ("payload_com", [0.0, 0.0, 50.0], "millimetres"),
        ("payload_com", [0.0, 0.05], "shape"),
        ("payload_com", [0.0, np.inf, 0.0], "NaN"),
        ("current_lag", -0.001, "within 0-0.1 s"),
        ("current_lag", 1.0, "within 0-0.1 s, got 1"),
        ("current_lag", [0.001, 0.0], "shape"),
    ],
)
def test_bad_payload(field, value, words):
    data = synthetic()
    data[field] = np.array(value)
    _fails(data, f"'{field}'", words)


def test_payload_is_kept():
    data = synthetic()
    data["payload_mass"] = np.array(0.35)
    data["payload_com"] = np.array([0.0, 0.01, 0.05])
    rec = validate(data)
    assert rec.payload_mass == 0.35
    np.testing.assert_allclose(rec.payload_com, [0, 0.01, 0.05])


def test_extra_fields():
    data = synthetic()
    N = len(data["t"])
    data["ee"] = np.zeros((N, 3))
    assert validate(data).extra["ee"].shape == (N, 3)
    data["ee"] = np.zeros((N - 1, 3))
    _fails(data, "'ee'", "per sample")
    data["ee"] = np.full((N, 3), np.nan)
    _fails(data, "'ee'", "NaN")


def test_select_keeps_metadata():
    data = synthetic()
    data["gravity"] = np.array([0.0, -9.81, 0.0])
    rec = validate(data)
    part = rec.select(rec.joint >= 0)
    assert part.n_samples == int((rec.joint >= 0).sum())
    np.testing.assert_allclose(part.gravity, rec.gravity)


# --------------------------------------------------------------------- files
def _same(a: Recording, b: Recording) -> None:
    for k, v in a.to_arrays().items():
        np.testing.assert_array_equal(np.asarray(v), np.asarray(b.to_arrays()[k]), err_msg=k)


def test_save_load_round_trip(tmp_path):
    data = synthetic()
    data["gravity"] = np.array([0.0, 0.0, -9.80])
    data["payload_mass"] = np.array(0.2)
    data["payload_com"] = np.array([0.0, 0.0, 0.04])
    data["current_lag"] = np.array(0.002)
    data["ee"] = np.arange(len(data["t"]) * 3.0).reshape(-1, 3)
    rec = validate(data)
    path = rec.save(tmp_path / "sub" / "rec.npz")
    back = load_recording(path)
    _same(rec, back)
    assert back.current_lag == 0.002 and rec.select(rec.joint >= 0).current_lag == 0.002
    assert back.extra.keys() == {"ee"} and back.model == "gen3_lite"
    assert [p.name for p in path.parent.iterdir()] == ["rec.npz"]  # no temp files left


def test_load_validates_with_the_path(tmp_path):
    data = synthetic()
    data["q"] = np.rad2deg(data["q"])
    np.savez(tmp_path / "deg.npz", **data)
    with pytest.raises(InputError, match=r"deg\.npz: recording field 'q'"):
        load_recording(tmp_path / "deg.npz")


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_recording(tmp_path / "nothing.npz")


@pytest.mark.parametrize("keep", [0.2, 0.5, 0.9])
def test_truncated_file_is_one_input_error(tmp_path, keep):
    path = validate(synthetic()).save(tmp_path / "rec.npz")
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])
    with pytest.raises(InputError, match="not a readable .npz recording"):
        load_recording(path)


def test_not_an_npz(tmp_path):
    (tmp_path / "rec.npz").write_text("hello")
    with pytest.raises(InputError, match="not a readable"):
        load_recording(tmp_path / "rec.npz")


def test_failed_save_leaves_nothing_half_written(tmp_path, monkeypatch):
    rec = validate(synthetic())
    old = rec.select(rec.joint >= 0)
    path = old.save(tmp_path / "rec.npz")
    before = path.read_bytes()

    def broken(file, **arrays):
        file.write(b"PK\x03\x04 half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(recording.np, "savez", broken)
    with pytest.raises(FileError, match=f"cannot write {path}: No space left on device"):
        rec.save(path)
    with pytest.raises(FileError):
        rec.save(tmp_path / "new.npz")
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.npz"]
    assert path.read_bytes() == before
    _same(load_recording(path), old)


# --------------------------------------------------------------------- incremental writing
def _write(writer: RecordingWriter, data: dict, rows, segment=None, end=True) -> None:
    writer.begin(segment)
    for i in rows:
        writer.append(
            data["t"][i],
            data["q"][i],
            data["dq"][i],
            data["current"][i],
            data["joint"][i],
            data["direction"][i],
            **{k: data[k][i] for k in writer.meta["extra"]},
        )
    if end:
        writer.end()


def test_writer_joins_segments(tmp_path):
    data = synthetic(sweeps=2)
    data["ee"] = np.random.default_rng(0).normal(size=(len(data["t"]), 3))
    N, half = len(data["t"]), len(data["t"]) // 2
    path = tmp_path / "rec.npz"
    w = RecordingWriter(path, "gen3_lite", N_JOINTS, extra={"ee": (3,)}, flush_every=100)
    _write(w, data, range(half), 0)
    _write(w, data, range(half, N), 1)
    assert w.samples == N and w.completed == [0, 1]
    assert len(list(w.parts.glob("part-*.npz"))) == int(np.ceil(half / 100)) * 2
    rec = w.close()
    assert not w.parts.exists() and path.is_file()
    _same(rec, validate(data))
    _same(load_recording(path), rec)


def test_writer_metadata(tmp_path):
    data = synthetic()
    w = RecordingWriter(
        tmp_path / "r.npz",
        "gen3_lite",
        N_JOINTS,
        gravity=[-9.81, 0, 0],
        payload_mass=0.3,
        payload_com=[0, 0, 0.05],
    )
    _write(w, data, range(len(data["t"])), 0)
    rec = w.close()
    np.testing.assert_allclose(rec.gravity, [-9.81, 0, 0])
    assert rec.payload_mass == 0.3
    np.testing.assert_allclose(rec.payload_com, [0, 0, 0.05])


def test_crash_recover_and_resume(tmp_path):
    data = synthetic(sweeps=2)
    N, half = len(data["t"]), len(data["t"]) // 2
    path = tmp_path / "rec.npz"
    w = RecordingWriter(path, "gen3_lite", N_JOINTS, flush_every=100)
    _write(w, data, range(half), 0)
    _write(w, data, range(half, half + 250), 1, end=False)  # crash mid-segment: no close
    manifest = json.loads((w.parts / "manifest.json").read_text())
    assert manifest["completed"] == [0] and len(manifest["open"]) == 2
    assert not path.exists()

    # recover: the completed segment and what the open one flushed (200 of 250 samples)
    rec = recover(path)
    assert rec.n_samples == half + 200 and path.is_file()
    np.testing.assert_array_equal(rec.t, data["t"][: half + 200])
    path.unlink()

    # resume: the completed segment stays, the open one is discarded and written again
    w2 = RecordingWriter(path, "gen3_lite", N_JOINTS, flush_every=100, resume=True)
    assert w2.completed == [0]
    assert len(list(w2.parts.glob("part-*.npz"))) == int(np.ceil(half / 100))
    _write(w2, data, range(half, N), 1)
    _same(w2.close(), validate(data))


def test_resume_with_other_settings_is_refused(tmp_path):
    data = synthetic()
    path = tmp_path / "rec.npz"
    w = RecordingWriter(path, "gen3_lite", N_JOINTS)
    _write(w, data, range(100), 0)
    with pytest.raises(InputError, match="the gravity differs"):
        RecordingWriter(path, "gen3_lite", N_JOINTS, gravity=[0, 0, -9.8], resume=True)
    # without resume the old parts are discarded
    w3 = RecordingWriter(path, "gen3_lite", N_JOINTS)
    assert w3.completed == [] and not list(w3.parts.glob("part-*.npz"))


def test_recover_nothing(tmp_path):
    with pytest.raises(InputError, match="no interrupted recording"):
        recover(tmp_path / "rec.npz")
    w = RecordingWriter(tmp_path / "rec.npz", "gen3_lite", N_JOINTS)
    with pytest.raises(InputError, match="nothing was recorded"):
        recover(w.path)


def test_close_validates(tmp_path):
    data = synthetic()
    data["joint"][:] = -1
    data["direction"][:] = 0
    w = RecordingWriter(tmp_path / "rec.npz", "gen3_lite", N_JOINTS)
    _write(w, data, range(len(data["t"])), 0)
    with pytest.raises(JaxcompError, match="no sweep"):
        w.close()
    assert w.parts.is_dir() and not (tmp_path / "rec.npz").exists()  # nothing lost


# --------------------------------------------------------------------- bins
@pytest.mark.parametrize("half", [0.4, 0.9])  # rad: cruises of 1.0 s and 2.5 s
def test_steady_excludes_the_ramps(half):
    rec = validate(synthetic(lower=-half, upper=half))
    keep = steady(rec)
    j = 1
    speed = rec.dq[:, j] * rec.direction
    constant = (rec.joint == j) & np.isclose(speed, SPEED)
    ramp = (rec.joint == j) & (np.abs(rec.dq[:, j]) < 0.9 * SPEED)
    assert ramp.sum() >= 300  # four 100 ms ramps, less their fast ends
    assert not keep[ramp].any() and not keep[rec.joint < 0].any()
    assert np.all(constant[keep])
    for d in (-1, 1):  # each pass keeps one contiguous stretch: its cruise less the servo's
        rows = np.flatnonzero(keep & (rec.direction == d))  # settling and the trimmed end
        assert rows.size and np.all(np.diff(rows) == 1)
        cruise = np.flatnonzero(constant & (rec.direction == d))
        start, end = rec.t[rows[0]] - rec.t[cruise[0]], rec.t[cruise[-1]] - rec.t[rows[-1]]
        long = rec.t[cruise[-1]] - rec.t[cruise[0]] >= SETTLE_CRUISE
        assert long == (half > 0.5)
        settle = STEADY_SETTLE if long else STEADY_TRIM  # a short pass cannot spare it
        assert abs(start - settle) <= 0.005  # the ramp's last ms are within 2 %
        assert abs(end - STEADY_TRIM) <= 0.005


def test_bin_means():
    rec = validate(synthetic())
    width = np.deg2rad(2.0)
    bins = bin_sweeps(rec, width)
    keep = steady(rec)
    j = 1
    assert np.all(bins.joint == j) and set(np.unique(bins.direction)) == {-1, 1}
    assert bins.count.sum() == keep.sum()
    assert np.all(bins.sweep == bins.sweep[0])
    # each bin: the mean of the steady samples of its direction and angle bin
    index = np.floor(rec.q[:, j] / width).astype(int)
    for b in range(bins.n_bins):
        sel = keep & (rec.direction == bins.direction[b]) & (index == bins.index[b])
        assert sel.sum() == bins.count[b]
        np.testing.assert_allclose(bins.q[b], rec.q[sel].mean(axis=0), atol=1e-12)
        np.testing.assert_allclose(bins.dq[b], rec.dq[sel].mean(axis=0), atol=1e-12)
        np.testing.assert_allclose(bins.current[b], rec.current[sel].mean(axis=0), atol=1e-12)
    # the model of the synthetic current holds for the bin means (to the bin's curvature)
    model = RATIO * 5.0 * np.sin(bins.q[:, j]) + FRICTION * bins.direction
    np.testing.assert_allclose(bins.swept_current, model, atol=1e-3)
    np.testing.assert_allclose(bins.gravity, [0, 0, -9.81])
    assert bins.width == width


def test_bins_keep_separate_sweeps_apart():
    rec = validate(synthetic(sweeps=2))
    bins = bin_sweeps(rec)
    assert len(np.unique(bins.sweep)) == 2
    first = bins.count[bins.sweep == bins.sweep.min()].sum()
    second = bins.count[bins.sweep == bins.sweep.max()].sum()
    assert abs(first - second) <= 0.01 * first


def test_bins_without_steady_samples():
    data = synthetic()
    data["dq"][:] = 0.0  # nothing moves at speed: no steady sample
    with pytest.raises(InputError, match="steady"):
        bin_sweeps(validate(data))
    with pytest.raises(InputError, match="width"):
        bin_sweeps(validate(synthetic()), width=0.0)
