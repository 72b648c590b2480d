"""Joint-fit throughput on the default backend (a GPU when present): recordings per minute.

``--count`` recordings of the calibration plan (default: the paper's, ~230 s of sweeps),
recorded at 1 kHz / ``--every`` (10: 100 Hz, as ``jaxcomp study calibration`` records them),
each of its own true robot (``studies.truth_draw.draw_truth``: ratios and friction 20-30 % off,
COM offsets of a few mm, 0.05 A current noise). The recordings are computed from the model, as
MJX would record them in the steady part of the sweeps: q along the plan's 1 kHz reference,
current = r g_true(q) + l d + noise for the swept joint (Eq. 13, ``current.sweep_current``;
g_true: ``identify.evaluate.gravity_torque_at``, the JAX gravity model with the world's COM
offsets; generated on the device, not timed). Then, timed separately:

- moments: each recording reduced to its sweep moments on the host
  (``identify.sweep_reduction.sweep_moments_batch``, vectorized over the recordings of a block,
  blocks spread over ``--workers`` threads: numpy releases the GIL);
- fits: ``identify.batched_fit.fit_batch`` of all recordings from their moments on the device, in
  batches of ``--batch`` (default all), compile time apart; best of ``--repeats``.

Prints recordings/minute of each stage and of both together, with the errors of the fits
against the truth (a check that the fits are real). Small numbers run on the CPU:

    python experiments/bench_fit_gpu.py --count 64 --plan short
    python experiments/bench_fit_gpu.py --count 4096 [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import load_robot
from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.current import sweep_current
from jaxcomp.hardware.mjx import batch_mesh
from jaxcomp.identify.batched_fit import fit_batch
from jaxcomp.identify.evaluate import gravity_torque_at
from jaxcomp.identify.fit_model import fit_model
from jaxcomp.identify.moments import stack_worlds
from jaxcomp.identify.named_plans import named_plan
from jaxcomp.identify.sweep_reduction import sweep_moments_batch
from jaxcomp.studies.plan_signal import plan_signal, start_pose
from jaxcomp.studies.truth_draw import TruthSpread, draw_truth


def recordings(robot, truth, signal, every: int, block: int, seed: int):
    """Yield (t, q (W, R, n), dq, current, joint, direction) for blocks of ``block`` worlds:
    the model's current along the plan (see the module docstring)."""
    rec = np.arange(0, len(signal.q_ref), every)
    q = signal.q_ref[rec]
    dq = np.gradient(signal.q_ref, CONTROL_PERIOD, axis=0)[rec]
    joint, direction = signal.joint[rec], signal.direction[rec]
    n = q.shape[1]
    swept = np.zeros((len(rec), n))
    swept[np.arange(len(rec)), np.maximum(joint, 0)] = (joint >= 0) * direction
    tree, nominal = robot.tree, robot.nominal_params()
    arm = np.arange(n)

    @jax.jit
    def current(ratio, friction, com, noise, key):
        def one(r, f, c, sigma, k):
            g = gravity_torque_at(tree, nominal, arm, jnp.asarray(q), c)
            e = jax.random.normal(k, g.shape) * sigma
            return sweep_current(g, jnp.asarray(swept), r, f) + e

        return jax.vmap(one)(ratio, friction, com, noise, key)

    keys = jax.random.split(jax.random.PRNGKey(seed), truth.worlds)
    for s in range(0, truth.worlds, block):
        idx = np.minimum(np.arange(s, s + block), truth.worlds - 1)  # one shape: pad
        cur = current(
            truth.ratio[idx],
            truth.friction[idx],
            truth.com_offset[idx],
            truth.current_noise[idx],
            keys[idx],
        )
        k = min(block, truth.worlds - s)
        cur = np.asarray(cur)[:k]
        shape = (k,) + q.shape
        yield (
            (rec + 1) * CONTROL_PERIOD,
            np.broadcast_to(q, shape),
            np.broadcast_to(dq, shape),
            cur,
            joint,
            direction,
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=4096, help="recordings")
    ap.add_argument("--batch", type=int, default=None, help="fits per vmapped batch")
    ap.add_argument("--plan", default="default", help="default, short or a plan JSON file")
    ap.add_argument("--every", type=int, default=10, help="record every k-th 1 kHz sample")
    ap.add_argument("--block", type=int, default=256, help="recordings generated at once")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--devices", type=int, default=None, help="shard the fits over K devices")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--workers", type=int, default=os.cpu_count(), help="host threads for the moments"
    )
    ap.add_argument("--json", default=None, help="also write the numbers to this JSON file")
    args = ap.parse_args()
    if args.count < 1 or args.every < 1 or args.block < 1 or args.repeats < 1:
        ap.error("--count, --every, --block and --repeats must be >= 1")

    robot = load_robot("gen3_lite")
    model = fit_model(robot)
    plan = named_plan(robot, args.plan)
    signal = plan_signal(plan, start_pose(robot))
    truth = draw_truth(robot, args.count, args.seed, TruthSpread())
    mesh = batch_mesh(args.devices)
    print(f"backend: {jax.default_backend()}, devices: {[str(d) for d in mesh.devices.flat]}")
    print(
        f"{args.count} recordings of plan {args.plan!r}: {len(plan.sweeps)} sweeps, "
        f"{len(signal.q_ref) * CONTROL_PERIOD:.0f} s, "
        f"{-(-len(signal.q_ref) // args.every)} samples each "
        f"({1 / (CONTROL_PERIOD * args.every):g} Hz)"
    )

    blocks = list(recordings(robot, truth, signal, args.every, args.block, args.seed))
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max(1, args.workers)) as pool:
        parts = list(pool.map(lambda b: sweep_moments_batch(*b), blocks))
    moments_s = time.perf_counter() - t0
    moments = stack_worlds(parts)

    runs, compile_s, fit = [], 0.0, None
    for _ in range(args.repeats):
        fit = fit_batch(model, moments, batch=args.batch, mesh=mesh)
        compile_s += fit.compile_seconds
        runs.append(fit.seconds)
    best = min(runs)
    sol = fit.solution
    err = {
        "ratio_rel_rms": float(
            np.sqrt(np.mean((sol.ratio[:, 1:5] / truth.ratio[:, 1:5] - 1) ** 2))
        ),
        "friction_rms_A": float(np.sqrt(np.mean((sol.friction - truth.friction) ** 2))),
        "noise_estimate_median_A": float(np.median(sol.sigma)),
    }
    per_min = lambda seconds: 60.0 * args.count / seconds  # noqa: E731
    out = {
        "machine": platform.processor() or platform.machine(),
        "backend": jax.default_backend(),
        "devices": [str(d) for d in mesh.devices.flat],
        "count": args.count,
        "plan": args.plan,
        "samples_per_recording": int(-(-len(signal.q_ref) // args.every)),
        "batch": args.batch or args.count,
        "moment_workers": args.workers,
        "moments_s": moments_s,
        "fit_compile_s": compile_s,
        "fit_s": runs,
        "fits_per_min": per_min(best),
        "moments_per_min": per_min(moments_s),
        "end_to_end_per_min": per_min(best + moments_s),
        "converged": int(sol.converged.sum()),
        "errors": err,
    }
    print(f"compile (fit): {compile_s:.1f} s")
    print(
        f"fits on {out['backend']}: best {best:.3f} s of {args.repeats} -> "
        f"{out['fits_per_min']:.3g} recordings/min (converged {out['converged']}/{args.count})"
    )
    print(
        f"moments on the host ({args.workers} threads): {moments_s:.2f} s -> "
        f"{out['moments_per_min']:.3g} recordings/min; "
        f"both: {out['end_to_end_per_min']:.3g} recordings/min"
    )
    print(
        f"check: ratio error (joints 1-4) {100 * err['ratio_rel_rms']:.2f} % RMS, friction "
        f"{1e3 * err['friction_rms_A']:.1f} mA RMS, noise estimate "
        f"{1e3 * err['noise_estimate_median_A']:.1f} mA (truth 50 mA)"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
