"""How good is a params set: gravity-current prediction error against a known truth.

What the controller needs from identification is the current that holds the arm,
``ratio * g(q)`` per joint (Eq. 7 with the COM-corrected model); ratios and COM offsets may
trade off along directions no sweep determines, but this product may not.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.errors import InputError
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices


def random_poses(robot: Robot, count: int, seed: int = 0) -> np.ndarray:
    """(count, n) rad: poses drawn uniformly within the current-controlled joints' limits."""
    lo, hi = robot.joint_limits[arm_joint_indices(robot)].T
    return np.random.default_rng(seed).uniform(lo, hi, (count, len(lo)))


def gravity_current(robot: Robot, params: RobotParams, poses: np.ndarray) -> np.ndarray:
    """(count, n) A: ratio x g(q) of ``params`` at ``poses`` (arm joints, default gravity)."""
    joints = arm_joint_indices(robot)
    full = np.zeros((len(poses), robot.nv))
    full[:, joints] = poses
    inertial = params.inertial_params(robot)
    g = jax.jit(jax.vmap(lambda q: dynamics.gravity(robot.tree, q, inertial)))(full)
    return np.asarray(g)[:, joints] * params.ratio


def gravity_current_error(
    robot: Robot, truth: RobotParams, fitted: RobotParams, poses: np.ndarray
) -> np.ndarray:
    """(n,) per joint: RMS error of the predicted gravity current over ``poses``, relative to
    the RMS true gravity current (NaN for a joint gravity never loads)."""
    true = gravity_current(robot, truth, poses)
    err = gravity_current(robot, fitted, poses) - true
    scale = np.sqrt((true**2).mean(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(scale > 1e-9, np.sqrt((err**2).mean(0)) / scale, np.nan)


_BATCH_GRAVITY: dict[tuple, Callable] = {}


def gravity_current_error_batch(
    robot: Robot,
    truth_ratio: np.ndarray,
    truth_com: np.ndarray,
    ratio: np.ndarray,
    com: np.ndarray,
    poses: np.ndarray,
    batch: int = 256,
) -> np.ndarray:
    """``gravity_current_error`` of W params sets against W truths, batched on the default
    backend; (W, n) per world and joint, NaN where the true gravity current is ~0.

    ``truth_ratio``, ``ratio``: (W, n) A/(N m); ``truth_com``, ``com``: (W, nb, 3) m, COM
    offsets of every link (``robot.link_names`` order, link frame) added to the nominal model;
    ``poses`` (P, n) rad of the current-controlled joints; default gravity, no payload.
    Worlds go ``batch`` at a time (the last batch padded), one compilation per robot and shape.
    """
    truth_ratio, ratio = np.asarray(truth_ratio, float), np.asarray(ratio, float)
    truth_com, com = np.asarray(truth_com, float), np.asarray(com, float)
    w, n = ratio.shape
    nb = len(robot.link_names)
    if truth_ratio.shape != (w, n) or truth_com.shape != (w, nb, 3) or com.shape != (w, nb, 3):
        raise InputError(f"ratios must be (W, n) = {(w, n)} and COM offsets (W, {nb}, 3)")
    joints = arm_joint_indices(robot)
    full = np.zeros((len(poses), robot.nv))
    full[:, joints] = poses
    b = max(1, min(int(batch), w))
    key = (robot.name, str(robot.source), b, full.shape)
    if key not in _BATCH_GRAVITY:
        tree, nominal = robot.tree, robot.nominal_params()

        @jax.jit
        def errors(tr, tc, r, c, q):
            def current(ratio_w, com_w):
                p = nominal._replace(com=nominal.com + com_w)
                g = jax.vmap(lambda x: dynamics.gravity(tree, x, p))(q)[:, joints]
                return g * ratio_w

            true = jax.vmap(current)(tr, tc)  # (b, P, n)
            err = jax.vmap(current)(r, c) - true
            return jnp.sqrt(jnp.mean(err**2, axis=1)), jnp.sqrt(jnp.mean(true**2, axis=1))

        _BATCH_GRAVITY[key] = errors
    fn = _BATCH_GRAVITY[key]
    rms, scale = np.zeros((w, n)), np.zeros((w, n))
    for s in range(0, w, b):
        idx = np.minimum(np.arange(s, s + b), w - 1)
        e, sc = fn(truth_ratio[idx], truth_com[idx], ratio[idx], com[idx], full)
        k = min(b, w - s)
        rms[s : s + k], scale[s : s + k] = np.asarray(e)[:k], np.asarray(sc)[:k]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(scale > 1e-9, rms / scale, np.nan)


def error_statistics(error: np.ndarray, std: np.ndarray | None = None, z: float = 1.96) -> dict:
    """Per-parameter statistics of estimate errors over W independent fits.

    ``error`` (W, P): estimate minus truth; ``std`` (W, P): the standard errors the fit
    reported (NaN or <= 0 where it reported none). Returns arrays (P,): ``bias`` (mean),
    ``rmse``, ``spread`` (standard deviation, ddof 1; NaN for W < 2), ``median_abs``,
    ``p95_abs``; with ``std`` also ``std_median``, ``std_rms`` (RMS of the reported std),
    ``coverage`` (fraction of fits with |error| < z std: 0.95 for z = 1.96 when the std are
    right) and ``spread_over_std`` (empirical spread / RMS reported std: 1 when the reported
    std, the Cramer-Rao bound of the fit, match the actual scatter). NaN entries are ignored.
    """
    error = np.asarray(error, float)
    if error.ndim != 2:
        raise InputError(f"error must be (W, P), got shape {error.shape}")
    count = np.isfinite(error).sum(axis=0)
    with warnings.catch_warnings():  # all-NaN columns: NaN is the answer
        warnings.simplefilter("ignore", RuntimeWarning)
        out = {
            "bias": np.nanmean(error, axis=0),
            "rmse": np.sqrt(np.nanmean(error**2, axis=0)),
            "spread": np.where(count > 1, np.nanstd(error, axis=0, ddof=1), np.nan),
            "median_abs": np.nanmedian(np.abs(error), axis=0),
            "p95_abs": np.nanpercentile(np.abs(error), 95, axis=0),
        }
        if std is not None:
            std = np.asarray(std, float)
            if std.shape != error.shape:
                raise InputError(f"std must have the shape of error {error.shape}")
            std = np.where(std > 0, std, np.nan)
            both = np.isfinite(std) & np.isfinite(error)
            covered = np.where(both, np.abs(error) < z * std, False).sum(axis=0)
            out["std_median"] = np.nanmedian(std, axis=0)
            out["std_rms"] = np.sqrt(np.nanmean(std**2, axis=0))
            out["coverage"] = np.where(both.any(axis=0), covered / both.sum(axis=0), np.nan)
            out["spread_over_std"] = out["spread"] / out["std_rms"]
    return out
