"""Paper Experiment 1 in simulation: consistency of the calibration over repeated rounds.

de Wolde et al., Sections V-A and VI-A, Figs. 11-12: the arm is calibrated R times (paper: 50);
each round records the calibration plan on the simulated Gen3 Lite (the same hidden true robot
every round: the paper's ratios and friction losses, COM offsets of a few mm; fresh current
noise of 0.05 A per round) and fits it with the joint JAX fit and the paper's scipy fit. Writes
boxplots of the identified ratio, friction loss and COM offsets with the truth marked
(exp1_ratio.png, exp1_friction.png, exp1_com.png), the estimates per round normalized by their
median (exp1_rounds.png, as the right halves of Figs. 11-12) and exp1_calibration.json; prints
mean and standard deviation per joint beside the paper's values.

The simulated motion is deterministic (lock step): rounds differ only in the current noise,
not in the drift the paper saw on the real arm (joint 1's friction, Fig. 12).

    python experiments/paper_exp1_calibration.py [--rounds 50] [--seed 0] [--short-plan]
        [--quick] [--out out/paper_exp1]
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from paper_common import (
    ARM,
    calibration_plan,
    finish,
    parser,
    print_table,
    record_calibration,
    save_figure,
)

from jaxcomp.hardware import PAPER_FRICTION, PAPER_RATIO, TrueRobot
from jaxcomp.identify import fit
from jaxcomp.identify.evaluate import gravity_current_error, random_poses
from jaxcomp.identify.fitting import METHODS
from jaxcomp.robot_params import RobotParams

#: Paper Section VI-A: every COM box (interquartile range over the 50 rounds) under 4 mm.
PAPER_COM_BOX = 0.004
#: Links of the paper's Fig. 11 (upper arm, forearm, lower wrist, upper wrist).
PAPER_LINKS = {"ARM": "ua", "FOREARM": "fa", "LOWER_WRIST": "lw", "UPPER_WRIST": "uw"}
#: Paper Section V-A: calibration rounds.
PAPER_ROUNDS = 50
#: Checks: |mean / truth - 1| of the JAX fit's ratio and friction loss, every joint (the short
#: plan's single hold per joint leaves ratio biases of up to about 1.5 %).
RATIO_TOL = 0.02
FRICTION_TOL = 0.03
#: Checks: the consistency the paper shows, std / mean of every JAX estimate.
SPREAD_TOL = 0.01


def noise_seed(seed: int, k: int) -> int:
    """Seed of round ``k``'s current noise (truth drawn from ``seed``; fewer than 1000 rounds)."""
    return 1000 * seed + k + 1


def run_rounds(truth: TrueRobot, rounds: int, short: bool, seed: int) -> list[dict]:
    """Record and fit ``rounds`` calibrations of ``truth``; per round: both methods' params
    and the seconds each step took."""
    plan = calibration_plan(short)
    poses = random_poses(ARM, 1000, seed=seed + 1)
    print(
        f"{rounds} rounds of {len(plan.sweeps)} sweeps ({plan.duration():.0f} s of motion each), "
        f"truth seed {seed}, current noise {truth.current_noise} A"
    )
    out = []
    for k in range(rounds):
        start = time.perf_counter()
        rec = record_calibration(dataclasses.replace(truth, seed=noise_seed(seed, k)), plan)
        recorded = time.perf_counter()
        fits: dict[str, RobotParams] = {m: fit(rec, m) for m in METHODS}
        row = {"record_s": recorded - start, "samples": rec.n_samples}
        for name, p in fits.items():
            row[name] = p
            row[f"{name}_fit_s"] = p.fit_seconds
            row[f"{name}_gravity_error"] = gravity_current_error(ARM, truth.params, p, poses)
        out.append(row)
        worst = {m: 100 * np.abs(fits[m].ratio / truth.ratio - 1).max() for m in METHODS}
        print(
            f"round {k + 1:>3}/{rounds}: {rec.n_samples} samples, recorded in "
            f"{row['record_s']:.1f} s, fits {row['jax_fit_s']:.2f} s (jax) "
            f"{row['scipy_fit_s']:.2f} s (scipy); worst ratio error jax {worst['jax']:.2f} %, "
            f"scipy {worst['scipy']:.2f} %"
        )
    return out


def stack(rows: list[dict], method: str, links: list[str]) -> dict[str, np.ndarray]:
    """Per-round arrays of one method: ratio, friction, phase_shift (R, n); com (R, L, 3) m."""
    fits = [r[method] for r in rows]
    return {
        "ratio": np.array([p.ratio for p in fits]),
        "friction": np.array([p.friction for p in fits]),
        "phase_shift": np.array([p.phase_shift for p in fits], dtype=float),
        "com": np.array([[p.com_offset.get(k, np.zeros(3)) for k in links] for p in fits]),
        "gravity_error": np.array([r[f"{method}_gravity_error"] for r in rows]),
    }


def iqr(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """Interquartile range (the box of a boxplot)."""
    q1, q3 = np.percentile(x, [25, 75], axis=axis)
    return q3 - q1


def summarize(est: dict[str, dict], truth: TrueRobot, links: list[str]) -> dict:
    """Mean, std, IQR per joint (ratio, friction) and per link axis (COM, m) of each method."""
    true_com = np.array([truth.params.com_offset.get(k, np.zeros(3)) for k in links])
    out = {}
    for m, e in est.items():
        out[m] = {
            **{
                f"{q}_{s}": f(e[q], axis=0)
                for q in ("ratio", "friction")
                for s, f in (("mean", np.mean), ("std", np.std), ("iqr", iqr))
            },
            "ratio_error": e["ratio"].mean(0) / truth.ratio - 1,
            "friction_error": e["friction"].mean(0) / truth.friction - 1,
            "com_mean": e["com"].mean(0),
            "com_std": e["com"].std(0),
            "com_iqr": iqr(e["com"]),
            "com_bias": e["com"].mean(0) - true_com,
            "gravity_current_error": e["gravity_error"].mean(0),
        }
    return out


# ----------------------------------------------------------------------------- figures


def plot_joint_boxes(est: dict, key: str, truth: np.ndarray, unit: str, path: Path) -> Path:
    """One panel per joint: boxplots of both methods' estimates, the truth as a red line."""
    n = truth.size
    fig, axes = plt.subplots(1, n, figsize=(2.0 * n, 3.0))
    for j, ax in enumerate(axes):
        ax.boxplot([est[m][key][:, j] for m in METHODS], widths=0.6)
        ax.set_xticks([1, 2], ["JAX", "scipy"])
        ax.axhline(truth[j], color="tab:red", ls="--", lw=1, label="truth = paper's value")
        ax.set_title(f"joint {j}", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(axis="y", useOffset=False)
    axes[0].set_ylabel(f"{key} ({unit})")
    axes[0].legend(fontsize=6, loc="best")
    rounds = est[METHODS[0]][key].shape[0]
    fig.suptitle(f"Exp. 1: identified {key} over {rounds} rounds (as paper Fig. 12)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_com(est: dict, truth: TrueRobot, links: list[str], path: Path) -> Path:
    """Boxplots of the COM estimate minus the truth (mm) for the paper's Fig. 11 links."""
    shown = [i for i, k in enumerate(links) if k in PAPER_LINKS]
    true = np.array([truth.params.com_offset.get(links[i], np.zeros(3)) for i in shown])
    labels = [f"{PAPER_LINKS[links[i]]} {a}" for i in shown for a in "xyz"]
    fig, axes = plt.subplots(1, len(METHODS), figsize=(10, 3.2), sharey=True)
    for ax, m in zip(axes, METHODS, strict=True):
        err = 1e3 * (est[m]["com"][:, shown] - true)
        ax.boxplot(err.reshape(err.shape[0], -1), widths=0.6)
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=90, fontsize=7)
        ax.axhline(0.0, color="tab:red", ls="--", lw=1)
        ax.set_title(f"{'JAX joint fit' if m == 'jax' else 'scipy (paper) fit'}", fontsize=9)
    axes[0].set_ylabel("COM estimate - truth (mm)")
    fig.suptitle("Exp. 1: COM offsets (link frame) over the rounds (as paper Fig. 11)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_rounds(est: dict, path: Path) -> Path:
    """Ratio and friction per round, normalized by their median (Figs. 11-12, right)."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.2), sharey=True)
    for ax, key in zip(axes, ("ratio", "friction"), strict=True):
        for m, style in zip(METHODS, ("-", ":"), strict=True):
            v = est[m][key]
            for j in range(v.shape[1]):
                ax.plot(
                    np.arange(1, v.shape[0] + 1),
                    v[:, j] / np.median(v[:, j]),
                    style,
                    color=f"C{j}",
                    lw=1,
                    label=f"#{j}" if m == "jax" else None,
                )
        ax.set_xlabel("calibration round")
        ax.set_title(f"{key} / median (solid: JAX, dotted: scipy)", fontsize=9)
    axes[0].set_ylabel("estimate / median")
    axes[0].legend(fontsize=7, ncol=3)
    fig.tight_layout()
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> dict:
    """Run the experiment; returns the results written to exp1_calibration.json."""
    p = parser(__doc__, "out/paper_exp1")
    p.add_argument(
        "--rounds", type=int, help=f"calibration rounds (default {PAPER_ROUNDS}; 3 quick)"
    )
    p.add_argument(
        "--short-plan", action="store_true", help="one sweep per joint (implied by --quick)"
    )
    args = p.parse_args(argv)
    rounds = args.rounds or (3 if args.quick else PAPER_ROUNDS)
    short = args.short_plan or args.quick
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    truth = TrueRobot.draw(ARM, args.seed)
    truth.save(out / "truth.json")
    rows = run_rounds(truth, rounds, short, args.seed)
    links = sorted(truth.params.com_offset, key=ARM.link_index)
    est = {m: stack(rows, m, links) for m in METHODS}
    summary = summarize(est, truth, links)

    print("\nfigures:")
    plot_joint_boxes(est, "ratio", truth.ratio, "A/(N m)", out / "exp1_ratio.png")
    plot_joint_boxes(est, "friction", truth.friction, "A", out / "exp1_friction.png")
    plot_com(est, truth, links, out / "exp1_com.png")
    plot_rounds(est, out / "exp1_rounds.png")

    jx, sp = summary["jax"], summary["scipy"]
    n = ARM.nv
    rows_r = [
        [
            f"ratio[{j}] A/(N m)",
            PAPER_RATIO[j],
            truth.ratio[j],
            f"{jx['ratio_mean'][j]:.4f} ± {jx['ratio_std'][j]:.4f}",
            f"{sp['ratio_mean'][j]:.4f} ± {sp['ratio_std'][j]:.4f}",
        ]
        for j in range(n)
    ]
    rows_l = [
        [
            f"friction[{j}] A",
            PAPER_FRICTION[j],
            truth.friction[j],
            f"{jx['friction_mean'][j]:.4f} ± {jx['friction_std'][j]:.4f}",
            f"{sp['friction_mean'][j]:.4f} ± {sp['friction_std'][j]:.4f}",
        ]
        for j in range(n)
    ]
    paper_idx = [i for i, k in enumerate(links) if k in PAPER_LINKS]
    box = {m: 1e3 * summary[m]["com_iqr"][paper_idx].max() for m in METHODS}
    print_table(
        f"Exp. 1: {rounds} rounds (paper {PAPER_ROUNDS}), mean ± std over the rounds",
        ["", "paper", "sim truth", "ours: JAX", "ours: scipy (paper's fit)"],
        rows_r
        + rows_l
        + [
            [
                "widest COM box (IQR) mm, ua fa lw uw",
                "< 4",
                "-",
                f"{box['jax']:.3f}",
                f"{box['scipy']:.3f}",
            ]
        ],
        ".4f",
    )
    print(
        "(paper: ratio and friction boxes narrow except joint 1's friction, which drifted over "
        "the rounds on the real arm)"
    )

    spread = max(np.max(jx[f"{q}_std"] / np.abs(jx[f"{q}_mean"])) for q in ("ratio", "friction"))
    checks = {
        f"JAX mean ratio within {100 * RATIO_TOL:g} % of the truth, every joint": bool(
            np.all(np.abs(jx["ratio_error"]) < RATIO_TOL)
        ),
        f"JAX mean friction within {100 * FRICTION_TOL:g} % of the truth, every joint": bool(
            np.all(np.abs(jx["friction_error"]) < FRICTION_TOL)
        ),
        f"JAX ratio and friction std below {100 * SPREAD_TOL:g} % of the mean": bool(
            spread < SPREAD_TOL
        ),
        "JAX COM boxes (IQR) narrower than the paper's 4 mm": bool(
            box["jax"] < 1e3 * PAPER_COM_BOX
        ),
    }
    results = {
        "experiment": "paper Exp. 1, calibration consistency (Sections V-A, VI-A, Figs. 11-12)",
        "rounds": rounds,
        "seed": args.seed,
        "plan": "short (1 sweep per joint)" if short else "default (14 sweeps)",
        "samples_per_round": rows[0]["samples"],
        "current_noise_A": truth.current_noise,
        "links": links,
        "truth": truth.params.to_dict(),
        "paper": {
            "ratio": PAPER_RATIO,
            "friction": PAPER_FRICTION,
            "com_box_max_m": PAPER_COM_BOX,
            "rounds": PAPER_ROUNDS,
        },
        "summary": summary,
        "rounds_data": {m: {k: v for k, v in e.items()} for m, e in est.items()},
        "seconds": {
            "record_mean": float(np.mean([r["record_s"] for r in rows])),
            **{f"{m}_fit_mean": float(np.mean([r[f"{m}_fit_s"] for r in rows])) for m in METHODS},
        },
    }
    return finish(out / "exp1_calibration.json", results, checks, start)


if __name__ == "__main__":
    raise SystemExit(0 if main()["ok"] else 1)
