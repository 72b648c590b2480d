"""How a control run ended and what it measured (``ControlResult``, ``run_control``'s return)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from jaxcomp.recording import Recording


@dataclass
class ControlResult:
    """How a run ended and what it measured.

    Attributes:
        kind: "completed", "stopped" (``RunLink.stop``), "interrupted" (Ctrl-C), a watchdog
            trip kind
            (``control.watchdog``; "not_tracking": the end effector stayed off its target),
            "hardware_fault" (a simulator's instability too), "command_refused" or "error".
        reason: one readable line.
        cycles: ``arm.cycle`` calls made (the last may be the one that tripped).
        duration: s of robot time controlled (to the last state received).
        rms_error: m, RMS of |ee - target| over the run (world frame). final_error: m, the
            last sample's. max_error: m.
        recording: the joined ``Recording`` (None if nothing was recorded).
        out_dir, recording_path, timing_path: where the files are.
        timing: ``CycleTimer.summary()``.
        stop_errors: problems met while stopping (empty when the stop was clean).
        file_error: why the recording or timing.json could not be written (read-only, full
            disk), None when they were.
        trajectory: the trajectory's description. mode: "guidance" or "tracking".
    """

    kind: str
    reason: str
    cycles: int = 0
    duration: float = 0.0
    rms_error: float = math.nan
    final_error: float = math.nan
    max_error: float = math.nan
    recording: Recording | None = None
    out_dir: Path | None = None
    recording_path: Path | None = None
    timing_path: Path | None = None
    timing: dict = field(default_factory=dict)
    stop_errors: list[str] = field(default_factory=list)
    file_error: str | None = None
    trajectory: str = ""
    mode: str = ""

    @property
    def ok(self) -> bool:
        """True when the run completed, or was stopped or interrupted by the user (no
        fault)."""
        return self.kind in ("completed", "stopped", "interrupted")

    def summary(self) -> str:
        """A few readable lines: how it ended, tracking error, timing."""
        tm = self.timing
        lines = [
            f"{self.mode} mode, {self.trajectory}",
            f"ended: {self.kind} ({self.reason})",
            f"duration {self.duration:.3f} s, {self.cycles} cycles",
            f"tracking error |ee - target|: RMS {1e3 * self.rms_error:.2f} mm, "
            f"max {1e3 * self.max_error:.2f} mm, final {1e3 * self.final_error:.2f} mm",
        ]
        if tm.get("cycles"):
            lines.append(_timing_line(tm))
        if self.recording_path is not None:
            lines.append(f"recording: {self.recording_path}")
        if self.timing_path is not None:
            lines.append(f"timing: {self.timing_path}")
        lines += [f"stop problem: {e}" for e in self.stop_errors]
        return "\n".join(lines)

    def run_info(self) -> dict:
        """The run's part of timing.json: mode, trajectory, how it ended, cycles, duration s,
        RMS and max tracking error m (None when nothing was measured)."""
        return {
            "run": {
                "mode": self.mode,
                "trajectory": self.trajectory,
                "kind": self.kind,
                "reason": self.reason,
                "cycles": self.cycles,
                "duration_s": self.duration,
                "rms_error_m": None if math.isnan(self.rms_error) else self.rms_error,
                "max_error_m": None if math.isnan(self.max_error) else self.max_error,
            }
        }


def _timing_line(tm: dict) -> str:
    """The summary's line of a ``CycleTimer.summary()``: compute, period, missed deadlines."""
    c, p = tm["compute"], tm["period"]
    speed, cpu = tm.get("speed_x_realtime"), tm.get("speed_x_realtime_cpu")
    return (
        f"timing ({tm['mode']}): compute median {c['median_us']:.0f} us, p99 "
        f"{c['p99_us']:.0f} us, max {c['max_us']:.0f} us; period median "
        f"{p.get('median_us', math.nan):.0f} us, p99 {p.get('p99_us', math.nan):.0f} us,"
        f" max {p.get('max_us', math.nan):.0f} us; missed deadlines "
        f"{tm['missed_deadlines']} ({100 * tm['missed_fraction']:.2f} %)"
        + (f"; {speed:.1f}x real time" if speed else "")
        + (f" ({cpu:.1f}x per CPU second)" if speed and cpu else "")
    )


__all__ = ["ControlResult"]
