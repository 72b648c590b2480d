"""A ring buffer of numeric frames shared by two processes: the control loop writes, the page's
server reads, and neither ever waits for the other.

The ring lives in a file both processes map (``/dev/shm`` where there is one): a header
(frames written so far, width, slots) and ``slots`` slots, each a sequence number and one frame
of ``width`` float64. The writer stamps a slot odd while it writes and even when done (a
sequence lock); the reader copies the frames written since it last looked and keeps those
whose stamp was even and unchanged around the copy. A reader slower than the writer loses the
oldest frames (overwritten before it got to them): ``read`` counts them as dropped. A write
is a few numpy slice assignments (microseconds): the loop never blocks on the page.
"""

from __future__ import annotations

import mmap
import os
import tempfile
from pathlib import Path

import numpy as np

from jaxcomp.errors import InputError

_MAGIC = 0x6A78636F6E73  # "jxcons"
_HEADER = 4  # magic | frames written | width | slots


class FrameRing:
    """``slots`` frames of ``width`` float64 in the file ``path`` (see the module doc).

    ``FrameRing.create(width, slots)`` makes one (the writer's side; ``close`` removes the
    file), ``FrameRing(path)`` maps an existing one (the reader's side).
    """

    def __init__(self, path: str | Path, *, _owner: bool = False):
        self.path = Path(path)
        head = np.memmap(self.path, dtype=np.float64, mode="r", shape=(_HEADER,))
        if int(head[0]) != _MAGIC:
            raise InputError(f"{self.path} is not a frame ring")
        self.width, self.slots = int(head[2]), int(head[3])
        del head
        size = _HEADER + self.slots * (self.width + 1)
        self._mem = np.memmap(self.path, dtype=np.float64, mode="r+", shape=(size,))
        self._head = self._mem[:_HEADER]
        self._body = self._mem[_HEADER:].reshape(self.slots, self.width + 1)
        self._seq = self._body[:, 0]
        self._frames = self._body[:, 1:]
        self._owner = _owner
        self._read = int(self._head[1])  # the reader starts from now
        self.dropped = 0

    @classmethod
    def create(cls, width: int, slots: int = 64, folder: str | Path | None = None) -> FrameRing:
        """A new, empty ring in a fresh file (in ``folder``, default ``/dev/shm`` when it
        exists, else the temporary folder).

        Args:
            width: float64 numbers per frame, >= 1.
            slots: frames it holds before overwriting the oldest, >= 2.
            folder: where its file goes (None: as above).

        Returns:
            The writer's side (``close`` removes the file).

        Raises:
            InputError: ``width`` < 1 or ``slots`` < 2.
        """
        if width < 1 or slots < 2:
            raise InputError(f"a frame ring needs width >= 1 and slots >= 2, got {width}, {slots}")
        if folder is None:
            folder = "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()
        fd, name = tempfile.mkstemp(prefix="jaxcomp-console-", suffix=".ring", dir=folder)
        os.close(fd)
        size = _HEADER + slots * (width + 1)
        mem = np.memmap(name, dtype=np.float64, mode="w+", shape=(size,))
        mem[:] = 0.0
        mem[:_HEADER] = (_MAGIC, 0, width, slots)
        mem.flush()
        del mem
        return cls(name, _owner=True)

    @property
    def written(self) -> int:
        """Frames written so far."""
        return int(self._head[1])

    def write(self, frame: np.ndarray) -> None:
        """Append one frame (``width`` floats; shorter ones are padded with NaN). Never
        blocks; overwrites the oldest slot.

        Args:
            frame: (k,) float64; numbers past ``width`` are left out.
        """
        count = int(self._head[1])
        slot = count % self.slots
        self._seq[slot] = 2 * count + 1  # writing
        row = self._frames[slot]
        k = min(len(frame), self.width)
        row[:k] = frame[:k]
        if k < self.width:
            row[k:] = np.nan
        self._seq[slot] = 2 * count + 2  # done
        self._head[1] = count + 1

    def read(self) -> np.ndarray:
        """The frames written since the last ``read`` that are still whole, oldest first,
        (k, width); frames overwritten before they were read add to ``dropped``."""
        count = int(self._head[1])
        first = max(self._read, count - self.slots + 1)  # the slot being written may be next
        self.dropped += first - self._read
        out = []
        for c in range(first, count):
            slot = c % self.slots
            stamp = self._seq[slot]
            frame = self._frames[slot].copy()
            if stamp == 2 * c + 2 and self._seq[slot] == stamp:
                out.append(frame)
            else:  # overwritten meanwhile
                self.dropped += 1
        self._read = count
        return np.array(out).reshape(len(out), self.width)

    def close(self) -> None:
        """Unmap; the writer's side also removes the file."""
        mapped = self._mem.base  # the memmap's mmap.mmap
        if isinstance(mapped, mmap.mmap):
            mapped.close()
        if self._owner:
            self.path.unlink(missing_ok=True)


__all__ = ["FrameRing"]
