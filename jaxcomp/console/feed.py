"""The console's frames: what the control thread hands the page, at most 30 times a second.

A frame is one float64 row (``FrameLayout``): a head (cycle, phase, missed deadlines, cycles,
the number of loop periods that follow), up to ``PERIODS`` loop periods (us) since the last
frame, then one sample in the order the control loop records it (t s | q rad | dq rad/s |
current A | command | target m | ee m | base (x m, y m, yaw rad) | current_model A | wrench N
| wrench_band N; world frame), NaN where the phase has none (no target when the arm holds).

``Feed`` writes them into a ``FrameRing``: as a ``control.run_link.LoopMonitor`` during a
control run (every 33rd cycle: 30 Hz at 1 kHz), and through ``state`` (at most every
``1 / RATE`` s of wall time) while the arm holds or calibrates. It only copies numbers: no
allocation beyond a few small arrays, no waiting.
"""

from __future__ import annotations

import time

import numpy as np

from jaxcomp.console.ring import FrameRing

#: Frames per second, at most.
RATE = 30.0
#: Loop periods a frame carries (33 expected at 30 Hz and 1 kHz).
PERIODS = 64
#: Phase codes of a frame.
PHASES = {"idle": 0.0, "guidance": 1.0, "tracking": 2.0, "calibrating": 3.0}
PHASE_NAMES = {v: k for k, v in PHASES.items()}


class FrameLayout:
    """Where each quantity lies in a frame of a robot with ``n`` arm joints (slices)."""

    HEAD = ("k", "phase", "missed", "cycles", "n_periods")

    def __init__(self, n: int):
        self.n = n
        widths = {name: 1 for name in self.HEAD} | {"periods": PERIODS}
        widths |= {"t": 1, "q": n, "dq": n, "current": n, "command": n}
        widths |= {"target": 3, "ee": 3, "base": 3, "current_model": n}
        widths |= {"wrench": 3, "wrench_band": 3}
        self.slices: dict[str, slice] = {}
        start = 0
        for name, w in widths.items():
            self.slices[name] = slice(start, start + w)
            start += w
        self.width = start
        self.row = self.slices["t"].start  # a control run's recorded row starts here

    def __getitem__(self, name: str) -> slice:
        return self.slices[name]

    def get(self, frame: np.ndarray, name: str):
        """The quantity ``name`` of ``frame`` (a float for one value, else an array view).

        Args:
            frame: (width,) one frame, or (..., width) frames.
            name: a quantity (``HEAD``, "periods", or a sample's column, e.g. "q"); units as
                the module doc.

        Returns:
            A float for a one-number quantity of one frame, else a (..., w) view.
        """
        part = frame[..., self.slices[name]]
        return float(part[0]) if part.shape[-1] == 1 and part.ndim == 1 else part


class Feed:
    """Writes frames into ``ring`` (see the module doc); a ``LoopMonitor`` of control runs."""

    every = 33  # cycles between samples: 30 Hz at 1 kHz

    def __init__(self, ring: FrameRing, n: int):
        self.ring, self.layout = ring, FrameLayout(n)
        if ring.width < self.layout.width:
            raise ValueError(
                f"the ring's frames hold {ring.width} numbers, not {self.layout.width}"
            )
        self._frame = np.full(self.layout.width, np.nan)
        self._timer = None
        self._phase = 0.0
        self._count = 0  # the timer's cycles at the last frame
        self._wall = 0.0

    # ---- LoopMonitor (control runs, on the loop's thread)
    def started(self, start) -> None:
        """A control run starts: its timer and phase are taken.

        Args:
            start: the run's ``control.run_link.MonitorStart``.
        """
        self._timer, self._count = start.timer, 0
        self._phase = PHASES.get(start.mode, 0.0)

    def sample(self, k: int, row: np.ndarray) -> None:
        """A frame of cycle ``k``: its head, the loop periods (us) since the last frame, and
        ``row``.

        Args:
            k: the cycle.
            row: the cycle's recorded row, in the order of the module doc (t s first).
        """
        f, lay, timer = self._frame, self.layout, self._timer
        count = timer.count
        periods = np.diff(timer.sends(self._count - 1, count))[-PERIODS:]
        self._count = count
        f[: lay.row] = np.nan
        f[0], f[1], f[2], f[3], f[4] = k, self._phase, timer.missed, count, len(periods)
        f[lay.slices["periods"].start : lay.slices["periods"].start + len(periods)] = periods * 1e-3
        stop = lay.row + len(row)
        f[lay.row : stop] = row
        f[stop:] = np.nan
        self.ring.write(f)

    def ended(self, result) -> None:
        """The control run ended: no more frames of it.

        Args:
            result: its ``ControlResult`` (unused).
        """
        self._timer = None

    # ---- anything else (holding, calibrating): decimated on the wall clock
    def state(self, phase: str, state, base_pose=None, force: bool = False) -> bool:
        """A frame of an ``ArmState`` (t, q, dq, current) and the base's pose (x, y, yaw;
        None: none) in ``phase`` ("idle", "calibrating"), unless one went out less than
        ``1 / RATE`` s ago (``force``: anyway); returns whether it was written.

        Args:
            phase: a key of ``PHASES``.
            state: the arm's ``ArmState`` (t s, q rad, dq rad/s, current A; (n,) each).
            base_pose: (3,) the base's (x m, y m, yaw rad) in the world frame; None: none.
            force: write even if a frame went out less than ``1 / RATE`` s ago.

        Returns:
            Whether the frame was written.
        """
        now = time.perf_counter()
        if not force and now - self._wall < 1.0 / RATE:
            return False
        self._wall = now
        f, lay = self._frame, self.layout
        f[:] = np.nan
        f[1], f[4] = PHASES[phase], 0.0
        f[lay.slices["t"]] = state.t
        f[lay.slices["q"]] = state.q
        f[lay.slices["dq"]] = state.dq
        f[lay.slices["current"]] = state.current
        if base_pose is not None:
            f[lay.slices["base"]] = base_pose
        self.ring.write(f)
        return True


__all__ = ["PERIODS", "PHASES", "PHASE_NAMES", "RATE", "Feed", "FrameLayout"]
