"""Pure-NumPy reference implementation of adaptive-resolution (AR) cell lists.

Follows Awile, Büyükkeçeci, Reboux, Sbalzarini, "Fast neighbor lists for
adaptive-resolution particle simulations", Comput. Phys. Commun. 183 (2012):
Algorithm 1 (level assignment), Algorithm 2 (per-level recursive partition),
the ``cells`` hash table keyed by the level-order index J(c), the operations
Op1-Op5 and Algorithm 3 (Verlet lists).  It exists to cross-validate the
Fortran core, so it mirrors the paper's data structures; it favours clarity
over speed (vectorised where easy: ~20k particles take about a second).

Conventions
-----------
Neighbour rule (gather): p and q interact iff ``|x_p - x_q| <= min(rc_p, rc_q)``.
With a skin s every cutoff is replaced by ``rc + s``, i.e. the rule becomes
``|x_p - x_q| <= min(rc_p, rc_q) + s``, and the tree is built with ``rc + s``.
The test is evaluated exactly as ``r2 <= rm * rm`` with
``r2 = ((0 + dx_1*dx_1) + dx_2*dx_2) [+ dx_3*dx_3]``, ``dx_i = x_q,i - x_p,i`` and
``rm = min(rc_p, rc_q) + s`` (same expression, same order as the Fortran
brute force), so both implementations take bit-identical decisions.

Domain.  The domain (given ``(lo, hi)``, default: bounding box of the particles)
is made cubic by extending it *upwards* from ``lo``: the cube is
``[lo, lo + D_m]^d``.  The paper (footnote 1) takes ``D_m = max_i (hi_i - lo_i)``,
which leaves the cells of the finest level anywhere between the smallest cutoff and
twice it, depending on N.  Here the root is fitted to the smallest cutoff
(:func:`root_edge`): ``D_m = r 2^K`` with ``r`` the double just above ``min(rc)`` and
``K`` the fewest doublings that reach the extent, so the smallest cutoffs sit on
level K in cells ``r`` wide, the narrowest the rule below allows; only where that
would need a level beyond ``MAX_LEVEL`` is the paper's ``D_m`` used (``max(rc)``
if all particles coincide).  A particle on an upper face of the cube
(``x_i == lo_i + D_m``) is put into the last cell along that axis ("clamping").
This is exactly what the paper's partition rule ``x_i < m_i`` / ``x_i >= m_i``
does anyway: a point on the upper face is ``>=`` every midpoint.

All geometry is done in normalised coordinates ``u = (x - lo) / D_m`` (clipped
to [0, 1]).  In u-space every cell corner and midpoint is an exact dyadic
rational, so the paper's midpoint comparisons (Algorithm 2, Op1) and the integer
cell coordinates ``floor(u * 2^k)`` agree bit for bit; a Fortran code that
computes ``u`` with the same two IEEE operations gets the same cells.

Levels.  Level k (root = level 0, cell edge ``D_m / 2^k``) holds the particles
with ``D_m / 2^k > rc >= D_m / 2^(k+1)``, i.e. ``k = ceil(log2(D_m / rc)) - 1``,
evaluated with exact power-of-two comparisons; cutoffs ``rc >= D_m / 2`` (in
particular ``rc >= D_m``) go to level 0.  A level-k cell is therefore strictly
larger than the cutoff of every particle on level k >= 1, so all partners of a
level-k particle on levels >= k lie in the 3^d stencil of cells around it.
``maxlevel`` is the deepest level that holds a particle (0-based, inclusive);
the paper's ``maxlevel`` of Algorithm 1 is our ``maxlevel + 1`` (number of levels).

Level-order index J(c): see :mod:`arpy.reference.ar_keys`.

The ``cells`` table.  ``cells[J] = (first, last)`` for every cell J that holds
at least one particle *on its own level*; the range is HALF-OPEN and 0-based
into the sorted particle array: the particles of cell J are
``order[first:last]`` (a 1-based closed Fortran range is ``(first + 1, last)``).
Cells with no particle on their own level are not in ``cells`` (Algorithm 1
step 4(b): "Empty leafs are not added").  The set ``finer`` holds the J of every
cell whose region contains at least one particle on a strictly finer level
(these are exactly the internal nodes visited by Algorithm 2).  A cell "exists"
in the sense of Op5 ("no particles in its region on this level and below") iff
``J in cells or J in finer``; descent in Algorithm 3 stops as soon as no cell
of the current 3^d stencil is in ``finer``.

Sorted order: levels ascending (= cutoffs descending, Algorithm 1 step 1), then
J ascending (Algorithm 2), and within a cell by descending cutoff, ties by the
original index (both construction methods here are stable).  Only the cell
ranges, not the order inside a cell, are meant to be compared with other
implementations.
"""

from __future__ import annotations

from itertools import product
from typing import Dict, FrozenSet, List, Optional, Sequence, Tuple

import numpy as np

from .ar_keys import MAX_LEVEL, in_sorted, level_first_index, level_of_index, morton_decode, morton_encode, root_edge
from .ar_pairs import check_cutoffs, check_skin, expand_ranges, to_csr, within

__all__ = ["ARCellListRef"]


class ARCellListRef:
    """Adaptive-resolution cell list (reference implementation).

    Parameters
    ----------
    x : array_like, shape (n, d), float
        Particle positions, d = 2 or 3 (any length unit).
    rc : array_like, shape (n,), float
        Interaction cutoff radius of each particle (same unit as ``x``), > 0.
    domain : (lo, hi) of shape (d,) each, optional
        Box that contains every particle (``lo <= x <= hi``, else ValueError).
        Default: bounding box of the particles.  It is made cubic with edge
        ``D_m = max(hi - lo)`` anchored at ``lo`` (see module docstring).
    method : {"sort", "recursive"}
        How Phase II is done.  ``"recursive"`` runs Algorithm 2 literally
        (recursive stable partitions along each axis); ``"sort"`` computes
        J for every particle and does one stable sort by J.  Both give the
        same ``order``, ``cells`` and ``finer``.

    Attributes
    ----------
    x, rc : arrays
        Copies of the input (original particle order).
    n, d : int
        Number of particles, dimension.
    lo : array (d,)
        Lower corner of the cubic domain.
    edge : float
        Its edge D_m; ``hi = lo + edge``.
    level : int64 array (n,)
        Tree level of each particle (original indexing).
    maxlevel : int
        Deepest level that holds a particle (0-based).
    order : int64 array (n,)
        Sorted position -> original particle index.
    rank : int64 array (n,)
        Original index -> sorted position (inverse of ``order``).
    cell_of : int64 array (n,)
        Level-order index J of the cell of each particle.
    cells : dict
        int -> (first, last), half-open 0-based ranges into ``order`` for the cells holding
        particles on their own level.
    finer : frozenset of int
        Cells whose region holds particles on finer levels.
    level_start : int64 array (maxlevel + 2,)
        Particles of level k are ``order[level_start[k]:level_start[k+1]]``.
    """

    # ------------------------------------------------------------------ build
    def __init__(self, x: np.ndarray, rc: np.ndarray,
                 domain: Optional[Tuple[Sequence[float], Sequence[float]]] = None,
                 method: str = "sort") -> None:
        x = np.array(x, dtype=np.float64, copy=True)
        if x.ndim != 2 or x.shape[1] not in (2, 3):
            raise ValueError(f"x must have shape (n, 2) or (n, 3), got {x.shape}")
        n, d = x.shape
        if n == 0:
            raise ValueError("empty particle set: at least one particle is needed")
        if not np.all(np.isfinite(x)):
            raise ValueError("x contains NaN or Inf")
        rc = check_cutoffs(rc, n, "rc").copy()
        if method not in ("sort", "recursive"):
            raise ValueError(f"unknown method {method!r} (use 'sort' or 'recursive')")

        if domain is None:
            lo = x.min(axis=0)
            hi = x.max(axis=0)
        else:
            lo = np.array(domain[0], dtype=np.float64).reshape(-1)
            hi = np.array(domain[1], dtype=np.float64).reshape(-1)
            if lo.shape != (d,) or hi.shape != (d,):
                raise ValueError(f"domain bounds must have shape ({d},)")
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
                raise ValueError("domain bounds must be finite")
            edge = float(np.max(hi - lo))
            if np.any(hi < lo) or not edge > 0.0:
                raise ValueError("domain must satisfy lo <= hi with a positive extent")
            outside = np.any((x < lo) | (x > hi), axis=1)
            if np.any(outside):
                i = int(np.flatnonzero(outside)[0])
                raise ValueError(f"particle {i} at {x[i]} lies outside the domain [{lo}, {hi}]")
        self._build(x, rc, lo, root_edge(float(np.max(hi - lo)), rc, x.shape[1]), method)

    def _build(self, x: np.ndarray, rc: np.ndarray, lo: np.ndarray, edge: float,
               method: str) -> None:
        """Algorithm 1 on validated input, cube ``[lo, lo + edge]^d``."""
        n, d = x.shape
        self.x: np.ndarray = x
        self.rc: np.ndarray = rc
        self.n: int = n
        self.d: int = d
        self.lo: np.ndarray = lo.copy()
        self.edge: float = edge
        self.hi: np.ndarray = lo + edge
        self.method: str = method
        self._nchild = 1 << d
        # normalised coordinates in [0, 1]
        self._u: np.ndarray = np.clip((x - lo) / edge, 0.0, 1.0)

        # ---- Algorithm 1, phase I: sort by descending cutoff, assign levels
        level = self.level_of_cutoff(rc)
        maxlevel = int(level.max())
        if maxlevel > MAX_LEVEL[d]:
            raise ValueError(
                f"AR cell tree too deep: the smallest cutoff {rc.min():.6g} needs level "
                f"{maxlevel} for domain edge D_m = {edge:.6g}, but level-order indices J fit "
                f"int64 only up to level {MAX_LEVEL[d]} in {d}D "
                f"(resolution span D_m/min(rc) must stay below 2^{MAX_LEVEL[d] + 1})")
        self.level: np.ndarray = level
        self.maxlevel: int = maxlevel
        order0 = np.lexsort((np.arange(n), -rc))       # descending rc, ties by index
        assert np.all(np.diff(level[order0]) >= 0)

        # ---- per-particle cell index on its own level
        cell_of = np.empty(n, np.int64)
        for k in range(maxlevel + 1):
            sel = np.flatnonzero(level == k)
            if sel.size:
                cell_of[sel] = self._cell_index(self._u[sel], k)
        self.cell_of: np.ndarray = cell_of

        # ---- Algorithm 1, phase II
        if method == "sort":
            order = order0[np.argsort(cell_of[order0], kind="stable")]
            cells, finer = self._cells_from_order(order)
        else:
            order, cells, finer = self._algorithm2(order0)
        self.order: np.ndarray = order
        self.rank: np.ndarray = np.empty(n, np.int64)
        self.rank[order] = np.arange(n)
        self.cells: Dict[int, Tuple[int, int]] = cells
        self.finer: FrozenSet[int] = frozenset(finer)
        self.level_start: np.ndarray = np.searchsorted(
            level[order], np.arange(maxlevel + 2)).astype(np.int64)

        # sorted key arrays per level: the "hash table" for vectorised lookups
        keys = np.array(sorted(cells), dtype=np.int64)
        rng = np.array([cells[int(j)] for j in keys], dtype=np.int64).reshape(-1, 2)
        fk = np.array(sorted(self.finer), dtype=np.int64)
        self._keys: List[np.ndarray] = []
        self._first: List[np.ndarray] = []
        self._last: List[np.ndarray] = []
        self._fkeys: List[np.ndarray] = []
        for k in range(maxlevel + 1):
            a, b = level_first_index(k, d), level_first_index(k + 1, d)
            s = (keys >= a) & (keys < b)
            self._keys.append(keys[s])
            self._first.append(rng[s, 0])
            self._last.append(rng[s, 1])
            self._fkeys.append(fk[(fk >= a) & (fk < b)])

    def _cell_coords(self, u: np.ndarray, k: int) -> np.ndarray:
        """Integer coordinates of the level-k cells containing normalised points u (clamped)."""
        m = 1 << k
        return np.minimum(np.floor(u * m).astype(np.int64), m - 1)

    def _cell_index(self, u: np.ndarray, k: int) -> np.ndarray:
        """J of the level-k cells containing normalised points u (m, d) in [0, 1]."""
        return level_first_index(k, self.d) + morton_encode(self._cell_coords(u, k), k, self.d)

    def _cells_from_order(self, order: np.ndarray) -> Tuple[Dict[int, Tuple[int, int]], set]:
        """cells table from runs of equal J in sorted order; finer set from ancestors."""
        js = self.cell_of[order]
        uniq, first, count = np.unique(js, return_index=True, return_counts=True)
        cells = {int(j): (int(a), int(a + c)) for j, a, c in zip(uniq, first, count)}
        finer: set = set()
        for k in range(self.maxlevel):
            sel = np.flatnonzero(self.level > k)
            finer.update(int(j) for j in np.unique(self._cell_index(self._u[sel], k)))
        return cells, finer

    def _algorithm2(self, order0: np.ndarray):
        """Phase II by literal recursion (Algorithm 2), one call chain per level."""
        d, nc = self.d, self._nchild
        perm = order0.copy()
        u = self._u
        cells: Dict[int, Tuple[int, int]] = {}
        finer: set = set()
        lev = self.level[perm]

        def recurse(a: int, b: int, J: int, lo_u: np.ndarray, h: float,
                    curr: int, target: int) -> None:
            m = lo_u + 0.5 * h                       # centre of cell J (exact dyadic)
            segs = [(a, b)]
            for i in range(d):                       # step 3: split along each axis
                new = []
                for s, e in segs:
                    seg = perm[s:e]
                    below = u[seg, i] < m[i]
                    perm[s:e] = np.concatenate((seg[below], seg[~below]))
                    t = s + int(below.sum())
                    new += [(s, t), (t, e)]
                segs = new
            for l, (s, e) in enumerate(segs):
                if s == e:                           # empty leaf: not added, no recursion
                    continue
                child = J * nc - nc + 2 + l           # Op3
                bits = np.array([(l >> (d - 1 - i)) & 1 for i in range(d)], float)
                clo = lo_u + bits * (0.5 * h)
                if curr == target:
                    cells[child] = (s, e)
                else:
                    finer.add(child)
                    recurse(s, e, child, clo, 0.5 * h, curr + 1, target)

        for k in range(self.maxlevel + 1):
            a = int(np.searchsorted(lev, k, side="left"))
            b = int(np.searchsorted(lev, k, side="right"))
            if a == b:
                continue
            if k == 0:
                cells[1] = (a, b)                    # level 0: the root cell, no partition
            else:
                finer.add(1)
                recurse(a, b, 1, np.zeros(d), 1.0, 1, k)
        return perm, cells, finer

    # ------------------------------------------------------- level and cells
    def level_of_cutoff(self, rc: np.ndarray | float) -> np.ndarray:
        """Tree level of cutoff(s) ``rc``: the k >= 0 with D_m/2^k > rc >= D_m/2^(k+1).

        Cutoffs ``rc >= D_m/2`` give 0.  Exact (power-of-two scaling only).
        Returns an int64 array of the shape of ``rc``.
        """
        rc = np.asarray(rc, dtype=np.float64)
        D = self.edge
        with np.errstate(divide="ignore", over="ignore"):
            est = np.ceil(np.log2(D / rc)) - 1.0
        k = np.clip(np.nan_to_num(est, nan=0.0, posinf=2000.0), 0, 2000).astype(np.int64)
        # correct the log2 estimate with exact power-of-two comparisons
        while True:                                   # need rc >= D/2^(k+1)
            up = np.ldexp(rc, (k + 1).astype(np.int32)) < D
            if not np.any(up):
                break
            k = k + up
        while True:                                   # need rc < D/2^k unless k == 0
            down = (k > 0) & (np.ldexp(rc, k.astype(np.int32)) >= D)
            if not np.any(down):
                break
            k = k - down
        return k

    def cell_level(self, J: int) -> int:
        """Level of the cell with level-order index J (J >= 1)."""
        J = int(J)
        if J < 1:
            raise ValueError(f"invalid cell index {J}")
        return level_of_index(J, self.d)

    def cell_coords(self, J: int) -> Tuple[int, Tuple[int, ...]]:
        """(level, integer coordinates) of cell J; coordinates in [0, 2^level)."""
        k = self.cell_level(J)
        return k, morton_decode(int(J) - level_first_index(k, self.d), k, self.d)

    def cell_from_coords(self, k: int, coords: Sequence[int]) -> Optional[int]:
        """J of the level-k cell with integer coordinates ``coords``; None if outside."""
        m = 1 << k
        c = [int(ci) for ci in coords]
        if len(c) != self.d:
            raise ValueError(f"coords must have {self.d} entries")
        if any(ci < 0 or ci >= m for ci in c):
            return None
        code = 0
        for b in range(k):
            for i in range(self.d):
                code |= ((c[i] >> b) & 1) << (self.d * b + self.d - 1 - i)
        return level_first_index(k, self.d) + code

    def cell_region(self, J: int) -> Tuple[np.ndarray, np.ndarray]:
        """Physical lower and upper corners of cell J, each shape (d,)."""
        k, c = self.cell_coords(J)
        h = self.edge / (1 << k)
        lo = self.lo + np.asarray(c, float) * h
        return lo, lo + h

    def cell_center_u(self, J: int) -> np.ndarray:
        """Centre of cell J in normalised coordinates (exact dyadic numbers)."""
        k, c = self.cell_coords(J)
        return (2.0 * np.asarray(c, float) + 1.0) / float(1 << (k + 1))

    # ---------------------------------------------------------- Op1 - Op5
    def find_cell(self, point: Sequence[float], level: int) -> Optional[int]:
        """Op1: J of the level-``level`` cell containing ``point`` (shape (d,)).

        Traverses the tree from the root comparing with cell centres, as in the
        paper.  The cell need not exist in ``cells``.  Returns None if the point
        lies outside the cubic domain.  Points on an upper face go to the last
        cell along that axis.
        """
        u = (np.asarray(point, dtype=np.float64) - self.lo) / self.edge
        if u.shape != (self.d,):
            raise ValueError(f"point must have shape ({self.d},)")
        if np.any(u < 0.0) or np.any(u > 1.0) or not np.all(np.isfinite(u)):
            return None
        return self._find_cell_u(u, int(level))

    def _find_cell_u(self, u: np.ndarray, level: int) -> int:
        """Op1 in normalised coordinates: descend from the root ``level`` times."""
        d, nc = self.d, self._nchild
        J = 1
        lo_u = np.zeros(d)
        h = 1.0
        for _ in range(level):
            m = lo_u + 0.5 * h                      # centre of the current cell
            bits = (u >= m)
            l = 0
            for i in range(d):
                l |= int(bits[i]) << (d - 1 - i)
            J = J * nc - nc + 2 + l                  # Op3: child number l
            lo_u = lo_u + bits * (0.5 * h)
            h *= 0.5
        return J

    def _child_containing(self, J: int, u: np.ndarray) -> int:
        """Op3 + centre test: the child of J that contains the normalised point u."""
        m = self.cell_center_u(J)
        l = 0
        for i in range(self.d):
            l |= int(u[i] >= m[i]) << (self.d - 1 - i)
        return self.children(J)[l]

    def find_cell_for_cutoff(self, point: Sequence[float], rc: float) -> Optional[int]:
        """Op1 with a cutoff: cell of ``point`` on the level of cutoff ``rc``."""
        return self.find_cell(point, int(self.level_of_cutoff(rc)))

    def cell_range(self, J: int) -> Optional[Tuple[int, int]]:
        """Op2: half-open range (first, last) into ``order`` of cell J, or None."""
        return self.cells.get(int(J))

    def particles_in_cell(self, J: int) -> np.ndarray:
        """Op2: original indices of the particles of cell J on its own level (may be empty)."""
        r = self.cells.get(int(J))
        if r is None:
            return np.empty(0, np.int64)
        return self.order[r[0]:r[1]].copy()

    def children(self, J: int) -> List[int]:
        """Op3: the 2^d children ``J*2^d + l``, l = -2^d+2 .. 1 (in partition order)."""
        J = int(J)
        if self.cell_level(J) >= MAX_LEVEL[self.d]:
            raise ValueError(f"children of a level-{MAX_LEVEL[self.d]} cell would overflow int64")
        nc = self._nchild
        return [J * nc + l for l in range(-nc + 2, 2)]

    def parent(self, J: int) -> Optional[int]:
        """Op4: ``(J + 2^d - 2) // 2^d``; None for the root (J = 1)."""
        J = int(J)
        if J < 1:
            raise ValueError(f"invalid cell index {J}")
        if J == 1:
            return None
        return (J + self._nchild - 2) // self._nchild

    def neighbor_cells(self, J: int, existing_only: bool = False) -> List[int]:
        """Op5: indices of the (up to 3^d - 1) same-level cells adjacent to J.

        Computed from integer cell coordinates +-1, which is equivalent to the
        paper's "centre +- edge, then Op1" (exact in normalised coordinates).
        Cells outside the domain are omitted.  With ``existing_only`` only cells
        that exist (``cell_exists``) are returned.  Order: lexicographic offsets.
        """
        k, c = self.cell_coords(J)
        out = []
        for off in product((-1, 0, 1), repeat=self.d):
            if not any(off):
                continue
            Jn = self.cell_from_coords(k, [ci + oi for ci, oi in zip(c, off)])
            if Jn is not None and (not existing_only or self.cell_exists(Jn)):
                out.append(Jn)
        return out

    def has_finer(self, J: int) -> bool:
        """True iff the region of cell J holds particles on a level finer than J's."""
        return int(J) in self.finer

    def cell_exists(self, J: int) -> bool:
        """True iff cell J's region holds particles on its level or below (Op5 sense)."""
        J = int(J)
        return J in self.cells or J in self.finer

    # ---------------------------------------------------- Algorithm 3
    def _offsets(self) -> np.ndarray:
        return np.array(list(product((-1, 0, 1), repeat=self.d)), dtype=np.int64)

    def _pairs_vectorized(self) -> Tuple[np.ndarray, np.ndarray]:
        """Algorithm 3 (Verlet branch), level by level, for all particles at once.

        Returns sorted positions (finder p, partner q), each unordered pair once.
        A particle of level k is processed on level k with the half stencil
        (q > p in its own cell, neighbour cells with larger J) and then on every
        finer level delta with the full stencil around the level-delta cell that
        contains it, as long as its stencil on level delta-1 holds finer particles.
        """
        d = self.d
        us = self._u[self.order]
        xs = self.x[self.order]
        rs = self.rc[self.order]
        offs = self._offsets()
        zero = int(np.flatnonzero(~np.any(offs != 0, axis=1))[0])
        out_p: List[np.ndarray] = []
        out_q: List[np.ndarray] = []
        active = np.empty(0, np.int64)
        for lev in range(self.maxlevel + 1):
            new = np.arange(self.level_start[lev], self.level_start[lev + 1], dtype=np.int64)
            P = np.concatenate((active, new))
            if P.size == 0:
                continue
            is_new = np.arange(P.size) >= active.size
            m = 1 << lev
            first = level_first_index(lev, d)
            c = self._cell_coords(us[P], lev)
            selfJ = first + morton_encode(c, lev, d)
            keys, fa, fb, fkeys = self._keys[lev], self._first[lev], self._last[lev], self._fkeys[lev]
            descend = np.zeros(P.size, bool)
            for io, o in enumerate(offs):
                nc = c + o
                valid = np.all((nc >= 0) & (nc < m), axis=1)
                nJ = first + morton_encode(np.where(valid[:, None], nc, 0), lev, d)
                if fkeys.size:
                    f, _ = in_sorted(fkeys, nJ)
                    descend |= valid & f
                if keys.size == 0:                   # no particle on this level
                    continue
                found, pos = in_sorted(keys, nJ)
                found &= valid
                a, b = fa[pos], fb[pos]
                if io == zero:
                    a = np.where(is_new, np.maximum(a, P + 1), a)   # q > p in own cell
                else:
                    found &= ~is_new | (nJ > selfJ)                  # half stencil on own level
                for pp, qq in expand_ranges(P[found], a[found], b[found]):
                    ok = within(xs[pp], rs[pp], xs[qq], rs[qq])
                    out_p.append(pp[ok])
                    out_q.append(qq[ok])
            active = P[descend]
        if not out_p:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        return np.concatenate(out_p), np.concatenate(out_q)

    def _pairs_loop(self) -> Tuple[np.ndarray, np.ndarray]:
        """Algorithm 3 (Verlet branch) literally, one particle at a time, via Op1-Op5.

        Slow (pure Python); meant for small sets and for reading.
        """
        xs = self.x[self.order]
        rs = self.rc[self.order]
        out_p: List[int] = []
        out_q: List[int] = []

        def scan(s: int, a: int, b: int) -> None:
            if b <= a:
                return
            q = np.arange(a, b)
            ok = within(np.broadcast_to(xs[s], (q.size, self.d)), np.full(q.size, rs[s]),
                         xs[q], rs[q])
            out_p.extend([s] * int(ok.sum()))
            out_q.extend(q[ok].tolist())

        for s in range(self.n):
            p = int(self.order[s])
            k = int(self.level[p])
            up = self._u[p]
            J = self._find_cell_u(up, k)                         # 1. Op1
            first, last = self.cells[J]                          # Op2
            scan(s, s + 1, last)                                 # 2(b) q > p in c_k
            for Jn in self.neighbor_cells(J):                    # 2(a) Op5, J(n) > J(c_k)
                if Jn > J and Jn in self.cells:
                    scan(s, *self.cells[Jn])
            Jd = J
            for _delta in range(k + 1, self.maxlevel + 1):       # 4.
                stencil = [Jd] + self.neighbor_cells(Jd)
                if not any(Jc in self.finer for Jc in stencil):  # early stop: nothing below
                    break
                Jd = self._child_containing(Jd, up)              # 4(a) Op3
                for Jc in [Jd] + self.neighbor_cells(Jd):        # 4(b) Op5, 4(c) Op2
                    r = self.cells.get(Jc)
                    if r is not None:
                        scan(s, *r)
        return np.asarray(out_p, np.int64), np.asarray(out_q, np.int64)

    def _with_skin(self, skin: float) -> "ARCellListRef":
        """The same domain cube, rebuilt with cutoffs rc + skin (Verlet-list skin)."""
        if skin == 0.0:
            return self
        other = ARCellListRef.__new__(ARCellListRef)
        other._build(self.x, self.rc + skin, self.lo, self.edge, self.method)  # same cube
        return other

    def verlet_list(self, skin: float = 0.0, *, full: bool = False,
                    method: str = "vectorized",
                    halo_bits: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Verlet lists by Algorithm 3.

        Parameters
        ----------
        skin : float >= 0
            Safety margin; the rule becomes ``|x_p - x_q| <= min(rc_p, rc_q) + skin``
            and the tree is rebuilt (same domain) with cutoffs rc + skin.
        full : bool
            False (a half list): every unordered pair once, in the row of the particle
            that found it in Algorithm 3 (the coarser one; on equal levels the one
            earlier in sorted order or in the cell with smaller J).  True: both directions.
        method : {"vectorized", "loop"}
            Same result; "loop" follows Algorithm 3 particle by particle.
        halo_bits : (n,) int array, optional
            §2.3.1 ghost-ghost filter: 0 marks a real particle, otherwise bit i is
            set iff the ghost lies in the halo layer along axis i.  A pair of two
            ghosts is kept only if the AND of their bit strings is 0.

        Returns
        -------
        offsets : (n+1,) int64 and indices : int64 CSR arrays, original indexing,
        each row sorted ascending.
        """
        skin = check_skin(skin)
        cl = self._with_skin(skin)
        if method == "vectorized":
            ps, qs = cl._pairs_vectorized()
        elif method == "loop":
            ps, qs = cl._pairs_loop()
        else:
            raise ValueError(f"unknown method {method!r} (use 'vectorized' or 'loop')")
        rows, cols = cl.order[ps], cl.order[qs]
        if halo_bits is not None:
            hb = np.asarray(halo_bits, dtype=np.int64)
            if hb.shape != (self.n,):
                raise ValueError(f"halo_bits must have shape ({self.n},)")
            a, b = hb[rows], hb[cols]
            keep = (a == 0) | (b == 0) | ((a & b) == 0)
            rows, cols = rows[keep], cols[keep]
        if full:
            rows, cols = np.concatenate((rows, cols)), np.concatenate((cols, rows))
        return to_csr(rows, cols, self.n)

    def cross_list(self, x_query: np.ndarray, rc_query: np.ndarray,
                   skin: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
        """Neighbours in this (reference) set of other query points.

        Row i lists every reference particle q (original index) with
        ``|x_query_i - x_q| <= min(rc_query_i, rc_q) + skin``.  Query points may
        lie anywhere (also outside the domain).  For every level j the 3^d
        stencil of the level-j cell containing the query point is searched
        (levels below the query's own level are its ancestors, Op4; finer ones
        its descendants, Op3); on level 0 all level-0 particles are candidates
        (their cutoffs may exceed D_m).

        Returns CSR ``offsets`` (m+1,) int64, ``indices`` int64, rows sorted.
        """
        skin = check_skin(skin)
        xq = np.ascontiguousarray(x_query, dtype=np.float64)
        if xq.ndim != 2 or xq.shape[1] != self.d:
            raise ValueError(f"x_query must have shape (m, {self.d}), got {xq.shape}")
        if not np.all(np.isfinite(xq)):
            raise ValueError("x_query contains NaN or Inf")
        mq = xq.shape[0]
        rq = check_cutoffs(rc_query, mq, "rc_query") + skin
        cl = self._with_skin(skin)
        d = self.d
        xs = cl.x[cl.order]
        rs = cl.rc[cl.order]
        uq = np.clip((xq - cl.lo) / cl.edge, -2.0, 3.0)
        inside = (uq >= 0.0) & (uq <= 1.0)
        offs = cl._offsets()
        qidx = np.arange(mq, dtype=np.int64)
        out_r: List[np.ndarray] = []
        out_c: List[np.ndarray] = []

        def emit(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
            for pp, qq in expand_ranges(p, a, b):
                ok = within(xq[pp], rq[pp], xs[qq], rs[qq])
                out_r.append(pp[ok])
                out_c.append(qq[ok])

        for lev in range(cl.maxlevel + 1):
            keys = cl._keys[lev]
            if keys.size == 0:
                continue
            if lev == 0:
                a0, b0 = cl.cells[1]
                emit(qidx, np.full(mq, a0, np.int64), np.full(mq, b0, np.int64))
                continue
            m = 1 << lev
            first = level_first_index(lev, d)
            c = np.floor(uq * m).astype(np.int64)
            c = np.where(inside, np.minimum(c, m - 1), c)      # upper face -> last cell
            for o in offs:
                nc = c + o
                valid = np.all((nc >= 0) & (nc < m), axis=1)
                nJ = first + morton_encode(np.where(valid[:, None], nc, 0), lev, d)
                found, pos = in_sorted(keys, nJ)
                found &= valid
                emit(qidx[found], cl._first[lev][pos[found]], cl._last[lev][pos[found]])
        if out_r:
            rows = np.concatenate(out_r)
            cols = cl.order[np.concatenate(out_c)]
        else:
            rows = cols = np.empty(0, np.int64)
        return to_csr(rows, cols, mq)

    # ------------------------------------------------------------- helpers
    def __repr__(self) -> str:
        return (f"ARCellListRef(n={self.n}, d={self.d}, edge={self.edge:.6g}, "
                f"maxlevel={self.maxlevel}, cells={len(self.cells)}, finer={len(self.finer)})")
