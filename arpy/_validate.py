"""What the core accepts, checked once at the door: positions, cutoffs, counts, and the range of lengths.

Every public entry point of arpy validates its arrays here and hands the results down; the
modules below it take them as given.
"""

from __future__ import annotations

import math

import numpy as np

from . import _core
from ._codes import RANGE_EXP

__all__ = ["as_cutoffs", "as_positions", "check_count", "column_extremes", "core_exponent", "lengths_exponent"]


def as_positions(x: np.ndarray) -> np.ndarray:
    """Validate positions and return a C-contiguous float64 array of shape (n, d)."""
    arr = np.asarray(x)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise TypeError(f"positions must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise ValueError(f"positions must have shape (n, d), got shape {arr.shape}")
    if arr.shape[1] not in (2, 3):
        raise ValueError(f"positions must have d = 2 or d = 3 columns, got shape {arr.shape}")
    if arr.shape[0] > np.iinfo(np.int32).max:
        raise ValueError("at most 2**31 - 1 particles are supported")
    return np.ascontiguousarray(arr, dtype=np.float64)


def column_extremes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest entry of each column of x (n >= 1, d), shapes (d,); NaN shows in
    them.  C-ordered float64 arrays in the core, in parallel (twice as fast as NumPy at two
    threads); others by one strided NumPy reduction per column (ten times faster than
    ``x.min(axis=0)`` on a C-ordered (n, d) array, which NumPy reduces one row at a time)."""
    if x.dtype == np.float64 and x.ndim == 2 and x.shape[0] and x.shape[1] and x.flags.c_contiguous:
        lo, hi = _core.arpy_column_extremes(x.T)
        return lo, hi
    return (np.array([x[:, j].min() for j in range(x.shape[1])]),
            np.array([x[:, j].max() for j in range(x.shape[1])]))


def as_cutoffs(rc: float | np.ndarray, n: int) -> np.ndarray:
    """Broadcast a scalar cutoff or validate per-particle cutoffs; float64 shape (n,)."""
    arr = np.asarray(rc)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
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


def core_exponent(big: float, small: float) -> int:
    """The power of two ``2**k`` that brings lengths in ``[small, big]`` into the core's range.

    ``big`` is the largest |coordinate|, cutoff or skin, ``small`` the smallest
    cutoff (same length unit, both finite, ``small > 0``).  Returns k = 0 when
    they are in range already; otherwise k centres the two, so that
    ``2**k big <= 2**RANGE_EXP`` and ``2**k small >= 2**-RANGE_EXP``.
    Multiplying by a power of two is exact (``np.ldexp``), so the neighbour
    tests of the scaled problem give the answers of the unscaled one without
    overflowing or underflowing.

    Raises
    ------
    ValueError
        When no such k exists: the lengths span more than 2**(2 RANGE_EXP - 1)
        (about 5e300), far beyond the 2**53 resolution of the coordinates.
    """
    lim = math.ldexp(1.0, RANGE_EXP)
    if big <= lim and small >= 1.0 / lim:
        return 0
    e_big, e_small = math.frexp(big)[1], math.frexp(small)[1]
    if e_big - e_small > 2 * RANGE_EXP - 1:
        raise ValueError(
            f"lengths span too wide a range: the largest coordinate, cutoff or skin ({big:.3g}) is more than "
            f"2**{2 * RANGE_EXP - 1} times the smallest cutoff ({small:.3g}); squared distances would "
            "overflow or underflow in double precision")
    return -((e_big + e_small) // 2)


def lengths_exponent(coordinates, sizes) -> int:
    """:func:`core_exponent` of a problem's lengths: ``coordinates`` (positions, skins, box
    corners; arrays or scalars) count with their largest magnitude, ``sizes`` (cutoffs, core
    sizes; arrays) with their largest and smallest.  Returns 0 for input the core will reject
    (a non-finite value, a size <= 0; the core then names the offending particle) and when
    there are no sizes.  Two reductions per array (min and max propagate NaN), no temporaries."""
    coords = [_extremes(v) for v in coordinates if np.size(v)]
    sized = [_extremes(v) for v in sizes if np.size(v)]
    if not sized:
        return 0
    bounds = [b for pair in coords + sized for b in pair]
    small = min(lo for lo, _ in sized)
    if not (all(math.isfinite(b) for b in bounds) and small > 0):
        return 0
    return core_exponent(max(abs(b) for b in bounds), small)


def _extremes(v) -> tuple[float, float]:
    """(min, max) of an array or a scalar as floats (NaN if any value is NaN)."""
    if isinstance(v, np.ndarray):
        return float(v.min()), float(v.max())
    if isinstance(v, (float, int)):
        return float(v), float(v)
    return float(np.min(v)), float(np.max(v))
