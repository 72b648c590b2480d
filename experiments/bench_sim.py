"""Lock-step speed of the simulated Gen3 Lite, in multiples of real time (target >= 20x).

Runs on one CPU core: a current-mode controller loop (a new current command every 1 ms cycle,
as the impedance controller sends), a calibration sweep (``move_to`` at 40 deg/s recording
every state) and the bare physics step. Each workload runs ``repeats`` times, interleaved, and
prints the median and the best run, in robot time per wall-clock second and per CPU second of
the process (the speed on a core of its own: on a machine other jobs share, the wall-clock
figure also counts the time the others had the core).
Usage: ``python experiments/bench_sim.py [--seconds 10] [--repeats 3] [--json FILE]``.
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.hardware import ArmCommand, ControlMode, Simulator


def _timed(fn) -> tuple[float, float]:
    """(wall s, CPU s) of ``fn()``."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


def physics(sim: Simulator, steps: int) -> None:
    sim.step(steps)


def current_loop(sim: Simulator, steps: int) -> None:
    arm = sim.arm
    arm.set_modes(ControlMode.POSITION)
    q0 = arm.read().q
    arm.set_modes(ControlMode.CURRENT)
    c0 = arm.read().current
    r = sim.truth.ratio
    for _ in range(steps):
        s = arm.read()
        arm.cycle(ArmCommand(current=c0 + r * (20.0 * (q0 - s.q) - 0.5 * s.dq)))
    arm.set_modes(ControlMode.POSITION)


def sweep(sim: Simulator, seconds: float) -> float:
    arm = sim.arm
    records = []
    speed = np.deg2rad(40.0)
    q0 = arm.read().q
    a, b = q0.copy(), q0.copy()
    a[1] -= np.deg2rad(30.0)
    b[1] += np.deg2rad(30.0)
    arm.move_to(a, speed)
    t_sim = sim.t
    while sim.t - t_sim < seconds:
        arm.move_to(b, speed, on_state=records.append)
        arm.move_to(a, speed, on_state=records.append)
    return sim.t - t_sim


def main(seconds: float = 10.0, repeats: int = 3) -> dict:
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    steps = int(seconds / CONTROL_PERIOD)
    rows = {
        "bare physics step (Simulator.step)": [],
        "current-mode control loop (Arm.cycle)": [],
        "calibration sweep (move_to + recording)": [],
    }
    names = list(rows)
    for _ in range(repeats):
        sim = Simulator("gen3_lite", seed=0)
        wall, cpu = _timed(lambda sim=sim: physics(sim, steps))
        rows[names[0]].append((seconds / wall, seconds / cpu))
        wall, cpu = _timed(lambda sim=sim: current_loop(sim, steps))
        rows[names[1]].append((seconds / wall, seconds / cpu))
        simulated: list[float] = []
        wall, cpu = _timed(lambda sim=sim, out=simulated: out.append(sweep(sim, seconds)))
        rows[names[2]].append((simulated[0] / wall, simulated[0] / cpu))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"x real time, {repeats} runs of {seconds:g} s each (load {load:.2f})")
    print(f"{'workload':<42}{'median':>8}{'best':>8}{'per CPU s':>11}")
    for name, values in rows.items():
        v = np.array(values)
        wall, cpu = np.median(v, axis=0)
        print(f"{name:<42}{wall:>8.1f}{v[:, 0].max():>8.1f}{cpu:>11.1f}")
    ok = min(np.median(np.array(rows[n])[:, 0]) for n in names[1:]) >= 20.0
    print(f"target >= 20 x real time on one core (median): {'met' if ok else 'NOT met'}")
    return {
        "load": load,
        "x_realtime": {
            name: {
                "median": float(np.median(np.array(v)[:, 0])),
                "best": float(np.array(v)[:, 0].max()),
                "per_cpu_s": float(np.median(np.array(v)[:, 1])),
            }
            for name, v in rows.items()
        },
        "target_met": bool(ok),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="robot seconds per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each workload")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args()
    figures = main(args.seconds, args.repeats)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
