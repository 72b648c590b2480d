"""A recording with a known payload cures the ratio / first-moment confounding: the spread of
each excited joint's ratio over noise repetitions against its Cramer-Rao bound.

Per arm: a true robot (ratios 0.7-1.3 x the model's scale, COM offsets U(-4, 4) mm per axis)
records the default plan twice, once plain and once carrying a known payload (0.5 kg on the Gen3
Lite and the Gen3, 0.15 kg on the WidowX, at (5, 0, 5) cm in the end-effector frame, off the
last joint's axis); synthetic recordings at 1 kHz with the transfers between the sweeps (as a
recorder makes them; ``--no-transfers``: sweeps alone) and fresh current noise (the model's) in
every repetition. Printed per arm and excited joint: the ratio error RMS over the repetitions,
the RMS of the standard error the fit reports (the Cramer-Rao bound at the estimate), their
quotient, and how often the ratio is reported identified, for the plain recording alone and for
the pair.

    python experiments/payload_cure.py [--arms gen3_lite wx250s gen3] [--reps 12] [--no-transfers]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import synthetic  # noqa: E402  (the tests' synthetic recordings)

from jaxcomp.hardware.truth import model_current_noise  # noqa: E402
from jaxcomp.identify import fit  # noqa: E402
from jaxcomp.identify.fit_solver import EXCITED  # noqa: E402
from jaxcomp.identify.plan_design import default_plan  # noqa: E402
from jaxcomp.plausibility import stated_scale  # noqa: E402
from jaxcomp.robot import load_robot  # noqa: E402
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names  # noqa: E402

PAYLOAD = {"gen3_lite": 0.5, "gen3": 0.5, "wx250s": 0.15}


def truth_of(robot, seed: int) -> RobotParams:
    """A true robot: ratios 0.7-1.3 x the model's scale, friction losses of a few % of the
    current scale, COM offsets U(-4, 4) mm per axis on every moving link."""
    rng = np.random.default_rng(seed)
    scale, _ = stated_scale(robot)
    moved = robot.tree.moves[arm_joint_indices(robot)].any(axis=0)
    links = [k for k, m in zip(robot.link_names, moved, strict=True) if m]
    return RobotParams(
        robot.name,
        scale * rng.uniform(0.7, 1.3, len(scale)),
        0.05 * scale * rng.uniform(1, 3, len(scale)),
        {k: rng.uniform(-0.004, 0.004, 3) for k in links},
        joints=arm_joint_names(robot),
    )


def _summary(p: RobotParams, truth: RobotParams) -> tuple[np.ndarray, ...]:
    d = p.diagnostics
    excited = [e is not None and e < EXCITED for e in d["excitation"]]
    return (
        p.ratio / truth.ratio - 1,
        np.asarray(p.std["ratio"]) / truth.ratio,
        np.asarray(d["ratio_identified"], bool),
        np.asarray(excited),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arms", nargs="+", default=["gen3_lite", "wx250s", "gen3"])
    parser.add_argument("--reps", type=int, default=12)
    parser.add_argument("--no-transfers", action="store_true", help="record the sweeps alone")
    args = parser.parse_args()
    print(
        f"{'arm':<10}{'joint':<16}{'fit':<7}{'err RMS %':>10}{'CRB RMS %':>10}{'err/CRB':>9}"
        f"{'identified':>12}"
    )
    for arm in args.arms:
        robot = load_robot(arm)
        truth = truth_of(robot, 7)
        plan = default_plan(robot)
        sweeps = synthetic.plan_sweeps(plan)
        moves = 0.0 if args.no_transfers else plan.move_speed
        noise = model_current_noise(robot)
        mass = PAYLOAD.get(arm, 0.3)
        rows: dict[str, list] = {"alone": [], "pair": []}
        t0 = time.perf_counter()
        for rep in range(args.reps):
            plain = synthetic.recording(
                robot, truth, sweeps, noise=noise, seed=2 * rep, transfers=moves
            )
            loaded = synthetic.recording(
                robot,
                truth,
                sweeps,
                noise=noise,
                seed=2 * rep + 1,
                payload_mass=mass,
                payload_com=(0.05, 0.0, 0.05),
                transfers=moves,
            )
            rows["alone"].append(_summary(fit(plain), truth))
            rows["pair"].append(_summary(fit([plain, loaded]), truth))
        joints = arm_joint_names(robot)
        for name, got in rows.items():
            err, std, ident, excited = (np.array(x) for x in zip(*got, strict=True))
            for j in np.flatnonzero(excited.all(axis=0)):
                e, s = np.sqrt(np.mean(err[:, j] ** 2)), np.sqrt(np.mean(std[:, j] ** 2))
                print(
                    f"{arm:<10}{joints[j]:<16}{name:<7}{100 * e:>10.3f}{100 * s:>10.3f}"
                    f"{e / s:>9.2f}{ident[:, j].mean():>12.0%}"
                )
        seconds = time.perf_counter() - t0
        print(f"({arm}: {args.reps} repetitions, {seconds:.0f} s, noise {noise} A)")


if __name__ == "__main__":
    main()
