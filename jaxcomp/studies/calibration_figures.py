"""The calibration study's figures: estimate errors against the truth (errors.png) and the
reported standard errors against the actual scatter (coverage.png).

Inputs are the study's report and per-world arrays (``calibration.run_study``); ratio and
friction errors in % of the truth, COM offset errors in mm, gravity-current errors per joint
in % of the RMS true gravity current.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from jaxcomp.files import save_figure

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn
    from matplotlib.axes import Axes


def plot_errors(report: dict, arrays: dict, path: Path) -> Path:
    """Estimate errors against the truth per joint, JAX fit (all worlds) beside the scipy
    fit (its M worlds): ratio and friction (relative, %), gravity current (relative RMS, %),
    and the JAX fit's COM offset errors (mm) per link axis.

    Args:
        report: the study's report (study.json: worlds, seed, plan, record_rate_hz, backend).
        arrays: its worlds.npz arrays.
        path: the figure's file (its suffix the format).

    Returns:
        ``path``, written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [str(s) for s in arrays["parameter_names"]]
    n = sum(s.startswith("ratio[") for s in names)
    truth = arrays["truth"]
    ok = arrays["jax_ok"]
    # a JAX friction the data do not determine (joint never swept) is left out
    shown = np.where(arrays["jax_identified"][:, n : 2 * n], 1.0, np.nan)
    jax_rel = 100 * (arrays["jax_estimate"][ok, : 2 * n] / truth[ok, : 2 * n] - 1)
    jax_rel[:, n:] *= shown[ok]
    m = arrays["scipy_estimate"].shape[0]
    sci_rel = 100 * (arrays["scipy_estimate"] / truth[arrays["scipy_worlds"], : 2 * n] - 1)
    panels = [
        ("ratio error (%)", jax_rel[:, :n], sci_rel[:, :n]),
        ("friction loss error (%)", jax_rel[:, n:], sci_rel[:, n:]),
        (
            "gravity-current error, RMS / RMS true (%)",
            100 * arrays["jax_gravity_current_error"][ok],
            100 * arrays["scipy_gravity_current_error"],
        ),
    ]
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    for ax, (label, a, b) in zip(axes.flat, panels, strict=False):
        _paired_boxes(ax, a, b, [f"j{j}" for j in range(a.shape[1])])
        ax.set_ylabel(label)
        ax.axhline(0, color="k", lw=0.5)
    axes.flat[2].set_yscale("log")
    com = [i for i, s in enumerate(names) if s.startswith("com_offset[")]
    ax = axes.flat[3]
    err = 1e3 * (arrays["jax_estimate"][ok][:, com] - truth[ok][:, com])
    ident = arrays["jax_identified"][ok][:, com].mean(axis=0) > 0.5
    box = ax.boxplot(_columns(err), showfliers=False, patch_artist=True)
    for patch, good in zip(box["boxes"], ident, strict=True):
        patch.set_facecolor("C0" if good else "0.85")
    labels = [names[i].replace("com_offset[", "").replace("]", "") for i in com]
    ax.set_xticks(range(1, len(com) + 1), labels, rotation=90, fontsize=7)
    ax.set_ylabel("JAX COM offset error (mm)")
    ax.set_title("grey: prior-dominated (not determined by the sweeps)", fontsize=8)
    fig.suptitle(
        f"{report['worlds']} worlds (scipy: {m} of them), seed {report['seed']}, plan "
        f"{report['plan']['name']}, {report['record_rate_hz']:g} Hz, {report['backend']}"
    )
    fig.tight_layout()
    return save_figure(fig, path)


def plot_coverage(report: dict, arrays: dict, path: Path) -> Path:
    """Coverage of the reported standard errors per parameter (fraction of |error| < 1.96
    std; 0.95 expected), the Cramer-Rao comparison (empirical spread against the reported
    std, JAX fit), and the z-scores error / std of the determined parameters against N(0, 1).

    Args:
        report: the study's report (its parameter tables).
        arrays: its worlds.npz arrays.
        path: the figure's file (its suffix the format).

    Returns:
        ``path``, written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = report["jax"]["parameters"]
    names = [k for k, v in table.items() if v["identified"] > 0.5]
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(16, 4.5), gridspec_kw={"width_ratios": [3, 2, 2]})
    cov = [table[k]["coverage"] for k in names]
    a.bar(range(len(names)), cov, color="C0", label="JAX")
    sci = report["scipy"]["parameters"]
    s_cov = [sci[k]["coverage"] if k in sci else np.nan for k in names]
    a.plot(range(len(names)), s_cov, "s", color="C1", ms=4, label="scipy")
    a.axhline(0.95, color="k", lw=0.8, ls="--")
    a.set_xticks(range(len(names)), names, rotation=90, fontsize=6)
    a.set_ylim(0, 1.05)
    a.set_ylabel("coverage of +-1.96 std")
    a.legend(fontsize=7)
    spread = np.array([table[k]["spread"] for k in names], float)
    std = np.array([table[k]["std_rms"] for k in names], float)
    groups = ("ratio", "friction", "viscous", "com", "phase")
    for g, color in zip(groups, ("C0", "C1", "C2", "C3", "C4"), strict=True):
        sel = np.array([k.startswith(g) for k in names], bool)  # bool even when empty
        b.loglog(std[sel], spread[sel], "o", color=color, ms=4, label=g)
    good = np.isfinite(spread) & np.isfinite(std) & (spread > 0) & (std > 0)
    if good.any():
        lim = [min(std[good].min(), spread[good].min()), max(std[good].max(), spread[good].max())]
        b.loglog(lim, lim, "k--", lw=0.8)
    b.set_xlabel("reported std (RMS over worlds)")
    b.set_ylabel("empirical spread of the errors")
    b.set_title("Cramer-Rao comparison (JAX fit)", fontsize=9)
    b.legend(fontsize=7)
    mask = arrays["jax_identified"] & arrays["jax_ok"][:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (arrays["jax_estimate"] - arrays["truth"]) / arrays["jax_std"]
    z = z[mask & np.isfinite(z)]
    if z.size:
        c.hist(np.clip(z, -6, 6), bins=60, range=(-6, 6), density=True, color="C0")
    x = np.linspace(-6, 6, 200)
    c.plot(x, np.exp(-0.5 * x**2) / math.sqrt(2 * math.pi), "k", lw=1, label="N(0, 1)")
    c.set_xlabel("error / reported std (determined parameters, JAX)")
    c.legend(fontsize=7)
    fig.suptitle(f"Reported standard errors against the truth, {report['worlds']} worlds")
    fig.tight_layout()
    return save_figure(fig, path)


def _paired_boxes(ax: Axes, a: np.ndarray, b: np.ndarray, labels: list[str]) -> None:
    """Per column, a box of ``a`` (JAX) and one of ``b`` (scipy) side by side."""
    k = a.shape[1]
    pos = np.arange(k) * 3.0
    for data, shift, color, name in ((a, -0.5, "C0", "JAX"), (b, 0.5, "C1", "scipy")):
        if len(data):
            box = ax.boxplot(
                _columns(data),
                positions=pos + shift,
                widths=0.8,
                patch_artist=True,
                showfliers=False,
            )
            for patch in box["boxes"]:
                patch.set_facecolor(color)
            ax.plot([], [], "s", color=color, label=name)
    ax.set_xticks(pos, labels)
    ax.legend(fontsize=7)


def _columns(values: np.ndarray) -> list[np.ndarray]:
    """The finite values of each column (boxplot input)."""
    return [c[np.isfinite(c)] for c in np.asarray(values, float).T]
