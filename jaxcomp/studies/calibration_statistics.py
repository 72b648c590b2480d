"""Statistics of the calibration study's estimates over the worlds: errors per parameter,
coverage of the reported standard errors, the Cramer-Rao comparison, gravity-current errors.

Errors are in each parameter's unit (``Estimates.units``); relative errors and gravity-current
errors are fractions (0.01 = 1 %).
"""

import math
import warnings
from collections.abc import Sequence

import numpy as np

from jaxcomp.identify.evaluate import error_statistics
from jaxcomp.studies.calibration_estimates import Estimates

#: |error| < Z95 std holds 95 % of the time when the reported std are right.
Z95 = 1.96
#: Fewest determined fits of one parameter for its own coverage to count in ``worst``.
WORST_MIN_FITS = 100


def parameter_table(est: Estimates, relative: int) -> dict:
    """{parameter: {unit, identified, bias, rmse, spread, ..., coverage, spread_over_std}}
    over the worlds (``evaluate.error_statistics``); the first ``relative`` parameters
    (ratio and friction) also relative to the truth (``relative_bias``, ``relative_rmse``,
    ``relative_p95_abs``), over the fits where the data bear on it (``Estimates.determined``:
    a joint's friction counts only where its joint is swept). ``identified``: fraction of the
    fits where the data determine it.

    Args:
        est: one method's estimates of W worlds.
        relative: how many leading parameters also get relative errors (2n: ratio, friction).

    Returns:
        {parameter name: {statistic: float}}, errors in the parameter's unit, relative ones
        as fractions; ``identified`` over the fits that are ok.
    """
    err = np.where(est.determined, est.error, np.nan)
    stats = error_statistics(err, est.std)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = error_statistics(err[:, :relative] / est.truth[:, :relative])
    share = est.identified[est.ok].mean(axis=0) if est.ok.any() else np.zeros(len(est.names))
    table = {}
    for p, name in enumerate(est.names):
        row = {"unit": est.units[p], "identified": float(share[p])}
        row |= {k: float(v[p]) for k, v in stats.items()}
        if p < relative:
            row |= {f"relative_{k}": float(rel[k][p]) for k in ("bias", "rmse", "p95_abs")}
        table[name] = row
    return table


def groups(names: Sequence[str]) -> dict[str, np.ndarray]:
    """Parameter indices by kind: ratio, friction, viscous, com_offset, phase_shift.

    Args:
        names: the parameters' names ("ratio[j]", "com_offset[...]", ...).

    Returns:
        {kind: (k,) int indices into ``names``}, the kinds present only.
    """
    kinds = ("ratio", "friction", "viscous", "com_offset", "phase_shift")
    return {
        k: np.array([i for i, s in enumerate(names) if s.startswith(k + "[")], int)
        for k in kinds
        if any(s.startswith(k + "[") for s in names)
    }


def coverage_summary(est: Estimates) -> dict:
    """Coverage of +-1.96 std and moments of the z-scores error / std, pooled over the fits
    and the parameters the data determine: all of them and per kind.

    Args:
        est: one method's estimates.

    Returns:
        {"identified": pooled over every kind, "worst": ``worst_coverage``, kind: pooled},
        pooled = {count, coverage_95, z_mean, z_std} (NaN where too few).
    """

    def pooled(cols: np.ndarray | slice) -> dict:
        with np.errstate(invalid="ignore", divide="ignore"):
            z = est.error[:, cols] / est.std[:, cols]
        z = z[est.identified[:, cols] & np.isfinite(z)]
        return {
            "count": int(z.size),
            "coverage_95": float(np.mean(np.abs(z) < Z95)) if z.size else math.nan,
            "z_mean": float(np.mean(z)) if z.size else math.nan,
            "z_std": float(np.std(z, ddof=1)) if z.size > 1 else math.nan,
        }

    return {"identified": pooled(slice(None)), "worst": worst_coverage(est)} | {
        k: pooled(idx) for k, idx in groups(est.names).items()
    }


def worst_coverage(est: Estimates, min_fits: int = WORST_MIN_FITS) -> dict | None:
    """The determined parameter whose own coverage of +-1.96 std is lowest, over the
    parameters determined in at least ``min_fits`` fits: {parameter, coverage_95, count};
    None when none is.

    Args:
        est: one method's estimates.
        min_fits: fewest fits that determine a parameter for it to count.

    Returns:
        {"parameter": name, "coverage_95": fraction, "count": fits}, or None.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        z = est.error / est.std
    use = est.identified & np.isfinite(z)
    count = use.sum(axis=0)
    inside = (use & (np.abs(z) < Z95)).sum(axis=0)
    rows = np.flatnonzero(count >= min_fits)
    if not rows.size:
        return None
    p = rows[np.argmin(inside[rows] / count[rows])]
    return {
        "parameter": est.names[p],
        "coverage_95": float(inside[p] / count[p]),
        "count": int(count[p]),
    }


def cramer_rao_summary(table: dict, names: Sequence[str]) -> dict:
    """Per kind: median over the determined parameters of (empirical spread of the errors) /
    (RMS of the std the fit reported, its Cramer-Rao bound); 1 when they agree.

    Args:
        table: ``parameter_table`` of the estimates; a parameter counts where it is
            identified in more than half the fits.
        names: the parameters' names, in order.

    Returns:
        {kind: {parameters: count, median_spread_over_std, min, max}} (NaN: none).
    """
    out = {}
    for kind, idx in groups(names).items():
        rows = [table[names[i]] for i in idx if table[names[i]]["identified"] > 0.5]
        ratios = np.array([r["spread_over_std"] for r in rows], float)
        ratios = ratios[np.isfinite(ratios)]
        out[kind] = {
            "parameters": len(rows),
            "median_spread_over_std": float(np.median(ratios)) if ratios.size else math.nan,
            "min": float(ratios.min()) if ratios.size else math.nan,
            "max": float(ratios.max()) if ratios.size else math.nan,
        }
    return out


def gravity_summary(errors: np.ndarray) -> dict:
    """Per joint median, 95th percentile and max over the worlds of the relative gravity-
    current error per joint (NaN: the joint carries no gravity).

    Args:
        errors: (W, n) relative gravity-current errors, fractions (NaN: none).

    Returns:
        {"median", "p95", "max": n floats each}; empty lists for no world.
    """
    e = np.asarray(errors, float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN joints: NaN is the answer
        if not len(e):
            return {"median": [], "p95": [], "max": []}
        return {
            "median": np.nanmedian(e, axis=0).tolist(),
            "p95": np.nanpercentile(e, 95, axis=0).tolist(),
            "max": np.nanmax(e, axis=0).tolist(),
        }


def gravity_comparison(jax: Estimates, scipy: Estimates) -> dict:
    """On the worlds both fits have (the scipy sample, fits ok): how often the JAX fit's
    gravity-current error pooled over the swept joints (``Estimates.gravity_pooled``) is worse than
    the scipy fit's, and the medians of both.

    Args:
        jax: the joint fit's estimates of the scipy sample's worlds, in its order (its
            first M rows count).
        scipy: the scipy fit's estimates of those M worlds.

    Returns:
        {"worlds": count, "jax_worse_fraction", "jax_median", "scipy_median"}, errors as
        fractions (NaN: no world).
    """
    j, s = jax.gravity_pooled[: len(scipy.ok)], scipy.gravity_pooled
    both = jax.ok[: len(scipy.ok)] & scipy.ok & np.isfinite(j) & np.isfinite(s)
    j, s = j[both], s[both]
    return {
        "worlds": int(both.sum()),
        "jax_worse_fraction": float(np.mean(j > s)) if both.any() else math.nan,
        "jax_median": float(np.median(j)) if both.any() else math.nan,
        "scipy_median": float(np.median(s)) if both.any() else math.nan,
    }


def identified_ratio_error(est: Estimates, n: int) -> dict:
    """The largest |relative error| of the ratios (the first ``n`` parameters) over the fits
    that are ok and the ratios they report as identified: the value, its world and joint, and
    how many ratios count.

    Args:
        est: one method's estimates.
        n: the arm's joints (the ratios lead the parameters).

    Returns:
        {"count", "max_abs_relative": fraction, "world": row of ``est``, "joint"} (NaN and
        None when no ratio counts).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(est.estimate[:, :n] / est.truth[:, :n] - 1)
    use = est.identified[:, :n] & est.ok[:, None] & np.isfinite(rel)
    if not use.any():
        return {"count": 0, "max_abs_relative": math.nan, "world": None, "joint": None}
    w, j = np.unravel_index(int(np.argmax(np.where(use, rel, -np.inf))), rel.shape)
    return {
        "count": int(use.sum()),
        "max_abs_relative": float(rel[w, j]),
        "world": int(w),
        "joint": int(j),
    }
