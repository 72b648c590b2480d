"""The paper's calibration (de Wolde et al., Section IV-A) as a baseline: pinocchio and scipy.

``fit_baseline`` follows the paper step by step and adds nothing it does not have; it is the
yardstick the other identification methods are measured against.

1. Phase shift (IV-A.4, Eq. 17-19), joint by joint from the last link backwards: for each
   gravity-excited joint j, the forward and backward currents of its sweep are averaged at
   each angle (friction cancels), Eq. (19) ``c = s sin(theta + delta)`` is fitted to them and,
   the same way, to the model's gravity torque at the same poses; the difference of the two
   phases is the phase shift delta_j. The centre of mass of the link joint j moves directly is
   then moved in the plane perpendicular to the joint axis so that the gravity moment of the
   whole subtree carried by joint j turns by delta_j about the axis. One correction per joint.
2. Ratio and friction (IV-A.1-2, Eq. 13) on the corrected model: ``c = r tau + l d`` per
   excited joint over all its steady samples, tau = g(q) (the torque holding the arm, the
   sign convention of pinocchio and jaxcomp), d = the direction of motion; friction = |l|.
3. Joints gravity cannot excite (VI-A) get the mean ratio of the excited joints of their
   actuator type and the friction of their own sweep, the mean of ``c d``.

Samples enter as angle-bin means weighted by their counts (``identify.bins``): the same
least-squares solutions as the raw 1 kHz samples up to the curvature within a bin, at a
fraction of the pinocchio calls.
"""

from __future__ import annotations

import time

import numpy as np
import pinocchio as pin
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jaxcomp import checks
from jaxcomp.errors import InputError
from jaxcomp.identify.bins import BIN_WIDTH, SweepBins, bin_sweeps
from jaxcomp.params import InertialParams
from jaxcomp.plausibility import check_recordings
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names
from jaxcomp.urdf import to_urdf

#: A sweep excites its joint when the model's gravity torque amplitude reaches this, N m.
AMPLITUDE_THRESHOLD = 0.05
#: Fewest angles with both directions for a phase fit.
MIN_PAIRS = 3

__all__ = ["AMPLITUDE_THRESHOLD", "fit_baseline", "phase_fit"]


# ----------------------------------------------------------------------------- Eq. (19)
def _wrap(angle):
    """Angle(s) wrapped to [-pi, pi), rad."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def _sine_lstsq(theta: np.ndarray, c: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Closed-form weighted argmin of Eq. (19) via c = a sin(theta) + b cos(theta)."""
    sw = np.sqrt(w)
    basis = np.stack([np.sin(theta), np.cos(theta)], axis=1) * sw[:, None]
    (a, b), *_ = np.linalg.lstsq(basis, c * sw, rcond=None)
    return float(np.hypot(a, b)), float(np.arctan2(b, a))


def _phase_fit(theta: np.ndarray, c: np.ndarray, w: np.ndarray) -> tuple[float, float, float]:
    """Eq. (19) by ``scipy.optimize.least_squares``: s >= 0, delta rad and its std (rad)."""
    s0, d0 = _sine_lstsq(theta, c, w)
    if s0 == 0.0:  # no sinusoid at all: the phase is undefined
        return 0.0, 0.0, np.inf
    sw = np.sqrt(w)

    def residual(x):
        return sw * (c - x[0] * np.sin(theta + x[1]))

    def jacobian(x):
        return -sw[:, None] * np.stack([np.sin(theta + x[1]), x[0] * np.cos(theta + x[1])], axis=1)

    sol = least_squares(residual, [s0, d0], jac=jacobian, method="lm")
    s, delta = (float(v) for v in sol.x)
    if s < 0:
        s, delta = -s, delta + np.pi
    dof = max(len(c) - 2, 1)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * (2 * sol.cost / dof)
        std = float(np.sqrt(max(cov[1, 1], 0.0)))
    except np.linalg.LinAlgError:
        std = np.inf
    return s, float(_wrap(delta)), std


def phase_fit(theta, c, weights=None) -> tuple[float, float]:
    """Eq. (19): ``s*, delta* = argmin sum_i w_i (c_i - s sin(theta_i + delta))^2``.

    Args:
        theta: (N,) rad, joint angles.
        c: (N,) values (A, or N m for a model torque).
        weights: (N,) >= 0 sample weights (e.g. bin counts), default ones.

    Returns:
        s >= 0 (units of c) and delta in [-pi, pi) rad.

    Raises:
        InputError: shapes that differ, fewer than 2 finite samples, or bad weights.
    """
    theta = checks.array(theta, "phase_fit theta", unit="rad")
    n = theta.shape[0]
    c = checks.array(c, "phase_fit c", n=n)
    w = np.ones(n) if weights is None else weights
    w = checks.array(w, "phase_fit weights", n=n, nonneg=True)
    if n < 2:
        raise InputError("phase_fit needs at least 2 finite samples")
    s, delta, _ = _phase_fit(theta, c, w)
    return s, delta


# ----------------------------------------------------------------------------- Eq. (13)
def _ratio_friction(
    tau: np.ndarray, d: np.ndarray, c: np.ndarray, w: np.ndarray
) -> tuple[float, float, float, float]:
    """Eq. (13) with the friction sign from the direction: c = r tau + l d, weights w.

    Returns r A/(N m), l A and their standard errors.
    """
    sw = np.sqrt(w)
    design = np.stack([tau, d], axis=1) * sw[:, None]
    target = c * sw
    x0, *_ = np.linalg.lstsq(design, target, rcond=None)
    sol = least_squares(lambda x: design @ x - target, x0, jac=lambda x: design, method="lm")
    dof = max(len(c) - 2, 1)
    try:
        cov = np.linalg.inv(design.T @ design) * (2 * sol.cost / dof)
        std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        std = np.full(2, np.inf)
    return float(sol.x[0]), float(sol.x[1]), float(std[0]), float(std[1])


# ----------------------------------------------------------------------------- model
class _PinocchioGravity:
    """A pinocchio model of ``robot`` (``to_urdf`` of its nominal inertials, payload merged into
    the end-effector site's body) under the recording's gravity; COMs then move in place.

    Joint indices are the recording's (current-controlled joints, 0..n-1); torques in N m.
    """

    def __init__(self, robot: Robot, rec: Recording):
        tree = robot.tree
        inertial = InertialParams(*(np.asarray(x, dtype=float) for x in tree.nominal))
        if rec.payload_mass > 0:
            payload = robot.with_payload(inertial, float(rec.payload_mass), rec.payload_com)
            inertial = InertialParams(*(np.asarray(x, dtype=float) for x in payload))
        model = pin.buildModelFromXML(to_urdf(tree, inertial))
        model.gravity.linear = np.asarray(rec.gravity, dtype=float)
        self.model, self.data = model, model.createData()
        names = [tree.joint_names[i] for i in arm_joint_indices(robot)]
        self.jid = [int(model.getJointId(nm)) for nm in names]
        self.iq = np.array([model.joints[i].idx_q for i in self.jid])
        self.iv = np.array([model.joints[i].idx_v for i in self.jid])
        self.q0 = pin.neutral(model)

    def _q(self, q: np.ndarray) -> np.ndarray:
        """Pinocchio configurations (..., nq) from the recording's joint angles (..., n)."""
        full = np.broadcast_to(self.q0, q.shape[:-1] + self.q0.shape).copy()
        full[..., self.iq] = q
        return full

    def torques(self, q: np.ndarray) -> np.ndarray:
        """g(q) (K, n) N m at K poses ``q`` (K, n) rad."""
        model, data = self.model, self.data
        g = [pin.computeGeneralizedGravity(model, data, qk) for qk in self._q(q)]
        return np.array(g).reshape(len(q), model.nv)[:, self.iv]

    def subtree_moment(self, q: np.ndarray, j: int) -> np.ndarray:
        """Sum of m (c - anchor) (3,) kg m over the subtree joint j carries, its body's frame."""
        model, data, jid = self.model, self.data, self.jid[j]
        pin.forwardKinematics(model, data, self._q(q))
        moment = np.zeros(3)  # world frame, about the world origin
        for k in model.subtrees[jid]:
            inertia = model.inertias[k]
            moment += inertia.mass * data.oMi[k].act(inertia.lever)
        frame = data.oMi[jid]
        mass = sum(model.inertias[k].mass for k in model.subtrees[jid])
        return frame.rotation.T @ (moment - mass * frame.translation)

    def move_com(self, j: int, mass: float, shift: np.ndarray) -> None:
        """Move the COM of the link joint j moves (its own ``mass`` kg) by ``shift`` (3,) m.

        The link's frame is the joint's frame (``to_urdf``), so the shift applies as is to the
        joint's inertia (the link's merged with any fixed children and payload).
        """
        inertia = self.model.inertias[self.jid[j]]
        lever = inertia.lever + mass * np.asarray(shift) / inertia.mass
        self.model.inertias[self.jid[j]] = pin.Inertia(inertia.mass, lever, inertia.inertia)


# ----------------------------------------------------------------------------- the fit
def _actuator_types(robot: Robot, n: int) -> list[str]:
    types = robot.actuator_types
    if types is None:
        return [f"joint{j}" for j in range(n)]  # no shared types: nothing to borrow from
    return list(types)


def _pairs(bins: SweepBins, rows: np.ndarray, j: int):
    """Forward/backward bins of one sweep at the same angle index, averaged (Section IV-A.4).

    Returns theta (P,) rad, mean current (P,) A, mean pose (P, n) rad, weights (P,) counts.
    """
    fwd = rows[bins.direction[rows] > 0]
    bwd = rows[bins.direction[rows] < 0]
    _, i_f, i_b = np.intersect1d(bins.index[fwd], bins.index[bwd], return_indices=True)
    f, b = fwd[i_f], bwd[i_b]
    q = 0.5 * (bins.q[f] + bins.q[b])
    c = 0.5 * (bins.current[f, j] + bins.current[b, j])
    return q[:, j], c, q, (bins.count[f] + bins.count[b]).astype(float)


def fit_baseline(
    rec: Recording,
    *,
    robot: Robot | None = None,
    bins: SweepBins | None = None,
    threshold: float = AMPLITUDE_THRESHOLD,
    width: float = BIN_WIDTH,
    complete: bool = True,
) -> RobotParams:
    """The paper's calibration of ratios, friction losses and COM phase shifts (method "scipy").

    Args:
        rec: a calibration recording (sweeps of single joints, both directions).
        robot: the model (default ``rec.robot()``); the fit starts from its nominal inertials.
        bins: precomputed ``bin_sweeps(rec, width)`` (default: computed here).
        threshold: N m, least model gravity-torque amplitude over a sweep for its joint to
            count as excited (phase shift and Eq. 13); others borrow their type's ratio.
        width: angle-bin width, rad.
        complete: refuse (InputError) a recording that is implausible or does not sweep every
            joint both ways (``plausibility.check_recordings``). False: a joint without sweeps
            borrows its type's ratio and friction, as the studies' random plans need.
    Returns:
        ``RobotParams`` of ``robot.name`` (= ``rec.model`` for a built-in): ratio A/(N m),
        friction A, com_offset {link: (3,) m vs the robot's nominal, link frame} of the links
        moved, phase_shift rad per joint (0 where not estimated), std of ratio, friction and
        phase_shift from the scipy fits (None where unknown), fit_seconds.
    """
    start = time.perf_counter()
    robot = rec.robot() if robot is None else load_robot(robot)
    arm = arm_joint_indices(robot)
    n = len(arm)
    if rec.n_joints != n:
        raise InputError(
            f"recording has {rec.n_joints} joints but {robot.name} has {n} current-controlled "
            "joints"
        )
    if complete:
        check_recordings([rec])
    if bins is None:
        bins = bin_sweeps(rec, width)
    types = _actuator_types(robot, n)
    tree = robot.tree
    nominal_com = np.asarray(tree.nominal.com, dtype=float)
    com = nominal_com.copy()
    model_mass = np.asarray(tree.nominal.mass, dtype=float)
    model = _PinocchioGravity(robot, rec)

    # excitation of each sweep on the nominal model
    tau = model.torques(bins.q)
    sweeps: dict[int, list[np.ndarray]] = {j: [] for j in range(n)}
    excited_sweeps: dict[int, list[np.ndarray]] = {j: [] for j in range(n)}
    for k in np.unique(bins.sweep):
        rows = np.flatnonzero(bins.sweep == k)
        j = int(bins.joint[rows[0]])
        sweeps[j].append(rows)
        amplitude, _ = _sine_lstsq(bins.q[rows, j], tau[rows, j], bins.count[rows].astype(float))
        if amplitude >= threshold:
            excited_sweeps[j].append(rows)
    excited = [j for j in range(n) if excited_sweeps[j]]

    # 1. phase shifts and COM corrections, last link first
    phase = np.zeros(n)
    phase_std = np.zeros(n)
    for j in sorted(excited, reverse=True):
        body = int(tree.joint_body[arm[j]])
        axis = np.asarray(tree.joint_axis[arm[j]], dtype=float)
        axis = axis / np.linalg.norm(axis)
        shifts, stds, moves, weights = [], [], [], []
        for rows in excited_sweeps[j]:
            theta, c, q, w = _pairs(bins, rows, j)
            if len(theta) < MIN_PAIRS:
                continue
            _, d_real, sd = _phase_fit(theta, c, w)
            _, d_model, _ = _phase_fit(theta, model.torques(q)[:, j], w)
            delta = float(_wrap(d_real - d_model))
            moment = model.subtree_moment(q.mean(axis=0), j)
            turn = Rotation.from_rotvec(delta * axis).as_matrix() - np.eye(3)
            shifts.append(delta)
            stds.append(sd)
            moves.append(turn @ moment / model_mass[body])
            weights.append(w.sum())
        if not shifts:
            continue
        weights = np.asarray(weights) / np.sum(weights)
        phase[j] = float(weights @ np.asarray(shifts))
        phase_std[j] = float(np.sqrt(weights**2 @ np.asarray(stds) ** 2))
        move = weights @ np.asarray(moves)
        com[body] += move
        model.move_com(j, model_mass[body], move)

    # 2. Eq. (13) on the corrected model
    tau = model.torques(bins.q)
    ratio = np.full(n, np.nan)
    friction = np.zeros(n)
    ratio_std = np.zeros(n)
    friction_std = np.zeros(n)
    for j in range(n):
        if not sweeps[j]:
            continue
        rows = np.concatenate(sweeps[j])
        c = bins.current[rows, j]
        d = bins.direction[rows].astype(float)
        w = bins.count[rows].astype(float)
        if j in excited:
            r, l, sr, sl = _ratio_friction(tau[rows, j], d, c, w)
            if not r > 0:
                raise InputError(
                    f"joint {j}: Eq. (13) gives a current/torque ratio of {r:.4g} A/(N m); "
                    "the current does not follow the model's gravity torque"
                )
            ratio[j], friction[j], ratio_std[j], friction_std[j] = r, abs(l), sr, sl
        else:  # 3. friction of an unexcited joint: mean of c d over its sweep(s)
            cd = c * d
            mean = float(w @ cd / w.sum())
            spread = float(w @ (cd - mean) ** 2) / max(len(cd) - 1, 1)  # A^2 per sample
            friction[j] = abs(mean)
            friction_std[j] = np.sqrt(spread / w.sum())

    # 3. ratios of unexcited joints: the mean of the excited joints of their actuator type
    fallback = RobotParams.nominal(robot).ratio
    for j in range(n):
        if j in excited:
            continue
        peers = [i for i in excited if types[i] == types[j]]
        if peers:
            ratio[j] = float(np.mean(ratio[peers]))
            ratio_std[j] = float(np.sqrt(np.sum(ratio_std[peers] ** 2)) / len(peers))
        else:  # no excited joint of this type: the model's nominal ratio
            ratio[j] = fallback[j]
            ratio_std[j] = np.inf
        if not sweeps[j]:  # never swept: the type's mean friction too (the paper's VI-A rule)
            friction[j] = float(np.mean(friction[peers])) if peers else 0.0
            friction_std[j] = (
                float(np.sqrt(np.sum(friction_std[peers] ** 2)) / len(peers)) if peers else np.inf
            )

    offsets = {
        tree.body_names[b]: com[b] - nominal_com[b]
        for b in range(tree.nb)
        if np.any(com[b] != nominal_com[b])
    }
    std = {
        "ratio": _finite_or_none(ratio_std),
        "friction": _finite_or_none(friction_std),
        "phase_shift": _finite_or_none(phase_std),
    }
    return RobotParams(
        model=robot.name,
        ratio=ratio,
        friction=friction,
        com_offset=offsets,
        phase_shift=phase,
        std=std,
        method="scipy",
        fit_seconds=time.perf_counter() - start,
        joints=arm_joint_names(robot),
    )


def _finite_or_none(values: np.ndarray) -> list:
    """JSON-safe list: unknown (inf/nan) entries become None."""
    return [float(v) if np.isfinite(v) else None for v in values]
