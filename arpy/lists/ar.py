"""Adaptive-resolution (AR) cell lists: the tree object and its Verlet and cross lists.

The AR cell list of Awile et al. (2012) sorts particles into a tree of cells
whose level follows each particle's cutoff: level k (root = 0, cell edge
D_m / 2**k, D_m = the largest edge of the domain, which is made cubic) holds
the particles with D_m/2**k > rc >= D_m/2**(k+1).  Cells are identified by
their level-order index J (root 1, children of J are J*2**d + l - 2**d + 2)
and kept in a hash table; Verlet lists are built from it with Algorithm 3.
Everything runs in the Fortran core (fortran/ar/).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import numpy.typing as npt

from .. import _bridge
from .._bridge import lengths_exponent, raise_for_info, scaled
from .._codes import AR_OPS, RANGE_EXP
from .._validate import as_cutoffs, as_positions, column_extremes, resolve_full
from ..domain import Domain, as_domain
from .neighborlist import NeighborList, collect_list

__all__ = ["ARCellList", "halo_bits", "MAX_LEVEL"]


#: Deepest level whose level-order index still fits int64, per dimension.
MAX_LEVEL = {2: 30, 3: 20}


def _last_key(d: int) -> int:
    """The largest level-order index J of a cell on a level <= MAX_LEVEL[d]."""
    return sum(1 << (d * k) for k in range(MAX_LEVEL[d] + 1))


def _as_domain(domain: Domain | None, d: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The corners of the tree's domain: (lo, hi, 1) of a box, (0, 0, 0) for None (the particles' bounding box)."""
    dom = as_domain(domain, d)
    if not dom.bounded:
        return np.zeros(d), np.zeros(d), 0
    if dom.any_periodic:
        raise ValueError("ARCellList does not image periodic axes: build the lists with "
                         "arpy.neighbor_list(..., domain=...) or add arpy.periodic_ghosts yourself")
    assert dom.lo is not None and dom.hi is not None
    return dom.lo, dom.hi, 1


class ARCellList:
    """An adaptive-resolution cell list (Algorithms 1 and 2) kept in the Fortran core.

    Parameters
    ----------
    x : array, shape (n, d), d = 2 or 3
        Particle positions.
    rc : float or array, shape (n,)
        Cutoff radii (> 0), same unit as ``x``.
    domain : Domain or None
        A box (walls, not periodic) the tree's root covers.  Default: the
        particles' bounding box.  The box is made cubic with edge
        ``D_m = max(hi - lo)`` anchored at ``lo``; particles outside it raise ``ValueError``.
    skin : float
        Verlet skin: the tree is built for the cutoffs ``rc + skin``.

    Attributes
    ----------
    n, d : int
        Number of particles and dimension.
    edge : float
        The edge of the root cell: the smallest cutoff times a power of two, at least D_m (coordinates
        and cutoffs must stay below 2**1021, where it could exceed the largest double).
    lo : array (d,)
        The lower corner of the cubic domain.
    maxlevel : int
        Deepest level that holds a particle.
    level : int array (n,)
        The level of every particle.
    order : int array (n,)
        Particle index at every sorted position (slot).
    cells : dict
        J -> (first, last), the half-open slot range of the particles that live on the level of
        cell J, for every non-empty cell.
    finer : set
        The J whose region holds particles of a finer level.

    Examples
    --------
    Particles whose cutoffs differ by a factor 10 sit on different levels of the tree:

    >>> import numpy as np
    >>> import arpy
    >>> x = np.random.default_rng(0).random((1000, 2))
    >>> rc = np.where(x[:, 0] < 0.5, 0.01, 0.1)
    >>> tree = arpy.ARCellList(x, rc)
    >>> tree.n, tree.d, sorted(set(tree.level.tolist()))
    (1000, 2, [3, 7])

    The cell operations Op1 (the cell of a point on a level) and Op2 (its particles):

    >>> J = tree.find_cell(x[0], int(tree.level[0]))
    >>> 0 in tree.particles_in_cell(J)
    True

    Its Verlet list holds the same pairs as every other method:

    >>> ar, brute = tree.verlet_list(), arpy.neighbor_list(x, rc, method="brute")
    >>> all(np.array_equal(a, b) for a, b in zip(ar.pairs(), brute.pairs()))
    True
    """

    def __init__(self, x: np.ndarray, rc: float | np.ndarray, *, domain: Domain | None = None,
                 skin: float = 0.0) -> None:
        xs = as_positions(x)
        n, d = xs.shape
        if n == 0:
            raise ValueError("ARCellList needs at least one particle")
        rcs = as_cutoffs(rc, n)
        lo, hi, has_domain = _as_domain(domain, d)
        skin = float(skin)
        if not (np.isfinite(skin) and skin >= 0.0):
            raise ValueError(f"skin must be a finite number >= 0, got {skin}")
        if np.shares_memory(xs, x):
            xs = xs.copy()                   # the tree's particles, whatever the caller does to x
        self._x, self._rc, self._domain = xs, rcs, domain if has_domain else None
        # lengths reach the core times an exact power of two 2**k where they must (see core_exponent)
        self._k = k = lengths_exponent([xs, skin, lo, hi], [rcs])
        handle, nleaf, nkey, maxlevel, dm = _bridge.ar_create(
            scaled(k, xs), scaled(k, rcs), scaled(k, skin), has_domain, scaled(k, lo), scaled(k, hi))
        self._handle = handle
        self._reach = float(rcs.max()) + skin
        self.n, self.d = n, d
        self.skin = skin
        with np.errstate(over="ignore"):
            self.edge = float(np.ldexp(float(dm), -k))
        if not math.isfinite(self.edge):
            # (the root edge is a power of two times the smallest cutoff, up to twice the extent: lengths
            # within 2**1021 always fit)
            raise ValueError(f"ARCellList: coordinates and cutoffs up to {max(self._reach, float(np.abs(xs).max())):.3g} "
                             "make the tree's root cell (the smallest cutoff times a power of two, at least the "
                             "particles' extent) wider than the largest double; keep lengths below 2**1021")
        self.maxlevel = int(maxlevel)
        perm, level, leaf_key, leaf_first, leaf_last, keys, first, last, finer, lo3 = _bridge.ar_tables(
            handle, n, nleaf, nkey)
        self.lo = np.ldexp(lo3[:d], -k)
        self.order = perm.astype(np.int64)
        self.level = np.empty(n, np.int64)
        self.level[self.order] = level
        self._table = (keys, first, last, finer)

    @functools.cached_property
    def cells(self) -> dict[int, tuple[int, int]]:
        """J -> (first, last), the half-open slot range of the particles on the level of cell J, for
        every non-empty cell (made when first asked for: lists do not need it)."""
        keys, first, last, _ = self._table
        own = np.flatnonzero(last > first)
        own = own[np.argsort(keys[own])]
        return {int(j): (int(a), int(b)) for j, a, b in zip(keys[own], first[own], last[own])}

    @functools.cached_property
    def finer(self) -> frozenset[int]:
        """The J whose region holds particles of a finer level."""
        keys, _, _, finer = self._table
        return frozenset(int(j) for j in keys[finer != 0])

    def __del__(self) -> None:
        handle = getattr(self, "_handle", 0)
        if handle:
            _bridge.ar_free(handle)
            self._handle = 0

    def __reduce__(self):
        """Copies and pickles rebuild the tree from the particles: each has a core tree of its own."""
        return (_rebuild, (self._x, self._rc, self._domain, self.skin))

    def __repr__(self) -> str:
        return (f"ARCellList(n={self.n}, d={self.d}, edge={self.edge:g}, maxlevel={self.maxlevel}, "
                f"cells={len(self.cells)})")

    # ---------------------------------------------------------------- Op1-Op5
    def _ops(self, op: int, keys, pts=None, k: int = 0):
        keys = np.atleast_1d(np.asarray(keys, dtype=np.int64)).copy()
        if pts is None:
            pts = np.zeros((keys.size, self.d))
        return _bridge.ar_ops(self._handle, op, pts, k, keys)

    def _key(self, J) -> int:
        """Validate a level-order index: an integer in [1, J of the last cell on level MAX_LEVEL]."""
        if isinstance(J, (bool, np.bool_)) or not isinstance(J, (int, np.integer)):
            raise TypeError(f"a cell index J must be an integer, got {type(J).__name__}")
        if not 1 <= int(J) <= _last_key(self.d):
            raise ValueError(f"cell index J = {J} is not a cell of levels 0..{MAX_LEVEL[self.d]} "
                             f"(J in [1, {_last_key(self.d)}])")
        return int(J)

    def find_cell(self, point: npt.ArrayLike, level: int) -> int | None:
        """Op1: J of the level-``level`` cell containing ``point`` (None outside the cube)."""
        if not 0 <= level <= MAX_LEVEL[self.d]:
            raise ValueError(f"level must be in [0, {MAX_LEVEL[self.d]}]")
        pts = np.asarray(point, dtype=np.float64).reshape(1, self.d)
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"find_cell: point must be finite, got {pts[0]}")
        if np.any(pts < self.lo) or np.any(pts > self.lo + self.edge):
            return None
        keys, *_ = self._ops(AR_OPS["find_cell"], [0], np.ldexp(pts, self._k), int(level))
        return None if keys[0] < 0 else int(keys[0])

    def particles_in_cell(self, J: int) -> np.ndarray:
        """Op2: indices of the particles that live in cell J on its own level."""
        _, out, _, _ = self._ops(AR_OPS["lookup"], [self._key(J)])
        return self.order[out[0, 0]:out[1, 0]]

    def children(self, J: int) -> list[int]:
        """Op3: the 2**d children of cell J."""
        if self.cell_level(J) >= MAX_LEVEL[self.d]:
            raise ValueError("cells on the deepest representable level have no children")
        _, _, nbr, cnt = self._ops(AR_OPS["children"], [J])
        return [int(v) for v in nbr[: cnt[0], 0]]

    def parent(self, J: int) -> int | None:
        """Op4: the parent of cell J (None for the root)."""
        _, _, nbr, _ = self._ops(AR_OPS["parent"], [self._key(J)])
        return int(nbr[0, 0]) or None

    def neighbor_cells(self, J: int) -> list[int]:
        """Op5: the cells adjacent to J on its level that lie inside the domain."""
        _, _, nbr, cnt = self._ops(AR_OPS["neighbors"], [self._key(J)])
        return [int(v) for v in nbr[: cnt[0], 0]]

    def cell_level(self, J: int) -> int:
        """Level of the cell with level-order index J >= 1."""
        J = self._key(J)
        k, first = 0, 1
        while True:
            nxt = first + (1 << (self.d * k))
            if J < nxt:
                return k
            first, k = nxt, k + 1

    def has_finer(self, J: int) -> bool:
        """True if the region of cell J holds particles of a level finer than J's."""
        return int(J) in self.finer

    # ---------------------------------------------------------------- lists
    def verlet_list(self, skin: float = 0.0, *, full: bool = False, direct: bool = False,
                    ghost_bits: np.ndarray | None = None, symmetric: bool | None = None) -> NeighborList:
        """Algorithm 3: neighbour lists under ``|x_p - x_q| <= min(rc_p, rc_q) + skin`` (+ the tree's own skin).

        The tree is built for the cutoffs it was given; a further ``skin > 0``
        needs a tree for the larger cutoffs, so one is built on the same domain.
        A full list (``full=True``) is the half one with every pair written to both
        rows; ``direct=True`` builds it instead by the algorithm's asymmetric branch, each particle
        searching its own neighbours from the root (every pair tested twice, no expansion pass).
        Both give the same rows; the order within a row differs.

        ``ghost_bits`` (n,) ints: the ghost-ghost filter of §2.4 for a subdomain with halo layers on
        half of its faces: 0 for a real particle, for a ghost the d-bit string of the halos it lies in
        (:func:`halo_bits`).  Pairs of two ghosts whose strings share a bit are dropped (another
        subdomain has both particles and computes them); every other pair stays.

        ``symmetric`` is the deprecated name of ``not full``.  The list holds the tree's positions and
        domain.
        """
        full = resolve_full(full, symmetric, "verlet_list")
        if direct and not full:
            raise ValueError("verlet_list: direct=True builds a full list (full=True)")
        bits = np.zeros(0, np.int32)
        if ghost_bits is not None:
            bits = np.asarray(ghost_bits)
            if bits.shape != (self.n,) or not (np.issubdtype(bits.dtype, np.integer) or bits.size == 0):
                raise ValueError(f"verlet_list: ghost_bits must be {self.n} integers, got shape {bits.shape}, "
                                 f"dtype {bits.dtype}")
            if bits.size and (bits.min() < 0 or bits.max() >= 2 ** self.d):
                raise ValueError(f"verlet_list: ghost_bits must lie in [0, 2**d) = [0, {2 ** self.d})")
            bits = np.ascontiguousarray(bits, dtype=np.int32)
        skin = float(skin)
        if not (np.isfinite(skin) and skin >= 0.0):
            raise ValueError(f"verlet_list: skin must be a finite number >= 0, got {skin}")
        if skin > 0.0:
            cube = Domain(np.stack([self.lo, self.lo + self.edge]))
            wider = ARCellList(self._x, self._rc, domain=cube, skin=self.skin + skin)
            nl = wider.verlet_list(full=full, direct=direct, ghost_bits=ghost_bits)
            return NeighborList(nl.offsets, nl.indices, full=full, x=self._x, domain=self._domain)
        handle, nnz = _bridge.ar_verlet(self._handle, 2 if direct else int(not full), bits)
        return collect_list(handle, self.n, nnz, full=full, x=self._x, domain=self._domain)

    def cross_list(self, x_query: np.ndarray, rc_query: float | np.ndarray) -> NeighborList:
        """Rows = query points, entries = particles of this list with ``|x_i - x_q| <= min(rc_i, rc_q)``,
        each row in ascending order (the canonical layout: :meth:`NeighborList.canonical` keeps it); the
        list holds the query points and the tree's positions."""
        xq = as_positions(x_query)
        if xq.shape[1] != self.d:
            raise ValueError(f"query points must have d = {self.d} columns, got shape {xq.shape}")
        m = xq.shape[0]
        rq = as_cutoffs(rc_query, m)
        where = dict(full=True, n_ref=self.n, x=xq, x_ref=self._x)
        if m == 0:
            return NeighborList(np.zeros(1, np.int64), np.zeros(0, np.int32), **where)
        reach = self._reach                                 # the longest reach of any particle
        rows = slice(None)
        (x_min, x_max) = column_extremes(xq)
        if np.all(np.isfinite(x_min)) and np.all(np.isfinite(x_max)):
            # a query farther than every cutoff from the cube has no neighbours
            with np.errstate(over="ignore"):          # lo +- reach may round to +-inf: still correct
                low, high = self.lo - reach, self.lo + self.edge + reach
                if not (np.all(x_min >= low) and np.all(x_max <= high)):
                    rows = np.flatnonzero(np.all((xq >= low) & (xq <= high), axis=1))
                    if rows.size == 0:
                        return NeighborList(np.zeros(m + 1, np.int64), np.zeros(0, np.int32), **where)
        k = self._k
        rq = np.minimum(rq[rows], reach)                    # min(rc_q, rc_i) is at most the reach
        r_min, r_max = rq.min(), rq.max()                   # (NaN shows in both)
        if r_min > 0 and np.isfinite(r_max) and math.ldexp(float(r_min), k) < 2.0 ** -RANGE_EXP:
            raise ValueError(f"cross_list: query cutoffs down to {r_min:.3g} span too wide a range against "
                             f"the tree's lengths (up to {max(reach, self.edge):.3g}): squared distances would "
                             "underflow in double precision")
        xs = xq[rows]
        handle, nnz, info, bad = _bridge.ar_cross(self._handle, scaled(k, xs), scaled(k, rq))
        raise_for_info(info, (np.arange(m)[rows][bad - 1] + 1) if bad else 0, context="cross_list")
        nl = collect_list(handle, xs.shape[0], nnz, full=True)
        if isinstance(rows, slice):
            return NeighborList(nl.offsets, nl.indices, **where)
        offsets = np.zeros(m + 1, np.int64)
        offsets[rows + 1] = nl.stored_counts()
        np.cumsum(offsets, out=offsets)
        return NeighborList(offsets, nl.indices, **where)


def halo_bits(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The halo bit strings of :meth:`ARCellList.verlet_list`'s ghost-ghost filter: bit i (value
    2**i) set where a point lies outside [lo_i, hi_i) of a subdomain along axis i, shape (n,) int32
    (0: inside, a real particle).

    Parameters
    ----------
    x : array (n, d)
        Positions of the subdomain's particles and ghosts.
    lo, hi : array (d,)
        The subdomain's box.
    """
    xs = as_positions(x)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if lo.shape != (xs.shape[1],) or hi.shape != lo.shape or not np.all(lo < hi):
        raise ValueError(f"halo_bits: need lo < hi, each of shape ({xs.shape[1]},)")
    out = (xs < lo) | (xs >= hi)
    return (out * (1 << np.arange(xs.shape[1]))).sum(axis=1).astype(np.int32)


def _rebuild(x: np.ndarray, rc: np.ndarray, domain: Domain | None, skin: float) -> ARCellList:
    """A new tree of the same particles (for copy and pickle)."""
    return ARCellList(x, rc, domain=domain, skin=skin)
