"""How good is a params set: gravity-current prediction error against a known truth.

What the controller needs from identification is the current that holds the arm,
``ratio * g(q)`` per joint (Eq. 7 with the COM-corrected model); ratios and COM offsets may
trade off along directions no sweep determines, but this product may not.

One kernel, ``gravity_current_squares``, computes the error; it is reported two ways, under two
names: per joint (``gravity_current_error``, ``gravity_current_error_batch``: the calibration
study's and the paper's Exp. 1 ``gravity_current_error``) and pooled over all joints
(``gravity_current_error_batch(pooled=True)``: the control study's
``gravity_current_error_pooled``). Currents in A, ratios in A/(N m), COM offsets in m (link
frame), poses in rad of the current-controlled joints; default gravity, no payload.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.current import torque_to_current
from jaxcomp.errors import InputError
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices


def random_poses(robot: Robot, count: int, seed: int = 0) -> np.ndarray:
    """Poses drawn uniformly within the current-controlled joints' limits (-pi .. pi for a
    continuous joint).

    Args:
        robot: The robot.
        count: Poses.
        seed: Of the random generator.

    Returns:
        (count, n) rad.
    """
    lo, hi = robot.joint_limits[arm_joint_indices(robot)].T
    lo, hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, (count, len(lo)))


def gravity_torque_at(
    tree: KinematicTree,
    nominal: InertialParams,
    joints: np.ndarray,
    poses: jax.Array,
    com_offset: jax.Array,
) -> jax.Array:
    """g(q) for the nominal model with every link's COM moved. Pure; jit/vmap-able.

    Args:
        tree: The robot's kinematic tree.
        nominal: Its nominal inertials.
        joints: (n,) int, the current-controlled joints among the nv.
        poses: (P, nv) rad.
        com_offset: (nb, 3) m, added to every link's COM, link frame.

    Returns:
        (P, n) N m, the joints ``joints``' gravity torques.
    """
    p = nominal._replace(com=nominal.com + com_offset)
    return jax.vmap(lambda q: dynamics.gravity(tree, q, p))(poses)[:, joints]


def gravity_current_at(
    tree: KinematicTree,
    nominal: InertialParams,
    joints: np.ndarray,
    poses: jax.Array,
    ratio: jax.Array,
    com_offset: jax.Array,
) -> jax.Array:
    """The gravity current r g(q) (Eq. 7) of ``gravity_torque_at``. Pure; jit/vmap-able.

    Args:
        tree: The robot's kinematic tree.
        nominal: Its nominal inertials.
        joints: (n,) int, the current-controlled joints among the nv.
        poses: (P, nv) rad.
        ratio: (n,) A/(N m).
        com_offset: (nb, 3) m, added to every link's COM, link frame.

    Returns:
        (P, n) A.
    """
    return torque_to_current(gravity_torque_at(tree, nominal, joints, poses, com_offset), ratio)


def gravity_current_squares(
    tree: KinematicTree,
    nominal: InertialParams,
    joints: np.ndarray,
    poses: jax.Array,
    truth_ratio: jax.Array,
    truth_com: jax.Array,
    ratio: jax.Array,
    com: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """The gravity-current error of W models against W truths, as mean squares over the
    poses, with I = ``gravity_current_at`` of ``ratio`` and ``com``, I_true of
    ``truth_ratio`` and ``truth_com``. Pure; jit-able.

    Args:
        tree: The robot's kinematic tree.
        nominal: Its nominal inertials.
        joints: (n,) int, the current-controlled joints among the nv.
        poses: (P, nv) rad.
        truth_ratio: (W, n) A/(N m).
        truth_com: (W, nb, 3) m, COM offsets, link frame.
        ratio: (W, n) A/(N m).
        com: (W, nb, 3) m, COM offsets, link frame.

    Returns:
        (error, truth), (W, n) A^2 each: the mean over the poses of (I(q) - I_true(q))^2 and
        of I_true(q)^2.
    """

    def current(r: jax.Array, c: jax.Array) -> jax.Array:
        return gravity_current_at(tree, nominal, joints, poses, r, c)

    true = jax.vmap(current)(truth_ratio, truth_com)  # (W, P, n)
    err = jax.vmap(current)(ratio, com) - true
    return jnp.mean(err**2, axis=1), jnp.mean(true**2, axis=1)


def _jitted(robot: Robot, kernel: Callable) -> Callable:
    """``kernel`` (``gravity_current_at`` or ``gravity_current_squares``) of ``robot``'s
    nominal model and arm joints, jitted once and kept on the robot (one compilation per
    input shape)."""

    def build() -> Callable:
        tree, nominal, joints = robot.tree, robot.nominal_params(), arm_joint_indices(robot)
        return jax.jit(lambda *args: kernel(tree, nominal, joints, *args))

    return robot.cached(("evaluate", kernel.__name__), build)


def _full_poses(robot: Robot, poses: np.ndarray) -> np.ndarray:
    """(P, nv) joint positions: ``poses`` (P, n) rad of the arm joints, 0 elsewhere."""
    full = np.zeros((len(poses), robot.nv))
    full[:, arm_joint_indices(robot)] = poses
    return full


def _com_offsets(robot: Robot, params: RobotParams) -> np.ndarray:
    """(nb, 3) m: the COM offsets of ``params`` for every link (0 where it has none)."""
    params.check(robot)
    off = np.zeros((len(robot.link_names), 3))
    for link, d in params.com_offset.items():
        off[robot.link_index(link)] = d
    return off


def gravity_current(robot: Robot, params: RobotParams, poses: np.ndarray) -> np.ndarray:
    """The gravity current ratio x g(q) of ``params`` (default gravity).

    Args:
        robot: The robot.
        params: Its identified params.
        poses: (count, n) rad of the current-controlled joints.

    Returns:
        (count, n) A.

    Raises:
        InputError: ``params`` do not fit ``robot``.
    """
    fn = _jitted(robot, gravity_current_at)
    return np.asarray(fn(_full_poses(robot, poses), params.ratio, _com_offsets(robot, params)))


def gravity_current_error(
    robot: Robot, truth: RobotParams, fitted: RobotParams, poses: np.ndarray
) -> np.ndarray:
    """The RMS error of the predicted gravity current over ``poses``, relative to the RMS
    true gravity current.

    Args:
        robot: The robot.
        truth: The true params.
        fitted: The params to judge.
        poses: (P, n) rad of the current-controlled joints.

    Returns:
        (n,) per joint, relative (NaN for a joint gravity never loads).

    Raises:
        InputError: params that do not fit ``robot``.
    """
    return gravity_current_error_batch(
        robot,
        truth.ratio[None],
        _com_offsets(robot, truth)[None],
        fitted.ratio[None],
        _com_offsets(robot, fitted)[None],
        poses,
    )[0]


def gravity_current_error_batch(
    robot: Robot,
    truth_ratio: np.ndarray,
    truth_com: np.ndarray,
    ratio: np.ndarray,
    com: np.ndarray,
    poses: np.ndarray,
    batch: int = 256,
    *,
    pooled: bool = False,
    joints: np.ndarray | None = None,
    fixed: bool = False,
) -> np.ndarray:
    """``gravity_current_error`` of W params sets against W truths, batched on the default
    backend; (W, n) per world and joint, NaN where the true gravity current is ~0.

    ``pooled``: instead (W,) one number per world, the gravity-current error pooled over the
    joints: the RMS of the error over ``poses`` and joints together, relative to the RMS of the
    true gravity current over both; ``joints`` (W, n) bool: pool over these joints of each world
    only (default: all; NaN where they carry no gravity current).

    Default gravity, no payload. Worlds go ``batch`` at a time (the last batch padded), one
    compilation per robot and shape.

    Args:
        robot: The robot.
        truth_ratio: (W, n) A/(N m).
        truth_com: (W, nb, 3) m, COM offsets of every link (``robot.link_names`` order, link
            frame) added to the nominal model.
        ratio: (W, n) A/(N m).
        com: (W, nb, 3) m, as ``truth_com``.
        poses: (P, n) rad of the current-controlled joints.
        batch: Worlds per compiled call.
        pooled: Pool over the joints (see above).
        joints: (W, n) bool, the joints to pool over; None: all.
        fixed: ``batch`` worlds also when W is smaller (padded), so that a world's numbers
            are those of one compiled batch shape whatever the other worlds.

    Returns:
        (W, n) relative errors, or (W,) pooled.

    Raises:
        InputError: arrays of the wrong shapes.
    """
    truth_ratio, ratio = np.asarray(truth_ratio, float), np.asarray(ratio, float)
    truth_com, com = np.asarray(truth_com, float), np.asarray(com, float)
    w, n = ratio.shape
    nb = len(robot.link_names)
    if truth_ratio.shape != (w, n) or truth_com.shape != (w, nb, 3) or com.shape != (w, nb, 3):
        raise InputError(f"ratios must be (W, n) = {(w, n)} and COM offsets (W, {nb}, 3)")
    full = _full_poses(robot, poses)
    fn = _jitted(robot, gravity_current_squares)
    b = max(1, int(batch) if fixed else min(int(batch), w))
    err, true = np.zeros((w, n)), np.zeros((w, n))
    for s in range(0, w, b):
        idx = np.minimum(np.arange(s, s + b), w - 1)
        e, t = fn(full, truth_ratio[idx], truth_com[idx], ratio[idx], com[idx])
        k = min(b, w - s)
        err[s : s + k], true[s : s + k] = np.asarray(e)[:k], np.asarray(t)[:k]
    if pooled:
        mask = np.ones((w, n), bool) if joints is None else np.asarray(joints, bool)
        if mask.shape != (w, n):
            raise InputError(f"joints must be (W, n) = {(w, n)} booleans, got {mask.shape}")
        err_sum, true_sum = (err * mask).sum(axis=1), (true * mask).sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(true_sum > 0, np.sqrt(err_sum / true_sum), np.nan)
    rms, scale = np.sqrt(err), np.sqrt(true)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(scale > 1e-9, rms / scale, np.nan)


def error_statistics(error: np.ndarray, std: np.ndarray | None = None, z: float = 1.96) -> dict:
    """Per-parameter statistics of estimate errors over W independent fits. NaN entries are
    ignored.

    Args:
        error: (W, P), estimate minus truth, in each parameter's unit.
        std: (W, P), the standard errors the fit reported (NaN or <= 0 where it reported
            none); None: none.
        z: Coverage multiple of the std.

    Returns:
        Arrays (P,): ``bias`` (mean), ``rmse``, ``spread`` (standard deviation, ddof 1; NaN
        for W < 2), ``median_abs``, ``p95_abs``; with ``std`` also ``std_median``,
        ``std_rms`` (RMS of the reported std), ``coverage`` (fraction of fits with |error| <
        z std: 0.95 for z = 1.96 when the std are right) and ``spread_over_std`` (empirical
        spread / RMS reported std: 1 when the reported std, the Cramer-Rao bound of the fit,
        match the actual scatter).

    Raises:
        InputError: ``error`` not 2-D, or ``std`` of another shape.
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
