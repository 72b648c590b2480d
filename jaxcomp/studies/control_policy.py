"""The control study's closed-loop policy: the impedance controller with per-world params, as
``MjxSimulator.run_closed_loop`` drives each world with it.

A world's params are the controller's model (ratios A/(N m), friction losses A, every link's
COM m in its link frame); each reference row gives the target (position m, velocity m/s,
acceleration m/s^2, arm base frame) and the 0/1 weights of the study's metric windows; the
policy state carries the control loop's previous command and saturation watchdog and the sums
of the metrics (m, m^2).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.control import ImpedanceGains, make_impedance_controller
from jaxcomp.control.impedance import ResolvedModel, impedance_step_fn
from jaxcomp.hardware import ArmLimits
from jaxcomp.hardware.mjx import Observation, Policy
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import arm_joint_indices

#: Columns of a reference row: target pos (3) | vel (3) | acc (3) | w_track | w_base | w_push.
REFERENCE_COLUMNS = 12

PolicyParams = dict[str, jax.Array]
PolicyState = dict[str, jax.Array]


def impedance_policy(
    robot: Robot | str, gains: ImpedanceGains, max_saturated_cycles: int = 250
) -> Policy:
    """The impedance controller as a ``Policy`` for ``MjxSimulator.run_closed_loop``.

    Per-world params: ``ratio`` (n,) A/(N m), ``friction`` (n,) A, ``com`` (nb, 3) m (every
    link's centre of mass, link frame) — the controller's model. The reference row is
    target pos m | vel m/s | acc m/s^2 (arm frame) | w_track | w_base | w_push (0/1 weights of
    the metric windows). State: ``prev`` (n,) A (last command; at the start the measured
    current within the arm's current limit, as ``run_control``), ``sat`` (n,) consecutive
    cycles at the controller's saturation (stop beyond ``max_saturated_cycles``, as the loop's
    watchdog), and the sums of the metrics: ``track_sq`` m^2, ``track_n``, ``track_max`` m,
    ``base_sum``/``push_sum`` (3,) m of ee - target and ``base_n``/``push_n``.
    Kept on the robot per (gains, max_saturated_cycles): one compiled program per
    configuration and simulator.

    Args:
        robot: the controller's model (an arm alone), or its built-in name or file.
        gains: the controller's gains.
        max_saturated_cycles: consecutive saturated cycles beyond which a world's run stops
            (the loop's watchdog).

    Returns:
        The ``Policy`` (init, step).
    """
    robot = load_robot(robot)
    key = ("study_impedance_policy", gains, max_saturated_cycles)
    return robot.cached(key, lambda: _closed_loop_policy(robot, gains, max_saturated_cycles))


def _closed_loop_policy(robot: Robot, gains: ImpedanceGains, max_saturated_cycles: int) -> Policy:
    """The controller's resolved model (``ImpedanceController.resolved``; the params become
    per-world) wrapped with the watchdog and the metric sums."""
    controller = make_impedance_controller(robot, None, gains)
    base = controller.resolved
    limit = ArmLimits.from_robot(robot, arm_joint_indices(robot)).current
    saturation = np.minimum(controller.joint.limit, limit) - 1e-9  # the watchdog's test
    step = functools.partial(_policy_step, base, gains, saturation, max_saturated_cycles)
    return Policy(init=functools.partial(_policy_init, limit, controller.n), step=step)


def _policy_step(
    base: ResolvedModel,
    gains: ImpedanceGains,
    saturation: np.ndarray,
    max_saturated_cycles: int,
    p: PolicyParams,
    s: PolicyState,
    obs: Observation,
) -> tuple[jax.Array, PolicyState, jax.Array]:
    """One cycle of one world: the controller with the world's params, the watchdog and the
    metric sums (see ``impedance_policy``)."""
    res = base._replace(
        inertial=base.inertial._replace(com=p["com"]), ratio=p["ratio"], friction=p["friction"]
    )
    ref = obs.reference
    pos = ref[0:3]
    cur, diag = impedance_step_fn(res, gains)(obs.q, obs.dq, pos, ref[3:6], ref[6:9], s["prev"])
    sat = jnp.where(jnp.abs(cur) >= saturation, s["sat"] + 1, 0)
    err = diag.ee_pos - pos
    e2 = err @ err
    w_track, w_base, w_push = ref[9], ref[10], ref[11]
    state = {
        "prev": cur,
        "sat": sat,
        "track_sq": s["track_sq"] + w_track * e2,
        "track_n": s["track_n"] + w_track,
        "track_max": jnp.maximum(s["track_max"], w_track * jnp.sqrt(e2)),
        "base_sum": s["base_sum"] + w_base * err,
        "base_n": s["base_n"] + w_base,
        "push_sum": s["push_sum"] + w_push * err,
        "push_n": s["push_n"] + w_push,
    }
    return cur, state, jnp.any(sat > max_saturated_cycles)


def _policy_init(limit: np.ndarray, n: int, p: PolicyParams, obs: Observation) -> PolicyState:
    """A world's policy state at sample 0 (see ``impedance_policy``)."""
    zero = jnp.zeros((), obs.q.dtype)
    return {
        "prev": jnp.clip(obs.current, -limit, limit),
        "sat": jnp.zeros(n, jnp.int32),
        "track_sq": zero,
        "track_n": zero,
        "track_max": zero,
        "base_sum": jnp.zeros(3, obs.q.dtype),
        "base_n": zero,
        "push_sum": jnp.zeros(3, obs.q.dtype),
        "push_n": zero,
    }


def controller_params(
    robot: Robot, ratio: np.ndarray, friction: np.ndarray, com_offset: np.ndarray
) -> dict[str, np.ndarray]:
    """Per-world policy params: ratio (W, n) A/(N m), friction (W, n) A, and every link's COM
    (W, nb, 3) m = nominal + ``com_offset`` (W, nb, 3) m, link frame.

    Args:
        robot: the arm-alone model.
        ratio: (W, n) A/(N m), the controller's ratios.
        friction: (W, n) A, its friction losses.
        com_offset: (W, nb, 3) m, its COM offsets of every link (``robot.link_names``
            order, link frame).

    Returns:
        {"ratio": (W, n), "friction": (W, n), "com": (W, nb, 3)} float arrays.
    """
    com = np.asarray(robot.nominal_params().com)[None] + np.asarray(com_offset, float)
    return {"ratio": np.asarray(ratio, float), "friction": np.asarray(friction, float), "com": com}
