"""DC-PSE in a domain: ghost sources at the boundary, and the repair of stencils that fail or run wild.

:class:`DomainDCPSE` is the operator the adaptive method uses: DC-PSE (:class:`arpy.dcpse.kernel.DCPSE`, the
kernel of Appendix A of Reboux et al. 2012) with the particles' periodic images and mirror images
across walls as extra sources (even images: homogeneous Neumann, §2.4), and a repair policy for
the collocation points whose stencil the moment conditions cannot use as it is:

* **failed rows** (too few neighbours, singular or ill-conditioned moments, e.g. a particle in a hole
  of a set stretched by a flow): up to ``widen`` rounds, each rebuilding the row in the off-particle
  form from every source within 1.5 times the previous core size (gather rule);
* **wild rows** (off the particles, Lebesgue constant ``sum_q |zeta_q|`` above ``max_lebesgue``: an
  exact fit through barely enough neighbours, which amplifies data errors; at the particles, Laplacian
  rows whose Gershgorin radius is above ``max_row_sum``, :func:`~arpy.dcpse.rows.wild_rows`: a
  near-singular moment matrix that has not failed): rebuilt at order m from the 1.5x wider gather, and
  those still wild at order m - 1;
* **mildly wild rows** (constant in (``MILD_LEBESGUE``, ``max_lebesgue``]): rebuilt at order m from
  the wider gather only where that gather stays proportional to the row's own stencil (at most
  ``MILD_GATHER`` x 1.5^d x its own neighbours) and lowers the constant;
* **flooded gathers**: a wider gather holding more than ``MAX_GATHER`` x 1.5^d times the point's own
  neighbours has reached across a front the point's resolution does not see, into a much finer
  region, where an order-m fit can miss by several 1e-2; such a row is built at order m - 1 on the
  point's own stencil instead, where that one is sound.

The paper's own rule (§2.2: where the moment matrix is not invertible, randomly displace or insert
particles until it is) is in :mod:`arpy.dcpse.displace`; its operators are built without repair
(:data:`NO_REPAIR`).

:data:`REPAIR` is the policy a simulation uses for every operator.  :meth:`DomainDCPSE.interpolate`
carries a field from the old particles to the new ones, with the fall-backs a re-organization needs.
"""

from __future__ import annotations

import copy
from typing import Callable, Sequence, cast

import numpy as np
import scipy.sparse as sp

from .._validate import as_cutoffs, as_positions
from ..domain import Domain, as_domain, nearest
from ..lists.neighborlist import NeighborList, pairs_increasing
from ..lists.reuse import ReusedLists
from ..lists.search import cross_neighbor_list, neighbor_list, source_rows
from .boundary import Conditions
from .kernel import DCPSE, DegenerateStencilError
from .patched import Patched, Renumbered
from .rows import (LEBESGUE_MAX, MAX_GATHER, MILD_GATHER, MILD_LEBESGUE, NO_REPAIR, REPAIR, WIDE_GATHER, WIDEN, Repair,
                   abs_row_sums, bounded_apply, lebesgue_constants, wild_rows)

__all__ = ["DomainDCPSE", "LEBESGUE_MAX", "MAX_GATHER", "MILD_GATHER", "MILD_LEBESGUE", "NO_REPAIR", "REPAIR", "Repair",
           "WIDEN", "WIDE_GATHER", "bounded_apply", "lebesgue_constants"]


class DomainDCPSE:
    """DC-PSE operators of particles in a domain, with ghost sources and repaired stencils.

    Parameters
    ----------
    x : array (n, d)
        The particles (sources), inside the domain.
    eps : float or array (n,)
        Their core sizes (= cutoff radii), length unit of x.
    col_x : array (m, d) or None
        Collocation points.  None: the particles themselves; in free space the at-particle form
        ``sum_q eta_q (f_q - f_p)`` (Eq. A.8), with ghosts the off-particle form ``sum_q eta_q f_q``.
    col_eps : float or array (m,) or None
        Core sizes of the collocation points (default: that of the nearest source).
    domain : Domain or None
        Periodic axes add periodic images as sources, walls mirror images (homogeneous Neumann).
    order : int
        DC-PSE order m.
    strict : bool
        Raise :class:`arpy.DegenerateStencilError` if a point has no valid stencil after the repair;
        False: its rows are zero and it is listed in ``failed``.
    widen : int
        Repair rounds for failed points (and points with fewer than ``min_neighbors`` usable neighbours).
    min_neighbors : int
        Points with fewer usable neighbours are widened too.
    max_lebesgue : float or None
        Rebuild rows whose Lebesgue constant exceeds it (None: no such repair).  At the particles
        themselves (``col_x`` None) the interpolating kernel is the identity (its spline radii are at
        most half the distance to any other source, so every other source's spline term vanishes and
        the moment correction is zero): every constant is exactly 1 and no row is wild by it.
    max_row_sum : float or None
        At the particles, with the Laplacian among the ``operators``: rebuild as wild the rows whose
        Laplacian has ``sum_q |L_pq|`` above it (unit 1 / length^2; listed in ``heavy``; None: none;
        a simulation gives ``STABILITY / (nu dt)``: the rows that alone make its step unstable).
    operators : sequence or None
        The operators assembled with the stencils (see :class:`arpy.DCPSE`); None: the standard set.
        Others are assembled when first asked for.
    lists : ReusedLists or None
        At the particles (``col_x`` None): take the sources and neighbour lists from it (kept across
        calls).
    dirichlet : Conditions or None
        A field's conditions: its Dirichlet faces take boundary particles as sources instead of
        mirror images (:meth:`arpy.dcpse.boundary.Conditions.wall_points`), and the points within their
        core size of such a face one-sided stencils 2^(1/d) times as wide; :meth:`extend` then needs
        conditions with the same Dirichlet faces.  With ``ghosts``, the boundary particles are those of
        the particles and the ghosts (a periodic image's: the image of its particle's).
    ghosts : (array (g, d), array (g,)[, int array (g,)]) or None
        Sources besides the particles, with their core sizes, e.g. one rank's ghosts from the other
        ranks (:class:`arpy.distributed.DistributedDCPSE`), periodic images among them already
        shifted (the third array: a periodic image's shift, its place among {-1, 0, 1}^d with the
        first axis slowest, -1 for a particle itself; default all -1): no periodic images are made
        then, walls mirror the particles and these ghosts.  In a box (walls or periodic axes),
        without ``lists``; with ``col_x``, give ``col_eps``; :meth:`extend` and
        :meth:`interpolate` take values on the particles and then the ghosts (n + g,).
    only : callable, optional
        With ``ghosts``, without ``rows``: ``only(src_x, src_eps) ->`` the points (particles or collocation
        points; indices, ascending) whose rows are built, from the sources; the operators' rows are theirs.
    rows : callable, optional
        With ``ghosts`` at the particles: ``rows(x, eps, src_x, src_eps) ->`` the rows of the
        particles over the sources (the particles, the ghosts, then the mirror images made here),
        each source within the min rule (e.g. kept across calls,
        :meth:`arpy.distributed.kept.KeptGhosts.rows`); default: built here.
    keys : int array (n,) or (n + g,), optional
        A key per particle (and ghost): each row's sources go in the order this operator would
        sum them over all the particles numbered by key (particles by key, boundary particles by face
        and their particle's key, then periodic images by shift and as those, then mirror images by
        reflection and source), so that the sums do not
        depend on how the particles are numbered or spread over ranks, and with keys 0 .. n - 1
        equal those without keys; the nearest particles :meth:`interpolate` takes are chosen by
        (distance, key).

    Attributes
    ----------
    x : array (n, d)
        The particles; :meth:`extend` maps values on them to the sources.
    domain : Domain
        The domain of the particles.
    heavy : int array
        At the particles: the rows found wild by their weights and rebuilt (see ``max_row_sum``).

    The properties below give the sizes (:attr:`n_col`, :attr:`n_src`, :attr:`d`) and the points
    without a valid stencil (:attr:`failed`) or with rebuilt rows (:attr:`widened`).

    Examples
    --------
    The Laplacian of ``sin(2 pi x)`` on particles in a periodic box (their periodic images are
    the extra sources), and the interpolation of the field to new points:

    >>> import numpy as np
    >>> import arpy
    >>> box = arpy.Domain([1.0, 1.0], periodic=True)
    >>> def uniform(p):
    ...     return np.full(len(p), 0.05)
    >>> ps = arpy.self_organize(np.random.default_rng(0).random((400, 2)), uniform, domain=box, seed=0)
    >>> f = np.sin(2 * np.pi * ps.x[:, 0])
    >>> op = arpy.DomainDCPSE(ps.x, ps.eps, domain=box)
    >>> op.n_col == ps.n < op.n_src, op.failed.size
    (True, 0)
    >>> lap = op.laplacian() @ op.extend(f)
    >>> bool(np.abs(lap + 4 * np.pi ** 2 * f).max() < 0.05 * 4 * np.pi ** 2)
    True
    >>> new = np.random.default_rng(1).random((50, 2))
    >>> to_new = arpy.DomainDCPSE(ps.x, ps.eps, new, domain=box)
    >>> bool(np.abs(to_new.interpolate(f) - np.sin(2 * np.pi * new[:, 0])).max() < 1e-3)
    True
    """

    _rank: np.ndarray | None                   # (each source's place in key order; None: by index)

    def __init__(self, x: np.ndarray, eps: float | np.ndarray, col_x: np.ndarray | None = None,
                 col_eps: float | np.ndarray | None = None, *,
                 domain: Domain | None = None, order: int = 4, strict: bool = True, widen: int = 0,
                 min_neighbors: int = 0, max_lebesgue: float | None = None, max_row_sum: float | None = None,
                 operators: Sequence[object] | None = None, lists: ReusedLists | None = None,
                 dirichlet: Conditions | None = None, ghosts: tuple[np.ndarray, ...] | None = None,
                 keys: np.ndarray | None = None, rows: Callable[..., NeighborList] | None = None,
                 only: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> None:
        xs = as_positions(x)
        eps = as_cutoffs(eps, xs.shape[0])
        self.x, self.domain = xs, as_domain(domain, xs.shape[1])
        self._src = None
        self._sums: tuple[object, np.ndarray] | None = None     # (an operator set, its Laplacian's row sums)
        self._walls: tuple[np.ndarray, np.ndarray, Conditions] | None = None
        self._wall_src = np.zeros(0, np.int64)           # the particle (or ghost) of each boundary particle
        self._at_particles = col_x is None
        src_x, src_eps, nl = xs, eps, None
        self._n_values = xs.shape[0]                      # values extend() takes: particles (and ghosts)
        self._base_x: np.ndarray | None = None             # with ghosts: the particles and the ghosts
        self._base_shift: np.ndarray | None = None         # their periodic shifts (ids; -1: none)
        walls = dirichlet is not None and dirichlet.has_dirichlet
        if lists is not None and (walls or ghosts is not None):
            raise ValueError("reused lists (lists=) take neither ghosts= nor Dirichlet faces")
        if ghosts is not None:
            if not self.domain.bounded:
                raise ValueError("ghosts= is for operators in a box")
            if col_x is not None and col_eps is None:
                raise ValueError("ghosts= with collocation points needs their core sizes (col_eps)")
            gx = as_positions(ghosts[0])
            if gx.shape[1] != xs.shape[1]:
                raise ValueError(f"ghosts must have d = {xs.shape[1]} columns, got {gx.shape}")
            base_x, base_eps = np.concatenate([xs, gx]), np.concatenate([eps, as_cutoffs(ghosts[1], gx.shape[0])])
            self._n_values, self._base_x = base_x.shape[0], base_x
            shift = np.full(gx.shape[0], -1, np.int64) if len(ghosts) < 3 else np.asarray(ghosts[2], np.int64)
            if shift.shape != (gx.shape[0],):
                raise ValueError(f"ghosts: one shift per ghost ({gx.shape[0]}), got shape {shift.shape}")
            self._base_shift = np.concatenate([np.full(xs.shape[0], -1, np.int64), shift])
            keys = self._checked_keys(keys)
            if walls:                                     # (the boundary particles of the particles and ghosts)
                assert dirichlet is not None
                base_x, base_eps = self._boundary(dirichlet, base_x, base_eps, keys, self._base_shift)
            xm, self._src = self.domain.mirrors(base_x, base_eps, None if dirichlet is None or not walls
                                                else ~dirichlet.dirichlet_faces)
            src_x, src_eps = (np.concatenate([base_x, xm]), np.concatenate([base_eps, base_eps[self._src]])) \
                if self._src.size else (base_x, base_eps)
            if col_x is None:
                col_x, col_eps = xs, eps
                nl = None if rows is None else rows(xs, eps, src_x, src_eps)
        elif walls:
            assert dirichlet is not None
            base_x, base_eps = self._boundary(dirichlet, xs, eps, self._checked_keys(keys), None)
            xg, self._src = self.domain.ghosts(base_x, base_eps, ~dirichlet.dirichlet_faces)
            src_x, src_eps = np.concatenate([base_x, xg]), np.concatenate([base_eps, base_eps[self._src]])
            if col_x is None:
                col_x, col_eps = xs, eps
        elif lists is not None:
            if col_x is not None:
                raise ValueError("lists= is for operators at the particles (col_x None)")
            self._src, src_x, src_eps, nl = lists(xs, eps)
            if self._src is not None:                     # (the particles as the lists place them)
                col_x, col_eps = src_x[:xs.shape[0]], eps
        elif self.domain.bounded:
            xg, self._src = self.domain.ghosts(xs, eps)
            src_x, src_eps = np.concatenate([xs, xg]), np.concatenate([eps, eps[self._src]])
            if col_x is None:
                col_x, col_eps = xs, eps
        self.only: np.ndarray | None = None         # (with only: the points whose rows these are)
        if only is not None:
            if ghosts is None or rows is not None or col_x is None or col_eps is None:
                raise ValueError("only= is for operators with ghosts=, without rows=")
            self.only = np.asarray(only(src_x, src_eps), dtype=np.int64)
            col_x, col_eps = as_positions(col_x)[self.only], as_cutoffs(col_eps, len(col_x))[self.only]
            nl = cross_neighbor_list(col_x, col_eps, src_x, src_eps) if self._at_particles else None
        self._src_x, self._src_eps, self._order, self._max_lebesgue = src_x, src_eps, order, max_lebesgue
        self._max_row_sum = max_row_sum
        checked = self._checked_keys(keys)
        # (in index order: rows ascending by index are in source order, without keys or with ranks 0, 1, ...)
        self._rank, self._in_index_order = (None, True) if checked is None else self._source_rank(checked)
        if operators is not None and self._at_particles:
            operators = [o for o in operators if not (isinstance(o, str) and o.lower() == "interpolation")]
        self._operators = operators     # (the repairs assemble these too; others when asked for)
        ascending = nl is None and self._at_particles and col_x is not None
        if ascending:
            # the particles lead the sources: their rows from the sources' half list (rows ascending)
            nl = source_rows(src_x, src_eps, xs.shape[0])
        if self._rank is not None:                        # the default lists of DCPSE, in key order
            if nl is None and col_x is None:
                nl = neighbor_list(src_x, src_eps, method="auto", full=True)
            elif nl is None:
                assert col_x is not None
                if col_eps is None:                       # (DCPSE's default: the nearest source's core size)
                    col_eps = src_eps[nearest(src_x, y=as_positions(col_x))[1]]
                nl, ascending = cross_neighbor_list(col_x, col_eps, src_x, src_eps), True
            nl = self._ordered(nl, ascending)
        op = DCPSE(src_x, src_eps, col_x, col_eps, order=order, strict=strict and widen == 0, operators=operators,
                   neighbors=nl)
        self._cx, self._own_eps = op.col_x, op.col_eps
        self._nnb = op.n_neighbors.copy()
        self._reach = np.zeros(len(self._cx))              # the widest ball each row gathered from (0: none)
        if walls:
            op = self._one_sided(op, operators)
        self._unrepaired = op.failed
        self.heavy = np.zeros(0, dtype=np.int64)
        self._op = self._repair(op, widen, min_neighbors)
        if strict and self.failed.size:
            failed = self.failed
            raise DegenerateStencilError(f"DC-PSE: {failed.size} collocation points have no valid stencil even "
                                         f"after {widen} widening rounds: {failed[:10]}", failed,
                                         np.zeros(failed.size, int), np.zeros(failed.size, int),
                                         np.full(failed.size, np.inf))

    def _checked_keys(self, keys: np.ndarray | None) -> np.ndarray | None:
        """The keys given, int64 (one per value :meth:`extend` takes: particle and ghost), or None."""
        if keys is None:
            return None
        k, n = np.asarray(keys, dtype=np.int64), self._n_values
        if k.shape != (n,):
            raise ValueError(f"keys must have one entry per particle{' and ghost' if n > self.x.shape[0] else ''}"
                             f" ({n}), got shape {k.shape}")
        return k

    def _boundary(self, dirichlet: Conditions, x: np.ndarray, eps: np.ndarray, keys: np.ndarray | None,
                  group: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The points x (particles, ghosts) and their core sizes with the boundary particles of
        :meth:`~arpy.dcpse.boundary.Conditions.wall_points` after them (of coinciding ones the first by
        (face, key); only points of one periodic shift ``group`` coincide); each takes the core size of
        its particle."""
        wx, self._wall_src, wface = dirichlet.wall_points(x, eps, keys, group)
        self._walls = (wx, wface, dirichlet)
        return np.concatenate([x, wx]), np.concatenate([eps, eps[self._wall_src]])

    def _source_rank(self, k: np.ndarray) -> tuple[np.ndarray, bool]:
        """A distinct rank per source: the place it would have among the sources of this operator
        built over all the particles numbered by key (the order of :meth:`arpy.Domain.ghosts`:
        particles by key, then boundary particles by face and their particle's key; periodic images by
        shift, then as those; mirror images by reflection, then by their source's place, particles
        before images).  A boundary particle's key is thus (face, key of its particle), after every
        particle: any rank computes it from the particles it holds.  Returns (the ranks, whether they
        are known to be 0 .. n_src - 1: the sources in that order already)."""
        src_x, d, n = self._src_x, self._src_x.shape[1], self._n_values
        n_src, ws = src_x.shape[0], self._wall_src
        n_base = n + ws.size
        base_shift = np.full(n, -1, np.int64) if self._base_shift is None else self._base_shift
        if n_src == n and pairs_increasing(base_shift, k):    # (particles, ghosts given: by shift, then key)
            return np.arange(n_src, dtype=np.int64), True
        shift = np.concatenate([base_shift, base_shift[ws], np.full(n_src - n_base, -1, np.int64)])
        key = np.concatenate([k, k[ws], np.zeros(n_src - n_base, np.int64)])
        wall = np.concatenate([np.zeros(n, np.int64), np.ones(ws.size, np.int64), np.zeros(n_src - n_base, np.int64)])
        face = np.zeros(n_src, np.int64)
        if self._walls is not None:
            face[n:n_base] = self._walls[1]
        flip = np.zeros(n_src, np.int64)
        if n_src > n_base:                                # ghosts made here: periodic images and mirrors
            assert self._src is not None
            src = self._src
            gx, sx = src_x[n_base:], src_x[src]
            dom = self.domain
            assert dom.lo is not None and dom.hi is not None
            made = dom.image_ids(dom.whole_periods(gx - sx))            # an image made here: its shift
            shift[n_base:] = np.where(made >= 0, made, shift[src])
            code = np.where(gx < dom.lo, 1, np.where(gx > dom.hi, 2, 0)) * dom.walls
            flip[n_base:] = (code * 3 ** np.arange(d - 1, -1, -1)).sum(axis=1)
            key[n_base:], wall[n_base:], face[n_base:] = key[src], wall[src], face[src]
        kind = np.where(flip > 0, 2, np.where(shift >= 0, 1, 0))
        rank = np.empty(n_src, np.int64)
        # mirrors: by reflection, then their source's place (particles, then images by shift), then key
        rank[np.lexsort((key, face, wall, shift, flip, kind))] = np.arange(n_src)
        return rank, False

    def _ordered(self, nl: NeighborList, ascending: bool = False) -> NeighborList:
        """Each row in source order: by index, or with ``keys`` by :meth:`_source_rank`; ``ascending``: the
        rows are ascending by index (as the core's searches make them), the list as it is in index order."""
        if ascending and self._in_index_order:
            return nl
        return nl.canonical() if self._rank is None else nl.ordered_by(self._rank)

    # ------------------------------------------------------------------ repair
    def _one_sided(self, op, operators):
        """The rows of points within their core size of a Dirichlet face, rebuilt over every source
        within 2^(1/d) times that core size: the half ball by the wall holds about as many sources
        as a full ball elsewhere (with the core size alone such rows can have too few neighbours for
        their moments, and weights of either sign far above 1 / eps^2)."""
        assert self._walls is not None
        gap = self._walls[2].wall_gap(self._cx)
        # (only these rows and those at exactly their core size from a face can read boundary particles:
        # every boundary particle, image and mirror lies on a face's plane; all such rows are balls of
        # wide_gathers, the sources a rank must hold for them)
        edge = np.flatnonzero(gap == self._own_eps)
        self._reach[edge] = self._own_eps[edge]
        rows = np.flatnonzero(gap < self._own_eps)
        if rows.size == 0:
            return op
        wide = self._own_eps[rows] * 2.0 ** (1.0 / self._cx.shape[1])
        fix = DCPSE(self._src_x, self._src_eps, self._cx[rows], wide, order=self._order, strict=False,
                    operators=operators, neighbors=self._gather(rows, wide))
        self._own_eps = self._own_eps.copy()
        self._own_eps[rows] = wide
        self._nnb[rows] = fix.n_neighbors
        self._reach[rows] = wide                           # (a ball: wide_gathers)
        return Patched(op, fix, rows)

    def _wild(self, op, rows: np.ndarray) -> np.ndarray | None:
        """Which rows of an operator set of order > 2 (whose rows are the collocation points ``rows``) are
        wild, bool (len(rows),), or None without that check.  Off the particles: Lebesgue constants above
        ``max_lebesgue``; at the particles, where they are 1: Laplacian rows whose Gershgorin radius is
        above ``max_row_sum`` (:func:`~arpy.dcpse.rows.wild_rows`), but on Dirichlet faces (held)."""
        if not self._at_particles:
            return None if self._max_lebesgue is None else lebesgue_constants(op) > self._max_lebesgue
        if self._max_row_sum is None:
            return None
        wild = wild_rows(op, self._operators, self._max_row_sum, self._laplacian_sums)
        if wild is not None and self._walls is not None:        # (the values on Dirichlet faces are held)
            wild &= self._walls[2].wall_gap(self._cx[rows]) > 0
        return wild

    def _repair(self, op, widen: int, min_neighbors: int):
        """The repair policy of the module docstring, in its order: failed rows, wild rows, mild rows."""
        ce, order = self._own_eps, self._order
        for _ in range(int(widen)):
            rows = np.union1d(op.failed, np.flatnonzero(self._nnb < min_neighbors))
            if rows.size == 0:
                break
            op, ce, _, _ = self._patch_wider(op, ce, rows)
        wild = self._wild(op, np.arange(op.n_col)) if order > 2 else None
        if wild is not None:
            rows = np.setdiff1d(np.flatnonzero(wild), op.failed)
            if self._at_particles:
                self.heavy = rows
            if rows.size:                               # first: order m on a wider stencil
                op, ce, fix, take = self._patch_wider(op, ce, rows)
                # only the rows rebuilt wider can still be wild (a failed row's zero row has constant 0)
                still = self._wild(fix, rows)
                rows = rows[take & still] if still is not None else rows[:0]
            if rows.size:                               # then: order m - 1 on that stencil
                op = Patched(op, DCPSE(self._src_x, self._src_eps, self._cx[rows], ce[rows], order=order - 1,
                                        neighbors=self._gather(rows, ce[rows]), strict=False,
                                        operators=self._operators), rows, widened=True)
        if not self._at_particles and self._max_lebesgue is not None and MILD_LEBESGUE < self._max_lebesgue:
            op = self._repair_mild(op, ce)
        return op

    def _gather(self, rows: np.ndarray, radius: np.ndarray, src_eps: np.ndarray | None = None):
        """Every source within ``radius`` of the points ``rows`` (a cross list; with ``src_eps``, under
        the min rule with those source core sizes), None for no rows; rows ascending."""
        if rows.size == 0:
            return None
        reach = np.full(len(self._src_x), radius.max()) if src_eps is None else src_eps
        return self._ordered(cross_neighbor_list(self._cx[rows], radius, self._src_x, reach), ascending=True)

    def _wide_rows(self, ce: np.ndarray, rows: np.ndarray):
        """Rows at order m from every source within 1.5 ce: (the new core sizes, the DCPSE, and the
        sources a ball of 1.5x the row's own stencil at its own density would hold, 1.5^d x own
        neighbours)."""
        wide = 1.5 * ce[rows]
        self._reach[rows] = np.maximum(self._reach[rows], wide)
        fix = DCPSE(self._src_x, self._src_eps, self._cx[rows], wide, order=self._order,
                    neighbors=self._gather(rows, wide), strict=False, operators=self._operators)
        return wide, fix, 1.5 ** self._cx.shape[1] * np.maximum(self._nnb[rows], 1)

    def _patch_wider(self, op, ce: np.ndarray, rows: np.ndarray):
        """Rows rebuilt wider; a flooded gather is replaced by order m - 1 on the row's own stencil
        where that one is sound (valid and, with max_lebesgue, not wild).  Returns (op, core sizes,
        the wide DCPSE, take: the rows that took its wide row)."""
        order = self._order
        wide, fix, ball = self._wide_rows(ce, rows)
        take = np.ones(rows.size, dtype=bool)
        if order > 2:
            flood = np.flatnonzero(fix.n_neighbors > MAX_GATHER * ball)
            if flood.size:
                low = DCPSE(self._src_x, self._src_eps, self._cx[rows[flood]], self._own_eps[rows[flood]],
                            order=order - 1, strict=False, operators=self._operators,
                            neighbors=self._gather(rows[flood], self._own_eps[rows[flood]], self._src_eps))
                ok = np.ones(flood.size, dtype=bool)
                ok[low.failed] = False
                wild = self._wild(low, rows[flood])
                if wild is not None:
                    ok &= ~wild
                if ok.any():
                    op = Patched(op, low, rows[flood[ok]], take=np.flatnonzero(ok))
                    take[flood[ok]] = False
        ce = ce.copy()
        ce[rows[take]] = wide[take]
        self._nnb[rows[take]] = fix.n_neighbors[take]
        if take.any():
            op = Patched(op, fix, rows[take], widened=True, take=np.flatnonzero(take))
        return op, ce, fix, take

    def _repair_mild(self, op, ce: np.ndarray):
        """Mildly wild rows: wider only where no finer region is near and the constant drops."""
        lc = lebesgue_constants(op)
        rows = np.setdiff1d(np.flatnonzero((lc > MILD_LEBESGUE) & (lc <= self._max_lebesgue)),
                            np.union1d(op.failed, op.widened))
        if rows.size:
            _, fix, ball = self._wide_rows(ce, rows)
            good = (fix.n_neighbors <= MILD_GATHER * ball) & (lebesgue_constants(fix) < lc[rows])
            good[fix.failed] = False
            if good.any():
                op = Patched(op, fix, rows[good], widened=True, take=np.flatnonzero(good))
        return op

    def spliced(self, old: "DomainDCPSE", columns: np.ndarray) -> "DomainDCPSE":
        """These rows (built with ``only``) and the others of ``old`` (fewer sources, numbered ``columns`` here)."""
        out, rows = copy.copy(self), cast(np.ndarray, self.only)
        out.only, out._sums, out._cx = None, None, old._cx
        out._op = Renumbered(old._op, columns, self.n_src)
        if rows.size:
            out._op = Patched(out._op, self._op, rows)
            out._op.widened = np.union1d(np.setdiff1d(old.widened, rows), rows[self.widened])
        for name in ("_own_eps", "_nnb", "_reach"):
            setattr(out, name, getattr(old, name).copy())
            getattr(out, name)[rows] = getattr(self, name)
        for name in ("_unrepaired", "heavy"):
            setattr(out, name, np.union1d(np.setdiff1d(getattr(old, name), rows), rows[getattr(self, name)]))
        return out

    def __repr__(self) -> str:
        where = "at the particles" if self._at_particles else f"{self.n_col} collocation points"
        return (f"DomainDCPSE(order={self._order}, {self.x.shape[0]} particles + {self.n_src - self.x.shape[0]} "
                f"ghosts, {where}, {self.widened.size} widened, {self.failed.size} failed, {self.domain!r})")

    # ------------------------------------------------------------------ operators
    @property
    def failed(self) -> np.ndarray:
        """Collocation points without a valid stencil (their rows are zero), int array."""
        return self._op.failed

    @property
    def unrepaired(self) -> np.ndarray:
        """Collocation points without a valid stencil of their own, before any repair, int array."""
        return self._unrepaired

    @property
    def wide_gathers(self) -> tuple[np.ndarray, np.ndarray]:
        """The rows that gathered sources beyond their own stencils (int64 (k,), ascending): the one-sided
        rows by Dirichlet faces and the repaired rows, and the widest ball each gathered from (radius,
        length unit; (k,)): a row and the repair's decisions for it depend on the sources within it
        (and within its own stencil)."""
        rows = np.flatnonzero(self._reach > 0)
        return rows, self._reach[rows]

    @property
    def widened(self) -> np.ndarray:
        """Collocation points whose rows were rebuilt on wider stencils, int array."""
        return self._op.widened

    @property
    def n_neighbors(self) -> np.ndarray:
        """Usable neighbours of each collocation point's stencil (after the repair), int (n_col,)."""
        return self._nnb.copy()

    @property
    def d(self) -> int:
        """Dimension."""
        return self._op.d

    @property
    def n_col(self) -> int:
        """Number of collocation points (rows)."""
        return self._op.n_col

    @property
    def n_src(self) -> int:
        """Number of sources, particles and ghosts (columns)."""
        return self._op.n_src

    @property
    def sources(self) -> np.ndarray:
        """Positions of the sources, particles then ghosts, (n_src, d)."""
        return self._src_x

    @property
    def ghost_source(self) -> np.ndarray | None:
        """The particle (or boundary particle, numbered after the particles) each ghost is an image
        of, int; None without ghosts."""
        return self._src

    @property
    def n_boundary(self) -> int:
        """Boundary particles on Dirichlet faces (sources after the particles and the ghosts given, before
        the images made here)."""
        return 0 if self._walls is None else int(self._walls[0].shape[0])

    @property
    def wall_columns(self) -> np.ndarray:
        """Which sources carry the walls' values (data, not unknowns): the boundary particles and their
        images, bool (n_src,)."""
        out = np.zeros(self.n_src, dtype=bool)
        n_base = self.n_src - (0 if self._src is None else self._src.size)
        out[self._n_values:n_base] = True
        if self._src is not None:
            out[n_base:] = self._src >= self._n_values
        return out

    def extend(self, f: np.ndarray, bc: Conditions | None = None, t: float = 0.0) -> np.ndarray:
        """Values on the particles (n,) -> values on the sources (particles, then ghosts).  An operator
        built with ``ghosts=`` takes the values on the particles and then on those ghosts (n + g,).

        Ghosts carry their particle's value (periodic images; mirror images: homogeneous Neumann),
        or with ``bc`` the values its walls' conditions give at time t
        (:meth:`arpy.dcpse.boundary.Conditions.ghost_values`).  An operator built with ``dirichlet``
        needs conditions with the same Dirichlet faces: its boundary particles carry their values."""
        f = np.asarray(f, dtype=np.float64)
        if f.shape[:1] != (self._n_values,):
            raise ValueError(f"extend needs {self._n_values} values, got shape {f.shape}")
        if self._src is None or (self._src.size == 0 and self._walls is None):
            return f
        if self._walls is not None:                       # the boundary particles carry the walls' values
            wx, wface, walls = self._walls
            if bc is None or not np.array_equal(bc.dirichlet_faces, walls.dirichlet_faces):
                raise ValueError("this operator reads boundary particles on Dirichlet faces: extend needs "
                                 "conditions with the same Dirichlet faces")
            f = np.concatenate([f, bc.wall_values(wx, wface, t)])
        if bc is None or bc.homogeneous:
            return np.concatenate([f, f[self._src]])
        nb, src = f.shape[0], self._src
        xg, start = self._src_x[nb:], f[src]
        of_wall = np.flatnonzero(src >= self._n_values)
        if of_wall.size:         # images of boundary particles: the walls' values where they lie before reflections
            assert self._walls is not None
            y = xg[of_wall].copy()
            axes = self.domain.walls
            y[:, axes] = self._src_x[src[of_wall]][:, axes]
            start[of_wall] = bc.wall_values(y, self._walls[1][src[of_wall] - self._n_values], t)
        return np.concatenate([f, bc.ghost_values(f, self._src_x[:nb], src, xg, t, start)])

    def slip(self, v: np.ndarray) -> np.ndarray:
        """A vector field (n, d) at the particles (with ``ghosts=``: (n + g, d), the ghosts' too) on every
        source: mirror images flip the component normal to their wall (slip), periodic images copy it."""
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (self._n_values, self.x.shape[1]):
            raise ValueError(f"a vector array must have shape {(self._n_values, self.x.shape[1])}, got {v.shape}")
        if self._src is None or self._src.size == 0:
            return v
        xg = self._src_x[self._src_x.shape[0] - self._src.size:]
        vg = v[self._src].copy()
        if self.domain.has_walls:
            flip = self.domain.beyond_walls(xg)
            vg[flip] = -vg[flip]
        return np.concatenate([v, vg])

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]:
        """The operators d^alpha, (n_col, n_src) each (see :meth:`arpy.DCPSE.derivatives`)."""
        return self._op.derivatives(alphas)

    def derivative(self, alpha: Sequence[int]) -> sp.csr_matrix:
        """The operator d^alpha, (n_col, n_src), unit ``length^-|alpha|``."""
        return self.derivatives([alpha])[0]

    def gradient(self) -> list[sp.csr_matrix]:
        """The d first-derivative operators, (n_col, n_src) each, unit 1 / length."""
        return self._op.gradient()

    def laplacian(self) -> sp.csr_matrix:
        """The Laplacian (Eq. A.6), (n_col, n_src), unit 1 / length^2."""
        return self._op.laplacian()

    def laplacian_row_sums(self) -> np.ndarray:
        """``sum_q |L_pq|`` of each row of :meth:`laplacian` (:func:`~arpy.dcpse.rows.abs_row_sums`, the
        Gershgorin radii), (n_col,); at the particles computed once with the weighing of wild rows."""
        return self._laplacian_sums(self._op)

    def _laplacian_sums(self, op) -> np.ndarray:
        """abs_row_sums of the Laplacian of ``op`` (these operators or a repair's), kept for the last op."""
        if self._sums is None or self._sums[0] is not op:
            self._sums = (op, abs_row_sums(op.laplacian()))
        return self._sums[1]

    def interpolation(self) -> sp.csr_matrix:
        """The interpolating kernel (Eqs. A.9-A.11), (n_col, n_src); at the particles the identity."""
        if self._at_particles:
            return sp.eye(self.n_col, self.n_src, format="csr")
        return self._op.interpolation()

    def apply(self, op: str | Sequence[int], f: np.ndarray) -> np.ndarray:
        """An operator ("laplacian", "interpolation" or a multi-index) applied to values f (n,) on the
        particles; returns (n_col,)."""
        if isinstance(op, str) and op.lower() in ("laplacian", "interpolation"):
            mat = self.laplacian() if op.lower() == "laplacian" else self.interpolation()
        elif isinstance(op, str):
            raise ValueError(f"unknown operator {op!r}")
        else:
            mat = self.derivative(op)
        return mat @ self.extend(f)

    def interpolate(self, f: np.ndarray, bounded: bool = False, bc: Conditions | None = None,
                    t: float = 0.0, *, near: Callable[[np.ndarray, int], np.ndarray] | None = None,
                    median: float | None = None) -> np.ndarray:
        """f given on the particles (n,) at the collocation points (m,): old set -> new set.

        Points without a stencil (``failed``) take the value of the nearest particle instead of
        the zero of their empty row (a zero inside a field would make the monitor ask for a very
        fine resolution there).  ``bounded``: every row is limited to the range of its stencil's
        values (:func:`bounded_apply`); a widened row that gathered more than ``WIDE_GATHER`` times
        the median row's sources reaches into a finer region of the old set (e.g. across a thin
        filament) and is limited, in addition, to the range of the 2d particles nearest to the
        point, so that the filament's values do not leak into the empty space around it
        (:meth:`clipped_rows`).  ``bc``, t: the values of the ghosts (see :meth:`extend`).
        ``near(rows, k)``: the values (len(rows), k) of the k particles nearest those collocation
        points (default: among the particles, with ``ghosts`` the particles and the ghosts), and
        ``median``: the median row's sources, when they come from elsewhere (the ranks of
        :class:`arpy.distributed.DistributedDCPSE`)."""
        f = np.asarray(f, dtype=np.float64)
        fe, mat = self.extend(f, bc, t), self.interpolation()
        out = bounded_apply(mat, fe) if bounded else mat @ fe
        if near is None:
            def near(rows: np.ndarray, k: int) -> np.ndarray:
                return f[self._nearest(self._cx[rows], k)]
        if bounded:
            rows = self.clipped_rows(median)
            if rows.size:
                v = near(rows, 2 * self.x.shape[1])
                out[rows] = np.clip(out[rows], v.min(axis=1), v.max(axis=1))
        if self.failed.size:
            out[self.failed] = near(self.failed, 1)[:, 0]
        return out

    def clipped_rows(self, median: float | None = None) -> np.ndarray:
        """The rows bounded interpolation also limits to the range of the nearest particles (see
        :meth:`interpolate`): widened, not failed, with more than ``WIDE_GATHER`` times the median
        row's sources (``median``: that of this operator's rows, or the one given)."""
        nnz = np.diff(self.interpolation().indptr)
        rows = np.setdiff1d(self.widened, self.failed)
        return rows[nnz[rows] > WIDE_GATHER * (np.median(nnz) if median is None else median)]

    def _nearest(self, points: np.ndarray, k: int) -> np.ndarray:
        """The k particles (with ``ghosts``: particles and ghosts) nearest each point, indices (m, k)
        into the values :meth:`extend` takes; with ``keys``, ties go by key."""
        base, dom = (self.x, self.domain) if self._base_x is None else (self._base_x, None)
        if self._rank is None:
            _, j = nearest(base, k, y=points, domain=dom)
            return j.reshape(points.shape[0], k)
        m = min(k + 2, base.shape[0])                  # (a few more: the k-th may tie with the next)
        dist, j = nearest(base, m, y=points, domain=dom)
        dist, j = dist.reshape(points.shape[0], m), j.reshape(points.shape[0], m)
        pick = np.lexsort((self._rank[j], dist), axis=1)[:, :k]
        return np.take_along_axis(j, pick, axis=1)
