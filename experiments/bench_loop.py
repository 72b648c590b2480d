"""Benchmark: the whole 1 kHz control loop on the simulated Gen3 Lite.

Four parts, each optional:

- lock step (default): ``run_control`` as fast as the CPU allows, arm alone (Exp. 2's half
  circle) and on the Dingo-O (guidance with a push, tracking a circle), ``--repeats`` runs
  each; prints the speed in multiples of real time (target >= 5x) and the per-cycle compute
  (state in -> command ready: controller, watchdog, base follower, recording) and exchange
  (``Arm.cycle``: one physics step) medians;
- ``--profile``: the wall time of each part of the cycle (controller, physics step, twist
  limiter, watchdog, base follower, recording, ...) in one lock-step run of the mobile robot;
- ``--realtime SECONDS`` (the issue's check: 60): one tracking-mode run of the mobile robot
  with the simulator and the loop paced to the wall clock; prints the missed deadlines (target
  < 0.1 %), the period median / p99 / max and the compute p99. The loop thread runs under
  SCHED_FIFO when the OS allows (``--rt-priority``, 0: off). For comparison it first measures
  the platform itself the same way: a loop that only waits for each 1 ms deadline and spins
  ``--baseline-work`` us (no Python objects, no JAX), so a shared or virtual machine's own
  scheduling jitter can be told apart from the loop's;
- ``--behaviour``: controller behaviour for each gains preset (the paper's, the paper's with the
  motion-torque friction direction, ``ImpedanceGains.tracking()``), with params identified by
  the joint fit on a simulated calibration (made here, ~45 s, or read from a ``jaxcomp
  calibrate`` folder with ``--calibration DIR``): half-circle RMS error, F/K of steady pushes,
  guidance and tracking after a push.

Run: python experiments/bench_loop.py [--repeats N] [--profile] [--realtime 60] [--behaviour]
"""

import os

# one core, single-threaded XLA kernels: before JAX runs anything
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from paper_common import after, ramped_push  # noqa: E402

from jaxcomp.control import ImpedanceGains, make_impedance_controller  # noqa: E402
from jaxcomp.control.cycle import Cycle  # noqa: E402
from jaxcomp.control.loop import run_control  # noqa: E402
from jaxcomp.control.mount import arm_model  # noqa: E402
from jaxcomp.control.run_recording import Recorder  # noqa: E402
from jaxcomp.control.timing import (  # noqa: E402
    configure_jax_for_control,
    realtime_priority,
    wait_until,
)
from jaxcomp.hardware import Simulator, TrueRobot  # noqa: E402
from jaxcomp.plausibility import checked_arm_params  # noqa: E402
from jaxcomp.robot import load_robot  # noqa: E402
from jaxcomp.robot_params import RobotParams  # noqa: E402

MOBILE = load_robot("mobile_gen3_lite")
ARM = arm_model(MOBILE)
SEED = 11


# ----------------------------------------------------------------------------- set-up


def calibrated(calibration: str | None) -> tuple[RobotParams, TrueRobot]:
    """(identified params, the truth they were identified on): from a ``jaxcomp calibrate``
    folder, or a simulated calibration made here (the default plan on the truth of seed 11,
    then the joint fit with the simulator's 0.05 A current noise)."""
    if calibration is not None:
        folder = Path(calibration)
        return RobotParams.load(folder / "params.json"), TrueRobot.load(folder / "truth.json")
    from jaxcomp.identify import fit
    from jaxcomp.identify.plan_design import default_plan
    from jaxcomp.identify.recorder import record

    truth = TrueRobot.draw(ARM, seed=SEED)
    sim = Simulator(ARM, truth, seed=SEED)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, sim.arm as arm:
        rec = record(arm, default_plan(ARM), Path(tmp) / "rec.npz", model=ARM.name, progress=False)
    params = fit(rec)
    print(f"(simulated calibration and joint fit: {time.perf_counter() - t0:.0f} s)")
    return params, truth


def simulator(robot, truth: TrueRobot, realtime: bool = False) -> Simulator:
    params = dataclasses.replace(truth.params, model=robot.name)
    true = TrueRobot(params, truth.current_noise, truth.viscous, truth.seed)
    return Simulator(robot, true, seed=truth.seed, realtime=realtime)


# ----------------------------------------------------------------------------- lock step


def lockstep(params, truth, repeats: int) -> dict:
    ctrl = make_impedance_controller(ARM, params, ImpedanceGains.tracking())
    ctrl.compile()
    runs = {
        "arm alone, half circle (Exp. 2)": (ARM, "tracking", "half-circle:passes=1", 6.0, False),
        "mobile, guidance + push (Exp. 3)": (MOBILE, "guidance", None, 4.0, True),
        "mobile, tracking circle (Exp. 3)": (MOBILE, "tracking", "circle:r=0.05", 4.0, True),
    }
    print(f"lock step, ImpedanceGains.tracking(), {repeats} runs each (load {load():.2f})")
    print(
        f"{'run':<36}{'x real time':>12}{'(best)':>8}{'per CPU s':>11}{'compute us':>12}"
        f"{'exchange us':>13}"
    )
    figures = {name: [] for name in runs}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):  # interleaved: every scenario sees the same machine conditions
            for name, (robot, mode, traj, seconds, push) in runs.items():
                sim = simulator(robot, truth)
                if push:
                    ramped_push(sim, 0.5, 0.8, [10.0, 0.0, 0.0])
                base = sim.base if sim.has_base else None
                tm = run_control(sim.arm, base, ctrl, mode, traj, seconds, tmp).timing
                figures[name].append(
                    (
                        tm["speed_x_realtime"],
                        tm["speed_x_realtime_cpu"],
                        tm["compute"]["median_us"],
                        tm["exchange"]["median_us"],
                    )
                )
    out = {}
    for name, rows in figures.items():
        v = np.array(rows)
        speed, cpu, compute, exchange = np.median(v, axis=0)
        out[name] = {
            "x_realtime": float(speed),
            "x_realtime_best": float(v[:, 0].max()),
            "x_realtime_per_cpu_s": float(cpu),
            "compute_median_us": float(compute),
            "exchange_median_us": float(exchange),
        }
        print(
            f"{name:<36}{speed:>12.1f}{v[:, 0].max():>8.1f}{cpu:>11.1f}"
            f"{compute:>12.0f}{exchange:>13.0f}"
        )
    print(
        "(median over the runs; target >= 5x real time. 'per CPU s': robot time per CPU second "
        "of the loop's thread,\n the speed on a core of its own; compute and exchange: per-cycle "
        "medians, wall clock)"
    )
    return out


# ----------------------------------------------------------------------------- profile


def profile(params, truth, seconds: float = 3.0) -> None:
    """Per-call wall time of each part of the cycle in one lock-step run of the mobile robot
    (tracking a circle, pushed): each part is wrapped in a timer (~0.3 us added per call)."""
    from collections import defaultdict

    ctrl = make_impedance_controller(ARM, params, ImpedanceGains.tracking())
    ctrl.compile()
    times = defaultdict(list)
    clock = time.perf_counter_ns

    def wrap(obj, attr: str, label: str) -> None:
        fn = getattr(obj, attr)

        def timed(*a, **k):
            t0 = clock()
            out = fn(*a, **k)
            times[label].append(clock() - t0)
            return out

        setattr(obj, attr, timed)

    sim = simulator(MOBILE, truth)
    ramped_push(sim, 0.5, 0.8, [10.0, 0.0, 0.0])
    wrap(sim.arm, "cycle", "arm.cycle (exchange)")
    wrap(sim, "step", "  sim.step")
    wrap(sim, "_drive_base", "    sim._drive_base (twist limiter)")
    wrap(sim, "_apply_interaction", "    sim._apply_interaction (push)")
    wrap(sim, "_measure", "    sim._measure (current, faults)")
    wrap(sim.base, "odometry", "base.odometry")
    wrap(sim.base, "send_twist", "base.send_twist")
    wrap(ctrl, "packed_step", "  controller.packed_step (JAX)")
    cycle_init = Cycle.__init__

    def init(self, *a, **k):
        cycle_init(self, *a, **k)
        wrap(self, "targets", "targets (trajectory, frames)")
        wrap(self.law, "run", "law.run (controller)")
        wrap(self.wd, "check_state", "watchdog.check_state")
        wrap(self.wd, "check_odometry", "watchdog.check_odometry")
        wrap(self.wd, "check_command", "watchdog.check_command")
        wrap(self.follower, "twist", "follower.twist (Eq. 20)")

    recorder_init = Recorder.__init__

    def rec_init(self, *a, **k):
        recorder_init(self, *a, **k)
        wrap(self, "add", "recorder.add")
        wrap(self, "write_rows", "recorder.write_rows (per 1000 samples)")

    Cycle.__init__, Recorder.__init__ = init, rec_init
    try:
        with tempfile.TemporaryDirectory() as tmp:
            res = run_control(sim.arm, sim.base, ctrl, "tracking", "circle:r=0.05", seconds, tmp)
    finally:
        Cycle.__init__, Recorder.__init__ = cycle_init, recorder_init
    tm = res.timing
    print(
        f"profile of one lock-step cycle, mobile tracking + push, {seconds:g} s "
        f"(load {load():.2f}): compute median {tm['compute']['median_us']:.0f} us, exchange median "
        f"{tm['exchange']['median_us']:.0f} us"
    )
    print(f"{'part':<40}{'calls':>7}{'median us':>11}{'mean us':>9}")
    for label, values in times.items():
        v = np.array(values) / 1e3
        print(f"{label:<40}{v.size:>7}{np.median(v):>11.1f}{v.mean():>9.1f}")


# ----------------------------------------------------------------------------- real time


def platform_baseline(seconds: float, work_us: float, priority: int | None) -> dict:
    """Missed deadlines of a loop that waits for each 1 ms deadline as the control loop does
    and then spins ``work_us`` us: the scheduling jitter of the machine itself."""
    n = int(seconds * 1000)
    period = 1_000_000
    late = np.zeros(n)
    with realtime_priority(priority) as fifo:
        deadline = time.perf_counter_ns() + period
        for k in range(n):
            wait_until(deadline)
            t0 = time.perf_counter_ns()
            while time.perf_counter_ns() - t0 < work_us * 1e3:
                pass
            deadline += period
            done = time.perf_counter_ns()
            late[k] = done - deadline
            if done > deadline:
                deadline += -(-(done - deadline) // period) * period
    missed = int((late > 0).sum())
    return {"fifo": fifo, "missed": missed, "fraction": missed / n}


def realtime(params, truth, seconds: float, priority: int | None, work_us: float) -> dict:
    ctrl = make_impedance_controller(ARM, params, ImpedanceGains.tracking())
    ctrl.compile()
    base_line = platform_baseline(min(seconds, 10.0), work_us, priority)
    sim = simulator(MOBILE, truth, realtime=True)
    with tempfile.TemporaryDirectory() as tmp, realtime_priority(priority) as fifo:
        res = run_control(
            sim.arm, sim.base, ctrl, "tracking", "circle:r=0.05,v=0.05", seconds, tmp, True
        )
    tm = res.timing
    per, comp = tm["period"], tm["compute"]
    ok = res.kind == "completed" and tm["missed_fraction"] < 1e-3
    print(f"real time, {seconds:g} s, mobile tracking mode (load {load():.2f})")
    print(f"  ended: {res.kind} ({res.reason}); SCHED_FIFO {'on' if fifo else 'off'}")
    print(
        f"  missed deadlines {tm['missed_deadlines']} of {tm['cycles']} "
        f"({100 * tm['missed_fraction']:.3f} %; target < 0.1 %: {'met' if ok else 'NOT met'})"
    )
    print(
        f"  period median {per['median_us']:.1f} us, p99 {per['p99_us']:.1f} us, "
        f"max {per['max_us']:.1f} us"
    )
    print(
        f"  compute median {comp['median_us']:.0f} us, p99 {comp['p99_us']:.0f} us, "
        f"max {comp['max_us']:.0f} us; exchange median {tm['exchange']['median_us']:.0f} us"
    )
    print(
        f"  platform baseline ({min(seconds, 10.0):g} s waiting for 1 ms deadlines, "
        f"{work_us:g} us of spinning each): missed {base_line['missed']} "
        f"({100 * base_line['fraction']:.3f} %), SCHED_FIFO {'on' if base_line['fifo'] else 'off'}"
    )
    return {
        "seconds": seconds,
        "ended": res.kind,
        "fifo": bool(fifo),
        "missed_deadlines": tm["missed_deadlines"],
        "missed_fraction": tm["missed_fraction"],
        "period_us": {k: per[k] for k in ("median_us", "p99_us", "max_us")},
        "compute_us": {k: comp[k] for k in ("median_us", "p99_us", "max_us")},
        "platform_baseline_missed_fraction": base_line["fraction"],
    }


# ----------------------------------------------------------------------------- behaviour


def behaviour(params, truth) -> dict:
    presets = {
        "paper": ImpedanceGains.paper(),
        "paper, motion dir.": ImpedanceGains.paper(friction_direction="motion"),
        "tracking, K 40 D 3": ImpedanceGains.tracking(stiffness=40.0, damping=3.0),
        "tracking": ImpedanceGains.tracking(),
    }
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, gains in presets.items():
            ctrl = make_impedance_controller(ARM, params, gains)
            ctrl.compile()
            k = gains.stiffness[0]
            force = 0.025 * k  # N: F / K = 25 mm
            rows[name] = {
                "K_d N/m": k,
                **half_circle(ctrl, truth, tmp),
                **pushes(ctrl, truth, tmp, force, k),
                **guidance(ctrl, truth, tmp, force, k),
                **tracking(ctrl, truth, tmp, force, k),
            }
    keys = list(dict.fromkeys(key for row in rows.values() for key in row))
    print("behaviour with identified params (F / K = 25 mm pushes, ramped over 0.1 s)")
    print(f"{'':<36}" + "".join(f"{n:>20}" for n in rows))
    for key in keys:
        cells = []
        for row in rows.values():
            v = row.get(key, "-")
            cells.append(f"{v:>20}" if isinstance(v, str) else f"{v:>20.3g}")
        print(f"{key:<36}" + "".join(cells))
    print(
        "(tracking: ImpedanceGains.tracking(); 'tracking, K 40 D 3': the same with the paper's "
        "K_d, D_d;\n 'paper, motion dir.': the paper's gains with friction_direction='motion'. "
        "A run that ended early is measured up to its end.)"
    )
    return rows


def half_circle(ctrl, truth, tmp) -> dict:
    sim = simulator(ARM, truth)
    res = run_control(sim.arm, None, ctrl, "tracking", "half-circle", None, tmp)
    if res.recording is None:
        return {"half circle x4: ended": res.kind}
    rec = res.recording
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    arcs = t > t[-1] - 4 * math.pi * 0.315 / 0.101
    return {
        "half circle x4: ended": res.kind,
        "half circle RMS mm": 1e3 * float(np.sqrt(np.mean(err**2))),
        "half circle RMS on the arcs mm": 1e3 * float(np.sqrt(np.mean(err[arcs] ** 2))),
        "half circle max mm": 1e3 * float(err.max()),
    }


def pushes(ctrl, truth, tmp, force, k) -> dict:
    sim = simulator(ARM, truth)
    dirs = {"+x": [1, 0, 0], "-y": [0, -1, 0], "+z": [0, 0, 1], "-x": [-1, 0, 0]}
    windows, start = [], 0.2
    for d in dirs.values():
        end = ramped_push(sim, start, 1.0, force * np.asarray(d, float))
        windows.append(end)
        start = end + 0.8
    res = run_control(sim.arm, None, ctrl, "tracking", "static", start, tmp)
    out = {"push F N": force, "push: ended": res.kind}
    rec = res.recording
    if rec is None:
        return out
    t = rec.t - rec.t[0]
    disp = rec.extra["ee"] - rec.extra["target"]
    for (name, d), end in zip(dirs.items(), windows, strict=True):
        w = (t > end - 0.25) & (t < end - 0.05)
        along = float(disp[w].mean(axis=0) @ np.asarray(d, float)) if w.any() else math.nan
        out[f"push {name}: displacement / (F/K)"] = along / (force / k)
    return out


def guidance(ctrl, truth, tmp, force, k) -> dict:
    sim = simulator(MOBILE, truth)
    release = ramped_push(sim, 0.3, 0.8, [force, 0.0, 0.0])
    res = run_control(sim.arm, sim.base, ctrl, "guidance", None, 3.5, tmp)
    out = {"guidance: ended": res.kind}
    rec = res.recording
    if rec is None or res.kind != "completed":
        return out
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    base = rec.extra["base"]
    speed = np.r_[0.0, np.linalg.norm(np.diff(base[:, :2], axis=0), axis=1) / np.diff(rec.t)]
    pushed = (t > release - 0.3) & (t < release - 0.1)
    out.update(
        {
            "guidance: pushed error / (F/K)": float(err[pushed].mean()) / (force / k),
            "guidance: base moved m": float(np.linalg.norm(base[-1, :2] - base[0, :2])),
            "guidance: ee back (3 mm) after s": after(t, err, release, 3e-3),
            "guidance: base stopped after s": after(t, speed, release, 2e-3),
            "guidance: final error mm": 1e3 * float(err[-1]),
        }
    )
    return out


def tracking(ctrl, truth, tmp, force, k) -> dict:
    sim = simulator(MOBILE, truth)
    release = ramped_push(sim, 0.6, 0.8, [force, 0.0, 0.0])
    res = run_control(sim.arm, sim.base, ctrl, "tracking", "circle:r=0.05,v=0.05", 3.0, tmp)
    out = {"tracking: ended": res.kind}
    rec = res.recording
    if rec is None or res.kind != "completed":
        return out
    t = rec.t - rec.t[0]
    err = np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)
    out.update(
        {
            "tracking: max error before push mm": 1e3 * float(err[(t > 0.2) & (t < 0.6)].max()),
            "tracking: ee back (3 mm) after s": after(t, err, release, 3e-3),
            "tracking: max error 1 s after mm": 1e3 * float(err[t > release + 1.0].max()),
        }
    )
    return out


# ----------------------------------------------------------------------------- main


def load() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="lock-step runs per scenario")
    parser.add_argument("--no-lockstep", action="store_true", help="skip the lock-step part")
    parser.add_argument("--realtime", type=float, default=0.0, help="s of real-time run (60)")
    parser.add_argument("--rt-priority", type=int, default=50, help="SCHED_FIFO priority, 0: off")
    parser.add_argument("--baseline-work", type=float, default=300.0, help="us (baseline loop)")
    parser.add_argument("--profile", action="store_true", help="time each part of a cycle")
    parser.add_argument("--behaviour", action="store_true", help="the controller's behaviour table")
    parser.add_argument("--core", type=int, help="pin the process to this CPU core")
    parser.add_argument("--calibration", help="a `jaxcomp calibrate` folder (params, truth)")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args()
    configure_jax_for_control()
    if args.core is not None:
        os.sched_setaffinity(0, {args.core})
    params, truth = calibrated(args.calibration)
    params = checked_arm_params(params, ARM)
    result: dict = {"load": load()}
    if not args.no_lockstep:
        result["lockstep"] = lockstep(params, truth, args.repeats)
    if args.profile:
        profile(params, truth)
    if args.realtime > 0:
        result["realtime"] = realtime(
            params, truth, args.realtime, args.rt_priority or None, args.baseline_work
        )
    if args.behaviour:
        result["behaviour"] = behaviour(params, truth)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
