"""Input checks shared by every part of jaxcomp: a number, or an array of numbers, that is
finite, of the expected shape and, where asked, of a sign.

Each check returns the value as float64 (a Python float or a numpy array) or raises one
``InputError`` that names the input, its unit and what is wrong: not a number, the shape
(stating the one expected), NaN or inf (naming the entries: by ``labels``, such as joint or
link names, else by index) or the sign.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from jaxcomp.errors import InputError

#: Entries named at most in a message; more are counted.
_NAMED = 6


def number(
    value, name: str, *, positive: bool = False, nonneg: bool = False, unit: str | None = None
) -> float:
    """``value`` as a finite float.

    Args:
        value: anything ``float()`` takes (a number, a numeric string, a 0-d array).
        name: the input's name, for the error.
        positive: refuse values <= 0.
        nonneg: refuse values < 0.
        unit: the value's unit, for the error (e.g. ``"s"``).

    Returns:
        The value as a float.

    Raises:
        InputError: not a number, NaN or inf, or of the wrong sign.
    """
    try:
        x = float(value)
    except (TypeError, ValueError):
        of = f" of {unit}" if unit else ""
        raise InputError(f"{name} must be a number{of}, got {value!r:.60}") from None
    if math.isfinite(x) and not (positive and x <= 0) and not (nonneg and x < 0):
        return x
    raise InputError(_bad_number(name, x, positive, nonneg, unit))


def array(
    value,
    name: str,
    *,
    n: int | None = None,
    shape: tuple[int | None, ...] | None = None,
    labels: Sequence[str] | None = None,
    kind: str = "",
    unit: str | None = None,
    positive: bool = False,
    nonneg: bool = False,
    scalar: bool = False,
) -> np.ndarray:
    """``value`` as a finite float64 array of the expected shape.

    Args:
        value: a sequence or array of numbers.
        name: the input's name, for the errors.
        n: the length of a 1-D input (shape ``(n,)``).
        shape: the expected shape, ``None`` for an axis of any length (e.g. ``(None, 3)``),
            ``()`` for one number; neither ``n`` nor ``shape``: a 1-D input of any length.
        labels: names of the entries along the first axis (joint names, link names, axes),
            for the errors; else they are named by index.
        kind: what the labels name, put before them in the errors (e.g. ``"joint(s)"``).
        unit: the values' unit, for the errors (e.g. ``"rad"``).
        positive: refuse entries <= 0.
        nonneg: refuse entries < 0.
        scalar: also take one number: broadcast to ``n`` or ``shape`` when given, else
            returned as a 0-d array.

    Returns:
        The float64 array (``value`` itself when it is one already).

    Raises:
        InputError: not numbers, another shape, NaN or inf, or an entry of the wrong sign.
    """
    want = (n,) if n is not None else shape if shape is not None else (None,)
    arr = _floats(value, name, want, unit, scalar)
    if arr.ndim == 0 and (scalar or want == ()):
        number(arr, name, positive=positive, nonneg=nonneg, unit=unit)
        return np.full(want, float(arr)) if want and None not in want else arr
    if arr.shape != want and not _fits(arr.shape, want):
        named = "" if labels is None else f" for {_joined(labels, kind, len(labels))}"
        raise InputError(
            f"{name} must have shape {_shape(want)}{_in(unit)}{named}, got shape {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or inf at {_where(~np.isfinite(arr), labels, kind)}")
    if positive or nonneg:
        _check_sign(arr, name, labels, kind, unit, positive)
    return arr


def _floats(value, name: str, want: tuple, unit: str | None, scalar: bool) -> np.ndarray:
    """``value`` as a float64 array, or the error of one that holds no numbers (None, which
    numpy would take for NaN, included)."""
    try:
        if value is None:
            raise TypeError
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(
            f"{name} must be {'a number or ' if scalar else ''}an array of numbers of shape "
            f"{_shape(want)}{_in(unit)}, got {value!r:.60}"
        ) from None


def _fits(shape: tuple[int, ...], want: tuple[int | None, ...]) -> bool:
    """``shape`` is ``want`` but for the axes of any length (``None``)."""
    return len(shape) == len(want) and all(
        w is None or a == w for a, w in zip(shape, want, strict=True)
    )


def _check_sign(
    arr: np.ndarray, name: str, labels, kind: str, unit: str | None, positive: bool
) -> None:
    """The error of entries <= 0 (``positive``), else < 0."""
    bad = arr <= 0 if positive else arr < 0
    if bad.any():
        u = f" {unit}" if unit else ""
        sign, fault = ("> 0", "not positive") if positive else (">= 0", "negative")
        raise InputError(
            f"{name} must be {sign}{u}; {fault} for {_where(bad, labels, kind, arr, u)}"
        )


def _bad_number(name: str, x: float, positive: bool, nonneg: bool, unit: str | None) -> str:
    """The error of a number ``x`` that is NaN, inf or of the wrong sign."""
    if not (positive or nonneg):
        return f"{name} is {x}, not a finite number"
    need = f"{'> 0' if positive else '>= 0'}{f' {unit}' if unit else ''}"
    return f"{name} must be {need}{'' if math.isfinite(x) else ' and finite'}, got {x:g}"


def _shape(want: tuple[int | None, ...]) -> str:
    """A shape as the errors write it: ``(N, 3)`` for ``(None, 3)``."""
    axes = ["N" if w is None else str(w) for w in want]
    return f"({axes[0]},)" if len(axes) == 1 else f"({', '.join(axes)})"


def _in(unit: str | None) -> str:
    """`` in UNIT`` (nothing without a unit)."""
    return f" in {unit}" if unit else ""


def _joined(names: Sequence[str], kind: str, most: int = _NAMED) -> str:
    """``names`` in a message, after their ``kind``: the first ``most``, then a count."""
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return (f"{kind} " if kind else "") + ", ".join(names[:most]) + more


def _where(
    bad: np.ndarray,
    labels: Sequence[str] | None,
    kind: str = "",
    arr: np.ndarray | None = None,
    u: str = "",
) -> str:
    """The entries ``bad`` marks: by label (rows of the first axis) or by index, a 1-D
    ``arr``'s values with them when it is given."""
    if labels is None and bad.ndim != 1:
        where = np.argwhere(bad)
        first = tuple(int(i) for i in where[0])
        return f"index {first}" + (f" ({len(where)} entries)" if len(where) > 1 else "")
    rows = np.flatnonzero(bad.reshape(len(bad), -1).any(axis=1))
    named = [str(i) if labels is None else labels[i] for i in rows]
    if arr is not None and arr.ndim == 1:
        named = [f"{s} ({arr[i]:g}{u})" for s, i in zip(named, rows, strict=True)]
    return _joined(named, "index" if labels is None else kind)
