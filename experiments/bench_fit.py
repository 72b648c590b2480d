"""Identification speed: the joint JAX fit against the paper's scipy fit, side by side.

Recordings come from the simulator: one clean run of the default calibration plan (the true
robot drawn from --seed, current noise off), then fresh Gaussian current noise (0.05 A) per
repetition, as the simulator adds it (a pool of ``--pool`` distinct recordings, cycled, made
before the clocks start). Printed in one run:

- one recording (~230 000 samples) on one CPU core: JAX fit time after compilation (and the
  compile time), the scipy baseline's time;
- ``--count`` recordings fitted independently: JAX ``fit_each`` on the default backend (a GPU
  when present, fed by every host core; else the one CPU core) against the scipy baseline
  looping over them on one core (measured on ``--scipy-count`` of them, per recording).

The CPU backend runs single-threaded (XLA flags) and the CPU stages run pinned to one core;
``--cores all`` lifts both.

    python experiments/bench_fit.py [--count 1000] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from contextlib import contextmanager, nullcontext

_ARGS = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
_ARGS.add_argument("--count", type=int, default=1000, help="recordings for the batch test")
_ARGS.add_argument("--scipy-count", type=int, default=20, help="recordings the baseline loops")
_ARGS.add_argument("--pool", type=int, default=64, help="distinct noisy recordings to cycle")
_ARGS.add_argument("--batch", type=int, default=None, help="fit_each batch (default: its own)")
_ARGS.add_argument("--seed", type=int, default=0)
_ARGS.add_argument("--cores", choices=["one", "all"], default="one")
_ARGS.add_argument("--json", default=None, help="also write the numbers to this JSON file")
ARGS = _ARGS.parse_args()
if ARGS.cores == "one":
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false"
        " intra_op_parallelism_threads=1"
    )

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxcomp  # noqa: E402
from jaxcomp.hardware import Simulator, TrueRobot  # noqa: E402
from jaxcomp.identify import batched_fit, joint_fit  # noqa: E402
from jaxcomp.identify.baseline import fit_baseline  # noqa: E402
from jaxcomp.identify.plan_design import default_plan  # noqa: E402
from jaxcomp.identify.recorder import record  # noqa: E402
from jaxcomp.recording import Recording  # noqa: E402

ALL_CORES = os.sched_getaffinity(0)
ACCELERATED = jax.default_backend() != "cpu"  # initialises the backends, threads unpinned
CPU = jax.devices("cpu")[0]


@contextmanager
def one_core():
    """The calling thread pinned to one core (with --cores one), on the CPU backend."""
    if ARGS.cores == "one":
        os.sched_setaffinity(0, {min(ALL_CORES)})
    try:
        with jax.default_device(CPU):
            yield
    finally:
        os.sched_setaffinity(0, ALL_CORES)


def noisy(clean: Recording, seed: int, sigma: float = 0.05) -> Recording:
    rng = np.random.default_rng(seed)
    return Recording(
        clean.t,
        clean.q,
        clean.dq,
        clean.current + sigma * rng.standard_normal(clean.current.shape),
        clean.joint,
        clean.direction,
        clean.model,
        clean.gravity,
    )


def main() -> None:
    robot = jaxcomp.load_robot("gen3_lite")
    truth = TrueRobot.draw(robot, seed=ARGS.seed, current_noise=0.0)
    sim = Simulator(robot, truth, seed=ARGS.seed)
    t = time.perf_counter()
    with sim.arm as arm:
        clean = record(
            arm,
            default_plan(robot),
            "/tmp/jaxcomp_bench_fit.npz",
            model="gen3_lite",
            progress=False,
        )
    sim_seconds = time.perf_counter() - t
    rec = noisy(clean, 1)
    pool = [noisy(clean, 1000 + k) for k in range(ARGS.pool)]

    with one_core():
        t = time.perf_counter()
        joint_fit.fit(rec)
        compile_single = time.perf_counter() - t
        single = []
        for k in range(5):
            r = noisy(clean, 10 + k)
            t = time.perf_counter()
            joint_fit.fit(r)
            single.append(time.perf_counter() - t)
        base_times = []
        for k in range(ARGS.scipy_count):
            r = pool[k % len(pool)]
            t = time.perf_counter()
            fit_baseline(r)
            base_times.append(time.perf_counter() - t)

    # --each: warm the compiled batch once, then time --count recordings
    stage = one_core() if not ACCELERATED else nullcontext()
    with stage:
        t = time.perf_counter()
        batched_fit.fit_each(pool[: ARGS.batch or 256], batch=ARGS.batch)
        compile_batch = time.perf_counter() - t
        t = time.perf_counter()
        fitted = len(
            batched_fit.fit_each((pool[k % len(pool)] for k in range(ARGS.count)), batch=ARGS.batch)
        )
        jax_total = time.perf_counter() - t

    jax_rate = fitted / jax_total
    base_rate = 1.0 / float(np.mean(base_times))
    out = {
        "machine": platform.processor() or platform.machine(),
        "cores": ARGS.cores,
        "each_backend": jax.default_backend() if ACCELERATED else "cpu",
        "each_device": str(jax.devices()[0]) if ACCELERATED else "one CPU core",
        "samples_per_recording": rec.n_samples,
        "simulate_s": sim_seconds,
        "single": {
            "jax_median_s": float(np.median(single)),
            "jax_compile_s": compile_single,
            "scipy_median_s": float(np.median(base_times)),
        },
        "batch": {
            "recordings": fitted,
            "jax_per_s": jax_rate,
            "jax_compile_s": compile_batch,
            "scipy_per_s": base_rate,
            "ratio": jax_rate / base_rate,
        },
    }
    s = out["single"]
    b = out["batch"]
    print(f"recording: {rec.n_samples} samples (default plan, simulated in {sim_seconds:.1f} s)")
    print(f"{'one recording, one CPU core':<34}{'JAX joint fit':>16}{'scipy baseline':>16}")
    print(f"{'  fit time, median (s)':<34}{s['jax_median_s']:>16.3f}{s['scipy_median_s']:>16.3f}")
    print(f"{'  compile time (s)':<34}{s['jax_compile_s']:>16.2f}{'-':>16}")
    print(f"{'many recordings (--each)':<34}{'JAX fit_each':>16}{'scipy loop':>16}")
    print(f"{'  runs on':<34}{out['each_device'][:16]:>16}{'one CPU core':>16}")
    print(f"{'  recordings per second':<34}{b['jax_per_s']:>16.2f}{b['scipy_per_s']:>16.2f}")
    print(f"{'  compile + first batch (s)':<34}{b['jax_compile_s']:>16.2f}{'-':>16}")
    print(
        f"  throughput ratio JAX / scipy: {b['ratio']:.1f}x over {fitted} recordings "
        f"(target >= 100x); scipy measured on {ARGS.scipy_count}"
    )
    if ARGS.json:
        with open(ARGS.json, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
