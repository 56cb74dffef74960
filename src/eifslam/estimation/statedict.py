"""Checked reading of state dictionaries (sessions; pure NumPy).

An object that can be saved says what it keeps with ``state_dict()``: a nested ``dict``
whose leaves are NumPy arrays or JSON values (numbers, strings, lists, None), and takes
it back with ``load_state_dict(d)``. The dictionary may come from a file a user was sent,
so every read goes through :func:`take` and friends, which check the key, the dtype, the
number of dimensions, the fixed sizes and finiteness, and raise :class:`SessionError`
naming the entry (never ``KeyError``, ``IndexError`` or an unchecked array).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from ..errors import SessionError

__all__ = ["take", "take_int", "take_float", "take_ids", "check_index", "sub"]


def sub(d: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    """The nested dictionary ``d[key]``."""
    v = d.get(key) if isinstance(d, Mapping) else None
    if not isinstance(v, Mapping):
        raise SessionError(f"entry {key!r} is missing or not a mapping")
    return v


def take(d: Mapping[str, Any], key: str, dtype, shape: tuple[int | None, ...], finite: bool = True) -> NDArray:
    """The array ``d[key]``, checked.

    Parameters
    ----------
    d : mapping
    key : str
    dtype : dtype or tuple of dtypes
        Allowed dtypes (exact; no conversion from, say, float to int).
    shape : tuple
        Expected shape, ``None`` for a free size.
    finite : bool
        Floating arrays must be finite (NaN and inf never reach the filter).
    """
    a = d.get(key) if isinstance(d, Mapping) else None
    if not isinstance(a, np.ndarray):
        raise SessionError(f"array {key!r} is missing")
    allowed = tuple(np.dtype(t) for t in (dtype if isinstance(dtype, tuple) else (dtype,)))
    if a.dtype not in allowed:
        raise SessionError(f"array {key!r} has dtype {a.dtype}, expected {' or '.join(map(str, allowed))}")
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise SessionError(f"array {key!r} has shape {a.shape}, expected {want}")
    if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise SessionError(f"array {key!r} holds NaN or inf")
    return a


def take_ids(d: Mapping[str, Any], key: str, n: int | None = None, lo: int = 0) -> NDArray[np.int64]:
    """A 1-D ``int64`` array ``d[key]`` (of length ``n`` if given) with every value ``>= lo``."""
    a = take(d, key, np.int64, (n,))
    if a.size and a.min() < lo:
        raise SessionError(f"array {key!r} holds a value below {lo}")
    return a


def check_index(a: NDArray, n: int, what: str) -> None:
    """Every value of the integer array ``a`` indexes a sequence of length ``n``."""
    if a.size and (a.min() < 0 or a.max() >= n):
        raise SessionError(f"{what} holds an index outside [0, {n})")


def take_int(d: Mapping[str, Any], key: str, lo: int | None = None) -> int:
    """The integer ``d[key]`` (``>= lo`` if given)."""
    v = d.get(key) if isinstance(d, Mapping) else None
    if isinstance(v, bool) or not isinstance(v, int) or (lo is not None and v < lo):
        raise SessionError(f"entry {key!r} must be an integer{'' if lo is None else f' >= {lo}'}, got {v!r}")
    return v


def take_float(d: Mapping[str, Any], key: str) -> float:
    """The finite number ``d[key]``."""
    v = d.get(key) if isinstance(d, Mapping) else None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise SessionError(f"entry {key!r} must be a finite number, got {v!r}")
    return float(v)
