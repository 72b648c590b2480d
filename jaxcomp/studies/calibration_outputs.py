"""The calibration study's outputs: its files written into the report folder, the study run
into that folder in one call (``study_into``), and its few lines for people (``summary``).

The folder holds study.json (the report, ``calibration_report``), worlds.npz (the per-world
arrays), errors.png and coverage.png (``calibration_figures``), and, while the study runs, its
finished chunks (``study_chunks``) and the kept worlds' recordings (``calibration.SAMPLES_DIR``).
"""

import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import NamedTuple, Unpack

import numpy as np

from jaxcomp.files import writing
from jaxcomp.robot_params import json_ready, write_json_atomic
from jaxcomp.studies.calibration import run_study
from jaxcomp.studies.calibration_figures import plot_coverage, plot_errors
from jaxcomp.studies.calibration_settings import CalibrationSettings
from jaxcomp.studies.study_chunks import StudyOptions, into_folder

__all__ = ["FIGURES", "STUDY_FILE", "WORLDS_FILE", "StudyOutputs", "study_into", "summary",
           "write_outputs"]  # fmt: skip

STUDY_FILE = "study.json"
WORLDS_FILE = "worlds.npz"
FIGURES = ("errors.png", "coverage.png")


# ----------------------------------------------------------------------------- the files
def write_outputs(out: Path, report: dict, arrays: dict) -> list[Path]:
    """Write the figures, ``worlds.npz`` and ``study.json`` (last) into ``out``.

    Everything is written to a staging folder inside ``out`` first and moved in by
    ``os.replace`` only once all of it is written: an error leaves ``out`` as it was.

    Args:
        out: the report folder (it exists).
        report: the study's report (``run_study``), JSON-able but for NaN (written as null).
        arrays: the per-world arrays (``run_study``), {name: array}.

    Returns:
        The paths written: the figures, worlds.npz, study.json.
    """
    with writing(out):
        stage = Path(tempfile.mkdtemp(prefix=".study-calibration.", dir=out))
    try:
        plot_errors(report, arrays, stage / FIGURES[0])
        plot_coverage(report, arrays, stage / FIGURES[1])
        with writing(out / WORLDS_FILE):
            np.savez_compressed(stage / WORLDS_FILE, **arrays)
        with writing(out / STUDY_FILE):
            write_json_atomic(stage / STUDY_FILE, json_ready(report))
        names = [*FIGURES, WORLDS_FILE, STUDY_FILE]
        with writing(out):
            for name in names:
                os.replace(stage / name, out / name)
        return [out / name for name in names]
    finally:
        shutil.rmtree(stage, ignore_errors=True)


# ----------------------------------------------------------------------------- one call
class StudyOutputs(NamedTuple):
    """What ``study_into`` made: the report (study.json), the per-world arrays (worlds.npz)
    and the files written."""

    report: dict
    arrays: dict
    paths: list[Path]


def study_into(
    out: Path, settings: CalibrationSettings, **options: Unpack[StudyOptions]
) -> StudyOutputs | None:
    """``run_study`` and ``write_outputs`` into one folder (``study_chunks.into_folder``).

    Args:
        out: the report folder, created and locked before the worlds run.
        settings: what the study runs.
        options: progress, robot, resume, processes (``StudyOptions``).

    Returns:
        The report, arrays and files written, on process 0; None on the others.
    """
    return into_folder(out, run_study, settings, _write, **options)


def _write(folder: Path, result: tuple[dict, dict]) -> StudyOutputs:
    """``run_study``'s ``result`` written into ``folder`` (``write_outputs``)."""
    report, arrays = result
    return StudyOutputs(report, arrays, write_outputs(folder, report, arrays))


# ----------------------------------------------------------------------------- for people
def summary(report: dict) -> str:
    """A few lines for people: per-joint errors of both fits, coverage, run times.

    Args:
        report: the study's report (``run_study``; study.json as read back).

    Returns:
        The lines, joined by newlines.
    """
    return "\n".join([*_head(report), *_joint_table(report), *_findings(report),
                      _times(report)])  # fmt: skip


def _pct(v: float | None) -> str:
    """A fraction as a percentage with two decimals ("-": none or not finite)."""
    return "-" if v is None or not math.isfinite(v) else f"{100 * v:.2f}%"


def _head(report: dict) -> list[str]:
    """The study in one line: worlds, plan, devices, what the table shows."""
    plan = report["plan"]
    plans = len(plan["groups"])
    length = (
        f"{plan['duration_s']:.0f} s"
        if plans == 1
        else f"{plans} plans, mean {plan['duration_s']:.0f} s"
    )
    return [
        f"{report['worlds']} worlds, plan {plan['name']} ({length}), "
        f"{report['backend']} x{len(report['devices'])}; "
        f"RMS relative errors (scipy on {report['scipy']['worlds']} of them, "
        f"{report['scipy'].get('plans', 1)} plans), "
        "gravity current: median over worlds"
    ]


def _joint_table(report: dict) -> list[str]:
    """Per joint: both fits' RMS relative ratio and friction errors, median gravity-current
    errors."""
    n = sum(k.startswith("ratio[") for k in report["jax"]["parameters"])
    jp, sp = report["jax"]["parameters"], report["scipy"]["parameters"]
    jg, sg = report["jax"]["gravity_current_error"], report["scipy"]["gravity_current_error"]
    heads = ("ratio jax", "ratio scipy", "friction jax", "fric. scipy", "g-cur jax",
             "g-cur scipy")  # fmt: skip
    lines = [f"{'joint':<6}" + "".join(f"{h:>14}" for h in heads)]
    for j in range(n):
        r, f = f"ratio[{j}]", f"friction[{j}]"
        row = [
            jp[r]["relative_rmse"],
            sp.get(r, {}).get("relative_rmse"),
            jp[f]["relative_rmse"],
            sp.get(f, {}).get("relative_rmse"),
            jg["median"][j] if jg["median"] else None,
            sg["median"][j] if sg["median"] else None,
        ]
        lines.append(f"{j:<6}" + "".join(f"{_pct(v):>14}" for v in row))
    return lines


def _findings(report: dict) -> list[str]:
    """The pooled gravity comparison, the largest identified ratio error, the coverage and
    the faulted worlds."""
    lines = []
    pooled = report["jax"]["on_scipy_worlds"]["pooled_gravity_current_error"]
    if pooled["worlds"]:
        lines.append(
            f"gravity current pooled over the swept joints, {pooled['worlds']} worlds both fits "
            f"have: JAX worse than scipy in {_pct(pooled['jax_worse_fraction'])}; median JAX "
            f"{_pct(pooled['jax_median'])}, scipy {_pct(pooled['scipy_median'])}"
        )
    worst = report["jax"]["largest_identified_ratio_error"]
    if worst["count"]:
        lines.append(
            f"largest ratio error the JAX fit reports identified ({worst['count']} ratios): "
            f"{_pct(worst['max_abs_relative'])} (world {worst['world']}, joint {worst['joint']})"
        )
    else:
        lines.append(
            "no ratio reported identified (in one mounting each rests partly on the COM prior; "
            "a recording with a known payload identifies them)"
        )
    cov, worst = report["coverage"]["jax"]["identified"], report["coverage"]["jax"]["worst"]
    lines.append(
        f"coverage of +-1.96 std (JAX, {cov['count']} determined estimates): "
        f"{_pct(cov['coverage_95'])}; z std {cov['z_std']:.2f}"
        + (
            f"; lowest of one parameter: {worst['parameter']} {_pct(worst['coverage_95'])} "
            f"of {worst['count']}"
            if worst
            else ""
        )
    )
    if report["faulted_worlds"]:
        lines.append(
            f"{report['faulted_worlds']} of {report['worlds']} worlds faulted before their plan "
            "ended (following error, overspeed, a limit: a true robot that cannot follow it) "
            "and are left out; per plan: " + ", ".join(str(c) for c in report["faulted_by_plan"])
        )
    return lines


def _times(report: dict) -> str:
    """The run times: simulation, JAX fits, scipy fits, total."""
    t = report["timing_s"]
    return (
        f"time: simulate {t['simulate']:.1f} s (compile {t['simulate_compile']:.1f} s, "
        f"{report['throughput']['world_steps_per_s']:.3g} world-steps/s), JAX fits "
        f"{t['fit_jax']:.1f} s (compile {t['fit_jax_compile']:.1f} s, and "
        f"{t['fit_jax_compile_aside']:.1f} s beside the simulation; "
        f"{report['throughput']['jax_fits_per_min']:.3g}/min), scipy {t['fit_scipy']:.1f} s, "
        f"total {t['total']:.1f} s"
    )
