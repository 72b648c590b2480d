"""Lock-step speed of the simulated Gen3 Lite, in multiples of real time (target >= 20x).

Runs on one CPU core: a current-mode controller loop (a new current command every 1 ms cycle,
as the impedance controller sends), a calibration sweep (``move_to`` at 40 deg/s recording
every state) and the bare physics step. Usage: ``python experiments/bench_sim.py [seconds]``.
"""

import os
import sys
import time

import numpy as np

from jaxcomp.hardware import ArmCommand, ControlMode, Simulator


def _rate(sim_seconds: float, wall: float) -> float:
    return sim_seconds / wall


def main(seconds: float = 10.0) -> None:
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    sim = Simulator("gen3_lite", seed=0)
    arm = sim.arm
    steps = int(seconds / arm.dt)

    t0 = time.perf_counter()
    sim.step(steps)
    physics = _rate(seconds, time.perf_counter() - t0)

    q0 = arm.read().q
    arm.set_modes(ControlMode.CURRENT)
    c0 = arm.read().current
    r = sim.truth.ratio
    t0 = time.perf_counter()
    for _ in range(steps):
        s = arm.read()
        arm.cycle(ArmCommand(current=c0 + r * (20.0 * (q0 - s.q) - 0.5 * s.dq)))
    current_loop = _rate(seconds, time.perf_counter() - t0)

    arm.set_modes(ControlMode.POSITION)
    records = []
    speed = np.deg2rad(40.0)
    a, b = q0.copy(), q0.copy()
    a[1] -= np.deg2rad(30.0)
    b[1] += np.deg2rad(30.0)
    arm.move_to(a, speed)
    t_sim, t0 = sim.t, time.perf_counter()
    while sim.t - t_sim < seconds:
        arm.move_to(b, speed, on_state=records.append)
        arm.move_to(a, speed, on_state=records.append)
    sweep = _rate(sim.t - t_sim, time.perf_counter() - t0)

    print(f"bare physics step (Simulator.step):        {physics:6.1f} x real time")
    print(f"current-mode control loop (Arm.cycle):     {current_loop:6.1f} x real time")
    print(f"calibration sweep (move_to + recording):   {sweep:6.1f} x real time")
    ok = min(current_loop, sweep) >= 20.0
    print(f"target >= 20 x real time on one core: {'met' if ok else 'NOT met'}")


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 10.0)
