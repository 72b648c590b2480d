"""The joint fit's solver: priors, the prefit and the variable-projection solve on ``Stats``.

One least-squares loss covers all joints, all sweeps and transfers and all recordings (which
may differ in gravity and payload), each joint with its own noise variance; it reduces to the
per-joint sufficient statistics of ``identify.fit_stats``.

The solve (``solve``) is variable projection: for given ratios the model is linear in delta,
l and b, which are solved exactly inside; log r follows damped Newton steps on the reduced
objective, started from each joint's ratio from its nominal gravity torque alone.

Priors, each the same in any current unit and on any robot:
- offsets: Gaussian toward the nominal model, per link ``com_prior`` m per axis
  (``identify.fit_model``);
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
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import current
from jaxcomp.identify.fit_model import JOINT_PARAMS
from jaxcomp.identify.fit_stats import Stats

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
#: Scales that make the parameters comparable for the identifiability report.
_COM_SCALE = 1e-3  # m: offsets in mm


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


def _beta(theta: jax.Array, n: int, K: int) -> jax.Array:
    """(n, F) per-joint coefficients [r_j, r_j delta, l_j, b_j] of the features
    [tau0, reg, d, v]; theta = [r (n), l (n), b (n), delta (K)]: the gradient of the current
    model ``current.viscous_sweep_current`` (linear in the features) with respect to them."""
    r, l, b, delta = theta[:n], theta[n : 2 * n], theta[2 * n : 3 * n], theta[3 * n :]

    def model(phi):  # (n, F) features -> (n,) A
        tau = phi[:, 0] + phi[:, 1 : K + 1] @ delta
        return current.viscous_sweep_current(tau, phi[:, K + 1], phi[:, K + 2], r, l, b)

    return jax.grad(lambda phi: jnp.sum(model(phi)))(jnp.zeros((n, K + 3)))


def joint_rss(theta: jax.Array, st: Stats, n: int, K: int) -> jax.Array:
    """Residual sum of squares of each joint's steady samples under parameters ``theta``.

    Args:
        theta: (3 n + K,) [ratio (n,) A/(N m), friction (n,) A, viscous (n,) A s/rad,
            COM offsets (K,) m].
        st: the fit's sufficient statistics.
        n: the number of joints.
        K: the number of COM offset components.

    Returns:
        (n,) A^2, each joint's residual sum of squares.
    """
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
    step. Jitted (``model_key`` static); ``solve.__wrapped__`` is the pure function, vmap-able.

    Args:
        model_key: the static description of the model, ``FitModel.key``: (n, K, nominal
            ratios (n,) A/(N m), actuator types or None, COM prior (L,) m per link).
        st: the sufficient statistics of the recordings' sweeps and transfers.
        max_iter: the most Newton steps.

    Returns:
        The ``Solution``: ratio (n,) A/(N m), friction (n,) A, viscous (n,) A s/rad, COM
        offsets (K,) m, their covariance and what the data determine.
    """
    n, K = model_key[0], model_key[1]
    pr, r_hat, rel, excited, cs = _priors(st, model_key)
    rho, it, done, s2 = _newton(st, pr, _start(r_hat, excited, pr), cs, n, K, max_iter)
    r = jnp.exp(rho)
    z, _ = _inner(r, st, pr, s2)
    theta = _theta(r, z, n, K)
    H_data = _fisher(theta, st, s2, n, K)
    cov, dominated, identified, link = _determined(H_data, pr, r, excited, st.samples, n, K)
    return Solution(
        ratio=r,
        friction=theta[n : 2 * n],
        viscous=theta[2 * n : 3 * n],
        com=theta[3 * n :],
        cov=cov,
        sigma=jnp.sqrt(s2),
        singular=_singular_values(H_data, r, cs, st, K),
        excited=excited,
        excitation=rel,
        identified=identified,
        data_dominated=dominated,
        confounded=excited & ~dominated[:n],
        confounded_link=link,
        iterations=it,
        converged=_converged(done, theta, rho, pr, n),
        rss=jnp.sum(joint_rss(theta, st, n, K)),
    )


def _start(r_hat: jax.Array, excited: jax.Array, pr: _Priors) -> jax.Array:
    """The Newton steps' start, log r (n,): each excited joint's prefit ratio ``r_hat``, unless
    the prior puts it beyond ``_START_SPAN`` widths (a prefit that the unknown COM offsets
    dominate): there the prior's centre."""
    log_hat = jnp.log(jnp.maximum(r_hat, 1e-300))
    near = jnp.abs(log_hat - pr.centre) <= _START_SPAN * PRIOR_LOG_RATIO
    return jnp.where(excited & near, log_hat, pr.centre)


def _newton(
    st: Stats, pr: _Priors, rho0: jax.Array, cs: jax.Array, n: int, K: int, max_iter: int
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Damped Newton steps in log r on the projected objective from ``rho0``, each joint's
    noise variance re-estimated from its residuals at every step (``cs`` (n,) A: the current
    scales): log r (n,), the steps taken, converged, the noise variances (n,) A^2."""
    dof = jnp.maximum(st.samples - JOINT_PARAMS, 1.0)
    floor = (1e-12 * cs) ** 2

    def value(rho, s2):
        return _inner(jnp.exp(rho), st, pr, s2)[1] + _log_prior(rho, pr)

    def full(x, s2):
        # the objective in x = [log r, z] (before z is projected out)
        rho, z = x[:n], x[n:]
        rss = joint_rss(_theta(jnp.exp(rho), z, n, K), st, n, K)
        lam = jnp.concatenate([pr.com, pr.friction, pr.viscous])
        return 0.5 * jnp.sum(rss / s2) + 0.5 * jnp.sum(lam * z**2) + _log_prior(rho, pr)

    def variances(rho, s2):
        r = jnp.exp(rho)
        z, _ = _inner(r, st, pr, s2)
        rss = joint_rss(_theta(r, z, n, K), st, n, K)
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

    s2_0 = variances(rho0, jnp.where(st.samples > 0, cs**2, 1.0))
    init = (rho0, jnp.asarray(1e-3), jnp.asarray(0), jnp.asarray(False), s2_0)
    rho, _, it, done, s2 = jax.lax.while_loop(cont, step, init)
    return rho, it, done, s2


def _fisher(theta: jax.Array, st: Stats, s2: jax.Array, n: int, K: int) -> jax.Array:
    """(P, P) Fisher information (Gauss-Newton) of theta from the data, at the noise
    variances ``s2`` (n,) A^2."""
    Bj = jax.jacfwd(lambda th: _beta(th, n, K))(theta)  # (n, F, P)
    return jnp.einsum("jfp,jfg,jgq->pq", Bj, st.S / s2[:, None, None], Bj)


def _prior_information(pr: _Priors, r: jax.Array, relax: float, n: int, K: int) -> jax.Array:
    """(P, P) information of the priors about theta at the ratios ``r`` (n,); the ratios'
    (not their ties), the viscous terms' (not those held at 0) and the COM offsets' scaled by
    ``relax``."""
    soft = jnp.where(pr.held, pr.viscous, pr.viscous * relax)
    H = jnp.zeros((JOINT_PARAMS * n + K,) * 2)
    ratio = jnp.diag(pr.ratio * relax) + pr.tie.T @ (pr.tie_w[:, None] * pr.tie)
    H = H.at[:n, :n].add(ratio / r[:, None] / r[None, :])  # d log r = dr / r
    H = H.at[n : 2 * n, n : 2 * n].add(jnp.diag(pr.friction))
    H = H.at[2 * n : 3 * n, 2 * n : 3 * n].add(jnp.diag(soft))
    return H.at[3 * n :, 3 * n :].add(jnp.diag(pr.com * relax))


def _determined(
    H_data: jax.Array,
    pr: _Priors,
    r: jax.Array,
    excited: jax.Array,
    samples: jax.Array,
    n: int,
    K: int,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """What the data determine: the covariance (P, P) of theta with the priors, and with every
    prior relaxed 100-fold which parameters the data dominate (P,), which are identified (P,)
    and each ratio's most correlated link (n,) (see ``Solution``)."""
    cov = _inverse(H_data + _prior_information(pr, r, 1.0, n, K))
    wide = _inverse(H_data + _prior_information(pr, r, 1e-4, n, K))
    var, var_wide = jnp.diag(cov), jnp.diag(wide)
    dominated = var_wide <= DATA_DOMINATED**2 * var
    std_ratio = jnp.sqrt(jnp.maximum(var[:n], 0.0))
    ratio_ok = dominated[:n] & excited & (std_ratio <= RATIO_IDENTIFIED * r)
    ident = dominated.at[:n].set(ratio_ok)
    ident = ident.at[n : 2 * n].set(dominated[n : 2 * n] & (samples > 0))
    ident = ident.at[2 * n : 3 * n].set(dominated[2 * n : 3 * n] & ~pr.held)
    norm = jnp.sqrt(jnp.maximum(var_wide[:n, None] * var_wide[None, 3 * n :], 1e-300))
    corr = wide[:n, 3 * n :] / norm
    link = jnp.argmax(jnp.abs(corr).reshape(n, -1, 3).max(axis=2), axis=1)
    return cov, dominated, ident, link


def _singular_values(
    H_data: jax.Array, r: jax.Array, cs: jax.Array, st: Stats, K: int
) -> jax.Array:
    """(P,) singular values of the Fisher information in comparable units (ratio scaled by
    r, friction by the current scale ``cs``, viscous by cs over the pass speed, COM offsets in
    ``_COM_SCALE``), largest first."""
    vs = jnp.sqrt(st.S[:, -1, -1] / jnp.maximum(st.samples, 1.0))
    scale = jnp.concatenate([r, cs, cs / jnp.where(vs > 0, vs, 1.0), jnp.full(K, _COM_SCALE)])
    # symmetric positive semi-definite: the singular values are the eigenvalues, and a batched
    # eigvalsh is ~1000x faster than a batched SVD of this size on a GPU
    eig = jnp.linalg.eigvalsh(H_data * scale[:, None] * scale[None, :])
    return jnp.sort(jnp.abs(eig))[::-1]


def _converged(done: jax.Array, theta: jax.Array, rho: jax.Array, pr: _Priors, n: int) -> jax.Array:
    """The Newton steps converged to finite parameters; a ratio at the edge of its range, or
    an offset far beyond its prior, is a fit that ran away along a direction the data barely
    see: reported as not converged."""
    return (
        done
        & jnp.all(jnp.isfinite(theta))
        & jnp.all(jnp.abs(rho - pr.centre) < RATIO_RANGE - 1e-6)
        & jnp.all(jnp.abs(theta[3 * n :]) * jnp.sqrt(pr.com) < COM_RANGE)
    )
