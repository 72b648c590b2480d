"""Benchmark: jitted JAX dynamics of the Gen3 Lite against pinocchio, on one CPU core.

Prints, side by side: one call of gravity + site Jacobian + mass matrix (median and p99 latency,
inputs already on the device and as numpy arrays) next to the same three pinocchio calls, and
vmapped gravity throughput over 10^5 poses. Run: python experiments/bench_dynamics.py

JAX runs a call synchronously on the calling thread here (``jax_cpu_enable_async_dispatch``
off), as a 1 kHz controller should: with JAX's default asynchronous CPU dispatch, XLA runs any
program it estimates at >= 1000 flops on a worker thread, and on one pinned core that hand-off
costs ~20 us per call. ``--async-dispatch`` measures JAX's default instead.
"""

import os

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pinocchio as pin  # noqa: E402

import jaxcomp  # noqa: E402
from jaxcomp import dynamics  # noqa: E402
from jaxcomp.urdf import to_urdf  # noqa: E402


def cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def latency(fn, args_list, repeats: int) -> np.ndarray:
    """Per-call wall time in microseconds over ``repeats`` calls cycling through args_list."""
    times = np.empty(repeats)
    n = len(args_list)
    for k in range(repeats):
        args = args_list[k % n]
        t0 = time.perf_counter()
        fn(*args)
        times[k] = time.perf_counter() - t0
    return times * 1e6


def compiled(fn, *args):
    """jax.jit(fn), compiled for args; returns (function, compile seconds)."""
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    jitted.lower(*args).compile()
    seconds = time.perf_counter() - t0
    jax.block_until_ready(jitted(*args))
    return jitted, seconds


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=20000, help="calls timed per variant")
    parser.add_argument("--poses", type=int, default=100_000, help="poses for the vmap figure")
    parser.add_argument(
        "--async-dispatch", action="store_true", help="keep JAX's default asynchronous dispatch"
    )
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args()
    # before the CPU backend starts (the first computation below)
    jax.config.update("jax_cpu_enable_async_dispatch", bool(args.async_dispatch))

    robot = jaxcomp.load_robot("gen3_lite")
    tree = robot.tree
    site = robot.site_index("end_effector")
    rng = np.random.default_rng(0)
    lo, hi = robot.joint_limits.T
    qs = rng.uniform(lo, hi, (256, robot.nv))
    q0 = jnp.asarray(qs[0])

    def one_pass(q):  # g + J + M of one call, as the old three-function row
        out = dynamics.kinematics_and_dynamics(tree, q, site)
        return out.gravity, out.jacobian, out.mass_matrix

    def separate(q):  # the same three quantities from the separate functions
        return (
            dynamics.gravity(tree, q),
            dynamics.site_jacobian(tree, q, site),
            dynamics.mass_matrix(tree, q),
        )

    def controller(q):  # everything the controller reads: g, J, x, R, M (a NamedTuple)
        return dynamics.kinematics_and_dynamics(tree, q, site)

    functions = {"one_pass": one_pass, "separate": separate, "controller": controller}
    jitted, compile_s = {}, {}
    for name, fn in functions.items():
        jitted[name], compile_s[name] = compiled(fn, q0)

    on_device = [(jnp.asarray(q),) for q in qs]
    as_numpy = [(q,) for q in qs]

    def timer(fn):
        def run(q):
            jax.block_until_ready(fn(q))

        return run

    for a in on_device[:50]:
        for fn in jitted.values():
            timer(fn)(*a)
    rows = {
        "jax_device_inputs": latency(timer(jitted["one_pass"]), on_device, args.repeats),
        "jax_numpy_inputs": latency(timer(jitted["one_pass"]), as_numpy, args.repeats),
        "jax_separate_functions": latency(timer(jitted["separate"]), on_device, args.repeats),
        "jax_controller_5_outputs": latency(timer(jitted["controller"]), on_device, args.repeats),
    }

    pm = pin.buildModelFromXML(to_urdf(tree))
    pd = pm.createData()
    fid = pm.getFrameId("end_effector")

    def pin_step(q):
        pin.computeGeneralizedGravity(pm, pd, q)
        pin.computeFrameJacobian(pm, pd, q, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        pin.crba(pm, pd, q)

    rows["pinocchio"] = latency(pin_step, as_numpy, args.repeats)

    gravity_batch, compile_s["gravity_vmap"] = compiled(
        jax.vmap(lambda q: dynamics.gravity(tree, q)), jnp.asarray(qs[:1])
    )
    big = jnp.asarray(rng.uniform(lo, hi, (args.poses, robot.nv)))
    jax.block_until_ready(gravity_batch(big))
    reps = []
    for _ in range(7):
        t0 = time.perf_counter()
        jax.block_until_ready(gravity_batch(big))
        reps.append(time.perf_counter() - t0)
    vmap_rate = args.poses / float(np.median(reps))

    t0 = time.perf_counter()
    for q in qs[:100].repeat(10, axis=0):
        pin.computeGeneralizedGravity(pm, pd, q)
    pin_rate = 1000 / (time.perf_counter() - t0)

    result = {
        "cpu": cpu_name(),
        "jax": jax.__version__,
        "pinocchio": pin.__version__,
        "async_dispatch": bool(args.async_dispatch),
        "compile_s": compile_s,
        "latency_us": {
            k: {"median": float(np.median(v)), "p99": float(np.percentile(v, 99))}
            for k, v in rows.items()
        },
        "gravity_poses_per_s": {"jax_vmap": vmap_rate, "pinocchio_loop": pin_rate},
    }
    mode = "asynchronous (JAX default)" if args.async_dispatch else "synchronous"
    print(f"Gen3 Lite, gravity + EE Jacobian + mass matrix, one call, one core of {result['cpu']}")
    print(f"JAX dispatch: {mode}")
    print(f"{'variant':<26}{'median us':>12}{'p99 us':>12}")
    for k, v in result["latency_us"].items():
        print(f"{k:<26}{v['median']:>12.1f}{v['p99']:>12.1f}")
    print(
        "(jax_* rows except separate_functions: dynamics.kinematics_and_dynamics; "
        "targets: median <= 40 us, p99 <= 150 us)"
    )
    print("compile s: " + ", ".join(f"{k} {v:.2f}" for k, v in compile_s.items()))
    print(f"\nGravity throughput over {args.poses} poses (median of 7)")
    print(f"{'jax vmap':<26}{vmap_rate:>14.3e} poses/s   (target >= 1e6)")
    print(f"{'pinocchio loop':<26}{pin_rate:>14.3e} poses/s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return result


if __name__ == "__main__":
    main()
