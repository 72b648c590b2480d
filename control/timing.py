"""Per-cycle timing of the control loop: compute time, exchange time, period, missed deadlines.

``CycleTimer`` keeps three ``time.perf_counter_ns`` stamps per cycle in preallocated arrays
(no allocation in the loop): when the cycle's command was sent (``arm.cycle`` called), when the
new state came back, and when the next command was ready. From them:

- compute: state received -> next command ready (controller, watchdog, base follower, logging);
- exchange: the ``arm.cycle`` call itself (in simulation: one physics step);
- cycle: compute + exchange; period: from one send to the next;
- missed deadline: the next command was ready after the cycle's deadline (real time: the
  absolute 1 kHz tick; lock step: one period after the send, i.e. the work would not have fit);
- speed: robot time per wall-clock second of the loop, and per CPU second of the loop's
  thread (the speed it would have on a core of its own, whatever else the machine runs).

``summary()`` gives median, p99, max (us) and histograms of each; ``dump(path)`` writes it as
JSON (``timing.json``).
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.robot_params import write_json_atomic

#: Histogram bin edges, us: 25 us wide up to 2 ms, then coarser up to 20 ms, then overflow.
HIST_EDGES_US = np.concatenate(
    [np.arange(0.0, 2000.0, 25.0), np.arange(2000.0, 20001.0, 1000.0), [np.inf]]
)


def _stats(x_us: np.ndarray) -> dict:
    """median, p99, max, mean, min (us) and a histogram of ``x_us``."""
    if x_us.size == 0:
        return {"count": 0}
    counts, _ = np.histogram(x_us, HIST_EDGES_US)
    nz = np.flatnonzero(counts)
    last = int(nz[-1]) + 1 if nz.size else 0
    return {
        "count": int(x_us.size),
        "median_us": float(np.median(x_us)),
        "p99_us": float(np.percentile(x_us, 99)),
        "max_us": float(x_us.max()),
        "mean_us": float(x_us.mean()),
        "min_us": float(x_us.min()),
        "histogram": {
            "edges_us": [float(e) if np.isfinite(e) else None for e in HIST_EDGES_US[: last + 1]],
            "counts": counts[:last].tolist(),
        },
    }


class CycleTimer:
    """Timing stamps of up to ``capacity`` cycles of period ``period`` s (see module doc).

    Args:
        period: s, the control period (deadline budget), ``CONTROL_PERIOD`` (1 kHz) by default.
        capacity: cycles to keep (grows by doubling when exceeded).
        realtime: whether deadlines are absolute wall-clock ticks (True) or one period after
            each send (lock step).
    """

    def __init__(
        self, period: float = CONTROL_PERIOD, capacity: int = 10_000, realtime: bool = False
    ):
        self.period = float(period)
        self.period_ns = int(round(self.period * 1e9))
        self.realtime = bool(realtime)
        self._sent = np.zeros(max(int(capacity), 1), np.int64)
        self._recv = np.zeros_like(self._sent)
        self._done = np.zeros_like(self._sent)
        self._deadline = np.zeros_like(self._sent)
        self.count = 0
        self._missed = 0
        self.start_ns = time.perf_counter_ns()
        self.end_ns: int | None = None
        self.sim_time = 0.0
        self._cpu0 = time.thread_time()
        self.cpu_s: float | None = None  # CPU time of the loop's thread, s

    def _grow(self) -> None:
        for name in ("_sent", "_recv", "_done", "_deadline"):
            old = getattr(self, name)
            new = np.zeros(2 * old.size, np.int64)
            new[: old.size] = old
            setattr(self, name, new)

    def record(self, sent_ns: int, recv_ns: int, done_ns: int, deadline_ns: int) -> bool:
        """Add one cycle.

        Args:
            sent_ns: When its command was sent, ns (``perf_counter_ns``).
            recv_ns: When the new state came back, ns.
            done_ns: When the next command was ready, ns.
            deadline_ns: The cycle's deadline, ns.

        Returns:
            Whether it missed its deadline (``done_ns > deadline_ns``).
        """
        k = self.count
        if k >= self._sent.size:
            self._grow()
        self._sent[k], self._recv[k], self._done[k] = sent_ns, recv_ns, done_ns
        self._deadline[k] = deadline_ns
        self.count = k + 1
        if done_ns > deadline_ns:
            self._missed += 1
            return True
        return False

    def finish(self, sim_time: float = 0.0) -> None:
        """Mark the end of the run.

        Args:
            sim_time: s of robot (simulation) time elapsed.
        """
        self.end_ns = time.perf_counter_ns()
        self.cpu_s = time.thread_time() - self._cpu0
        self.sim_time = float(sim_time)

    @property
    def missed(self) -> int:
        """Cycles whose next command was ready after their deadline."""
        return self._missed

    def sends(self, start: int, stop: int) -> np.ndarray:
        """The send stamps of some cycles (for monitors).

        Args:
            start: First cycle.
            stop: One past the last cycle (both clipped to those recorded).

        Returns:
            ns (``perf_counter_ns``), a read-only view.
        """
        view = self._sent[max(start, 0) : min(stop, self.count)]
        view.flags.writeable = False
        return view

    def summary(self) -> dict:
        """JSON-ready statistics (us; see module doc)."""
        n = self.count
        sent, recv, done = self._sent[:n], self._recv[:n], self._done[:n]
        compute = (done - recv) / 1e3
        exchange = (recv - sent) / 1e3
        period = np.diff(sent) / 1e3
        end = self.end_ns if self.end_ns is not None else time.perf_counter_ns()
        wall = (end - self.start_ns) / 1e9
        loop_wall = (int(done[-1]) - int(sent[0])) / 1e9 if n else 0.0
        missed = self.missed
        return {
            "mode": "realtime" if self.realtime else "lockstep",
            "period_s": self.period,
            "cycles": n,
            "wall_s": wall,
            "loop_wall_s": loop_wall,
            "sim_time_s": self.sim_time,
            "speed_x_realtime": (self.sim_time / loop_wall) if loop_wall > 0 else None,
            "cpu_s": self.cpu_s,
            # robot time per CPU second of the loop's thread: the speed on a core of its own
            "speed_x_realtime_cpu": (self.sim_time / self.cpu_s) if self.cpu_s else None,
            "missed_deadlines": missed,
            "missed_fraction": missed / n if n else 0.0,
            "compute": _stats(compute),
            "exchange": _stats(exchange),
            "cycle": _stats(compute + exchange),
            "period": _stats(period),
        }

    def dump(self, path: str | Path, extra: dict | None = None) -> Path:
        """Write ``summary()`` as JSON, atomically.

        Args:
            path: The file.
            extra: Keys to add.

        Returns:
            The path written.
        """
        data = self.summary()
        if extra:
            data.update(extra)
        return write_json_atomic(path, data)


def wait_until(deadline_ns: int, spin_ns: int = 200_000) -> None:
    """Block until ``time.perf_counter_ns() >= deadline_ns``: sleep until ``spin_ns`` before
    it, then spin (sleep alone overshoots by 50-100 us on a stock kernel).

    Args:
        deadline_ns: ns, ``perf_counter_ns`` clock.
        spin_ns: ns of spinning before it.
    """
    now = time.perf_counter_ns()
    rest = deadline_ns - now - spin_ns
    if rest > 0:
        time.sleep(rest / 1e9)
    while time.perf_counter_ns() < deadline_ns:
        pass


@contextlib.contextmanager
def realtime_priority(priority: int | None = 50):
    """Run the calling thread under ``SCHED_FIFO`` at ``priority`` (1-99) inside the block, if
    the OS allows it (Linux, root or CAP_SYS_NICE), restoring the old policy after; yields
    whether it was granted. ``None``: leave the scheduling alone (yields False). A 1 kHz loop
    on a shared machine misses deadlines when other processes preempt it for a time slice
    (several ms); the kernel's real-time throttling still leaves other tasks 5 % of the CPU.

    Args:
        priority: 1-99, or None.

    Yields:
        Whether real-time priority was granted.
    """
    if priority is None or not hasattr(os, "sched_setscheduler"):
        yield False
        return
    old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except (OSError, ValueError):
        yield False
        return
    try:
        yield True
    finally:
        os.sched_setscheduler(0, old_policy, old_param)


def configure_jax_for_control() -> None:
    """JAX settings for a 1 kHz loop of small jitted calls: run each call on the calling thread
    (no async hand-off) and, unless ``XLA_FLAGS`` is already set, single-threaded XLA kernels
    (no thread-pool hand-off inside a call; ~10-15 us less per controller step on a 2-core
    CPU). The flags only take effect if JAX has not run a computation yet in this process."""
    import jax

    jax.config.update("jax_cpu_enable_async_dispatch", False)
    os.environ.setdefault(
        "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    )


__all__ = [
    "HIST_EDGES_US",
    "CycleTimer",
    "configure_jax_for_control",
    "realtime_priority",
    "wait_until",
]
