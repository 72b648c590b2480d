"""A study's worlds in chunks: their layout, and each finished chunk's results on disk.

A study of any number of worlds runs in chunks of contiguous global world ids
(``study_chunks``), cut at the boundaries of the worlds' plan groups too (a chunk records one
plan). Each finished chunk's per-world results go to one file in the study's output folder
(``ChunkStore``: ``OUT/chunks/worlds_<first>_<stop>.npz``, written atomically: temp file +
rename), beside the settings they belong to (``chunks/settings.json``). A resumed study
(``ChunkStore.prepare(resume=True)``) keeps the chunks already there after checking that
they belong to the same settings (one ``InputError`` naming what differs, as
``jaxcomp calibrate --resume`` does: ``recording.setting_differences``).

A chunk file holds flat arrays: ``<part>.<name>`` for the parts of ``ChunkStore.write``
(e.g. ``world.truth``, ``scipy.estimate``, ``timing.simulate``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, TypedDict, TypeVar

import numpy as np
from tqdm.auto import tqdm

from jaxcomp.errors import InputError
from jaxcomp.files import atomic_output, output_folder, reading, writing
from jaxcomp.recording import setting_differences
from jaxcomp.robot_params import json_ready, write_json_atomic
from jaxcomp.studies.processes import ONE_PROCESS, Processes, together

if TYPE_CHECKING:
    from jaxcomp.robot import Robot

#: The folder of the chunk files inside a study's output folder.
CHUNKS_DIR = "chunks"
#: Worlds per chunk and device when the chunk size is not given: a few thousand fill an
#: accelerator (and its memory) well; on several devices each gets as many.
CHUNK_WORLDS_PER_DEVICE = 4096
#: The settings the chunk files belong to, in ``CHUNKS_DIR``.
SETTINGS_FILE = "settings.json"


class Chunk(NamedTuple):
    """Chunk ``index`` of a study: the global world ids ``rows``, all of plan group
    ``group``."""

    index: int
    group: int
    rows: range


def study_chunks(groups: Sequence[range], size: int) -> list[Chunk]:
    """The chunks of a study's worlds, each group cut from its first world.

    Args:
        groups: the contiguous plan groups, covering the worlds 0..N-1 in order.
        size: worlds per chunk at most (``--chunk-worlds``).

    Returns:
        The chunks in world order, the last chunk of a group shorter.

    Raises:
        InputError: ``size`` is not an integer >= 1.
    """
    if isinstance(size, bool) or int(size) != size or size < 1:
        raise InputError(f"--chunk-worlds must be an integer >= 1, got {size}")
    size = int(size)
    cuts = [(g, range(a, min(a + size, rows.stop))) for g, rows in enumerate(groups)
            for a in range(rows.start, rows.stop, size)]  # fmt: skip
    return [Chunk(i, g, rows) for i, (g, rows) in enumerate(cuts)]


def flatten(parts: Mapping[str, Mapping[str, Any]]) -> dict[str, np.ndarray]:
    """A chunk's parts as the flat arrays of its file.

    Args:
        parts: {part: {name: array}}.

    Returns:
        {"part.name": array}.
    """
    return {f"{p}.{k}": np.asarray(v) for p, arrays in parts.items() for k, v in arrays.items()}


def unflatten(flat: Mapping[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """A chunk file's flat arrays as its parts (``flatten`` undone).

    Args:
        flat: {"part.name": array}.

    Returns:
        {part: {name: array}}.
    """
    out: dict[str, dict[str, np.ndarray]] = {}
    for key, value in flat.items():
        part, _, name = key.partition(".")
        out.setdefault(part, {})[name] = value
    return out


class ChunkStore:
    """The finished chunks of a study in ``folder``, see the module docstring.

    ``prepare`` first (one process), then ``done``/``write``/``read`` per chunk (any process
    sharing the folder), ``remove`` once the report is written.

    Args:
        folder: the chunks' folder, ``OUT/chunks``.
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def path(self, chunk: Chunk) -> Path:
        """The file of ``chunk``'s results.

        Args:
            chunk: a chunk of the study.

        Returns:
            ``folder``/worlds_<first>_<stop>.npz.
        """
        return self.folder / f"worlds_{chunk.rows.start:09d}_{chunk.rows.stop:09d}.npz"

    def prepare(self, settings: Mapping[str, Any], resume: bool) -> int:
        """Get the folder ready for a study of ``settings``.

        Args:
            settings: what the chunks belong to (JSON-able).
            resume: keep the chunk files of an earlier run of the same settings.

        Returns:
            The number of chunk files kept.

        Raises:
            InputError: resumed with other settings (naming what differs), or not resumed
                in a folder that holds an earlier run's chunks (``--resume`` continues it).
        """
        stored = self.folder / SETTINGS_FILE
        files = sorted(self.folder.glob("worlds_*.npz")) if self.folder.is_dir() else []
        now = json.loads(json.dumps(json_ready(dict(settings))))
        if stored.is_file() or files:
            if not resume:
                raise InputError(
                    f"{self.folder} holds the partial results of an interrupted study "
                    f"({len(files)} chunks): --resume continues it; remove {self.folder} to "
                    "start over"
                )
            earlier = _read_json(stored)
            differ = (
                "its settings are unreadable"
                if not isinstance(earlier, dict)
                else setting_differences(earlier, now)
            )
            if differ:
                raise InputError(
                    f"cannot resume the study in {self.folder.parent}: {differ} (start over in "
                    f"another folder, or remove {self.folder})"
                )
            return len(files)
        with writing(self.folder):
            self.folder.mkdir(parents=True, exist_ok=True)
        write_json_atomic(stored, now)
        return 0

    def earlier(self, name: str) -> Any:
        """A setting of the run whose chunks the folder holds.

        Args:
            name: the setting's name (``prepare``'s ``settings``).

        Returns:
            Its value; None when none is stored.
        """
        stored = _read_json(self.folder / SETTINGS_FILE)
        return stored.get(name) if isinstance(stored, dict) else None

    def done(self, chunk: Chunk) -> bool:
        """Whether ``chunk``'s results are on disk.

        Args:
            chunk: a chunk of the study.

        Returns:
            True when its file exists.
        """
        return self.path(chunk).is_file()

    def write(self, chunk: Chunk, parts: Mapping[str, Mapping[str, Any]]) -> Path:
        """Write ``chunk``'s results atomically.

        Args:
            chunk: a chunk of the study.
            parts: its results, {part: {name: array}}.

        Returns:
            The file written (``path``).
        """
        path = self.path(chunk)
        with atomic_output(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, **flatten(parts))
        return path

    def read(self, chunk: Chunk) -> dict[str, dict[str, np.ndarray]]:
        """``chunk``'s results as written.

        Args:
            chunk: a chunk of the study.

        Returns:
            {part: {name: array}}.

        Raises:
            InputError: its file is missing (a process that does not share the folder wrote
                it elsewhere).
        """
        path = self.path(chunk)
        if not path.is_file():
            raise InputError(
                f"{path} is missing: every process of a study must write into the same --out "
                "folder (a shared file system)"
            )
        with reading(path), np.load(path) as data:
            return unflatten({k: data[k] for k in data.files})

    def remove(self) -> None:
        """Remove the folder and its chunk files (the study's report holds them all)."""
        shutil.rmtree(self.folder, ignore_errors=True)


def _read_json(path: Path) -> Any:
    """The JSON in ``path``; None when it is missing or not JSON."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_chunks(
    processes: Processes,
    chunks: Sequence[Chunk],
    store: ChunkStore | None,
    compute: Callable[[Chunk], dict],
    *,
    settings: dict,
    resume: bool,
    progress: bool,
) -> list[dict] | None:
    """Every chunk's parts, each process computing its own chunks (``Processes.mine``).

    Args:
        processes: this process among the study's.
        chunks: all the study's chunks, in order.
        store: where the finished chunks go (None: kept in memory, one process).
        compute: ``compute(chunk)`` -> {part: {name: array}}.
        settings: what the chunks belong to (``ChunkStore.prepare``).
        resume: keep the finished chunks in ``store``.
        progress: show a progress bar over the worlds.

    Returns:
        All chunks' parts in order on process 0, once every process is done; None on the
        others.
    """
    lead = processes.index == 0
    if store is not None:
        together(processes, lambda: lead and store.prepare(settings, resume),
                 "to prepare the output folder")  # fmt: skip
    mine, kept = processes.mine(chunks), {}
    worlds = sum(len(c.rows) for c in chunks)

    def run_mine() -> None:
        bar = tqdm(total=sum(len(c.rows) for c in mine), unit="world",
                   desc=f"{worlds} worlds", disable=not progress)  # fmt: skip
        for chunk in mine:
            if store is None or not store.done(chunk):
                parts = compute(chunk)
                if store is None:
                    kept[chunk.index] = parts
                else:
                    store.write(chunk, parts)
            bar.update(len(chunk.rows))
        bar.close()

    together(processes, run_mine, "to run its chunks")
    if not lead:
        return None
    return [kept[c.index] if store is None else store.read(c) for c in chunks]


R = TypeVar("R")
S = TypeVar("S")
T = TypeVar("T")


def chunk_store(folder: Path | None, settings: S, resume: bool) -> tuple[ChunkStore | None, S]:
    """The chunk store of a study's output folder, and the study's settings as resumed.

    Args:
        folder: the study's output folder (None: the chunks stay in memory).
        settings: the study's settings, a dataclass with ``chunk_worlds`` (None: the default).
        resume: the study continues an interrupted run in ``folder``.

    Returns:
        (``ChunkStore`` of ``folder``/chunks, None without a folder; ``settings``, resumed
        without a chunk size: with the interrupted run's, whatever the device count).
    """
    store = None if folder is None else ChunkStore(Path(folder) / CHUNKS_DIR)
    if resume and store is not None and settings.chunk_worlds is None:
        settings = dataclasses.replace(settings, chunk_worlds=store.earlier("chunk_worlds"))
    return store, settings


class StudyOptions(TypedDict, total=False):
    """How a study runs into its report folder: the keywords of ``into_folder`` and of every
    study's ``study_into``.

    Attributes:
        progress: show progress bars (on process 0 only; default True).
        robot: the studied robot, whose simulator and compiled programs the study keeps
            (default None: the studies' ``MODEL``, freshly loaded).
        resume: keep the finished chunks of an interrupted run of the same settings in the
            folder (default False).
        processes: this process among the study's (``processes.start_processes``; default
            ``ONE_PROCESS``): process 0 holds the folder and writes the report, the others
            write their chunks into it.
    """

    progress: bool
    robot: Robot | None
    resume: bool
    processes: Processes


def into_folder(
    out: Path,
    run_study: Callable[..., R | None],
    settings: Any,
    write: Callable[[Path, R], T],
    *,
    progress: bool = True,
    robot: Robot | None = None,
    resume: bool = False,
    processes: Processes = ONE_PROCESS,
) -> T | None:
    """A chunked study run into its report folder: the one call of every study.

    Process 0 creates and locks ``out`` first (``files.output_folder``: FileError before
    minutes of simulation), the others wait for it and run their chunks into it; process 0
    then writes the outputs and removes the chunk files. On error nothing is written but the
    finished chunks (``resume`` keeps them), and a folder it created and left empty is
    removed.

    Args:
        out: the study's report folder.
        run_study: the study's ``run_study(settings, folder=, progress=, robot=, resume=,
            processes=)``: its result on process 0, None on the others.
        settings: the study's settings.
        write: ``write(folder, result)``: the outputs written, what ``into_folder`` returns.
        progress, robot, resume, processes: ``StudyOptions``.

    Returns:
        What ``write`` returns on process 0; None on the others.
    """
    where = "to open the output folder"
    run = partial(run_study, settings, robot=robot, resume=resume, processes=processes)
    if processes.index != 0:
        together(processes, lambda: None, where)
        run(folder=Path(out), progress=False)
        return None
    with contextlib.ExitStack() as stack:
        folder = together(processes, lambda: stack.enter_context(output_folder(out)), where)
        done = write(folder, run(folder=folder, progress=progress))
        ChunkStore(folder / CHUNKS_DIR).remove()
        return done
