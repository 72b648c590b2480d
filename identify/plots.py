"""Calibration plots (matplotlib, PNG): sweeps against the fitted models, residuals, batches.

``plot_sweeps`` draws, per joint, the measured current over the swept angle in both
directions with the current each params set predicts (the paper's Fig. 4-6), and the
residuals below; ``plot_batch`` draws boxplots of many fits normalized by their median (the
paper's Fig. 11-12).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxcomp import dynamics  # noqa: E402
from jaxcomp.current import sweep_current  # noqa: E402
from jaxcomp.files import save_figure  # noqa: E402
from jaxcomp.identify.bins import bin_sweeps  # noqa: E402
from jaxcomp.recording import Recording  # noqa: E402
from jaxcomp.robot_params import RobotParams, arm_joint_indices  # noqa: E402

_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def predicted_current(
    rec: Recording, params: RobotParams, q: np.ndarray, joint: np.ndarray, direction: np.ndarray
) -> np.ndarray:
    """Eq. (13) current of the swept joint, for ``params`` and the recording's gravity and
    payload.

    Args:
        rec: The recording (its model, gravity and payload).
        params: The params set.
        q: Poses, (B, n) rad.
        joint: The swept joint at each, (B,) int.
        direction: Its direction, (B,) +1 or -1.

    Returns:
        (B,) A.
    """
    robot = rec.robot()
    joints = arm_joint_indices(robot)
    inertial = params.inertial_params(robot)
    if rec.payload_mass > 0:
        inertial = robot.with_payload(inertial, rec.payload_mass, rec.payload_com)
    full = np.zeros((q.shape[0], robot.nv))
    full[:, joints] = q
    g = jax.vmap(lambda x: dynamics.gravity(robot.tree, x, inertial, rec.gravity))(full)
    tau = np.asarray(g)[:, joints][np.arange(q.shape[0]), joint]
    return sweep_current(tau, direction, params.ratio[joint], params.friction[joint])


def plot_sweeps(rec: Recording, fits: Mapping[str, RobotParams], path: str | Path) -> Path:
    """Per joint: measured current (bin means) and each fit's model over the swept angle
    (deg), forward and backward; residuals (A) in the row below.

    Args:
        rec: The recording.
        fits: Params sets by label.
        path: The PNG file.

    Returns:
        The path written.
    """
    bins = bin_sweeps(rec)
    joints = np.unique(bins.joint)
    fig, axes = plt.subplots(
        2,
        len(joints),
        figsize=(3.2 * len(joints), 5.5),
        squeeze=False,
        gridspec_kw={"height_ratios": [3, 1.3]},
        sharex="col",
    )
    preds = {
        k: predicted_current(rec, p, bins.q, bins.joint, bins.direction) for k, p in fits.items()
    }
    for col, j in enumerate(joints):
        top, bottom = axes[0, col], axes[1, col]
        first = bins.sweep[bins.joint == j].min()
        for d, marker in ((1, "^"), (-1, "v")):
            sel = (bins.sweep == first) & (bins.direction == d)
            angle = np.rad2deg(bins.q[sel, j])
            top.plot(
                angle,
                bins.swept_current[sel],
                marker,
                ms=2,
                color="0.4",
                label="measured" if d == 1 else None,
            )
            for (name, pred), color in zip(preds.items(), _COLORS, strict=False):
                top.plot(angle, pred[sel], "-", lw=1, color=color, label=name if d == 1 else None)
                bottom.plot(angle, bins.swept_current[sel] - pred[sel], marker, ms=1.5, color=color)
        top.set_title(f"joint {j} (first sweep)")
        bottom.set_xlabel("swept angle (deg)")
        bottom.axhline(0, color="k", lw=0.5)
    axes[0, 0].set_ylabel("current (A)")
    axes[1, 0].set_ylabel("residual (A)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Calibration sweeps: measured current and fitted models (Eq. 13)")
    fig.tight_layout()
    return save_figure(fig, path)


def plot_batch(results: Sequence[RobotParams], path: str | Path) -> Path:
    """Boxplots over many fits of the COM offsets (mm, minus their median) and of ratio and
    friction (normalized by their median), as the paper's Fig. 11-12.

    Args:
        results: The fits' params sets.
        path: The PNG file.

    Returns:
        The path written.
    """
    links = sorted({k for r in results for k in r.com_offset})
    com = np.array([[r.com_offset.get(k, np.zeros(3)) for k in links] for r in results]) * 1e3
    com = com - np.median(com, axis=0)
    ratio = np.array([r.ratio for r in results])
    friction = np.array([r.friction for r in results])
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
    labels = [f"{k} {ax}" for k in links for ax in "xyz"]
    a.boxplot(com.reshape(len(results), -1), showfliers=True)
    a.set_xticks(range(1, len(labels) + 1), labels, rotation=90, fontsize=7)
    a.set_ylabel("COM offset minus median (mm)")
    a.set_title(f"centre of mass, {len(results)} fits")
    n = ratio.shape[1]
    norm = np.concatenate([ratio / np.median(ratio, 0), friction / np.median(friction, 0)], 1)
    b.boxplot(norm, showfliers=True)
    b.set_xticks(range(1, 2 * n + 1), [f"r{j}" for j in range(n)] + [f"l{j}" for j in range(n)])
    b.set_ylabel("estimate / median")
    b.set_title("ratio r and friction loss l")
    fig.tight_layout()
    return save_figure(fig, path)
