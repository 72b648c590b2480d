"""The MjModel the MJX simulator steps: the CPU Simulator's model of an arm.

``build_model`` compiles a robot's model file as ``Simulator._build`` does for an arm-only
model: 1 ms implicitfast, one servo actuator (gain 1, affine bias, set per world) per arm
joint, and optionally a massless payload body at the end-effector site whose mass is set per
world. ``end_effector_site`` and ``end_effector_point`` locate the end effector;
``WORLD_MODEL_FIELDS`` names the fields each world sets from its truth. Units: m, s, N m.
"""

from __future__ import annotations

import mujoco
import numpy as np

from jaxcomp.errors import ModelError
from jaxcomp.hardware.sim_model import simulation_spec
from jaxcomp.robot import Robot
from jaxcomp.robot_params import BASE_JOINTS, arm_joint_indices

#: Line-search steps per Newton iteration of the constraint solver (MuJoCo's default, which
#: the CPU Simulator keeps: 50). MJX runs the line search as a scan of this many steps (a
#: vmapped ``lax.cond`` computes every step for every world), so the cap is paid at every
#: Newton iteration (a ``lax.while_loop`` that stops when the worlds are done was slower on an
#: H100: 7.1e6 against 8.1e6 world-steps/s, 36 864 worlds). At 12 (1.9x the world-steps/s of
#: 50) the friction-loss solve was left unconverged on light joints: a line search stopped at
#: the cap barely lowers the cost, and the Newton loop then ends on its improvement test
#: (relative to the trace of M, the heavy joints'). On ``serial_arm(31, n=6, continuous=(0,
#: 3))`` (last roll joint 1.8e-4 kg m^2, friction loss 1.35 N m) one such step left a
#: gradient of 1.47 N m (converged: 1e-12) and 2.2 rad/s in 1 ms, an overspeed in 671 of 1024
#: study worlds that the CPU Simulator never shows. That step converges from 14 steps on
#: (``tests/test_mjx_sim.py``); 16 keeps a margin. H100, 36 864 worlds: 9.96e6 world-steps/s
#: at 12, 8.43e6 at 20, about 3.4e6 at 8 (the unconverged solves cost more Newton
#: iterations).
LS_ITERATIONS = 16
#: Name of the payload body ``build_model(payload=True)`` adds at the end-effector site.
PAYLOAD_BODY = "jaxcomp_payload"
#: N m, the friction loss of a friction-free joint: MJX treats a friction row of zero loss as
#: a locked joint (its force is only bounded by the loss when the loss is > 0).
MIN_FRICTION_LOSS = 1e-9
#: The MJX model fields that differ between worlds (set from each world's truth, vmap axis 0),
#: by their tree path; the rest of the model is shared.
WORLD_MODEL_FIELDS = (
    "body_ipos",
    "body_mass",
    "dof_frictionloss",
    "dof_damping",
    "actuator_biasprm",
    "opt.gravity",
)


def end_effector_site(robot: Robot) -> str:
    """The end-effector site's name (``Robot.end_effector``), checked to exist.

    Args:
        robot: the robot.

    Returns:
        The site's name.

    Raises:
        ModelError: the model has no such site.
    """
    name = robot.end_effector
    if mujoco.mj_name2id(robot.model, mujoco.mjtObj.mjOBJ_SITE, name) < 0:
        raise ModelError(f"the model has no end-effector site {name!r}")
    return name


def end_effector_point(robot: Robot) -> tuple[str, np.ndarray]:
    """Where the end-effector site is.

    Args:
        robot: the robot.

    Returns:
        (the name of the site's body, the site's position (3,) m in that body's frame).

    Raises:
        ModelError: the model has no end-effector site.
    """
    m = robot.model
    s = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, end_effector_site(robot))
    b = int(m.site_bodyid[s])
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b), m.site_pos[s].copy()


def build_model(robot: Robot, payload: bool = False) -> mujoco.MjModel:
    """The CPU Simulator's MjModel of ``robot`` (``simulation_spec``: 1 ms implicitfast, one
    actuator per arm joint) with ``LS_ITERATIONS``.

    Args:
        robot: an arm-only robot loaded from a model file.
        payload: add a massless body ``PAYLOAD_BODY`` at the end-effector site (its mass is
            set per world).

    Returns:
        The compiled ``MjModel``.

    Raises:
        ModelError: no model file, mobile-base joints, a joint other than hinge or slide,
            or a model that does not compile.
    """
    if robot.source is None:
        raise ModelError("the MJX simulator needs a robot loaded from a model file")
    names = robot.joint_names
    if any(b in names for b in BASE_JOINTS):
        raise ModelError(f"{robot.name} has mobile-base joints: the MJX simulator is arm-only")
    spec = simulation_spec(robot, arm_joint_indices(robot))
    spec.option.ls_iterations = LS_ITERATIONS
    if payload:
        body, pos = end_effector_point(robot)
        spec.body(body).add_body(
            name=PAYLOAD_BODY,
            pos=pos,
            ipos=[0.0, 0.0, 0.0],
            iquat=[1.0, 0.0, 0.0, 0.0],
            mass=0.0,
            inertia=[0.0, 0.0, 0.0],
            explicitinertial=True,
        )
    try:
        model = spec.compile()
    except Exception as exc:
        raise ModelError(f"cannot compile the simulation model: {exc}") from None
    if model.nq != model.nv or model.nv != model.nu:
        raise ModelError(f"{robot.name}: the MJX simulator needs hinge/slide arm joints only")
    return model
