"""Inertial parameters of a robot's links: the pytree that calibration corrects."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class InertialParams(NamedTuple):
    """Inertial parameters of every link (body) of a kinematic tree, world body excluded.

    Attributes:
        mass: (nb,) kg.
        com: (nb, 3) m, centre of mass in the link's own frame.
        inertia: (nb, 3, 3) kg m^2, rotational inertia about the centre of mass,
            expressed in the link's own frame.

    A NamedTuple is a JAX pytree, so ``jax.grad`` with respect to any field works.
    """

    mass: jax.Array
    com: jax.Array
    inertia: jax.Array


def add_point_mass(params: InertialParams, body: int, mass, point) -> InertialParams:
    """``params`` with a point mass (kg) fixed to link ``body`` at ``point`` (3,) m, link frame.

    The link's mass, centre of mass and rotational inertia (about the new centre of mass, by
    the parallel-axis theorem) become those of the link and the point mass together. Pure and
    jit/grad-able; a zero mass leaves the params unchanged.

    Args:
        params: the link inertials (COMs and inertias in the link frames).
        body: index of the link (body) the point mass is fixed to.
        mass: the point mass, kg (scalar).
        point: (3,) m, where it sits, in the link's frame.

    Returns:
        ``params`` with link ``body``'s mass (kg), COM (m) and inertia (kg m^2) replaced.
    """
    mass_all, com_all = jnp.asarray(params.mass), jnp.asarray(params.com)
    inertia_all = jnp.asarray(params.inertia)
    m0, c0, point = mass_all[body], com_all[body], jnp.asarray(point)
    total = m0 + mass
    com = (m0 * c0 + mass * point) / total

    def steiner(m, d):
        return m * (jnp.dot(d, d) * jnp.eye(3) - jnp.outer(d, d))

    inertia = inertia_all[body] + steiner(m0, c0 - com) + steiner(mass, point - com)
    return InertialParams(
        mass_all.at[body].set(total), com_all.at[body].set(com), inertia_all.at[body].set(inertia)
    )


def gyration_radii(params: InertialParams) -> np.ndarray:
    """(nb,) m: each link's radius of gyration about its centre of mass, sqrt(trace(I) / 2 m)
    (a uniform rod of length L: 0.29 L); 0 for a massless link.

    Args:
        params: the link inertials: mass (nb,) kg, inertia (nb, 3, 3) kg m^2.

    Returns:
        (nb,) m, numpy.
    """
    mass = np.asarray(params.mass, float)
    trace = np.trace(np.asarray(params.inertia, float), axis1=-2, axis2=-1)
    return np.sqrt(np.maximum(trace, 0.0) / (2.0 * np.maximum(mass, 1e-12))) * (mass > 0)
