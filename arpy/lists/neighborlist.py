"""The neighbour list container: :class:`NeighborList`, compressed sparse rows (offsets, indices).

Particles p and q are neighbours iff ``|x_p - x_q| <= min(rc_p, rc_q) + skin``
(the adaptive-resolution "gather" rule; with one cutoff it is the usual
fixed-radius rule).  A particle is never its own neighbour; coincident
particles are neighbours of each other.  The searches that fill the container are in
:mod:`arpy.lists.search` and :mod:`arpy.lists.ar`; :func:`collect_list` fetches a list the core
has published.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

from .. import _bridge
from .._bridge import raise_for_info
from .._codes import STATUS
from .._validate import as_positions, check_index, is_integer, resolve_full
from ..domain import Domain, as_domain

__all__ = ["COUNT_BLOCK", "NeighborList", "collect_list", "pair_order", "pairs_increasing", "row_blocks"]

#: :meth:`NeighborList.stored_counts_where` counts in blocks of about this many entries.
COUNT_BLOCK = 1 << 20


def row_blocks(offsets: np.ndarray, block: int) -> list[tuple[int, int]]:
    """Rows of a CSR layout (``offsets`` (n + 1,), from 0) in blocks ``[first, last)`` of whole rows of
    about ``block`` entries each (more where one row is longer), in order; leading empty rows, which
    hold nothing, in none."""
    n = offsets.size - 1
    cuts = np.unique(np.searchsorted(offsets, np.arange(0, int(offsets[-1]), block), side="right") - 1).tolist()
    return list(zip(cuts, cuts[1:] + [n]))


def pair_order(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """The permutation that sorts distinct pairs (i, j) lexicographically, 0 <= j < n: one sort of
    the int64 keys i n + j (the order of ``np.lexsort((j, i))``, at less than half its cost)."""
    return np.argsort(np.asarray(i, np.int64) * np.int64(max(n, 1)) + j, kind="stable")


def pairs_increasing(i: np.ndarray, j: np.ndarray) -> bool:
    """Whether the pairs (i, j) (integer arrays of one length) strictly increase lexicographically: in
    the order ``np.lexsort((j, i))`` gives them, and distinct (that sort would leave them as they are)."""
    di, dj = np.diff(i), np.diff(j)
    return bool(np.all((di > 0) | ((di == 0) & (dj > 0))))


def check_layout(nl: "NeighborList", n_cols: int, context: str) -> None:
    """Raise the core's "inconsistent neighbour list" error (with ``context``) unless the offsets
    start at 0, never decrease and end at the number of entries, and every index is in [0, n_cols)."""
    off, idx = nl.offsets, nl.indices
    if off[0] != 0 or off[-1] != idx.size or np.any(np.diff(off) < 0) or (
            idx.size and not 0 <= idx.min() <= idx.max() < n_cols):
        raise_for_info(STATUS["ERR_LIST"], context=context)


@dataclass(frozen=True, eq=False, init=False, repr=False)
class NeighborList:
    """Neighbour lists in compressed sparse row (CSR) form, with the positions and the domain they were
    built from.

    Parameters
    ----------
    offsets : int64 array (n + 1,)
    indices : int32 array (entries,)
        The stored rows: row ``p`` is ``indices[offsets[p]:offsets[p + 1]]``.
    full : bool
        True: each pair stored in both rows.  False (default): a half list, each unordered pair stored
        once, in the row of either of its particles.  A cross list is always full.
    n_ref : int or None
        None for a list within one particle set; for a cross-set list (rows = query points, indices =
        particles of a reference set) the size of the reference set.
    x : array (n, d), optional
        The positions of the rows' particles (length), held by reference: see ``x`` below.
    x_ref : array (n_ref, d), optional
        For a cross list, the positions of the reference particles (length), by reference.
    domain : Domain, optional
        Where the particles live (periodic axes: the minimum image); None: free space.
    symmetric : bool, optional
        Deprecated name of ``not full`` (a DeprecationWarning).

    Attributes
    ----------
    offsets, indices, full, n_ref
        As above.
    x, x_ref : arrays or None
        The positions the list was built from, as the search checked them: the caller's own array when
        it was a C-ordered float64 (n, d) array, else the converted copy the search used.  They are a
        reference, not a copy (a copy would cost every list build time and memory that most callers
        never use): particles moved in place after the build give :meth:`distances` and the others
        their values at the new positions, for the pairs of the build (the Verlet use, a list with a
        skin kept while particles move).  None for lists made by :meth:`from_pairs` (or without
        ``x=``): then :meth:`vectors`, :meth:`distances`, :meth:`shifts` and :meth:`to_sparse` need
        the positions as arguments.
    domain : Domain or None
        The domain of the search (None: free space).

    Examples
    --------
    >>> import numpy as np
    >>> import arpy
    >>> x = np.array([[0.0, 0.0], [0.1, 0.0], [0.5, 0.0]])
    >>> nl = arpy.neighbor_list(x, 0.2)
    >>> nl
    NeighborList(n=3, entries=1, half)
    >>> nl.pairs()
    (array([0]), array([1]))
    >>> nl.counts().tolist(), nl.stored_counts().tolist()      # neighbours; entries stored per row
    ([1, 1, 0], [1, 0, 0])
    >>> nl.distances().tolist()
    [0.1]
    >>> nl.to_sparse().toarray()
    array([[0. , 0.1, 0. ],
           [0.1, 0. , 0. ],
           [0. , 0. , 0. ]])
    """

    offsets: np.ndarray
    indices: np.ndarray
    full: bool
    n_ref: int | None
    x: np.ndarray | None
    x_ref: np.ndarray | None
    domain: Domain | None

    def __init__(self, offsets: np.ndarray, indices: np.ndarray, *, full: bool = False, n_ref: int | None = None,
                 x: np.ndarray | None = None, x_ref: np.ndarray | None = None, domain: Domain | None = None,
                 symmetric: bool | None = None) -> None:
        full = resolve_full(full, symmetric, "NeighborList")
        xs = None if x is None else as_positions(x)
        xr = None if x_ref is None else as_positions(x_ref)
        n = int(np.shape(offsets)[0]) - 1
        if xs is not None and xs.shape[0] != n:
            raise ValueError(f"NeighborList: x must hold the positions of the {n} rows, got shape {xs.shape}")
        if xr is not None and (n_ref is None or xr.shape != (n_ref, xs.shape[1] if xs is not None else xr.shape[1])):
            raise ValueError(f"NeighborList: x_ref is for a cross list (n_ref = {n_ref}): the positions of its "
                             f"{n_ref} reference particles, got shape {xr.shape}")
        for name, value in (("offsets", offsets), ("indices", indices), ("full", n_ref is not None or bool(full)),
                            ("n_ref", n_ref), ("x", xs), ("x_ref", xr),
                            ("domain", None if domain is None else as_domain(domain))):
            object.__setattr__(self, name, value)

    def _like(self, offsets: np.ndarray, indices: np.ndarray) -> "NeighborList":
        """A list of the same form, reference set, positions and domain with other stored rows."""
        return NeighborList(offsets, indices, full=self.full, n_ref=self.n_ref, x=self.x, x_ref=self.x_ref,
                            domain=self.domain)

    @property
    def symmetric(self) -> bool:
        """Deprecated: ``not full`` (True for a half list)."""
        warnings.warn("NeighborList.symmetric is deprecated, use NeighborList.full (symmetric == not full)",
                      DeprecationWarning, stacklevel=2)
        return not self.full

    @property
    def cross(self) -> bool:
        """True for a cross-set list (rows and indices refer to different sets)."""
        return self.n_ref is not None

    @property
    def n(self) -> int:
        """Number of rows (particles)."""
        return int(self.offsets.size - 1)

    def __len__(self) -> int:
        """Number of stored entries (the pairs in a half list, twice the pairs in a full one)."""
        return int(self.indices.size)

    # ------------------------------------------------------------ neighbours and stored rows
    def counts(self) -> np.ndarray:
        """The number of neighbours of every particle (row), int64 (n,), for either form.

        A full or cross list: the stored entries per row (no pass over the entries).  A half list:
        its stored entries per row plus the entries that name the particle in other rows (one pass
        over the entries, a ``bincount``).  :meth:`stored_counts` gives the stored entries alone.
        """
        stored = np.diff(self.offsets)
        if self.full:
            return stored
        return stored + np.bincount(self.indices, minlength=self.n)

    def neighbors(self, p: int) -> np.ndarray:
        """The neighbours of particle (row) ``p``, 0 <= p < n, for either form; order unspecified.

        A full or cross list: its stored row (a view).  A half list: the row of the list's full form,
        made at the first call (one pass over the entries, then held: memory for twice the entries);
        later calls are views into it.  :meth:`stored_row` gives the stored row alone.

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
        if self.full:
            return self.indices[self.offsets[p]:self.offsets[p + 1]]
        offsets, indices, _ = self._both_rows
        return indices[offsets[p]:offsets[p + 1]]

    def stored_counts(self) -> np.ndarray:
        """The entries stored in every row, int64 (n,): ``np.diff(offsets)`` (in a half list each pair
        counts in one row only; :meth:`counts` gives the neighbours)."""
        return np.diff(self.offsets)

    def stored_counts_where(self, mask: np.ndarray) -> np.ndarray:
        """The entries stored in every row where ``mask`` (bool, one per stored entry, (offsets[-1],)) is
        True, int64 (n,).  Counted in blocks of whole rows of about :data:`COUNT_BLOCK` entries: no
        array over all the entries besides ``mask``."""
        mask = np.asarray(mask)
        ptr = self.offsets
        if mask.dtype != bool or mask.shape != (int(ptr[-1]),):
            raise ValueError(f"stored_counts_where: mask must be bool with one entry per stored entry "
                             f"({int(ptr[-1])},), got {mask.dtype} {mask.shape}")
        out = np.zeros(ptr.size - 1, np.int64)
        for first, last in row_blocks(ptr, COUNT_BLOCK):
            a, b = int(ptr[first]), int(ptr[last])
            run = np.zeros(b - a + 1, np.int64)
            np.cumsum(mask[a:b], out=run[1:])
            out[first:last] = run[ptr[first + 1:last + 1] - a] - run[ptr[first:last] - a]
        return out

    def stored_row(self, p: int) -> np.ndarray:
        """The indices stored in row ``p`` (a view), 0 <= p < n: all of p's neighbours in a full or cross
        list, those of the pairs stored in p's row in a half list.  Errors as :meth:`neighbors`."""
        p = check_index("p", p, self.n)
        return self.indices[self.offsets[p]:self.offsets[p + 1]]

    @functools.cached_property
    def _both_rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A half list's full form: (offsets (n + 1,), indices (2 entries,) int32, and for every entry of
        it the stored entry it comes from); row p is p's stored row followed by the rows that store p
        (ascending).  One transpose (scipy's CSR to CSC, linear) and two scatters."""
        import scipy.sparse as sp

        n, m = self.n, len(self)
        kind = np.int32 if 2 * m < np.iinfo(np.int32).max else np.int64
        ids = np.arange(m, dtype=kind)
        stored = np.diff(self.offsets)
        t = sp.csc_array(sp.csr_array((ids, self.indices, self.offsets), shape=(n, n), copy=True))
        moved = np.diff(t.indptr).astype(np.int64)
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(stored + moved, out=offsets[1:])
        own = ids + np.repeat(offsets[:-1] - self.offsets[:-1], stored)
        other = ids + np.repeat(offsets[:-1] + stored - t.indptr[:-1], moved)
        indices, source = np.empty(2 * m, np.int32), np.empty(2 * m, kind)
        indices[own], source[own] = self.indices, ids
        indices[other], source[other] = t.indices, t.data
        return offsets, indices, source

    def rows(self) -> np.ndarray:
        """Row index of every stored entry, shape (len(self),)."""
        return np.repeat(np.arange(self.n, dtype=np.int64), self.stored_counts())

    def pairs(self, sort: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Every unordered pair once as arrays ``(i, j)`` with ``i < j``, sorted lexicographically
        (``sort=False``: in the list's own order, without the cost of sorting).

        For a cross-set list: every (query, reference) pair.
        """
        rows, cols = self.rows(), self.indices
        if self.cross:
            i, j = rows, cols.astype(np.int64)
        elif not self.full:
            i, j = np.minimum(rows, cols), np.maximum(rows, cols)
        else:
            keep = rows < cols
            i, j = rows[keep], cols[keep]
        if not sort:
            return i, j
        order = pair_order(i, j, self.n_ref if self.n_ref is not None else self.n)
        return i[order], j[order]

    # ------------------------------------------------------------ geometry of the stored entries
    def _where(self, x: np.ndarray | None, x_ref: np.ndarray | None, domain: Domain | None, what: str
               ) -> tuple[np.ndarray, np.ndarray, Domain]:
        """(positions of the rows, of the indices, the domain): those given, else the list's own."""
        xs = self.x if x is None else as_positions(x)
        if xs is None:
            raise ValueError(f"NeighborList.{what}: this list holds no positions (made by from_pairs, or "
                             "without x=): pass x=, the positions of its rows"
                             + (", and x_ref=, those of the reference set" if self.cross else ""))
        if self.cross:
            xr = self.x_ref if x_ref is None else as_positions(x_ref)
            if xr is None:
                raise ValueError(f"NeighborList.{what}: a cross list needs x_ref, the reference positions")
        elif x_ref is not None:
            raise ValueError(f"NeighborList.{what}: x_ref is for cross lists; this list is within one set")
        else:
            xr = xs
        if xs.shape[0] != self.n or (self.cross and xr.shape[0] != self.n_ref):
            raise ValueError(f"NeighborList.{what}: positions must have {self.n} rows (and x_ref {self.n_ref}) "
                             f"for this list, got {xs.shape[0]}" + ("" if not self.cross else f" and {xr.shape[0]}"))
        if xr.shape[1] != xs.shape[1]:
            raise ValueError(f"NeighborList.{what}: x and x_ref must have the same dimension, got "
                             f"{xs.shape[1]} and {xr.shape[1]}")
        return xs, xr, as_domain(self.domain if domain is None else domain, xs.shape[1])

    def _axes(self, x: np.ndarray | None, x_ref: np.ndarray | None, domain: Domain | None, what: str,
              rows: np.ndarray | None = None) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
        """Per axis a: (x_q - x_p along a for every stored entry, float64 (len,), the whole periods
        ``round((x_q - x_p) / period)`` along a periodic axis, else None), computed one axis at a time
        (1-D gathers: faster than NumPy's row gathers of (n, d) arrays); ``rows``: :meth:`rows`, if
        the caller has it."""
        xs, xr, dom = self._where(x, x_ref, domain, what)
        rows, cols = self.rows() if rows is None else rows, self.indices
        period = dom.period if dom.any_periodic else np.zeros(xs.shape[1])
        for a in range(xs.shape[1]):
            e = np.take(np.ascontiguousarray(xr[:, a]), cols)
            e -= np.take(np.ascontiguousarray(xs[:, a]), rows)
            if period[a] > 0:
                k = np.round(e / period[a])
                e -= period[a] * k
                yield e, k
            else:
                yield e, None

    def vectors(self, x: np.ndarray | None = None, x_ref: np.ndarray | None = None,
                domain: Domain | None = None) -> np.ndarray:
        """The displacement x_q - x_p of every stored entry (row p, index q), in the list's order
        (``rows()``, ``indices``), by the minimum image along the periodic axes of the list's domain.

        Parameters
        ----------
        x : array (n, d), optional
            Positions of the rows' particles (length); default: those the list was built from.
        x_ref : array (n_ref, d), optional
            For a cross list, the reference particles' positions; default: the list's.
        domain : Domain, optional
            Where the particles live (periodic axes: minimum image); default: the list's.

        Returns
        -------
        array (len(self), d), float64 (length)

        Raises
        ------
        ValueError
            For a list without positions (:meth:`from_pairs`) when ``x`` (and for a cross list
            ``x_ref``) is not given, or positions of the wrong shape.

        Examples
        --------
        >>> import numpy as np, arpy
        >>> x = np.array([[0.05, 0.5], [0.95, 0.5]])
        >>> box = arpy.Domain([1.0, 1.0], periodic=True)
        >>> nl = arpy.neighbor_list(x, 0.2, domain=box, full=True)     # rows 0 and 1
        >>> nl.vectors().round(12).tolist(), nl.shifts().tolist()
        ([[-0.1, 0.0], [0.1, 0.0]], [[-1, 0], [1, 0]])
        """
        return np.stack([e for e, _ in self._axes(x, x_ref, domain, "vectors")], axis=1)

    def distances(self, x: np.ndarray | None = None, x_ref: np.ndarray | None = None,
                  domain: Domain | None = None) -> np.ndarray:
        """``|x_q - x_p|`` of every stored entry (length), float64 (len(self),), by the minimum image
        (arguments and errors as :meth:`vectors`)."""
        return self._distances(x, x_ref, domain, "distances")

    def _distances(self, x: np.ndarray | None, x_ref: np.ndarray | None, domain: Domain | None,
                   what: str) -> np.ndarray:
        """:meth:`distances`, its errors naming the method ``what`` called."""
        return _lengths([e for e, _ in self._axes(x, x_ref, domain, what)])

    def shifts(self, x: np.ndarray | None = None, x_ref: np.ndarray | None = None,
               domain: Domain | None = None) -> np.ndarray:
        """The periodic shift S of every stored entry, int64 (len(self), d): the displacement of
        :meth:`vectors` is ``x_q - x_p + S * edge`` (S = 0 along non-periodic axes and in free space),
        as in the i, j, S triplets of ASE-style neighbour lists (arguments and errors as
        :meth:`vectors`)."""
        return _shift_columns([k for _, k in self._axes(x, x_ref, domain, "shifts")], len(self))

    def quantities(self, spec: str) -> tuple[np.ndarray, ...]:
        """Per-entry arrays in one pass over the stored entries, as ASE's and vesin's
        ``neighbor_list("ijdDS", ...)``: one array per letter of ``spec``, in its order.

        Letters: ``i`` the row of every stored entry and ``j`` its index (int64, (len(self),));
        ``d`` the distance (float64 (len(self),), length); ``D`` the displacement x_j - x_i + S edge
        (float64 (len(self), d), as :meth:`vectors`); ``S`` the periodic shift (int64 (len(self), d),
        as :meth:`shifts`).  A half list gives each pair once, a full list in both directions.  The
        positions and the domain are the list's own (:func:`~arpy.neighbor_list` keeps them).

        Raises
        ------
        ValueError
            For an empty ``spec``, a letter not among ``ijdDS`` or given twice, or a geometric letter
            (``dDS``) on a list that holds no positions.

        Examples
        --------
        >>> import numpy as np, arpy
        >>> box = arpy.Domain([1.0, 1.0], periodic=True)
        >>> nl = arpy.neighbor_list(np.array([[0.05, 0.5], [0.95, 0.5]]), 0.2, domain=box, full=True)
        >>> i, j, d, S = nl.quantities("ijdS")
        >>> i.tolist(), j.tolist(), d.round(12).tolist(), S.tolist()
        ([0, 1], [1, 0], [0.1, 0.1], [[-1, 0], [1, 0]])
        """
        if not isinstance(spec, str) or not spec or set(spec) - set("ijdDS") or len(set(spec)) != len(spec):
            raise ValueError(f"quantities: spec must be distinct letters of 'ijdDS' (i, j: indices; d: "
                             f"distances; D: vectors; S: shifts), got {spec!r}")
        rows = self.rows() if set(spec) - set("j") else None
        out: dict[str, np.ndarray] = {}
        if rows is not None:
            out["i"] = rows
        if "j" in spec:
            out["j"] = self.indices.astype(np.int64)
        if set(spec) & set("dDS"):
            axes = list(self._axes(None, None, None, "quantities", rows))
            if "D" in spec:
                out["D"] = np.stack([e for e, _ in axes], axis=1)
            if "S" in spec:
                out["S"] = _shift_columns([k for _, k in axes], len(self))
            if "d" in spec:                     # (last: it squares the differences in place)
                out["d"] = _lengths([e for e, _ in axes])
        return tuple(out[c] for c in spec)

    def to_sparse(self, x: np.ndarray | None = None, x_ref: np.ndarray | None = None,
                  domain: Domain | None = None, *, mode: str = "distance", format: str = "csr") -> sp.sparray:
        """The list as a ``scipy.sparse`` array, like ``cKDTree.sparse_distance_matrix``.

        Entry (p, q) for every neighbour pair; a list within one set gives both (p, q) and (q, p),
        half or full alike, shape (n, n); a cross list gives (query, reference), shape (n, n_ref).
        Rows are sorted (``has_sorted_indices``).

        Parameters
        ----------
        x, x_ref, domain : optional
            As for :meth:`vectors` (default: the list's own positions and domain).
        mode : {"distance", "connectivity"}
            The values: the distances ``|x_p - x_q|`` (by the minimum image; a pair at distance 0 is an
            explicit zero), or 1 for every pair (no positions needed).
        format : str
            A scipy.sparse format: "csr" (default: built directly from the rows), or "csc", "coo", ...
            (converted from it).

        Returns
        -------
        scipy.sparse.csr_array (or the array of ``format``)
        """
        import scipy.sparse as sp

        if mode not in ("distance", "connectivity"):
            raise ValueError(f"to_sparse: mode must be 'distance' or 'connectivity', got {mode!r}")
        values = self._distances(x, x_ref, domain, "to_sparse") if mode == "distance" else np.ones(len(self))
        if self.full:
            offsets, indices = self.offsets.copy(), self.indices.copy()       # (sort_indices works in place)
        else:
            offsets, indices, source = self._both_rows
            offsets, indices, values = offsets.copy(), indices.copy(), values[source]
        shape = (self.n, self.n if self.n_ref is None else self.n_ref)
        mat = sp.csr_array((values, indices, offsets), shape=shape)
        mat.sort_indices()
        return mat if format == "csr" else mat.asformat(format)

    # ------------------------------------------------------------ layouts
    def canonical(self) -> "NeighborList":
        """The same entries in the sorted layout: each row ascending, and in a half list each pair in
        the row of its smaller index (the layout of :meth:`from_pairs`).  Lists built by different
        methods, thread counts or searches have one canonical form (with this list's positions and
        domain)."""
        if not self.full:
            nl = NeighborList.from_pairs(self.n, *self.pairs(sort=False))
            return self._like(nl.offsets, nl.indices)
        return self.ordered_by(np.arange(self.n if self.n_ref is None else self.n_ref, dtype=np.int64))

    def ordered_by(self, rank: np.ndarray) -> "NeighborList":
        """The same entries with each row sorted by ``rank[column]`` (distinct int64 values, one per
        column index, e.g. the particles' keys): sums over a row in that order do not depend on the
        method or layout that built the list."""
        rank = np.ascontiguousarray(rank, dtype=np.int64)
        # (rows already in that order, e.g. the rows of a cross list, ascending: the list as it is)
        if _bridge.rows_sorted(self.offsets, self.indices, rank, context="NeighborList.ordered_by"):
            return self._like(self.offsets, self.indices)
        # the core sorts the array it is given in place: give it a copy, this list stays as it is
        idx = _bridge.sort_rows(self.offsets, self.indices.copy(), rank, context="NeighborList.ordered_by")
        return self._like(self.offsets, idx)

    @classmethod
    def from_pairs(cls, n: int, i: np.ndarray, j: np.ndarray, *, full: bool = False,
                   symmetric: bool | None = None) -> "NeighborList":
        """Build the list of n particles from unordered pairs (i, j), each given once.

        Half (``full=False``, the default): pair (i, j) is stored in row min(i, j).  Full: in both rows.
        Rows are sorted.  The list holds no positions: its :meth:`vectors`, :meth:`distances`,
        :meth:`shifts` and :meth:`to_sparse` (``mode="distance"``) need them as arguments.
        ``symmetric`` is the deprecated name of ``not full``.

        Raises
        ------
        ValueError
            For an n that is not an integer >= 0, i and j not of one length, or a pair that is not one:
            an index outside [0, n), a particle paired with itself, or a pair given twice (either way
            round); the message names the first such pair.
        TypeError
            For indices that are not integers.
        """
        full = resolve_full(full, symmetric, "NeighborList.from_pairs")
        i, j, n = _checked_pairs(n, i, j)
        a, b = np.minimum(i, j), np.maximum(i, j)
        if full:
            a, b = np.concatenate([a, b]), np.concatenate([b, a])
        order = pair_order(a, b, n)
        twice = np.flatnonzero((np.diff(a[order]) == 0) & (np.diff(b[order]) == 0))
        if twice.size:
            k = order[twice[0]]
            raise ValueError(f"from_pairs: the pair ({a[k]}, {b[k]}) is given twice (pairs are unordered: give each "
                             "once)")
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(a, minlength=n), out=offsets[1:])
        return cls(offsets, b[order].astype(np.int32), full=full)

    def __repr__(self) -> str:
        kind = f"cross, n_ref={self.n_ref}" if self.cross else ("full" if self.full else "half")
        return f"NeighborList(n={self.n}, entries={len(self)}, {kind})"


def _lengths(parts: list[np.ndarray]) -> np.ndarray:
    """sqrt(sum of the squares of ``parts``), the per-axis differences (float64 (m,) each, at least
    one), summed axis by axis; the parts after the first are squared in place."""
    total = parts[0] * parts[0]
    for e in parts[1:]:
        e *= e
        total += e
    return np.sqrt(total, out=total)


def _shift_columns(whole: list[np.ndarray | None], m: int) -> np.ndarray:
    """The periodic shifts S, int64 (m, d), from the per-axis whole periods of :meth:`NeighborList._axes`
    (None along non-periodic axes: 0)."""
    parts = [np.zeros(m, np.int64) if k is None else -k.astype(np.int64) for k in whole]
    return np.stack(parts, axis=1) if parts else np.zeros((m, 0), np.int64)


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


def collect_list(handle: int, n: int, nnz: int, *, full: bool, x: np.ndarray | None = None,
                 domain: Domain | None = None) -> NeighborList:
    """Fetch the list the core has published under ``handle`` (and free it there), n rows and nnz
    entries (:func:`arpy._bridge.result_take`), of positions x in ``domain``."""
    offsets, indices = _bridge.result_take(handle, n, nnz, context="neighbor_list")
    return NeighborList(offsets, indices, full=full, x=x, domain=domain)
