"""The joint fit's model of a robot: its current-controlled joints, the moving links whose
centre-of-mass offsets are fitted, the nominal ratios, the actuator types and the COM prior.

The fit (``identify.joint_fit``, ``identify.batched_fit``) takes a ``FitModel`` as the static
argument of its jitted functions. Compiled code is shared by equal models: a ``FitModel``
compares equal by the content of the robot's compiled model (not its name or file), so an
edited model never reuses stale code.

The COM prior of each link (a Gaussian toward the nominal model, m per axis): the model's
``jaxcomp_com_prior``, else ``PRIOR_COM_FRACTION`` of the link's radius of gyration, at least
``PRIOR_COM_MIN``; ``fit_model(robot, com_prior=...)`` sets one for every link.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError
from jaxcomp.params import gyration_radii
from jaxcomp.robot import Robot, load_robot
from jaxcomp.robot_params import RobotParams, arm_joint_indices

#: Default prior standard deviation of each COM offset component, as a fraction of the link's
#: radius of gyration about its COM (its size as the mass sees it), m/m; at least ``PRIOR_COM_MIN``.
PRIOR_COM_FRACTION = 0.1
#: Smallest default COM prior, m.
PRIOR_COM_MIN = 0.002
#: Parameters per joint, in this order: ratio, friction, viscous (the K COM offsets follow the
#: n joints' 3 n).
JOINT_PARAMS = 3


@dataclass(frozen=True, eq=False)
class FitModel:
    """What a fit needs of the robot: its current-controlled joints, the moving links whose
    COM offsets are fitted, the nominal ratios, the actuator types and the COM prior.

    Made once per robot and kept on it (``fit_model``). It is the static argument of the
    jitted fit functions; two ``FitModel`` compare equal (and hash alike) when their robots'
    compiled models have the same content and they fit the same joints and links with the same
    prior, so equal models share compiled code and an edited model gets its own.

    Attributes:
        robot: the robot model.
        joints: (n,) indices of the current-controlled joints among the robot's joints.
        links: names of the L links whose COM offset is fitted (K = 3 L components).
        link_ids: (L,) their indices among the robot's links.
        ratio0: (n,) A/(N m), the nominal current/torque ratios (only their proportions
            matter: the fit scales them to the data).
        types: the actuator type of each joint when the model declares them, else None.
        com_prior: (L,) m, prior standard deviation of each link's COM offset per axis.
    """

    robot: Robot
    joints: np.ndarray
    links: tuple[str, ...]
    link_ids: np.ndarray
    ratio0: np.ndarray
    types: tuple[str, ...] | None
    com_prior: np.ndarray

    @cached_property
    def identity(self) -> tuple:
        """What makes two models equal: the robot's model digest, the joints, the links and
        their indices, the nominal ratios, the actuator types and the COM prior (hashable;
        its repr names the model's traced programs on disk)."""
        return (
            self.robot.digest,
            tuple(int(j) for j in self.joints),
            self.links,
            tuple(int(i) for i in self.link_ids),
            tuple(float(r) for r in self.ratio0),
            self.types,
            tuple(float(c) for c in self.com_prior),
        )

    def __eq__(self, other: object) -> bool:
        return isinstance(other, FitModel) and self.identity == other.identity

    def __hash__(self) -> int:
        return hash(self.identity)

    @property
    def n(self) -> int:
        """The number of current-controlled joints."""
        return len(self.joints)

    @property
    def K(self) -> int:
        """The number of fitted COM offset components, 3 per link."""
        return 3 * len(self.links)

    @property
    def key(self) -> tuple:
        """The static description of the model that ``fit_solver.solve`` takes: (n, K, the
        nominal ratios (n,) A/(N m), the actuator types or None, the COM prior (L,) m)."""
        return (
            self.n,
            self.K,
            tuple(float(r) for r in self.ratio0),
            self.types,
            tuple(float(c) for c in self.com_prior),
        )

    def parameter_names(self) -> list[str]:
        """The names of the P = 3 n + K fitted parameters, in the solver's order: ratio[j],
        friction[j], viscous[j], then com_offset[link].x, .y, .z."""
        names = [f"ratio[{j}]" for j in range(self.n)]
        names += [f"friction[{j}]" for j in range(self.n)]
        names += [f"viscous[{j}]" for j in range(self.n)]
        names += [f"com_offset[{link}].{ax}" for link in self.links for ax in "xyz"]
        return names

    def with_com_prior(self, length: float | None) -> FitModel:
        """This model with another COM prior.

        Args:
            length: m, the COM prior on every link per axis (None: this model unchanged).

        Returns:
            The ``FitModel`` with that prior.

        Raises:
            InputError: ``length`` is not a finite length > 0.
        """
        if length is None:
            return self
        length = checks.number(length, "the COM prior", positive=True, unit="m")
        return dataclasses.replace(self, com_prior=np.full(len(self.links), length))


def fit_model(robot: Robot | str, com_prior: float | None = None) -> FitModel:
    """The ``FitModel`` of a robot, made once and kept on the robot.

    Args:
        robot: a robot name, model path or ``Robot``.
        com_prior: m, the COM prior on every link per axis (None: the model's,
            ``default_com_prior``).

    Returns:
        The robot's ``FitModel``.

    Raises:
        InputError: a COM prior that is not a length > 0, or actuator types that do not match
            the joints.
    """
    robot = load_robot(robot)
    model = robot.cached(("fit_model.FitModel",), lambda: _build_model(robot))
    return model.with_com_prior(com_prior)


def default_com_prior(robot: Robot, link_ids: np.ndarray) -> np.ndarray:
    """The default COM prior of each link.

    The model's ``jaxcomp_com_prior`` (m, one value) when it declares one, else
    ``PRIOR_COM_FRACTION`` of the link's radius of gyration about its COM,
    sqrt(trace(I) / 2 m), and at least ``PRIOR_COM_MIN``.

    Args:
        robot: the robot model.
        link_ids: (L,) indices of the links among the robot's links.

    Returns:
        (L,) m, the prior standard deviation of each link's COM offset per axis.
    """
    declared = robot.custom_numeric("jaxcomp_com_prior")
    if declared is not None:
        first = np.asarray(declared).ravel()[0]
        value = checks.number(first, f"{robot.name}: jaxcomp_com_prior", positive=True, unit="m")
        return np.full(len(link_ids), value)
    gyration = gyration_radii(robot.nominal_params())[link_ids]
    return np.maximum(PRIOR_COM_FRACTION * gyration, PRIOR_COM_MIN)


def _build_model(robot: Robot) -> FitModel:
    """The robot's ``FitModel``: its arm joints, the links they move that have mass."""
    joints = arm_joint_indices(robot)
    tree = robot.tree
    moved = np.asarray(tree.moves)[joints].any(axis=0)
    mass = np.asarray(robot.nominal_params().mass)
    ids = np.flatnonzero(moved & (mass > 0))
    types = robot.actuator_types
    if types is not None and len(types) != len(joints):
        raise InputError(
            f"{robot.name}: jaxcomp_actuator_types lists {len(types)} types for "
            f"{len(joints)} joints"
        )
    return FitModel(
        robot=robot,
        joints=joints,
        links=tuple(tree.body_names[i] for i in ids),
        link_ids=ids,
        ratio0=RobotParams.nominal(robot).ratio,
        types=None if types is None else tuple(types),
        com_prior=default_com_prior(robot, ids),
    )
