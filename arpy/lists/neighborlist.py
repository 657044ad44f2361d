"""The neighbour list container: :class:`NeighborList`, compressed sparse rows (offsets, indices).

Particles p and q are neighbours iff ``|x_p - x_q| <= min(rc_p, rc_q) + skin``
(the adaptive-resolution "gather" rule; with one cutoff it is the usual
fixed-radius rule).  A particle is never its own neighbour; coincident
particles are neighbours of each other.  The searches that fill the container are in
:mod:`arpy.lists.search` and :mod:`arpy.lists.ar`; :func:`collect_list` fetches a list the core
has published.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

from .. import _bridge
from .._bridge import raise_for_info
from .._codes import STATUS
from .._validate import as_positions, check_index, is_integer
from ..domain import Domain, as_domain

__all__ = ["NeighborList", "collect_list", "pair_order"]


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
        """Indices stored in row ``p`` (a view), 0 <= p < n.

        Raises
        ------
        IndexError
            For p outside [0, n).  A negative p is refused, not counted from the end: a row index
            computed wrongly would otherwise give another particle's row (``-2``: row n - 2) or an
            empty one (``-1``).
        TypeError
            For a p that is not an integer (Python or NumPy; a bool is not).
        """
        p = check_index("p", p, self.n)
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
        dom = as_domain(domain, e.shape[1])
        if dom.any_periodic:
            e -= dom.whole_periods(e)
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
        dom = as_domain(domain, e.shape[1])
        if not dom.any_periodic:
            return np.zeros(e.shape, np.int64)
        per = dom.period
        return np.rint(-dom.whole_periods(e) / np.where(per > 0, per, 1.0)).astype(np.int64)

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
        # (rows already in that order, e.g. the rows of a cross list, ascending: the list as it is)
        if _bridge.rows_sorted(self.offsets, self.indices, rank, context="NeighborList.ordered_by"):
            return NeighborList(self.offsets, self.indices, self.symmetric, n_ref=self.n_ref)
        # the core sorts the array it is given in place: give it a copy, this list stays as it is
        idx = _bridge.sort_rows(self.offsets, self.indices.copy(), rank, context="NeighborList.ordered_by")
        return NeighborList(self.offsets, idx, self.symmetric, n_ref=self.n_ref)

    @classmethod
    def from_pairs(cls, n: int, i: np.ndarray, j: np.ndarray, symmetric: bool = True) -> "NeighborList":
        """Build the list of n particles from unordered pairs (i, j), each given once.

        Symmetric: pair (i, j) is stored in row min(i, j).  Full: in both rows.
        Rows are sorted.

        Raises
        ------
        ValueError
            For an n that is not an integer >= 0, i and j not of one length, or a pair that is not one:
            an index outside [0, n), a particle paired with itself, or a pair given twice (either way
            round); the message names the first such pair.
        TypeError
            For indices that are not integers.
        """
        i, j, n = _checked_pairs(n, i, j)
        a, b = np.minimum(i, j), np.maximum(i, j)
        if not symmetric:
            a, b = np.concatenate([a, b]), np.concatenate([b, a])
        order = pair_order(a, b, n)
        twice = np.flatnonzero((np.diff(a[order]) == 0) & (np.diff(b[order]) == 0))
        if twice.size:
            k = order[twice[0]]
            raise ValueError(f"from_pairs: the pair ({a[k]}, {b[k]}) is given twice (pairs are unordered: give each "
                             "once)")
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(a, minlength=n), out=offsets[1:])
        return cls(offsets, b[order].astype(np.int32), bool(symmetric))

    def __repr__(self) -> str:
        kind = f"cross, n_ref={self.n_ref}" if self.cross else ("symmetric" if self.symmetric else "full")
        return f"NeighborList(n={self.n}, entries={len(self)}, {kind})"


def _checked_pairs(n: object, i: object, j: object) -> tuple[np.ndarray, np.ndarray, int]:
    """The pairs of :meth:`NeighborList.from_pairs` as int64 arrays, and n as an int, checked: n an integer
    >= 0, i and j integer arrays (m,), every pair two different particles of [0, n)."""
    if not is_integer(n) or n < 0:
        raise ValueError(f"from_pairs: n (the number of particles) must be an integer >= 0, got {n!r}")
    count = int(n)
    arrays = np.asarray(i), np.asarray(j)
    if arrays[0].ndim != 1 or arrays[0].shape != arrays[1].shape:
        raise ValueError(f"from_pairs: i and j must be arrays (m,) of one length m, got shapes {arrays[0].shape} "
                         f"and {arrays[1].shape}")
    for name, v in zip("ij", arrays):
        if v.size and not np.issubdtype(v.dtype, np.integer):
            raise TypeError(f"from_pairs: {name} must hold integer particle indices, got dtype {v.dtype}")
    i64, j64 = (v.astype(np.int64) for v in arrays)
    outside = np.flatnonzero((i64 < 0) | (i64 >= count) | (j64 < 0) | (j64 >= count))
    if outside.size:
        k = outside[0]
        raise ValueError(f"from_pairs: pair {k} is ({i64[k]}, {j64[k]}): an index outside [0, {count}) "
                         f"({count} particles)")
    itself = np.flatnonzero(i64 == j64)
    if itself.size:
        k = itself[0]
        raise ValueError(f"from_pairs: pair {k} is ({i64[k]}, {j64[k]}): a particle paired with itself (a particle "
                         "is never its own neighbour)")
    return i64, j64, count


def collect_list(handle: int, n: int, nnz: int, symmetric: bool) -> NeighborList:
    """Fetch the list the core has published under ``handle`` (and free it there), n rows and nnz
    entries (:func:`arpy._bridge.result_take`)."""
    offsets, indices = _bridge.result_take(handle, n, nnz, context="neighbor_list")
    return NeighborList(offsets=offsets, indices=indices, symmetric=symmetric)
