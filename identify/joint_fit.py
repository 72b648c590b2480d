"""The joint fit of recordings: ratio, friction, viscous term and COM offsets of all joints at once.

``fit`` fits one or several recordings of one robot jointly (they may differ in gravity and
payload): each recording's sweeps and transfers reduce to sufficient statistics
(``prepare``, ``identify.fit_stats``), which add, and one solve (``identify.fit_solver``)
gives one params set (``solution_params``, with the phase shift of each joint's gravity
torque, ``phase_shift``). ``warnings_of`` names the ratios the fit could not identify on its
own. ``identify.batched_fit`` fits many recordings each on its own; ``identify.fitting`` is
the entry point that checks the params.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from jaxcomp.errors import InputError, JaxcompError
from jaxcomp.identify.fit_model import JOINT_PARAMS, FitModel, fit_model
from jaxcomp.identify.fit_solver import Solution, solve
from jaxcomp.identify.fit_stats import (
    Stats,
    padded_sweeps,
    sweep_bucket,
    sweep_stats,
    transfer_stats,
)
from jaxcomp.identify.moments import SweepMoments
from jaxcomp.identify.sweep_reduction import sweep_moments
from jaxcomp.identify.transfers import bucket, padded_bins, transfer_bins
from jaxcomp.plausibility import check_recordings
from jaxcomp.recording import Recording
from jaxcomp.robot_params import RobotParams, arm_joint_names


class FitError(JaxcompError):
    """The fit did not converge or produced non-finite parameters."""


def prepare(
    model: FitModel, rec: Recording, transfers: bool = True
) -> tuple[Stats, jax.Array, SweepMoments]:
    """Moments, sufficient statistics and torque coefficients of one recording.

    Args:
        model: the fit's model of the recording's robot.
        rec: the recording.
        transfers: add the transfers' statistics (``identify.transfers``) to the sweeps'.

    Returns:
        The recording's ``Stats``; the torque coefficients (S, 1 + K, 3) of its S sweeps
        (padded to ``fit_stats.sweep_bucket``; see ``fit_stats.sweep_stats``); its sweep
        moments (unpadded).
    """
    m = sweep_moments(rec)
    st, coef = sweep_stats(model, padded_sweeps(m, sweep_bucket(m.n_sweeps)))
    if transfers:
        tb = transfer_bins(rec)
        tb = padded_bins(tb, bucket(tb.size))
        st = st + transfer_stats(model, tb, m.gravity, m.payload_mass, m.payload_com)
    return st, coef, m


def phase_shift(
    model: FitModel, coef: np.ndarray, joint: np.ndarray, com: np.ndarray, cov_com: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Phase shift of each joint's gravity torque over its first sweep, fitted COM against
    nominal, and its standard error (delta method).

    The phase of a sin + b cos is atan2(b, a) (cf. Eq. 17-19); 0 for a joint without a sweep
    or without gravity torque.

    Args:
        model: the fit's model (n joints, K offset components).
        coef: (S, 1 + K, 3) torque coefficients of each sweep (``prepare``).
        joint: (S,) the swept joint of each sweep (-1: an empty sweep).
        com: (K,) m, the fitted COM offsets.
        cov_com: (K, K) m^2, their covariance.

    Returns:
        (n,) rad, each joint's phase shift in [-pi, pi); (n,) rad, its standard error.
    """
    coef = np.asarray(coef)
    phase = np.zeros(model.n)
    std = np.zeros(model.n)
    for j in range(model.n):
        sweeps = np.flatnonzero(np.asarray(joint) == j)
        if sweeps.size == 0:
            continue
        k = sweeps[0]
        a0, b0 = coef[k, 0, 0], coef[k, 0, 1]
        A, Bv = coef[k, 1:, 0], coef[k, 1:, 1]
        a1, b1 = a0 + A @ com, b0 + Bv @ com
        if min(np.hypot(a0, b0), np.hypot(a1, b1)) < 1e-6:
            continue
        phase[j] = np.arctan2(b1, a1) - np.arctan2(b0, a0)
        grad = (a1 * Bv - b1 * A) / (a1**2 + b1**2)
        std[j] = float(np.sqrt(max(grad @ cov_com @ grad, 0.0)))
    return (phase + np.pi) % (2 * np.pi) - np.pi, std


def _check_same_model(recs: list[Recording]) -> FitModel:
    """The ``FitModel`` of recordings of one robot model and joints (InputError otherwise)."""
    if not recs:
        raise InputError("no recording to fit")
    names = {(r.model, r.robot().controlled_joints) for r in recs}
    if len(names) > 1:
        raise InputError(
            f"recordings of different models (or joints) cannot be fitted jointly: {sorted(names)}"
        )
    return fit_model(recs[0].robot())


#: What to do about a ratio confounded with a link's first moment.
CURE = (
    "add a recording with a known payload (or one in a second mounting) and fit the recordings "
    "together"
)


def _params(
    model: FitModel, name: str, sol: Solution, phase, phase_std, seconds: float
) -> RobotParams:
    """The ``RobotParams`` of a converged solution with its phase shifts (``FitError``
    otherwise)."""
    sol = jax.tree.map(np.asarray, sol)
    if not bool(sol.converged) or not np.all(np.isfinite(sol.ratio)):
        raise FitError(
            f"the joint fit did not converge after {int(sol.iterations)} iterations "
            f"(noise estimate {np.max(sol.sigma):.3g} A); nothing was written"
        )
    n = model.n
    std = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))
    com = sol.com.reshape(-1, 3)
    com_std = std[JOINT_PARAMS * n :].reshape(-1, 3)
    names = model.parameter_names()
    joints = arm_joint_names(model.robot)
    return RobotParams(
        model=name,
        ratio=sol.ratio,
        friction=np.abs(sol.friction),
        com_offset={link: com[i] for i, link in enumerate(model.links)},
        phase_shift=phase,
        std={
            "ratio": std[:n],
            "friction": std[n : 2 * n],
            "com_offset": {link: com_std[i] for i, link in enumerate(model.links)},
            "phase_shift": phase_std,
        },
        method="jax",
        fit_seconds=seconds,
        joints=joints,
        diagnostics={
            "iterations": int(sol.iterations),
            "current_noise": sol.sigma,
            "viscous": sol.viscous,
            "viscous_std": std[2 * n : 3 * n],
            "excitation": [float(e) if np.isfinite(e) else None for e in sol.excitation],
            "ratio_identified": sol.identified[:n],
            "ratio_source": [_ratio_source(model, sol, j) for j in range(n)],
            "confounded": [
                {"joint": joints[j], "link": model.links[int(sol.confounded_link[j])]}
                for j in np.flatnonzero(sol.confounded)
            ],
            "com_prior": {
                link: float(c) for link, c in zip(model.links, model.com_prior, strict=True)
            },
            "unidentified": [names[i] for i in np.flatnonzero(~sol.identified)],
            "singular_values": sol.singular,
        },
    )


def _ratio_source(model: FitModel, sol: Solution, j: int) -> str:
    """Where joint j's ratio comes from, in words ("fit": identified)."""
    if sol.identified[j]:
        return "fit"
    if sol.confounded[j]:
        return f"confounded with the COM of {model.links[int(sol.confounded_link[j])]}"
    if not sol.excited[j]:
        if model.types is not None and any(
            sol.excited[k] and model.types[k] == model.types[j] for k in range(model.n)
        ):
            return f"mean of type {model.types[j]}"
        return "prior: no gravity signal"
    return "fit, imprecise"


def warnings_of(params: RobotParams) -> list[str]:
    """The ratios the fit could not identify on its own, in words.

    Args:
        params: params of the JAX fit (their diagnostics).

    Returns:
        One line per ratio confounded with a link's first moment (naming the cure, ``CURE``)
        or without gravity signal; none for params without diagnostics.
    """
    d = params.diagnostics or {}
    joints = params.joints or [str(j) for j in range(params.n)]
    out = [
        f"warning: the ratio of joint {c['joint']} is confounded with the centre of mass of "
        f"{c['link']} (it rests on the COM prior): {CURE}"
        for c in d.get("confounded", [])
    ]
    for j, source in enumerate(d.get("ratio_source", [])):
        if source.startswith("prior"):
            out.append(
                f"warning: joint {joints[j]} carries no gravity signal in these sweeps: its ratio "
                "is the data's ratio scale, not a measurement"
            )
    return out


def fit(
    recordings: Recording | list[Recording],
    max_iter: int = 50,
    com_prior: float | None = None,
    complete: bool = True,
    transfers: bool = True,
) -> RobotParams:
    """Fit one parameter set to one or several recordings of one robot, jointly: their sweeps
    and, unless ``transfers`` is False, the cruise of their transfers between sweeps
    (``identify.transfers``). The recordings may differ in gravity (mounting) and payload.

    Args:
        recordings: one recording or several of one robot model and joints.
        max_iter: the solver's most Newton steps.
        com_prior: m, the COM prior on every link per axis (None: the model's,
            ``fit_model.default_com_prior``).
        complete: refuse recordings that are implausible or do not sweep every joint both
            ways (``plausibility.check_recordings``); False: an unswept joint keeps zero
            friction with an error bar of the prior's width (the studies' random plans sweep
            a subset).
        transfers: fit the transfers' cruise too.

    Returns:
        The params: ratio (n,) A/(N m), friction (n,) A, COM offsets (3,) m per link, phase
        shift (n,) rad, their standard errors and the fit's diagnostics.

    Raises:
        InputError: no recording, recordings of different models, or (``complete``)
            implausible ones.
        FitError: the fit did not converge.
    """
    recs = [recordings] if isinstance(recordings, Recording) else list(recordings)
    model = _check_same_model(recs).with_com_prior(com_prior)
    if complete:
        check_recordings(recs)
    start = time.perf_counter()
    prepared = [prepare(model, r, transfers) for r in recs]
    st = prepared[0][0]
    for other in prepared[1:]:
        st = st + other[0]
    sol = jax.block_until_ready(solve(model.key, st, max_iter))
    _, coef, m = prepared[0]
    return solution_params(model, recs[0].model, sol, coef, m.joint, time.perf_counter() - start)


def solution_params(
    model: FitModel,
    name: str,
    sol: Solution,
    coef: np.ndarray,
    joint: np.ndarray,
    seconds: float,
) -> RobotParams:
    """The params of one solution.

    Args:
        model: the fit's model (n joints, K offset components).
        name: the robot model of the recordings.
        sol: the solver's ``Solution`` (one recording's: no batch axis).
        coef: (S, 1 + K, 3) torque coefficients of the first recording's sweeps.
        joint: (S,) the swept joint of each of them (-1: an empty sweep).
        seconds: s, the fit's time, kept in the params.

    Returns:
        The ``RobotParams`` (method "jax"), with the phase shifts (``phase_shift``) and the
        diagnostics.

    Raises:
        FitError: the solution did not converge.
    """
    cov = np.asarray(sol.cov)[JOINT_PARAMS * model.n :, JOINT_PARAMS * model.n :]
    phase, phase_std = phase_shift(model, coef, joint, np.asarray(sol.com), cov)
    return _params(model, name, sol, phase, phase_std, seconds)
