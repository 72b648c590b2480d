"""Throughput of the MJX simulator: world-steps per second of a batched calibration plan.

Every world is a Gen3 Lite with its own truth (paper ratios and friction x U(0.9, 1.1), COM
offsets U(+-4 mm), current noise 0.05 A) following joint sweeps at 0.5 rad/s. Prints the
backend and devices, the compile time, and world-steps/s (worlds x (settle + plan steps) per
wall second of a second, compiled run). Small numbers run on the CPU:

    python experiments/bench_mjx.py --worlds 4 --steps 200
    python experiments/bench_mjx.py --worlds 32768 --steps 5000 --devices 1 --dtype float32

``--devices N`` shards the worlds over N devices (on a CPU, force host devices first:
``XLA_FLAGS=--xla_force_host_platform_device_count=N``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import load_robot
from jaxcomp.hardware import PAPER_FRICTION, PAPER_RATIO
from jaxcomp.hardware.mjx import (
    BatchTruth,
    MjxSimulator,
    Move,
    batch_mesh,
    reference_trajectory,
)


def sweep_plan(robot, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(start (n,), q_ref (steps, n)): +-20 deg sweeps of each joint in turn about home."""
    home = robot.pose("home")
    moves = []
    while True:
        for j in range(len(home)):
            for sign in (1.0, -1.0):
                pose = home.copy()
                pose[j] += sign * np.deg2rad(20.0)
                moves.append(Move(pose, 0.5))
        q_ref = reference_trajectory(moves, home)
        if len(q_ref) >= steps:
            return home, q_ref[:steps]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=200, help="plan steps (1 ms each)")
    ap.add_argument("--settle", type=int, default=500, help="settling steps before the plan")
    ap.add_argument("--devices", type=int, default=None, help="shard over N devices")
    ap.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    ap.add_argument("--every", type=int, default=1, help="record every k-th sample")
    ap.add_argument("--chunk", type=int, default=None, help="steps per compiled call")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--no-keep",
        action="store_true",
        help="keep no recording: the samples stay on the device (with --stream: streamed)",
    )
    ap.add_argument(
        "--stream",
        action="store_true",
        help="copy each chunk's samples to the host (and drop them there), as a consumer would",
    )
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args()

    robot = load_robot("gen3_lite")
    rng = np.random.default_rng(args.seed)
    w, n, nb = args.worlds, len(PAPER_RATIO), len(robot.link_names)
    truth = BatchTruth.from_arrays(
        robot,
        np.array(PAPER_RATIO) * rng.uniform(0.9, 1.1, (w, n)),
        np.array(PAPER_FRICTION) * rng.uniform(0.9, 1.1, (w, n)),
        com_offset=rng.uniform(-0.004, 0.004, (w, nb, 3)) * (np.arange(nb) > 0)[:, None],
        current_noise=0.05,
    )
    start, q_ref = sweep_plan(robot, args.steps)
    mesh = None if args.devices is None else batch_mesh(args.devices)
    dtype = jnp.float32 if args.dtype == "float32" else jnp.float64
    sim = MjxSimulator(robot, dtype=dtype, mesh=mesh, chunk_steps=args.chunk)

    print(f"backend: {jax.default_backend()}, devices: {[str(d) for d in jax.devices()]}")
    print(f"mesh: {'none' if mesh is None else dict(mesh.shape)}, dtype: {args.dtype}")
    rec_bytes = 3 * w * -(-len(q_ref) // args.every) * n * np.dtype(args.dtype).itemsize
    print(f"worlds: {w}, plan steps: {len(q_ref)}, settle steps: {args.settle}")
    to_host = not args.no_keep or args.stream
    print(
        f"recorded: {rec_bytes / 2**30:.2f} GiB (q, dq, current every {args.every} samples), "
        f"{'copied to the host' if to_host else 'left on the device'}"
    )

    def timed() -> float:
        t0 = time.perf_counter()
        sim.run(
            truth,
            q_ref,
            start,
            settle_steps=args.settle,
            every=args.every,
            keep=not args.no_keep,
            on_chunk=(lambda first, rec: None) if args.stream else None,
        )
        return time.perf_counter() - t0

    first = timed()
    print(f"compile: {sim.compile_seconds:.1f} s (first run {first:.1f} s in all)")
    wall = timed()
    tm = sim.last_timing
    stepping = tm["settle"] + tm["plan"]
    steps = w * (args.settle + len(q_ref))
    print(
        f"run: {wall:.3f} s in all (prepare {tm['prepare']:.3f} s: truth fields, servo gains; "
        f"stepping {stepping:.3f} s)"
    )
    print(
        f"{steps / stepping:.3e} world-steps/s stepping, {steps / wall:.3e} world-steps/s "
        f"in all ({steps} world-steps)"
    )
    if args.json:
        figures = {
            "backend": jax.default_backend(),
            "devices": 1 if mesh is None else mesh.size,
            "dtype": args.dtype,
            "worlds": w,
            "plan_steps": len(q_ref),
            "every": args.every,
            "samples_to_host": to_host,
            "compile_s": sim.compile_seconds,
            "world_steps_per_s": steps / stepping,
            "world_steps_per_s_in_all": steps / wall,
        }
        Path(args.json).write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
