"""The joint fit: ratio, friction, viscous term and centre-of-mass offsets of all joints at once.

Model (paper Eq. 13 with a viscous term and the gravity model of ``jaxcomp.dynamics``): in a
steady pass of joint j in direction d at pass velocity v (rad/s) the measured current is

    c = r_j tau_j(q; delta) + l_j d + b_j v,      tau_j(q; delta) = tau0_j(q) + a_j(q) . delta

where tau is the gravity torque the actuator holds (N m) at the sample's pose q (the held
joints to first order about the sweep's mean pose: they give way under load), r_j > 0 the
current/torque ratio (A/(N m)), l_j the friction loss (A), b_j the viscous term (A s/rad) and
delta the centre-of-mass offsets (m, each moving link's own frame) of every moving link. The
transfers between sweeps add every moving joint's cruise samples with the same model, tau
then the gravity plus the inertial, Coriolis and centrifugal torques at the sample's velocity
and acceleration (``identify.transfers``, ``_transfer_stats``). One least-squares loss
covers all joints, all sweeps and transfers and all recordings (which may differ in gravity
and payload), each joint with its own noise variance.

Sweep moments make it exact and independent of the sample count (``identify.moments``): each
sweep's steady samples reduce to one small matrix; the regressors are evaluated at a few poses
per sweep (``jax.grad`` of the gravity model) and the loss reduces to per-joint sufficient
statistics (``Stats``, a K + 3 square matrix per joint for K offset components): an iteration
costs the same for 10^3 or 10^6 samples.

The solve (``solve``) is variable projection: for given ratios the model is linear in delta,
l and b, which are solved exactly inside; log r follows damped Newton steps on the reduced
objective, started from each joint's ratio from its nominal gravity torque alone. ``fit`` fits
recordings jointly, ``fit_each`` and ``fit_batch`` fit many recordings each on its own in
vmapped batches on the default backend (a GPU when present).

Priors, each the same in any current unit and on any robot:
- offsets: Gaussian toward the nominal model, per link ``com_prior`` m per axis (the model's
  ``jaxcomp_com_prior``, else ``PRIOR_COM_FRACTION`` of the link's radius of gyration, at
  least ``PRIOR_COM_MIN``; ``fit(com_prior=...)`` sets one for every link);
- ratios: log r Gaussian (``PRIOR_LOG_RATIO``) around the data's ratio scale, the nominal
  ratios' proportions scaled by the median of the excited joints' ratios to them (a joint whose
  prefit the unknown COM offsets dominate does not drag it); a joint the
  data do not excite (its nominal torque determines its ratio to worse than
  ``EXCITED``) is tied (``TIE``) to the excited joints of its actuator type only where the
  model declares types (``jaxcomp_actuator_types``), and keeps the data's scale otherwise;
- viscous terms: ``PRIOR_VISCOUS`` x the joint's RMS current over its RMS pass speed; a joint
  swept at one speed only (pass speeds within ``SPEED_SPREAD``) cannot tell b from l and has b
  held at 0; friction losses: none to speak of.

What the data determine, and what not: standard errors come from the Gauss-Newton Hessian
with the priors (Cramer-Rao bound), and again with every prior relaxed 100-fold. A parameter
whose error widens by ``DATA_DOMINATED`` or more is prior-dominated; a ratio is identified when
the data determine it to ``RATIO_IDENTIFIED``. Upright in one mounting a ratio trades with the
radial COM offsets of the links it carries (masses stay nominal): it is reported as confounded
with the link's COM, and a recording with a known payload (or a second mounting) fitted
jointly identifies it.

Compiled code is shared by equal models: a ``FitModel`` compares equal by the content of the
robot's compiled model (not its name or file), so an edited model never reuses stale code.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
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
from jaxcomp.identify import traced
from jaxcomp.identify.moments import SweepMoments, z_index
from jaxcomp.identify.packing import PackBuffer, Packed, pack
from jaxcomp.identify.steady import STEADY_FRACTION, STEADY_TRIM
from jaxcomp.identify.sweep_reduction import on_cpu, reduce_batch, sweep_moments
from jaxcomp.identify.transfers import (
    TransferBins,
    bucket,
    empty_bins,
    padded_bins,
    stack_bins,
    transfer_bins,
)
from jaxcomp.params import gyration_radii
from jaxcomp.plausibility import check_recordings, recording_problems
from jaxcomp.recording import Recording
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names

#: Default prior standard deviation of each COM offset component, as a fraction of the link's
#: radius of gyration about its COM (its size as the mass sees it), m/m; at least ``PRIOR_COM_MIN``.
PRIOR_COM_FRACTION = 0.1
#: Smallest default COM prior, m.
PRIOR_COM_MIN = 0.002
#: Prior standard deviation of log(ratio) around the data's ratio scale (the median of the
#: excited joints' ratios relative to the nominal ones): a factor e either way.
PRIOR_LOG_RATIO = 1.0
#: A joint is excited when its swept nominal gravity torque alone determines its ratio to
#: this relative standard error (the gravity signal against the current noise), 1.
EXCITED = 0.05
#: Width of the tie of an unexcited joint's log(ratio) to the mean of the excited joints of its
#: actuator type (only where the model declares types: ``jaxcomp_actuator_types``).
TIE = 0.05
#: Prior standard deviation of each viscous term, as a fraction of the joint's RMS current over
#: its RMS pass speed, (A s/rad) / (A s/rad).
PRIOR_VISCOUS = 1.0
#: Relative spread of pass speeds below which a joint counts as swept at one speed.
SPEED_SPREAD = 0.1
#: A parameter is determined by the data when relaxing every prior 100-fold widens its
#: standard error by less than this factor.
DATA_DOMINATED = 1.5
#: A ratio is reported as identified when it is determined by the data and its relative
#: standard error is at most this (so that its error stays within 1 % with ~3 sigma).
RATIO_IDENTIFIED = 0.003
#: Ratios stay within exp(+-RATIO_RANGE) of the data's scale; a COM offset beyond COM_RANGE
#: prior widths means a fit that ran away (not converged).
RATIO_RANGE = float(np.log(1e3))
COM_RANGE = 100.0
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
    the current (A); samples (n,).
    """

    S: jax.Array
    s: jax.Array
    c2: jax.Array
    samples: jax.Array

    def __add__(self, other: Stats) -> Stats:  # type: ignore[override]
        return Stats(*(a + b for a, b in zip(self, other, strict=True)))


class Solution(NamedTuple):
    """Result of ``solve`` (device arrays; vmapped fits have a leading batch axis).

    P = 3 n + K parameters [ratio, friction, viscous, com]. ``identified`` (P,): the data
    determine the parameter (a ratio: also to ``RATIO_IDENTIFIED``); ``data_dominated`` (P,):
    relaxing the priors 100-fold widens its standard error by less than ``DATA_DOMINATED``;
    ``confounded`` (n,): an excited joint whose ratio rests on the COM prior, and
    ``confounded_link`` (n,) the fitted link (index into ``FitModel.links``) most correlated
    with it; ``excitation`` (n,): relative standard error of each ratio from the nominal
    torque alone (gravity; in the transfers also inertial and Coriolis; inf: no signal).
    """

    ratio: jax.Array  # (n,) A/(N m)
    friction: jax.Array  # (n,) A, signed (the params file stores |l|)
    viscous: jax.Array  # (n,) A s/rad
    com: jax.Array  # (K,) m
    cov: jax.Array  # (P, P) covariance of [ratio, friction, viscous, com]
    sigma: jax.Array  # (n,) A, noise standard deviation of each joint from the residuals
    singular: jax.Array  # (P,) singular values of the scaled Fisher information
    excited: jax.Array  # (n,) bool
    excitation: jax.Array  # (n,)
    identified: jax.Array  # (P,) bool
    data_dominated: jax.Array  # (P,) bool
    confounded: jax.Array  # (n,) bool
    confounded_link: jax.Array  # (n,) int
    iterations: jax.Array
    converged: jax.Array
    rss: jax.Array  # residual sum of squares over the steady samples, A^2


@dataclass(frozen=True, eq=False)
class FitModel:
    """What a fit needs of the robot: its current-controlled joints, the moving links whose
    COM offsets are fitted, the nominal ratios, the actuator types and the COM prior.

    Made once per robot and kept on it (``fit_model``). It is the static argument of the
    jitted fit functions; two ``FitModel`` compare equal (and hash alike) when their robots'
    compiled models have the same content and they fit the same joints and links with the same
    prior, so equal models share compiled code and an edited model gets its own.

    Attributes:
        robot: the robot model.
        joints: (n,) indices of the current-controlled joints among the robot's joints.
        links: names of the L links whose COM offset is fitted (K = 3 L components).
        link_ids: (L,) their indices among the robot's links.
        ratio0: (n,) A/(N m), the nominal current/torque ratios (only their proportions
            matter: the fit scales them to the data).
        types: the actuator type of each joint when the model declares them, else None.
        com_prior: (L,) m, prior standard deviation of each link's COM offset per axis.
    """

    robot: Robot
    joints: np.ndarray
    links: tuple[str, ...]
    link_ids: np.ndarray
    ratio0: np.ndarray
    types: tuple[str, ...] | None
    com_prior: np.ndarray

    @cached_property
    def _identity(self) -> tuple:
        return (
            self.robot.digest,
            tuple(int(j) for j in self.joints),
            self.links,
            tuple(int(i) for i in self.link_ids),
            tuple(float(r) for r in self.ratio0),
            self.types,
            tuple(float(c) for c in self.com_prior),
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

    def with_com_prior(self, length: float | None) -> FitModel:
        """This model with a COM prior of ``length`` m on every link (None: unchanged)."""
        if length is None:
            return self
        length = float(length)
        if not (np.isfinite(length) and length > 0):
            raise InputError(f"the COM prior must be a length > 0 m, got {length}")
        return dataclasses.replace(self, com_prior=np.full(len(self.links), length))


def fit_model(robot: Robot | str, com_prior: float | None = None) -> FitModel:
    """The ``FitModel`` of a robot (name, path or ``Robot``), kept on the robot; ``com_prior``
    m overrides the model's COM prior (``default_com_prior``) on every link."""
    robot = load_robot(robot)
    model = robot.cached(("jax_fit.FitModel",), lambda: _build_model(robot))
    return model.with_com_prior(com_prior)


def default_com_prior(robot: Robot, link_ids: np.ndarray) -> np.ndarray:
    """(L,) m: the COM prior of each link: the model's ``jaxcomp_com_prior`` (m, one value)
    when it declares one, else ``PRIOR_COM_FRACTION`` of the link's radius of gyration about
    its COM, sqrt(trace(I) / 2 m), and at least ``PRIOR_COM_MIN``."""
    declared = robot.custom_numeric("jaxcomp_com_prior")
    if declared is not None:
        value = float(np.asarray(declared).ravel()[0])
        if not (np.isfinite(value) and value > 0):
            raise InputError(f"{robot.name}: jaxcomp_com_prior must be a length > 0 m, got {value}")
        return np.full(len(link_ids), value)
    gyration = gyration_radii(robot.nominal_params())[link_ids]
    return np.maximum(PRIOR_COM_FRACTION * gyration, PRIOR_COM_MIN)


def _build_model(robot: Robot) -> FitModel:
    joints = arm_joint_indices(robot)
    tree = robot.tree
    moved = np.asarray(tree.moves)[joints].any(axis=0)
    mass = np.asarray(robot.nominal_params().mass)
    ids = np.flatnonzero(moved & (mass > 0))
    types = robot.actuator_types
    if types is not None and len(types) != len(joints):
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
        types=None if types is None else tuple(types),
        com_prior=default_com_prior(robot, ids),
    )


def _offset_params(model: FitModel, payload_mass, payload_com) -> Callable:
    """delta (K,) m -> the nominal ``InertialParams`` with every moving link's COM moved by
    its offset in delta (the offset moves the link's own mass; the recording's payload is
    merged in after it)."""
    robot = model.robot
    nominal = robot.nominal_params()

    def params(delta):
        com = nominal.com.at[model.link_ids].add(delta.reshape(-1, 3))
        return robot.with_payload(nominal._replace(com=com), payload_mass, payload_com)

    return params


def _gravity_of(model: FitModel, gravity, payload_mass, payload_com) -> Callable:
    """(delta (K,) m, q (n,) rad) -> (n,) N m: the current-controlled joints' gravity torque
    at arm pose q under ``gravity`` (3,) m/s^2, the COM offsets delta applied
    (``_offset_params``)."""
    tree, params = model.robot.tree, _offset_params(model, payload_mass, payload_com)

    def tau(delta, qa):
        qf = jnp.zeros(tree.nv).at[model.joints].set(qa)
        return dynamics.gravity(tree, qf, params(delta), gravity)[model.joints]

    return tau


def _motion_of(model: FitModel, payload_mass, payload_com) -> Callable:
    """(delta (K,) m, q (n,) rad, dq (n,) rad/s, ddq (n,) rad/s^2) -> (n,) N m: the
    current-controlled joints' torque of motion M(q) ddq + C(q, dq) dq (the other joints at
    rest), the COM offsets delta applied (``_offset_params``)."""
    tree, params = model.robot.tree, _offset_params(model, payload_mass, payload_com)

    def tau(delta, qa, va, aa):
        qf, vf, af = (jnp.zeros(tree.nv).at[model.joints].set(x) for x in (qa, va, aa))
        return dynamics.inverse_dynamics(tree, qf, vf, af, params(delta), jnp.zeros(3))[
            model.joints
        ]

    return tau


@partial(jax.jit, static_argnums=0)
def _regressors(model: FitModel, q, swept, gravity, payload_mass, payload_com):
    """[tau0 (N m), d tau0 / d delta (K, N)] (B, 1 + K) of the swept joint ``swept`` (B,) at
    each arm pose ``q`` (B, n) rad, under ``gravity`` (3,) m/s^2 with the recording's
    payload."""
    tau = _gravity_of(model, gravity, payload_mass, payload_com)
    delta0 = jnp.zeros(model.K)

    def one(qa, j):
        def of(delta):
            return tau(delta, qa)[j]

        return jnp.concatenate([of(delta0)[None], jax.grad(of)(delta0)])

    return jax.vmap(one)(q, swept)


#: Transfer bins whose features are formed at once (``_transfer_stats``).
_TRANSFER_CHUNK = 64
#: Transfer bins that share the Coriolis torque's offset Jacobian, interpolated between the
#: block's first and last bin (a bin of another leg than both gets none): the Jacobian costs
#: ~30 times a bin's torque (``dynamics.inverse_dynamics``).
_CORIOLIS_BLOCK = 16
#: Bins of one leg: velocities within this fraction of the largest joint speed.
_SAME_LEG = 0.05


def _transfer_stats(model: FitModel, tb: TransferBins, gravity, payload_mass, payload_com) -> Stats:
    """Sufficient statistics of one recording's transfer bins (``identify.transfers``): every
    joint's features [tau0 = g(q) + M(q) ddq + C(q, dq) dq (N m, nominal model), d tau0 /
    d delta (K), sign dq, dq (rad/s)] at each bin's mean pose, velocity and acceleration,
    weighted by the samples it counts (M ddq + C dq in one ``dynamics.inverse_dynamics``).
    The Coriolis torque's dependence on the COM offsets counts (to first order, as gravity's;
    its Jacobian interpolated over ``_CORIOLIS_BLOCK`` bins of one leg): on a joint that
    gravity hardly loads it can be most of the signal. The inertial torque's does not: it is
    a correction of a few mA, the offsets change it by ~1 %."""
    grav = _gravity_of(model, gravity, payload_mass, payload_com)
    motion = _motion_of(model, payload_mass, payload_com)
    delta0 = jnp.zeros(model.K)
    n, F, B, G = model.n, model.K + 3, tb.count.shape[0], _CORIOLIS_BLOCK

    def coriolis_jacobian(pose, velocity):  # (c, n, K), see _CORIOLIS_BLOCK
        P, V = (jnp.reshape(a, (-1, G, n)) for a in (pose, velocity))
        ends = jnp.stack([P[:, 0], P[:, -1]]), jnp.stack([V[:, 0], V[:, -1]])
        coriolis = jax.jacrev(lambda d, q, v: motion(d, q, v, jnp.zeros_like(v)))
        J = jax.vmap(jax.vmap(lambda q, v: coriolis(delta0, q, v)))(*ends)
        top = jnp.abs(V).max(axis=(1, 2))[:, None] + 1e-300
        at_a = jnp.abs(V - V[:, :1]).max(-1) <= _SAME_LEG * top  # (c / G, G)
        at_z = jnp.abs(V - V[:, -1:]).max(-1) <= _SAME_LEG * top
        t = jnp.arange(G) / (G - 1)
        w_a = jnp.where(at_a & at_z, 1.0 - t, at_a.astype(float))
        w_z = jnp.where(at_a & at_z, t, at_z.astype(float))
        out = w_a[..., None, None] * J[0][:, None] + w_z[..., None, None] * J[1][:, None]
        return out.reshape(-1, n, model.K)

    def add(st: Stats, part: tuple) -> tuple[Stats, None]:
        pose, velocity, acceleration, cur, square, count = part
        tau0 = jax.vmap(lambda q, v, a: grav(delta0, q) + motion(delta0, q, v, a))(
            pose, velocity, acceleration
        )
        reg = jax.vmap(lambda q: jax.jacfwd(grav)(delta0, q))(pose)
        reg = reg + coriolis_jacobian(pose, velocity)
        phi = jnp.concatenate(
            [tau0[..., None], reg, jnp.sign(velocity)[..., None], velocity[..., None]], -1
        )  # (c, n, F)
        return st + Stats(
            S=jnp.einsum("bj,bjf,bjg->jfg", count, phi, phi),
            s=jnp.einsum("bjf,bj->jf", phi, cur),
            c2=square.sum(0),
            samples=count.sum(0),
        ), None

    zero = Stats(jnp.zeros((n, F, F)), jnp.zeros((n, F)), jnp.zeros(n), jnp.zeros(n))
    if B == 0:
        return zero
    c = math.gcd(B, _TRANSFER_CHUNK)  # bins at a time: the Jacobians of many are large
    parts = tuple(jnp.reshape(a, (B // c, c, *a.shape[1:])) for a in tb)
    return jax.lax.scan(add, zero, parts)[0]


_transfer_stats_jit = jax.jit(_transfer_stats, static_argnums=0)


#: Angles (rad) at which a degree-one trigonometric polynomial a sin + b cos + c is sampled.
_ANGLES = (0.0, 0.5 * np.pi, np.pi)


def _trig(f0, f90, f180):
    """(a, b, c) of f(x) = a sin x + b cos x + c from f at 0, pi/2 and pi."""
    c = 0.5 * (f0 + f180)
    return f90 - c, 0.5 * (f0 - f180), c


@partial(jax.jit, static_argnums=0)
def _sweep_stats(model: FitModel, m: SweepMoments) -> tuple[Stats, jax.Array]:
    """Sufficient statistics of one recording's sweeps, and each sweep's torque coefficients.

    The swept joint's tau0 and regressor and their held-angle derivatives are evaluated at
    three angles per sweep and written as a sin + b cos + c: the coefficients (S, 1 + K, 3,
    n + 1) map the moments of z onto the features (``identify.moments``). Returned: the
    statistics and the coefficients at the held pose (S, 1 + K, 3): a, b, c.
    """
    S, n = m.joint.shape[0], model.n
    # every value is a degree-one trigonometric polynomial in each joint angle alone (rotating
    # one joint turns a rigid subtree, or the whole tree about the swept axis): sampled at the
    # swept angles 0, pi/2, pi, and with each held joint moved by 0, pi/2, pi from its hold,
    # the samples give the coefficients in the swept angle and the derivatives in each held
    # angle exactly
    shift = jnp.concatenate([jnp.zeros((1, n)), jnp.repeat(jnp.eye(n), 2, axis=0)])
    shift = shift * jnp.concatenate([jnp.zeros(1), jnp.tile(jnp.asarray(_ANGLES[1:]), n)])[:, None]
    poses = m.hold[:, None, None, :] + shift[None, None, :, :]  # (S, 3, 1 + 2n, n)
    swept = jax.nn.one_hot(m.joint, n, dtype=float)[:, None, None, :]
    poses = poses * (1.0 - swept) + jnp.asarray(_ANGLES)[None, :, None, None] * swept
    V = _regressors(
        model,
        poses.reshape(-1, n),
        jnp.repeat(m.joint, 3 * (1 + 2 * n)),
        m.gravity,
        m.payload_mass,
        m.payload_com,
    ).reshape(S, 3, 1 + 2 * n, 1 + model.K)
    base = V[:, :, 0]  # (S, 3, 1 + K)
    moved = V[:, :, 1:].reshape(S, 3, n, 2, 1 + model.K)
    slope, _, _ = _trig(base[:, :, None], moved[:, :, :, 0], moved[:, :, :, 1])  # (S, 3, n, 1 + K)
    slope = slope * (1.0 - swept[:, 0, :, :, None])  # the swept joint's entry is 0
    U = jnp.concatenate([base[:, :, None], slope], axis=2)  # (S, 3, n + 1, 1 + K)
    C = jnp.stack(_trig(U[:, 0], U[:, 1], U[:, 2]), axis=1)  # (S, 3, n + 1, 1 + K)
    C = jnp.moveaxis(C, -1, 1)  # (S, 1 + K, 3, n + 1)
    F, Z = model.K + 3, 3 * (n + 1)
    L = jnp.zeros((S, F, Z + 2))
    L = L.at[:, : F - 2, :Z].set(C.reshape(S, F - 2, Z))
    L = L.at[:, F - 2, Z].set(1.0).at[:, F - 1, Z + 1].set(1.0)
    onehot = jax.nn.one_hot(m.joint, n, dtype=float)  # (S, n)
    M = m.moments
    per_S = jnp.einsum("sfa,sab,sgb->sfg", L, M[:, : Z + 2, : Z + 2], L)
    per_s = jnp.einsum("sfa,sa->sf", L, M[:, : Z + 2, Z + 2])
    one = z_index(2, 0, n)
    st = Stats(
        S=jnp.einsum("sj,sfg->jfg", onehot, per_S),
        s=jnp.einsum("sj,sf->jf", onehot, per_s),
        c2=onehot.T @ M[:, Z + 2, Z + 2],
        samples=onehot.T @ M[:, one, one],
    )
    return st, C[..., 0]


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
    """(n,) A^2: residual sum of squares of each joint's steady samples."""
    b = _beta(theta, n, K)
    return st.c2 - 2 * jnp.einsum("jf,jf->j", b, st.s) + jnp.einsum("jf,jfg,jg->j", b, st.S, b)


class _Priors(NamedTuple):
    """Quadratic priors: on log(ratio) mean ``centre`` (n,) and precision ``ratio`` (n,), tie
    rows ``tie`` (n, n) with weights ``tie_w`` (n,); precisions of friction (n,) A^-2,
    viscous (n,) (A s/rad)^-2 and COM offsets (K,) m^-2; ``held`` (n,): viscous held at 0
    (one speed)."""

    centre: jax.Array
    ratio: jax.Array
    tie: jax.Array
    tie_w: jax.Array
    friction: jax.Array
    viscous: jax.Array
    com: jax.Array
    held: jax.Array


def _prefit(st: Stats, K: int) -> tuple[jax.Array, jax.Array]:
    """Each joint's ratio (n,) from its nominal torque tau0 alone (gravity; in the transfers
    also inertial and Coriolis; COM offsets 0, current = r tau0 + l d), and its relative
    standard error (n,; inf without a signal)."""
    idx = jnp.asarray([0, K + 1])
    A = st.S[:, idx][:, :, idx]
    y = st.s[:, idx]
    tiny = 1e-12 * jnp.trace(A, axis1=1, axis2=2)[:, None, None] + 1e-300
    A = A + tiny * jnp.eye(2)
    x = jnp.linalg.solve(A, y[..., None])[..., 0]
    rss = st.c2 - 2 * jnp.sum(x * y, 1) + jnp.einsum("ja,jab,jb->j", x, A, x)
    s2 = jnp.maximum(rss, 0.0) / jnp.maximum(st.samples - 2, 1.0)
    var = s2 * jnp.linalg.inv(A)[:, 0, 0]
    r = x[:, 0]
    rel = jnp.sqrt(var) / jnp.abs(r)
    rel = jnp.where((st.samples > 2) & (r > 0) & jnp.isfinite(rel), rel, jnp.inf)
    return r, rel


def _priors(st: Stats, key: tuple) -> tuple[_Priors, jax.Array, jax.Array, jax.Array, jax.Array]:
    """The priors, scaled to the data (every one means the same in A or mA), each joint's
    ``_prefit`` ratio and excitation (its relative standard error), excited flags and current
    scale (A)."""
    n, K, ratio0, types, com_prior = key
    ratio0 = jnp.asarray(ratio0)
    r_hat, rel = _prefit(st, K)
    excited = rel < EXCITED
    logs = jnp.log(jnp.maximum(r_hat, 1e-300) / ratio0)
    positive = r_hat > 0
    use = jnp.where(jnp.any(excited), excited, positive)
    scale = jnp.where(jnp.any(use), jnp.nanmedian(jnp.where(use, logs, jnp.nan)), 0.0)
    centre = jnp.log(ratio0) + scale
    if types is None:
        tie, tie_w = jnp.zeros((n, n)), jnp.zeros(n)
    else:
        same = jnp.asarray([[types[i] == types[k] for k in range(n)] for i in range(n)], float)
        donors = same * excited[None, :]
        has = (donors.sum(1) > 0) & ~excited
        mean_of = donors / jnp.maximum(donors.sum(1, keepdims=True), 1.0)
        tie = has[:, None] * (jnp.eye(n) - mean_of)
        tie_w = jnp.where(has, 1.0 / TIE**2, 0.0)
    # current and speed scales of each joint (the whole recording's for an unswept joint)
    total = jnp.sqrt(jnp.sum(st.c2) / jnp.maximum(jnp.sum(st.samples), 1.0)) + 1e-300
    cs = jnp.where(st.samples > 0, jnp.sqrt(st.c2 / jnp.maximum(st.samples, 1.0)), total)
    cs = jnp.maximum(cs, 1e-9 * total)
    vv, vd, dd = st.S[:, -1, -1], st.S[:, -1, -2], st.S[:, -2, -2]
    vs = jnp.sqrt(vv / jnp.maximum(st.samples, 1.0))
    width = PRIOR_VISCOUS * cs / jnp.where(vs > 0, vs, 1.0)
    # viscous friction needs passes at different speeds: with one speed (v = speed d) it is
    # indistinguishable from the friction loss and is held at 0
    held = (vd**2 >= (1.0 - SPEED_SPREAD**2) * vv * dd) | (st.samples == 0)
    viscous = jnp.where(held, 1.0 / (1e-6 * width) ** 2, 1.0 / width**2)
    pr = _Priors(
        centre=centre,
        ratio=jnp.full(n, 1.0 / PRIOR_LOG_RATIO**2),
        tie=tie,
        tie_w=tie_w,
        friction=1.0 / (1e3 * cs) ** 2,
        viscous=viscous,
        com=jnp.repeat(1.0 / jnp.asarray(com_prior) ** 2, 3),
        held=held,
    )
    return pr, r_hat, rel, excited, cs


def _design(n: int, K: int) -> tuple[jax.Array, jax.Array]:
    """Constant parts of beta_j = r_j e0 + (A0_j + r_j Ad_j) z, z = [delta (K), l (n), b (n)]:
    A0, Ad (n, F, K + 2 n)."""
    F, P = K + 3, K + 2 * n
    j = jnp.arange(n)
    A0 = jnp.zeros((n, F, P)).at[j, F - 2, K + j].set(1.0).at[j, F - 1, K + n + j].set(1.0)
    k = jnp.arange(K)
    Ad = jnp.zeros((n, F, P)).at[:, 1 + k, k].set(1.0)
    return A0, Ad


def _log_prior(rho: jax.Array, pr: _Priors) -> jax.Array:
    tied = pr.tie @ rho
    return 0.5 * jnp.sum(pr.ratio * (rho - pr.centre) ** 2) + 0.5 * jnp.sum(pr.tie_w * tied**2)


def _inner(r: jax.Array, st: Stats, pr: _Priors, s2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """For fixed ratios ``r`` (n,) and noise variances ``s2`` (n,) A^2: the best
    z = [delta, l, b] (exact: the model is linear in them) and the data-and-prior objective
    0.5 sum_j RSS_j / s2_j + 0.5 z' Lambda z there."""
    n, F = st.c2.shape[0], st.S.shape[-1]
    K = F - 3
    A0, Ad = _design(n, K)
    A = A0 + r[:, None, None] * Ad
    W = st.S / s2[:, None, None]
    H = jnp.einsum("jfp,jfg,jgq->pq", A, W, A)
    H = H + jnp.diag(jnp.concatenate([pr.com, pr.friction, pr.viscous]))
    g = jnp.einsum("jfp,jf->p", A, W[:, :, 0] * r[:, None] - st.s / s2[:, None])
    z = -_solve_spd(H, g)
    const = jnp.sum((st.c2 - 2 * r * st.s[:, 0] + r**2 * st.S[:, 0, 0]) / s2)
    return z, 0.5 * (const + g @ z)


def _theta(r: jax.Array, z: jax.Array, n: int, K: int) -> jax.Array:
    """[ratio, friction, viscous, com] from r and z = [delta, l, b]."""
    return jnp.concatenate([r, z[K : K + n], z[K + n :], z[:K]])


def _solve_spd(H: jax.Array, b: jax.Array) -> jax.Array:
    """H^-1 b for a symmetric positive definite H (b a vector or matrix), Jacobi-scaled for
    its conditioning."""
    d = jnp.sqrt(jnp.maximum(jnp.diag(H), 1e-300))
    scale = d if b.ndim == 1 else d[:, None]
    return jnp.linalg.solve(H / d[:, None] / d[None, :], b / scale) / scale


def _inverse(H: jax.Array) -> jax.Array:
    """Inverse of a symmetric positive definite matrix (``_solve_spd``)."""
    return _solve_spd(H, jnp.eye(H.shape[0]))


#: The fit starts from a joint's prefit ratio within this many prior widths of the prior's
#: centre (``solve``).
_START_SPAN = 2.0


@partial(jax.jit, static_argnums=0)
def solve(model_key: tuple, st: Stats, max_iter: int = 50) -> Solution:
    """The joint fit on sufficient statistics (pure given the statics; vmap-able).

    Variable projection: for given ratios the model is linear in COM offsets, friction and
    viscous terms, which are solved exactly inside; the ratios follow damped Newton steps in
    log(ratio) (so they stay > 0), started from each joint's ratio from its nominal gravity
    torque alone. Each joint's noise variance is re-estimated from its residuals at every
    step. ``model_key`` = (n, K, nominal ratios, actuator types or None, COM prior per link),
    the static description of the model (``_key``).
    """
    n, K = model_key[0], model_key[1]
    P = _LIN * n + K
    pr, r_hat, rel, excited, cs = _priors(st, model_key)
    dof = jnp.maximum(st.samples - _LIN, 1.0)
    floor = (1e-12 * cs) ** 2

    def value(rho, s2):
        return _inner(jnp.exp(rho), st, pr, s2)[1] + _log_prior(rho, pr)

    def full(x, s2):
        # the objective in x = [log r, z] (before z is projected out)
        rho, z = x[:n], x[n:]
        rss = _rss(_theta(jnp.exp(rho), z, n, K), st, n, K)
        lam = jnp.concatenate([pr.com, pr.friction, pr.viscous])
        return 0.5 * jnp.sum(rss / s2) + 0.5 * jnp.sum(lam * z**2) + _log_prior(rho, pr)

    def variances(rho, s2):
        r = jnp.exp(rho)
        z, _ = _inner(r, st, pr, s2)
        rss = _rss(_theta(r, z, n, K), st, n, K)
        return jnp.where(st.samples > 0, jnp.maximum(rss / dof, floor), 1.0)

    def derivatives(rho, s2):
        # gradient and Hessian of the projected objective: at the inner optimum the gradient
        # is the full one's in log r, the Hessian the Schur complement of the full Hessian's
        z, _ = _inner(jnp.exp(rho), st, pr, s2)
        x = jnp.concatenate([rho, z])
        G, H = jax.grad(full)(x, s2), jax.hessian(full)(x, s2)
        return G[:n], H[:n, :n] - H[:n, n:] @ _solve_spd(H[n:, n:], H[n:, :n])

    def step(carry):
        rho, lam, it, done, s2 = carry
        g, H = derivatives(rho, s2)
        H = 0.5 * (H + H.T)
        damp = lam * jnp.diag(jnp.abs(jnp.diag(H))) + 1e-12 * jnp.eye(n)
        cand = rho - jnp.linalg.solve(H + damp, g)
        cand = jnp.clip(cand, pr.centre - RATIO_RANGE, pr.centre + RATIO_RANGE)
        f, fc = value(rho, s2), value(cand, s2)
        better = fc <= f
        new = jnp.where(better, cand, rho)
        # converged: the step changes no ratio by 1e-10 (relative), or the objective only at
        # the level of rounding
        done = (jnp.max(jnp.abs(cand - rho)) < 1e-10) | (jnp.abs(fc - f) <= 1e-12 * jnp.abs(f))
        lam = jnp.where(better, lam * 0.1, lam * 10.0)
        return new, lam, it + 1, done, variances(new, s2)

    def cont(carry):
        return (~carry[3]) & (carry[2] < max_iter) & (carry[1] < 1e12)

    # start from each excited joint's prefit ratio, unless the prior puts it beyond
    # ``_START_SPAN`` widths (a prefit that the unknown COM offsets dominate): there from
    # the prior's centre
    log_hat = jnp.log(jnp.maximum(r_hat, 1e-300))
    near = jnp.abs(log_hat - pr.centre) <= _START_SPAN * PRIOR_LOG_RATIO
    rho0 = jnp.where(excited & near, log_hat, pr.centre)
    s2_0 = variances(rho0, jnp.where(st.samples > 0, cs**2, 1.0))
    init = (rho0, jnp.asarray(1e-3), jnp.asarray(0), jnp.asarray(False), s2_0)
    rho, lam, it, done, s2 = jax.lax.while_loop(cont, step, init)
    r = jnp.exp(rho)
    z, _ = _inner(r, st, pr, s2)
    theta = _theta(r, z, n, K)

    # Fisher information of theta (Gauss-Newton) plus the priors; and with the priors relaxed
    # 100-fold (what the data alone determine)
    Bj = jax.jacfwd(lambda th: _beta(th, n, K))(theta)  # (n, F, P)
    H_data = jnp.einsum("jfp,jfg,jgq->pq", Bj, st.S / s2[:, None, None], Bj)

    def prior(relax):
        soft = jnp.where(pr.held, pr.viscous, pr.viscous * relax)
        H = jnp.zeros((P, P))
        ratio = jnp.diag(pr.ratio * relax) + pr.tie.T @ (pr.tie_w[:, None] * pr.tie)
        H = H.at[:n, :n].add(ratio / r[:, None] / r[None, :])  # d log r = dr / r
        H = H.at[n : 2 * n, n : 2 * n].add(jnp.diag(pr.friction))
        H = H.at[2 * n : 3 * n, 2 * n : 3 * n].add(jnp.diag(soft))
        return H.at[3 * n :, 3 * n :].add(jnp.diag(pr.com * relax))

    cov = _inverse(H_data + prior(1.0))
    wide = _inverse(H_data + prior(1e-4))
    var, var_wide = jnp.diag(cov), jnp.diag(wide)
    dominated = var_wide <= DATA_DOMINATED**2 * var
    std_ratio = jnp.sqrt(jnp.maximum(var[:n], 0.0))
    ratio_ok = dominated[:n] & excited & (std_ratio <= RATIO_IDENTIFIED * r)
    ident = dominated.at[:n].set(ratio_ok)
    ident = ident.at[n : 2 * n].set(dominated[n : 2 * n] & (st.samples > 0))
    ident = ident.at[2 * n : 3 * n].set(dominated[2 * n : 3 * n] & ~pr.held)
    norm = jnp.sqrt(jnp.maximum(var_wide[:n, None] * var_wide[None, 3 * n :], 1e-300))
    corr = wide[:n, 3 * n :] / norm
    link = jnp.argmax(jnp.abs(corr).reshape(n, -1, 3).max(axis=2), axis=1)
    vs = jnp.sqrt(st.S[:, -1, -1] / jnp.maximum(st.samples, 1.0))
    scale = jnp.concatenate([r, cs, cs / jnp.where(vs > 0, vs, 1.0), jnp.full(K, _COM_SCALE)])
    # symmetric positive semi-definite: the singular values are the eigenvalues, and a batched
    # eigvalsh is ~1000x faster than a batched SVD of this size on a GPU
    eig = jnp.linalg.eigvalsh(H_data * scale[:, None] * scale[None, :])
    return Solution(
        ratio=r,
        friction=theta[n : 2 * n],
        viscous=theta[2 * n : 3 * n],
        com=theta[3 * n :],
        cov=cov,
        sigma=jnp.sqrt(s2),
        singular=jnp.sort(jnp.abs(eig))[::-1],
        excited=excited,
        excitation=rel,
        identified=ident,
        data_dominated=dominated,
        confounded=excited & ~dominated[:n],
        confounded_link=link,
        iterations=it,
        # a ratio at the edge of its range, or an offset far beyond its prior, is a fit that
        # ran away along a direction the data barely see: reported as not converged
        converged=done
        & jnp.all(jnp.isfinite(theta))
        & jnp.all(jnp.abs(rho - pr.centre) < RATIO_RANGE - 1e-6)
        & jnp.all(jnp.abs(theta[3 * n :]) * jnp.sqrt(pr.com) < COM_RANGE),
        rss=jnp.sum(_rss(theta, st, n, K)),
    )


def _key(model: FitModel) -> tuple:
    return (
        model.n,
        model.K,
        tuple(float(r) for r in model.ratio0),
        model.types,
        tuple(float(c) for c in model.com_prior),
    )


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


def prepare(
    model: FitModel, rec: Recording, transfers: bool = True
) -> tuple[Stats, jax.Array, SweepMoments]:
    """Moments, sufficient statistics and torque coefficients of one recording; its transfers
    (``identify.transfers``) added to the statistics unless ``transfers`` is False."""
    m = sweep_moments(rec)
    st, coef = _sweep_stats(model, _padded(m, _bucket(m.n_sweeps)))
    if transfers:
        tb = transfer_bins(rec)
        tb = padded_bins(tb, bucket(tb.size))
        st = st + _transfer_stats_jit(model, tb, m.gravity, m.payload_mass, m.payload_com)
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


#: What to do about a ratio confounded with a link's first moment.
CURE = (
    "add a recording with a known payload (or one in a second mounting) and fit the recordings "
    "together"
)


def _params(
    model: FitModel, name: str, sol: Solution, phase, phase_std, seconds: float
) -> RobotParams:
    sol = jax.tree.map(np.asarray, sol)
    if not bool(sol.converged) or not np.all(np.isfinite(sol.ratio)):
        raise FitError(
            f"the joint fit did not converge after {int(sol.iterations)} iterations "
            f"(noise estimate {np.max(sol.sigma):.3g} A); nothing was written"
        )
    n = model.n
    std = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))
    com = sol.com.reshape(-1, 3)
    com_std = std[_LIN * n :].reshape(-1, 3)
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
    """One line per ratio the fit could not identify on its own: confounded with a link's
    first moment (naming the cure), or without gravity signal."""
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
    (``identify.transfers``).

    The recordings may differ in gravity (mounting) and payload. ``com_prior``: m, the COM
    prior on every link (default: the model's, ``default_com_prior``). ``complete``: refuse
    (InputError) recordings that are implausible or do not sweep every joint both ways
    (``plausibility.check_recordings``); False: an unswept joint keeps zero friction with an
    error bar of the prior's width (the studies' random plans sweep a subset). Raises
    ``FitError`` when the fit does not converge.
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
    sol = jax.block_until_ready(solve(_key(model), st, max_iter))
    _, coef, m = prepared[0]
    return _result(model, recs[0].model, sol, coef, m.joint, time.perf_counter() - start)


def _result(model, name, sol, coef, joint, seconds) -> RobotParams:
    """The ``RobotParams`` of a solution, for recordings of the robot model ``name``."""
    cov = np.asarray(sol.cov)[_LIN * model.n :, _LIN * model.n :]
    phase, phase_std = phase_shift(model, coef, joint, np.asarray(sol.com), cov)
    return _params(model, name, sol, phase, phase_std, seconds)


@partial(jax.jit, static_argnums=(0, 2, 3))
def _fit_packed(model: FitModel, data: tuple[Packed, TransferBins], length: int, sequential: bool):
    """Stacked packed recordings and their transfer bins (leading batch axis) -> (Solution,
    coef, joint, count) of each: moments, statistics and fit in one computation on the device
    (``sequential``: the moments one recording after another, see ``moments.reduce_batch``)."""
    p, tb = data
    m = reduce_batch(p, length, STEADY_FRACTION, STEADY_TRIM, sequential)
    sol, coef = _fit_moments.__wrapped__(model, m, tb)
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
        a = a[0] if len(a) == 1 else jnp.concatenate(a)
        fill = size - a.shape[0]  # no copy of a full batch in one group (the CPU's case)
        return a if fill == 0 else jnp.concatenate([a, jnp.repeat(a[-1:], fill, axis=0)])

    padded = [jax.tree.map(fit, p, shapes) for p in leaves]
    return jax.tree.map(join, *padded), length


#: Recordings per host-to-device transfer in ``fit_each`` (a worker's reused buffer).
_GROUP = 16


def fit_each(
    recordings: Iterable[Recording],
    batch: int | None = None,
    progress: bool = False,
    workers: int | None = None,
    com_prior: float | None = None,
    transfers: bool = True,
) -> list[RobotParams]:
    """Fit every recording on its own, ``batch`` at a time in one vmapped computation on the
    default backend (a GPU when present): moments, statistics and fit of a batch in one call
    (each as ``fit``, its transfers too unless ``transfers`` is False).

    The host reads (``recordings`` may be a generator that loads them), checks and packs a
    batch while the device fits the two before; the device's program is loaded (or traced and
    compiled) for a batch like the first recording while the rest of the first batch is read,
    and a recording is let go once packed.

    ``batch``: recordings per call (default 256 on an accelerator; 4 on a CPU, where a smaller
    batch maps less fresh memory and starts the device sooner). ``workers``: host threads that
    pack the recordings (``_GROUP`` to a transfer) and send them to the device (default: up to
    8 on an accelerator, where more only contend for host memory bandwidth; 1 on a CPU).
    ``com_prior``: m, as ``fit``'s. Raises ``FitError`` naming the recordings whose fit did not
    converge (no result then).
    """
    accelerated = not on_cpu()
    batch = int(batch or (256 if accelerated else 4))
    workers = max(1, int(workers or (min(8, os.cpu_count() or 1) if accelerated else 1)))
    group = min(_GROUP, batch)
    local = threading.local()
    out: list[RobotParams] = []
    failed: list[int] = []
    model: FitModel | None = None
    name = None  # the recordings' model
    robots: dict[tuple, Robot] = {}  # each recording's robot, by its model and joints
    buffers: dict[tuple[int, int], PackBuffer] = {}  # a CPU's, by batch parity and group
    bar = tqdm(desc="fitting", unit="rec", disable=not progress)

    def send(item: tuple[tuple[int, int], list[Recording]]) -> tuple[Packed, int]:
        which, recs = item
        if accelerated:  # copied to the device: each thread packs into its own buffer again
            buffer = local.__dict__.setdefault("buffer", PackBuffer())
        else:  # the device array aliases the buffer: packed into again two batches later, once
            # the batch that used it is fitted (fresh memory costs a page fault per 4 kB)
            buffer = buffers.setdefault(which, PackBuffer())
        packed, length = pack(recs, buffer)
        return jax.block_until_ready(jax.device_put((packed, _bins_of(recs, transfers)))), length

    def finish(names: list[str], result: Future, start: float) -> None:
        sols, coef, joint, count = jax.tree.map(np.asarray, result.result())
        joint = np.where(count > 0, joint, -1)
        seconds = (time.perf_counter() - start) / len(names)
        for i, recorded in enumerate(names):
            sol = jax.tree.map(lambda a, i=i: a[i], sols)
            try:
                out.append(_result(model, recorded, sol, coef[i], joint[i], seconds))
            except FitError:
                failed.append(len(out) + len(failed))
        bar.update(len(names))

    def program(packed, length: int) -> Callable:
        return traced.program(
            "fit_packed",
            repr((model._identity, length, not accelerated)),
            partial(_fit_packed, model, length=length, sequential=not accelerated),
            (packed,),
            (Packed, TransferBins, Solution),
        )

    def load(rec: Recording) -> None:  # the program for a batch of recordings like ``rec``
        packed, length = pack([rec])
        packed = (packed, _bins_of([rec], transfers))
        if not accelerated:  # and the pack buffers' memory, mapped ahead of the first packs
            for which in itertools.product((0, 1), range(-(-batch // group))):
                shape = packed[0].samples.shape[1:]
                buffers.setdefault(which, PackBuffer()).take(group, *shape, True)
        like = jax.tree.map(lambda a: jax.ShapeDtypeStruct((batch, *a.shape[1:]), a.dtype), packed)
        program(like, length)

    def run(packed, length: int):  # the batch's results, asynchronously
        return program(packed, length)(packed)

    pending: deque = deque()  # (names, result, start) of the batches not finished yet
    seen = 0
    stream = iter(recordings)
    first = next(stream, None)
    # the device thread loads the kept program and starts each batch's fit (asynchronous)
    # while this one reads (``recordings`` may be a generator), checks and packs the next ones
    with ThreadPoolExecutor(workers) as pool, ThreadPoolExecutor(1) as device:
        if first is not None:
            name = first.model
            model = fit_model(name, com_prior)
            device.submit(load, first)  # while the rest of the first batch is read
            stream = itertools.chain([first], stream)
            del first
        for k, chunk in enumerate(_chunks(stream, batch)):
            if any(r.model != name for r in chunk):
                raise InputError("fit_each needs recordings of one robot model")
            for i, rec in enumerate(chunk):
                if (rec.model, rec.joints) not in robots:
                    robots[rec.model, rec.joints] = rec.robot()
                if problems := recording_problems([rec], robots[rec.model, rec.joints]):
                    raise InputError(f"recording {seen + i}: {'; '.join(problems)}")
            seen += len(chunk)
            while len(pending) > 1 or (pending and pending[0][1].done()):
                finish(*pending.popleft())  # the batch two before: its pack buffer is free
            start = time.perf_counter()
            groups = [((k % 2, i), chunk[i : i + group]) for i in range(0, len(chunk), group)]
            packed, length = _join(list(pool.map(send, groups)), batch)
            result = device.submit(run, packed, length)
            pending.append(([r.model for r in chunk], result, start))
            del chunk, groups  # the samples are packed: the recordings can go
        while pending:
            finish(*pending.popleft())
    bar.close()
    if model is None:
        raise InputError("no recording to fit")
    if failed:
        raise FitError(f"the fit of recording(s) {failed} did not converge; nothing was written")
    return out


def _bins_of(recs: list[Recording], transfers: bool) -> TransferBins:
    """The recordings' transfer bins, stacked (none with ``transfers`` False)."""
    if not transfers:
        return empty_bins(recs[0].n_joints, stack=len(recs))
    return stack_bins([transfer_bins(r) for r in recs])


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
def _fit_moments(model: FitModel, m: SweepMoments, tb: TransferBins) -> tuple[Solution, jax.Array]:
    """Stacked moments and transfer bins (leading batch axis) -> (Solution, coef) of every
    recording."""
    st, coef = jax.vmap(_sweep_stats.__wrapped__, in_axes=(None, 0))(model, m)
    moving = jax.vmap(_transfer_stats, in_axes=(None, 0, 0, 0, 0))(
        model, tb, m.gravity, m.payload_mass, m.payload_com
    )
    return jax.vmap(solve.__wrapped__, in_axes=(None, 0))(_key(model), st + moving), coef


def _compiled_fit(
    model: FitModel,
    chunk: tuple[SweepMoments, TransferBins],
    shape: tuple,
    options: dict | None = None,
) -> tuple[Callable, float]:
    """``_fit_moments`` compiled ahead of time for ``chunk`` (so that its time is known),
    kept on the robot per model and ``shape`` = (batch, sweeps, mesh); and the seconds spent
    compiling it now (0 when it was compiled before). ``options``: XLA compiler options."""
    seconds = 0.0

    def build() -> Callable:
        nonlocal seconds
        t0 = time.perf_counter()
        compiled = _fit_moments.lower(model, *chunk).compile(options)
        seconds = time.perf_counter() - t0
        return compiled

    types = tuple(str(a.dtype) for a in jax.tree.leaves(chunk))
    return model.robot.cached(("jax_fit.fit_batch", model, *shape, types), build), seconds


def _batch_input(
    moments: SweepMoments, transfers: TransferBins | None, batch: int, mesh: Mesh | None
) -> tuple[tuple[SweepMoments, TransferBins], int, tuple[int, int], Callable]:
    """``fit_batch``'s input: ((the moments with their sweeps padded to the bucket size and
    float gravity and payload, the transfer bins padded to theirs: none when ``transfers`` is
    None), rows per batch (``batch`` rounded up to the mesh), the padded sweep and bin counts,
    the function that places a batch on the mesh)."""
    shards = 1 if mesh is None else mesh.size
    b = -(-max(1, int(batch)) // shards) * shards
    size = _bucket(moments.moments.shape[1])
    padded = _padded(moments, size, axis=1)
    padded = padded._replace(
        payload_mass=np.asarray(padded.payload_mass, float),
        gravity=np.asarray(padded.gravity, float),
        payload_com=np.asarray(padded.payload_com, float),
    )
    w, n = moments.hold.shape[0], moments.hold.shape[-1]
    if transfers is None:
        tb = empty_bins(n, stack=w)
    else:
        tb = padded_bins(transfers, bucket(transfers.size))
    place = (
        (lambda x: x)
        if mesh is None
        else partial(jax.device_put, device=NamedSharding(mesh, PartitionSpec("batch")))
    )
    return (padded, tb), b, (size, tb.size), place


def compile_fit_batch(
    model: FitModel,
    like: SweepMoments,
    batch: int,
    mesh: Mesh | None = None,
    transfers: TransferBins | None = None,
) -> float:
    """Compile ``fit_batch``'s program for batches of ``batch`` recordings with moments and
    transfer bins like ``like`` and ``transfers`` (stacked; any number of rows) ahead of the
    data themselves, e.g. while the simulation that makes them runs on the same device:
    without autotuning, which would time its candidate kernels behind that work; the seconds
    spent (0 when compiled before)."""
    padded, b, size, _ = _batch_input(like, transfers, batch, mesh)
    sharding = None if mesh is None else NamedSharding(mesh, PartitionSpec("batch"))
    shaped = jax.tree.map(
        lambda a: jax.ShapeDtypeStruct(
            (b, *np.shape(a)[1:]), np.asarray(a).dtype, sharding=sharding
        ),
        padded,
    )
    return _compiled_fit(model, shaped, (b, size, mesh), {"xla_gpu_autotune_level": 0})[1]


def fit_batch(
    model: FitModel,
    moments: SweepMoments,
    *,
    transfers: TransferBins | None = None,
    batch: int | None = None,
    mesh: Mesh | None = None,
    progress: Callable[[int], None] | None = None,
) -> BatchFit:
    """Fit W recordings each on its own from their stacked sweep moments, on the default
    backend (a GPU when present), ``batch`` at a time in one vmapped computation.

    ``moments``: a ``SweepMoments`` with a leading axis W on every field (joint (W, S), hold
    (W, S, n), moments (W, S, 6, 6), count (W, S), gravity (W, 3), payload_mass (W,),
    payload_com (W, 3)), e.g. ``identify.moments.sweep_moments_batch``; a sweep of zero moments
    adds nothing. ``transfers``: the recordings' stacked ``TransferBins`` (W, B, n) (None:
    sweeps alone). ``mesh``: a ``jax.sharding.Mesh`` with the single axis "batch" to shard each
    batch over (its devices); the batch is rounded up to a multiple of the mesh size and the
    last batch padded with copies of the last recording (dropped). The results are those of
    ``solve`` per recording; non-converged fits are reported in ``solution.converged``, not
    raised. ``progress(k)`` after each batch of k recordings.
    """
    w = int(moments.moments.shape[0])
    if w < 1 or moments.moments.ndim != 4:
        raise InputError("moments must be stacked: moments (W, S, 6, 6) with W >= 1")
    rows = w if batch is None else max(1, min(int(batch), w))
    padded, b, size, place = _batch_input(moments, transfers, rows, mesh)
    compile_seconds, seconds = 0.0, 0.0
    sols, coefs = [], []
    for start in range(0, w, b):
        idx = np.minimum(np.arange(start, start + b), w - 1)
        chunk = place(jax.tree.map(lambda a, idx=idx: np.asarray(a)[idx], padded))
        compiled, compiling = _compiled_fit(model, chunk, (b, size, mesh))
        compile_seconds += compiling
        t0 = time.perf_counter()
        sol, coef = jax.block_until_ready(compiled(*chunk))
        k = min(b, w - start)
        sols.append(jax.tree.map(lambda a, k=k: np.asarray(a)[:k], sol))
        coefs.append(np.asarray(coef)[:k])
        seconds += time.perf_counter() - t0
        if progress is not None:
            progress(k)
    solution = jax.tree.map(lambda *a: np.concatenate(a), *sols)
    std = np.sqrt(np.clip(np.diagonal(solution.cov, axis1=-2, axis2=-1), 0.0, None))
    return BatchFit(solution, np.concatenate(coefs), std, compile_seconds, seconds)


def identified(sol: Solution) -> np.ndarray:
    """(..., P) bool: which of [ratio, friction, viscous, com] the data determine in a fit
    (``Solution.identified``; ratios also to ``RATIO_IDENTIFIED``)."""
    return np.asarray(sol.identified, bool)
