"""The control study's figures: tracking.png and compliance.png, each a histogram over the
worlds and a scatter against the controller's model error (``control.model_errors``)."""

from pathlib import Path

import numpy as np

from jaxcomp.files import save_figure

#: The figures ``write_figures`` writes.
FIGURES = ("tracking.png", "compliance.png")


def write_figures(report: dict, out: Path) -> list[Path]:
    """tracking.png and compliance.png: histograms over the worlds whose phase ended before
    any fault, and scatter against the controller's model error.

    Args:
        report: the control study's report (its per_world arrays, worlds, seed, backend).
        out: the folder the figures go to.

    Returns:
        The paths written, in ``FIGURES`` order.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pw = report["per_world"]
    panels = [
        (
            FIGURES[0],
            1e3 * np.asarray(pw["tracking_rms_m"], float),
            "tracking RMS error (mm)",
            100 * np.asarray(pw["gravity_current_error_pooled"]),
            "gravity-current error of the controller's model, pooled over joints (%)",
        ),
        (
            FIGURES[1],
            np.asarray(pw["compliance_ratio"], float),
            "compliance ratio: displacement / (F / K_d)",
            100 * np.asarray(pw["ratio_error"]),
            "ratio error of the controller's model, RMS over joints (%)",
        ),
    ]
    paths = []
    for name, values, label, error, error_label in panels:
        ok = np.isfinite(values)
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
        ax0.hist(values[ok], bins=max(5, min(50, int(ok.sum() ** 0.5) * 2)), color="C0")
        ax0.set_xlabel(label)
        ax0.set_ylabel("worlds")
        ax1.scatter(error[ok], values[ok], s=6, color="C0")
        ax1.set_xlabel(error_label)
        ax1.set_ylabel(label)
        fig.suptitle(
            f"{report['worlds']} worlds, seed {report['seed']}, {report['backend']}; "
            f"{int((~ok).sum())} faulted before the end of the phase (not shown)"
        )
        fig.tight_layout()
        paths.append(save_figure(fig, out / name, dpi=120))
    return paths
