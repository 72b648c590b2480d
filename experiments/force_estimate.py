"""The external force estimate (control/external_force.py) under known simulated pushes.

The simulated Gen3 Lite (true robot of seed 0: the paper's ratios and full friction, COM
offsets of a few mm, 0.05 A of current noise) runs the impedance controller (tracking gains)
with the true params, or with ``--identified`` the params a simulated calibration fits (the
default plan, the joint fit). A constant push of 5, 10 or 15 N (ramped over 0.1 s, as a hand
does) acts on the end effector from 1.0 s for 2.0 s; the recorded ``wrench`` and
``wrench_band`` (world frame) are compared with it:

- tracking: the arm alone tracks a horizontal circle (r 0.1 m, 5 cm/s) while pushed; the
  estimate averaged over the push (after its first 0.4 s) against the force: |error| / |F|
  (target < 15 %);
- mobile: the same on the mobile manipulator, whose base carries the end effector round, so
  the arm's joints mostly rest: the estimate then reports a band;
- rest: the arm alone holding a static target with its friction compensation off (live
  gains), so static friction holds it still: the fraction of the last second of the push in
  which the applied force lies within estimate +- band (target: all of it), and the band.

Run: python experiments/force_estimate.py [--identified] [--json FILE]
"""

import os

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402

import numpy as np  # noqa: E402
from paper_common import ramped_push  # noqa: E402

from jaxcomp.control import ImpedanceGains, make_impedance_controller  # noqa: E402
from jaxcomp.control.impedance_io import live_gains  # noqa: E402
from jaxcomp.control.loop import run_control  # noqa: E402
from jaxcomp.control.mount import arm_model  # noqa: E402
from jaxcomp.control.run_link import RunLink, Tuning  # noqa: E402
from jaxcomp.hardware import Simulator, TrueRobot  # noqa: E402
from jaxcomp.plausibility import checked_arm_params  # noqa: E402
from jaxcomp.robot import load_robot  # noqa: E402

MOBILE = load_robot("mobile_gen3_lite")
GEN3_LITE = load_robot("gen3_lite")
ARM = arm_model(MOBILE)
TRUTH = TrueRobot.draw(GEN3_LITE, 0)
START, LENGTH = 1.0, 2.0  # s
DIRECTIONS = {
    "+x": (1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-y+z": (0.0, -0.6, 0.8),
    "-x+y+z": (-1.0, 1.0, 1.0),
}


def identified_params():
    """The joint fit of a simulated calibration (default plan) of the true robot."""
    from jaxcomp.identify import fit
    from jaxcomp.identify.named_plans import named_plan
    from jaxcomp.identify.recorder import record

    sim = Simulator(GEN3_LITE, TRUTH, seed=0)
    with tempfile.TemporaryDirectory() as tmp, sim.arm as arm:
        plan = named_plan(GEN3_LITE, "default")
        rec = record(arm, plan, f"{tmp}/r.npz", model=GEN3_LITE, progress=False)
    return fit([rec], "jax")


def push_run(controller, scenario: str, force: np.ndarray) -> dict:
    """One run of ``scenario`` under ``force`` (N, world); the estimate's figures."""
    mobile = scenario == "mobile"
    sim = Simulator(MOBILE if mobile else GEN3_LITE, TRUTH, seed=0)
    release = ramped_push(sim, START, LENGTH, force)
    rest = scenario == "rest"
    link = RunLink(tuning=Tuning(live_gains(400.0, 30.0, False))) if rest else None
    mode, traj = ("guidance", None) if rest else ("tracking", "circle:r=0.1,v=0.05")
    with tempfile.TemporaryDirectory() as tmp:
        res = run_control(
            sim.arm, sim.base if mobile else None, controller, mode, traj, 3.3, tmp, link=link
        )
    if res.kind != "completed":
        return {"ended": res.kind, "reason": res.reason}
    rec = res.recording
    t = rec.t - rec.t[0]
    w, b = rec.extra["wrench"], rec.extra["wrench_band"]
    pushed = (t > (release - 1.0 if rest else START + 0.4)) & (t < release - 0.05)
    mean = w[pushed].mean(0)
    inside = np.all(np.abs(w[pushed] - force) <= b[pushed], axis=1).mean()
    return {
        "ended": res.kind,
        "estimate_N": mean.round(3).tolist(),
        "error": float(np.linalg.norm(mean - force) / np.linalg.norm(force)),
        "band_N": b[pushed].mean(0).round(3).tolist(),
        "inside": float(inside),
        "mean_inside": bool(np.all(np.abs(mean - force) <= b[pushed].mean(0))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--identified", action="store_true", help="params of a simulated fit")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    params = identified_params() if args.identified else TRUTH.params
    checked = checked_arm_params(params, ARM)
    controller = make_impedance_controller(ARM, checked, ImpedanceGains.tracking())
    controller.compile()
    print(f"params: {'identified (default plan, joint fit)' if args.identified else 'true'}")
    print("| scenario | push (N) | estimate (N) | error | band (N) | F within est. +- band |")
    print("| --- | --- | --- | ---: | --- | ---: |")
    out = {}
    plan = [("tracking", m, d) for m in (5.0, 10.0, 15.0) for d in DIRECTIONS]
    plan += [("mobile", 10.0, d) for d in DIRECTIONS]
    plan += [("rest", m, d) for m in (5.0, 10.0, 15.0) for d in ("+x", "+y", "-y+z")]
    for scenario, magnitude, name in plan:
        direction = np.asarray(DIRECTIONS[name])
        force = magnitude * direction / np.linalg.norm(direction)
        r = push_run(controller, scenario, force)
        out[f"{scenario} {magnitude:g} N {name}"] = r
        label = f"{magnitude:g} {name}"
        if r["ended"] != "completed":
            print(f"| {scenario} | {label} | {r['ended']}: {r['reason'][:60]} | | | |", flush=True)
            continue
        est = ", ".join(f"{x:.2f}" for x in r["estimate_N"])
        band = ", ".join(f"{x:.2f}" for x in r["band_N"])
        print(
            f"| {scenario} | {label} | ({est}) | {100 * r['error']:.1f} % | ({band}) | "
            f"{100 * r['inside']:.0f} % |",
            flush=True,
        )
    done = {k: v for k, v in out.items() if v["ended"] == "completed"}
    track = [v["error"] for k, v in done.items() if k.startswith("tracking")]
    rest = [v["inside"] for k, v in done.items() if k.startswith("rest")]
    summary = {
        "tracking_error_max": max(track),
        "tracking_error_median": float(np.median(track)),
        "rest_inside_min": min(rest),
        "faulted": [k for k, v in out.items() if v["ended"] != "completed"],
    }
    print(
        f"tracking: error median {100 * summary['tracking_error_median']:.1f} %, max "
        f"{100 * summary['tracking_error_max']:.1f} % (target < 15 %); rest: the force within "
        f"estimate +- band in at least {100 * summary['rest_inside_min']:.0f} % of the samples"
    )
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"runs": out, "summary": summary}, f, indent=1)


if __name__ == "__main__":
    main()
