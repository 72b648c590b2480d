"""Traced programs kept on disk: a second call (as in a new process) runs the kept program
without tracing, with the same results; other shapes or statics get their own program; a
program loaded from shapes serves the call with the data."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import export

from jaxcomp.identify import traced


class Pair(NamedTuple):
    a: jax.Array
    b: jax.Array


def _fn(scale):
    return lambda p: Pair(scale * p.a + p.b, jnp.sum(p.a * p.b))


def test_a_traced_program_is_kept_and_reused(tmp_path, monkeypatch):
    monkeypatch.setattr(traced, "cache_folder", lambda: tmp_path)
    args = (Pair(jnp.arange(3.0), jnp.ones(3)),)
    first = traced.call("pair", "scale 2", _fn(2.0), args, (Pair,))
    kept = sorted(tmp_path.iterdir())
    assert len(kept) == 1 and kept[0].name.startswith("pair-")

    def no_tracing(*a, **k):
        raise AssertionError("traced again")

    monkeypatch.setattr(export, "export", no_tracing)
    monkeypatch.setattr(traced, "_PROGRAMS", {})  # as in a new process
    again = traced.call("pair", "scale 2", _fn(2.0), args, (Pair,))
    assert isinstance(again, Pair)
    np.testing.assert_array_equal(again.a, [1.0, 3.0, 5.0])
    assert float(again.b) == 3.0
    np.testing.assert_array_equal(again.a, first.a)
    with pytest.raises(AssertionError, match="traced again"):  # other statics: a new program
        traced.call("pair", "scale 3", _fn(3.0), args, (Pair,))
    with pytest.raises(AssertionError, match="traced again"):  # other shapes: a new program
        traced.call("pair", "scale 2", _fn(2.0), (Pair(jnp.ones(4), jnp.ones(4)),), (Pair,))


def test_without_a_cache_folder_nothing_is_kept(tmp_path, monkeypatch):
    monkeypatch.setattr(traced, "cache_folder", lambda: None)
    out = traced.call("pair", "scale 2", _fn(2.0), (Pair(jnp.ones(2), jnp.ones(2)),), (Pair,))
    np.testing.assert_array_equal(out.a, [3.0, 3.0])
    assert list(tmp_path.iterdir()) == []


def test_a_damaged_program_file_is_traced_again(tmp_path, monkeypatch):
    monkeypatch.setattr(traced, "cache_folder", lambda: tmp_path)
    args = (Pair(jnp.arange(2.0), jnp.ones(2)),)
    traced.call("pair", "scale 2", _fn(2.0), args, (Pair,))
    (kept,) = tmp_path.iterdir()
    kept.write_bytes(b"not a program")
    monkeypatch.setattr(traced, "_PROGRAMS", {})  # as in a new process
    out = traced.call("pair", "scale 2", _fn(2.0), args, (Pair,))
    np.testing.assert_array_equal(out.a, [1.0, 3.0])
    assert kept.read_bytes() != b"not a program"


def test_a_program_loaded_from_shapes_serves_the_call(tmp_path, monkeypatch):
    monkeypatch.setattr(traced, "cache_folder", lambda: tmp_path)
    monkeypatch.setattr(traced, "_PROGRAMS", {})
    args = (Pair(jnp.arange(3.0), jnp.full(3, 2.0)),)
    shapes = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), args)
    loaded = traced.program("pair", "scale 2", _fn(2.0), shapes, (Pair,))
    assert traced.program("pair", "scale 2", _fn(2.0), args, (Pair,)) is loaded
    out = traced.call("pair", "scale 2", _fn(2.0), args, (Pair,))
    np.testing.assert_array_equal(out.a, [2.0, 4.0, 6.0])
    assert float(out.b) == 6.0
