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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.interface import Arm, ArmState
from jaxcomp.identify.plan import CalibrationPlan, plan_from_dict
from jaxcomp.recording import Recording, RecordingWriter, validate
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import arm_joint_indices, write_json_atomic

#: The plan being recorded, kept beside the writer's part files to check a resume.
PLAN_FILE = "plan.json"
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
) -> Recording:
    """Record ``plan`` on ``arm`` into the recording ``path`` (``.npz``) and return it.

    Args:
        arm: the arm (simulated or real), started, in any mode; it ends in position mode at
            the last sweep's start.
        plan: the sweeps (validated against ``model`` first).
        path: the recording to write; part files go to ``<path>.parts/`` meanwhile.
        model: the robot model (name, path or ``Robot``) stored in the recording with its
            current-controlled joints' names (which must match the arm's).
        gravity: (3,) m/s^2 in the base frame; payload_mass: kg; payload_com: (3,) m in the
            end-effector frame (recording metadata; None leaves the field out).
        progress: show a tqdm bar over the plan's samples.
        resume: keep the sweeps an interrupted ``record`` of the same plan to ``path``
            finished, and record only the others.

    On any exception (KeyboardInterrupt included) the finished sweeps stay on disk and the
    exception propagates; ``jaxcomp.recording.recover(path)`` joins what was written.
    Raises InputError before moving for a plan, model or metadata that does not fit.
    """
    robot = load_robot(model)
    model = robot.reference if isinstance(model, Robot) else str(model)
    joints = tuple(robot.joint_names[j] for j in arm_joint_indices(robot))
    n = len(joints)
    if arm.n != n:
        raise InputError(
            f"the arm has {arm.n} joints but model {model!r} has {n} current-controlled joints"
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
    _check_metadata(model, joints, gravity, payload_mass, payload_com)

    writer = RecordingWriter(
        path,
        str(model),
        n,
        gravity=gravity,
        payload_mass=payload_mass,
        payload_com=payload_com,
        joints=joints,
        resume=resume,
    )
    plan_file = writer.parts / PLAN_FILE
    if plan_file.is_file():
        try:
            earlier = plan_from_dict(json.loads(plan_file.read_text()))
        except (ValueError, InputError):
            earlier = None
        if earlier != plan:
            raise InputError(
                f"cannot resume {writer.path}: it was recorded with a different plan "
                f"({plan_file}); record without resume to start over"
            )
    else:
        write_json_atomic(plan_file, plan.to_dict())
    done = {int(i) for i in writer.completed}
    todo = [i for i in range(len(plan.sweeps)) if i not in done]

    state = arm.read()
    last = writer.last_t
    # samples start one cycle after ``state``: keep t increasing across a resume
    offset = 0.0 if last is None or state.t + arm.dt > last else last - state.t
    from tqdm.auto import tqdm

    bar = tqdm(
        total=plan.samples(state.q, todo),
        disable=not progress,
        unit="sample",
        unit_scale=True,
        desc=f"calibration ({len(todo)}/{len(plan.sweeps)} sweeps)",
    )

    def recorder(joint: int, direction: int):
        def on_state(s: ArmState) -> None:
            writer.append(s.t + offset, s.q, s.dq, s.current, joint, direction)
            bar.update()

        return on_state

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
        except Exception:  # the original exception matters more
            pass
        raise
    finally:
        bar.close()
    return writer.close()
