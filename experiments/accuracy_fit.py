"""Identification accuracy on the simulator: the joint JAX fit against the paper's scipy fit.

A true robot with realistic model error (the paper's ratios, 20-30 % off Kinova's nominal
ones, and friction losses; COM offsets of a few mm per axis; 0.05 A current noise; viscous
friction) runs the default calibration plan in the simulator; both methods fit the recording.
Printed side by side: the error of the predicted gravity current ratio x g(q) at random poses
(RMS, relative to the true one), and the friction-loss and ratio errors.

    python experiments/accuracy_fit.py [--seed 0] [--viscous 0.01] [--json out.json]
"""

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

import jaxcomp
from jaxcomp.hardware import Simulator, TrueRobot
from jaxcomp.identify import fit
from jaxcomp.identify.evaluate import gravity_current_error, random_poses
from jaxcomp.identify.plan_design import default_plan
from jaxcomp.identify.recorder import record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--viscous", type=float, default=0.01, help="N m s/rad, every joint")
    parser.add_argument("--poses", type=int, default=5000)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    robot = jaxcomp.load_robot("gen3_lite")
    truth = TrueRobot.draw(robot, seed=args.seed, viscous=np.full(6, args.viscous))
    with tempfile.TemporaryDirectory() as tmp, Simulator(robot, truth, seed=args.seed).arm as arm:
        rec = record(arm, default_plan(robot), Path(tmp) / "rec.npz", model="gen3_lite")
    fits = {method: fit(rec, method) for method in ("jax", "scipy")}
    poses = random_poses(robot, args.poses, seed=args.seed + 1)
    out = {"seed": args.seed, "viscous": args.viscous, "samples": rec.n_samples}
    for name, p in fits.items():
        out[name] = {
            "gravity_current_error": gravity_current_error(robot, truth.params, p, poses).tolist(),
            "friction_error": (p.friction / truth.friction - 1).tolist(),
            "ratio_error": (p.ratio / truth.ratio - 1).tolist(),
            "fit_seconds": p.fit_seconds,
        }
    print(f"{rec.n_samples} samples; truth seed {args.seed}, viscous {args.viscous} N m s/rad")
    print(
        f"{'joint':<7}"
        + "".join(
            f"{h:>14}"
            for h in (
                "g-current jax",
                "g-curr scipy",
                "friction jax",
                "fric. scipy",
                "ratio jax",
                "ratio scipy",
            )
        )
    )
    for j in range(6):
        row = [
            out[m][k][j]
            for k in ("gravity_current_error", "friction_error", "ratio_error")
            for m in ("jax", "scipy")
        ]
        print(f"{j:<7}" + "".join(f"{100 * v:>13.2f}%" for v in row))
    print(
        "g-current: RMS error of ratio x g(q) at random poses / RMS true value; joints 0 and 5 "
        "carry no gravity torque upright (nan)"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
