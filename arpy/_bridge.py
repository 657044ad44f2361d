"""The one bridge to the Fortran core: every call of the f2py extension ``arpy._core`` is made here.

Each core routine the package uses has one thin function below, named as the routine without its
``arpy_`` prefix.  The conventions of the hand-over live here, once:

* **Positions.**  Python holds points as C-ordered float64 arrays (n, d); the core takes them as
  ``x(d, n)``.  They are handed over as the transposed view ``x.T`` (:func:`core_view`): a
  Fortran-ordered array of the right type, which f2py passes to the core as it is, without a copy
  (a C-ordered ``(d, n)`` copy would make f2py copy it again).  Points the core returns as (d, m)
  come back transposed to (m, d), C-ordered views of the core's arrays (:func:`from_core`).
* **Status codes.**  A routine reports failure in ``info`` (and often the 1-based index ``bad`` of
  the offending particle); each function raises the matching exception
  (:func:`arpy._errors.raise_for_info`, re-exported here) with the ``context`` its caller names.
  The searches whose callers react to a status first (a retry with another method, a rescaling,
  a fallback) return ``info`` and ``bad`` unchecked; their callers raise with
  :func:`raise_for_info`.
* **Range of lengths.**  The core computes with ``|coordinates| <= 2**RANGE_EXP`` and cutoffs in
  ``[2**-RANGE_EXP, 2**RANGE_EXP]``; :func:`core_exponent` and :func:`lengths_exponent` give the
  power of two that brings a problem's lengths into that range, :func:`scaled` multiplies by it
  (exactly: ``np.ldexp``).

``arpy._validate`` (the checks of user arrays at the door) and every module that needs the core call
the functions here; no other module imports ``arpy._core`` (``tests/test_layout.py`` checks it).
"""

from __future__ import annotations

import math
from typing import Any, overload

import numpy as np
import numpy.typing as npt

from . import _core
from ._codes import RANGE_EXP
from ._errors import raise_for_info

__all__ = ["core_exponent", "core_view", "from_core", "lengths_exponent", "raise_for_info", "scaled"]

# ---------------------------------------------------------------- conventions


def core_view(x: np.ndarray) -> np.ndarray:
    """Points (n, d) as the core takes them, (d, n): the transposed view of the C-ordered float64
    array (no copy when x is one already, as validated positions are)."""
    return np.ascontiguousarray(x, dtype=np.float64).T


def from_core(a: np.ndarray) -> np.ndarray:
    """Points the core returned as (d, m), as (m, d) C-ordered (the transposed view of f2py's
    Fortran-ordered result: no copy)."""
    return np.ascontiguousarray(a.T)


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


@overload
def scaled(k: int, v: float) -> float: ...
@overload
def scaled(k: int, v: np.ndarray) -> np.ndarray: ...
def scaled(k: int, v: Any) -> Any:
    """``v * 2**k`` (exact): an array by ``np.ldexp``, a number by ``math.ldexp``; v itself for k = 0."""
    if not k:
        return v
    return math.ldexp(v, k) if isinstance(v, (float, int)) else np.ldexp(v, k)


# ---------------------------------------------------------------- threads and memory
def set_threads(n: int) -> None:
    """The core's thread count (0: OpenMP's default)."""
    _core.arpy_set_threads(n)


def get_threads() -> int:
    """The number of threads of the core's next parallel loop."""
    return int(_core.arpy_get_threads()[0])


def set_parallel_thresholds(rows: int = 0, points: int = 0) -> tuple[int, int]:
    """The sizes from which the core's parallel loops run on more than one thread: loops over rows
    (lists, sorts, checks; default 20000) and over points (searches, pair potentials; default 2000).
    A value <= 0 restores the default.  Returns the sizes before, to be passed back.  For tests:
    results do not depend on the sizes, and small inputs then take the parallel branches."""
    old = _core.arpy_set_parallel_thresholds(int(rows), int(points))
    return int(old[0]), int(old[1])


def set_huge_pages(on: bool) -> bool:
    """Huge-page advice for the core's large arrays; returns the setting before."""
    return bool(_core.arpy_set_huge_pages(int(bool(on))))


# ---------------------------------------------------------------- checks
def column_extremes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest entry of each column of a C-ordered float64 array x (n >= 1, d)."""
    lo, hi = _core.arpy_column_extremes(core_view(x))
    return lo, hi


def box_owners(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, top: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The id of the first box (lo, hi: (m, d); ids (m,) int64) holding each point of x (n, d), -1 if
    none, the upper faces at ``top`` (d,) belonging to the boxes there: int64 (n,)."""
    return _core.arpy_box_owners(core_view(x), core_view(lo), core_view(hi), np.asarray(top, np.float64),
                                 np.asarray(ids, np.int64))


# ---------------------------------------------------------------- neighbour lists
def neighbors(x: np.ndarray, rc: np.ndarray, skin: float, method: int, symmetric: bool, in_cells: bool,
              order: np.ndarray, rule: int = 0) -> tuple[int, int, int, int]:
    """The free-space list of particles x (n, d) under the cutoff rule ``rule`` (a code of
    :data:`arpy._codes.RULES`) published in the core: (handle, entries, info, bad), info unchecked.
    ``in_cells``: the particles in the search's cell order, written into ``order``."""
    return _core.arpy_neighbors(core_view(x), rc, skin, method, rule, int(symmetric), int(in_cells), order)


def periodic_neighbors(x: np.ndarray, rc: np.ndarray, skin: float, method: int, symmetric: bool, lo: np.ndarray,
                       hi: np.ndarray, periodic: npt.ArrayLike, rule: int = 0) -> tuple[int, int, int, int]:
    """The list of particles x (n, d) in a box with periodic axes under the cutoff rule ``rule``:
    (handle, entries, info, bad), unchecked."""
    return _core.arpy_periodic_neighbors(core_view(x), rc, skin, method, rule, int(symmetric), lo, hi,
                                         np.asarray(periodic, np.int32))


def source_rows(x: np.ndarray, rc: np.ndarray, n: int, method: int, itself: bool) -> tuple[int, int, int, int]:
    """The rows of the first n sources of x (m, d) against all of them: (handle, entries, info, bad),
    unchecked."""
    return _core.arpy_source_rows(core_view(x), rc, n, method, int(bool(itself)))


def crowding_counts(x: np.ndarray, step: int, lo: np.ndarray, g: float, nc: list[int]) -> np.ndarray:
    """Of each sampled particle ``x[::step]`` (x (n, d)), the number of the other sampled particles in
    the ``3**d`` cells around its own on the grid of cells of edge g from lo, nc[a] along axis a
    (particles outside the grid in its border cells): int64 (ns,)."""
    block, info = _core.arpy_crowding_counts(core_view(x), step, lo, g, np.asarray(nc, np.int32))
    raise_for_info(info, 0, context="auto_work")
    return block


def auto_terms(x: np.ndarray, rc: np.ndarray, skin: float, knob: list[float], rule: int = 0) -> np.ndarray:
    """The six statistics of arpy.lists.auto.auto_terms under the rule code ``rule``, computed by the
    core (arpy_crowding.auto_terms) with its sampling constants ``knob`` (9): float64 (6,)."""
    w, info = _core.arpy_auto_terms(core_view(x), rc, skin, np.asarray(knob, np.float64), rule)
    raise_for_info(info, 0, context="auto_work")
    return w


def cross_brute(xq: np.ndarray, rq: np.ndarray, xr: np.ndarray, rr: np.ndarray,
                rule: int = 0) -> tuple[int, int, int, int]:
    """The cross list of query points xq (m, d) against xr (n, d) under the cutoff rule ``rule`` by
    testing every pair: (handle, entries, info, bad), unchecked."""
    return _core.arpy_cross_brute(core_view(xq), rq, core_view(xr), rr, rule)


def build_only(x: np.ndarray, rc: np.ndarray, method: int) -> int:
    """Build a search structure over x (n, d) and drop it (a benchmark's timing); info unchecked."""
    return int(_core.arpy_build_only(core_view(x), rc, method)[0])


def result_take(handle: int, n: int, nnz: int, context: str = "neighbor_list") -> tuple[np.ndarray, np.ndarray]:
    """The list the core published under ``handle`` (freed there): (offsets (n + 1,) int64, indices
    (nnz,) int32).  The arrays are allocated here, uninitialised: the core writes every entry (f2py
    would zero them first); on any failure the core's copy is freed."""
    try:
        offsets, indices = np.empty(max(n, 0) + 1, np.int64), np.empty(max(nnz, 0), np.int32)
        info = _core.arpy_result_take(handle, offsets, indices)
    except BaseException:
        _core.arpy_result_free(handle)
        raise
    raise_for_info(info, context=context)
    return offsets, indices


def rows_sorted(offsets: np.ndarray, indices: np.ndarray, rank: np.ndarray, context: str) -> bool:
    """Whether every row of a CSR list is in ascending ``rank[column]`` order already."""
    done, info, bad = _core.arpy_rows_sorted(offsets, indices, rank)
    raise_for_info(info, bad, context=context)
    return bool(done)


def sort_rows(offsets: np.ndarray, indices: np.ndarray, rank: np.ndarray, context: str) -> np.ndarray:
    """Each row of a CSR list sorted by ``rank[column]``, in place in ``indices`` (give a copy to keep
    the list); returns the sorted indices."""
    idx, info, bad = _core.arpy_sort_rows(offsets, indices, rank)
    raise_for_info(info, bad, context=context)
    return idx


def filter_rows(xq: np.ndarray, rq: np.ndarray, xs: np.ndarray, rs: np.ndarray, offsets: np.ndarray,
                indices: np.ndarray, context: str) -> tuple[np.ndarray, np.ndarray]:
    """The entries of a CSR list (rows: points xq (m, d) with cutoffs rq; columns: sources xs, rs) that
    the min rule keeps at these positions: (offsets, indices; only the first offsets[-1] meaningful)."""
    off, idx, info, bad = _core.arpy_filter_rows(core_view(xq), rq, core_view(xs), rs, offsets, indices)
    raise_for_info(info, bad, context=context)
    return off, idx


def cache_order(x: np.ndarray, lo: np.ndarray, s: float, context: str = "cache_order") -> np.ndarray:
    """The Morton order of points x (n, d) on a grid of cells 1 / s wide from lo: a permutation, int32."""
    perm, info = _core.arpy_cache_order(core_view(x), lo, s)
    raise_for_info(info, 0, context=context)
    return perm


# ---------------------------------------------------------------- the AR cell tree
def ar_create(x: np.ndarray, rc: np.ndarray, skin: float, has_domain: int, lo: np.ndarray, hi: np.ndarray,
              context: str = "ARCellList") -> tuple[int, int, int, int, float]:
    """Build an AR tree of particles x (n, d) in the core: (handle, leaves, keys, deepest level, root edge)."""
    handle, nleaf, nkey, maxlevel, dm, info, bad = _core.arpy_ar_create(core_view(x), rc, skin, has_domain, lo, hi)
    raise_for_info(info, bad, context=context)
    return handle, nleaf, nkey, maxlevel, dm


def ar_tables(handle: int, n: int, nleaf: int, nkey: int, context: str = "ARCellList") -> tuple[np.ndarray, ...]:
    """The tree's tables: (perm, level, leaf_key, leaf_first, leaf_last, keys, first, last, finer, lo)."""
    perm, level, leaf_key, leaf_first, leaf_last, keys, first, last, finer, lo, info = _core.arpy_ar_tables(
        handle, n, nleaf, nkey)
    raise_for_info(info, context=context)
    return perm, level, leaf_key, leaf_first, leaf_last, keys, first, last, finer, lo


def ar_free(handle: int) -> None:
    """Free a tree of the core."""
    _core.arpy_ar_free(handle)


def ar_ops(handle: int, op: int, pts: np.ndarray, k: int, keys: np.ndarray,
           context: str = "ARCellList") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cell operation ``op`` (Op1-Op5) on cells ``keys`` or points pts (m, d) at level k:
    (keys, out, nbr, cnt)."""
    keys, out, nbr, cnt, info = _core.arpy_ar_ops(handle, op, core_view(pts), k, keys)
    raise_for_info(info, context=context)
    return keys, out, nbr, cnt


def ar_verlet(handle: int, mode: int, bits: np.ndarray, context: str = "verlet_list") -> tuple[int, int]:
    """The tree's Verlet list, published in the core: (handle, entries)."""
    handle, nnz, info = _core.arpy_ar_verlet(handle, mode, bits)
    raise_for_info(info, context=context)
    return handle, nnz


def ar_cross(handle: int, xq: np.ndarray, rq: np.ndarray) -> tuple[int, int, int, int]:
    """The cross list of query points xq (m, d) against the tree, published in the core: (handle,
    entries, info, bad), unchecked (the caller names the query)."""
    return _core.arpy_ar_cross(handle, core_view(xq), rq)


# ---------------------------------------------------------------- DC-PSE
def dcpse(src_x: np.ndarray, a: np.ndarray, col_x: np.ndarray, col_eps: np.ndarray, offsets: np.ndarray,
          indices: np.ndarray, order: int, c: float, form: int, kinds: npt.ArrayLike, alphas: npt.ArrayLike,
          max_cond: float, context: str = "DCPSE") -> tuple[np.ndarray, ...]:
    """DC-PSE weights of sources src_x (n, d) at points col_x (m, d), every operator of ``kinds`` with
    multi-indices ``alphas`` (ops, d): (data, diag, neighbours, rcond, status)."""
    data, diag, nnb, rcond, status, info, bad = _core.arpy_dcpse(
        core_view(src_x), a, core_view(col_x), col_eps, offsets, indices, order, c, form,
        np.asarray(kinds, np.int32), np.asarray(alphas, np.int32).T.copy(order="F"), max_cond)
    raise_for_info(info, bad, context=context)
    return data, diag, nnb, rcond, status


# ---------------------------------------------------------------- periodic images and nearest points
def images_count(x: np.ndarray, r: np.ndarray, lo: np.ndarray, hi: np.ndarray, periodic: npt.ArrayLike) -> int:
    """How many periodic images of particles x (n, d) with reach r :func:`images` makes."""
    return int(_core.arpy_images_count(core_view(x), r, lo, hi, np.asarray(periodic, np.int32)))


def images(x: np.ndarray, r: np.ndarray, lo: np.ndarray, hi: np.ndarray, periodic: npt.ArrayLike, m: int,
           context: str = "periodic_ghosts") -> tuple[np.ndarray, np.ndarray]:
    """The m periodic images of particles x (n, d): (positions (m, d), their particles, int32)."""
    xg, src, info = _core.arpy_images(core_view(x), r, lo, hi, np.asarray(periodic, np.int32), m)
    raise_for_info(info, context=context)
    return from_core(xg), src


def knn(x: np.ndarray, y: np.ndarray, k: int, period: np.ndarray,
        context: str = "nearest") -> tuple[np.ndarray, np.ndarray]:
    """The k points of x (n, d) nearest each point of y (m, d): (distances (m, k), indices (m, k))."""
    dk, ik, info = _core.arpy_knn(core_view(x), core_view(y), k, period)
    raise_for_info(info, context=context)
    return dk.T, ik.T


def min_distance(x: np.ndarray, period: np.ndarray, context: str = "h_min") -> float:
    """The smallest distance between two of the points x (n, d)."""
    dmin, info = _core.arpy_min_distance(core_view(x), period)
    raise_for_info(info, context=context)
    return float(dmin)


# ---------------------------------------------------------------- self-organization and resolution
def exact_sum(v: np.ndarray) -> tuple[float, bool]:
    """The exactly rounded sum of the float64 values v (n,), and whether the core could form it."""
    s, ok = _core.arpy_exact_sum(v)
    return float(s), bool(ok)


def exact_partials(v: np.ndarray) -> tuple[np.ndarray, bool]:
    """Nonoverlapping doubles (m,), m <= 64, whose exact sum is that of the float64 values v (n,), and
    whether the core could form them (not: a term not finite, or a partial sum overflowing)."""
    p, m, ok = _core.arpy_exact_partials(v)
    return p[:m].copy(), bool(ok)


def pair_potential(kind: int, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """V(r) and V'(r) of the potential ``kind`` at the distances r (n,)."""
    v, dv = _core.arpy_pair_potential(kind, r)
    return v, dv


def so_energy(x: np.ndarray, D: np.ndarray, grad_D: np.ndarray, period: np.ndarray, offsets: np.ndarray,
              indices: np.ndarray, kind: int, vshift: float, gradient: bool,
              context: str = "energy") -> tuple[np.ndarray, np.ndarray]:
    """Per-particle pseudo-force energies of particles x (n, d) over a full list, and their gradient (n, d)."""
    e, g, info, bad = _core.arpy_so_energy(core_view(x), D, core_view(grad_D), period, offsets, indices, kind,
                                           vshift, int(bool(gradient)))
    raise_for_info(info, bad, context=context)
    return e, from_core(g)


def so_ratios(x: np.ndarray, D: np.ndarray, period: np.ndarray, offsets: np.ndarray, indices: np.ndarray,
              context: str = "self_organize") -> np.ndarray:
    """Per list entry of particles x (n, d), the distance over D_pq."""
    rho, info, bad = _core.arpy_so_ratios(core_view(x), D, period, offsets, indices)
    raise_for_info(info, bad, context=context)
    return rho


def so_fuse(x: np.ndarray, period: np.ndarray, a: np.ndarray, b: np.ndarray,
            context: str = "self_organize") -> np.ndarray:
    """Particles x (n, d) after fusing each pair (a_i, b_i) at its midpoint (minimum image): (n, d)."""
    xe, _, _, info, bad = _core.arpy_so_fuse(core_view(x), period, a, b)
    raise_for_info(info, bad, context=context)
    return from_core(xe)


def grade(x: np.ndarray, target: np.ndarray, sources: np.ndarray, source_target: np.ndarray, rstar: float,
          context: str = "graded_resolution") -> np.ndarray:
    """Eq. 2.9 at the particles x (n, d) over the sources (m, d) with their targets."""
    D, info, bad = _core.arpy_grade(core_view(x), target, core_view(sources), source_target, rstar)
    raise_for_info(info, bad, context=context)
    return D


def shepard(y: np.ndarray, x: np.ndarray, rc: np.ndarray, D: np.ndarray, offsets: np.ndarray, indices: np.ndarray,
            context: str = "SampledResolution") -> tuple[np.ndarray, np.ndarray]:
    """Shepard interpolation of D at the points y (m, d) from the particles x (n, d) reaching them:
    (values, reached (m,) int32)."""
    out, ok, info, bad = _core.arpy_shepard(core_view(y), core_view(x), rc, D, offsets, indices)
    raise_for_info(info, bad, context=context)
    return out, ok
