"""One physics step of an MJX world: MuJoCo C's implicitfast integrator.

``implicitfast_step(model, dtype)`` returns the step ``(m, d) -> (qpos, qvel, qacc_warmstart,
applied actuator torque, d_forward)`` that both runners vmap over worlds. It integrates as
MuJoCo C does when an effort limit clamps a servo (see its docstring), which ``mjx.step`` does
not, and reports the actuator torque as the CPU Simulator measures it (its damping at the
step's new velocity), so that the MJX worlds agree with it. Units: rad, rad/s, N m, s.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxcomp.errors import ModelError

#: One world's step: (model, data) -> (qpos, qvel, qacc_warmstart, applied actuator torque,
#: the data after ``mjx.forward`` at the step's start).
Step = Callable[[mjx.Model, mjx.Data], tuple[jax.Array, jax.Array, jax.Array, jax.Array, mjx.Data]]


def implicitfast_step(model: mujoco.MjModel, dtype: jnp.dtype) -> Step:
    """One ``mj_step`` of MuJoCo C's implicitfast integrator for hinge/slide joints driven
    by joint-transmission actuators.

    ``mjx.step`` keeps a servo's velocity derivative (-kv) in the implicit matrix even when its
    joint torque is clamped at the effort limit (``jnt_actfrcrange``); MuJoCo C (4.0) leaves it
    out, as the clamped torque no longer depends on the velocity. This step does as C does:
    M_hat = M + dt (diag(dof_damping) - sum over unclamped actuators of gear^2 biasprm[2]),
    qacc = M_hat^-1 (qfrc_smooth + qfrc_constraint), qvel += dt qacc, qpos += dt qvel.

    Args:
        model: the MjModel whose actuators' joints, gears, effort limits and timestep the step
            fixes (the ``mjx.Model`` it is called with supplies the rest, per world).
        dtype: the worlds' float dtype.

    Returns:
        The ``Step`` (m, d) -> (qpos, qvel, qacc_warmstart, applied, d_forward): applied (nv,)
        N m the actuators' joint torque over the step, qfrc_actuator with the servo damping at
        the new velocity (qfrc_actuator + dt (d qfrc_actuator / d qvel) qacc, as the implicit
        integration applies it), d_forward the data after ``mjx.forward`` at the step's start
        (kinematics).

    Raises:
        ModelError: an actuator that does not drive a joint, or one with a force range or a
            gain that is not fixed.
    """
    if not (model.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT).all():
        raise ModelError("the MJX simulator drives joints only")
    if model.actuator_forcelimited.any() or (model.actuator_gaintype != 0).any():
        raise ModelError("the MJX simulator's actuators have fixed gain and no force range")
    jnt = model.actuator_trnid[:, 0]
    dof = model.jnt_dofadr[jnt]
    gear_np = model.actuator_gear[:, 0]
    limited = model.jnt_actfrclimited[jnt].astype(bool)
    lo_np = np.where(limited, model.jnt_actfrcrange[jnt, 0], -np.inf)
    hi_np = np.where(limited, model.jnt_actfrcrange[jnt, 1], np.inf)
    nv, dt = model.nv, float(model.opt.timestep)

    def step(
        m: mjx.Model, d: mjx.Data
    ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, mjx.Data]:
        gear, lo, hi = (jnp.asarray(a, dtype) for a in (gear_np, lo_np, hi_np))
        d = mjx.forward(m, d)
        raw = jnp.zeros(nv, dtype).at[dof].add(gear * d.actuator_force)
        clamped = (raw[dof] <= lo) | (raw[dof] >= hi)
        bias_vel = jnp.where(clamped, 0.0, gear * gear * m.actuator_biasprm[:, 2])
        actuated = jnp.zeros(nv, dtype).at[dof].add(bias_vel)
        m_hat = mjx.full_m(m, d) - dt * jnp.diag(actuated - m.dof_damping)
        factor = jax.scipy.linalg.cho_factor(m_hat)
        qacc = jax.scipy.linalg.cho_solve(factor, d.qfrc_smooth + d.qfrc_constraint)
        qvel = d.qvel + dt * qacc
        applied = d.qfrc_actuator + dt * actuated * qacc
        return d.qpos + dt * qvel, qvel, d.qacc, applied, d

    return step
