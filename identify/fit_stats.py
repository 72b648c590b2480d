"""The joint fit's sufficient statistics: the features of sweeps and transfers, reduced per joint.

Model (paper Eq. 13 with a viscous term and the gravity model of ``jaxcomp.dynamics``): in a
steady pass of joint j in direction d at pass velocity v (rad/s) the measured current is

    c = r_j tau_j(q; delta) + l_j d + b_j v,      tau_j(q; delta) = tau0_j(q) + a_j(q) . delta

where tau is the gravity torque the actuator holds (N m) at the sample's pose q (the held
joints to first order about the sweep's mean pose: they give way under load), r_j > 0 the
current/torque ratio (A/(N m)), l_j the friction loss (A), b_j the viscous term (A s/rad) and
delta the centre-of-mass offsets (m, each moving link's own frame) of every moving link. The
transfers between sweeps add every moving joint's cruise samples with the same model, tau
then the gravity plus the inertial, Coriolis and centrifugal torques at the sample's velocity
and acceleration (``identify.transfers``, ``transfer_stats``).

Sweep moments make it exact and independent of the sample count (``identify.moments``): each
sweep's steady samples reduce to one small matrix; the regressors are evaluated at a few poses
per sweep (``jax.grad`` of the gravity model) and the loss reduces to per-joint sufficient
statistics (``Stats``, a K + 3 square matrix per joint for K offset components): an iteration
of the solver (``identify.fit_solver``) costs the same for 10^3 or 10^6 samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.identify.fit_model import FitModel
from jaxcomp.identify.moments import SweepMoments, z_index
from jaxcomp.identify.transfers import TransferBins


class Stats(NamedTuple):
    """Per-joint sufficient statistics of the least squares (F = K + 3 features).

    Sums over the steady samples of each joint's sweeps (and transfers), with the features
    phi = [tau0 (N m), reg (K, N), d, v (rad/s)] and c the current (A). Statistics of several
    recordings add (``+``).

    Attributes:
        S: (n, F, F), sum phi phi^T.
        s: (n, F), sum phi c.
        c2: (n,) A^2, sum c^2.
        samples: (n,), the samples each joint counts.
    """

    S: jax.Array
    s: jax.Array
    c2: jax.Array
    samples: jax.Array

    def __add__(self, other: Stats) -> Stats:  # type: ignore[override]
        return Stats(*(a + b for a, b in zip(self, other, strict=True)))


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


#: Transfer bins whose features are formed at once (``transfer_stats``).
_TRANSFER_CHUNK = 64
#: Transfer bins that share the Coriolis torque's offset Jacobian, interpolated between the
#: block's first and last bin (a bin of another leg than both gets none): the Jacobian costs
#: ~30 times a bin's torque (``dynamics.inverse_dynamics``).
_CORIOLIS_BLOCK = 16
#: Bins of one leg: velocities within this fraction of the largest joint speed.
_SAME_LEG = 0.05


@partial(jax.jit, static_argnums=0)
def transfer_stats(model: FitModel, tb: TransferBins, gravity, payload_mass, payload_com) -> Stats:
    """Sufficient statistics of one recording's transfer bins (``identify.transfers``).

    Every joint's features [tau0 = g(q) + M(q) ddq + C(q, dq) dq (N m, nominal model),
    d tau0 / d delta (K), sign dq, dq (rad/s)] at each bin's mean pose, velocity and
    acceleration, weighted by the samples it counts (M ddq + C dq in one
    ``dynamics.inverse_dynamics``). The Coriolis torque's dependence on the COM offsets counts
    (to first order, as gravity's; its Jacobian interpolated over ``_CORIOLIS_BLOCK`` bins of
    one leg): on a joint that gravity hardly loads it can be most of the signal. The inertial
    torque's does not: it is a correction of a few mA, the offsets change it by ~1 %. Jitted
    (``model`` static); ``transfer_stats.__wrapped__`` is the pure function, vmap-able.

    Args:
        model: the fit's model (n joints, K offset components).
        tb: the recording's B transfer bins, (B, n) each, padded to ``transfers.bucket``.
        gravity: (3,) m/s^2, gravity in the robot's base frame.
        payload_mass: kg, the recording's payload.
        payload_com: (3,) m, the payload's point in the end-effector site's frame.

    Returns:
        The transfers' ``Stats``.
    """
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


#: Angles (rad) at which a degree-one trigonometric polynomial a sin + b cos + c is sampled.
_ANGLES = (0.0, 0.5 * np.pi, np.pi)


def _trig(f0, f90, f180):
    """(a, b, c) of f(x) = a sin x + b cos x + c from f at 0, pi/2 and pi."""
    c = 0.5 * (f0 + f180)
    return f90 - c, 0.5 * (f0 - f180), c


@partial(jax.jit, static_argnums=0)
def sweep_stats(model: FitModel, m: SweepMoments) -> tuple[Stats, jax.Array]:
    """Sufficient statistics of one recording's sweeps, and each sweep's torque coefficients.

    The swept joint's tau0 and regressor and their held-angle derivatives are evaluated at
    three angles per sweep and written as a sin + b cos + c: the coefficients (S, 1 + K, 3,
    n + 1) map the moments of z onto the features (``identify.moments``). Jitted (``model``
    static); ``sweep_stats.__wrapped__`` is the pure function, vmap-able.

    Args:
        model: the fit's model (n joints, K offset components).
        m: the recording's S sweep moments (``identify.sweep_reduction.sweep_moments``; padded with
            zero sweeps, ``padded_sweeps``, for few compiled shapes).

    Returns:
        The sweeps' ``Stats``, and the coefficients (S, 1 + K, 3) at each sweep's held pose:
        a, b, c of tau0 (N m) and of its derivatives in the offsets (N) as
        a sin q_j + b cos q_j + c of the swept angle q_j (rad).
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


#: Sweeps are padded to a multiple of this, so few shapes get compiled.
SWEEP_BUCKET = 8


def padded_sweeps(m: SweepMoments, size: int, axis: int = 0) -> SweepMoments:
    """Sweep moments with zero sweeps appended (a sweep of zero moments adds nothing to a fit).

    Args:
        m: the sweep moments.
        size: the sweep count to pad to (at least ``m``'s).
        axis: the sweep axis of ``m``'s fields (1 when stacked).

    Returns:
        ``m`` with ``size`` sweeps along ``axis``.
    """

    def pad(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a)
        width = [(0, 0)] * a.ndim
        width[axis] = (0, size - a.shape[axis])
        return np.pad(a, width)

    return m._replace(**{k: pad(getattr(m, k)) for k in ("joint", "hold", "moments", "count")})


def sweep_bucket(n: int) -> int:
    """The padded sweep count of ``n`` sweeps.

    Args:
        n: Sweeps.

    Returns:
        ``n`` rounded up to ``SWEEP_BUCKET``.
    """
    return -(-n // SWEEP_BUCKET) * SWEEP_BUCKET
