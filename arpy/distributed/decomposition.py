"""Which rank owns each particle: the ranks' boxes (:class:`Decomposition`) and recursive coordinate
bisection (:func:`bisect`).

:func:`bisect`: recursive coordinate bisection weighted by particle count (or any weight), no
minimum box size.  Each cut splits the longest edge of the current box; a particle on a cut plane
belongs to the upper side (on the upper face of the box, to the box below), so ownership is a
property of the boxes (:meth:`Decomposition.locate`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .. import _bridge
from .._validate import as_positions, check_count, check_index, column_extremes, non_finite_rows
from ..domain import Domain, as_domain
from .comm import Comm, SerialComm, order_keys

__all__ = ["Decomposition", "bisect", "bounding_box", "box_gap", "box_gap2"]


@dataclass(frozen=True)
class Decomposition:
    """Boxes of the ranks: rank r owns the points with ``lo[r] <= x < hi[r]`` along every axis (``<=``
    at the upper face of the decomposed box; where boxes share that face, the first rank).  Along the
    ``open`` axes the boxes on a face of the decomposed box reach on to infinity beyond it
    (:meth:`box`), so that a particle a time step carries past a wall stays owned, and its ghosts are
    found, as inside.

    Attributes
    ----------
    lo, hi : array (P, d)
        The boxes' lower and upper corners; together they tile ``[lo.min(0), hi.max(0)]``.
    open : array (d,) bool or None
        The axes along which the outer boxes reach beyond the decomposed box (:func:`bisect`: every
        axis that is not periodic); None: none.
    """

    lo: np.ndarray
    hi: np.ndarray
    open: np.ndarray | None = None

    @property
    def parts(self) -> int:
        """The number of ranks P."""
        return int(self.lo.shape[0])

    def box(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """The region rank r owns: its box, with the faces it has on the decomposed box's faces moved
        out to -+infinity along the ``open`` axes.  (lo, hi), each (d,).  IndexError for r outside
        [0, P) (a negative r is not counted from the end)."""
        r = check_index("r", r, self.parts, "ranks")
        lo, hi = self.boxes()
        return lo[r], hi[r]

    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Every rank's region (:meth:`box`) at once: (lo, hi), each (P, d) (computed once)."""
        return self._regions

    @cached_property
    def _regions(self) -> tuple[np.ndarray, np.ndarray]:
        if self.open is None:
            return self.lo, self.hi
        return (np.where(self.open & (self.lo == self.lo.min(axis=0)), -np.inf, self.lo),
                np.where(self.open & (self.hi == self.hi.max(axis=0)), np.inf, self.hi))

    def reaching(self, lo: np.ndarray, hi: np.ndarray, reach: float = 0.0, period: np.ndarray | None = None
                 ) -> np.ndarray:
        """The ranks (int64, ascending) whose regions (:meth:`box`, closed) come within ``reach`` of the box
        [lo, hi] (each (d,)), along the axes with ``period`` > 0 also of its images shifted by one period
        either way: a superset of the ranks within ``reach`` of any point of [lo, hi], so that a search
        over the points and the ranks' boxes can test these ranks only (O(P) array operations instead of
        O(P) passes over the points).  Each axis's gap to a box is no larger than a point's in rounding
        too (rounding is monotone), and the distance is compared with a margin of 1e-9 of the reach."""
        blo, bhi = self.boxes()
        g2 = np.zeros(self.parts)
        for i in range(blo.shape[1]):
            shifts = (0.0,) if period is None or not period[i] > 0 else (-period[i], 0.0, period[i])
            with np.errstate(invalid="ignore"):              # (fmax: inf - inf, NaN, counts as no gap)
                g = np.min([np.fmax(np.fmax(blo[:, i] - (hi[i] + s), (lo[i] + s) - bhi[:, i]), 0.0)
                            for s in shifts], axis=0)
            g2 = g2 + g * g
        return np.flatnonzero(g2 <= (reach * (1.0 + 1e-9)) ** 2)

    def reaching_points(self, points: np.ndarray, reach: float = 0.0, period: np.ndarray | None = None
                        ) -> np.ndarray:
        """:meth:`reaching` of the bounding box of the finite ``points`` (m, d): the ranks whose boxes can
        come within ``reach`` of one of them (none if no point is finite: a point that is not finite
        lies within no distance of a box)."""
        box = _finite_extremes(points)
        if box is None:
            return np.zeros(0, np.int64)
        return self.reaching(*box, reach, period)

    def locate(self, x: np.ndarray) -> np.ndarray:
        """The rank owning each point, int64 (n,); -1 outside the decomposed box (along an axis that is
        not ``open``; an infinite coordinate along it lies in the outer boxes there).  Only the boxes that
        meet the points' bounding box are tested."""
        xs = as_positions(x)
        box = _finite_extremes(xs, nan_only=True)                 # (no other point lies in a box)
        if box is None:
            return np.full(xs.shape[0], -1, np.int64)
        ranks = self.reaching(*box).astype(np.int64)
        lo, hi = self.boxes()
        return _bridge.box_owners(xs, lo[ranks], hi[ranks], self.hi.max(axis=0), ranks)

    def deal(self, points: np.ndarray, most: float = np.inf) -> tuple[np.ndarray, float]:
        """A rank for each of the ``points`` (m, d), the same list on every rank, so that the ranks get
        about as many points each: a point goes to the rank owning it (:meth:`locate`), or to the rank
        of a box touching that one which holds fewer points.  In passes over the pairs of touching boxes,
        the fuller one gives half the difference, the points it owns nearest to the other box first
        (within ``most`` of it), until touching boxes differ by at most one point (or can give no more):
        a rank is handed only points by the faces of its box, and the counts even out along chains of
        boxes.  For work at points that only needs the particles near them (a rank holds those within a
        skin of its box): the points of a dense part of the set are shared by the neighbouring ranks.
        Returns (the ranks, int64 (m,); the skin, the farthest any point lies from its rank's box, 0 if
        none moved).  Points outside every box keep -1."""
        xs = as_positions(points)
        rank = self.locate(xs)
        P = self.parts
        counts = np.bincount(rank[rank >= 0], minlength=P)
        owned = [np.flatnonzero(rank == r) for r in range(P)]
        touching = [[r for r in self.reaching(self.lo[s], self.hi[s]).tolist() if r != s] for s in range(P)]
        skin2, moving = 0.0, True
        while moving:
            moving = False
            for s in range(P):
                for r in touching[s]:
                    k = (int(counts[r]) - int(counts[s])) // 2
                    if k <= 0:
                        continue
                    cand = owned[r][rank[owned[r]] == r]
                    g2 = box_gap2(xs[cand], *self.box(s))
                    near = np.flatnonzero(g2 <= most * most)
                    moved = near[np.argsort(g2[near], kind="stable")[:k]]
                    if moved.size:
                        rank[cand[moved]] = s
                        counts[r] -= moved.size
                        counts[s] += moved.size
                        skin2 = max(skin2, float(g2[moved].max()))
                        moving = True
        skin = float(np.sqrt(skin2))
        while skin * skin < skin2:                  # (the halo's measure holds every point it moved)
            skin = float(np.nextafter(skin, np.inf))
        return rank, skin


def box_gap2(y: np.ndarray, lo: np.ndarray, hi: np.ndarray, period: np.ndarray | None = None) -> np.ndarray:
    """Squared distance from points y (m, d) to the box [lo, hi], summed axis by axis from 0 (the
    list builders' order); along the axes with ``period`` > 0, to the nearest of the box's images one
    period either way (no farther than any point of the box by the minimum image)."""
    g2 = np.zeros(y.shape[0])
    for i in range(y.shape[1]):
        shifts = (-period[i], 0.0, period[i]) if period is not None and period[i] > 0 else (0.0,)
        g = np.min([np.maximum(np.maximum(lo[i] - (y[:, i] + s), (y[:, i] + s) - hi[i]), 0.0) for s in shifts], axis=0)
        g2 = g2 + g * g
    return g2


def box_gap(y: np.ndarray, lo: np.ndarray, hi: np.ndarray, period: np.ndarray | None = None) -> np.ndarray:
    """Distance from points y (m, d) to the box [lo, hi]: the square root of :func:`box_gap2`."""
    return np.sqrt(box_gap2(y, lo, hi, period))


def _finite_extremes(points: np.ndarray, nan_only: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """(least, largest) coordinates (d,) of the rows of ``points`` (m, d) that are finite (``nan_only``:
    that hold no NaN), or None if there is none: the :func:`bounding_box` of the points where every entry
    is finite (the search's points, nearly always), else that of a filtered copy."""
    lo, hi = bounding_box(points)
    if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)):
        return lo, hi
    keep = points[~np.any(np.isnan(points), axis=1) if nan_only else np.all(np.isfinite(points), axis=1)]
    return bounding_box(keep) if keep.shape[0] else None


#: Keys :func:`bisect` tries per exchange in its search for a cut (one allgather narrows the range
#: PROBES-fold: 16 exchanges for the 64 bits of a coordinate).
PROBES = 16


def bisect(x: np.ndarray, parts: int, *, weights: np.ndarray | None = None, domain: Domain | None = None,
           comm: Comm | None = None) -> tuple[Decomposition, np.ndarray]:
    """Recursive coordinate bisection of particles into ``parts`` boxes of about equal weight.

    Each cut halves the longest edge of its box at a particle coordinate: with v0 the smallest
    coordinate whose particles at or below it carry at least the lower boxes' share of the weight,
    the cut is the next coordinate above v0, so the lower box takes every particle at or below v0
    (all of them if none is above).  Every decision comes from global sums, minima and maxima, so
    the boxes do not depend on how the particles are spread over the ranks of ``comm``.

    Parameters
    ----------
    x : array (n, d)
        Positions (this rank's particles).
    parts : int
        The number of boxes P >= 1 (any integer; a box of p is cut into p // 2 and p - p // 2, with
        the weight split in that proportion).
    weights : int array (n,), optional
        Cost per particle, non-negative integers (default: 1, balancing by count; integers keep the
        global sums exact).
    domain : Domain, optional
        The box to decompose (default: the particles' global bounding box).
    comm : Comm, optional
        The ranks holding the particles (default: this process alone).

    Returns
    -------
    (Decomposition, array (n,))
        The boxes and the box of each of this rank's particles (as ``Decomposition.locate(x)``).
    """
    comm = comm or SerialComm()
    xs = as_positions(x)
    n, d = xs.shape
    check_count("parts", parts)
    dom = as_domain(domain, d)
    w = np.ones(n, np.int64) if weights is None else np.asarray(weights)
    if w.shape != (n,) or not np.issubdtype(w.dtype, np.integer) or np.any(w < 0):
        raise ValueError(f"weights must be non-negative integers with shape ({n},)")
    w = w.astype(np.int64)
    bad = non_finite_rows(xs)
    total = comm.sum(int(bad.size))                      # (every rank refuses, not only the one holding them)
    if total:
        where = f", the first of particle {bad[0]}" if comm.size == 1 else (
            f", {bad.size} on this rank (the first of its particle {bad[0]})" if bad.size else " (on other ranks)")
        raise ValueError(f"bisect: {total} position{'s' if total > 1 else ''} not finite (NaN or Inf){where}; the "
                         "boxes are cut at finite positions only")
    if dom.bounded:
        assert dom.lo is not None and dom.hi is not None
        lo0, hi0 = dom.lo.astype(np.float64), dom.hi.astype(np.float64)
    else:
        mins, maxs = bounding_box(xs)
        lo0, hi0 = comm.min(mins), comm.max(maxs)
        lo0, hi0 = np.where(np.isfinite(lo0), lo0, 0.0), np.where(np.isfinite(hi0), hi0, 0.0)
    box_lo, box_hi = np.zeros((int(parts), d)), np.zeros((int(parts), d))
    owner = np.zeros(n, np.int64)

    # the boxes cut depth first, the lower half first, in the same order on every rank (collective
    # calls); a work list, not a recursive closure: that would be a reference cycle holding x, w and
    # owner until the garbage collector's next full pass
    todo = [(np.arange(n, dtype=np.int64), lo0.copy(), hi0.copy(), int(parts), 0)]
    while todo:
        idx, lo, hi, p, first = todo.pop()
        if p == 1:
            box_lo[first], box_hi[first] = lo, hi
            owner[idx] = first
            continue
        axis = int(np.argmax(hi - lo))
        v, wi = xs[idx, axis], w[idx]
        target = comm.sum(int(wi.sum())) * (p // 2)           # the lower share, times p (integers)
        keys = order_keys(v)
        order = np.argsort(keys, kind="stable")
        sorted_keys, below = keys[order], np.concatenate([[0], np.cumsum(wi[order])])
        a, b = int(order_keys(np.array([lo[axis]]))[0]), int(order_keys(np.array([hi[axis]]))[0])
        while a < b:            # the least key with p * W(x <= key) >= target: PROBES keys per exchange
            probes = sorted({a + (b - a) * j // PROBES for j in range(1, PROBES)})
            mine = below[np.searchsorted(sorted_keys, np.array(probes, np.int64), side="right")]
            ok = [int(t) * p >= target for t in comm.add(mine)]
            if not any(ok):
                a = probes[-1] + 1
            else:
                i = ok.index(True)
                a, b = (probes[i - 1] + 1 if i else a), probes[i]
        v0 = float(order_keys(np.array([a], np.int64), back=True)[0])
        above = v[v > v0]
        cut = float(comm.min(np.array([above.min() if above.size else np.inf]))[0])
        if not np.isfinite(cut):
            cut = hi[axis]
            low = np.ones(idx.size, bool)
        else:
            low = v < cut
        left_hi, right_lo = hi.copy(), lo.copy()
        left_hi[axis], right_lo[axis] = cut, cut
        todo += [(idx[~low], right_lo, hi, p - p // 2, first + p // 2), (idx[low], lo, left_hi, p // 2, first)]
    periodic = np.asarray(dom.periodic, bool) if dom.bounded else np.zeros(d, bool)
    return Decomposition(box_lo, box_hi, ~periodic), owner


def bounding_box(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the points x (n, d); an empty box (lo = inf, hi = -inf) without points."""
    d = x.shape[1]
    return column_extremes(x) if x.shape[0] else (np.full(d, np.inf), np.full(d, -np.inf))
