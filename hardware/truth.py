"""The simulator's hidden "true robot": what identification has to find.

The truth differs from the nominal model by per-joint current/torque ratios and friction
losses (default: the values identified on the paper's real Gen3 Lite), per-link centre-of-mass
offsets of a few mm (link frame, drawn from a seed), current-sensor noise and optional viscous
friction. It is stored in the ``RobotParams`` JSON format plus two extra keys,
``current_noise`` (A, standard deviation) and ``viscous`` (N m s/rad per joint or null).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, _vector, arm_joint_indices, arm_joint_names

#: Ratios (A/(N m)) and friction losses (A) identified on the paper's real arm, joints 0..5.
PAPER_RATIO = (1.0282, 0.3074, 1.0282, 1.9074, 2.0373, 1.9724)
PAPER_FRICTION = (0.5318, 1.4776, 0.6695, 0.3013, 0.3732, 0.5923)
DEFAULT_CURRENT_NOISE = 0.05  # A, standard deviation of the measured current
DEFAULT_COM_OFFSET = 0.004  # m, COM offsets are drawn uniformly in +-this per axis


def friction_loss_torque(friction: np.ndarray, ratio: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """MuJoCo's ``dof_frictionloss`` (N m) of joints whose Coulomb friction loss is
    ``friction`` A at current/torque ratio ``ratio`` A/(N m): friction / ratio, at least
    ``floor`` N m (elementwise; any shapes that broadcast)."""
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
        self.current_noise = float(self.current_noise)
        if not np.isfinite(self.current_noise) or self.current_noise < 0:
            raise InputError(f"current_noise must be >= 0 A, got {self.current_noise}")
        if self.viscous is not None:
            self.viscous = _vector(self.viscous, "viscous", self.params.n)
            if np.any(self.viscous < 0):
                raise InputError("viscous friction must be >= 0 N m s/rad")

    @property
    def ratio(self) -> np.ndarray:
        return self.params.ratio

    @property
    def friction(self) -> np.ndarray:
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
        current_noise: float = DEFAULT_CURRENT_NOISE,
        viscous: np.ndarray | None = None,
    ) -> TrueRobot:
        """A truth for ``robot`` drawn from ``seed``.

        Ratios and friction losses: the paper's values for a 6-joint arm, else the nominal
        ratio times U(0.9, 1.25) and U(0.2, 0.6) A. COM offsets: U(-com_offset, com_offset) m
        per axis on every link an arm joint moves.
        """
        rng = np.random.default_rng(seed)
        nominal = RobotParams.nominal(robot)
        arm = arm_joint_indices(robot)
        if nominal.n == len(PAPER_RATIO):
            ratio, friction = np.array(PAPER_RATIO), np.array(PAPER_FRICTION)
        else:
            ratio = nominal.ratio * rng.uniform(0.9, 1.25, nominal.n)
            friction = rng.uniform(0.2, 0.6, nominal.n)
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
        return cls(params, current_noise, viscous, seed)

    # ----------------------------------------------------------------- files
    def save(self, path: str | Path) -> Path:
        """Write the truth as a params JSON file (atomic) with its noise and viscous keys."""
        extra = {
            "current_noise": self.current_noise,
            "viscous": None if self.viscous is None else self.viscous.tolist(),
            "seed": self.seed,
        }
        return self.params.save(path, extra=extra)

    @classmethod
    def load(cls, path: str | Path, robot: Robot | None = None) -> TrueRobot:
        """Read a truth (or any params file: noise then defaults to ``DEFAULT_CURRENT_NOISE``)."""
        params = RobotParams.load(path, robot)
        data = json.loads(Path(path).read_text())
        return cls(
            params,
            data.get("current_noise", DEFAULT_CURRENT_NOISE),
            data.get("viscous"),
            int(data.get("seed", 0)),
        )

    # ----------------------------------------------------------------- the true MjModel
    def apply(self, model: mujoco.MjModel, robot: Robot, friction_timeconst: float) -> None:
        """Write the truth into ``model`` (a compiled copy of ``robot``'s model), in place.

        body_ipos += com_offset (both in the body frame); dof_frictionloss = friction / ratio
        (N m, ``friction_loss_torque``) with a stiff solver reference (``friction_timeconst``
        s) so that the Coulomb friction is delivered in full; dof_damping = viscous.
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
