"""Fitting recordings into params, checked: the identification's entry point.

``fit`` fits one params set to recordings, ``fit_each`` one to each recording, by either
method: "jax", the joint fit of all joints (``identify.joint_fit``; several recordings
jointly; ``identify.batched_fit`` for ``fit_each``), or "scipy", the paper's per-joint fit
(``identify.baseline``; one recording). The params are then checked against the recording's
robot (``plausibility.check_params``): implausible params are refused, never returned.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable

from jaxcomp.errors import InputError
from jaxcomp.identify import batched_fit, joint_fit
from jaxcomp.plausibility import check_params
from jaxcomp.recording import Recording
from jaxcomp.robot_params import RobotParams

#: The fit methods: the joint JAX fit, the paper's scipy per-joint fit.
METHODS = ("jax", "scipy")


def fit(
    recordings: Recording | Iterable[Recording],
    method: str = "jax",
    *,
    com_prior: float | None = None,
    transfers: bool = True,
) -> RobotParams:
    """Fit one params set to recordings of one robot, and check it.

    Args:
        recordings: one recording, or several of one robot model and joints (the "jax"
            method fits them jointly; they may differ in gravity and payload).
        method: "jax" (the joint fit) or "scipy" (the paper's per-joint fit, one recording).
        com_prior: m, the COM prior on every link per axis ("jax" only; None: the model's).
        transfers: "jax" only: also fit the transfers' cruise (the moves between sweeps).

    Returns:
        The params: ratio (n,) A/(N m), friction (n,) A, COM offsets (3,) m per link, phase
        shift (n,) rad and, by the "jax" method, their standard errors and diagnostics.

    Raises:
        InputError: an unknown method, several recordings for "scipy", an invalid recording,
            or implausible params.
        FitError: the "jax" fit did not converge.
    """
    recs = [recordings] if isinstance(recordings, Recording) else list(recordings)
    _check_method(method)
    if method == "jax":
        params = joint_fit.fit(recs, com_prior=com_prior, transfers=transfers)
    else:
        if len(recs) > 1:
            raise InputError(
                "--method scipy fits one recording (the paper's per-joint fit); use --method "
                "jax to fit several recordings jointly, or --each"
            )
        params = _fit_baseline(recs[0])
    return check_params(params, recs[0].robot(), f"the {method} fit's params")


def fit_each(
    recordings: Iterable[Recording],
    method: str = "jax",
    *,
    com_prior: float | None = None,
    transfers: bool = True,
    progress: bool = False,
) -> list[RobotParams]:
    """Fit every recording on its own, and check each params set.

    By the "jax" method in vmapped batches on the default backend (a GPU when present,
    ``batched_fit.fit_each``): ``recordings`` may be a generator that loads them, read while
    the batches before are fitted. By "scipy", one after another (``fit``).

    Args:
        recordings: recordings of one robot model.
        method: "jax" (the joint fit) or "scipy" (the paper's per-joint fit).
        com_prior: m, the COM prior on every link per axis ("jax" only; None: the model's).
        transfers: "jax" only: also fit the transfers' cruise.
        progress: "jax" only: show a progress bar.

    Returns:
        One params set per recording, in their order (see ``fit``).

    Raises:
        InputError: an unknown method, no recording, recordings of different models, an
            invalid recording, or implausible params (naming the recording).
        FitError: a "jax" fit did not converge (naming the recordings; no result then).
    """
    _check_method(method)
    if method == "scipy":
        return [fit([r], "scipy") for r in recordings]
    stream = iter(recordings)
    first = next(stream, None)
    if first is None:
        raise InputError("no recording to fit")
    results = batched_fit.fit_each(
        itertools.chain([first], stream),
        progress=progress,
        com_prior=com_prior,
        transfers=transfers,
    )
    robot = first.robot()
    for k, params in enumerate(results):
        check_params(params, robot, f"the jax fit's params of recording {k}")
    return results


def _check_method(method: str) -> None:
    """InputError unless ``method`` is one of ``METHODS``."""
    if method not in METHODS:
        raise InputError(
            f"unknown fit method {method!r}: the methods are {', '.join(map(repr, METHODS))}"
        )


def _fit_baseline(rec: Recording) -> RobotParams:
    """The paper's scipy fit of ``rec`` (``baseline.fit_baseline``; pinocchio is loaded here,
    only when that method is asked for)."""
    from jaxcomp.identify.baseline import fit_baseline

    return fit_baseline(rec)
