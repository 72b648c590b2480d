"""The joint JAX fit against the paper's scipy fit on any arm, under plans and truths drawn at
random (the protocol of a new user, on the CPU simulator).

Per arm and seed: a true robot (ratios U(0.3, 2.0) A/(N m) and friction losses U(0.15, 0.8) A,
both times the joint's ratio scale where the model states one (``plausibility.stated_scale``: the
built-in arms do; on them the bare ranges would draw currents that no such arm gives, e.g. 44 A
on the Gen3's shoulder, which the fit refuses, or friction torques its servo cannot overcome),
COM offsets N(0, 4 mm) per axis on every moving link, 0.03 A current noise) records a plan of
every joint swept from -100 to +100 deg (inside its limits) at 20 deg/s, once from the model's
rest pose and once from a pose drawn within the middle 60 % of the limits. Both fits take the
same recording. Printed per recording: the pooled gravity-current error at random poses (RMS
error over joints and poses / RMS true current), the ratio errors of the joints the JAX fit
reports as identified, and the largest |error| / std of its identified parameters.

    python experiments/fit_any_arm.py --arms gen3 wx250s --seeds 0 1 2 [--cache DIR]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.hardware import Simulator, TrueRobot
from jaxcomp.hardware.interface import HardwareFault
from jaxcomp.identify import fit as fit_recordings
from jaxcomp.identify.evaluate import gravity_current_error_batch, random_poses
from jaxcomp.identify.plan import CalibrationPlan, Sweep
from jaxcomp.identify.recorder import record
from jaxcomp.plausibility import stated_scale
from jaxcomp.recording import load_recording
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names

SWEEP = math.radians(100.0)
SPEED = math.radians(20.0)
MARGIN = math.radians(3.0)


def arm_for(name: str) -> Robot:
    """A built-in arm, or ``odd<seed>`` / ``oddc<seed>``: a generated serial arm (c: with
    continuous joints)."""
    if name.startswith("odd"):
        from odd_arms import serial_arm

        cont = name.startswith("oddc")
        seed = int(name[4:] if cont else name[3:])
        path = Path("/tmp/fit_any_arm_models") / f"{name}.xml"
        path.parent.mkdir(exist_ok=True)
        n = 5 + seed % 3
        path.write_text(
            serial_arm(seed, n=n, scale=0.6 + 0.3 * (seed % 3), continuous=(0, 2) if cont else ())
        )
        return load_robot(str(path))
    return load_robot(name)


def draw_truth(robot: Robot, seed: int) -> TrueRobot:
    rng = np.random.default_rng(1000 + seed)
    n = len(arm_joint_indices(robot))
    moved = robot.tree.moves[arm_joint_indices(robot)].any(axis=0)
    offsets = {
        link: rng.normal(0.0, 0.004, 3)
        for link, m in zip(robot.link_names, moved, strict=True)
        if m
    }
    scale, stated = stated_scale(robot)
    scale = np.where(stated, scale, 1.0)
    params = RobotParams(
        robot.name,
        scale * rng.uniform(0.3, 2.0, n),
        scale * rng.uniform(0.15, 0.8, n),
        offsets,
        method="truth",
        joints=arm_joint_names(robot),
    )
    return TrueRobot(params, 0.03, None, seed)


def user_plan(robot: Robot, seed: int) -> CalibrationPlan:
    lo, hi = robot.joint_limits[arm_joint_indices(robot)].T
    lo, hi = np.maximum(lo, -4.0), np.minimum(hi, 4.0)
    rest = robot.rest_pose
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    rng = np.random.default_rng(2000 + seed)
    other = mid + half * rng.uniform(-0.6, 0.6, len(lo))
    sweeps = []
    for hold in (rest, other):
        for j in range(len(lo)):
            a, b = max(-SWEEP, lo[j] + MARGIN), min(SWEEP, hi[j] - MARGIN)
            sweeps.append(Sweep(j, hold, a, b, SPEED))
    return CalibrationPlan(tuple(sweeps), move_speed=math.radians(40.0)).validate(robot)


def recording(arm: str, seed: int, cache: Path):
    robot = arm_for(arm)
    truth = draw_truth(robot, seed)
    path = cache / f"{arm}_{seed}.npz"
    if not path.exists():
        try:
            with Simulator(robot, truth, seed=seed).arm as sim:
                record(sim, user_plan(robot, seed), path, model=robot, progress=False)
        except HardwareFault as e:  # the drawn robot cannot follow the plan, as a real one
            return robot, truth, str(e)
    return robot, truth, load_recording(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arms", nargs="+", default=["gen3", "wx250s", "gen3_lite"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--cache", default="/tmp/fit_any_arm")
    parser.add_argument("--no-scipy", action="store_true")
    args = parser.parse_args()
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    print(
        f"{'arm':<10}{'seed':>5}{'g-err jax':>11}{'g-err scipy':>12}{'ratio err jax':>14}"
        f"{'scipy':>8}{'max |z|':>9}{'identified':>11}{'worst id.':>10}{'s':>6}"
    )
    for arm in args.arms:
        for seed in args.seeds:
            robot, truth, rec = recording(arm, seed, cache)
            if isinstance(rec, str):
                print(f"{arm:<10}{seed:>5}  fault: {rec}")
                continue
            t0 = time.perf_counter()
            fit = fit_recordings(rec, "jax")
            seconds = time.perf_counter() - t0
            fits = {"jax": fit}
            if not args.no_scipy:
                try:  # the paper's fit may give what no real arm gives: refused, shown as nan
                    fits["scipy"] = fit_recordings(rec, "scipy")
                except InputError as exc:
                    print(f"{arm:<10}{seed:>5}  scipy fit refused: {exc}")
            poses = random_poses(robot, 2000, seed)
            err = {
                name: gravity_current_error_batch(
                    robot,
                    truth.ratio[None],
                    _coms(robot, truth.params)[None],
                    p.ratio[None],
                    _coms(robot, p)[None],
                    poses,
                    pooled=True,
                )[0]
                for name, p in fits.items()
            }
            d = fit.diagnostics
            excited = np.array([e is not None and e < 0.05 for e in d["excitation"]])
            ident = np.asarray(d["ratio_identified"], bool)
            rel = np.abs(fit.ratio / truth.ratio - 1)
            z = np.abs(fit.ratio - truth.ratio) / fit.std["ratio"]
            worst = f"{100 * rel[ident].max():.2f}%" if ident.any() else "-"
            sc = fits.get("scipy")
            srel = np.nan if sc is None else np.median(np.abs(sc.ratio / truth.ratio - 1)[excited])
            print(
                f"{arm:<10}{seed:>5}{100 * err['jax']:>10.3f}%"
                f"{100 * err.get('scipy', np.nan):>11.3f}%{100 * np.median(rel[excited]):>13.2f}%"
                f"{100 * srel:>7.2f}%{z[excited].max():>9.1f}"
                f"{f'{ident.sum()}/{excited.sum()}':>11}{worst:>10}{seconds:>6.1f}"
            )
    print(
        "g-err: RMS gravity-current error over joints and 2000 random poses / RMS true; ratio "
        "err: median |relative error| over the excited joints; max |z|: largest |error| / std "
        "of an excited joint's ratio; identified: ratios reported identified / excited; worst id.: "
        "largest |relative error| of a ratio reported identified"
    )


def _coms(robot: Robot, p: RobotParams) -> np.ndarray:
    out = np.zeros((len(robot.link_names), 3))
    for link, off in p.com_offset.items():
        out[robot.link_index(link)] = off
    return out


if __name__ == "__main__":
    main()
