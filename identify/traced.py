"""Traced programs kept on disk between processes (``jax.export``), so that a new process runs a
jitted computation without tracing it again; the XLA compilation cache then skips compiling it.

Tracing the batched joint fit takes ~5 s on a CPU, in every process: JAX's persistent cache
keeps compiled programs, found by the traced program, never the trace. The programs go beside
that cache (``jax_compilation_cache_dir``/traced, which the CLI sets: ``$JAXCOMP_CACHE``); with
no cache folder set, nothing is kept on disk. A program is found by its name, a description of
its static arguments, the arguments' shapes and dtypes, JAX's version, the backend and a digest
of jaxcomp's source, so an edited jaxcomp traces afresh. A process keeps the programs it has
compiled (``program``): one can be loaded from shapes alone while its data are being read.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
from jax import export

from jaxcomp.errors import FileError
from jaxcomp.files import atomic_output


@functools.cache
def _source_digest() -> str:
    """SHA-256 of jaxcomp's Python source (the core and the identification package)."""
    import jaxcomp
    import jaxcomp.identify

    digest = hashlib.sha256()
    for package in (jaxcomp, jaxcomp.identify):
        for path in sorted(Path(package.__file__).parent.rglob("*.py")):
            digest.update(path.read_bytes())
    return digest.hexdigest()


@functools.cache
def _register(t: type) -> None:
    """Make the NamedTuple ``t`` serializable in exported programs (once per process)."""
    export.register_namedtuple_serialization(t, serialized_name=f"jaxcomp.{t.__qualname__}")


def cache_folder() -> Path | None:
    """Where traced programs are kept: ``traced/`` in JAX's compilation cache folder (None when
    none is set)."""
    where = jax.config.jax_compilation_cache_dir
    return Path(where) / "traced" if where else None


#: This process's compiled programs, by their key and cache folder.
_PROGRAMS: dict[tuple[str, Path | None], Callable] = {}
_LOCK = threading.Lock()


def program(
    name: str, statics: str, fn: Callable, args: tuple, types: tuple[type, ...] = ()
) -> Callable:
    """``fn`` (a function of arrays and pytrees of them, jit-able) compiled for arguments like
    ``args`` (arrays, or ``jax.ShapeDtypeStruct`` to load it before the data are there), from
    its traced program kept on disk when a compilation cache folder is set; kept in this
    process.

    Args:
        name: The program's name (file names).
        statics: A stable text of what ``fn`` closes over (e.g. a model's identity).
        fn: The function.
        args: Example arguments: arrays, or ``jax.ShapeDtypeStruct``.
        types: The NamedTuple types of its arguments and results (registered for
            serialization).

    Returns:
        The compiled function, taking arguments like ``args``.
    """
    folder = cache_folder()
    if importlib.util.find_spec("flatbuffers") is None:  # export needs it
        folder = None
    shapes = jax.tree.map(lambda a: (tuple(a.shape), str(a.dtype)), args)
    key = repr((name, statics, shapes, jax.tree.structure(args), jax.__version__))
    key += jax.default_backend() + _source_digest()
    with _LOCK:
        if (key, folder) not in _PROGRAMS:
            _PROGRAMS[key, folder] = _compile(name, key, folder, fn, args, types)
        return _PROGRAMS[key, folder]


def call(name: str, statics: str, fn: Callable, args: tuple, types: tuple[type, ...] = ()) -> Any:
    """``fn(*args)`` through its ``program``.

    Args:
        name: The program's name.
        statics: A stable text of what ``fn`` closes over.
        fn: The function.
        args: Its arguments.
        types: The NamedTuple types of its arguments and results.

    Returns:
        What ``fn`` returns.
    """
    return program(name, statics, fn, args, types)(*args)


def _compile(
    name: str, key: str, folder: Path | None, fn: Callable, args: tuple, types: tuple[type, ...]
) -> Callable:
    if folder is None:
        return jax.jit(fn).lower(*args).compile()
    for t in types:
        _register(t)
    path = folder / f"{name}-{hashlib.sha256(key.encode()).hexdigest()}.bin"
    kept = None
    if path.is_file():
        try:
            kept = export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # noqa: BLE001 - a damaged or foreign file: trace again
            kept = None
    if kept is None:
        kept = export.export(jax.jit(fn))(*args)
        try:
            with atomic_output(path) as tmp:
                tmp.write_bytes(kept.serialize())
        except FileError:  # a read-only or full cache folder: the program still runs
            pass
    return jax.jit(kept.call).lower(*args).compile()
