"""Paper Experiment 2 in simulation: compliant against velocity control, rope with a spring.

de Wolde et al., Sections V-B and VI-B, Figs. 9, 10 and 13: a rope with a spring ties the end
effector to an anchor d_o = 0.145 m in front of the arm's origin; the rope is slack within
d_f = 0.260 m of the anchor and pulls with the spring's stiffness beyond. The target runs four
times over a half circle of radius d_t = 0.315 m about the arm's vertical axis at 0.101 m/s,
partly inside the free circle and partly outside. Each of the paper's three springs (0.01,
0.04, 0.12 N/mm) is run with the compliant current-based impedance controller (K_d 40 N/m,
D_d 3 N s/m, the params identified by a simulated calibration) and with the stiff Cartesian
velocity controller (the robot's default mode), plus one run of each without the rope.

The arm (alone, simulated truth with the paper's ratios and full friction losses) starts at its
nullspace posture "preferred"; the half circle and the anchor lie at the end effector's start
height, so the free space is the circle of radius d_f in that plane (Fig. 10). Writes
exp2_trajectories.png (as Fig. 13), exp2_error.png (error and rope force over time, stiff
spring), exp2_rope.json; prints the tracking-precision table beside the paper's figures.

    python experiments/paper_exp2_rope.py [--seed 0] [--quick] [--params FILE --truth FILE]
        [--gains paper-k|paper|tracking] [--springs 0.01,0.04,0.12] [--passes 4]
        [--out out/paper_exp2]
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from paper_common import (
    ARM,
    START_POSE,
    add_control_options,
    calibrated,
    finish,
    impedance_gains,
    parser,
    print_table,
    save_figure,
    simulator,
    tracking_error,
)

from jaxcomp.control import make_impedance_controller
from jaxcomp.control.impedance import ImpedanceController
from jaxcomp.control.loop import run_control
from jaxcomp.control.trajectory import Piecewise, parse_trajectory
from jaxcomp.control.velocity import VelocityController, make_velocity_controller
from jaxcomp.hardware import TrueRobot
from jaxcomp.hardware.interaction import Rope

#: Paper Section V-B / Fig. 10: free rope length d_f, target radius d_t, anchor distance d_o
#: (m), target speed v (m/s), passes over the half circle, springs (N/mm).
D_F = 0.260
D_T = 0.315
D_O = 0.145
SPEED = 0.101
PASSES = 4
SPRINGS = (0.01, 0.04, 0.12)
#: Paper Section VI-B: tracking precision inside the free circle, m (compliant "about 5 mm",
#: velocity controller "less than 1 mm").
PAPER_PRECISION = {"impedance": 0.005, "velocity": 0.001}
#: Paper Fig. 13 (a)-(d): where the end effector runs outside the free circle, as the fraction
#: of the target's excursion beyond it (1: on the target, 0: on the circle), in words.
PAPER_EXCURSION = {
    ("impedance", 0.01): "(a) close to the target",
    ("impedance", 0.04): "(b) about halfway",
    ("impedance", 0.12): "(c) close to the circle",
    ("velocity", 0.12): "(d) on the target",
}
CONTROLLERS = ("impedance", "velocity")
#: Samples whose target lies beyond the free circle by more than this fraction of the largest
#: excursion measure the end effector's excursion ratio.
FAR = 0.5


def half_circle(passes: int) -> tuple[Piecewise, float, np.ndarray]:
    """(the target trajectory in the arm frame, its lead-in duration s, the start (3,) m)."""
    start = np.asarray(ARM.site_position(ARM.pose(START_POSE), "end_effector"), dtype=float)
    traj = parse_trajectory(f"half-circle:r={D_T},v={SPEED},passes={passes}").build(start)
    lead = traj.pieces[0][1].duration if len(traj.pieces) > passes else 0.0
    return traj, lead, start


def run_one(
    ctrl: ImpedanceController | VelocityController,
    truth: TrueRobot,
    traj: Piecewise,
    rope: Rope | None,
    lead: float,
    tmp: str,
) -> dict:
    """One tracking run of the arm alone with ``rope`` (None: free) attached; the measures in
    m and N, arm frame (= world). The rope force is ``Rope.force`` (what the simulator applies)
    at each recorded end-effector position; "free" samples are those after the ``lead`` s
    lead-in whose target lies inside the free circle while the rope is slack."""
    sim = simulator(ARM, truth)
    if rope is not None:
        sim.attach_rope(rope.anchor, rope.free_length, rope.stiffness)
    start = time.perf_counter()
    res = run_control(sim.arm, None, ctrl, "tracking", traj, None, tmp)
    seconds = time.perf_counter() - start
    rec = res.recording
    t, err = tracking_error(rec)
    ee, target = rec.extra["ee"], rec.extra["target"]
    geometry = rope or Rope(np.array([D_O, 0.0, traj(0.0).pos[2]]), D_F, 0.0)
    force = np.array([np.linalg.norm(geometry.force(p)) for p in ee])
    arcs = t >= lead
    out_t = np.linalg.norm((target - geometry.anchor)[:, :2], axis=1) - D_F
    out_e = np.linalg.norm((ee - geometry.anchor)[:, :2], axis=1) - D_F
    free = arcs & (out_t < 0) & (force == 0)
    far = arcs & (out_t > FAR * out_t[arcs].max())
    return {
        "kind": res.kind,
        "reason": res.reason,
        "duration_s": res.duration,
        "cpu_s": seconds,
        "free_rms_m": float(np.sqrt(np.mean(err[free] ** 2))) if free.any() else math.nan,
        "free_max_m": float(err[free].max()) if free.any() else math.nan,
        "arcs_rms_m": float(np.sqrt(np.mean(err[arcs] ** 2))),
        "arcs_max_m": float(err[arcs].max()),
        "rope_force_max_N": float(force.max()),
        "rope_force_mean_stretched_N": float(force[force > 0].mean()) if (force > 0).any() else 0.0,
        "excursion_ratio": float(np.median(out_e[far] / out_t[far])) if far.any() else math.nan,
        "series": {"t": t, "err": err, "force": force, "ee": ee, "target": target},
    }


def ideal_ratio(k_arm: float, k_spring: float | None, controller: str) -> float:
    """Excursion ratio of two springs in series at rest: K_arm / (K_arm + k) (velocity: 1)."""
    if controller == "velocity" or not k_spring:
        return 1.0
    return k_arm / (k_arm + k_spring)


# ----------------------------------------------------------------------------- figures


def panel_label(controller: str, spring: float | None) -> str:
    """Title of one panel, with the paper's letter of Fig. 13 where there is one."""
    paper = PAPER_EXCURSION.get((controller, spring), "")
    letter = paper.split(" ")[0] + " " if paper else ""
    what = "no rope" if spring is None else f"{spring:g} N/mm"
    return f"{letter}{controller}, {what}"


def plot_trajectories(
    runs: dict, anchor: np.ndarray, springs: list, lead: float, path: Path
) -> Path:
    """Top-down x-y of target (orange) and end effector (blue) per run after the ``lead`` s
    lead-in, the free circle in black, the anchor (+) and the arm's origin (square)."""
    cols = len(springs)
    fig, axes = plt.subplots(2, cols, figsize=(2.9 * cols, 5.8), squeeze=False)
    circle = anchor[:2, None] + D_F * np.array(
        [np.cos(np.linspace(0, 2 * np.pi, 200)), np.sin(np.linspace(0, 2 * np.pi, 200))]
    )
    for row, controller in enumerate(CONTROLLERS):
        for col, spring in enumerate(springs):
            ax = axes[row, col]
            r = runs[controller][spring]["series"]
            arcs = r["t"] >= lead
            ax.plot(*circle, "k-", lw=0.8)
            ax.plot(*r["target"][arcs, :2].T, "-", color="tab:orange", lw=2.5)
            ax.plot(*r["ee"][arcs, :2].T, "-", color="tab:blue", lw=0.9)
            ax.plot(*anchor[:2], "k+", ms=6)
            ax.plot(0, 0, "ks", ms=4)
            ax.set_aspect("equal")
            ax.set_title(panel_label(controller, spring), fontsize=8)
            ax.tick_params(labelsize=6)
    for ax in axes[-1]:
        ax.set_xlabel("x (m)", fontsize=7)
    for ax in axes[:, 0]:
        ax.set_ylabel("y (m)", fontsize=7)
    fig.suptitle(
        "Exp. 2 (as paper Fig. 13), arm frame:\n"
        "target orange, end effector blue, free circle black",
        fontsize=8,
    )
    fig.tight_layout()
    return save_figure(fig, path)


def plot_error(runs: dict, spring: float, path: Path) -> Path:
    """Tracking error (mm) and rope force (N) over time of both controllers for ``spring``."""
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 4.2), sharex=True)
    for controller, color in zip(CONTROLLERS, ("tab:blue", "tab:green"), strict=True):
        s = runs[controller][spring]["series"]
        a.plot(s["t"], 1e3 * s["err"], color=color, lw=0.8, label=controller)
        b.plot(s["t"], s["force"], color=color, lw=0.8, label=controller)
    a.set_ylabel("|ee - target| (mm)")
    b.set_ylabel("rope force (N)")
    b.set_xlabel("t (s)")
    a.legend(fontsize=7)
    a.set_title(f"Exp. 2: spring {spring:g} N/mm", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> dict:
    """Run the experiment; returns the results written to exp2_rope.json."""
    p = parser(__doc__, "out/paper_exp2")
    add_control_options(p)
    p.add_argument("--springs", help="spring stiffnesses N/mm, comma-separated (default paper's)")
    p.add_argument("--passes", type=int, help=f"passes over the half circle (default {PASSES})")
    p.add_argument("--no-free", action="store_true", help="skip the runs without the rope")
    args = p.parse_args(argv)
    quick = args.quick
    springs = (
        [float(s) for s in args.springs.split(",")]
        if args.springs
        else ([max(SPRINGS)] if quick else list(SPRINGS))
    )
    passes = args.passes or (1 if quick else PASSES)
    cases = ([] if args.no_free or quick else [None]) + springs
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    params, truth = calibrated(args, out)
    gains = impedance_gains(args.gains)
    controllers = {
        "impedance": make_impedance_controller(ARM, params, gains),
        "velocity": make_velocity_controller(ARM),
    }
    controllers["impedance"].compile()
    traj, lead, ee0 = half_circle(passes)
    anchor = np.array([D_O, 0.0, ee0[2]])
    k_arm = gains.stiffness[0]
    print(f"target: {traj.description}; anchor {anchor.round(3).tolist()} m, free length {D_F} m")
    print(f"impedance gains {args.gains}: K_d {k_arm:g} N/m, D_d {gains.damping[0]:g} N s/m")

    runs: dict[str, dict] = {c: {} for c in CONTROLLERS}
    with tempfile.TemporaryDirectory() as tmp:
        for spring in cases:
            rope = None if spring is None else Rope(anchor, D_F, 1e3 * spring)
            for controller in CONTROLLERS:
                r = run_one(controllers[controller], truth, traj, rope, lead, tmp)
                r["ideal_excursion_ratio"] = ideal_ratio(k_arm, rope and rope.stiffness, controller)
                runs[controller][spring] = r
                what = "no rope" if spring is None else f"spring {spring:g} N/mm"
                print(
                    f"{controller:>9}, {what:<18} {r['kind']} ({r['duration_s']:.1f} s in "
                    f"{r['cpu_s']:.1f} s): free RMS {1e3 * r['free_rms_m']:.2f} mm, max rope "
                    f"force {r['rope_force_max_N']:.2f} N"
                )

    print("\nfigures:")
    plot_trajectories(runs, anchor, cases, lead, out / "exp2_trajectories.png")
    stiff = max(springs)
    plot_error(runs, stiff, out / "exp2_error.png")

    rows = []
    for spring in cases:
        for controller in CONTROLLERS:
            r = runs[controller][spring]
            rows.append(
                [
                    panel_label(controller, spring),
                    1e3 * r["free_rms_m"],
                    1e3 * r["free_max_m"],
                    f"{'<' if controller == 'velocity' else '~'}"
                    f"{1e3 * PAPER_PRECISION[controller]:g}",
                    r["rope_force_max_N"] if spring is not None else None,
                    r["excursion_ratio"] if spring is not None else None,
                    r["ideal_excursion_ratio"] if spring is not None else None,
                    PAPER_EXCURSION.get((controller, spring), "-").split(" ", 1)[-1],
                ]
            )
    print_table(
        f"Exp. 2: tracking precision inside the free circle ({passes} passes, gains {args.gains})",
        [
            "run",
            "RMS mm",
            "max mm",
            "paper mm",
            "max rope N",
            "excursion",
            "2 springs",
            "paper (Fig. 13)",
        ],
        rows,
        ".3g",
    )
    print(
        "(excursion: the end effector's distance beyond the free circle over the target's, where "
        "the target is far out;\n '2 springs': K_d / (K_d + k) of two springs in series at rest)"
    )

    done = all(r["kind"] == "completed" for c in runs.values() for r in c.values())
    roped = [s for s in cases if s is not None]
    imp, vel = runs["impedance"], runs["velocity"]
    order = [imp[s]["excursion_ratio"] for s in sorted(roped)]
    checks = {
        "every run completed": done,
        "compliant: lower rope force than the velocity controller, every spring": all(
            imp[s]["rope_force_max_N"] < vel[s]["rope_force_max_N"] for s in roped
        ),
        f"velocity controller: free-space RMS below the paper's "
        f"{1e3 * PAPER_PRECISION['velocity']:g} mm": all(
            vel[s]["free_rms_m"] < PAPER_PRECISION["velocity"] for s in cases
        ),
        f"compliant: free-space RMS below twice the paper's "
        f"{1e3 * PAPER_PRECISION['impedance']:g} mm": all(
            imp[s]["free_rms_m"] < 2 * PAPER_PRECISION["impedance"] for s in cases
        ),
        "velocity controller follows the target outside (excursion ratio > 0.9)": all(
            vel[s]["excursion_ratio"] > 0.9 for s in roped
        ),
        "compliant: the stiffer the spring, the nearer the circle (Fig. 13 a-c)": bool(
            np.all(np.diff(order) < 0)
        ),
    }
    results = {
        "experiment": "paper Exp. 2, rope with a spring (Sections V-B, VI-B, Figs. 9-13)",
        "seed": args.seed,
        "gains": {
            "preset": args.gains,
            "stiffness_N_per_m": k_arm,
            "damping_Ns_per_m": gains.damping[0],
        },
        "params_method": params.method,
        "geometry": {
            "free_length_m": D_F,
            "radius_m": D_T,
            "anchor_m": anchor,
            "speed_m_per_s": SPEED,
            "passes": passes,
            "lead_in_s": lead,
            "start_pose": START_POSE,
        },
        "paper": {
            "precision_m": PAPER_PRECISION,
            "springs_N_per_mm": SPRINGS,
            "excursion": {f"{c} {s:g}": v for (c, s), v in PAPER_EXCURSION.items()},
        },
        "runs": {
            c: {
                ("no_rope" if s is None else f"{s:g}_N_per_mm"): {
                    k: v for k, v in r.items() if k != "series"
                }
                for s, r in rs.items()
            }
            for c, rs in runs.items()
        },
    }
    return finish(out / "exp2_rope.json", results, checks, start)


if __name__ == "__main__":
    raise SystemExit(0 if main()["ok"] else 1)
