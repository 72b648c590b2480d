"""Files and folders (jaxcomp/files.py and the commands that write): one `error:` line with
status 2 and no traceback wherever a file cannot be written, and no file that existed before
a failing command changed (by hash); one writer per output folder (a lock file); an interrupted
calibration leaves a loadable recording of its finished sweeps, and --resume refuses a run of
another seed, plan or true robot.

The commands run in this process through ``jaxcomp.cli.main`` (what the ``jaxcomp`` script
runs): an exception other than its ``SystemExit`` fails the test (it would be a traceback). A
full disk and a read-only folder are injected (``os.fsync`` raising ENOSPC for chosen files,
``os.open`` / ``os.mkdir`` raising EROFS), the calibrations use a plan of two 20 deg sweeps.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import math
import os
import re
import shutil
import subprocess
import sys
from contextlib import redirect_stderr
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import jaxcomp.cli
from jaxcomp import load_robot
from jaxcomp.errors import FileError
from jaxcomp.files import LOCK_NAME, atomic_output, output_folder
from jaxcomp.hardware import TrueRobot
from jaxcomp.hardware.sim_arm import SimArm
from jaxcomp.identify.plan import plan_for_joints
from jaxcomp.recording import load_recording

ROBOT = load_robot("gen3_lite")
DEG20 = math.radians(20.0)


def run(args: list, monkeypatch, capsys) -> tuple[int, str, str]:
    """``jaxcomp ARGS`` in this process: (status, stdout, stderr)."""
    monkeypatch.setattr("sys.argv", ["jaxcomp", *map(str, args)])
    monkeypatch.setenv("JAXCOMP_CACHE", "off")  # no persistent XLA cache from this process
    capsys.readouterr()
    try:
        jaxcomp.cli.main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def one_error(code: int, err: str, *words: str) -> str:
    """Assert status 2, exactly one `error:` line (holding ``words``), no traceback."""
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (relative path -> digest)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def full_disk(monkeypatch, pattern: str) -> None:
    """``os.fsync`` raises ENOSPC for the files whose path matches ``pattern`` (every atomic
    writer flushes its temp file before moving it in place)."""
    real = os.fsync

    def fsync(fd):
        if re.search(pattern, os.readlink(f"/proc/self/fd/{fd}")):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)


needs_proc = pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")


@pytest.fixture(scope="module")
def plan_file(tmp_path_factory) -> Path:
    """Joints 1 and 2 swept over +-20 deg from the home pose (about 6 s of motion)."""
    plan = plan_for_joints(ROBOT, [1, 2], "home", lower=-DEG20, upper=DEG20, settle=0.2)
    return plan.save(tmp_path_factory.mktemp("plan") / "plan.json")


def _interrupt_at_move(monkeypatch, move: int) -> None:
    """Ctrl-C at the start of the simulated arm's ``move``-th ``move_to`` (0-based)."""
    real, count = SimArm.move_to, {"n": 0}

    def move_to(self, *args, **kwargs):
        count["n"] += 1
        if count["n"] > move:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(SimArm, "move_to", move_to)


@pytest.fixture(scope="module")
def interrupted(plan_file, tmp_path_factory) -> Path:
    """`jaxcomp calibrate --plan PLAN --out D` stopped by Ctrl-C as its second sweep starts
    (a sweep is 3 moves: travel, up, down): D as the user finds it."""
    out = tmp_path_factory.mktemp("interrupted") / "cal"
    args = ["jaxcomp", "calibrate", "--plan", str(plan_file), "--out", str(out)]
    with pytest.MonkeyPatch.context() as mp, redirect_stderr(io.StringIO()) as err:
        _interrupt_at_move(mp, 3)
        mp.setattr("sys.argv", args)
        mp.setenv("JAXCOMP_CACHE", "off")
        with pytest.raises(SystemExit) as exc:
            jaxcomp.cli.main()
    assert exc.value.code == 130, err.getvalue()
    assert f"interrupted: the finished sweeps are in {out / 'recording.npz'}" in err.getvalue()
    assert "Traceback" not in err.getvalue()
    return out


@pytest.fixture()
def cal(interrupted, tmp_path) -> Path:
    """A copy of the interrupted calibration folder."""
    return Path(shutil.copytree(interrupted, tmp_path / "cal"))


# ----------------------------------------------------------------------------- resume
def test_an_interrupted_calibration_leaves_its_finished_sweeps_loadable(interrupted):
    rec = load_recording(interrupted / "recording.npz")
    assert set(np.unique(rec.joint)) == {-1, 1}  # sweep 0 (joint 1) done, sweep 1 not begun
    assert set(np.unique(rec.direction[rec.joint == 1])) == {-1, 1}  # up and down
    manifest = json.loads((interrupted / "recording.npz.parts" / "manifest.json").read_text())
    assert manifest["completed"] == [0]
    assert not (interrupted / LOCK_NAME).exists()


def test_resume_refuses_another_seed_plan_or_truth(cal, plan_file, monkeypatch, capsys):
    before = hashes(cal)
    other_plan = plan_for_joints(ROBOT, [1, 3], "home", lower=-DEG20, upper=DEG20, settle=0.2)
    other_plan = other_plan.save(cal.parent / "other_plan.json")
    truth = TrueRobot.draw(ROBOT, 5).save(cal.parent / "other_truth.json")
    base = ["calibrate", "--out", cal, "--resume"]
    for extra, words in [
        (["--plan", plan_file, "--seed", "7"], ["cannot resume", "seed 0 then, 7 now"]),
        (["--plan", other_plan], ["cannot resume", "the plan differs"]),
        (["--plan", plan_file, "--truth", truth], ["cannot resume", "the truth differs"]),
    ]:
        one_error(*run(base + extra, monkeypatch, capsys)[::2], *words)
    # a new calibration into the folder needs --overwrite; both flags at once are refused
    code, _, err = run(["calibrate", "--plan", plan_file, "--out", cal], monkeypatch, capsys)
    one_error(code, err, "holds an earlier calibration", "--resume", "--overwrite")
    code, _, err = run(base + ["--overwrite", "--plan", plan_file], monkeypatch, capsys)
    one_error(code, err, "--resume", "--overwrite")
    assert hashes(cal) == before


def test_resume_records_only_the_missing_sweeps(cal, plan_file, monkeypatch, capsys):
    """--resume keeps sweep 0 as recorded and adds sweep 1 (the fits are stubbed: this is
    about the recording)."""
    kept = load_recording(cal / "recording.npz")
    truth = replace(TrueRobot.load(cal / "truth.json", ROBOT).params, fit_seconds=0.0)
    monkeypatch.setattr(
        "jaxcomp.identify.fit", lambda recs, method, com_prior=None, transfers=True: truth
    )
    monkeypatch.setattr("jaxcomp.cli.calibrate._warn", lambda params: None)
    monkeypatch.setattr("jaxcomp.identify.plots.plot_sweeps", lambda *a: None)
    args = ["calibrate", "--plan", plan_file, "--out", cal, "--resume"]
    code, out, err = run(args, monkeypatch, capsys)
    assert code == 0, err
    assert "resuming: 1 of 2 sweeps already recorded" in out
    rec = load_recording(cal / "recording.npz")
    assert set(np.unique(rec.joint)) == {-1, 1, 2}
    np.testing.assert_array_equal(rec.current[: kept.n_samples], kept.current)
    assert not np.any(rec.joint[kept.n_samples :] == 1)
    assert not (cal / "recording.npz.parts").exists() and not (cal / LOCK_NAME).exists()
    code, _, err = run(args, monkeypatch, capsys)  # nothing left to resume
    one_error(code, err, "is complete, there is nothing to resume")


# ----------------------------------------------------------------------------- outputs
def test_an_output_that_is_an_input_is_refused(cal, plan_file, monkeypatch, capsys):
    shutil.copy(cal / "truth.json", cal / "params.json")  # a truth kept as params.json
    before = hashes(cal)
    for args in (
        ["control", "--params", cal / "recording.npz", "--out", cal],
        ["calibrate", "--plan", plan_file, "--truth", cal / "params.json", "--out", cal],
        ["fit", cal / "recording.npz", "--out", cal / "recording.npz"],
    ):
        code, _, err = run(args, monkeypatch, capsys)
        one_error(code, err, "is also an input")
    assert hashes(cal) == before


def test_control_refuses_a_folder_with_an_earlier_recording(cal, monkeypatch, capsys):
    before = hashes(cal)
    code, _, err = run(["control", "--out", cal], monkeypatch, capsys)
    one_error(code, err, "holds the recording of an earlier run", "--overwrite")
    assert hashes(cal) == before


# ----------------------------------------------------------------------------- the lock
def test_one_writer_per_folder_and_stale_locks(tmp_path):
    out = tmp_path / "out"
    with output_folder(out) as folder:
        assert (folder / LOCK_NAME).read_text().split()[0] == str(os.getpid())
        with pytest.raises(FileError, match=rf"in use by another jaxcomp run \(pid {os.getpid()}"):
            with output_folder(out):
                pass
    assert not (out / LOCK_NAME).exists() and out.is_dir()
    # the lock file of a process that died is taken over
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        check=True,
        capture_output=True,
        text=True,
    )
    (out / LOCK_NAME).write_text(dead.stdout)
    with output_folder(out):
        assert (out / LOCK_NAME).read_text().split()[0] == str(os.getpid())
    # a folder it created and that stayed empty is removed when the block fails
    with pytest.raises(RuntimeError), output_folder(tmp_path / "new"):
        raise RuntimeError
    assert not (tmp_path / "new").exists()


def _hold_lock(folder: Path) -> subprocess.Popen:
    """Another process holding ``folder``'s lock until it is killed."""
    code = (
        "import sys, time; from jaxcomp.files import output_folder\n"
        "with output_folder(sys.argv[1]):\n    print('held', flush=True); time.sleep(600)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_locked_folder_is_refused_by_every_command(cal, plan_file, monkeypatch, capsys):
    proc = _hold_lock(cal)
    try:
        before = hashes(cal)
        for args in (
            ["calibrate", "--plan", plan_file, "--out", cal, "--resume"],
            ["fit", cal / "recording.npz", "--out", cal / "params.json"],
            ["control", "--out", cal, "--overwrite"],
            ["study", "calibration", "--worlds", "1", "--out", cal],
            ["study", "control", "--worlds", "1", "--out", cal],
        ):
            code, _, err = run(args, monkeypatch, capsys)
            one_error(code, err, f"pid {proc.pid}", str(cal / LOCK_NAME))
        assert hashes(cal) == before
    finally:
        proc.kill()
        proc.wait()


# ----------------------------------------------------------------------------- full disk
@needs_proc
def test_a_full_disk_ends_in_one_error_and_keeps_the_old_file(cal, monkeypatch, capsys):
    params = TrueRobot.draw(ROBOT, 0).params
    monkeypatch.setattr(
        "jaxcomp.identify.fit", lambda recs, method, com_prior=None, transfers=True: params
    )
    old = cal / "p.json"
    old.write_text("{}")
    before = hashes(cal)
    full_disk(monkeypatch, r"\.p\.json\.")
    code, _, err = run(["fit", cal / "recording.npz", "--out", old], monkeypatch, capsys)
    one_error(code, err, f"cannot write {old}", "No space left on device")
    assert hashes(cal) == before  # the old file as it was, no temp file left


@needs_proc
def test_a_full_disk_while_calibrating_keeps_the_finished_sweeps(
    interrupted, plan_file, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "cal"
    sweep0 = load_recording(interrupted / "recording.npz")
    part = f"part-{math.ceil(sweep0.n_samples / 1000) + 1:06d}.npz"  # the 2nd of sweep 1
    full_disk(monkeypatch, part.replace(".", r"\."))
    code, _, err = run(["calibrate", "--plan", plan_file, "--out", out], monkeypatch, capsys)
    one_error(code, err, part, "No space left on device")
    rec = load_recording(out / "recording.npz")
    assert set(np.unique(rec.joint)) == {-1, 1}
    np.testing.assert_array_equal(rec.current, sweep0.current)  # same seed, same sweep
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


@needs_proc
def test_control_on_a_full_disk_keeps_the_earlier_recording(cal, monkeypatch, capsys):
    """The recording is joined at the end: ENOSPC there is an error (status 2), and the
    earlier run's recording that --overwrite would replace stays as it was."""
    before = hashes(cal)
    full_disk(monkeypatch, r"/\.recording\.npz\.[^/]*\.tmp\.npz$")
    args = ["control", "--model", "gen3_lite", "--controller", "velocity", "--duration", "0.05"]
    code, out, err = run(args + ["--out", cal, "--overwrite"], monkeypatch, capsys)
    one_error(code, err, "the recording was not written", "No space left on device")
    assert "ended: completed" in out
    assert hashes(cal)["recording.npz"] == before["recording.npz"]
    assert not [p for p in cal.rglob("*") if ".tmp" in p.name]


def test_a_read_only_folder_is_one_error(interrupted, plan_file, tmp_path, monkeypatch, capsys):
    """Read-only (EROFS; injected, as the tests may run as root): the lock file is the
    first thing written, so every command stops there."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real_open, real_mkdir = os.open, os.mkdir

    def erofs(path):
        return OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))

    def fake_open(path, flags, *args, **kwargs):
        if str(path).startswith(str(ro)) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise erofs(path)
        return real_open(path, flags, *args, **kwargs)

    def fake_mkdir(path, *args, **kwargs):
        if str(path).startswith(str(ro)):
            raise FileExistsError(str(path)) if Path(path).exists() else erofs(path)
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)
    monkeypatch.setattr(os, "mkdir", fake_mkdir)
    for args, words in [
        (["calibrate", "--plan", plan_file, "--out", ro], "cannot write to --out"),
        (["control", "--out", ro / "run"], "cannot create --out"),
        (["fit", interrupted / "recording.npz", "--out", ro / "p.json"], "cannot write to the"),
        (["study", "control", "--worlds", "1", "--out", ro], "cannot write to --out"),
    ]:
        code, _, err = run(args, monkeypatch, capsys)
        one_error(code, err, words, "Read-only file system")
    assert not any(ro.iterdir())


# ----------------------------------------------------------------------------- studies
def test_a_study_checks_its_arguments_before_making_its_folder(monkeypatch, capsys, tmp_path):
    out = tmp_path / "study"
    args = ["study", "calibration", "--worlds", "1", "--plan", "short", "--every", "100000"]
    code, _, err = run(args + ["--out", out], monkeypatch, capsys)
    one_error(code, err, "--every 100000 records fewer than", "use --every")
    code, _, err = run(["study", "control", "--worlds", "0", "--out", out], monkeypatch, capsys)
    one_error(code, err, "--worlds")
    assert not out.exists()


def test_atomic_output_never_leaves_a_half_written_file(tmp_path):
    path = tmp_path / "a.bin"
    path.write_bytes(b"good")
    with pytest.raises(KeyboardInterrupt), atomic_output(path) as tmp:
        tmp.write_bytes(b"half")
        raise KeyboardInterrupt
    assert path.read_bytes() == b"good" and sorted(tmp_path.iterdir()) == [path]
    with atomic_output(path) as tmp:
        tmp.write_bytes(b"new")
    assert path.read_bytes() == b"new" and sorted(tmp_path.iterdir()) == [path]
    assert (path.stat().st_mode & 0o777) == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
