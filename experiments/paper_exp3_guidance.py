"""Paper Experiment 3 in simulation: guidance and tracking modes of the mobile manipulator.

de Wolde et al., Sections IV-B, V-C and VI-C, Fig. 1: the Gen3 Lite on the Dingo-O, the arm
under the compliant impedance controller (K_d 40 N/m, D_d 3 N s/m, end-effector error clipped
to 0.1 m; the params identified by a simulated calibration), the base following the end
effector (Eq. 20, the paper's code's gains: K_b 4 1/s up to 1 m/s, 0.01 m deadband, yaw 0.5
1/s on joint 0 beyond 10 deg). Scripted pushes stand in for the person:

- guidance (target fixed in the base frame): the end effector is pushed forward, pulled back
  and pushed to the left; the base follows while the arm is displaced, the end effector
  returns to its target and the base stops after each release;
- tracking (target in the world, on a circle of 0.4 m at 0.1 m/s): the end effector is held
  back for 2 s while the target moves on; released, it returns to the target and the base
  follows it round the circle.

The arm starts at, and holds as its nullspace posture, POSE_DEG: "preferred" with the wrist
turned (joint 3 at 90 deg, joint 4 at 45 deg), as the paper uses "a different preferred pose"
in this experiment to ease the interaction: at "preferred" itself a 3 N forward push cannot
overcome joint 1's friction (4.8 N m) and the end effector does not move. Writes
exp3_guidance.png and exp3_tracking.png (top-down world x-y of base, end effector and target,
as Fig. 1, with error and base speed over time) and exp3_guidance.json; prints displacements,
return times and base motion. The paper reports this experiment qualitatively (Fig. 1 and
its video).

    python experiments/paper_exp3_guidance.py [--seed 0] [--quick] [--params FILE --truth FILE]
        [--gains paper-k|paper|tracking] [--force 3] [--out out/paper_exp3]
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Polygon
from paper_common import (
    ARM,
    MOBILE,
    add_control_options,
    after,
    base_speed,
    calibrated,
    finish,
    impedance_gains,
    parser,
    print_table,
    ramped_push,
    save_figure,
    simulator,
    tracking_error,
)

from jaxcomp.control import make_impedance_controller
from jaxcomp.control.gains import BaseGains
from jaxcomp.control.impedance import ImpedanceController
from jaxcomp.control.loop import run_control
from jaxcomp.control.mount import ArmMount
from jaxcomp.control.run_result import ControlResult
from jaxcomp.control.trajectory import parse_trajectory
from jaxcomp.hardware import TrueRobot
from jaxcomp.recording import Recording

#: Paper Section V-C: the end-effector error is clipped to 0.1 m in this experiment.
PAPER_ERROR_CLIP = 0.1
#: Start pose and nullspace posture of this experiment, deg, joints 0..5.
POSE_DEG = (0.0, 20.0, 90.0, 90.0, 45.0, 0.0)
#: Push force of the scripted person, N (a light push: 75 mm at K_d 40 N/m).
FORCE = 3.0
#: The end effector is back when its error stays below this, m (twice the paper's 5 mm
#: tracking precision, Section VI-B); the base has stopped below STOP_SPEED m/s.
RETURN_TOL = 0.01
STOP_SPEED = 0.002
#: Tracking-mode target: circle radius m, speed m/s, one turn.
CIRCLE = "circle:r=0.4,v=0.1,turns=1"
#: Dingo-O chassis footprint half sizes, m (the model's chassis box).
FOOTPRINT = (0.32, 0.175)


class ScriptedPush(NamedTuple):
    """A scripted push along ``direction`` (world) on the end effector from ``start`` s for
    ``duration`` s, ramped up over 0.1 s (``ramped_push``); its force is set per run (N)."""

    name: str
    start: float
    duration: float
    direction: tuple[float, float, float]


def guidance_pushes(quick: bool) -> tuple[list[ScriptedPush], float]:
    """(pushes, run duration s) of the guidance scenario."""
    if quick:
        return [ScriptedPush("push forward", 0.3, 1.0, (1.0, 0.0, 0.0))], 3.5
    return [
        ScriptedPush("push forward", 0.5, 1.5, (1.0, 0.0, 0.0)),
        ScriptedPush("pull back", 5.0, 1.5, (-1.0, 0.0, 0.0)),
        ScriptedPush("push left", 9.5, 1.5, (0.0, 1.0, 0.0)),
    ], 14.0


def against_target(t: float) -> tuple[float, float, float]:
    """Unit world direction against the tracking target's motion at ``t`` s (the target
    ``run_control`` builds: CIRCLE from the end effector's start, base at the origin)."""
    mount, pose0 = ArmMount.from_model(MOBILE), np.zeros(3)
    ee0 = ARM.site_position(np.radians(POSE_DEG), "end_effector")
    traj = parse_trajectory(CIRCLE).build(mount.arm_to_world(ee0, pose0), *mount.arm_pose(pose0))
    v = traj(t).vel
    return tuple(float(x) for x in -v / np.linalg.norm(v))


def tracking_pushes(quick: bool) -> tuple[list[ScriptedPush], float]:
    """(pushes, run duration s) of the tracking scenario: the end effector is held back
    against the target's motion."""
    start, length, duration = (2.0, 1.5, 7.0) if quick else (6.0, 2.0, 26.0)
    return [ScriptedPush("hold back", start, length, against_target(start))], duration


def run_mode(
    ctrl: ImpedanceController,
    truth: TrueRobot,
    mode: str,
    pushes: list[ScriptedPush],
    force: float,
    duration: float,
    tmp: str,
) -> tuple[ControlResult, list[float]]:
    """One run of the mobile manipulator in ``mode`` from POSE_DEG with the scripted pushes;
    (result, release times s)."""
    sim = simulator(MOBILE, truth, pose=np.radians(POSE_DEG))
    releases = [
        ramped_push(sim, p.start, p.duration, force * np.asarray(p.direction)) for p in pushes
    ]
    traj = CIRCLE if mode == "tracking" else None
    start = time.perf_counter()
    res = run_control(sim.arm, sim.base, ctrl, mode, traj, duration, tmp)
    print(
        f"{mode}: {res.kind} ({res.duration:.1f} s simulated in {time.perf_counter() - start:.1f}"
        f" s), RMS error {1e3 * res.rms_error:.1f} mm"
    )
    return res, releases


def path_length(xy: np.ndarray) -> float:
    """m along a (N, 2) path."""
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())


def first_below(t: np.ndarray, values: np.ndarray, since: float, threshold: float) -> float:
    """s after ``since`` at which ``values`` first fell below ``threshold`` (inf: never)."""
    idx = np.flatnonzero((t > since) & (values < threshold))
    return float(t[idx[0]] - since) if idx.size else math.inf


def push_measures(rec: Recording, pushes: list[ScriptedPush], releases: list[float], force: float):
    """Per push: displacement and error during it, base travel, return and stop times."""
    t, err = tracking_error(rec)
    speed = base_speed(rec)
    xy = rec.extra["base"][:, :2]
    out = []
    for k, (p, release) in enumerate(zip(pushes, releases, strict=True)):
        end = pushes[k + 1].start if k + 1 < len(pushes) else math.inf
        during = (t >= p.start) & (t < release)
        held = (t > release - 0.3) & (t < release - 0.1)
        window = (t >= p.start) & (t < end)
        rest = t < end
        ended = release >= t[-1]  # the run stopped before the release: nothing to measure
        out.append(
            {
                "name": p.name,
                "force_N": force * np.asarray(p.direction),
                "start_s": p.start,
                "release_s": release,
                "displacement_m": float(err[held].mean()),
                "max_error_m": float(err[during].max()),
                "base_travel_m": path_length(xy[window]),
                "base_speed_pushed_m_per_s": float(speed[held].mean()),
                "ee_back_first_s": math.nan if ended else first_below(t, err, release, RETURN_TOL),
                "ee_back_s": math.nan if ended else after(t[rest], err[rest], release, RETURN_TOL),
                "base_stopped_s": (
                    math.nan if ended else after(t[rest], speed[rest], release, STOP_SPEED)
                ),
                "error_at_end_m": float(err[rest][-1]),
            }
        )
    return out


def run_summary(rec: Recording) -> dict:
    """Whole-run motion: base displacement, yaw, path length; target travel; final error."""
    t, err = tracking_error(rec)
    base, target = rec.extra["base"], rec.extra["target"]
    return {
        "duration_s": float(t[-1]),
        "base_displacement_m": float(np.linalg.norm(base[-1, :2] - base[0, :2])),
        "base_yaw_change_rad": float(base[-1, 2] - base[0, 2]),
        "base_path_m": path_length(base[:, :2]),
        "target_path_m": path_length(target[:, :2]),
        "ee_path_m": path_length(rec.extra["ee"][:, :2]),
        "rms_error_m": float(np.sqrt(np.mean(err**2))),
        "final_error_m": float(err[-1]),
    }


# ----------------------------------------------------------------------------- figures


def footprint(pose: np.ndarray) -> np.ndarray:
    """(4, 2) corners of the base's chassis at odometry pose (x, y, yaw), world m."""
    a, b = FOOTPRINT
    c, s = math.cos(pose[2]), math.sin(pose[2])
    corners = np.array([[a, b], [-a, b], [-a, -b], [a, -b]])
    return pose[:2] + corners @ np.array([[c, s], [-s, c]])


def plot_mode(rec: Recording, pushes, releases, force: float, title: str, path: Path) -> Path:
    """Left: top-down world x-y of base (footprints at the start, each release and the end),
    end effector (green), target (red), pushes (arrows); right: error and base speed."""
    t, err = tracking_error(rec)
    base, ee, target = rec.extra["base"], rec.extra["ee"], rec.extra["target"]
    fig, (top, series) = plt.subplots(
        1, 2, figsize=(10, 4.2), gridspec_kw={"width_ratios": [1.1, 1]}
    )
    marks = [0.0, *releases, t[-1]]
    for k, when in enumerate(marks):
        i = min(int(np.searchsorted(t, when)), len(t) - 1)
        shade = 0.25 + 0.6 * k / max(len(marks) - 1, 1)
        top.add_patch(Polygon(footprint(base[i]), fill=False, ec=str(1 - shade), lw=1))
    top.plot(base[:, 0], base[:, 1], "-", color="0.4", lw=1, label="base")
    top.plot(target[:, 0], target[:, 1], "--", color="tab:red", lw=1, label="target")
    top.plot(ee[:, 0], ee[:, 1], "-", color="tab:green", lw=1.2, label="end effector")
    for k, p in enumerate(pushes):
        i = int(np.searchsorted(t, p.start))
        d = 0.05 * force * np.asarray(p.direction)[:2]
        top.annotate(
            "",
            xy=ee[i, :2] + d,
            xytext=ee[i, :2],
            arrowprops={"arrowstyle": "->", "color": "tab:purple", "lw": 1.5},
        )
        label = ee[i, :2] + 0.5 * d + [0.0, 0.03 * (-1) ** k]
        top.text(*label, p.name, fontsize=7, color="tab:purple", ha="center")
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("world x (m)")
    top.set_ylabel("world y (m)")
    top.legend(fontsize=7, loc="best")
    top.set_title(title, fontsize=9)
    (line,) = series.plot(t, 1e3 * err, color="tab:green", lw=0.8, label="|ee - target|")
    series.set_ylabel("error (mm)")
    series.set_xlabel("t (s)")
    speed_ax = series.twinx()
    (speed_line,) = speed_ax.plot(t, base_speed(rec), color="0.4", lw=0.8, label="base speed")
    speed_ax.set_ylabel("base speed (m/s)")
    for p, release in zip(pushes, releases, strict=True):
        series.axvspan(p.start, release, color="tab:purple", alpha=0.15)
    series.axhline(1e3 * RETURN_TOL, color="k", ls=":", lw=0.8)
    series.legend(handles=[line, speed_line], fontsize=7, loc="upper right")
    series.set_title("error, base speed; pushes shaded", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> dict:
    """Run the experiment; returns the results written to exp3_guidance.json."""
    p = parser(__doc__, "out/paper_exp3")
    add_control_options(p)
    p.add_argument("--force", type=float, default=FORCE, help=f"push force N (default {FORCE})")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    params, truth = calibrated(args, out)
    gains = impedance_gains(args.gains).replace(
        error_clip=PAPER_ERROR_CLIP, posture=tuple(np.radians(POSE_DEG))
    )
    ctrl = make_impedance_controller(ARM, params, gains)
    ctrl.compile()
    print(
        f"impedance gains {args.gains}: K_d {gains.stiffness[0]:g} N/m, D_d {gains.damping[0]:g} "
        f"N s/m, error clip {gains.error_clip} m; pushes of {args.force:g} N"
    )

    results: dict = {
        "experiment": "paper Exp. 3, guidance and tracking (Sections IV-B, V-C, VI-C, Fig. 1)",
        "seed": args.seed,
        "gains": {
            "preset": args.gains,
            "stiffness_N_per_m": gains.stiffness[0],
            "damping_Ns_per_m": gains.damping[0],
            "error_clip_m": gains.error_clip,
        },
        "base_gains": vars(BaseGains()),
        "params_method": params.method,
        "return_tolerance_m": RETURN_TOL,
        "stop_speed_m_per_s": STOP_SPEED,
        "pose_deg": POSE_DEG,
    }
    scenarios = {"guidance": guidance_pushes(args.quick), "tracking": tracking_pushes(args.quick)}
    with tempfile.TemporaryDirectory() as tmp:
        for mode, (pushes, duration) in scenarios.items():
            res, releases = run_mode(ctrl, truth, mode, pushes, args.force, duration, tmp)
            rec = res.recording
            t, err = tracking_error(rec)
            first = pushes[0]
            before = (t > 0.5) & (t < first.start) if first.start > 0.5 else t < first.start
            after_push = t > releases[-1] + 3.0
            results[mode] = {
                "kind": res.kind,
                "reason": res.reason,
                "trajectory": res.trajectory,
                **run_summary(rec),
                "rms_error_before_push_m": float(np.sqrt(np.mean(err[before] ** 2))),
                "max_error_before_push_m": float(err[before].max()),
                "rms_error_3s_after_release_m": (
                    float(np.sqrt(np.mean(err[after_push] ** 2))) if after_push.any() else None
                ),
                "pushes": push_measures(rec, pushes, releases, args.force),
            }
            title = (
                "guidance: target fixed to the base (as Fig. 1, top)"
                if mode == "guidance"
                else "tracking: target on a world circle (as Fig. 1, bottom)"
            )
            plot_mode(rec, pushes, releases, args.force, title, out / f"exp3_{mode}.png")

    rows = []
    for mode in scenarios:
        for m in results[mode]["pushes"]:
            rows.append(
                [
                    f"{mode}: {m['name']}",
                    1e3 * m["displacement_m"],
                    1e3 * m["max_error_m"],
                    m["base_travel_m"],
                    m["ee_back_first_s"],
                    m["ee_back_s"],
                    m["base_stopped_s"] if mode == "guidance" else None,
                    "base follows, ee returns" + (", base stops" if mode == "guidance" else ""),
                ]
            )
    print_table(
        f"Exp. 3: scripted pushes ({args.force:g} N), gains {args.gains}",
        [
            "push",
            "displ. mm",
            "max err mm",
            "base m",
            "ee back s",
            "settled s",
            "base stop s",
            "paper (Fig. 1, video)",
        ],
        rows,
        ".3g",
    )
    g, tr = results["guidance"], results["tracking"]
    print(
        f"(ee back: first below {1e3 * RETURN_TOL:g} mm after the release; settled: stays below "
        f"it; tracking error before the push RMS {1e3 * tr['rms_error_before_push_m']:.1f} mm, "
        f"base travelled {tr['base_path_m']:.2f} m with the target's {tr['target_path_m']:.2f} m)"
    )

    hold = tr["pushes"][0]
    checks = {
        "both runs completed": g["kind"] == "completed" and tr["kind"] == "completed",
        "guidance: the base follows each push (> 5 cm)": all(
            m["base_travel_m"] > 0.05 for m in g["pushes"]
        ),
        "guidance: the end effector returns and the base stops within 3 s of each release": all(
            m["ee_back_s"] < 3.0 and m["base_stopped_s"] < 3.0 for m in g["pushes"]
        ),
        "tracking: the push moves the end effector off the target (> 3 cm)": hold["max_error_m"]
        > 0.03,
        "tracking: the end effector is back on the moving target within 3 s": hold[
            "ee_back_first_s"
        ]
        < 3.0,
        "tracking: the base follows the target round (path > half the target's)": tr["base_path_m"]
        > 0.5 * tr["target_path_m"],
    }
    return finish(out / "exp3_guidance.json", results, checks, start)


if __name__ == "__main__":
    raise SystemExit(0 if main()["ok"] else 1)
