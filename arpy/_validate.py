"""What the core accepts, checked once at the door: positions, cutoffs, counts, indices, and the range of lengths.

Every public entry point of arpy validates its arrays here and hands the results down; the
modules below it take them as given.  (The power-of-two scaling of lengths into the core's range is
the bridge's: :mod:`arpy._bridge`.  A user's ``domain`` is checked beside the class it must be:
:func:`arpy.domain.as_domain`.)
"""

from __future__ import annotations

import warnings
from typing import TypeGuard

import numpy as np

from . import _bridge

__all__ = ["as_cutoffs", "as_positions", "check_count", "check_index", "column_extremes", "is_integer",
           "non_finite_rows", "resolve_full"]


#: The kinds of NumPy dtypes taken as real numbers: those np.issubdtype counts as np.floating or np.integer
#: (floats, signed and unsigned integers, and timedelta64, a signed integer to NumPy).
_REAL_KINDS = "fium"
#: The most particles the core indexes (int32 indices).
_MAX_PARTICLES = 2**31 - 1


def as_positions(x: np.ndarray) -> np.ndarray:
    """Validate positions and return a C-contiguous float64 array of shape (n, d)."""
    arr = np.asarray(x)
    if arr.dtype.kind not in _REAL_KINDS:
        raise TypeError(f"positions must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise ValueError(f"positions must have shape (n, d), got shape {arr.shape}")
    if arr.shape[1] not in (2, 3):
        raise ValueError(f"positions must have d = 2 or d = 3 columns, got shape {arr.shape}")
    if arr.shape[0] > _MAX_PARTICLES:
        raise ValueError("at most 2**31 - 1 particles are supported")
    return np.ascontiguousarray(arr, dtype=np.float64)


def column_extremes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest entry of each column of x (n >= 1, d), shapes (d,); NaN shows in
    them.  C-ordered float64 arrays in the core, in parallel (twice as fast as NumPy at two
    threads); others by one strided NumPy reduction per column (ten times faster than
    ``x.min(axis=0)`` on a C-ordered (n, d) array, which NumPy reduces one row at a time)."""
    if x.dtype == np.float64 and x.ndim == 2 and x.shape[0] and x.shape[1] and x.flags.c_contiguous:
        return _bridge.column_extremes(x)
    return (np.array([x[:, j].min() for j in range(x.shape[1])]),
            np.array([x[:, j].max() for j in range(x.shape[1])]))


def as_cutoffs(rc: float | np.ndarray, n: int) -> np.ndarray:
    """Broadcast a scalar cutoff or validate per-particle cutoffs; float64 shape (n,)."""
    arr = np.asarray(rc)
    if arr.dtype.kind not in _REAL_KINDS:
        raise TypeError(f"cutoff radii must be real numbers, got dtype {arr.dtype}")
    if arr.ndim == 0:
        return np.full(n, float(arr), dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"cutoff radii must be a scalar or have shape ({n},), got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def check_count(name: str, value) -> None:
    """A count parameter must be an integer >= 1 (NaN, inf, 2.5 and 0 are refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float, np.floating)) \
            or not np.isfinite(value) or int(value) != value or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def is_integer(value: object) -> TypeGuard[int | np.integer]:
    """Whether ``value`` is a Python or NumPy integer (a bool is not)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_index(name: str, value: object, n: int, what: str = "particles") -> int:
    """An index into n items (``what``): an integer (Python or NumPy, not bool) in [0, n), returned as
    an int.  TypeError for anything else; IndexError outside [0, n), negative values included (they
    are mistakes here, not counts from the end)."""
    if not is_integer(value):
        raise TypeError(f"{name} must be an integer index, got {value!r}")
    if not 0 <= value < n:
        raise IndexError(f"{name} = {value} is out of range: {n} {what}, indices 0 <= {name} < {n} (a negative "
                         "index is not counted from the end)")
    return int(value)


def non_finite_rows(x: np.ndarray) -> np.ndarray:
    """The rows of x (n, d) holding a NaN or Inf, ascending (int64; empty when every entry is finite,
    found by one pass of :func:`column_extremes`)."""
    if x.shape[0] == 0 or all(np.all(np.isfinite(v)) for v in column_extremes(x)):
        return np.zeros(0, np.int64)
    return np.flatnonzero(~np.all(np.isfinite(x), axis=1)).astype(np.int64)


def resolve_full(full: bool, symmetric: bool | None, context: str) -> bool:
    """The form of a neighbour list a caller asked for, ``full`` (True: each pair in both rows; False: a
    half list, each pair once), given ``symmetric``, the deprecated name of the opposite (True: a half
    list): None when not given; else a DeprecationWarning naming ``full=``, and ValueError when both
    are given and disagree (``full=True, symmetric=True``).  The one translation of the alias."""
    if symmetric is None:
        return bool(full)
    warnings.warn(f"{context}: symmetric= is deprecated, use full= (symmetric={bool(symmetric)} is "
                  f"full={not symmetric})", DeprecationWarning, stacklevel=3)
    if full and symmetric:
        raise ValueError(f"{context}: full=True and symmetric=True contradict each other (symmetric= is the "
                         "deprecated name of full=False); give full= only")
    return not bool(symmetric)
