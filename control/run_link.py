"""What connects a running 1 kHz loop to an operator outside its thread (e.g. the browser
console): a stop request, live gains, and a monitor fed with a few samples a second.

Everything here is read by the loop's thread once per cycle and written by other threads;
each exchange is one attribute read or one reference swap, so the loop never waits (no
locks): a request set between two reads is seen one cycle later.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np

if TYPE_CHECKING:
    from jaxcomp.control.timing import CycleTimer


class Tuning:
    """Live gains for a running impedance loop (``impedance_io.live_gains``: K_d N/m, D_d N s/m,
    friction compensation 1/0), set from any thread; the loop takes them up at its next cycle
    and then sets ``applied`` to their ``version``. The caller validates them
    (``presets.check_live_gains``)."""

    def __init__(self, live=None):
        self.values: np.ndarray | None = None
        self.version = 0
        self.applied = 0
        if live is not None:
            self.set(live)

    def set(self, live) -> None:
        """Set new live gains: a new array, so the loop never reads a half-written one.

        Args:
            live: (``impedance_io.LIVE_SIZE``,) K_d N/m | D_d N s/m | compensation 1/0.
        """
        self.values = np.array(live, dtype=float)
        self.version += 1


class MonitorStart(NamedTuple):
    """What a monitor learns when a run starts: ``mode`` ("guidance", "tracking"),
    ``trajectory`` (its description), ``columns`` (name -> slice of a sample row: t s, q rad,
    dq rad/s, current A, command, target, ee m (world), base (x m, y m, yaw rad)
    [, current_model A, wrench N, wrench_band N (world)]), ``timer`` (the run's
    ``CycleTimer``, its stamps read-only), ``duration`` s."""

    mode: str
    trajectory: str
    columns: dict[str, slice]
    timer: CycleTimer
    duration: float


class LoopMonitor(Protocol):
    """Watches a run from outside (runs on the loop's thread: copy and return, tens of us at
    most). ``every``: cycles between two ``sample`` calls (33: 30 Hz at 1 kHz)."""

    every: int

    def started(self, start: MonitorStart) -> None:
        """The run is set up and about to switch the arm.

        Args:
            start: The run's mode, trajectory, row layout, timer and duration.
        """

    def sample(self, k: int, row: np.ndarray) -> None:
        """Cycle ``k``'s recorded row.

        Args:
            k: The cycle.
            row: The recorded row, laid out as ``MonitorStart.columns`` (a view: copy what
                is kept).
        """

    def ended(self, result: Any) -> None:
        """The run ended; the arm is in POSITION mode.

        Args:
            result: The run's ``ControlResult``.
        """


@dataclass
class RunLink:
    """The optional links of one run (``run_control(link=...)``).

    Attributes:
        stop: set it to end the run at its next cycle, kind "stopped" (safe stop: arm in
            POSITION mode, base stopped).
        tuning: live gains (impedance controller only).
        monitor: fed every ``monitor.every`` cycles with the recorded row.
    """

    stop: threading.Event = field(default_factory=threading.Event)
    tuning: Tuning | None = None
    monitor: LoopMonitor | None = None


__all__ = ["LoopMonitor", "MonitorStart", "RunLink", "Tuning"]
