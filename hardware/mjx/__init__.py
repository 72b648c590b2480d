"""The simulated arm on MJX: thousands of true robots driven by one plan or policy at once.

``MjxSimulator`` is the CPU ``Simulator`` (hardware/simulator.py) of an arm-only model, batched
over worlds with ``jax.vmap``: the same MuJoCo model (actuators, 1 ms implicitfast step, stiff
friction-loss solver reference), the same servo ``tau = clip(kp (q_ref - q) + kv (0 - dq),
effort)`` with the same per-joint gains (computed as the CPU simulator does, from each world's
true inertia), the same settling of 500 steps at the initial pose before t = 0, and the same
measured current ``r tau_applied + noise``. Each world has its own truth (``BatchTruth``); the
per-world model fields go in through ``tree_replace`` with vmap axis 0, the shared model is
closed over. The world axis can be sharded over a ``jax.sharding.Mesh`` with axis ``"batch"``
(``batch_mesh``).

The stages, one module each, composed by ``MjxSimulator`` (simulator.py):

- reference: ``Move`` and ``reference_trajectory``, the 1 kHz position targets of a plan;
- model: ``build_model``, the MjModel the worlds share;
- truth: ``BatchTruth`` and ``true_inertial_params``, each world's hidden robot;
- gains: ``servo_gains``, each world's position servo;
- mesh: ``batch_mesh`` and the placement of the worlds on the devices;
- step: ``implicitfast_step``, one physics step as MuJoCo C integrates it;
- chunks: the compiled chunks of K steps and their decimated recording;
- runner: ``MjxSimulator.run``, POSITION mode through a plan (``MjxRecording``);
- closed_loop: ``MjxSimulator.run_closed_loop``, CURRENT mode driven by a ``Policy(init,
  step)`` (``Observation``, ``PushSchedule``, ``ClosedLoopResult``);
- faults: the ``FAULT_*`` codes of the closed loop.

Units: rad, rad/s, A, N m, kg, m, s; gravity and COM offsets as in ``BatchTruth``.
"""

from jaxcomp.hardware.mjx.closed_loop import (
    CLOSED_LOOP_AGREEMENT,
    ClosedLoopResult,
    Observation,
    Policy,
    PushSchedule,
)
from jaxcomp.hardware.mjx.faults import (
    FAULT_EFFORT,
    FAULT_LIMIT,
    FAULT_NAMES,
    FAULT_OVERSPEED,
    FAULT_REFUSED,
    FAULT_STOPPED,
    fault_names,
)
from jaxcomp.hardware.mjx.gains import servo_gains
from jaxcomp.hardware.mjx.mesh import batch_mesh
from jaxcomp.hardware.mjx.model import LS_ITERATIONS, PAYLOAD_BODY, build_model
from jaxcomp.hardware.mjx.reference import Move, reference_trajectory
from jaxcomp.hardware.mjx.runner import (
    AGREEMENT,
    PLAN,
    RESTART,
    SETTLE,
    SETTLE_STEPS,
    MjxRecording,
    Reduction,
)
from jaxcomp.hardware.mjx.simulator import MjxSimulator
from jaxcomp.hardware.mjx.truth import BatchTruth, true_inertial_params

__all__ = [
    "AGREEMENT",
    "CLOSED_LOOP_AGREEMENT",
    "FAULT_EFFORT",
    "FAULT_LIMIT",
    "FAULT_NAMES",
    "FAULT_OVERSPEED",
    "FAULT_REFUSED",
    "FAULT_STOPPED",
    "LS_ITERATIONS",
    "PAYLOAD_BODY",
    "PLAN",
    "RESTART",
    "SETTLE",
    "SETTLE_STEPS",
    "BatchTruth",
    "ClosedLoopResult",
    "MjxRecording",
    "Reduction",
    "MjxSimulator",
    "Move",
    "Observation",
    "Policy",
    "PushSchedule",
    "batch_mesh",
    "build_model",
    "fault_names",
    "reference_trajectory",
    "servo_gains",
    "true_inertial_params",
]
