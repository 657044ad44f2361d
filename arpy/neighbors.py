"""Neighbour lists: the public entry point and the CSR container.

Particles p and q are neighbours iff ``|x_p - x_q| <= min(rc_p, rc_q) + skin``
(the adaptive-resolution "gather" rule; with one cutoff it is the usual
fixed-radius rule).  A particle is never its own neighbour; coincident
particles are neighbours of each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _core
from ._codes import METHODS, RANGE_EXP, STATUS
from ._errors import raise_for_info

__all__ = ["NeighborList", "neighbor_list", "METHODS"]

#: method="auto" uses the AR cell list from this resolution span max(rc)/min(rc)
#: on (the break-even against the uniform cell list measured at N = 1e6 is
#: 1.1, higher at smaller N when the power-of-two levels give cells near
#: 2 r_c; see benchmarks/ar_cell_lists.py), the uniform cell list below it.
AUTO_AR_SPAN = 3.0



@dataclass(frozen=True, eq=False)
class NeighborList:
    """Neighbour lists in compressed sparse row (CSR) form.

    Attributes
    ----------
    offsets : int64 array, shape (n + 1,)
        Row ``p`` is ``indices[offsets[p]:offsets[p + 1]]``.
    indices : int64 array, shape (len(self),)
        Neighbour indices (0-based).  Within a row the order is unspecified.
    symmetric : bool
        True: each unordered pair is stored once, in the row of either of its
        particles.  False: each pair is stored in both rows.
    n_ref : int or None
        None for a list within one particle set.  For a cross-set list (rows =
        query points, indices = particles of a reference set) the size of the
        reference set; then ``symmetric`` is False.
    """

    offsets: np.ndarray
    indices: np.ndarray
    symmetric: bool
    n_ref: int | None = None

    @property
    def cross(self) -> bool:
        """True for a cross-set list (rows and indices refer to different sets)."""
        return self.n_ref is not None

    @property
    def n(self) -> int:
        """Number of rows (particles)."""
        return int(self.offsets.size - 1)

    def __len__(self) -> int:
        """Number of stored entries (pairs if symmetric, twice the pairs if not)."""
        return int(self.indices.size)

    def counts(self) -> np.ndarray:
        """Stored entries per row, shape (n,)."""
        return np.diff(self.offsets)

    def neighbors(self, p: int) -> np.ndarray:
        """Indices stored in row ``p`` (a view)."""
        return self.indices[self.offsets[p]:self.offsets[p + 1]]

    def rows(self) -> np.ndarray:
        """Row index of every stored entry, shape (len(self),)."""
        return np.repeat(np.arange(self.n, dtype=np.int64), self.counts())

    def pairs(self, sort: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Every unordered pair once as arrays ``(i, j)`` with ``i < j``, sorted lexicographically
        (``sort=False``: in the list's own order, without the cost of sorting).

        For a cross-set list: every (query, reference) pair.
        """
        rows, cols = self.rows(), self.indices
        if self.cross:
            i, j = rows, cols.astype(np.int64)
        elif self.symmetric:
            i, j = np.minimum(rows, cols), np.maximum(rows, cols)
        else:
            keep = rows < cols
            i, j = rows[keep], cols[keep]
        if not sort:
            return i, j
        order = np.lexsort((j, i))
        return i[order], j[order]

    @classmethod
    def from_pairs(cls, n: int, i: np.ndarray, j: np.ndarray, symmetric: bool = True) -> "NeighborList":
        """Build the list of n particles from unordered pairs (i, j), each given once.

        Symmetric: pair (i, j) is stored in row min(i, j).  Full: in both rows.
        Rows are sorted.
        """
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        a, b = np.minimum(i, j), np.maximum(i, j)
        if not symmetric:
            a, b = np.concatenate([a, b]), np.concatenate([b, a])
        order = np.lexsort((b, a))
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(a, minlength=n), out=offsets[1:])
        return cls(offsets, b[order].astype(np.int32), bool(symmetric))

    def __repr__(self) -> str:
        kind = f"cross, n_ref={self.n_ref}" if self.cross else ("symmetric" if self.symmetric else "full")
        return f"NeighborList(n={self.n}, entries={len(self)}, {kind})"


def _as_positions(x: np.ndarray) -> np.ndarray:
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


def _as_cutoffs(rc: float | np.ndarray, n: int) -> np.ndarray:
    """Broadcast a scalar cutoff or validate per-particle cutoffs; float64 shape (n,)."""
    arr = np.asarray(rc)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise TypeError(f"cutoff radii must be real numbers, got dtype {arr.dtype}")
    if arr.ndim == 0:
        return np.full(n, float(arr), dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"cutoff radii must be a scalar or have shape ({n},), got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


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
    coords = [(float(np.min(v)), float(np.max(v))) for v in coordinates if np.size(v)]
    sized = [(float(np.min(v)), float(np.max(v))) for v in sizes if np.size(v)]
    if not sized:
        return 0
    bounds = [b for pair in coords + sized for b in pair]
    small = min(lo for lo, _ in sized)
    if not (np.all(np.isfinite(bounds)) and small > 0):
        return 0
    return core_exponent(max(abs(b) for b in bounds), small)


def _collect(handle: int, n: int, nnz: int, symmetric: bool) -> NeighborList:
    """Fetch the list the core has published under ``handle`` (and free it)."""
    try:
        offsets, indices, info = _core.arpy_result_take(handle, n, nnz)
    except BaseException:
        _core.arpy_result_free(handle)
        raise
    raise_for_info(info, context="neighbor_list")
    return NeighborList(offsets=offsets, indices=indices, symmetric=symmetric)


def neighbor_list(
    x: np.ndarray,
    rc: float | np.ndarray,
    *,
    method: str = "cell",
    symmetric: bool = True,
    skin: float = 0.0,
    box=None,
) -> NeighborList:
    """Build neighbour lists of particles with one or per-particle cutoff radii.

    Parameters
    ----------
    x : array, shape (n, d), d = 2 or 3
        Particle positions (any length unit).
    rc : float or array, shape (n,)
        Cutoff radii, same unit as ``x``; finite and > 0.
    method : {"cell", "ar", "auto", "brute"}
        ``"cell"``: uniform cell list (cell edge = largest cutoff + skin),
        counting sort and half-shell pair iteration.  ``"ar"``: adaptive-
        resolution cell list (Awile et al. 2012), whose cost does not grow
        with the spread of cutoffs.  ``"auto"``: ``"ar"`` if
        max(rc)/min(rc) >= AUTO_AR_SPAN, else ``"cell"``.  ``"brute"``: all
        pairs, O(n^2), for small sets and checks.
    symmetric : bool
        True: each unordered pair once (half list).  False: both directions (full list).
    skin : float
        Verlet skin added to every cutoff (>= 0).
    box : None, edge lengths (d,) or (lo, hi)
        Periodic box: lists are correct for periodic boundaries (minimum
        image); particles must lie inside it and max(rc) + skin must be below
        half its smallest edge.  Built with ghost particles
        (:func:`arpy.periodic_ghosts`).

    Returns
    -------
    NeighborList
        CSR lists; ``pairs()`` gives the sorted unordered pairs.

    Raises
    ------
    ValueError, TypeError
        On bad shapes, dtypes, non-finite positions or non-positive cutoffs.
    """
    if method not in METHODS and method != "auto":
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(METHODS) + ['auto']}")
    xs = _as_positions(x)
    n = xs.shape[0]
    rcs = _as_cutoffs(rc, n)
    skin = float(skin)
    if not (np.isfinite(skin) and skin >= 0.0):
        raise ValueError(f"neighbor_list: skin must be a finite number >= 0, got {skin}")
    if n == 0:
        return NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), bool(symmetric))
    auto = method == "auto"
    if auto:
        with np.errstate(over="ignore"):
            span = rcs.max() / rcs.min() if np.all(rcs > 0) and np.all(np.isfinite(rcs)) else 1.0
        method = "ar" if span >= AUTO_AR_SPAN else "cell"
    if box is not None:       # ("auto" again inside: same choice, same fall-back)
        return _periodic_list(xs, rcs, box, "auto" if auto else method, bool(symmetric), skin)
    k = lengths_exponent([xs, skin], [rcs])
    if k:
        xs, rcs, skin = np.ldexp(xs, k), np.ldexp(rcs, k), math.ldexp(skin, k)
    handle, nnz, info, bad = _core.arpy_neighbors(xs.T, rcs, skin, METHODS[method], int(bool(symmetric)))
    if info == STATUS["ERR_DEPTH"] and auto:
        # the AR tree's keys cannot hold this many levels: the uniform list can
        handle, nnz, info, bad = _core.arpy_neighbors(xs.T, rcs, skin, METHODS["cell"], int(bool(symmetric)))
    raise_for_info(info, bad, context="neighbor_list")
    return _collect(handle, n, nnz, bool(symmetric))


def _periodic_list(x: np.ndarray, rc: np.ndarray, box, method: str, symmetric: bool, skin: float) -> NeighborList:
    """Lists over the real particles of a periodic box, through ghost particles."""
    from .periodic import as_box, periodic_ghosts

    n = x.shape[0]
    lo, hi = as_box(box, x.shape[1])
    k = lengths_exponent([x, skin, lo, hi], [rc])     # images x +- (hi - lo) must not overflow
    if k:
        x, rc, lo, hi, skin = (np.ldexp(v, k) for v in (x, rc, lo, hi, skin))
        skin = float(skin)
    xg, src = periodic_ghosts(x, rc, (lo, hi), skin)
    ext = neighbor_list(np.concatenate([x, xg]), np.concatenate([rc, rc[src]]), method=method, skin=skin)
    i, j = ext.pairs(sort=False)             # i < j: a ghost is never i when j is real
    real_j = j < n
    ghost_j = ~real_j & (i < n)
    js = src[j[ghost_j] - n]
    # a pair across the boundary is found twice (p with q's image and q with
    # p's image); keep it once
    keep = i[ghost_j] < js
    pi = np.concatenate([i[real_j], i[ghost_j][keep]])
    pj = np.concatenate([j[real_j], js[keep]])
    return NeighborList.from_pairs(n, pi, pj, symmetric)
