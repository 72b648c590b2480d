"""The control study's worlds: the timeline every world follows (the target's reference
rows, the ramped push, the half circle) and each world's drawn truth and controller, with the
controller's model error against that truth.

The timeline, s from the start of the closed loop: the static offset is measured over
``BASELINE``, a push of F ramps up from ``PUSH_START`` (``RAMP`` pushes of F / ``RAMP``,
``RAMP_STEP`` apart) until ``RELEASE``, the displacement is measured over ``HELD``, and the
half circle starts at ``TRACK_START``. Units SI (m, s, N, A, rad); positions in the world (=
arm base) frame.
"""

import math

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.control.trajectory import Trajectory, parse_trajectory
from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import BatchTruth, PushSchedule
from jaxcomp.hardware.truth import DEFAULT_COM_OFFSET, truth_centre
from jaxcomp.identify.evaluate import gravity_current_error_batch, random_poses
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices
from jaxcomp.studies.control_policy import REFERENCE_COLUMNS, controller_params

# ----------------------------------------------------------------------------- the timeline
#: s, the static offset's window.
BASELINE = (0.3, 0.5)
#: s, the first of the ramp's pushes.
PUSH_START = 0.5
#: Pushes of F / RAMP in the ramp, RAMP_STEP s apart.
RAMP = 5
RAMP_STEP = 0.02
#: s, every push ends here.
RELEASE = 1.5
#: s, the displacement's window.
HELD = (RELEASE - 0.25, RELEASE - 0.05)
#: s, the half circle starts here.
TRACK_START = 2.0
#: m, the radius of the paper's half circle (Exp. 2).
PAPER_RADIUS = 0.315


def trajectory_for(robot: Robot, passes: int) -> tuple[np.ndarray, Trajectory]:
    """The half circle the worlds track, from the end effector at the ``home`` pose (the
    worlds settle within a fraction of a mm of it; the controller starts from where each is).

    Args:
        robot: the studied arm.
        passes: half-circle passes (>= 1).

    Returns:
        (start (3,) m in the world frame, the half circle from it): of the paper's radius
        (``PAPER_RADIUS``), or the start's horizontal distance from the arm's vertical axis
        where that is smaller (a smaller arm).
    """
    start = np.asarray(robot.site_position(robot.pose("home"), robot.end_effector), float)
    radius = float(np.hypot(start[0], start[1]))
    spec = f"half-circle:passes={passes}"
    if radius < PAPER_RADIUS:
        spec += f",r={radius:.4f}"
    return start, parse_trajectory(spec).build(start)


def reference_rows(
    trajectory: Trajectory, start: np.ndarray, steps: int, windows: dict[str, tuple[float, float]]
) -> np.ndarray:
    """The policy's reference at t = k ms, k = 0..``steps``.

    Args:
        trajectory: the target's path from ``TRACK_START`` on.
        start: (3,) m, the target before ``TRACK_START`` (world frame).
        steps: 1 kHz steps of the run.
        windows: {"track"|"base"|"push": (from, to) s}, the phase metrics' windows.

    Returns:
        (steps + 1, ``REFERENCE_COLUMNS``): target position (m), velocity (m/s) and
        acceleration (m/s^2), then the window weights, 1 where from <= t < to (else 0).
    """
    t = np.arange(steps + 1) * CONTROL_PERIOD
    rows = np.zeros((steps + 1, REFERENCE_COLUMNS))
    rows[:, 0:3] = start
    moving = t >= TRACK_START
    if moving.any():
        sample = trajectory.sample(t[moving] - TRACK_START)
        rows[moving, 0:3], rows[moving, 3:6], rows[moving, 6:9] = sample
    for col, name in ((9, "track"), (10, "base"), (11, "push")):
        lo, hi = windows.get(name, (math.inf, math.inf))
        rows[(t >= lo) & (t < hi), col] = 1.0
    return rows


def ramped_pushes(direction: np.ndarray, force: float) -> PushSchedule:
    """The ramped push of every world.

    Args:
        direction: (W, 3) unit push directions, world frame.
        force: N, the whole push F.

    Returns:
        ``PushSchedule`` (W, ``RAMP``): F / RAMP along each world's direction, the k-th from
        ``PUSH_START`` + k ``RAMP_STEP`` until ``RELEASE`` (s).
    """
    w = len(direction)
    start = PUSH_START + RAMP_STEP * np.arange(RAMP)
    starts = np.broadcast_to(start, (w, RAMP)).copy()
    piece = force / RAMP * np.asarray(direction, float)
    return PushSchedule(starts, RELEASE - starts, np.repeat(piece[:, None], RAMP, axis=1))


# ----------------------------------------------------------------------------- the worlds
#: Random poses of the pooled gravity-current model error.
POSES = 64


def draw_worlds(
    robot: Robot,
    worlds: int,
    seed: int,
    params_error: float,
    com_error: float,
    nominal: bool,
    noise: float,
    push: str = "horizontal",
    first: int = 0,
) -> tuple[BatchTruth, dict[str, np.ndarray], np.ndarray]:
    """The truth, controller and push direction of the worlds ``first`` .. ``first`` + W - 1,
    each drawn from its own generator ``default_rng((seed, id))``: a world's draws do not
    depend on how many worlds are drawn with it (chunks, processes).

    Truth per world: the model's ratios and friction losses (``truth_centre``; the Gen3 Lite:
    the paper's) x U(0.9, 1.1) and x U(0.8, 1.2), COM offsets U(+-4 mm) per axis on every
    moving link, current noise ``noise`` A.

    Args:
        robot: the studied arm (n joints, nb links).
        worlds: W, the worlds drawn.
        seed: the study's seed.
        params_error: the "identified-like" controller's ratio and friction are the truth's x
            (1 + U(-E, E)) per joint (relative).
        com_error: m, its COM offsets are the truth's + U(-D, D) per axis (moving links).
        nominal: the controller has the model's nominal ratios, no friction compensation and
            nominal COM instead.
        noise: A, the truth's current noise (std).
        push: "horizontal" (uniform in the world's xy plane) or "sphere" (uniform on the unit
            sphere: a 10 N push down at ``home`` plus the friction compensation asks joint 1
            for more than its 14 N m).
        first: the global id of the first world.

    Returns:
        (truth ``BatchTruth`` of W worlds, controller params ``controller_params``: ratio
        (W, n) A/(N m), friction (W, n) A, com (W, nb, 3) m, push directions (W, 3) unit).

    Raises:
        InputError: an unknown ``push``.
    """
    if push not in ("horizontal", "sphere"):
        raise InputError(f"push direction must be 'horizontal' or 'sphere', got {push!r}")
    n, nb = len(arm_joint_indices(robot)), len(robot.link_names)
    moved = robot.tree.moves.any(axis=0)[None, :, None]
    ratio_c, friction_c = truth_centre(robot)
    draws = [_world_draws(np.random.default_rng((seed, w)), n, nb)
             for w in range(first, first + worlds)]  # fmt: skip
    u_ratio, u_friction, u_com, u_err, u_com_err, angle, normal = (
        np.stack(a) for a in zip(*draws, strict=True)
    )
    ratio = ratio_c * (0.9 + 0.2 * u_ratio)
    friction = friction_c * (0.8 + 0.4 * u_friction)
    com = DEFAULT_COM_OFFSET * (2 * u_com - 1) * moved
    truth = BatchTruth.from_arrays(robot, ratio, friction, com_offset=com, current_noise=noise)
    err = np.moveaxis(2 * u_err - 1, 1, 0) * params_error
    com_err = (2 * u_com_err - 1) * com_error * moved
    if push == "horizontal":
        angle = 2 * np.pi * angle
        direction = np.stack([np.cos(angle), np.sin(angle), np.zeros(worlds)], axis=1)
    else:
        direction = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    if nominal:
        nom = RobotParams.nominal(robot)
        params = controller_params(
            robot, np.tile(nom.ratio, (worlds, 1)), np.zeros((worlds, n)), np.zeros_like(com)
        )
    else:
        params = controller_params(
            robot, ratio * (1 + err[0]), friction * (1 + err[1]), com + com_err
        )
    return truth, params, direction


def _world_draws(rng: np.random.Generator, n: int, nb: int) -> tuple[np.ndarray, ...]:
    """One world's uniform [0, 1) draws (ratio (n,), friction (n,), COM (nb, 3), controller
    errors (2, n), controller COM errors (nb, 3), push angle ()) and its normal (3,) push
    direction, in this order whatever the push kind."""
    u = lambda *shape: rng.uniform(0.0, 1.0, shape)  # noqa: E731
    return u(n), u(n), u(nb, 3), u(2, n), u(nb, 3), u(), rng.normal(size=3)


def model_errors(
    robot: Robot, truth: BatchTruth, params: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Per-world model error of the controller's params against the truth.

    The pooled relative gravity-current error is the RMS of r_c g_c(q) - r_t g_t(q) over
    ``POSES`` random poses and all joints together, relative to the RMS of r_t g_t(q)
    (``evaluate.gravity_current_error_batch(pooled=True)``, in batches of one shape, so that
    a world's number does not depend on the others).

    Args:
        robot: the studied arm.
        truth: the W worlds' truth.
        params: the controllers' params (``draw_worlds``).

    Returns:
        {"ratio_error", "friction_error": (W,) RMS over joints of the relative errors;
        "com_error_m": (W,) m, RMS over the moving links' axes; "gravity_current_error_pooled":
        (W,) relative}.
    """
    nominal_com = np.asarray(robot.nominal_params().com)
    moved = robot.tree.moves.any(axis=0)
    true_com = nominal_com[None] + truth.com_offset
    poses = random_poses(robot, POSES, seed=0)
    rms = lambda a, axes: np.sqrt(np.mean(a**2, axis=axes))  # noqa: E731
    return {
        "ratio_error": rms(params["ratio"] / truth.ratio - 1, 1),
        "friction_error": rms(params["friction"] / truth.friction - 1, 1),
        "com_error_m": rms((params["com"] - true_com)[:, moved], (1, 2)),
        "gravity_current_error_pooled": gravity_current_error_batch(
            robot,
            truth.ratio,
            truth.com_offset,
            params["ratio"],
            params["com"] - nominal_com[None],
            poses,
            pooled=True,
            fixed=True,  # batches of one shape: a world's error whatever the chunk
        ),
    }
