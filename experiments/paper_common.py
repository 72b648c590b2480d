"""Shared set-up of the paper's experiments in simulation (``experiments/paper_exp*.py``).

de Wolde et al., Section V, reproduced on the simulated Gen3 Lite (and Dingo-O): the hidden
true robot and its calibration (the default plan recorded on ``jaxcomp.hardware.Simulator``,
fitted with the joint JAX fit, as ``jaxcomp calibrate`` does), the impedance gains presets,
fresh simulators for the control runs, the command-line options the scripts share, the JSON
output and the side-by-side table against the paper's figures.

Frames: the arm's base frame is the world for the arm alone; the mobile robot's world is the
base's odometry frame (``jaxcomp.control.loop``). Units SI: m, s, N, A, rad.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))


from jaxcomp.control import ImpedanceGains  # noqa: E402
from jaxcomp.hardware import Simulator, TrueRobot  # noqa: E402
from jaxcomp.identify import fit  # noqa: E402
from jaxcomp.identify.plan import CalibrationPlan  # noqa: E402
from jaxcomp.identify.plan_design import default_plan  # noqa: E402
from jaxcomp.identify.recorder import record  # noqa: E402
from jaxcomp.plausibility import checked_arm_params  # noqa: E402
from jaxcomp.recording import Recording  # noqa: E402
from jaxcomp.robot import Robot, load_robot  # noqa: E402
from jaxcomp.robot_params import RobotParams, json_ready, write_json_atomic  # noqa: E402

ARM = load_robot("gen3_lite")
MOBILE = load_robot("mobile_gen3_lite")

#: Impedance gains of the paper's Exp. 2 (Section V-B): K_d N/m and D_d N s/m, every axis.
PAPER_STIFFNESS = 40.0
PAPER_DAMPING = 3.0
#: Gains presets of ``impedance_gains`` (``--gains``).
GAINS_PRESETS = ("paper-k", "paper", "tracking")
#: Arm pose the control runs start from: the nullspace posture of both controllers.
START_POSE = "preferred"
#: PNG resolution of the figures, dots per inch.
DPI = 100


# ----------------------------------------------------------------------------- gains


def ramped_push(sim: Simulator, start: float, length: float, force) -> float:
    """Five pushes of force / 5, 20 ms apart (a 0.1 s ramp); returns the release time (s)."""
    for k in range(5):
        sim.push(start + 0.02 * k, length, np.asarray(force, float) / 5)
    return start + 0.08 + length


def after(t, values, release, threshold) -> float:
    """s after ``release`` at which ``values`` last exceeded ``threshold`` (inf: still at the
    end of the run)."""
    late = np.flatnonzero((t > release) & (values > threshold))
    if late.size and late[-1] == len(t) - 1:
        return math.inf
    return float(t[late[-1]] - release) if late.size else 0.0


def impedance_gains(name: str) -> ImpedanceGains:
    """The impedance gains preset ``name``.

    - ``paper-k``: the paper's K_d 40 N/m and D_d 3 N s/m (Section V-B) with the project's
      friction compensation (``ImpedanceGains.tracking``'s Eq. 16 variant: at-rest direction
      from the motion torque, t = 0.02 rad/s); the default of the experiments;
    - ``paper``: Eq. (16) as published (sign(tau) at rest, t = 0.3 rad/s), K_d 40, D_d 3: with
      the simulated arm's full friction it sticks (see ``bench_loop.py --behaviour``);
    - ``tracking``: ``ImpedanceGains.tracking()``, K_d 400 N/m, D_d 30 N s/m.
    """
    if name == "paper-k":
        return ImpedanceGains.tracking(stiffness=PAPER_STIFFNESS, damping=PAPER_DAMPING)
    return ImpedanceGains.preset(name)


# ----------------------------------------------------------------------------- calibration


def calibration_plan(short: bool = False) -> CalibrationPlan:
    """The default plan (14 sweeps, about 230 s) or, ``short``, one sweep per joint (6 sweeps,
    about 84 s; every joint then runs at one speed, so no viscous term is fitted)."""
    return default_plan(ARM, sweeps_per_joint=1 if short else 3)


def record_calibration(truth: TrueRobot, plan: CalibrationPlan) -> Recording:
    """Record ``plan`` on a fresh simulator of ``truth`` (the arm alone, lock step); the
    current noise is drawn from ``truth.seed``."""
    sim = Simulator(ARM, truth, seed=truth.seed)
    with tempfile.TemporaryDirectory() as tmp, sim.arm as arm:
        return record(arm, plan, Path(tmp) / "recording.npz", model=ARM.name, progress=False)


def calibrated(args: argparse.Namespace, out: Path) -> tuple[RobotParams, TrueRobot]:
    """(identified params of the arm, the simulated truth) for the control experiments.

    The truth is ``--truth FILE`` or drawn from ``--seed`` (the paper's ratios and friction
    losses, COM offsets of a few mm: ``TrueRobot.draw``); the params are ``--params FILE`` or
    the joint JAX fit of a calibration recorded here on that truth (``--quick``: the short
    plan). Both are written to ``out`` (params.json, truth.json).
    """
    truth = TrueRobot.load(args.truth, ARM) if args.truth else TrueRobot.draw(ARM, args.seed)
    if args.params:
        params = RobotParams.load(args.params)
        print(f"params: {args.params} ({params.method})")
    else:
        plan = calibration_plan(short=args.quick)
        start = time.perf_counter()
        print(f"calibrating the simulated arm: {len(plan.sweeps)} sweeps, {plan.duration():.0f} s")
        params = fit(record_calibration(truth, plan))
        print(f"  recorded and fitted in {time.perf_counter() - start:.0f} s")
    params = checked_arm_params(params, ARM).params
    params.save(out / "params.json")
    truth.save(out / "truth.json")
    return params, truth


# ----------------------------------------------------------------------------- simulation


def simulator(
    robot: Robot, truth: TrueRobot, pose: str | Sequence[float] = START_POSE
) -> Simulator:
    """A fresh lock-step simulator of ``truth`` on ``robot`` (arm alone or on the base),
    the arm at ``pose`` (a name or (n,) rad), with the truth's current noise."""
    true = dataclasses.replace(truth, params=dataclasses.replace(truth.params, model=robot.name))
    return Simulator(robot, true, seed=truth.seed, initial_pose=pose)


def tracking_error(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """(t (N,) s from the start, |ee - target| (N,) m, world frame) of a control recording."""
    return rec.t - rec.t[0], np.linalg.norm(rec.extra["ee"] - rec.extra["target"], axis=1)


def base_speed(rec: Recording) -> np.ndarray:
    """(N,) m/s: planar speed of the base from its recorded odometry pose."""
    base = rec.extra["base"]
    step = np.linalg.norm(np.diff(base[:, :2], axis=0), axis=1) / np.diff(rec.t)
    return np.r_[0.0, step]


# ----------------------------------------------------------------------------- command line


def parser(doc: str, out: str) -> argparse.ArgumentParser:
    """Options every experiment takes: --out, --seed, --quick."""
    p = argparse.ArgumentParser(
        description=doc.split("\n\n")[0],
        epilog=doc.split("\n\n", 1)[1] if "\n\n" in doc else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", default=out, help=f"output folder (default {out})")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated truth (default 0)")
    p.add_argument("--quick", action="store_true", help="small run for CPU / CI")
    return p


def add_control_options(p: argparse.ArgumentParser) -> None:
    """Options of the control experiments: identified params, truth, gains preset."""
    p.add_argument("--params", help="identified params JSON (default: calibrate here)")
    p.add_argument("--truth", help="true robot JSON (default: drawn from --seed)")
    p.add_argument(
        "--gains",
        choices=GAINS_PRESETS,
        default="paper-k",
        help="impedance gains preset (default paper-k: K_d 40 N/m, D_d 3 N s/m)",
    )


# ----------------------------------------------------------------------------- output


def write_results(path: Path, results: dict) -> Path:
    """Write ``results`` as JSON (atomically)."""
    return write_json_atomic(path, json_ready(results))


def save_figure(fig, path: Path) -> Path:
    """Save a figure as a small PNG and close it."""
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    print(f"  wrote {path}")
    return path


def cell(value: Any, fmt: str) -> str:
    """A table cell: numbers with ``fmt``, None and NaN as '-', strings as they are."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return value if isinstance(value, str) else format(value, fmt)


def print_table(
    title: str, header: Sequence[str], rows: Sequence[Sequence], fmt: str = ".3g"
) -> None:
    """Print a plain-text table: first column left-aligned, the others right-aligned."""
    body = [[cell(v, fmt) for v in row] for row in rows]
    widths = [max(len(str(r[i])) for r in [header, *body]) for i in range(len(header))]

    def line(r: Sequence) -> str:
        return "  ".join(
            str(v).ljust(w) if i == 0 else str(v).rjust(w)
            for i, (v, w) in enumerate(zip(r, widths, strict=True))
        )

    print(f"\n{title}")
    print(line(header))
    print("-" * (sum(widths) + 2 * (len(widths) - 1)))
    for r in body:
        print(line(r))


def finish(path: Path, results: dict, checks: dict[str, bool], start: float) -> dict:
    """Print each check (ok / FAILED), add them, ``ok`` (all passed) and the seconds since
    ``start`` (``time.perf_counter``) to ``results`` and write it as JSON to ``path``."""
    print("\nchecks:")
    for name, ok in checks.items():
        print(f"  {'ok    ' if ok else 'FAILED'} {name}")
    results.update(checks=checks, ok=all(checks.values()))
    results["seconds_total"] = time.perf_counter() - start
    write_results(path, results)
    print(f"wrote {path} ({results['seconds_total']:.0f} s in all)")
    return results
