"""Both fits' estimates of the calibration study's worlds against their truth.

The joint JAX fit (``identify.batched_fit.fit_batch``) of every world and the paper's scipy fit
(``identify.baseline``) of M of them: per parameter the estimate, the truth and the standard
error the fit reported, and per joint the relative gravity-current error at random poses
(``identify.evaluate.gravity_current_error_batch``). Units: ratio A/(N m), friction loss A,
viscous A s/rad (= ratio x the truth's N m s/rad), COM offsets m (link frame), phase shifts rad.
"""

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from jaxcomp.hardware.mjx import BatchTruth
from jaxcomp.identify.batched_fit import BatchFit, identified
from jaxcomp.identify.evaluate import gravity_current_error_batch
from jaxcomp.identify.fit_model import FitModel
from jaxcomp.identify.joint_fit import phase_shift
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams
from jaxcomp.studies.plan_recording import Simulated


class Estimates(NamedTuple):
    """One method's estimates of W worlds against their truth (P parameters).

    Attributes:
        names: (P,) the parameters' names. units: (P,) their units (module doc).
        estimate, truth: (W, P) in those units.
        std: (W, P) the standard errors the fit reported (NaN where none was).
        identified: (W, P) bool: the data determine the parameter
            (``batched_fit.identified``).
        ok: (W,) bool: the fit converged / did not fail.
        gravity: (W, n) relative RMS gravity-current error per joint at random poses, a
            fraction (``evaluate.gravity_current_error_batch``).
        gravity_pooled: (W,) the same pooled over the joints the world's plan sweeps
            (``pooled=True``: no fit learns the ratio of a joint it never moves).
        swept: (W, n) bool: the joints the world's plan sweeps.
    """

    names: list[str]
    units: list[str]
    estimate: np.ndarray
    truth: np.ndarray
    std: np.ndarray
    identified: np.ndarray
    ok: np.ndarray
    gravity: np.ndarray
    gravity_pooled: np.ndarray
    swept: np.ndarray

    @property
    def determined(self) -> np.ndarray:
        """(W, P) bool: the parameters the data bear on, ``identified`` but for the ratios
        (the first n), which are determined wherever their joint is swept, identified or
        confounded with COM offsets (reported as such)."""
        n = self.swept.shape[1]
        return np.concatenate([self.swept, self.identified[:, n:]], axis=1)

    @property
    def error(self) -> np.ndarray:
        """(W, P) estimate - truth, NaN for failed fits."""
        return np.where(self.ok[:, None], self.estimate - self.truth, np.nan)

    def rows(self, rows: slice) -> "Estimates":
        """The worlds ``rows``.

        Args:
            rows: the worlds, a slice or (k,) indices.

        Returns:
            Their ``Estimates`` (names and units shared).
        """
        return Estimates(*(x[rows] if isinstance(x, np.ndarray) else x for x in self))


def concat_estimates(parts: Sequence[Estimates]) -> Estimates:
    """The worlds of ``parts`` (one method, the same parameters) one after another.

    Args:
        parts: at least one ``Estimates``.

    Returns:
        The ``Estimates`` of all their worlds (names and units the first's).
    """
    first = parts[0]
    return Estimates(
        *(
            np.concatenate([getattr(p, f) for p in parts])
            if isinstance(getattr(first, f), np.ndarray)
            else getattr(first, f)
            for f in Estimates._fields
        )
    )


def jax_truth_vector(model: FitModel, truth: BatchTruth) -> np.ndarray:
    """(W, 3n + K) the truth in the joint fit's parameter order [ratio, friction, viscous
    (A s/rad: ratio x viscous), com (the fitted links, m)].

    Args:
        model: the joint fit's model (n joints, K COM components of its fitted links).
        truth: the W true robots.

    Returns:
        (W, 3n + K): ratio A/(N m) | friction A | viscous A s/rad | COM offsets m (link
        frame).
    """
    return np.concatenate(
        [
            truth.ratio,
            truth.friction,
            truth.ratio * truth.viscous,
            truth.com_offset[:, model.link_ids].reshape(truth.worlds, -1),
        ],
        axis=1,
    )


def jax_parameters(model: FitModel) -> tuple[list[str], list[str]]:
    """The names and units of the joint fit's ``Estimates`` parameters: ratio, friction,
    viscous, COM offsets, phase shifts.

    Args:
        model: the joint fit's model.

    Returns:
        (names, units), 4n + K each.
    """
    n = model.n
    units = ["A/(N m)"] * n + ["A"] * n + ["A s/rad"] * n + ["m"] * model.K + ["rad"] * n
    return model.parameter_names() + [f"phase_shift[{j}]" for j in range(n)], units


def jax_estimates(
    robot: Robot,
    model: FitModel,
    truth: BatchTruth,
    simulated: Simulated,
    fits: BatchFit,
    poses: np.ndarray,
    batch: int | None = None,
) -> Estimates:
    """The joint fit's ``BatchFit`` of every world as ``Estimates``: ratio, friction, viscous,
    COM offsets and the phase shifts of each joint's first sweep (rad; the truth's from the
    true COM offsets through the same sweep coefficients). ``ok``: converged, and the world
    ran the plan without a fault (a real arm would have stopped). ``batch``: the gravity
    errors in batches of exactly that many worlds (``gravity_current_error_batch(fixed=)``;
    None: its default).

    Args:
        robot: the nominal model.
        model: the joint fit's model.
        truth: the W true robots.
        simulated: their simulation (moments, faults).
        fits: the joint fit of every world.
        poses: (p, n) rad, the random poses of the gravity errors.
        batch: as above.

    Returns:
        The ``Estimates`` of the W worlds, 4n + K parameters.
    """
    sol, n, w = fits.solution, model.n, truth.worlds
    lin = 3 * n
    true = jax_truth_vector(model, truth)
    joint = np.where(simulated.moments.count > 0, simulated.moments.joint, -1)  # -1: empty
    phases = []
    for i in range(w):
        cov = sol.cov[i, lin:, lin:]
        fit_phase = phase_shift(model, fits.coef[i], joint[i], sol.com[i], cov)
        true_phase, _ = phase_shift(model, fits.coef[i], joint[i], true[i, lin:], cov)
        phases.append((fit_phase[0], fit_phase[1], true_phase))
    phase, phase_std, true_phase = (np.array(x) for x in zip(*phases, strict=True))
    ident = identified(sol)
    swept = (joint[:, :, None] == np.arange(n)).any(axis=1)  # (W, n)
    nb = len(robot.link_names)
    fit_com = np.zeros((w, nb, 3))
    fit_com[:, model.link_ids] = sol.com.reshape(w, -1, 3)
    names, units = jax_parameters(model)
    return Estimates(
        names=names,
        units=units,
        estimate=np.concatenate([sol.ratio, sol.friction, sol.viscous, sol.com, phase], axis=1),
        truth=np.concatenate([true, true_phase], axis=1),
        std=np.concatenate([fits.std, np.where(phase_std > 0, phase_std, np.nan)], axis=1),
        identified=np.concatenate([ident, ident[:, :n] & (phase_std > 0)], axis=1),
        ok=np.asarray(sol.converged, bool) & (simulated.fault_step < 0),
        **_gravity_errors(
            robot, swept, batch, truth.ratio, truth.com_offset, sol.ratio, fit_com, poses
        ),
        swept=swept,
    )


def _gravity_errors(
    robot: Robot, swept: np.ndarray, batch: int | None, *args: np.ndarray
) -> dict[str, np.ndarray]:
    """``gravity`` and ``gravity_pooled`` (over the ``swept`` joints) of ``Estimates`` (the
    other arguments: those of ``gravity_current_error_batch``; ``batch`` as ``jax_estimates``
    takes it)."""
    kw = {} if batch is None else {"batch": batch, "fixed": True}
    return {
        "gravity": gravity_current_error_batch(robot, *args, **kw),
        "gravity_pooled": gravity_current_error_batch(
            robot, *args, pooled=True, joints=swept, **kw
        ),
    }


def scipy_estimates(
    robot: Robot,
    truth: BatchTruth,
    worlds: np.ndarray,
    recordings: Sequence[Recording],
    jax: Estimates,
    poses: np.ndarray,
    progress: Callable[[], None] | None = None,
    batch: int | None = None,
) -> tuple[Estimates, list[dict]]:
    """The paper's scipy fit of the M worlds ``worlds`` (indices into ``truth`` and ``jax``),
    whose ``recordings`` these are: ratio and friction as ``Estimates`` (identified where the
    joint fit's are), and the fits that failed (their world index and the error); ``batch``
    as ``jax_estimates`` takes it.

    Args:
        robot: the nominal model.
        truth: the true robots of every world.
        worlds: (M,) the sample's world indices.
        recordings: their M recordings.
        jax: the joint fit's ``Estimates`` of every world (its ``ok``, ``identified``,
            ``swept`` and truth).
        poses: (p, n) rad, the random poses of the gravity errors.
        progress: called after each fit.
        batch: as above.

    Returns:
        (the ``Estimates`` of the M worlds, 2n parameters, ok only where the joint fit's
        world is; the failed fits [{"world", "error"}]).
    """
    if recordings:  # pinocchio, a heavy optional dependency: only when there is a fit to do
        from jaxcomp.identify.baseline import fit_baseline
    m, n, nb = len(recordings), truth.ratio.shape[1], len(robot.link_names)
    est, std = np.full((m, 2 * n), np.nan), np.full((m, 2 * n), np.nan)
    com = np.zeros((m, nb, 3))
    failed = []
    for w, rec in enumerate(recordings):
        try:
            p = fit_baseline(rec, robot=robot, complete=False)  # random plans sweep a subset
        except (ValueError, np.linalg.LinAlgError) as exc:  # the paper's fit gives up
            failed.append({"world": int(worlds[w]), "error": str(exc)})
        else:
            est[w] = np.r_[p.ratio, p.friction]
            std[w] = np.r_[_std(p, "ratio", n), _std(p, "friction", n)]
            for link, off in p.com_offset.items():
                com[w, robot.link_index(link)] = off
        if progress is not None:
            progress()
    ok = np.isfinite(est).all(axis=1) & jax.ok[worlds]  # faulted worlds left out, as for JAX
    ratio = np.where(ok[:, None], est[:, :n], 1.0)
    true_ratio, true_com = truth.ratio[worlds], truth.com_offset[worlds]
    swept = jax.swept[worlds]
    gravity = _gravity_errors(robot, swept, batch, true_ratio, true_com, ratio, com, poses)
    gravity["gravity"][~ok] = np.nan
    gravity["gravity_pooled"][~ok] = np.nan
    cut = slice(0, 2 * n)
    return (
        Estimates(
            names=jax.names[cut],
            units=jax.units[cut],
            estimate=est,
            truth=jax.truth[worlds, cut],
            std=std,
            identified=jax.identified[worlds, cut] & ok[:, None],
            ok=ok,
            **gravity,
            swept=swept,
        ),
        failed,
    )


def _std(params: RobotParams, key: str, n: int) -> np.ndarray:
    """(n,) a scipy fit's std of ``key`` (NaN where it reported none)."""
    values = (params.std or {}).get(key)
    if values is None:
        return np.full(n, np.nan)
    return np.array([np.nan if v is None else float(v) for v in values])
