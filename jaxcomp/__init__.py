"""jaxcomp: current-based impedance control for arms without joint torque sensors.

Importing the package enables float64 in JAX: identification and dynamics need it.
"""

import jax

jax.config.update("jax_enable_x64", True)

from jaxcomp.errors import InputError, JaxcompError, ModelError  # noqa: E402
from jaxcomp.params import InertialParams  # noqa: E402
from jaxcomp.robot import Robot, builtin_models, load_robot  # noqa: E402

__all__ = [
    "InertialParams",
    "InputError",
    "JaxcompError",
    "ModelError",
    "Robot",
    "builtin_models",
    "load_robot",
]
__version__ = "0.1.0"
