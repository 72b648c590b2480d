"""The hidden true robot of every MJX world: ``BatchTruth`` and its inertial parameters.

``BatchTruth`` is W ``TrueRobot``s side by side (ratio, friction loss, COM offsets, viscous
friction, current noise) plus two things the CPU simulator lacks: a point payload at the
end-effector site and the gravity vector of the mounting. ``BatchTruth.draw`` draws them as
``TrueRobot.draw`` does, relative to the model's own figures (``jaxcomp.hardware.truth``).
``true_inertial_params`` gives each world's inertial parameters (the nominal model with the
truth's COM offsets and payload).
Units: A/(N m), A, m, N m s/rad, kg, m/s^2.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx.model import end_effector_point
from jaxcomp.hardware.truth import DEFAULT_COM_OFFSET, TrueRobot, model_current_noise
from jaxcomp.params import InertialParams, add_point_mass
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices, arm_joint_names

#: What ``BatchTruth.from_arrays`` broadcasts to a per-joint, per-link or per-world array: a
#: number or anything ``np.asarray`` makes a float array of.
ArrayLike = float | Sequence[float] | np.ndarray


@dataclass(frozen=True)
class BatchTruth:
    """The hidden true robot of every world (W worlds, n arm joints, nb links).

    Attributes:
        ratio: (W, n) A/(N m), current per joint torque.
        friction: (W, n) A, Coulomb friction loss as current (as torque: friction / ratio, N m).
        com_offset: (W, nb, 3) m, added to each link's COM in the link's own frame; rows in
            ``robot.link_names`` order.
        current_noise: (W,) A, standard deviation of the measured current's noise.
        viscous: (W, n) N m s/rad, viscous friction.
        payload: (W,) kg, point mass at the end-effector site (needs ``payload=True`` sims).
        gravity: (W, 3) m/s^2, gravity in the robot's base (world) frame: the mounting.
    """

    ratio: np.ndarray
    friction: np.ndarray
    com_offset: np.ndarray
    current_noise: np.ndarray
    viscous: np.ndarray
    payload: np.ndarray
    gravity: np.ndarray

    def __post_init__(self) -> None:
        w, n = np.shape(self.ratio)[:2] if np.ndim(self.ratio) == 2 else (-1, -1)
        if w < 1 or n < 1:
            raise InputError(f"ratio must have shape (W, n), got {np.shape(self.ratio)}")
        want = {  # shape, unit, sign
            "ratio": ((w, n), "A/(N m)", "> 0"),
            "friction": ((w, n), "A", ">= 0"),
            "current_noise": ((w,), "A", ">= 0"),
            "viscous": ((w, n), "N m s/rad", ">= 0"),
            "payload": ((w,), "kg", ">= 0"),
            "gravity": ((w, 3), "m/s^2", ""),
            "com_offset": ((w, None, 3), "m", ""),
        }
        for name, (shape, unit, sign) in want.items():
            arr = checks.array(
                getattr(self, name),
                name,
                shape=shape,
                unit=unit,
                positive=sign == "> 0",
                nonneg=sign == ">= 0",
            )
            object.__setattr__(self, name, arr)

    @property
    def worlds(self) -> int:
        return self.ratio.shape[0]

    @classmethod
    def from_arrays(
        cls,
        robot: Robot,
        ratio: ArrayLike,
        friction: ArrayLike,
        *,
        com_offset: ArrayLike | None = None,
        current_noise: ArrayLike | None = None,
        viscous: ArrayLike | None = None,
        payload: ArrayLike = 0.0,
        gravity: ArrayLike | None = None,
        worlds: int | None = None,
    ) -> BatchTruth:
        """Broadcast per-joint (n,) or per-world (W, n) figures to a ``BatchTruth``; scalars
        broadcast to every world, W is the leading axis of any per-world argument.

        Args:
            robot: the nominal model.
            ratio: (n,) or (W, n) A/(N m). friction: (n,) or (W, n) A.
            com_offset: (nb, 3) or (W, nb, 3) m, link frames (default 0).
            current_noise: A, or (W,) (default the model's, ``model_current_noise``).
            viscous: (n,) or (W, n) N m s/rad (default 0). payload: kg, or (W,).
            gravity: (3,) or (W, 3) m/s^2, base frame (default the model's).
            worlds: W when no argument has a world axis (default 1).

        Returns:
            The ``BatchTruth``.

        Raises:
            InputError: an argument that does not broadcast, or as ``BatchTruth`` refuses.
        """
        if current_noise is None:
            current_noise = model_current_noise(robot)
        n, nb = len(arm_joint_indices(robot)), len(robot.link_names)
        # W: the leading axis of any per-world argument (else ``worlds``, else 1)
        per_world = [(ratio, 2), (friction, 2), (viscous, 2), (com_offset, 3), (gravity, 2)]
        per_world += [(payload, 1), (current_noise, 1)]
        sizes = [np.shape(v)[0] for v, nd in per_world if v is not None and np.ndim(v) == nd]
        w = worlds or max(sizes + [1])

        def bcast(val: ArrayLike, shape: tuple[int, ...], name: str) -> np.ndarray:
            try:
                return np.broadcast_to(np.asarray(val, dtype=float), shape).copy()
            except ValueError:
                raise InputError(f"{name} of shape {np.shape(val)} does not fit {shape}") from None

        g = robot.model.opt.gravity if gravity is None else gravity
        return cls(
            ratio=bcast(ratio, (w, n), "ratio"),
            friction=bcast(friction, (w, n), "friction"),
            com_offset=bcast(0.0 if com_offset is None else com_offset, (w, nb, 3), "com_offset"),
            current_noise=bcast(current_noise, (w,), "current_noise"),
            viscous=bcast(0.0 if viscous is None else viscous, (w, n), "viscous"),
            payload=bcast(payload, (w,), "payload"),
            gravity=bcast(g, (w, 3), "gravity"),
        )

    @classmethod
    def draw(
        cls,
        robot: Robot,
        seeds: Sequence[int],
        *,
        com_offset: float = DEFAULT_COM_OFFSET,
        current_noise: float | None = None,
        viscous: np.ndarray | None = None,
        payload: ArrayLike = 0.0,
        gravity: ArrayLike | None = None,
    ) -> BatchTruth:
        """One world per seed: world w is ``TrueRobot.draw(robot, seeds[w], com_offset,
        current_noise, viscous)`` (the model's stated truth, else ratios and friction losses
        drawn around its own figures).

        Args:
            robot: the nominal model. seeds: W seeds.
            com_offset: m, the COM offsets' bound per axis. current_noise: A (None: the model's).
            viscous: (n,) N m s/rad, or None. payload: kg, or (W,).
            gravity: (3,) or (W, 3) m/s^2, base frame (default the model's).

        Returns:
            The ``BatchTruth`` of W = len(seeds) worlds.
        """
        truths = [TrueRobot.draw(robot, int(s), com_offset, current_noise, viscous) for s in seeds]
        return cls.from_truths(robot, truths, payload=payload, gravity=gravity)

    @classmethod
    def from_truths(
        cls,
        robot: Robot,
        truths: Sequence[TrueRobot],
        *,
        payload: ArrayLike = 0.0,
        gravity: ArrayLike | None = None,
    ) -> BatchTruth:
        """One world per ``TrueRobot`` (as the CPU ``Simulator`` would use it).

        Args:
            robot: the nominal model. truths: W ``TrueRobot``s of it.
            payload: kg, or (W,). gravity: (3,) or (W, 3) m/s^2, base frame (default the model's).

        Returns:
            The ``BatchTruth`` of W = len(truths) worlds.

        Raises:
            InputError: no truth, a truth that does not fit ``robot``, or as ``from_arrays``.
        """
        if not truths:
            raise InputError("truths is empty: give one TrueRobot per world")
        links = list(robot.link_names)
        off = np.zeros((len(truths), len(links), 3))
        for w, t in enumerate(truths):
            t.params.check(robot)
            for link, d in t.params.com_offset.items():
                off[w, robot.link_index(link)] = d
        n = len(arm_joint_indices(robot))
        return cls.from_arrays(
            robot,
            np.stack([t.ratio for t in truths]),
            np.stack([t.friction for t in truths]),
            com_offset=off,
            current_noise=np.array([t.current_noise for t in truths]),
            viscous=np.stack([np.zeros(n) if t.viscous is None else t.viscous for t in truths]),
            payload=payload,
            gravity=gravity,
        )

    def true_robot(self, robot: Robot, w: int) -> TrueRobot:
        """World ``w`` as a ``TrueRobot`` for the CPU ``Simulator`` (payload, gravity dropped).

        Args:
            robot: the nominal model. w: the world's index.

        Returns:
            The ``TrueRobot``; its viscous friction is None where the world has none.
        """
        offsets = {
            name: self.com_offset[w, i]
            for i, name in enumerate(robot.link_names)
            if np.any(self.com_offset[w, i])
        }
        params = RobotParams(
            robot.name,
            self.ratio[w],
            self.friction[w],
            offsets,
            method="truth",
            joints=arm_joint_names(robot),
        )
        viscous = self.viscous[w] if np.any(self.viscous[w]) else None
        return TrueRobot(params, float(self.current_noise[w]), viscous)


def true_inertial_params(robot: Robot, truth: BatchTruth) -> InertialParams:
    """Per-world inertial params: nominal + COM offsets, payload folded into the end-effector
    body (``jaxcomp.params.add_point_mass``).

    Args:
        robot: the nominal model. truth: the worlds' truth.

    Returns:
        ``InertialParams`` with a leading world axis: mass (W, nb) kg, COM (W, nb, 3) m and
        inertia (W, nb, 3, 3) kg m^2 about the COM, link frames.
    """
    p = robot.nominal_params()
    w = truth.worlds
    mass = np.broadcast_to(np.asarray(p.mass), (w,) + np.shape(p.mass))
    com = np.asarray(p.com)[None] + truth.com_offset
    inertia = np.broadcast_to(np.asarray(p.inertia), (w,) + np.shape(p.inertia))
    params = InertialParams(jnp.asarray(mass), jnp.asarray(com), jnp.asarray(inertia))
    if truth.payload.any():
        body, point = end_effector_point(robot)
        fold = jax.vmap(add_point_mass, in_axes=(0, None, 0, None))
        params = fold(params, robot.link_index(body), jnp.asarray(truth.payload), point)
    return params
