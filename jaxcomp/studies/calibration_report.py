"""The calibration study's report (study.json) from its per-world arrays (worlds.npz) alone.

A study runs in chunks of worlds (``study_chunks``); each chunk gives its worlds' rows of the
arrays (``WORLD_KEYS``), the scipy sample's worlds inside it (``SCIPY_KEYS``) and its run
times. ``concat_chunks`` joins them in world order and ``study_report`` computes every finding
from the joined arrays, so the report does not depend on how the worlds were chunked (or on
which process ran which chunk). Units: those of ``calibration_estimates``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from jaxcomp.studies.calibration_estimates import Estimates
from jaxcomp.studies.calibration_statistics import (
    coverage_summary,
    cramer_rao_summary,
    gravity_comparison,
    gravity_summary,
    identified_ratio_error,
    parameter_table,
)

#: Per-world arrays of worlds.npz (leading axis: the worlds, in global order).
WORLD_KEYS = (
    "plan_group",
    "truth",
    "jax_estimate",
    "jax_std",
    "jax_identified",
    "jax_converged",
    "jax_ok",
    "jax_noise_estimate",
    "jax_gravity_current_error",
    "jax_gravity_current_error_pooled",
    "swept",
    "fault_step",
)
#: Arrays of the scipy sample's worlds (leading axis: those worlds, ascending), and the fits
#: that failed (their world and message).
SCIPY_KEYS = (
    "scipy_worlds",
    "scipy_estimate",
    "scipy_std",
    "scipy_gravity_current_error",
    "scipy_gravity_current_error_pooled",
    "scipy_failed_world",
    "scipy_failed_error",
)


def concat_chunks(
    parts: Sequence[Mapping[str, Mapping[str, np.ndarray]]], names: Sequence[str], units
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """(worlds.npz arrays, summed run times s and counts) of the chunks' ``parts`` in world
    order ({"world": ..., "scipy": ..., "timing": {key: s}}, as ``ChunkStore`` keeps them);
    ``names``, ``units``: the parameters'.

    Args:
        parts: the chunks, in world order: {"world": {``WORLD_KEYS``}, "scipy":
            {``SCIPY_KEYS``}, "timing": {key: s or a count}}.
        names: the P parameters' names (``calibration_estimates.jax_parameters``).
        units: their units.

    Returns:
        (the worlds.npz arrays, with parameter_names and parameter_units; the timings summed
        over the chunks).
    """
    arrays = {"parameter_names": np.array(names), "parameter_units": np.array(units)}
    for part, keys in (("world", WORLD_KEYS), ("scipy", SCIPY_KEYS)):
        for k in keys:
            arrays[k] = np.concatenate([np.asarray(p[part][k]) for p in parts])
    timing = {k: float(sum(float(p["timing"][k]) for p in parts)) for k in parts[0]["timing"]}
    return arrays, timing


def estimates(arrays: Mapping[str, np.ndarray]) -> tuple[Estimates, Estimates, list[dict]]:
    """(JAX estimates of every world, scipy estimates of its sample, the failed scipy fits
    [{world, error}]) from worlds.npz arrays (as ``calibration_estimates`` made them).

    Args:
        arrays: the worlds.npz arrays (``concat_chunks``).

    Returns:
        (JAX ``Estimates`` (W worlds, P parameters), scipy ``Estimates`` (M worlds, ratio and
        friction), the failed scipy fits).
    """
    names, units = [str(s) for s in arrays["parameter_names"]], list(arrays["parameter_units"])
    n = arrays["swept"].shape[1]
    jax_est = Estimates(
        names=names,
        units=[str(u) for u in units],
        estimate=arrays["jax_estimate"],
        truth=arrays["truth"],
        std=arrays["jax_std"],
        identified=arrays["jax_identified"],
        ok=arrays["jax_ok"],
        gravity=arrays["jax_gravity_current_error"],
        gravity_pooled=arrays["jax_gravity_current_error_pooled"],
        swept=arrays["swept"],
    )
    worlds, est = arrays["scipy_worlds"], arrays["scipy_estimate"]
    ok = np.isfinite(est).all(axis=1) & jax_est.ok[worlds]  # as scipy_estimates has it
    cut = slice(0, 2 * n)
    scipy_est = Estimates(
        names=jax_est.names[cut],
        units=jax_est.units[cut],
        estimate=est,
        truth=jax_est.truth[worlds, cut],
        std=arrays["scipy_std"],
        identified=jax_est.identified[worlds, cut] & ok[:, None],
        ok=ok,
        gravity=arrays["scipy_gravity_current_error"],
        gravity_pooled=arrays["scipy_gravity_current_error_pooled"],
        swept=jax_est.swept[worlds],
    )
    failed = [
        {"world": int(w), "error": str(e)}
        for w, e in zip(arrays["scipy_failed_world"], arrays["scipy_failed_error"], strict=True)
    ]
    return jax_est, scipy_est, failed


def study_report(arrays: Mapping[str, np.ndarray], run: Mapping[str, Any]) -> dict:
    """study.json: the findings computed from the worlds.npz ``arrays`` only, with the run's
    description ``run`` (format, model, seed, plan, truth, backend, devices, timing_s, ...;
    ``timing_s`` must hold simulate_stepping, fit_jax_run, fit_scipy and ``world_steps`` the
    simulated world-steps) placed around them.

    Args:
        arrays: the worlds.npz arrays (``concat_chunks``).
        run: the run's description, as above (``run["plan"]["groups"]``: the plans).

    Returns:
        The report, JSON-able but for NaN: ``run`` (less timing_s and world_steps), the
        faults, both fits' findings, coverage, Cramer-Rao, timing_s and throughput.
    """
    jax_est, scipy_est, failed = estimates(arrays)
    sample, n = arrays["scipy_worlds"], arrays["swept"].shape[1]
    keep, worlds = len(sample), len(jax_est.ok)
    on_m = jax_est.rows(sample)
    jax_table = parameter_table(jax_est, 2 * n)
    scipy_table = parameter_table(scipy_est, 2 * n) if keep else {}
    sigma = arrays["jax_noise_estimate"][jax_est.ok]
    fault_step, converged = arrays["fault_step"], arrays["jax_converged"]
    timing = dict(run["timing_s"])
    head = {k: v for k, v in run.items() if k not in ("timing_s", "world_steps")}
    return head | {
        "faulted_worlds": int((fault_step >= 0).sum()),
        "faulted_by_plan": np.bincount(
            arrays["plan_group"][fault_step >= 0], minlength=len(run["plan"]["groups"])
        ).tolist(),
        "jax": {
            "converged": int(converged.sum()),
            "used": int(jax_est.ok.sum()),
            "noise_estimate_median": float(np.median(sigma)) if sigma.size else math.nan,
            "parameters": jax_table,
            "gravity_current_error": gravity_summary(
                np.where(jax_est.ok[:, None], jax_est.gravity, np.nan)
            ),
            "largest_identified_ratio_error": identified_ratio_error(jax_est, n),
            "on_scipy_worlds": {
                "parameters": {
                    k: {"rmse": v["rmse"], "relative_rmse": v.get("relative_rmse")}
                    for k, v in parameter_table(on_m, 2 * n).items()
                    if k in scipy_table
                },
                "gravity_current_error": gravity_summary(on_m.gravity[on_m.ok]),
                "pooled_gravity_current_error": gravity_comparison(on_m, scipy_est),
            },
        },
        "scipy": {
            "worlds": keep,
            "plans": len(np.unique(arrays["plan_group"][sample])),
            "failed": failed,
            "parameters": scipy_table,
            "gravity_current_error": gravity_summary(scipy_est.gravity),
        },
        "coverage": {"jax": coverage_summary(jax_est), "scipy": coverage_summary(scipy_est)},
        "cramer_rao": cramer_rao_summary(jax_table, jax_est.names),
        "timing_s": timing,
        "throughput": {
            "world_steps_per_s": run["world_steps"] / max(timing["simulate_stepping"], 1e-9),
            "jax_fits_per_min": 60.0 * worlds / max(timing["fit_jax_run"], 1e-9),
            "scipy_fits_per_min": 60.0 * keep / max(timing["fit_scipy"], 1e-9) if keep else None,
        },
    }
