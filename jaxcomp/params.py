"""Inertial parameters of a robot's links: the pytree that calibration corrects."""

from typing import NamedTuple

import jax


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
