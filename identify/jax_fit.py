"""The joint fit: ratio, friction, viscous term and centre-of-mass offsets of all joints at once.

Model (paper Eq. 13 with a viscous term and the gravity model of ``jaxcomp.dynamics``): in a
steady pass of joint j in direction d at pass velocity v (rad/s) the measured current is

    c = r_j tau_j(q; delta) + l_j d + b_j v,      tau_j(q; delta) = tau0_j(q) + a_j(q) . delta

where tau is the gravity torque the actuator holds (N m), r_j the current/torque ratio
(A/(N m)), l_j the friction loss (A), b_j the viscous term (A s/rad) and delta the
centre-of-mass offsets (m, each moving link's own frame) of every moving link. One
least-squares loss covers all joints, all sweeps and all recordings (which may differ in
gravity and payload).

Sweep moments make it exact and independent of the sample count: while joint j sweeps with
the others held, tau0_j and every column of a_j are a sin(theta) + b cos(theta) + c in the
swept angle, so each sweep's steady samples reduce to one 6 x 6 matrix of moments
(``identify.moments``), the regressors are evaluated at three angles per sweep (``jax.grad``
of the gravity model), and the loss reduces to per-joint sufficient statistics (``Stats``, a
K + 3 square matrix per joint for K offset components): an iteration costs the same for 10^3
or 10^6 samples.

The solve (``solve``) is variable projection: r, l and b are linear given delta and are solved
exactly inside; delta follows damped Newton steps on the reduced objective, started from three
alternating least-squares rounds (the reduced objective is not convex); the noise variance is
re-estimated from the residuals at every step. ``fit`` fits recordings jointly, ``fit_each``
and ``fit_batch`` fit many recordings each on its own in vmapped batches on the default
backend (a GPU when present).

What the data cannot determine is handled explicitly:
- offsets: a Gaussian prior toward the nominal model, ``PRIOR_COM`` m per component; directions
  no sweep excites (e.g. along a joint axis) stay at the nominal COM;
- ratios: masses stay nominal, so r is the ratio relative to the nominal mass scale (a uniform
  mass error shows as a ratio error, the gravity current the controller needs stays right); a
  joint whose swept gravity torque stays below ``EXCITATION`` N m RMS (joint 0 of an upright
  arm) gets the mean ratio of the excited joints of its actuator type (the paper's rule; the
  nominal ratio when none is excited) through a tie of relative width ``TIE``; a weak prior of
  relative width ``PRIOR_RATIO`` toward the nominal ratio keeps the problem well posed;
- viscous terms: a prior of ``PRIOR_VISCOUS`` A s/rad; a joint swept at one speed only (pass
  speeds within ``SPEED_SPREAD``) cannot tell b from l and has b held at 0.
Standard errors come from the Gauss-Newton Hessian with the noise variance estimated from the
residuals (Cramer-Rao bound); the singular values of the scaled Fisher information report the
identifiability.

Compiled code is shared by equal models: a ``FitModel`` compares equal by the content of the
robot's compiled model (not its name or file), so an edited model never reuses stale code.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from jaxcomp import current, dynamics
from jaxcomp.errors import InputError, JaxcompError
from jaxcomp.identify.bins import STEADY_FRACTION, STEADY_TRIM
from jaxcomp.identify.moments import (
    PackBuffer,
    Packed,
    SweepMoments,
    on_cpu,
    pack,
    reduce_batch,
    sweep_moments,
)
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names

#: Prior standard deviation of each COM offset component, m.
PRIOR_COM = 0.02
#: Prior relative standard deviation of each ratio around the nominal ratio.
PRIOR_RATIO = 1.0
#: Relative width of the tie of an unexcited joint's ratio to its actuator type's mean.
TIE = 1e-4
#: RMS swept gravity torque (N m) below which gravity does not excite a joint.
EXCITATION = 0.05
#: Prior standard deviation of the viscous friction, A s/rad (as current per joint speed).
PRIOR_VISCOUS = 0.1
#: Relative spread of pass speeds below which a joint counts as swept at one speed.
SPEED_SPREAD = 0.1
#: Linear parameters per joint: ratio, friction, viscous.
_LIN = 3
#: Scales that make the parameters comparable for the identifiability report.
_COM_SCALE = 1e-3  # m: offsets in mm


class FitError(JaxcompError):
    """The fit did not converge or produced non-finite parameters."""


class Stats(NamedTuple):
    """Per-joint sufficient statistics of the least squares (F = K + 3 features).

    S (n, F, F) = sum phi phi^T, s (n, F) = sum phi c, c2 (n,) = sum c^2 (A^2) over the steady
    samples of each joint's sweeps, with phi = [tau0 (N m), reg (K, N), d, v (rad/s)] and c
    the current (A); samples (n,); torque2 (n,) = sum tau0^2, N^2 m^2 (excitation).
    """

    S: jax.Array
    s: jax.Array
    c2: jax.Array
    samples: jax.Array
    torque2: jax.Array

    @property
    def excitation(self) -> jax.Array:
        """(n,) N m, RMS nominal gravity torque of each joint over its sweeps."""
        return jnp.sqrt(self.torque2 / jnp.maximum(self.samples, 1.0))

    def __add__(self, other: Stats) -> Stats:  # type: ignore[override]
        return Stats(*(a + b for a, b in zip(self, other, strict=True)))


class Solution(NamedTuple):
    """Result of ``solve`` (device arrays; vmapped fits have a leading batch axis)."""

    ratio: jax.Array  # (n,) A/(N m)
    friction: jax.Array  # (n,) A, signed (the params file stores |l|)
    viscous: jax.Array  # (n,) A s/rad
    com: jax.Array  # (K,) m
    cov: jax.Array  # (P, P) covariance of [ratio, friction, viscous, com], P = 3 n + K
    sigma: jax.Array  # A, noise standard deviation estimated from the residuals
    singular: jax.Array  # (P,) singular values of the scaled Fisher information
    excited: jax.Array  # (n,) bool
    iterations: jax.Array
    converged: jax.Array
    rss: jax.Array  # residual sum of squares over the steady samples, A^2


@dataclass(frozen=True, eq=False)
class FitModel:
    """What a fit needs of the robot: its current-controlled joints, the moving links whose
    COM offsets are fitted, the nominal ratios and the actuator types.

    Made once per robot and kept on it (``fit_model``). It is the static argument of the
    jitted fit functions; two ``FitModel`` compare equal (and hash alike) when their robots'
    compiled models have the same content and they fit the same joints and links, so equal
    models share compiled code and an edited model gets its own.

    Attributes:
        robot: the robot model.
        joints: (n,) indices of the current-controlled joints among the robot's joints.
        links: names of the L links whose COM offset is fitted (K = 3 L components).
        link_ids: (L,) their indices among the robot's links.
        ratio0: (n,) A/(N m), the nominal current/torque ratios.
        types: actuator type label of each joint (ratio ties between unexcited joints).
    """

    robot: Robot
    joints: np.ndarray
    links: tuple[str, ...]
    link_ids: np.ndarray
    ratio0: np.ndarray
    types: tuple[str, ...]

    @cached_property
    def _identity(self) -> tuple:
        return (
            self.robot.digest,
            tuple(int(j) for j in self.joints),
            self.links,
            tuple(int(i) for i in self.link_ids),
            tuple(float(r) for r in self.ratio0),
            self.types,
        )

    def __eq__(self, other: object) -> bool:
        return isinstance(other, FitModel) and self._identity == other._identity

    def __hash__(self) -> int:
        return hash(self._identity)

    @property
    def n(self) -> int:
        return len(self.joints)

    @property
    def K(self) -> int:
        return 3 * len(self.links)

    def parameter_names(self) -> list[str]:
        names = [f"ratio[{j}]" for j in range(self.n)]
        names += [f"friction[{j}]" for j in range(self.n)]
        names += [f"viscous[{j}]" for j in range(self.n)]
        names += [f"com_offset[{link}].{ax}" for link in self.links for ax in "xyz"]
        return names


def fit_model(robot: Robot | str) -> FitModel:
    """The ``FitModel`` of a robot (name, path or ``Robot``), kept on the robot."""
    robot = load_robot(robot)
    return robot.cached(("jax_fit.FitModel",), lambda: _build_model(robot))


def _build_model(robot: Robot) -> FitModel:
    joints = arm_joint_indices(robot)
    tree = robot.tree
    moved = np.asarray(tree.moves)[joints].any(axis=0)
    mass = np.asarray(robot.nominal_params().mass)
    ids = np.flatnonzero(moved & (mass > 0))
    types = robot.actuator_types or tuple(f"joint{j}" for j in range(len(joints)))
    if len(types) != len(joints):
        raise InputError(
            f"{robot.name}: jaxcomp_actuator_types lists {len(types)} types for "
            f"{len(joints)} joints"
        )
    return FitModel(
        robot=robot,
        joints=joints,
        links=tuple(tree.body_names[i] for i in ids),
        link_ids=ids,
        ratio0=RobotParams.nominal(robot).ratio,
        types=tuple(types),
    )


@partial(jax.jit, static_argnums=0)
def _regressors(model: FitModel, q, swept, gravity, payload_mass, payload_com):
    """tau0 (B,) N m and d tau0 / d delta (B, K) N of the swept joint ``swept`` (B,) at each
    arm pose ``q`` (B, n) rad, under ``gravity`` (3,) m/s^2 with the recording's payload."""
    robot = model.robot
    tree = robot.tree
    nominal = robot.nominal_params()

    def tau(delta, qa, j):
        # the offset moves the link's own mass; a payload is merged in after it
        com = nominal.com.at[model.link_ids].add(delta.reshape(-1, 3))
        params = robot.with_payload(nominal._replace(com=com), payload_mass, payload_com)
        qf = jnp.zeros(tree.nv).at[model.joints].set(qa)
        return dynamics.gravity(tree, qf, params, gravity)[model.joints][j]

    delta0 = jnp.zeros(model.K)

    def one(qa, j):
        return tau(delta0, qa, j), jax.grad(tau)(delta0, qa, j)

    return jax.vmap(one)(q, swept)


_ANGLES = (0.0, 0.5 * np.pi, np.pi)


@partial(jax.jit, static_argnums=0)
def _sweep_stats(model: FitModel, m: SweepMoments) -> tuple[Stats, jax.Array]:
    """Sufficient statistics of one recording's sweeps, and each sweep's torque coefficients.

    The swept joint's tau0 and regressor are evaluated at three angles per sweep and written
    as a sin + b cos + c; the coefficients (S, 1 + K, 3) map the moments onto the features.
    """
    S = m.joint.shape[0]
    angles = jnp.asarray(_ANGLES)
    poses = jnp.repeat(m.hold[:, None, :], 3, axis=1)
    poses = poses.at[jnp.arange(S)[:, None], jnp.arange(3)[None, :], m.joint[:, None]].set(
        angles[None, :]
    )
    joint3 = jnp.repeat(m.joint, 3)
    t0, reg = _regressors(
        model, poses.reshape(-1, model.n), joint3, m.gravity, m.payload_mass, m.payload_com
    )
    vals = jnp.concatenate([t0[:, None], reg], axis=1).reshape(S, 3, 1 + model.K)
    at0, at90, at180 = vals[:, 0], vals[:, 1], vals[:, 2]
    c = 0.5 * (at0 + at180)
    coef = jnp.stack([at90 - c, 0.5 * (at0 - at180), c], axis=2)  # (S, 1 + K, 3): a, b, c
    F = model.K + 3
    L = jnp.zeros((S, F, 5))
    L = L.at[:, : F - 2, :3].set(coef).at[:, F - 2, 3].set(1.0).at[:, F - 1, 4].set(1.0)
    onehot = jax.nn.one_hot(m.joint, model.n, dtype=float)  # (S, n)
    per_S = jnp.einsum("sfa,sab,sgb->sfg", L, m.moments[:, :5, :5], L)
    per_s = jnp.einsum("sfa,sa->sf", L, m.moments[:, :5, 5])
    st = Stats(
        S=jnp.einsum("sj,sfg->jfg", onehot, per_S),
        s=jnp.einsum("sj,sf->jf", onehot, per_s),
        c2=onehot.T @ m.moments[:, 5, 5],
        samples=onehot.T @ m.moments[:, 2, 2],
        torque2=onehot.T @ per_S[:, 0, 0],
    )
    return st, coef


def _beta(theta: jax.Array, n: int, K: int) -> jax.Array:
    """(n, F) per-joint coefficients [r_j, r_j delta, l_j, b_j] of the features
    [tau0, reg, d, v]; theta = [r (n), l (n), b (n), delta (K)]: the gradient of the current
    model ``current.viscous_sweep_current`` (linear in the features) with respect to them."""
    r, l, b, delta = theta[:n], theta[n : 2 * n], theta[2 * n : 3 * n], theta[3 * n :]

    def model(phi):  # (n, F) features -> (n,) A
        tau = phi[:, 0] + phi[:, 1 : K + 1] @ delta
        return current.viscous_sweep_current(tau, phi[:, K + 1], phi[:, K + 2], r, l, b)

    return jax.grad(lambda phi: jnp.sum(model(phi)))(jnp.zeros((n, K + 3)))


def _rss(theta, st: Stats, n: int, K: int) -> jax.Array:
    b = _beta(theta, n, K)
    return jnp.sum(
        st.c2 - 2 * jnp.einsum("jf,jf->j", b, st.s) + jnp.einsum("jf,jfg,jg->j", b, st.S, b)
    )


class _Priors(NamedTuple):
    """Quadratic priors: ratio precision (n,) and mean (n,), tie rows (n, n) and weights
    (n,), viscous precision (n,)."""

    prec: jax.Array
    mean: jax.Array
    tie: jax.Array
    tie_w: jax.Array
    viscous: jax.Array


def _priors(st: Stats, ratio0: jax.Array, types: tuple[str, ...]) -> tuple[_Priors, jax.Array]:
    n = ratio0.shape[0]
    excited = st.excitation > EXCITATION
    same = jnp.asarray([[types[i] == types[k] for k in range(n)] for i in range(n)], float)
    donors = same * excited[None, :]
    has = donors.sum(1) > 0
    mean_of = donors / jnp.maximum(donors.sum(1, keepdims=True), 1.0)
    tie = (~excited)[:, None] * (jnp.eye(n) - mean_of)
    tie_w = jnp.where(has & ~excited, 1.0 / (TIE * ratio0) ** 2, 0.0)
    width = jnp.where(excited | has, PRIOR_RATIO, TIE)  # no donor: stay at the nominal ratio
    # viscous friction needs passes at different speeds: with one speed (v = speed d) it is
    # indistinguishable from the friction loss and is held at 0
    vv, vd, dd = st.S[:, -1, -1], st.S[:, -1, -2], st.S[:, -2, -2]
    one_speed = vd**2 >= (1.0 - SPEED_SPREAD**2) * vv * dd
    viscous = jnp.where(one_speed, 1.0 / (1e-6 * PRIOR_VISCOUS) ** 2, 1.0 / PRIOR_VISCOUS**2)
    return _Priors(1.0 / (width * ratio0) ** 2, ratio0, tie, tie_w, viscous), excited


def _inner(delta, st: Stats, pr: _Priors, sigma2):
    """Best linear parameters x = [r, l, b] (3n,) for fixed offsets ``delta``, and the
    objective 0.5 RSS / sigma2 + 0.5 (priors) there."""
    n = st.c2.shape[0]
    K = delta.shape[0]
    # beta_j = r_j [1, delta, 0, 0] + l_j [0, .., 1, 0] + b_j [0, .., 0, 1]
    E = jnp.zeros((K + 3, _LIN)).at[0, 0].set(1.0).at[1 : K + 1, 0].set(delta)
    E = E.at[K + 1, 1].set(1.0).at[K + 2, 2].set(1.0)
    M = jnp.einsum("fa,jfg,gb->jab", E, st.S, E)  # (n, 3, 3)
    v = jnp.einsum("fa,jf->aj", E, st.s).reshape(-1)  # (3n,) ordered [r.., l.., b..]
    A = jnp.einsum("iab,ik->aibk", M, jnp.eye(n)).reshape(_LIN * n, _LIN * n) / sigma2
    A = A + jnp.diag(jnp.concatenate([pr.prec, jnp.full(n, 1e-12), pr.viscous]))
    A = A.at[:n, :n].add(pr.tie.T @ (pr.tie_w[:, None] * pr.tie))
    rhs = v / sigma2
    rhs = rhs.at[:n].add(pr.prec * pr.mean)
    x = jnp.linalg.solve(A, rhs)
    value = (
        0.5 * (jnp.sum(st.c2) / sigma2 - x @ rhs)
        + 0.5 * jnp.sum(pr.prec * pr.mean**2)
        + 0.5 * jnp.sum(delta**2) / PRIOR_COM**2
    )
    return x, value


def _theta(delta, st, pr, sigma2):
    x, _ = _inner(delta, st, pr, sigma2)
    return jnp.concatenate([x, delta])


@partial(jax.jit, static_argnums=0)
def solve(model_key: tuple, st: Stats, max_iter: int = 50) -> Solution:
    """The joint fit on sufficient statistics (pure given the statics; vmap-able).

    Variable projection: ratio, friction and viscous terms are linear given the offsets, so
    they are solved exactly inside; the offsets follow damped Newton steps on the reduced
    objective (the ratio-versus-mass-scale valley of the full problem is flat there, not
    curved), started from three alternating least-squares rounds. The noise variance is
    re-estimated from the residuals at every step. ``model_key`` = (n, K, nominal ratios,
    actuator types), the static description of the model.
    """
    n, K, ratio0, types = model_key
    ratio0 = jnp.asarray(ratio0)
    P = _LIN * n + K
    pr, excited = _priors(st, ratio0, types)
    dof = jnp.maximum(jnp.sum(st.samples) - P, 1.0)

    def rss(delta, sigma2):
        return _rss(_theta(delta, st, pr, sigma2), st, n, K)

    def value(delta, sigma2):
        return _inner(delta, st, pr, sigma2)[1]

    grad = jax.grad(value)
    hess = jax.hessian(value)

    def step(carry):
        delta, lam, it, done, sigma2 = carry
        g, H = grad(delta, sigma2), hess(delta, sigma2)
        H = 0.5 * (H + H.T)
        cand = delta - jnp.linalg.solve(
            H + lam * jnp.diag(jnp.abs(jnp.diag(H))) + 1e-9 * jnp.eye(K), g
        )
        f, fc = value(delta, sigma2), value(cand, sigma2)
        better = fc <= f
        new = jnp.where(better, cand, delta)
        # converged: the step moves no COM by a nanometre, or changes the objective only at
        # the level of rounding
        done = (jnp.max(jnp.abs(cand - delta)) < 1e-9) | (jnp.abs(fc - f) <= 1e-13 * jnp.abs(f))
        lam = jnp.where(better, lam * 0.1, lam * 10.0)
        return new, lam, it + 1, done, jnp.maximum(rss(new, sigma2) / dof, 1e-12)

    def cont(carry):
        return (~carry[3]) & (carry[2] < max_iter) & (carry[1] < 1e10)

    def offsets_given_ratio(r, sigma2):
        # for fixed ratios the objective is quadratic in z = [l, b, delta]: one Newton step
        def objective(z):
            theta = jnp.concatenate([r, z])
            return 0.5 * _rss(theta, st, n, K) / sigma2 + 0.5 * (
                jnp.sum(pr.viscous * z[n : 2 * n] ** 2) + jnp.sum(z[2 * n :] ** 2) / PRIOR_COM**2
            )

        z0 = jnp.zeros(2 * n + K)
        H = jax.hessian(objective)(z0) + 1e-12 * jnp.eye(2 * n + K)
        return -jnp.linalg.solve(H, jax.grad(objective)(z0))[2 * n :]

    def alternate(_, delta):
        sigma2 = jnp.maximum(rss(delta, 1.0) / dof, 1e-12)
        r = _inner(delta, st, pr, sigma2)[0][:n]
        return offsets_given_ratio(r, sigma2)

    # start the Newton iteration from a few alternating (ratio | offsets) least-squares
    # rounds: the reduced objective is not convex, and from the nominal COM it may otherwise
    # end in a local minimum
    delta0 = jax.lax.fori_loop(0, 3, alternate, jnp.zeros(K))
    sigma2_0 = jnp.maximum(rss(delta0, 1.0) / dof, 1e-12)
    init = (delta0, jnp.asarray(1e-4), jnp.asarray(0), jnp.asarray(False), sigma2_0)
    delta, lam, it, done, sigma2 = jax.lax.while_loop(cont, step, init)
    theta = _theta(delta, st, pr, sigma2)

    # Fisher information of [r, l, delta] (Gauss-Newton Hessian) plus the priors
    Bj = jax.jacfwd(lambda th: _beta(th, n, K))(theta)  # (n, F, P)
    H_data = jnp.einsum("jfp,jfg,jgq->pq", Bj, st.S, Bj) / sigma2
    H_prior = jnp.zeros((P, P))
    H_prior = H_prior.at[:n, :n].add(jnp.diag(pr.prec) + pr.tie.T @ (pr.tie_w[:, None] * pr.tie))
    H_prior = H_prior.at[2 * n : 3 * n, 2 * n : 3 * n].add(jnp.diag(pr.viscous))
    H_prior = H_prior.at[3 * n :, 3 * n :].add(jnp.eye(K) / PRIOR_COM**2)
    H_prior = H_prior.at[n : 2 * n, n : 2 * n].add(jnp.eye(n) * 1e-12)
    cov = jnp.linalg.inv(H_data + H_prior)
    scale = jnp.concatenate([ratio0, jnp.full(n, 0.1), jnp.full(n, 0.01), jnp.full(K, _COM_SCALE)])
    # symmetric positive semi-definite: the singular values are the eigenvalues, and a batched
    # eigvalsh is ~1000x faster than a batched SVD of this size on a GPU
    eig = jnp.linalg.eigvalsh(H_data * scale[:, None] * scale[None, :])
    singular = jnp.sort(jnp.abs(eig))[::-1]
    converged = done & jnp.all(jnp.isfinite(theta))
    return Solution(
        ratio=theta[:n],
        friction=theta[n : 2 * n],
        viscous=theta[2 * n : 3 * n],
        com=theta[3 * n :],
        cov=cov,
        sigma=jnp.sqrt(sigma2),
        singular=singular,
        excited=excited,
        iterations=it,
        converged=converged,
        rss=_rss(theta, st, n, K),
    )


def _key(model: FitModel) -> tuple:
    return (model.n, model.K, tuple(float(r) for r in model.ratio0), model.types)


_BUCKET = 8  # sweeps are padded to a multiple of this, so few shapes get compiled


def _padded(m: SweepMoments, size: int, axis: int = 0) -> SweepMoments:
    """``m`` with zero sweeps appended along its sweep ``axis`` (1 when stacked) up to
    ``size``: a sweep of zero moments adds nothing to a fit."""

    def pad(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a)
        width = [(0, 0)] * a.ndim
        width[axis] = (0, size - a.shape[axis])
        return np.pad(a, width)

    return m._replace(**{k: pad(getattr(m, k)) for k in ("joint", "hold", "moments", "count")})


def _bucket(n: int) -> int:
    return -(-n // _BUCKET) * _BUCKET


def prepare(model: FitModel, rec: Recording) -> tuple[Stats, jax.Array, SweepMoments]:
    """Moments, sufficient statistics and torque coefficients of one recording."""
    m = sweep_moments(rec)
    st, coef = _sweep_stats(model, _padded(m, _bucket(m.n_sweeps)))
    return st, coef, m


def phase_shift(
    model: FitModel, coef: np.ndarray, joint: np.ndarray, com: np.ndarray, cov_com: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Phase shift (rad) of each joint's gravity torque over its first sweep, fitted COM
    against nominal, and its standard error (delta method); 0 for a joint without a sweep or
    without gravity torque. ``joint`` (S,): the swept joint of each sweep of ``coef`` (-1: an
    empty sweep). The phase of a sin + b cos is atan2(b, a) (cf. Eq. 17-19).
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
    if not recs:
        raise InputError("no recording to fit")
    names = {(r.model, r.robot().controlled_joints) for r in recs}
    if len(names) > 1:
        raise InputError(
            f"recordings of different models (or joints) cannot be fitted jointly: {sorted(names)}"
        )
    return fit_model(recs[0].robot())


def _params(
    model: FitModel, rec: Recording, sol: Solution, phase, phase_std, seconds: float
) -> RobotParams:
    sol = jax.tree.map(np.asarray, sol)
    if not bool(sol.converged) or not np.all(np.isfinite(sol.ratio)):
        raise FitError(
            f"the joint fit did not converge after {int(sol.iterations)} iterations "
            f"(noise estimate {float(sol.sigma):.3g} A); nothing was written"
        )
    n = model.n
    std = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))
    com = sol.com.reshape(-1, 3)
    com_std = std[_LIN * n :].reshape(-1, 3)
    names = model.parameter_names()
    prior = _prior_widths(model)
    return RobotParams(
        model=rec.model,
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
        joints=arm_joint_names(model.robot),
        diagnostics={
            "iterations": int(sol.iterations),
            "current_noise": float(sol.sigma),
            "viscous": sol.viscous,
            "viscous_std": std[2 * n : 3 * n],
            "ratio_source": [
                "fit" if e else f"mean of type {model.types[j]}" for j, e in enumerate(sol.excited)
            ],
            "singular_values": sol.singular,
            "prior_dominated": [names[i] for i in np.flatnonzero(std > 0.5 * prior)],
        },
    )


def _prior_widths(model: FitModel) -> np.ndarray:
    """Prior standard deviation of each parameter (inf: no prior)."""
    n = model.n
    return np.concatenate(
        [
            PRIOR_RATIO * model.ratio0,
            np.full(n, np.inf),
            np.full(n, PRIOR_VISCOUS),
            np.full(model.K, PRIOR_COM),
        ]
    )


def fit(recordings: Recording | list[Recording], max_iter: int = 50) -> RobotParams:
    """Fit one parameter set to one or several recordings of one robot, jointly.

    The recordings may differ in gravity (mounting) and payload. Raises ``FitError`` when the
    fit does not converge.
    """
    recs = [recordings] if isinstance(recordings, Recording) else list(recordings)
    model = _check_same_model(recs)
    start = time.perf_counter()
    prepared = [prepare(model, r) for r in recs]
    st = prepared[0][0]
    for other in prepared[1:]:
        st = st + other[0]
    sol = jax.block_until_ready(solve(_key(model), st, max_iter))
    _, coef, m = prepared[0]
    return _result(model, recs[0], sol, coef, m.joint, time.perf_counter() - start)


def _result(model, rec, sol, coef, joint, seconds) -> RobotParams:
    cov = np.asarray(sol.cov)[_LIN * model.n :, _LIN * model.n :]
    phase, phase_std = phase_shift(model, coef, joint, np.asarray(sol.com), cov)
    return _params(model, rec, sol, phase, phase_std, seconds)


@partial(jax.jit, static_argnums=(0, 2, 3))
def _fit_packed(model: FitModel, p: Packed, length: int, sequential: bool):
    """Stacked packed recordings (leading batch axis) -> (Solution, coef, joint, count) of
    each: moments, statistics and fit in one computation on the device (``sequential``: the
    moments one recording after another, see ``moments.reduce_batch``)."""
    m = reduce_batch(p, length, STEADY_FRACTION, STEADY_TRIM, sequential)
    sol, coef = _fit_moments.__wrapped__(model, m)
    return sol, coef, m.joint, m.count


def _join(parts: list[tuple[Packed, int]], size: int) -> tuple[Packed, int]:
    """Groups of packed recordings on the device as one batch of ``size``: padded to the
    largest sizes, the last recording repeated to fill the batch."""
    length = max(n for _, n in parts)
    leaves = [p for p, _ in parts]
    shapes = jax.tree.map(
        lambda *a: tuple(max(dims) for dims in zip(*(x.shape[1:] for x in a), strict=True)),
        *leaves,
    )

    def fit(a, shape):
        if a.shape[1:] == shape:
            return a
        return jnp.pad(a, [(0, 0)] + [(0, s - d) for s, d in zip(shape, a.shape[1:], strict=True)])

    def join(*a):
        a = jnp.concatenate(a)
        return jnp.concatenate([a, jnp.repeat(a[-1:], size - a.shape[0], axis=0)])

    padded = [jax.tree.map(fit, p, shapes) for p in leaves]
    return jax.tree.map(join, *padded), length


#: Recordings per host-to-device transfer in ``fit_each`` (a worker's reused buffer).
_GROUP = 16


def fit_each(
    recordings: Iterable[Recording],
    batch: int | None = None,
    progress: bool = False,
    workers: int | None = None,
) -> list[RobotParams]:
    """Fit every recording on its own, ``batch`` at a time in one vmapped computation on the
    default backend (a GPU when present): moments, statistics and fit of a batch in one call.

    ``batch``: recordings per call (default 256 on an accelerator, 8 on a CPU). ``workers``:
    host threads that pack the recordings (``_GROUP`` to a transfer) and send them to the
    device while the device fits the batch before (default: up to 8 on an accelerator, where
    more only contend for host memory bandwidth; 1 on a CPU). Raises
    ``FitError`` naming the recordings whose fit did not converge (no result then).
    """
    accelerated = not on_cpu()
    batch = int(batch or (256 if accelerated else 8))
    workers = max(1, int(workers or (min(8, os.cpu_count() or 1) if accelerated else 1)))
    group = min(_GROUP, batch)
    local = threading.local()
    out: list[RobotParams] = []
    failed: list[int] = []
    model: FitModel | None = None
    name = None  # the recordings' model
    bar = tqdm(desc="fitting", unit="rec", disable=not progress)

    def send(recs: list[Recording]) -> tuple[Packed, int]:
        # on a CPU the device array may alias the host buffer: no reuse there
        if accelerated and not hasattr(local, "buffer"):
            local.buffer = PackBuffer()
        packed, length = pack(recs, local.buffer if accelerated else None)
        return jax.block_until_ready(jax.device_put(packed)), length

    def finish(chunk: list[Recording], result, start: float) -> None:
        sols, coef, joint, count = jax.tree.map(np.asarray, result)
        joint = np.where(count > 0, joint, -1)
        seconds = (time.perf_counter() - start) / len(chunk)
        for i, rec in enumerate(chunk):
            sol = jax.tree.map(lambda a, i=i: a[i], sols)
            try:
                out.append(_result(model, rec, sol, coef[i], joint[i], seconds))
            except FitError:
                failed.append(len(out) + len(failed))
        bar.update(len(chunk))

    pending = None
    with ThreadPoolExecutor(workers) as pool:
        for chunk in _chunks(recordings, batch):
            if model is None:
                name = chunk[0].model
                model = fit_model(name)
            if any(r.model != name for r in chunk):
                raise InputError("fit_each needs recordings of one robot model")
            start = time.perf_counter()
            groups = [chunk[i : i + group] for i in range(0, len(chunk), group)]
            packed, length = _join(list(pool.map(send, groups)), batch)
            result = _fit_packed(model, packed, length, not accelerated)  # async: runs on
            if pending is not None:
                finish(*pending)
            pending = (chunk, result, start)
        if pending is not None:
            finish(*pending)
    bar.close()
    if model is None:
        raise InputError("no recording to fit")
    if failed:
        raise FitError(f"the fit of recording(s) {failed} did not converge; nothing was written")
    return out


def _chunks(items: Iterable, size: int) -> Iterable[list]:
    chunk: list = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class BatchFit(NamedTuple):
    """Result of ``fit_batch`` (host arrays, leading axis W = recordings).

    Attributes:
        solution: the ``Solution`` of every recording (ratio (W, n) A/(N m), friction (W, n)
            A, viscous (W, n) A s/rad, com (W, K) m, cov (W, P, P), ...).
        coef: (W, S, 1 + K, 3) torque coefficients of each sweep (see ``phase_shift``).
        std: (W, P) standard errors of [ratio, friction, viscous, com], sqrt(diag cov).
        compile_seconds: s spent compiling (0 when the batch shape was compiled before).
        seconds: s of the fits proper (compilation excluded, device sync included).
    """

    solution: Solution
    coef: np.ndarray
    std: np.ndarray
    compile_seconds: float
    seconds: float


@partial(jax.jit, static_argnums=0)
def _fit_moments(model: FitModel, m: SweepMoments) -> tuple[Solution, jax.Array]:
    """Stacked moments (leading batch axis) -> (Solution, coef) of every recording."""
    st, coef = jax.vmap(_sweep_stats.__wrapped__, in_axes=(None, 0))(model, m)
    return jax.vmap(solve.__wrapped__, in_axes=(None, 0))(_key(model), st), coef


def _compiled_fit(model: FitModel, chunk: SweepMoments, shape: tuple) -> tuple[Callable, float]:
    """``_fit_moments`` compiled ahead of time for ``chunk`` (so that its time is known),
    kept on the robot per model and ``shape`` = (batch, sweeps, mesh); and the seconds spent
    compiling it now (0 when it was compiled before)."""
    seconds = 0.0

    def build() -> Callable:
        nonlocal seconds
        t0 = time.perf_counter()
        compiled = _fit_moments.lower(model, chunk).compile()
        seconds = time.perf_counter() - t0
        return compiled

    return model.robot.cached(("jax_fit.fit_batch", model, *shape), build), seconds


def fit_batch(
    model: FitModel,
    moments: SweepMoments,
    *,
    batch: int | None = None,
    mesh: Mesh | None = None,
    progress: Callable[[int], None] | None = None,
) -> BatchFit:
    """Fit W recordings each on its own from their stacked sweep moments, on the default
    backend (a GPU when present), ``batch`` at a time in one vmapped computation.

    ``moments``: a ``SweepMoments`` with a leading axis W on every field (joint (W, S), hold
    (W, S, n), moments (W, S, 6, 6), count (W, S), gravity (W, 3), payload_mass (W,),
    payload_com (W, 3)), e.g. ``identify.moments.sweep_moments_batch``; a sweep of zero moments
    adds nothing. ``mesh``: a ``jax.sharding.Mesh`` with the single axis "batch" to shard each
    batch over (its devices); the batch is rounded up to a multiple of the mesh size and the
    last batch padded with copies of the last recording (dropped). The results are those of
    ``solve`` per recording; non-converged fits are reported in ``solution.converged``, not
    raised. ``progress(k)`` after each batch of k recordings.
    """
    w = int(moments.moments.shape[0])
    if w < 1 or moments.moments.ndim != 4:
        raise InputError("moments must be stacked: moments (W, S, 6, 6) with W >= 1")
    shards = 1 if mesh is None else mesh.size
    b = w if batch is None else max(1, min(int(batch), w))
    b = -(-b // shards) * shards
    size = _bucket(moments.moments.shape[1])
    padded = _padded(moments, size, axis=1)
    padded = padded._replace(
        payload_mass=np.asarray(padded.payload_mass, float),
        gravity=np.asarray(padded.gravity, float),
        payload_com=np.asarray(padded.payload_com, float),
    )
    place = (
        (lambda x: x)
        if mesh is None
        else partial(jax.device_put, device=NamedSharding(mesh, PartitionSpec("batch")))
    )
    compile_seconds, seconds = 0.0, 0.0
    sols, coefs = [], []
    for start in range(0, w, b):
        idx = np.minimum(np.arange(start, start + b), w - 1)
        chunk = place(jax.tree.map(lambda a, idx=idx: np.asarray(a)[idx], padded))
        compiled, compiling = _compiled_fit(model, chunk, (b, size, mesh))
        compile_seconds += compiling
        t0 = time.perf_counter()
        sol, coef = jax.block_until_ready(compiled(chunk))
        k = min(b, w - start)
        sols.append(jax.tree.map(lambda a, k=k: np.asarray(a)[:k], sol))
        coefs.append(np.asarray(coef)[:k])
        seconds += time.perf_counter() - t0
        if progress is not None:
            progress(k)
    solution = jax.tree.map(lambda *a: np.concatenate(a), *sols)
    std = np.sqrt(np.clip(np.diagonal(solution.cov, axis1=-2, axis2=-1), 0.0, None))
    return BatchFit(solution, np.concatenate(coefs), std, compile_seconds, seconds)


#: A friction loss whose standard error exceeds this (A) is not determined (no sweep of its joint).
_FRICTION_UNKNOWN = 1.0


def identified(model: FitModel, excited: np.ndarray, std: np.ndarray) -> np.ndarray:
    """(..., P) bool: which of [ratio, friction, viscous, com] the data determine in a fit.

    Not determined: the ratio of an unexcited joint (``excited`` (..., n) false: tied to its
    actuator type's mean), a viscous term held at zero (joint swept at one speed), a friction
    loss with a standard error beyond 1 A (joint not swept), and any parameter whose standard
    error ``std`` (..., P) exceeds half its prior width (``prior_dominated`` in the params).
    """
    n = model.n
    std = np.asarray(std, float)
    ok = std <= 0.5 * _prior_widths(model)
    ok[..., :n] &= np.asarray(excited, bool)
    ok[..., n : 2 * n] &= std[..., n : 2 * n] < _FRICTION_UNKNOWN
    ok[..., 2 * n : 3 * n] &= std[..., 2 * n : 3 * n] > 1e-3 * PRIOR_VISCOUS
    return ok
