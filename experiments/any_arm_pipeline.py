"""Any arm, end to end: calibrate in the simulator, fit, then track a circle with the params.

For every built-in arm and for arms generated here (``odd_arms``: no sites, no keyframes,
continuous joints, a coupled gripper, a branched tree, a URDF), runs exactly what a user runs::

    jaxcomp calibrate --model M --out D [--plan P]
    jaxcomp control --mode tracking --model M --params D/params.json \\
        --trajectory "circle:r=0.05,v=0.05" --duration 12

and prints, side by side: the plan's sweeps and motion time, the largest ratio error against
the simulator's truth (JAX fit and the paper's scipy fit) over the joints whose ratio the JAX
fit identifies (gravity loads them), the RMS and largest tracking
error after a 3 s settle (mm), and the wall time of each step. The arms run in parallel
processes (``--jobs``). Usage::

    python experiments/any_arm_pipeline.py [--plan default|short] [--jobs 4] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from odd_arms import serial_arm, serial_arm_urdf  # noqa: E402

CIRCLE = "circle:r=0.05,v=0.05"
SETTLE = 3.0  # s
BUILT_IN = ("gen3_lite", "gen3", "wx250s")
GENERATED = {
    "odd7_continuous.xml": lambda: serial_arm(1, n=7, continuous=(0, 2, 4, 6)),
    "odd_gripper.xml": lambda: serial_arm(2, n=6, gripper=True, scale=0.5),
    "odd_branched.xml": lambda: serial_arm(3, n=6, branched=True),
    "odd_keyframes_site.xml": lambda: serial_arm(4, n=5, keyframes=True, site=True),
    "odd6.urdf": lambda: serial_arm_urdf(5, n=6, continuous=(0, 3)),
}


def _jaxcomp(args: list[str], log: Path) -> float:
    """Run one jaxcomp command (its output to ``log``); wall time, s. Raises on failure."""
    start = time.perf_counter()
    with log.open("w") as f:
        done = subprocess.run(
            [sys.executable, "-c", "from jaxcomp.cli import main; main()", *args],
            stdout=f,
            stderr=subprocess.STDOUT,
        )
    if done.returncode != 0:
        raise RuntimeError(f"jaxcomp {args[0]} failed, see {log}:\n{log.read_text()[-2000:]}")
    return time.perf_counter() - start


def run_arm(model: str, where: Path, plan: str, duration: float) -> dict:
    """Calibrate, fit and track on one arm; the row of the table."""
    name = Path(model).stem
    cal, ctl = where / f"{name}_calibration", where / f"{name}_control"
    row: dict = {"arm": name}
    try:
        row["calibrate_s"] = _jaxcomp(
            ["calibrate", "--model", model, "--out", str(cal), "--plan", plan, "--overwrite"],
            where / f"{name}_calibrate.log",
        )
        truth = json.loads((cal / "truth.json").read_text())
        jax_fit = json.loads((cal / "params.json").read_text())
        fitted = np.array(
            [e is not None and e < 0.05 for e in jax_fit["diagnostics"]["excitation"]]
        )
        row["fitted"] = f"{int(fitted.sum())}/{fitted.size}"
        for method, file in (("jax", "params.json"), ("scipy", "params_scipy.json")):
            params = json.loads((cal / file).read_text())
            err = np.abs(np.divide(params["ratio"], truth["ratio"]) - 1)[fitted]
            row[f"ratio_error_{method}"] = float(err.max())
        args = ["control", "--mode", "tracking", "--model", model, "--params"]
        args += [str(cal / "params.json"), "--trajectory", CIRCLE, "--duration", str(duration)]
        args += ["--overwrite", "--out", str(ctl)]  # --out of an earlier run: replaced
        row["control_s"] = _jaxcomp(args, where / f"{name}_control.log")
        with np.load(ctl / "recording.npz") as rec:
            t = rec["t"] - rec["t"][0]
            err = np.linalg.norm(rec["ee"] - rec["target"], axis=1)[t >= SETTLE]
        row["rms_mm"] = 1e3 * float(np.sqrt(np.mean(err**2)))
        row["max_mm"] = 1e3 * float(err.max())
        log = (where / f"{name}_calibrate.log").read_text().splitlines()
        row["plan"] = next((line for line in log if line.startswith("plan:")), "")
    except RuntimeError as exc:
        row["failed"] = str(exc)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--plan", default="default", help="calibration plan: default | short")
    parser.add_argument("--duration", type=float, default=12.0, help="tracking run, s")
    parser.add_argument("--jobs", type=int, default=max(1, (os.cpu_count() or 2) // 2))
    parser.add_argument("--arms", nargs="*", default=None, help="only these (names or files)")
    parser.add_argument("--out", default=None, help="folder for the runs (default: temporary)")
    args = parser.parse_args()
    where = Path(args.out or tempfile.mkdtemp(prefix="any_arm_"))
    where.mkdir(parents=True, exist_ok=True)
    models = list(BUILT_IN)
    for file, make in GENERATED.items():
        (where / file).write_text(make())
        models.append(str(where / file))
    if args.arms:
        models = [m for m in models if Path(m).stem in args.arms or m in args.arms]
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda m: run_arm(m, where, args.plan, args.duration), models))
    head = (
        f"{'arm':<22}{'fitted':>7}{'ratio err JAX':>14}{'scipy':>8}{'RMS mm':>8}{'max mm':>8}"
        f"{'calibrate s':>13}{'control s':>11}  plan"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        if "failed" in r:
            print(f"{r['arm']:<22} FAILED: {r['failed'].splitlines()[-1]}")
            continue
        jax_err, scipy_err = 100 * r["ratio_error_jax"], 100 * r["ratio_error_scipy"]
        print(
            f"{r['arm']:<22}{r['fitted']:>7}{jax_err:>13.2f}%{scipy_err:>7.2f}%{r['rms_mm']:>8.2f}{r['max_mm']:>8.2f}"
            f"{r['calibrate_s']:>13.0f}{r['control_s']:>11.0f}"
            f"  {r['plan']}"
        )
    (where / "any_arm.json").write_text(json.dumps(rows, indent=2))
    print(f"runs in {where}; table in {where / 'any_arm.json'}")
    if any("failed" in r for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
