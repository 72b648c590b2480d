"""The recording of a control run: one row per cycle, written a block at a time.

Each cycle the loop adds one row of t | q | dq | current | command | target | ee | base
[| current_model | wrench | wrench_band] (``Recorder.add``, into a preallocated block); each full
block of 1000 rows goes to the ``RecordingWriter`` (``append_block``: one part file) on a
writer thread in real time (the loop never waits for the disk), inline in lock step.
``Recorder.close`` joins the parts into ``out_dir/recording.npz``.

Fields: t s, q rad, dq rad/s, current A, ``command`` (n,) A (rad/s for the velocity
controller), ``target`` (3,) world m, ``ee`` (3,) world m, ``base`` (3,) x m, y m, yaw rad, and
with the impedance controller ``current_model`` (n,) A, ``wrench`` (3,) N and ``wrench_band``
(3,) N (world frame); joint -1, direction 0 (no sweep).
"""

from __future__ import annotations

import queue
import threading
from pathlib import Path

import numpy as np

from jaxcomp.recording import Recording, RecordingWriter

#: The run's recording, in its output folder.
RECORDING = "recording.npz"
#: The run's timing (``timing.CycleTimer.dump``), in its output folder.
TIMING = "timing.json"
#: Samples per block (and per part file).
BLOCK = 1000
#: The fields every run records besides the command: shapes per sample.
FRAME_FIELDS = {"target": (3,), "ee": (3,), "base": (3,)}


class Recorder:
    """Per-sample rows into preallocated blocks of ``block`` samples, each full block handed to
    the writer (see the module doc).

    Args:
        writer: the run's ``RecordingWriter`` (fed with ``append_block``).
        n: joints.
        block: samples per block.
        threaded: hand the blocks to a writer thread (real time), else write them inline.
        estimate: rows carry current_model | wrench | wrench_band (the impedance controller).

    Attributes:
        columns: {field: slice of a row}. width: a row's length. last_row: the row written
            last (a view; the monitor's sample).
    """

    def __init__(self, writer: RecordingWriter, n: int, block: int, threaded: bool, estimate: bool):
        self.writer, self.n, self.block = writer, n, block
        widths = {"t": 1, "q": n, "dq": n, "current": n, "command": n}
        widths |= {"target": 3, "ee": 3, "base": 3}
        if estimate:
            widths |= {"current_model": n, "wrench": 3, "wrench_band": 3}
        stops = np.cumsum(list(widths.values()))
        self.columns = {
            name: slice(int(stop - w), int(stop))
            for (name, w), stop in zip(widths.items(), stops, strict=True)
        }
        self._cols = dict(self.columns, t=0)
        self.width = int(stops[-1])
        self._new()
        self.last_row = self.rows[0]
        self._error: BaseException | None = None
        self._queue: queue.Queue | None = None
        self._thread = None
        if threaded:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._run, name="jaxcomp-recorder", daemon=True)
            self._thread.start()

    def _new(self) -> None:
        self.rows = np.empty((self.block, self.width))
        self.i = 0

    def add(self, t, q, dq, current, command, frames, current_model=None) -> None:
        """One sample.

        Args:
            t: s.
            q: (n,) rad.
            dq: (n,) rad/s.
            current: (n,) A.
            command: (n,) A or rad/s.
            frames: 9 floats target (world m) | ee (world m) | base pose (x m, y m, yaw rad)
                [| wrench (3) world N | band (3) world N].
            current_model: (n,) A, the model's current, when estimating.
        """
        n = self.n
        row = self.rows[self.i]
        row[0] = t
        row[1 : 1 + n] = q
        row[1 + n : 1 + 2 * n] = dq
        row[1 + 2 * n : 1 + 3 * n] = current
        row[1 + 3 * n : 1 + 4 * n] = command
        if current_model is None:
            row[1 + 4 * n :] = frames
        else:
            row[1 + 4 * n : 10 + 4 * n] = frames[:9]
            row[10 + 4 * n : 10 + 5 * n] = current_model
            row[10 + 5 * n :] = frames[9:]
        self.last_row = row
        self.i += 1
        if self.i == self.block:
            self._emit()

    def _emit(self) -> None:
        if self.i == 0:
            return
        rows = self.rows[: self.i]
        self._new()
        if self._queue is not None:
            self._queue.put(rows)
        else:
            self.write_rows(rows)

    def write_rows(self, rows: np.ndarray) -> None:
        """Hand a block to the writer.

        Args:
            rows: (k, width) samples, one per row (``columns``).
        """
        self.writer.append_block(**{name: rows[:, col] for name, col in self._cols.items()})

    def _run(self) -> None:
        while True:
            rows = self._queue.get()
            if rows is None:
                return
            try:
                self.write_rows(rows)
            except BaseException as exc:  # noqa: BLE001 - reported by close()
                self._error = exc
                return

    def close(self) -> Recording:
        """Write what is left, wait for the writer thread, join the parts.

        Returns:
            The joined ``Recording``.

        Raises:
            Whatever the writer raised (``FileError``, ``OSError``, too few samples).
        """
        self._emit()
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
        if self._error is not None:
            raise self._error
        return self.writer.close()


def open_recorder(
    out: Path, model: str, joint_names: tuple[str, ...], threaded: bool, estimate: bool
) -> Recorder:
    """The recorder of a run into ``out`` (created).

    Args:
        out: the run's output folder; the recording goes to ``out / RECORDING``.
        model: the recording's ``model`` field.
        joint_names: the arm's joints (the recording's ``joints``).
        threaded: write on a thread of its own (real time).
        estimate: record the impedance controller's force estimate too.

    Returns:
        The ``Recorder``.
    """
    n = len(joint_names)
    out.mkdir(parents=True, exist_ok=True)
    extra = {**FRAME_FIELDS, "command": (n,)}
    if estimate:
        extra |= {"current_model": (n,), "wrench": (3,), "wrench_band": (3,)}
    writer = RecordingWriter(
        out / RECORDING,
        model,
        n,
        extra=extra,
        joints=joint_names,
        flush_every=BLOCK,
        require_sweep=False,
    )
    return Recorder(writer, n, BLOCK, threaded, estimate)


__all__ = [
    "BLOCK",
    "FRAME_FIELDS",
    "RECORDING",
    "TIMING",
    "Recorder",
    "open_recorder",
]
