"""`jaxcomp fit --each` end to end: the joint JAX fit against the paper's scipy fit on a batch of
recordings, as a user runs it (a fresh process each, start-up and file reading included).

``--count`` recordings of the Gen3 Lite's default plan (synthetic, 1 kHz, its sweeps and the
transfers between them, fresh 0.05 A noise per recording) are written to a temp folder; then,
side by side: `jaxcomp fit --each` with the JAX fit with an empty XLA cache (cold) and again
with the cache it left (warm), and `jaxcomp fit --each --method scipy`, the last two
``--repeat`` times in turn (a busy machine slows both alike). Printed: wall seconds of each
command (median, and the range over the repeats).

    python experiments/bench_fit_each.py [--count 32] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np  # noqa: E402
import synthetic  # noqa: E402  (the tests' synthetic recordings)

from jaxcomp.identify.plan_design import default_plan  # noqa: E402
from jaxcomp.robot import load_robot  # noqa: E402
from jaxcomp.robot_params import RobotParams  # noqa: E402


def _run(args: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(args, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args[:4])} ...: {done.stderr.strip().splitlines()[-1]}")
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=32)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    robot = load_robot("gen3_lite")
    nominal = RobotParams.nominal(robot)
    rng = np.random.default_rng(0)
    truth = RobotParams(
        robot.name,
        nominal.ratio * rng.uniform(0.8, 1.2, 6),
        rng.uniform(0.3, 1.0, 6),
        {k: rng.uniform(-0.004, 0.004, 3) for k in ("ARM", "FOREARM", "LOWER_WRIST")},
    )
    plan = default_plan(robot)
    sweeps = synthetic.plan_sweeps(plan)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        files = []
        for k in range(args.count):
            rec = synthetic.recording(
                robot, truth, sweeps, noise=0.05, seed=k, transfers=plan.move_speed
            )
            files.append(str(rec.save(folder / f"rec{k:03d}.npz")))
        samples = rec.n_samples
        env = os.environ | {"JAXCOMP_CACHE": str(folder / "xla")}
        jaxcomp = [sys.executable, "-m", "jaxcomp.cli"]
        if subprocess.run([*jaxcomp, "--help"], capture_output=True).returncode != 0:
            jaxcomp = [sys.executable, "-c", "from jaxcomp.cli import main; main()"]
        out = str(folder / "each.json")
        jax_run = [*jaxcomp, "fit", *files, "--each", "--out", out]
        times = {"jax, cold cache": [_run(jax_run, env)], "jax, warm cache": [], "scipy": []}
        for _ in range(max(1, args.repeat)):
            times["jax, warm cache"].append(_run(jax_run, env))
            times["scipy"].append(_run([*jax_run, "--method", "scipy"], env))
    print(f"{args.count} recordings of {samples} samples, `jaxcomp fit --each`, end to end:")
    for name, seconds in times.items():
        spread = f"  ({min(seconds):.2f}-{max(seconds):.2f})" if len(seconds) > 1 else ""
        print(f"  {name:<16}{np.median(seconds):>7.2f} s{spread}")


if __name__ == "__main__":
    main()
