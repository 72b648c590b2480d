"""The true robots of the calibration study: how they differ from the nominal model, drawn per
world from a seed.

Units: ratio A/(N m), friction loss A, friction torque N m, COM offsets m in each link's own
frame, current noise A, viscous friction N m s/rad.
"""

import dataclasses
import math

import numpy as np

from jaxcomp import checks
from jaxcomp.errors import InputError
from jaxcomp.hardware.mjx import BatchTruth
from jaxcomp.hardware.truth import friction_loss_torque, model_current_noise, truth_centre
from jaxcomp.identify.fit_model import fit_model
from jaxcomp.robot import Robot
from jaxcomp.robot_params import RobotParams

#: Seed stream of the truth draws: SeedSequence([seed, TRUTH_STREAM, quantity]).
TRUTH_STREAM = 1


@dataclasses.dataclass(frozen=True)
class TruthSpread:
    """How the true robots differ from the nominal model.

    Attributes:
        model_error: (lo, hi): each actuator type's current/torque ratio is off its nominal
            (Kinova's) by a factor 1 +- U(lo, hi), random sign; each joint's Coulomb friction
            torque off the model's (``hardware.truth.truth_centre``: the Gen3 Lite's are the
            paper's) by 1 +- U(lo, hi), the
            sign turned to - where + would leave less than ``headroom`` of the effort limit
            (the friction loss in A is then ratio x torque).
        type_spread: ratios of one actuator type differ by a further U(-s, s) (relative).
        com_offset: m, COM offsets U(-c, c) per axis of every moving link (link frame).
        noise: A, standard deviation of the current noise, every world; None: the model's
            (``hardware.truth.model_current_noise``: 0.05 A on the Gen3 Lite).
        viscous: N m s/rad, viscous friction U(0, v) per joint (0: none).
        headroom: fraction of each joint's effort limit left free of friction: the default
            plan lets gravity use 60 % of it, and a robot whose friction takes the rest cannot
            follow its sweeps (joint 1 of the paper's arm already spends 34 % on friction).
    """

    model_error: tuple[float, float] = (0.2, 0.3)
    type_spread: float = 0.03
    com_offset: float = 0.004
    noise: float | None = None
    viscous: float = 0.0
    headroom: float = 0.65

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.model_error)
        if not 0 <= lo <= hi < 1:
            raise InputError(f"--model-error must satisfy 0 <= LO <= HI < 1, got ({lo}, {hi})")
        for name in ("type_spread", "com_offset", "noise", "viscous", "headroom"):
            if getattr(self, name) is None:
                continue
            checks.number(getattr(self, name), f"--{name.replace('_', '-')}", nonneg=True)
        if self.type_spread >= 1 or self.headroom >= 1:
            raise InputError("type spread and headroom must be < 1")


def draw_truth(
    robot: Robot, worlds: int, seed: int, spread: TruthSpread, first: int = 0
) -> BatchTruth:
    """``BatchTruth`` of the ``worlds`` true robots ``first``, ..., ``first + worlds - 1`` drawn
    from ``seed`` (see ``TruthSpread``).

    Each quantity has its own stream and world w is row w of it, so world w is the same for
    any ``worlds`` > w, and a range of worlds is drawn without the ones before it (each
    stream advanced past their draws: one 64-bit PCG64 output per uniform double). Friction
    torques scale the model's (``truth_centre``). Payload 0, gravity the model's (upright).

    Args:
        robot: the nominal model.
        worlds: how many true robots.
        seed: the study's seed.
        spread: how they differ from ``robot``.
        first: the study world id of the first.

    Returns:
        The ``BatchTruth`` of the ``worlds`` robots (units as the module doc).
    """
    model = fit_model(robot)
    n, nb = model.n, len(robot.link_names)
    labels = model.types or tuple(f"joint {j}" for j in range(n))  # undeclared: each its own
    types = sorted(set(labels))
    type_of = np.array([types.index(t) for t in labels])

    def rng(k: int, shape: tuple[int, ...]) -> np.random.Generator:
        """Stream k, past the draws of the worlds before ``first`` (rows of ``shape``)."""
        bits = np.random.PCG64(np.random.SeedSequence([seed, TRUTH_STREAM, k]))
        return np.random.Generator(bits.advance(first * math.prod(shape[1:])))

    def uniform(k: int, low: float, high: float, shape: tuple[int, ...]) -> np.ndarray:
        return rng(k, shape).uniform(low, high, shape)

    def off(k: int, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:  # U(lo, hi), sign
        return uniform(k, *spread.model_error, shape), np.where(
            uniform(k + 1, 0.0, 1.0, shape) < 0.5, -1.0, 1.0
        )

    ratio0 = RobotParams.nominal(robot).ratio
    mag, sign = off(0, (worlds, len(types)))
    ratio = ratio0 * (1 + sign * mag)[:, type_of]
    ratio *= 1 + uniform(2, -1, 1, (worlds, n)) * spread.type_spread
    ratio_c, friction_c = truth_centre(robot)
    torque0 = friction_loss_torque(friction_c, ratio_c)  # N m
    mag, sign = off(3, (worlds, n))
    effort = np.abs(robot.model.jnt_actfrcrange).max(axis=1)[model.joints]  # N m
    sign = np.where(torque0 * (1 + mag) > (1 - spread.headroom) * effort, -1.0, sign)
    friction = ratio * torque0 * (1 + sign * mag)
    moved = np.zeros(nb, bool)
    moved[model.link_ids] = True
    com = uniform(5, -1, 1, (worlds, nb, 3)) * spread.com_offset * moved[None, :, None]
    viscous = uniform(6, 0, 1, (worlds, n)) * spread.viscous
    return BatchTruth.from_arrays(
        robot,
        ratio,
        friction,
        com_offset=com,
        current_noise=model_current_noise(robot) if spread.noise is None else spread.noise,
        viscous=viscous,
    )


def truth_rows(truth: BatchTruth, rows: slice | np.ndarray) -> BatchTruth:
    """The worlds ``rows`` of a ``BatchTruth``.

    Args:
        truth: W true robots.
        rows: a slice or (k,) world indices (repeats allowed).

    Returns:
        A ``BatchTruth`` of those worlds, in that order.
    """
    return type(truth)(**{f.name: getattr(truth, f.name)[rows] for f in dataclasses.fields(truth)})
