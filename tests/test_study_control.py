"""`jaxcomp study control` and the closed loop under it, on the CPU with a few worlds.

The MJX closed loop (``MjxSimulator.run_closed_loop`` driven by the study's impedance policy)
is checked against the CPU Simulator driven by ``control.loop.run_control`` in lock step, with
the same truth and controller: sample by sample, through a push and up to an effort fault.
Compiled programs (~15-25 s each on a 2-core CPU): the recorded 4-world run of the agreement,
and the study's own (no recording) for 2 worlds and, chunked, for 1 (slow).
"""

import dataclasses
import json

import numpy as np
import pytest
from click.testing import CliRunner

from jaxcomp import load_robot
from jaxcomp.cli import cli
from jaxcomp.control import ImpedanceGains, make_impedance_controller
from jaxcomp.control.loop import run_control
from jaxcomp.control.trajectory import parse_trajectory
from jaxcomp.errors import InputError
from jaxcomp.hardware import Push, Simulator, TrueRobot
from jaxcomp.hardware.mjx import (
    CLOSED_LOOP_AGREEMENT,
    FAULT_EFFORT,
    FAULT_REFUSED,
    BatchTruth,
    MjxSimulator,
    PushSchedule,
)
from jaxcomp.studies import control as sc
from jaxcomp.studies.control import ControlSettings
from jaxcomp.studies.control_policy import REFERENCE_COLUMNS, controller_params, impedance_policy
from jaxcomp.studies.control_worlds import (
    draw_worlds,
    ramped_pushes,
    reference_rows,
    trajectory_for,
)

ROBOT = load_robot("gen3_lite")
GAINS = ImpedanceGains.tracking()
STEPS = 300  # 0.3 s of the half circle's lead-in


def _com_offsets(params) -> np.ndarray:
    off = np.zeros((len(ROBOT.link_names), 3))
    for link, d in params.com_offset.items():
        off[ROBOT.link_index(link)] = d
    return off


@pytest.fixture(scope="session")  # session: never torn down between a worker's tests
def agreement(tmp_path_factory):
    """One truth (seed 11, paper friction, no noise) under four controllers: 0 = params 2-3 %
    off, 1 = exact params and a 7.8 N push from 50.5 ms to 250.5 ms, 2 = joint 1's ratio 3x
    (the gravity current asks for more than its effort limit), 3 = NaN ratios. CPU: 0-2."""
    truth = TrueRobot.draw(ROBOT, seed=11, current_noise=0.0)
    p = truth.params
    off = {k: v + 1e-3 for k, v in p.com_offset.items()}
    ctrl = [
        dataclasses.replace(p, ratio=p.ratio * 1.02, friction=p.friction * 0.97, com_offset=off),
        p,
        dataclasses.replace(p, ratio=p.ratio * np.array([1.0, 3.0, 1.0, 1.0, 1.0, 1.0])),
    ]
    pushes = [[], [Push(0.0505, 0.2, np.array([6.0, -4.0, 3.0]))], [], []]
    start = ROBOT.site_position(Simulator(ROBOT, truth=truth).arm.read().q, "end_effector")
    traj = parse_trajectory("half-circle:passes=1").build(start)  # from the settled start
    cpu = []
    for k, (cp, pw) in enumerate(zip(ctrl, pushes, strict=False)):
        sim = Simulator(ROBOT, truth=truth)
        for push in pw:
            sim.push(push.start, push.duration, push.force)
        out = tmp_path_factory.mktemp(f"cpu{k}")
        controller = make_impedance_controller(ROBOT, cp, GAINS)
        res = run_control(sim.arm, None, controller, "tracking", traj, STEPS * 1e-3, out)
        # after a fault the arm holds in POSITION mode: keep stepping it to the end
        held = [sim.arm.cycle().q for _ in range(STEPS - res.cycles)]
        cpu.append((res, np.array(held).reshape(-1, 6)))
    idle = Simulator(ROBOT, truth=truth).arm  # world 3's arm: never leaves POSITION mode
    cpu.append((None, np.array([idle.cycle().q for _ in range(STEPS)])))
    reference = np.zeros((STEPS + 1, REFERENCE_COLUMNS))
    sample = traj.sample(np.arange(STEPS + 1) * 1e-3)
    reference[:, 0:3], reference[:, 3:6], reference[:, 6:9] = sample
    reference[:, 9] = 1.0  # the RMS over every sample, as run_control's
    allp = ctrl + [p]
    ratio = np.stack([c.ratio for c in allp])
    ratio[3] = np.nan
    friction = np.stack([c.friction for c in allp])
    params = controller_params(ROBOT, ratio, friction, np.stack([_com_offsets(c) for c in allp]))
    policy = impedance_policy("gen3_lite", GAINS)
    sim = MjxSimulator(ROBOT)
    rec = sim.run_closed_loop(
        BatchTruth.from_truths(ROBOT, [truth] * 4),
        policy,
        params,
        None,
        STEPS,
        reference=reference,
        pushes=PushSchedule.from_pushes(pushes),
        every=1,
    )
    return cpu, rec


@pytest.mark.xdist_group("agreement")  # one worker computes the fixture
def test_closed_loop_agrees_with_the_cpu_control_loop(agreement):
    """Worlds 0 (params off) and 1 (exact, pushed): every sample within
    ``CLOSED_LOOP_AGREEMENT``; the tracking RMS of the policy's metric is run_control's."""
    cpu, rec = agreement
    tol = CLOSED_LOOP_AGREEMENT
    for w in (0, 1):
        res = cpu[w][0]
        assert res.kind == "completed", res.reason
        r = res.recording  # sample k = the state after k cycles; MJX sample i: after step i
        assert rec.q.shape == (4, STEPS, 6) and len(r.t) == STEPS + 1
        np.testing.assert_allclose(rec.t, r.t[1:] - r.t[0], atol=1e-12)
        np.testing.assert_allclose(rec.q[w], r.q[1:], atol=tol["q"], rtol=0)
        np.testing.assert_allclose(rec.dq[w], r.dq[1:], atol=tol["dq"], rtol=0)
        np.testing.assert_allclose(rec.current[w], r.current[1:], atol=tol["current"], rtol=0)
        np.testing.assert_allclose(
            rec.command[w], r.extra["command"][:-1], atol=tol["current"], rtol=0
        )
        s = rec.state
        assert s["track_n"][w] == STEPS + 1
        rms = np.sqrt(s["track_sq"][w] / s["track_n"][w])
        assert abs(rms - res.rms_error) < tol["rms"], (rms, res.rms_error)
    assert np.abs(rec.dq[:2]).max() > 0.05  # the arm moved
    # the push moved world 1's end effector by centimetres, the unpushed one stayed on target
    assert cpu[1][0].max_error > 0.01 > 3e-3 > cpu[0][0].max_error


@pytest.mark.xdist_group("agreement")  # one worker computes the fixture
def test_effort_fault_at_the_cpu_step_then_held(agreement):
    """World 2: the CPU arm faults (joint 1 beyond 14 N m) after k cycles; the MJX world at
    sample k, with the effort bit, then holds its position in POSITION mode as the CPU arm
    does; its metrics stop where the CPU loop's did."""
    cpu, rec = agreement
    res, held = cpu[2]
    assert res.kind == "hardware_fault" and "effort limit" in res.reason
    k = res.cycles
    assert 0 < k < 10 and rec.fault_step[2] == k and rec.fault_code[2] == FAULT_EFFORT
    np.testing.assert_allclose(rec.q[2, : k - 1], res.recording.q[1:k], atol=1e-8, rtol=0)
    np.testing.assert_allclose(rec.q[2, k:], held, atol=CLOSED_LOOP_AGREEMENT["q"], rtol=0)
    assert np.abs(held - rec.q[2, k - 1]).max() > 1e-3  # it sags back under the servo
    assert rec.state["track_n"][2] == len(res.recording.t) == k
    assert (rec.command[2, k:] == rec.command[2, k]).all()  # none sent since


@pytest.mark.xdist_group("agreement")  # one worker computes the fixture
def test_refused_command_holds_from_sample_0(agreement):
    """World 3: NaN params give a NaN command at sample 0: refused, never sent; the world
    stays in POSITION mode as a CPU arm that is never switched, and the policy state is the
    initial one (nothing counted, as run_control, which refuses to start)."""
    cpu, rec = agreement
    assert rec.fault_step[3] == 0 and rec.fault_code[3] == FAULT_REFUSED
    assert rec.state["track_n"][3] == 0 and not rec.command[3].any()  # nothing sent
    np.testing.assert_allclose(rec.q[3], cpu[3][1], atol=CLOSED_LOOP_AGREEMENT["q"], rtol=0)
    assert (rec.fault_step[:2] == -1).all()


# ----------------------------------------------------------------------------- the study
def test_reference_rows_and_pushes():
    start, traj = trajectory_for(ROBOT, 1)
    rows = reference_rows(traj, start, 2500, {"track": (2.0, 9.0), "base": (0.3, 0.5)})
    assert rows.shape == (2501, REFERENCE_COLUMNS)
    np.testing.assert_array_equal(rows[:2000, 0:3], np.broadcast_to(start, (2000, 3)))
    np.testing.assert_allclose(rows[2000, 0:3], start, atol=1e-12)  # the lead-in starts there
    assert np.linalg.norm(rows[2500, 3:6]) > 0.05  # 0.5 s later it moves (m/s)
    assert rows[:, 9].sum() == 501 and rows[:, 10].sum() == 200 and rows[:, 11].sum() == 0
    pushes = ramped_pushes(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), 10.0)
    assert pushes.force.shape == (2, 5, 3)
    np.testing.assert_allclose(pushes.force.sum(axis=1), [[0, 0, 10.0], [10.0, 0, 0]])
    np.testing.assert_allclose(pushes.start[0] + pushes.duration[0], 1.5)
    truth, params, direction = draw_worlds(ROBOT, 50, 0, 0.05, 0.002, False, 0.05)
    part = draw_worlds(ROBOT, 20, 0, 0.05, 0.002, False, 0.05, first=30)  # worlds 30-49 alone
    np.testing.assert_array_equal(part[0].ratio, truth.ratio[30:])
    np.testing.assert_array_equal(part[0].com_offset, truth.com_offset[30:])
    np.testing.assert_array_equal(part[1]["com"], params["com"][30:])
    np.testing.assert_array_equal(part[2], direction[30:])
    assert not direction[:, 2].any()  # horizontal by default
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0)
    rel = params["ratio"] / truth.ratio - 1
    assert 0.03 < np.abs(rel).max() <= 0.05 and params["com"].shape == (50, 7, 3)
    with pytest.raises(InputError, match="horizontal"):
        draw_worlds(ROBOT, 2, 0, 0.0, 0.0, False, 0.05, "up")


def _run_cli(tmp_path, name: str, seed: int):
    out = tmp_path / name
    args = ["study", "control", "--worlds", "2", "--seed", str(seed), "--duration", "0.3"]
    args += ["--params-error", "0", "--com-error", "0", "--push-direction", "sphere"]
    result = CliRunner().invoke(cli, args + ["--out", str(out)])
    assert result.exit_code == 0, result.output + repr(result.exception)
    return json.loads((out / "study.json").read_text()), out, result.output


def _same_numbers(a, b, name: str) -> None:
    """JSON values equal, their floats to 1e-12 relative (a batch of one world and one of two
    round the closed loop's matrix products differently on the CPU)."""
    if isinstance(b, dict):
        assert a.keys() == b.keys(), name
        for k in b:
            _same_numbers(a[k], b[k], f"{name}.{k}")
    elif isinstance(b, str) or (isinstance(b, list) and b and isinstance(b[0], str | bool)):
        assert a == b, name
    else:  # numbers, None as NaN
        fa, fb = np.array(a, dtype=float), np.array(b, dtype=float)
        np.testing.assert_allclose(fa, fb, rtol=1e-12, atol=1e-20, err_msg=name)


@pytest.mark.slow
def test_study_cli_exact_params_faults_and_reproduces(tmp_path):
    """2 worlds with exact controller params, seed 3: world 0 is pushed down (z -0.85) and the
    friction compensation on top overloads joint 1 (effort fault during the push, its figures
    left out); world 1 pushed up tracks the lead-in within 2 mm and yields as F / K_d within
    10 %. The same seed in chunks of one world, interrupted after the first and resumed, gives
    the same numbers (a world's draws and noise follow its index), to rounding."""
    first, out, text = _run_cli(tmp_path, "a", 3)
    assert (out / "tracking.png").stat().st_size > 10_000
    assert (out / "compliance.png").stat().st_size > 10_000
    assert "compliance ratio median" in text and "faulted 1" in text
    assert first["worlds"] == 2 and first["seed"] == 3 and first["backend"] == "cpu"
    assert first["config"]["steps"] == 2300 and first["timing_s"]["compile"] > 0
    pw, sm = first["per_world"], first["summary"]
    assert pw["faulted"] == [True, False] and pw["fault"] == ["effort limit", ""]
    assert pw["push_direction"][0][2] < -0.5 and 0.5 < pw["fault_time_s"][0] < 1.5
    assert pw["tracking_rms_m"][0] is None and pw["compliance_ratio"][0] is None
    assert pw["tracking_rms_m"][1] < 2e-3
    assert abs(pw["compliance_ratio"][1] - 1) < 0.1, pw["compliance_ratio"]
    assert sm["faulted"] == 1 and sm["tracking_rms_m"]["max"] == pw["tracking_rms_m"][1]
    assert max(pw["ratio_error"]) == 0 and max(pw["gravity_current_error_pooled"]) < 1e-12
    settings = ControlSettings(2, 3, duration=0.3, params_error=0.0, com_error=0.0,
                               push="sphere", chunk_worlds=1)  # fmt: skip
    real, calls = sc.chunk_results, []

    def interrupted(study, rows, progress=False):
        calls.append(rows.start)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(study, rows, progress)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sc, "chunk_results", interrupted)
        with pytest.raises(KeyboardInterrupt):
            sc.study_into(tmp_path / "b", settings, progress=False, robot=ROBOT)
        assert not (tmp_path / "b" / "study.json").exists()
        with pytest.raises(InputError, match="--resume continues it"):
            sc.study_into(tmp_path / "b", settings, progress=False, robot=ROBOT)
        calls.clear()
        again = sc.study_into(tmp_path / "b", settings, progress=False, robot=ROBOT, resume=True)
    assert calls == [1] and again.report["chunk_worlds"] == 1  # the first chunk was kept
    again = json.loads((tmp_path / "b" / "study.json").read_text())
    for part in ("per_world", "summary"):
        assert again[part].keys() == first[part].keys()
        for k, v in first[part].items():
            _same_numbers(again[part][k], v, k)
    assert not (tmp_path / "b" / "chunks").exists()
    # the numbers follow the drawn worlds, and the draws follow the seed
    a, b = (draw_worlds(ROBOT, 2, seed, 0.0, 0.0, False, 0.05, "sphere") for seed in (3, 4))
    assert not np.allclose(a[0].ratio, b[0].ratio) and not np.allclose(a[2], b[2])
    np.testing.assert_array_equal(a[2], pw["push_direction"])


@pytest.mark.parametrize(
    "args, message",
    [
        (["--worlds", "0"], "--worlds must be >= 1"),
        (["--force", "-1"], "--force must be > 0"),
        (["--params-error", "1.5"], "--params-error must be < 1"),
        (["--com-error", "nan"], "--com-error must be >= 0"),
        (["--duration", "0"], "--duration must be > 0"),
        (["--passes", "0"], "--passes must be >= 1"),
        (["--chunk-worlds", "0"], "--chunk-worlds must be an integer >= 1"),
    ],
)
def test_study_cli_refuses_bad_input(args, message, tmp_path):
    result = CliRunner().invoke(cli, ["study", "control", "--out", str(tmp_path), *args])
    assert isinstance(result.exception, InputError), result.output
    assert message in str(result.exception)
    assert not (tmp_path / "study.json").exists()
