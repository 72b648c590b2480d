"""What a calibration study runs: its settings, checked when made, and how its worlds are laid
out over the plans (``world_groups``), the scipy sample (``baseline_worlds``) and the worlds
whose samples come to the host (``sampled_worlds``).

Worlds are global ids 0..N-1; a plan group is a contiguous ``range`` of them. Units: m for the
COM prior.
"""

import dataclasses
import math

import numpy as np

from jaxcomp.errors import InputError
from jaxcomp.identify.named_plans import check_plan_name, plan_count
from jaxcomp.studies.truth_draw import TruthSpread

#: m: the least COM prior of a study (its truths may have no COM offset at all).
MIN_COM_PRIOR = 1e-4


@dataclasses.dataclass(frozen=True)
class CalibrationSettings:
    """What a calibration study runs, checked when made (InputError).

    Attributes:
        worlds: simulated true robots N (>= 1). seed: seed of every draw.
        plan: "default" (the paper's ~230 s of sweeps), "short", "random" or "random:K" (K
            random plans, each recorded by a group of the worlds: ``run_study``) or a plan
            JSON file.
        every: record every k-th 1 kHz state (10: 100 Hz) for the fits.
        spread: how the true robots differ from the nominal model (``TruthSpread``).
        baseline_sample: also fit M worlds with the paper's scipy fit (0: none), the first
            of each plan's group (``baseline_worlds``).
        devices: shard over the first K devices (None: all).
        world_batch: worlds per MJX run (None: all on an accelerator, one per device on the
            CPU, where MJX steps a batch of worlds slower than one world at a time).
        fit_batch: fits per vmapped batch (None: all).
        poses: random poses of the gravity-current error (drawn from ``seed``).
        parallel: the plan's sweeps side by side (``simulate``; None: on an accelerator,
            where a few thousand worlds leave it idle; on the CPU, where steps cost in
            proportion to the worlds, the sweeps run in turn).
        com_prior: m, the JAX fit's COM prior on every link (None: the spread the truths are
            drawn from, ``study_com_prior``: the fit is told the population it is tested on;
            ``jaxcomp fit`` has the model's default, ``fit_model``).
        chunk_worlds: worlds per chunk (``study_chunks``; None: ``CHUNK_WORLDS_PER_DEVICE`` per
            device, the whole study when it has fewer; a resumed study keeps its own).
        keep_samples: the recorded samples of the first K worlds are saved (``run_study``).

    Raises:
        InputError: a count out of range, an unknown plan, or fewer worlds than plans.
    """

    worlds: int
    seed: int = 0
    plan: str = "default"
    every: int = 10
    spread: TruthSpread = TruthSpread()  # frozen: one shared default is safe
    baseline_sample: int = 16
    devices: int | None = None
    world_batch: int | None = None
    fit_batch: int | None = None
    poses: int = 1000
    parallel: bool | None = None
    com_prior: float | None = None
    chunk_worlds: int | None = None
    keep_samples: int = 0

    def __post_init__(self) -> None:
        check_plan_name(self.plan)
        checks = {
            "--worlds": (self.worlds, 1),
            "--every": (self.every, 1),
            "--baseline-sample": (self.baseline_sample, 0),
            "--poses": (self.poses, 1),
            "--world-batch": (self.world_batch, 1),
            "--fit-batch": (self.fit_batch, 1),
            "--chunk-worlds": (self.chunk_worlds, 1),
            "--keep-samples": (self.keep_samples, 0),
        }
        for name, (value, low) in checks.items():
            if value is not None and (
                isinstance(value, bool) or int(value) != value or value < low
            ):
                raise InputError(f"{name} must be an integer >= {low}, got {value}")
        if plan_count(self.plan) > self.worlds:
            raise InputError(
                f"--plan {self.plan} needs at least as many --worlds ({self.worlds}) as plans"
            )

    def fit_com_prior(self) -> float:
        """The JAX fit's COM prior of the study.

        Returns:
            m per axis: ``com_prior``, else ``study_com_prior(spread)``.
        """
        return self.com_prior or study_com_prior(self.spread)


def study_com_prior(spread: TruthSpread) -> float:
    """The COM prior that matches the truths' COM offsets.

    Args:
        spread: the truths' spread; its ``com_offset`` c (m) bounds U(-c, c) per axis.

    Returns:
        m: the standard deviation per axis of U(-c, c), c / sqrt(3), at least
        ``MIN_COM_PRIOR``.
    """
    return max(float(spread.com_offset) / math.sqrt(3.0), MIN_COM_PRIOR)


def world_groups(worlds: int, count: int) -> list[range]:
    """The worlds cut into contiguous plan groups, as even as possible.

    Args:
        worlds: the study's worlds N (ids 0..N-1).
        count: the groups (plans), 1..N.

    Returns:
        ``count`` contiguous ranges covering 0..N-1 in order, the first ``worlds % count``
        one world longer.
    """
    size, extra = divmod(worlds, count)
    edges = np.cumsum([0] + [size + (g < extra) for g in range(count)])
    return [range(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def baseline_worlds(groups: list[range], sample: int) -> np.ndarray:
    """The worlds of the scipy sample, spread over the plans so that every plan is in it.

    Args:
        groups: the plans' contiguous world groups (``world_groups``).
        sample: the sample's size M (at most all worlds are taken).

    Returns:
        (min(M, N),) int64 world ids, ascending: M cut over the groups as ``world_groups``
        cuts the worlds, the first ones of each group.
    """
    shares = world_groups(min(sample, groups[-1].stop), len(groups))
    return np.concatenate(
        [
            np.arange(rows.start, rows.start + len(share))
            for rows, share in zip(groups, shares, strict=True)
        ]
    ).astype(np.int64)


def sampled_worlds(groups: list[range], sample: np.ndarray, keep_samples: int) -> np.ndarray:
    """The worlds whose samples come to the host: the scipy sample and the kept recordings.

    Args:
        groups: the plans' contiguous world groups (``world_groups``).
        sample: (M,) int world ids of the scipy sample (``baseline_worlds``).
        keep_samples: the first K worlds whose recordings are saved.

    Returns:
        (S,) int64 world ids, ascending: ``sample`` and the first ``keep_samples`` worlds. In
        each group they are its first worlds (a prefix), as ``simulate(keep=)`` takes them.
    """
    first = np.arange(min(keep_samples, groups[-1].stop))
    return np.union1d(sample, first).astype(np.int64)
