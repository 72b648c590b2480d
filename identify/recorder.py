"""Record a calibration plan on an ``Arm``: the 1 kHz sweeps identification fits (paper IV-A).

For each sweep of the plan the arm travels to the sweep's start (through its ``via`` poses) at
the plan's ``move_speed`` and settles; then the swept joint goes from ``lower`` to ``upper``
(direction +1) and back (direction -1) at the sweep's speed with the robot's own position
servo (``Arm.move_to``). Every 1 kHz state is written to a ``RecordingWriter``, the travel
and settling included with ``joint`` -1 and ``direction`` 0, so the recording is continuous
and consecutive sweeps of one joint stay separate. Directions come from the commanded motion,
not from the measured velocity.

Each sweep (its travel included) is one writer segment labelled with its index in the plan:
an interruption (an exception, Ctrl-C, a hardware fault) keeps the finished sweeps on disk,
and ``record(..., resume=True)`` records only the others. Time stamps of a resumed run are
shifted, when needed, to continue after the samples already recorded.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.files import reading, writing
from jaxcomp.hardware.interface import Arm, ArmState
from jaxcomp.identify.plan import CalibrationPlan, plan_from_dict
from jaxcomp.recording import (
    Recording,
    RecordingWriter,
    read_manifest,
    setting_differences,
    validate,
)
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import arm_joint_indices, json_ready, write_json_atomic

#: The plan being recorded, kept beside the writer's part files to check a resume.
PLAN_FILE = "plan.json"
#: The run's other settings (``record(settings=)``), kept there too to check a resume.
SETTINGS_FILE = "settings.json"
#: Recorded direction (+1, -1; 0 outside sweeps) of each kind of move of ``CalibrationPlan.moves``.
MOVE_DIRECTION = {"via": 0, "start": 0, "up": +1, "down": -1}


def _check_metadata(
    model: str, joints: tuple[str, ...], gravity, payload_mass, payload_com
) -> None:
    """Validate the metadata with the recording format's own rules before anything moves."""
    n = len(joints)
    data: dict[str, Any] = {
        "model": np.array(model),
        "joints": np.array(joints),
        "t": np.array([0.0, CONTROL_PERIOD]),
        "q": np.zeros((2, n)),
        "dq": np.zeros((2, n)),
        "current": np.zeros((2, n)),
        "joint": np.zeros(2, int),
        "direction": np.ones(2, int),
    }
    for key, value in (
        ("gravity", gravity),
        ("payload_mass", payload_mass),
        ("payload_com", payload_com),
    ):
        if value is not None:
            data[key] = np.asarray(value)
    validate(data, "record")


def _read_json(path: Path) -> Any:
    """The JSON in ``path``; None when it is missing or not JSON."""
    if not path.is_file():
        return None
    with reading(path):
        text = path.read_text()
    try:
        return json.loads(text)
    except ValueError:
        return None


def _recorded_model(model: str | Robot) -> tuple[Robot, str, tuple[str, ...]]:
    """The robot, the recording's ``model`` field and its current-controlled joints."""
    robot = load_robot(model)
    name = robot.reference if isinstance(model, Robot) else str(model)
    return robot, name, tuple(robot.joint_names[j] for j in arm_joint_indices(robot))


def check_resume(
    path: str | Path,
    plan: CalibrationPlan,
    model: str | Robot,
    settings: Mapping[str, Any] | None = None,
) -> list[int]:
    """The plan sweeps an interrupted ``record`` into ``path`` finished (empty when there is
    nothing to resume), after checking that it recorded the same ``plan`` on the same
    ``model`` (and joints) with the same ``settings`` (as ``record`` takes them). Reads only.

    Args:
        path: The recording ``record`` was writing.
        plan: The plan to resume.
        model: The robot (or its name).
        settings: ``record``'s settings; None: not compared.

    Returns:
        The indices of the finished sweeps.

    Raises:
        InputError: naming what differs.
    """
    path = Path(path)
    manifest = read_manifest(path)
    if manifest is None:
        return []
    _, name, joints = _recorded_model(model)
    parts = path.with_name(path.name + ".parts")
    meta = manifest["meta"]
    now: dict[str, Any] = {"model": name, "joints": list(joints)}
    earlier: dict[str, Any] = {k: meta.get(k) for k in now}
    data = _read_json(parts / PLAN_FILE)
    try:
        earlier_plan = plan_from_dict(data) if data is not None else None
    except InputError:
        earlier_plan = None
    stored = _read_json(parts / SETTINGS_FILE)
    if settings is not None and isinstance(stored, dict):  # older runs kept no settings
        earlier.update(stored)
        now.update(json.loads(json.dumps(json_ready(dict(settings)))))
    said = ["the plan differs"] if earlier_plan != plan else []
    said += [d for d in [setting_differences(earlier, now)] if d]
    if said:
        raise InputError(
            f"cannot resume {path}: {'; '.join(said)} (start over without resuming, or into "
            "another folder)"
        )
    return [int(i) for i in manifest["completed"]]


def record(
    arm: Arm,
    plan: CalibrationPlan,
    path: str | Path,
    *,
    model: str | Robot,
    gravity: Sequence[float] | None = None,
    payload_mass: float | None = None,
    payload_com: Sequence[float] | None = None,
    progress: bool = True,
    resume: bool = False,
    settings: Mapping[str, Any] | None = None,
    on_state: Callable[[ArmState, float], None] | None = None,
) -> Recording:
    """Record ``plan`` on ``arm`` into the recording ``path`` (``.npz``) and return it.

    Args:
        arm: the arm (simulated or real), started, in any mode; it ends in position mode at
            the last sweep's start.
        plan: the sweeps (validated against ``model`` first).
        path: the recording to write; part files go to ``<path>.parts/`` meanwhile.
        model: the robot model (name, path or ``Robot``) stored in the recording with its
            current-controlled joints' names (which must match the arm's).
        gravity: (3,) m/s^2 in the arm's base frame (recording metadata; None leaves the
            field out, as for the payload's).
        payload_mass: kg.
        payload_com: (3,) m in the end-effector frame.
        progress: show a tqdm bar over the plan's samples.
        resume: keep the sweeps an interrupted ``record`` of the same plan to ``path``
            finished, and record only the others (``check_resume``: InputError when the
            plan, model, joints or settings differ).
        settings: whatever else must match for a resume (e.g. the simulator's seed and
            truth), a JSON-able mapping kept beside the part files.
        on_state: called with every state recorded and the fraction of the plan's samples
            done (0-1), e.g. for a progress display; keep it quick (it runs every 1 ms).

    Returns:
        The recording written.

    Raises:
        InputError: before moving, for a plan, model or metadata that does not fit.

    On any exception (KeyboardInterrupt included) the finished sweeps are joined into
    ``path``, a loadable recording, and stay in the part files for a resume; the exception
    propagates. ``jaxcomp.recording.recover(path)`` also joins the unfinished sweep.
    """
    robot, name, joints = _recorded_model(model)
    n = len(joints)
    if arm.n != n:
        raise InputError(
            f"the arm has {arm.n} joints but model {name!r} has {n} current-controlled joints"
        )
    if not isinstance(plan, CalibrationPlan):
        raise InputError(f"plan must be a CalibrationPlan, got {type(plan).__name__}")
    plan.validate(robot)
    vmax = float(np.min(arm.limits.velocity))
    speeds = [plan.move_speed] + [s.speed for s in plan.sweeps]
    if max(speeds) > vmax:
        raise InputError(
            f"the plan moves at up to {max(speeds):.3g} rad/s, beyond the arm's speed limit "
            f"{vmax:.3g} rad/s"
        )
    _check_metadata(name, joints, gravity, payload_mass, payload_com)
    if resume:
        check_resume(path, plan, model, settings)

    writer = RecordingWriter(
        path,
        name,
        n,
        gravity=gravity,
        payload_mass=payload_mass,
        payload_com=payload_com,
        current_lag=getattr(arm, "current_lag", 0.0),
        joints=joints,
        resume=resume,
    )
    for file, data in ((PLAN_FILE, plan.to_dict()), (SETTINGS_FILE, settings)):
        where = writer.parts / file
        if data is not None and not where.is_file():
            with writing(where):
                write_json_atomic(where, json_ready(dict(data)))
    done = {int(i) for i in writer.completed}
    todo = [i for i in range(len(plan.sweeps)) if i not in done]

    state = arm.read()
    last = writer.last_t
    # samples start one cycle after ``state``: keep t increasing across a resume
    offset = 0.0 if last is None or state.t + arm.dt > last else last - state.t
    from tqdm.auto import tqdm

    total = plan.samples(state.q, todo)
    done_samples = 0
    bar = tqdm(
        total=total,
        disable=not progress,
        unit="sample",
        unit_scale=True,
        desc=f"calibration ({len(todo)}/{len(plan.sweeps)} sweeps)",
    )

    def recorder(joint: int, direction: int):
        def on_sample(s: ArmState) -> None:
            nonlocal done_samples
            writer.append(s.t + offset, s.q, s.dq, s.current, joint, direction)
            bar.update()
            done_samples += 1
            if on_state is not None:
                on_state(s, min(done_samples / max(total, 1), 1.0))

        return on_sample

    try:
        current = None
        for i, kind, target, speed, accel, settle in plan.moves(todo):
            if i != current:
                if current is not None:
                    writer.end()
                writer.begin(i)
                current = i
            direction = MOVE_DIRECTION[kind]  # from the commanded motion
            joint = plan.sweeps[i].joint if direction else -1
            arm.move_to(
                target, speed, on_state=recorder(joint, direction), accel=accel, settle=settle
            )
        if current is not None:
            writer.end()
    except BaseException:
        try:  # what the open sweep recorded, for recover(); resume discards it
            writer.flush()
        except Exception:  # noqa: BLE001, S110 - the original exception matters more
            pass
        try:  # the finished sweeps as a loadable recording
            writer.save_completed()
        except Exception:  # noqa: BLE001, S110
            pass
        raise
    finally:
        bar.close()
    return writer.close()
