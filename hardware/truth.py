"""The simulator's hidden "true robot": what identification has to find.

The truth differs from the nominal model by per-joint current/torque ratios and friction
losses, per-link centre-of-mass offsets of a few mm (link frame, drawn from a seed),
current-sensor noise and optional viscous friction. It is stored in the ``RobotParams`` JSON
format plus two extra keys, ``current_noise`` (A, standard deviation) and ``viscous`` (N m s/rad
per joint or null).

The truth is relative to the model's own figures (``TrueRobot.draw``):

- A model may state its simulator's true ratios and friction losses, per-joint custom numerics
  ``jaxcomp_sim_ratio`` (A/(N m)) and ``jaxcomp_sim_friction`` (A), and its current noise,
  ``jaxcomp_sim_current_noise`` (A): the Gen3 Lite states the paper's identified values.
- Otherwise ratios are the nominal ratio (``RobotParams.nominal``: the model's
  ``jaxcomp_nominal_ratio``, else ``DEFAULT_RATIO``, 1 A/(N m)) times U(``RATIO_SPREAD``), and
  friction losses and current noise scale with each joint's current limit
  (``jaxcomp.robot_params.current_limits``: the model's ``jaxcomp_current_limit``, else
  the effort limit times the nominal ratio, else ``DEFAULT_CURRENT_LIMIT``, 11 A). A joint whose
  current limit is 11 A (the Gen3 Lite's) gets friction losses U(``FRICTION_LOSS``) = U(0.2,
  0.6) A, 2-5 % of its limit, and the current noise ``DEFAULT_CURRENT_NOISE`` (0.05 A); other
  joints scale both by their current limit / 11 A, so that a small arm whose currents are
  ~1 A gets friction losses of ~0.02-0.05 A, not ones comparable to its gravity current. The
  rule trusts the model's limits: a model with placeholder effort limits (URDF
  ``effort="1000"``) and no current limit gets friction losses to match; state real limits or
  ``jaxcomp_sim_friction``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError, ModelError
from jaxcomp.robot import Robot
from jaxcomp.robot_params import (
    DEFAULT_CURRENT_LIMIT,
    RobotParams,
    arm_joint_indices,
    arm_joint_names,
    current_limits,
)

#: Ratios (A/(N m)) and friction losses (A) identified on the paper's real arm, joints 0..5
#: (the values of Figs. 11-12's calibration, the authors' published code; the Gen3 Lite models
#: state them as ``jaxcomp_sim_ratio`` and ``jaxcomp_sim_friction``, the simulator's default
#: truth). The one place of these figures in the code.
PAPER_RATIO = (1.0282, 0.3074, 1.0282, 1.9074, 2.0373, 1.9724)
PAPER_FRICTION = (0.5318, 1.4776, 0.6695, 0.3013, 0.3732, 0.5923)
#: A, standard deviation of the measured current of a joint whose current limit is 11 A.
DEFAULT_CURRENT_NOISE = 0.05
DEFAULT_COM_OFFSET = 0.004  # m, COM offsets are drawn uniformly in +-this per axis
#: A drawn true ratio is the nominal ratio times U(lo, hi).
RATIO_SPREAD = (0.9, 1.25)
#: A: a drawn friction loss is U(lo, hi) times the current limit / ``DEFAULT_CURRENT_LIMIT``.
FRICTION_LOSS = (0.2, 0.6)


def _stated(robot: Robot, name: str, positive: bool) -> np.ndarray | None:
    """A per-joint custom numeric of the simulator's truth (``Robot.joint_numeric``), or None
    when absent; ``ModelError`` unless every joint has a finite value > 0 (>= 0 unless
    ``positive``)."""
    value = robot.joint_numeric(name)
    if value is None:
        return None
    bad = ~np.isfinite(value) | ((value <= 0) if positive else (value < 0))
    if bad.any():
        sign = "> 0" if positive else ">= 0"
        raise ModelError(
            f"{robot.name}: custom numeric {name} must give every current-controlled joint a "
            f"finite value {sign}, got {value.tolist()}"
        )
    return value


def stated_truth(robot: Robot) -> tuple[np.ndarray, np.ndarray] | None:
    """The simulator's true ratios and friction losses that the model states (custom
    numerics ``jaxcomp_sim_ratio`` and ``jaxcomp_sim_friction``).

    Args:
        robot: the nominal model.

    Returns:
        (ratio (n,) A/(N m), friction (n,) A), or None when the model states neither.

    Raises:
        ModelError: it states one alone, or a value that is not finite and > 0 (ratio) or
            >= 0 (friction).
    """
    ratio = _stated(robot, "jaxcomp_sim_ratio", positive=True)
    friction = _stated(robot, "jaxcomp_sim_friction", positive=False)
    if (ratio is None) != (friction is None):
        raise ModelError(
            f"{robot.name}: the model states one of jaxcomp_sim_ratio and jaxcomp_sim_friction "
            "without the other"
        )
    return None if ratio is None else (ratio, friction)


def current_scale(robot: Robot) -> np.ndarray:
    """The scale of each joint's drawn friction loss and current noise.

    Args:
        robot: the nominal model.

    Returns:
        (n,) each current-controlled joint's current limit (``current_limits``) over
        ``DEFAULT_CURRENT_LIMIT``.
    """
    return current_limits(robot) / DEFAULT_CURRENT_LIMIT


def friction_loss_range(robot: Robot) -> np.ndarray:
    """The range of drawn friction losses.

    Args:
        robot: the nominal model.

    Returns:
        (n, 2) A, [low, high] per joint: ``FRICTION_LOSS`` times ``current_scale``.
    """
    return current_scale(robot)[:, None] * np.asarray(FRICTION_LOSS)


def model_current_noise(robot: Robot) -> float:
    """The standard deviation of the simulated current noise.

    Args:
        robot: the nominal model.

    Returns:
        A: the model's ``jaxcomp_sim_current_noise``, else ``DEFAULT_CURRENT_NOISE`` times
        the mean ``current_scale`` over the joints.

    Raises:
        ModelError: a stated noise that is not one finite value >= 0.
    """
    stated = robot.custom_numeric("jaxcomp_sim_current_noise")
    if stated is None:
        return DEFAULT_CURRENT_NOISE * float(np.mean(current_scale(robot)))
    if stated.size != 1 or not np.isfinite(stated[0]) or stated[0] < 0:
        raise ModelError(
            f"{robot.name}: custom numeric jaxcomp_sim_current_noise must be one value >= 0 "
            f"(A), got {stated.tolist()}"
        )
    return float(stated[0])


def truth_centre(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The centre of the model's truths: the stated ones (``stated_truth``), else the middle
    of the drawn ranges.

    Args:
        robot: the nominal model.

    Returns:
        (ratio (n,) A/(N m), friction (n,) A).
    """
    stated = stated_truth(robot)
    if stated is not None:
        return stated
    ratio = RobotParams.nominal(robot).ratio * np.mean(RATIO_SPREAD)
    return ratio, friction_loss_range(robot).mean(axis=1)


def friction_loss_torque(friction: np.ndarray, ratio: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """MuJoCo's ``dof_frictionloss`` of joints with a Coulomb friction loss in current.

    Args:
        friction: friction losses, A (any shape that broadcasts with ``ratio``).
        ratio: current/torque ratios, A/(N m).
        floor: N m, the smallest torque returned.

    Returns:
        friction / ratio, N m, at least ``floor`` (elementwise).
    """
    return np.maximum(np.asarray(friction, dtype=float) / np.asarray(ratio, dtype=float), floor)


@dataclass
class TrueRobot:
    """Hidden parameters of a simulated arm.

    Attributes:
        params: ratio (n,) A/(N m), friction (n,) A, com_offset {link: (3,) m, link frame}.
        current_noise: A, standard deviation of the Gaussian current-sensor noise.
        viscous: (n,) N m s/rad viscous friction per joint, or None.
        seed: seed of the noise (and of the draw, for a drawn truth).
    """

    params: RobotParams
    current_noise: float = DEFAULT_CURRENT_NOISE
    viscous: np.ndarray | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        self.current_noise = checks.number(
            self.current_noise, "current_noise", nonneg=True, unit="A"
        )
        if self.viscous is not None:
            self.viscous = checks.array(
                self.viscous, "viscous friction", n=self.params.n, nonneg=True, unit="N m s/rad"
            )

    @property
    def ratio(self) -> np.ndarray:
        """(n,) A/(N m), the true current/torque ratios."""
        return self.params.ratio

    @property
    def friction(self) -> np.ndarray:
        """(n,) A, the true friction losses."""
        return self.params.friction

    @property
    def friction_torque(self) -> np.ndarray:
        """(n,) Coulomb friction torque, N m (``friction_loss_torque``: friction loss / ratio)."""
        return friction_loss_torque(self.params.friction, self.params.ratio)

    @classmethod
    def draw(
        cls,
        robot: Robot,
        seed: int = 0,
        com_offset: float = DEFAULT_COM_OFFSET,
        current_noise: float | None = None,
        viscous: np.ndarray | None = None,
    ) -> TrueRobot:
        """A truth for ``robot`` drawn from ``seed`` (see the module docstring).

        Ratios and friction losses: the model's stated ones (``stated_truth``), else the
        nominal ratio times U(``RATIO_SPREAD``) and U(``FRICTION_LOSS``) A times
        ``current_scale`` (``friction_loss_range``).

        Args:
            robot: the nominal model.
            seed: of the draw (and of the noise).
            com_offset: m, COM offsets are U(-com_offset, com_offset) per axis (link frame)
                on every link an arm joint moves.
            current_noise: A, standard deviation (None: ``model_current_noise``).
            viscous: (n,) N m s/rad, or None.

        Returns:
            The ``TrueRobot``.
        """
        rng = np.random.default_rng(seed)
        arm = arm_joint_indices(robot)
        n = len(arm)
        stated = stated_truth(robot)
        if stated is not None:
            ratio, friction = stated
        else:
            ratio = RobotParams.nominal(robot).ratio * rng.uniform(*RATIO_SPREAD, n)
            friction = rng.uniform(*FRICTION_LOSS, n) * current_scale(robot)
        moved = robot.tree.moves[arm].any(axis=0)
        offsets = {
            name: rng.uniform(-com_offset, com_offset, 3)
            for name, m in zip(robot.link_names, moved, strict=True)
            if m
        }
        params = RobotParams(
            robot.name,
            ratio,
            friction,
            offsets,
            method=f"truth seed={seed}",
            joints=arm_joint_names(robot),
        )
        noise = model_current_noise(robot) if current_noise is None else current_noise
        return cls(params, noise, viscous, seed)

    # ----------------------------------------------------------------- files
    def _extra(self) -> dict:
        """What a truth adds to its params: current noise (A), viscous friction, seed."""
        return {
            "current_noise": self.current_noise,
            "viscous": None if self.viscous is None else self.viscous.tolist(),
            "seed": self.seed,
        }

    def to_dict(self) -> dict:
        """The truth file's contents (``save``).

        Returns:
            Its params' JSON dict and the noise and viscous keys.
        """
        return self.params.to_dict() | self._extra()

    def save(self, path: str | Path) -> Path:
        """Write the truth as a params JSON file (atomic) with its noise and viscous keys.

        Args:
            path: the file.

        Returns:
            The path written.
        """
        return self.params.save(path, extra=self._extra())

    @classmethod
    def load(cls, path: str | Path, robot: Robot | None = None) -> TrueRobot:
        """Read a truth, or any params file.

        Args:
            path: the file.
            robot: the model it is for (checked by ``RobotParams.load``); a file without a
                noise gets its ``model_current_noise`` (``DEFAULT_CURRENT_NOISE`` without one).

        Returns:
            The ``TrueRobot``.
        """
        params = RobotParams.load(path, robot)
        data = json.loads(Path(path).read_text())
        noise = DEFAULT_CURRENT_NOISE if robot is None else model_current_noise(robot)
        return cls(
            params,
            data.get("current_noise", noise),
            data.get("viscous"),
            int(data.get("seed", 0)),
        )

    # ----------------------------------------------------------------- the true MjModel
    def apply(self, model: mujoco.MjModel, robot: Robot, friction_timeconst: float) -> None:
        """Write the truth into a compiled model, in place.

        body_ipos += com_offset (both in the body frame); dof_frictionloss = friction / ratio
        (N m, ``friction_loss_torque``) with a stiff solver reference so that the Coulomb
        friction is delivered in full; dof_damping = viscous.

        Args:
            model: a compiled copy of ``robot``'s model (changed).
            robot: the nominal model the truth is for.
            friction_timeconst: s, the friction loss's solver time constant.
        """
        self.params.check(robot)
        for link, off in self.params.com_offset.items():
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, link)
            model.body_ipos[b] += off
        dofs = model.jnt_dofadr[
            [_joint_id(model, robot.joint_names[j]) for j in arm_joint_indices(robot)]
        ]
        model.dof_frictionloss[dofs] = self.friction_torque
        model.dof_solref[dofs] = [friction_timeconst, 1.0]
        # impedance near 1: little constraint softness, so that light joints get the full
        # friction loss down to ~1 deg/s (the default 0.9-0.95 leaves them short below ~20 deg/s)
        model.dof_solimp[dofs, :3] = [0.999, 0.999, 0.001]
        if self.viscous is not None:
            model.dof_damping[dofs] = self.viscous


def _joint_id(model: mujoco.MjModel, name: str) -> int:
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if j < 0:
        raise InputError(f"joint {name!r} not in the simulation model")
    return j
