"""Neighbour lists: the public entry point and the CSR container.

Particles p and q are neighbours iff ``|x_p - x_q| <= min(rc_p, rc_q) + skin``
(the adaptive-resolution "gather" rule; with one cutoff it is the usual
fixed-radius rule).  A particle is never its own neighbour; coincident
particles are neighbours of each other.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

from . import _core
from ._codes import METHODS, STATUS
from ._errors import raise_for_info
from ._validate import as_cutoffs, as_positions, column_extremes, core_exponent, lengths_exponent
from .domain import Domain

__all__ = ["METHODS", "NeighborList", "cache_order", "collect_list", "neighbor_list", "neighbor_list_in_cell_order",
           "pair_order"]

#: method="auto" uses the AR cell list from this resolution span max(rc)/min(rc)
#: on (the break-even against the uniform cell list measured at N = 1e6 is
#: 1.1, higher at smaller N when the power-of-two levels give cells near
#: 2 r_c; see benchmarks/ar_cell_lists.py), the uniform cell list below it.
AUTO_AR_SPAN = 3.0



def pair_order(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """The permutation that sorts distinct pairs (i, j) lexicographically, 0 <= j < n: one sort of
    the int64 keys i n + j (the order of ``np.lexsort((j, i))``, at less than half its cost)."""
    return np.argsort(np.asarray(i, np.int64) * np.int64(max(n, 1)) + j, kind="stable")


def check_layout(nl: "NeighborList", n_cols: int, context: str) -> None:
    """Raise the core's "inconsistent neighbour list" error (with ``context``) unless the offsets
    start at 0, never decrease and end at the number of entries, and every index is in [0, n_cols)."""
    off, idx = nl.offsets, nl.indices
    if off[0] != 0 or off[-1] != idx.size or np.any(np.diff(off) < 0) or (
            idx.size and not 0 <= idx.min() <= idx.max() < n_cols):
        raise_for_info(STATUS["ERR_LIST"], context=context)


@dataclass(frozen=True, eq=False)
class NeighborList:
    """Neighbour lists in compressed sparse row (CSR) form.

    Attributes
    ----------
    offsets : int64 array, shape (n + 1,)
        Row ``p`` is ``indices[offsets[p]:offsets[p + 1]]``.
    indices : int32 array, shape (len(self),)
        Neighbour indices (0-based).  Within a row the order is unspecified.
    symmetric : bool
        True: each unordered pair is stored once, in the row of either of its
        particles.  False: each pair is stored in both rows.
    n_ref : int or None
        None for a list within one particle set.  For a cross-set list (rows =
        query points, indices = particles of a reference set) the size of the
        reference set; then ``symmetric`` is False.

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x = np.array([[0.0, 0.0], [0.1, 0.0], [0.5, 0.0]])
    >>> nl = arpy.neighbor_list(x, 0.2)
    >>> nl
    NeighborList(n=3, entries=1, symmetric)
    >>> nl.pairs()
    (array([0]), array([1]))
    >>> nl.counts().tolist()
    [1, 0, 0]
    >>> nl.to_sparse(x).toarray()
    array([[0. , 0.1, 0. ],
           [0.1, 0. , 0. ],
           [0. , 0. , 0. ]])
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
        order = pair_order(i, j, self.n_ref if self.n_ref is not None else self.n)
        return i[order], j[order]

    def _offsets(self, x: np.ndarray, x_ref: np.ndarray | None) -> np.ndarray:
        """x_q - x_p of every stored entry (row p, index q), shape (len(self), d), not wrapped."""
        if self.n_ref is not None and x_ref is None:
            raise ValueError("a cross list needs x_ref, the reference positions, for its vectors")
        xs = as_positions(x)
        xr = as_positions(x_ref) if x_ref is not None and self.n_ref is not None else xs
        if xs.shape[0] != self.n or (self.n_ref is not None and xr.shape[0] != self.n_ref):
            raise ValueError(f"positions must have {self.n} rows (and x_ref {self.n_ref}) for this list, got "
                             f"{xs.shape[0]}" + ("" if x_ref is None else f" and {xr.shape[0]}"))
        return xr[self.indices] - xs[self.rows()]

    def vectors(self, x: np.ndarray, x_ref: np.ndarray | None = None, domain: Domain | None = None) -> np.ndarray:
        """The displacement x_q - x_p of every stored entry (row p, index q), in the list's order
        (``rows()``, ``indices``), by the minimum image along the periodic axes of ``domain``.

        Parameters
        ----------
        x : array (n, d)
            Positions of the rows' particles.
        x_ref : array (n_ref, d), optional
            For a cross list, the reference particles' positions.
        domain : Domain, optional
            Where the particles live (periodic axes: minimum image).

        Returns
        -------
        array (len(self), d), float64

        Examples
        --------
        >>> import numpy as np, arpy
        >>> x = np.array([[0.05, 0.5], [0.95, 0.5]])
        >>> box = arpy.Domain([1.0, 1.0], periodic=True)
        >>> nl = arpy.neighbor_list(x, 0.2, domain=box, symmetric=False)     # rows 0 and 1
        >>> nl.vectors(x, domain=box).round(12).tolist(), nl.shifts(x, domain=box).tolist()
        ([[-0.1, 0.0], [0.1, 0.0]], [[-1, 0], [1, 0]])
        """
        e = self._offsets(x, x_ref)
        if domain is not None:
            e -= domain.whole_periods(e)
        return e

    def distances(self, x: np.ndarray, x_ref: np.ndarray | None = None, domain: Domain | None = None
                  ) -> np.ndarray:
        """``|x_q - x_p|`` of every stored entry, shape (len(self),) (see :meth:`vectors`)."""
        e = self.vectors(x, x_ref, domain)
        return np.sqrt((e * e).sum(axis=1))

    def shifts(self, x: np.ndarray, x_ref: np.ndarray | None = None, domain: Domain | None = None) -> np.ndarray:
        """The periodic shift S of every stored entry, int64 (len(self), d): the displacement of
        :meth:`vectors` is ``x_q - x_p + S * edge`` (S = 0 along non-periodic axes and in free space),
        as in the i, j, S triplets of ASE-style neighbour lists."""
        e = self._offsets(x, x_ref)
        if domain is None or not domain.for_dim(e.shape[1]).any_periodic:
            return np.zeros(e.shape, np.int64)
        per = domain.for_dim(e.shape[1]).period
        return np.rint(-domain.whole_periods(e) / np.where(per > 0, per, 1.0)).astype(np.int64)

    def to_sparse(self, x: np.ndarray | None = None, x_ref: np.ndarray | None = None,
                  domain: Domain | None = None) -> sp.csr_matrix:
        """The list as a ``scipy.sparse.csr_matrix``, like ``cKDTree.sparse_distance_matrix``.

        Entry (p, q) for every neighbour pair; a list within one set gives both (p, q) and (q, p),
        symmetric or full alike, shape (n, n); a cross list gives (query, reference), shape
        (n, n_ref).

        Parameters
        ----------
        x : array (n, d), optional
            Positions of the rows' particles: the values are the distances ``|x_p - x_q|`` (by the
            minimum image along the periodic axes of ``domain``; a pair at distance 0 is an explicit
            zero).  None: the values are 1.
        x_ref : array (n_ref, d), optional
            For a cross list, the reference particles' positions (with ``x``).
        domain : Domain, optional
            Where the particles live (periodic axes: minimum image).

        Returns
        -------
        scipy.sparse.csr_matrix
        """
        import scipy.sparse as sp

        rows, cols = self.rows(), self.indices.astype(np.int64)
        values = np.ones(rows.size) if x is None else self.distances(x, x_ref, domain)
        if self.n_ref is None and self.symmetric:
            rows, cols, values = (np.concatenate([rows, cols]), np.concatenate([cols, rows]),
                                  np.concatenate([values, values]))
        shape = (self.n, self.n if self.n_ref is None else self.n_ref)
        mat = sp.csr_matrix((values, (rows, cols)), shape=shape)
        mat.sort_indices()
        return mat

    def canonical(self) -> "NeighborList":
        """The same entries in the sorted layout: each row ascending, and in a symmetric list each
        pair in the row of its smaller index (the layout of :meth:`from_pairs`).  Lists built by
        different methods, thread counts or searches have one canonical form."""
        if self.symmetric:
            return NeighborList.from_pairs(self.n, *self.pairs(sort=False), symmetric=True)
        return self.ordered_by(np.arange(self.n if self.n_ref is None else self.n_ref, dtype=np.int64))

    def ordered_by(self, rank: np.ndarray) -> "NeighborList":
        """The same entries with each row sorted by ``rank[column]`` (distinct int64 values, one per
        column index, e.g. the particles' keys): sums over a row in that order do not depend on the
        method or layout that built the list."""
        rank = np.ascontiguousarray(rank, dtype=np.int64)
        done, info, bad = _core.arpy_rows_sorted(self.offsets, self.indices, rank)
        raise_for_info(info, bad, context="NeighborList.ordered_by")
        if done:                                  # (e.g. the rows of a cross list, ascending)
            return NeighborList(self.offsets, self.indices, self.symmetric, n_ref=self.n_ref)
        # the core sorts the array it is given in place: give it a copy, this list stays as it is
        idx, info, bad = _core.arpy_sort_rows(self.offsets, self.indices.copy(), rank)
        raise_for_info(info, bad, context="NeighborList.ordered_by")
        return NeighborList(self.offsets, idx, self.symmetric, n_ref=self.n_ref)

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
        order = pair_order(a, b, n)
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(a, minlength=n), out=offsets[1:])
        return cls(offsets, b[order].astype(np.int32), bool(symmetric))

    def __repr__(self) -> str:
        kind = f"cross, n_ref={self.n_ref}" if self.cross else ("symmetric" if self.symmetric else "full")
        return f"NeighborList(n={self.n}, entries={len(self)}, {kind})"


def collect_list(handle: int, n: int, nnz: int, symmetric: bool) -> NeighborList:
    """Fetch the list the core has published under ``handle`` (and free it).  The arrays are
    allocated here, uninitialised: the core writes every entry (f2py would zero them first)."""
    try:
        offsets, indices = np.empty(max(n, 0) + 1, np.int64), np.empty(max(nnz, 0), np.int32)
        info = _core.arpy_result_take(handle, offsets, indices)
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
    domain: Domain | None = None,
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
    domain : Domain or None
        Where the particles live (default: free space).  Along periodic axes the
        lists hold the pairs by the minimum image; the particles must lie inside
        the box along those axes, and max(rc) + skin must be below half the
        smallest periodic edge.  The uniform list wraps its grid around the
        box (when that leaves 3 cells or more along every periodic axis);
        the AR list queries the periodic images of the particles near the
        faces against the particles' own tree; brute force (and a uniform
        grid too coarse to wrap) searches the particles with their images
        (:func:`arpy.periodic_ghosts`).  Walls do not change the lists.

    Returns
    -------
    NeighborList
        CSR lists; ``pairs()`` gives the sorted unordered pairs.

    Raises
    ------
    ValueError, TypeError
        On bad shapes, dtypes, non-finite positions or non-positive cutoffs.

    Examples
    --------
    Uniform random points with one cutoff, then cutoffs that differ by a factor 10:

    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((1000, 2))
    >>> nl = arpy.neighbor_list(x, 0.05)
    >>> i, j = nl.pairs()
    >>> bool(np.all(i < j)), len(i) == len(nl)
    (True, True)
    >>> full = arpy.neighbor_list(x, 0.05, symmetric=False)
    >>> len(full) == 2 * len(nl)
    True
    >>> rc = np.where(x[:, 0] < 0.5, 0.01, 0.1)
    >>> ar = arpy.neighbor_list(x, rc, method="ar")
    >>> brute = arpy.neighbor_list(x, rc, method="brute")
    >>> all(np.array_equal(a, b) for a, b in zip(ar.pairs(), brute.pairs()))
    True

    In a periodic unit square, pairs across the edges are found by the minimum image:

    >>> torus = arpy.Domain([1.0, 1.0], periodic=True)
    >>> arpy.neighbor_list(np.array([[0.01, 0.5], [0.99, 0.5]]), 0.05, domain=torus).pairs()
    (array([0]), array([1]))
    """
    xs, rcs, skin = list_input(x, rc, method, skin, "neighbor_list")
    n = xs.shape[0]
    if n == 0:
        return NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), bool(symmetric))
    method, auto = resolve_method(method, rcs)
    # the periodic box, if any (walls do not change the lists)
    pbox = domain if domain is not None and domain.for_dim(xs.shape[1]).any_periodic else None
    sym = int(bool(symmetric))
    if pbox is None:
        return free_list(xs, rcs, skin, method, auto, bool(symmetric), in_cells=False)[0]
    # one pass for the extremes of the positions (per axis) and of the cutoffs: they give the
    # scaling and the checks of the box
    x_min, x_max = column_extremes(xs)
    r_ext = np.array([rcs.min(), rcs.max()])
    k = lengths_exponent([x_min, x_max, skin, pbox.lo, pbox.hi], [r_ext])
    if k:                      # (the images x +- (hi - lo) must not overflow either)
        xs, rcs, skin = np.ldexp(xs, k), np.ldexp(rcs, k), math.ldexp(skin, k)
        x_min, x_max, r_ext = np.ldexp(x_min, k), np.ldexp(x_max, k), np.ldexp(r_ext, k)
        pbox = pbox.scaled(k)
    box = pbox.for_dim(xs.shape[1])
    # the particles in the box, the box large enough
    box.check_images(xs, rcs, skin, extremes=(x_min, x_max, float(r_ext[0]), float(r_ext[1])))
    lo, hi = box.lo, box.hi
    assert lo is not None and hi is not None
    handle, nnz = searched(
        lambda code: _core.arpy_periodic_neighbors(xs.T, rcs, skin, code, sym, lo, hi,
                                                   np.asarray(box.periodic, np.int32)),
        method, auto, "neighbor_list")
    return collect_list(handle, n, nnz, bool(symmetric))


def neighbor_list_in_cell_order(
    x: np.ndarray,
    rc: float | np.ndarray,
    *,
    method: str = "cell",
    symmetric: bool = True,
    skin: float = 0.0,
) -> tuple[np.ndarray, NeighborList]:
    """The particles' cell order and their neighbour list in it (free space).

    The search sorts the particles into its cells anyway (``"cell"``: the uniform grid's cells;
    ``"ar"``: the AR tree's levels and cells, :attr:`ARCellList.order`); :func:`neighbor_list` then
    puts every row back into input order and renames every entry, a pass that writes the list at
    random.  This function skips that pass: it returns the cell order and the list of the
    particles in that order, so a caller who keeps its particles sorted this way reads and writes
    memory in order.  Particles already in the returned order give that order back unchanged (the
    identity), and their list in one sequential pass.

    Parameters
    ----------
    x, rc, method, symmetric, skin
        As for :func:`neighbor_list` (``"brute"`` keeps the input order).

    Returns
    -------
    order : int64 array, shape (n,)
        ``x[order]`` are the particles in cell order; reorder every per-particle array the same
        way.  ``np.argsort(order)`` maps back.
    nl : NeighborList
        The list of ``x[order]``: row ``a`` and entry ``a`` mean particle ``order[a]`` of the input.

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((1000, 2))
    >>> order, nl = arpy.neighbor_list_in_cell_order(x, 0.05)
    >>> x_sorted = x[order]
    >>> same = arpy.neighbor_list(x_sorted, 0.05)
    >>> all(np.array_equal(a, b) for a, b in zip(nl.pairs(), same.pairs()))
    True
    >>> bool(np.array_equal(arpy.neighbor_list_in_cell_order(x_sorted, 0.05)[0], np.arange(1000)))
    True
    """
    xs, rcs, skin = list_input(x, rc, method, skin, "neighbor_list_in_cell_order")
    n = xs.shape[0]
    if n == 0:
        return np.zeros(0, np.int64), NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), bool(symmetric))
    method, auto = resolve_method(method, rcs)
    nl, order = free_list(xs, rcs, skin, method, auto, bool(symmetric), in_cells=True)
    assert order is not None
    return order, nl


def list_input(x: np.ndarray, rc: float | np.ndarray, method: str, skin: float,
               context: str) -> tuple[np.ndarray, np.ndarray, float]:
    """(positions (n, d), cutoffs (n,), skin) of a list search, checked; ValueError on a bad method
    or skin (the positions and cutoffs are checked by as_positions and as_cutoffs)."""
    if method not in METHODS and method != "auto":
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(METHODS) + ['auto']}")
    xs = as_positions(x)
    rcs = as_cutoffs(rc, xs.shape[0])
    skin = float(skin)
    if not (np.isfinite(skin) and skin >= 0.0):
        raise ValueError(f"{context}: skin must be a finite number >= 0, got {skin}")
    return xs, rcs, skin


def free_list(xs: np.ndarray, rcs: np.ndarray, skin: float, method: str, auto: bool, symmetric: bool,
              in_cells: bool) -> tuple[NeighborList, np.ndarray | None]:
    """(the free-space list of checked particles, None) or, ``in_cells``, (the list of the particles
    in the search's cell order, that order)."""
    order = np.empty(xs.shape[0] if in_cells else 0, np.int64)         # (written by the core)

    def run(xk: np.ndarray, rk: np.ndarray, sk: float, code: int) -> tuple[int, int, int, int]:
        return _core.arpy_neighbors(xk.T, rk, sk, code, int(symmetric), int(in_cells), order)

    handle, nnz = searched_in_range(run, xs, rcs, skin, method, auto, "neighbor_list")
    nl = collect_list(handle, xs.shape[0], nnz, symmetric)
    return nl, (order if in_cells else None)


def resolve_method(method: str, rcs: np.ndarray) -> tuple[str, bool]:
    """(the search method, whether it was chosen by "auto"): "auto" is "ar" where the cutoffs rcs
    span a factor of AUTO_AR_SPAN or more, else "cell"."""
    if method != "auto":
        return method, False
    with np.errstate(over="ignore"):
        span = rcs.max() / rcs.min() if np.all(rcs > 0) and np.all(np.isfinite(rcs)) else 1.0
    return ("ar" if span >= AUTO_AR_SPAN else "cell"), True


def searched(search: Callable[[int], tuple[int, int, int, int]], method: str, auto: bool,
             context: str, on_range: Callable[[], tuple[int, int]] | None = None) -> tuple[int, int]:
    """(handle, entries) of the list ``search(method code)`` publishes; a method chosen by "auto"
    whose AR tree cannot hold the cutoffs' levels is retried with the uniform list.  When the
    core reports lengths out of its range, ``on_range()`` answers instead, if given."""
    handle, nnz, info, bad = search(METHODS[method])
    if info == STATUS["ERR_DEPTH"] and auto:
        # the AR tree's keys cannot hold this many levels: the uniform list can
        handle, nnz, info, bad = search(METHODS["cell"])
    if info == STATUS["ERR_RANGE"] and on_range is not None:
        return on_range()
    raise_for_info(info, bad, context=context)
    return handle, nnz


def searched_in_range(run: Callable[[np.ndarray, np.ndarray, float, int], tuple[int, int, int, int]],
                      xs: np.ndarray, rcs: np.ndarray, skin: float, method: str, auto: bool,
                      context: str) -> tuple[int, int]:
    """:func:`searched` for ``run(positions, cutoffs, skin, method code)`` on the lengths as they
    are: the core checks their range in its first pass over the particles, so the scaling by a
    power of two (:func:`lengths_exponent`, two more passes) happens only when it reports them out
    of it."""
    def rescaled() -> tuple[int, int]:
        k = lengths_exponent([xs, skin], [rcs])
        if not k:                                        # (the core's range error stands)
            return searched(lambda code: run(xs, rcs, skin, code), method, auto, context)
        xk, rk, sk = np.ldexp(xs, k), np.ldexp(rcs, k), math.ldexp(skin, k)
        return searched(lambda code: run(xk, rk, sk, code), method, auto, context)

    return searched(lambda code: run(xs, rcs, skin, code), method, auto, context, on_range=rescaled)


#: Bits per axis of the cache order's grid (2D, 3D): the AR tree's deepest level, 60-bit codes.
CACHE_ORDER_BITS = {2: 30, 3: 20}


def cache_order(x: np.ndarray, *, domain: Domain | None = None) -> np.ndarray:
    """The permutation that puts particles in cache order: along the Morton (Z-order) curve.

    A cube over the particles (the box of a bounded ``domain``, else their bounding box, with
    the longest edge on every axis) is cut into 2**30 (2D) or 2**20 (3D) cells per axis, and
    the particles are sorted by the Morton code of their cell (axis 1 the most significant
    bit), ties by index.  Particles next to each other in this order are close in space, so
    neighbour lists, DC-PSE assembly and the loops over particle pairs read the data of a
    particle's neighbours from nearby memory instead of from anywhere in the arrays.

    Parameters
    ----------
    x : array, shape (n, d), d = 2 or 3
        Particle positions; finite.
    domain : Domain or None
        Its box, if it has one, anchors the curve (points outside it go to the nearest cell).

    Returns
    -------
    perm : int64 array, shape (n,)
        ``x[perm]`` is in cache order; reorder every per-particle array the same way.
        ``np.argsort(perm)`` maps back.

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((10_000, 2))
    >>> perm = arpy.cache_order(x)
    >>> steps = np.linalg.norm(np.diff(x[perm], axis=0), axis=1)
    >>> bool(np.median(steps) < 0.02 < np.median(np.linalg.norm(np.diff(x, axis=0), axis=1)))
    True
    """
    xs = as_positions(x)
    n, d = xs.shape
    if n < 2:
        return np.arange(n, dtype=np.int64)
    mins, maxs = column_extremes(xs)                        # (NaN and Inf show in them)
    if not (np.all(np.isfinite(mins)) and np.all(np.isfinite(maxs))):
        bad = int(np.flatnonzero(~np.all(np.isfinite(xs), axis=1))[0])
        raise ValueError(f"cache_order: position of particle {bad} is not finite (NaN or Inf)")
    box = domain.for_dim(d) if domain is not None and domain.bounded else None
    if box is not None:
        assert box.lo is not None and box.hi is not None
        lo, hi = np.asarray(box.lo, np.float64), np.asarray(box.hi, np.float64)
    else:
        lo, hi = mins, maxs
    half = float(np.max(hi / 2 - lo / 2))           # half the cube's edge (never overflows)
    if not half > 0:
        return np.arange(n, dtype=np.int64)
    # lengths brought into the core's range by a power of two (exact): edge and cells finite
    k = core_exponent(float(np.abs(np.concatenate([mins, maxs, lo, hi])).max()), half)
    if k:
        xs, lo, hi = np.ldexp(xs, k), np.ldexp(lo, k), np.ldexp(hi, k)
    edge = float(np.max(hi - lo))
    perm, info = _core.arpy_cache_order(xs.T, lo, math.ldexp(1.0, CACHE_ORDER_BITS[d]) / edge)
    raise_for_info(info, 0, context="cache_order")
    return perm.astype(np.int64)
