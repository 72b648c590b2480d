"""Current-based impedance control of the arm and the base follower.

``make_impedance_controller`` (paper Eq. 3-5, 16; jitted JAX: ``impedance``, its inputs and
diagnostics ``impedance_io``, its terms ``impedance_terms``) and its pinocchio twin,
``make_velocity_controller`` (the non-compliant reference), ``BaseFollower`` (Eq. 20), and
their gains (``ImpedanceGains``, ``VelocityGains``, ``BaseGains``; ``impedance_gains``
carries the impedance presets over to any arm). ``control.loop.run_control`` runs a controller
at 1 kHz on a ``hardware`` ``Arm`` (and ``Base``; frames and models: ``mount``), with its
``watchdog``, ``timing`` and end-effector ``trajectory``: ``run_setup``, then ``cycle`` by
``cycle`` (the controller through ``law_adapter``), recorded by ``run_recording`` into a
``run_result``; ``run_link`` connects a run to an operator on another thread
(stop, live gains, monitor). ``external_force`` estimates the force a person applies on the end
effector from the motor currents (in the impedance controller's step). Frames: the arm's base
frame; SI units (m, rad, s, N, N m, A).
"""

from jaxcomp.control.base_follower import BaseFollower, follow_twist
from jaxcomp.control.gains import BaseGains, ImpedanceGains, JointGains, VelocityGains
from jaxcomp.control.impedance import ImpedanceController, make_impedance_controller
from jaxcomp.control.impedance_io import Diagnostics
from jaxcomp.control.impedance_pinocchio import ImpedanceControllerPinocchio
from jaxcomp.control.presets import impedance_gains
from jaxcomp.control.velocity import (
    VelocityController,
    VelocityDiagnostics,
    make_velocity_controller,
)

__all__ = [
    "BaseFollower",
    "BaseGains",
    "Diagnostics",
    "ImpedanceController",
    "ImpedanceControllerPinocchio",
    "ImpedanceGains",
    "JointGains",
    "VelocityController",
    "VelocityDiagnostics",
    "VelocityGains",
    "follow_twist",
    "impedance_gains",
    "make_impedance_controller",
    "make_velocity_controller",
]
