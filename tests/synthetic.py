"""Calibration recordings computed straight from the model (no simulator): exact truth, fast.

current = r * g_true(q) + l * d + b * v + noise for the swept joint (g_true: the nominal model
with the truth's COM offsets and an optional payload), sampled at 1 kHz along each sweep of a
plan at constant speed (no ramps); optionally with the transfers between sweeps (straight
joint-space lines at constant velocity, every joint's current r (g_true + C_true(q, dq) dq) +
l sign(dq) + b dq + noise).
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import dynamics
from jaxcomp.identify.evaluate import gravity_current_error as relative_gravity_error  # noqa: F401
from jaxcomp.identify.evaluate import random_poses  # noqa: F401
from jaxcomp.recording import Recording, validate
from jaxcomp.robot_params import RobotParams


def sweep(joint: int, hold, lower: float, upper: float, speed: float, dt: float = 1e-3):
    """q (2m, n), dq, direction of one sweep lower -> upper -> lower at ``speed`` rad/s."""
    m = int(round((upper - lower) / speed / dt))
    up = lower + speed * dt * np.arange(m)
    q = np.tile(np.asarray(hold, float), (2 * m, 1))
    q[:m, joint] = up
    q[m:, joint] = up[::-1] + speed * dt
    dq = np.zeros_like(q)
    dq[:m, joint], dq[m:, joint] = speed, -speed
    return q, dq, np.r_[np.ones(m), -np.ones(m)].astype(int)


def transfer(a, b, speed: float, dt: float = 1e-3, ring=None):
    """q (m, n), dq, ddq of a straight move from pose ``a`` to ``b`` whose longest way goes at
    ``speed`` rad/s (none when the poses are the same). ``ring`` (fraction, Hz, s): the
    velocity rings as a servo's after its ramp, (1 + fraction e^(-t / s) sin(2 pi Hz t))
    times the cruise's (the move then ends a little off ``b``)."""
    way = np.asarray(b, float) - np.asarray(a, float)
    m = int(round(np.abs(way).max() / speed / dt))
    if m < 2:
        return (np.zeros((0, len(way))),) * 3
    t = np.arange(m) * dt
    s, ds, dds = t, np.ones(m), np.zeros(m)  # travelled (s), at the cruise speed 1 / (m dt)
    if ring is not None:
        eps, f, tau = ring
        w, k, decay = 2 * np.pi * f, 1.0 / tau, np.exp(-t / tau)
        s = s + eps * (w - decay * (w * np.cos(w * t) + k * np.sin(w * t))) / (w**2 + k**2)
        ds = ds + eps * decay * np.sin(w * t)
        dds = eps * decay * (w * np.cos(w * t) - k * np.sin(w * t))
    v = way / (m * dt)
    return np.asarray(a, float) + s[:, None] * v, ds[:, None] * v, dds[:, None] * v


def recording(
    robot,
    truth: RobotParams,
    sweeps,
    noise: float = 0.05,
    seed: int = 0,
    gravity=(0.0, 0.0, -9.81),
    payload_mass: float = 0.0,
    payload_com=(0.0, 0.0, 0.0),
    viscous=None,
    compliance: float = 0.0,
    scale: float = 1.0,
    lag: float = 0.0,
    transfers: float = 0.0,
    ring=None,
) -> Recording:
    """A recording of ``sweeps`` [(joint, hold, lower, upper, speed)] for ``truth``.

    ``compliance`` rad/(N m): held joints give way to their gravity torque as a stiff servo
    does (q = hold - compliance g(q)), the swept joint follows its path. ``scale``: the
    current's unit in A (1e-3: mA). ``lag`` s: the current flowed at the pose ``lag``
    earlier, q - lag dq (the recording says so in ``current_lag``, as the simulators').
    ``transfers`` rad/s: the speed of the moves between sweeps, recorded with ``joint`` -1
    (0: none, each sweep starts where the one before ends); ``ring``: how their velocity
    rings (``transfer``), the current then holds M(q) ddq too."""
    parts, joints, ddq = [], [], []
    for k, s in enumerate(sweeps):
        if transfers and k:
            q_t, dq_t, ddq_t = transfer(parts[-1][0][-1], sweep(*s)[0][0], transfers, ring=ring)
            parts.append((q_t, dq_t, np.zeros(len(q_t), int)))
            joints.append(np.full(len(q_t), -1))
            ddq.append(ddq_t)
        parts.append(sweep(*s))
        joints.append(np.full(len(parts[-1][2]), s[0]))
    q = np.concatenate([p[0] for p in parts])
    dq = np.concatenate([p[1] for p in parts])
    d = np.concatenate([p[2] for p in parts])
    joint = np.concatenate(joints)
    params = truth.inertial_params(robot)
    if payload_mass > 0:
        params = robot.with_payload(params, payload_mass, payload_com)
    g = jax.jit(jax.vmap(lambda x: dynamics.gravity(robot.tree, x, params, jnp.asarray(gravity))))
    if compliance:
        held = np.ones_like(q, bool)
        held[np.arange(len(d)), joint] = False
        target = q.copy()
        for _ in range(3):  # fixed point of q = hold - compliance g(q)
            q = np.where(held, target - compliance * np.asarray(g(q)), target)
    current = truth.ratio * np.asarray(g(q - lag * dq))
    moving = joint < 0
    if moving.any():  # the transfers: every joint moves

        def inverse(x, v, acc):  # M(q) ddq + C(q, dq) dq
            m = dynamics.mass_matrix(robot.tree, x, params)
            return m @ acc + dynamics.coriolis(robot.tree, x, v, params)

        qm, vm, am = q[moving] - lag * dq[moving], dq[moving], np.concatenate(ddq)
        torque = np.asarray(jax.jit(jax.vmap(inverse))(qm, vm, am))
        current[moving] += truth.ratio * torque + truth.friction * np.sign(vm)
    rows = np.flatnonzero(~moving)
    current[rows, joint[rows]] += truth.friction[joint[rows]] * d[rows]
    if viscous is not None:
        current += truth.ratio * np.asarray(viscous) * dq
    current += noise * np.random.default_rng(seed).standard_normal(current.shape)
    return validate(
        dict(
            t=np.arange(len(d)) * 1e-3,
            q=q,
            dq=dq,
            current=current / scale,
            joint=joint,
            direction=d,
            model=robot.reference,
            gravity=np.asarray(gravity, float),
            payload_mass=payload_mass,
            payload_com=np.asarray(payload_com, float),
            current_lag=lag,
        )
    )


def plan_sweeps(plan, speed_scale=None):
    """[(joint, hold, lower, upper, speed)] of a ``CalibrationPlan``."""
    out = []
    for k, s in enumerate(plan.sweeps):
        scale = 1.0 if speed_scale is None else speed_scale(k, s)
        out.append((s.joint, s.hold, s.lower, s.upper, s.speed * scale))
    return out


def with_noise(rec: Recording, sigma: float, seed: int) -> Recording:
    """``rec`` with fresh Gaussian current-sensor noise, as the simulator adds it."""
    noise = sigma * np.random.default_rng(seed).standard_normal(rec.current.shape)
    data = rec.to_arrays()
    data["current"] = rec.current + noise
    return Recording(
        **{k: data[k] for k in ("t", "q", "dq", "current", "joint", "direction")},
        model=rec.model,
        gravity=rec.gravity,
    )
