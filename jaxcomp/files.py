"""Files and folders that jaxcomp writes: atomic replacement, one writer per output folder.

- ``atomic_output(path)``: write to a temp file in ``path``'s folder, flushed to disk, then
  ``os.replace`` it onto ``path``; on any error the temp file goes and ``path`` is untouched
  (never half-written, a good file never replaced by an incomplete one).
- ``output_folder(folder)``: create ``folder`` if needed and hold its lock file ``LOCK_NAME``
  for a block; a second run writing into it gets one ``FileError`` naming the lock and the
  other run's pid. The lock is an ``fcntl.flock`` the system drops when its process ends, so
  the lock file of a run that died (a stale lock) is simply taken over. A folder the block
  created is removed again when the block fails and leaves it empty.
- ``writing(path)`` / ``reading(path)``: an ``OSError`` (read-only folder, full disk, missing
  permission) inside the block becomes one ``FileError`` naming ``path`` and the cause.
"""

from __future__ import annotations

import errno
import os
import socket
import sys
import tempfile
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

from jaxcomp.errors import FileError

try:  # POSIX; elsewhere the lock falls back to the pid it names
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

#: The lock file of an output folder.
LOCK_NAME = ".jaxcomp.lock"
#: The process's umask (read once): written files get the usual 0o666 & ~umask, not the
#: temp file's 0o600.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def os_reason(exc: OSError) -> str:
    """A short reason of ``exc``: its strerror (e.g. "No space left on device"), else str.

    Args:
        exc: the error.

    Returns:
        The reason, one line.
    """
    return exc.strerror or str(exc) or type(exc).__name__


def file_problem(exc: OSError | FileError) -> str:
    """One line for a file that could not be read or written: a ``FileError``'s message,
    an ``OSError``'s file (when it names one) and reason.

    Args:
        exc: the error.

    Returns:
        The line.
    """
    if not isinstance(exc, OSError):
        return str(exc)
    return f"{exc.filename}: {os_reason(exc)}" if exc.filename else os_reason(exc)


@contextmanager
def writing(path: str | Path, verb: str = "cannot write") -> Iterator[None]:
    """Turn an ``OSError`` of the block into one ``FileError``: "<verb> <path>: <reason>".

    Args:
        path: the file or folder the block works on, named in the message.
        verb: what the block does, for the message.

    Returns:
        A context manager.

    Raises:
        FileError: an ``OSError`` inside the block.
    """
    try:
        yield
    except OSError as exc:
        raise FileError(f"{verb} {path}: {os_reason(exc)}") from None


def reading(path: str | Path) -> AbstractContextManager[None]:
    """``writing`` for reads: "cannot read <path>: <reason>".

    Args:
        path: the file or folder the block reads, named in the message.

    Returns:
        A context manager.

    Raises:
        FileError: an ``OSError`` inside the block.
    """
    return writing(path, "cannot read")


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """A temp path beside ``path`` (same suffix, so writers that go by it keep working) to
    write; on success it is flushed to disk and moved onto ``path`` (``os.replace``); on any
    error (``KeyboardInterrupt`` included) it is removed and ``path`` stays as it was.

    Args:
        path: the file to write.

    Returns:
        A context manager giving the temp file's path.

    Raises:
        FileError: an ``OSError`` in the block or in the replacement, naming ``path``.
    """
    path = Path(path)
    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent
        )
        os.close(fd)
        tmp = Path(name)
        try:
            yield tmp
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.chmod(tmp, 0o666 & ~_UMASK)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Write a matplotlib figure atomically (format from ``path``'s suffix) and close it.

    Args:
        fig: the matplotlib figure (closed, also on error).
        path: the image file; its suffix gives the format (none: PNG).
        dpi: resolution, dots per inch.

    Returns:
        ``path``, as a ``Path``.

    Raises:
        FileError: ``path`` cannot be written.
    """
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return path


# ----------------------------------------------------------------------------- the lock
def _holder(path: Path) -> str:
    """Who holds the lock file ``path``, from what it says: "pid N on HOST" or "unknown"."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return "an unknown process"
    pid = lines[0].strip() if lines else "?"
    host = lines[1].strip() if len(lines) > 1 else ""
    here = host in ("", socket.gethostname())
    return f"pid {pid}" + ("" if here else f" on {host}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _locked_by_pid(path: Path) -> bool:
    """Without ``flock``: whether the pid the lock file names is another live process."""
    try:
        pid = int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return False
    return pid != os.getpid() and _alive(pid)


def _acquire(lock: Path, folder: Path, option: str) -> int:
    """Open and lock ``lock``; its file descriptor. ``FileError`` when another run holds it."""
    while True:
        with writing(folder, f"cannot write to {option}"):
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            busy = False
            if fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    busy = True
                except OSError as exc:  # a file system without flock: go by the pid
                    if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                        raise
                    busy = _locked_by_pid(lock)
            else:  # pragma: no cover
                busy = _locked_by_pid(lock)
            if busy:
                raise FileError(
                    f"{option} {folder} is in use by another jaxcomp run ({_holder(lock)}, lock "
                    f"file {lock}): wait for it to end, or write elsewhere"
                )
            try:  # its last holder may have removed it between our open and our lock
                same = os.path.samestat(os.fstat(fd), os.stat(lock))
            except FileNotFoundError:
                same = False
            if same:
                with writing(lock):
                    os.ftruncate(fd, 0)
                    text = f"{os.getpid()}\n{socket.gethostname()}\n{' '.join(sys.argv)}\n"
                    os.write(fd, text.encode())
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


@contextmanager
def output_folder(folder: str | Path, option: str = "--out") -> Iterator[Path]:
    """Create ``folder`` (and its parents) if needed and hold its lock for the block (see the
    module docstring); ``option`` names the folder in messages.

    Args:
        folder: the output folder.
        option: how messages name it, e.g. the CLI option that gave it.

    Returns:
        A context manager giving ``folder`` as a ``Path``.

    Raises:
        FileError: ``folder`` is a file, cannot be created or written, or another run holds it.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise FileError(f"{option} {folder} exists and is not a folder")
    created = not folder.exists()
    with writing(folder, f"cannot create {option}"):
        folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_NAME
    try:
        fd = _acquire(lock, folder, option)
    except BaseException:
        _remove_if_empty(folder, created)
        raise
    ok = False
    try:
        yield folder
        ok = True
    finally:
        try:
            lock.unlink(missing_ok=True)  # while still holding it: see _acquire
        except OSError:
            pass
        os.close(fd)
        if not ok:
            _remove_if_empty(folder, created)


def _remove_if_empty(folder: Path, created: bool) -> None:
    if created:
        try:
            folder.rmdir()  # only when empty
        except OSError:
            pass


def existing(folder: str | Path, names: tuple[str, ...]) -> list[str]:
    """Those of ``names`` (files or folders) that exist in ``folder``.

    Args:
        folder: the folder.
        names: names of files or folders in it.

    Returns:
        The names that exist, in ``names``' order.
    """
    return [name for name in names if (Path(folder) / name).exists()]


def check_outputs(inputs: tuple[str, ...], outputs: list[tuple[str, str | None]]) -> None:
    """One clear error (FileError) when an output file (option, path) would replace an
    input or another output, before anything is read or written.

    Args:
        inputs: paths of the input files.
        outputs: (option, path) of each output file; a None path is skipped.

    Raises:
        FileError: an output path that is also an input or another output.
    """
    given = {Path(p).resolve(): p for p in inputs}
    taken: dict[Path, str] = {}
    for option, path in outputs:
        if path is None:
            continue
        where = Path(path).resolve()
        if where in given:
            raise FileError(f"{option} {path} is also an input: it would replace {given[where]}")
        if where in taken:
            raise FileError(f"{option} {path} is also given as {taken[where]}")
        taken[where] = option
