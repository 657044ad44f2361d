"""DC-PSE over the ranks: :class:`DistributedDCPSE` and :class:`Laplacian`, operators of fixed
particles over owned particles and ghosts, rows in key order, failed stencils repaired over wider
balls fetched from the other ranks: bitwise the same for every rank count, and the one-process
operator's; :func:`nearest_values`, the k-nearest request they and
:class:`arpy.SampledResolution` make of the other ranks.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from .._validate import as_cutoffs, as_positions
from ..dcpse.boundary import Conditions
from ..dcpse.domain import LEBESGUE_MAX
from ..domain import Domain, as_domain, nearest
from ..lists.search import cache_order, cross_neighbor_list
from ..dcpse.kernel import DegenerateStencilError
from .comm import Comm
from .decomposition import Decomposition, bounding_box, box_gap, box_gap2
from .ghosts import ASK_MARGIN, halo, repair_sends, send_ghosts
from .kept import KeptGhosts
from .reductions import global_median

__all__ = ["DistributedDCPSE", "Laplacian", "nearest_values"]


class DistributedDCPSE:
    """DC-PSE operators at this rank's own particles over its own particles and ghosts (particles
    fixed while it is used): :class:`arpy.DomainDCPSE` with the ghosts from the other ranks as
    sources and each row's sources in the order one process sums them over the whole set numbered by
    key (``DomainDCPSE(keys=)``), so every operator gives bitwise the same values for every rank
    count, and those of the one-process operator (without ``keys`` when the keys are the indices).

    Stencils are repaired as in a simulation (:data:`arpy.dcpse.domain.REPAIR`): a row whose moment
    conditions fail is rebuilt over every source within a wider ball, up to ``1.5**widen`` times its
    core size, which may reach beyond the ghost layer; the rank then asks the others for their
    particles (and periodic images) within that ball of the row's particle, and they send them as
    extra ghosts (a receiver-side request, made only when some rank has a failed row).

    The methods are those of :class:`arpy.DomainDCPSE` (so :class:`arpy.dcpse.operators.Operators` takes
    it): the matrices' rows are this rank's particles in the order given, their columns the sources
    (own particles, ghosts, mirror images), and :meth:`extend` gives the values on the sources of
    values on the own particles (the ghosts' by one exchange: a collective call).

    Parameters
    ----------
    comm, dec : Comm, Decomposition
        The ranks and their boxes (the particles already migrated to their owners).
    x, eps, keys : arrays (n, d), (n,), (n,)
        This rank's particles (the sources), their core sizes (= cutoffs) and keys.
    col_x, col_eps : arrays (m, d), (m,), optional
        Collocation points inside this rank's box and their core sizes (old set -> new set: the new
        particles this rank owns); None: the particles themselves, and for col_eps the core size of
        the nearest particle of any rank (ties by key).
    domain : Domain
        The box: periodic axes take ghosts' images, walls mirror images of own particles and ghosts
        (homogeneous Neumann, or the walls' Neumann conditions in :meth:`extend`).
    order : int
        DC-PSE order m.
    skin : float
        Extra reach of the ghost layer: own particles may lie up to this far outside the rank's box
        (e.g. at an intermediate stage of a time step).
    widen, max_lebesgue : int, float, optional
        Repair rounds of failed rows (default: :data:`arpy.dcpse.domain.REPAIR`'s), and the Lebesgue
        constant above which a row off the particles is rebuilt (default: REPAIR's; None: no such
        repair, as in :class:`arpy.DomainDCPSE`).
    max_row_sum : float, optional
        At the particles, Laplacian rows with ``sum_q |L_pq|`` above it are rebuilt as wild
        (:class:`arpy.DomainDCPSE`; None: none).
    strict : bool
        Raise ValueError if a row still has no valid stencil; False: its row is zero.
    operators : sequence, optional
        The operators assembled with the stencils (see :class:`arpy.DCPSE`); default: the Laplacian
        at the particles, the interpolating kernel off them.
    reorder : bool
        Work on the particles in cache order (:func:`arpy.cache_order`; the matrices' rows are put
        back in the order given, which costs a copy of each); False: the particles are in cache
        order already, or should be taken as given.
    lists : KeptGhosts, optional
        At the particles (``col_x`` None, ``reorder=False``): the ghost layer and the rows kept
        from an earlier call while the particles moved less than its skin allows
        (:class:`arpy.distributed.kept.KeptGhosts`, Verlet lists over the ranks); the operators are
        bitwise those built afresh.
    dirichlet : Conditions, optional
        A field's conditions with Dirichlet faces (:class:`arpy.DomainDCPSE`'s ``dirichlet``): the
        boundary particles are made by each rank from its particles and ghosts, keyed by (face, key of
        their particle) after every particle, and the rows that read them (points within their core size
        of such a face: one-sided balls) ask the other ranks for every particle in their ball or whose
        boundary particle is, so the rows are bitwise those of one process.  Not with ``lists``.  (One
        exception: in a box with periodic axes, two particles whose boundary particles fall on exactly
        the same point, which random or self-organized positions never make, may leave a periodic image
        of it on ranks that one process does not make.)

    Attributes
    ----------
    failed : int array
        Rows (this rank's particles, or collocation points) without a valid stencil after the repair.
    repaired : int64 array
        Keys of this rank's particles (collocation points: their indices) whose rows were rebuilt.
    heavy : int array
        Rows (this rank's particles) found wild by their weights and rebuilt
        (:attr:`arpy.DomainDCPSE.heavy`).
    """

    def __init__(self, comm: Comm, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray,
                 col_x: np.ndarray | None = None, col_eps: float | np.ndarray | None = None, *,
                 domain: Domain, order: int = 4, skin: float = 0.0, widen: int | None = None,
                 max_lebesgue: float | None = LEBESGUE_MAX, max_row_sum: float | None = None, strict: bool = True,
                 operators: Sequence[object] | None = None, reorder: bool = True,
                 lists: KeptGhosts | None = None, dirichlet: Conditions | None = None) -> None:
        from ..dcpse.domain import REPAIR, DomainDCPSE

        xs = as_positions(x)
        n, d = xs.shape
        dom = as_domain(domain, d)
        if not dom.bounded and comm.size > 1:
            raise ValueError("DC-PSE on several ranks needs a box (a Domain with walls or periodic axes)")
        widen = REPAIR["widen"] if widen is None else int(widen)
        self.comm, self.n = comm, n
        # the own particles in cache order (they arrive in key order, which is no order in memory);
        # rows and sums go by key, so every operator is bitwise that of any other order
        # (_order None: the order given, nothing copied)
        perm = cache_order(xs, domain=domain) if reorder else None
        self._order: np.ndarray | None = perm
        self._back: np.ndarray | None = np.argsort(perm) if col_x is None and perm is not None else None
        xo, eo, ko = self._ordered(xs), self._ordered(as_cutoffs(eps, n)), self._ordered(np.asarray(keys, np.int64))
        cx = xo if col_x is None else as_positions(col_x)
        if cx.shape[1] != d:
            raise ValueError(f"collocation points must have d = {d} columns, got {cx.shape}")
        if col_x is not None and comm.size > 1:
            # (a point beyond the box would read a stencil the ghost layer does not hold: every rank refuses)
            out = np.flatnonzero(~(box_gap2(cx, *dec.box(comm.rank)) <= skin * skin))     # (the halo's measure)
            if comm.sum(int(out.size)):
                where = f"; on this rank {out.size}, the first at {cx[out[0]]}" if out.size else " (on other ranks)"
                raise ValueError("DistributedDCPSE: collocation points must lie in their rank's box (within the "
                                 f"skin {skin}){where}; give each rank the points its box holds (Decomposition.locate)")
        if col_x is None:
            ce = eo
        elif col_eps is None:                # the core size of the nearest particle of any rank
            ce = nearest_values(comm, xo, ko, eo, dom, cx, 1)[:, 0]
        else:
            ce = as_cutoffs(col_eps, cx.shape[0])
        if lists is not None and (col_x is not None or reorder):
            raise ValueError("lists= is for operators at the particles (col_x None), with reorder=False")
        walls = dirichlet if dirichlet is not None and dirichlet.has_dirichlet else None
        if walls is not None and lists is not None:
            raise ValueError("lists= (kept ghosts) do not take Dirichlet faces")
        # by Dirichlet faces the rows that read boundary particles (projections of particles within half
        # their core size of a face; of coinciding ones the first by face and key) are balls in
        # wide_gathers: their sources are asked for below, those particles with them.  Such a particle
        # lies up to half the largest core size of any rank (half) from its projection
        half = 0.0
        if walls is not None:
            gap = walls.wall_gap(xo)
            half = 0.5 * float(comm.max(np.array([eo[(gap > 0) & (gap <= 0.5 * eo)].max(initial=0.0)]))[0])
        if lists is None:
            sends = halo(xo, eo, dec, np.full(n, comm.rank, np.int64), skin=skin, domain=domain)
            self.ghosts = send_ghosts(comm, xo, eo, ko, sends, dom)
        else:
            self.ghosts, sends = lists.layer(comm, dec, xo, eo, ko, dom, skin)
        kept = None if lists is None else lists.rows
        wanted = (["laplacian"] if col_x is None else ["interpolation"]) if operators is None else list(operators)

        def build(w: int, lebesgue: float | None, only=None) -> DomainDCPSE:
            # (in free space, one rank alone: no ghosts, the particles are every source)
            # (no ghosts and the particles numbered 0 .. n-1 in order: their index order is the key order)
            alone = self.ghosts.keys.size == 0 and np.array_equal(ko, np.arange(n))
            ghosts = (self.ghosts.x, self.ghosts.rc, self.ghosts.shift) if dom.bounded and not alone else None
            return DomainDCPSE(xo, eo, None if col_x is None else cx, None if col_x is None else ce, domain=dom,
                               order=order, strict=False, widen=w, max_lebesgue=lebesgue, operators=wanted,
                               max_row_sum=max_row_sum, dirichlet=walls,
                               ghosts=ghosts, keys=None if alone else np.concatenate([ko, self.ghosts.keys]),
                               rows=kept if ghosts is not None else None, only=only)

        # a first build repairs with the sources at hand.  A repaired row is exact when its widest
        # ball (up to 1.5^widen times its core size; off the particles one round more, and rows wild
        # by their Lebesgue constant or at the particles by their row sums, 1.5 times; one-sided rows by
        # Dirichlet faces 2^(1/d) times) lies inside this rank's box, away from the faces
        # where other ranks' particles or periodic images begin (a ball reaching a Dirichlet face: with
        # the boundary particles' particles, up to E / 2 farther): no source it lacks can be in it.
        # The rows whose ball crosses such a face ask the other ranks (and the periodic images) for
        # what lies there, and those ranks build again (the rows of every other point are the same),
        # until no row gathers from a ball wider than the one it asked about.  The one-sided rows' balls
        # are known before any build: they are asked for first, so that they cost no second build
        asked = np.zeros(cx.shape[0])
        # (one rank without periodic axes: no other rank and no image holds a source, nothing to ask)
        lonely = comm.size == 1 and not dom.any_periodic

        def ask(rows: np.ndarray, radius: np.ndarray) -> bool | None:
            """Ask the other ranks for the sources within ``radius`` of the points ``rows`` whose balls
            reach past this rank's box (collective): whether this rank received sources it did not hold
            (a rank that asked for none received none; an answer may bring none), None if no rank asked."""
            nonlocal sends
            if lonely:
                return None
            lo, hi = dec.box(comm.rank)
            ball = radius * (1 + ASK_MARGIN)
            if walls is not None:
                ball = ball + np.where(walls.wall_gap(cx[rows]) <= ball, half, 0.0)
            out = ~np.all((cx[rows] - ball[:, None] > lo) & (cx[rows] + ball[:, None] < hi), axis=1)
            rows, radius = rows[out], radius[out]
            if not comm.sum(rows.size):
                return None
            asked[rows] = radius
            sends = repair_sends(comm, xo, eo, cx[rows], radius, dom, skin, sends, walls)
            held, self.ghosts = self.ghosts, send_ghosts(comm, xo, eo, ko, sends, dom)
            # (the same sources build the same operator: no second build)
            return bool(rows.size) and not all(np.array_equal(getattr(held, a), getattr(self.ghosts, a))
                                               for a in ("keys", "shift", "x", "rc"))

        if walls is not None:               # the one-sided rows' balls (wide_gathers), before the first build
            gap = walls.wall_gap(cx)
            rows = np.flatnonzero(gap <= ce)
            ask(rows, np.where(gap[rows] < ce[rows], ce[rows] * 2.0 ** (1.0 / d), ce[rows]))
        op = build(widen, max_lebesgue)
        while True:
            rows, radius = op.wide_gathers
            more = radius > asked[rows]
            old_sources = op.sources
            got = ask(rows[more], radius[more])
            if got is None:
                break
            kept = None                     # (the kept rows are not those of the wider layer)
            if got:                         # (only the rows the new sources reach)
                op = _spliced(op, old_sources, cx, ce, col_x is not None, lambda only: build(widen, max_lebesgue, only))
        self._rank_of = rank_of = np.arange(cx.shape[0]) if col_x is not None or self._order is None else self._order
        self.failed = np.sort(rank_of[op.failed])
        self.repaired = np.sort(ko[op.widened]) if col_x is None else np.sort(op.widened)
        self.heavy = np.sort(rank_of[op.heavy])
        if strict and self.failed.size:
            where = f"the particle of key {ko[op.failed[0]]}" if col_x is None else f"point {op.failed[0]}"
            raise DegenerateStencilError(f"DC-PSE: {self.failed.size} points have no valid stencil even after {widen} "
                                         f"widening rounds, the first at {where}", self.failed,
                                         np.zeros(self.failed.size, int), np.zeros(self.failed.size, int),
                                         np.full(self.failed.size, np.inf))
        self._op = op
        self._x, self._keys, self._domain, self._cx = xo, ko, dom, cx

    def _rows(self, mat: sp.csr_matrix) -> sp.csr_matrix:
        return mat if self._back is None else mat[self._back]

    def _ordered(self, v: np.ndarray) -> np.ndarray:
        """Values (n, ...) on this rank's particles in the order the operator holds them."""
        return v if self._order is None else v[self._order]

    @property
    def unrepaired(self) -> np.ndarray:
        """Rows (this rank's particles, or collocation points) without a valid stencil of their own,
        before any repair (:attr:`arpy.DomainDCPSE.unrepaired`)."""
        return np.sort(self._rank_of[self._op.unrepaired])

    @property
    def n_neighbors(self) -> np.ndarray:
        """Each row's sources within its core size (this rank's particles, or collocation points), int
        (rows,): :attr:`arpy.DomainDCPSE.n_neighbors`."""
        out = np.empty(self._rank_of.size, np.int64)
        out[self._rank_of] = self._op.n_neighbors
        return out

    @property
    def sources(self) -> np.ndarray:
        """Positions of the sources: own particles (in cache order), ghosts, boundary particles, mirror
        images."""
        return self._op.sources

    @property
    def wall_columns(self) -> np.ndarray:
        """Which sources carry the walls' values (:attr:`arpy.DomainDCPSE.wall_columns`), bool (n_sources,)."""
        return self._op.wall_columns

    def extend(self, f: np.ndarray, bc: Conditions | None = None, t: float = 0.0) -> np.ndarray:
        """Values on this rank's particles (n,) -> values on the sources (the ghosts' from their
        ranks; mirror images by ``bc``, see :meth:`arpy.DomainDCPSE.extend`).  Collective."""
        fo = self._ordered(np.asarray(f, dtype=np.float64))
        return self._op.extend(np.concatenate([fo, self.ghosts.refresh(self.comm, fo)]), bc, t)

    def slip(self, v: np.ndarray) -> np.ndarray:
        """A vector field (n, d) on this rank's particles on the sources (the ghosts' from their ranks;
        slip images at walls, see :meth:`arpy.DomainDCPSE.slip`).  Collective."""
        vo = self._ordered(np.asarray(v, dtype=np.float64))
        if vo.shape != (self.n, self._x.shape[1]):
            raise ValueError(f"a vector array must have shape {(self.n, self._x.shape[1])}, got {vo.shape}")
        return self._op.slip(np.concatenate([vo, self.ghosts.refresh(self.comm, vo)]))

    def laplacian(self) -> sp.csr_matrix:
        """The Laplacian, (n, n_sources), unit 1 / length^2."""
        return self._rows(self._op.laplacian())

    def laplacian_row_sums(self) -> np.ndarray:
        """``sum_q |L_pq|`` of each row of :meth:`laplacian`, (n,) (:meth:`arpy.DomainDCPSE.laplacian_row_sums`)."""
        sums = self._op.laplacian_row_sums()
        return sums if self._back is None else sums[self._back]

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]:
        """The operators d^alpha, (n, n_sources) each."""
        return [self._rows(m) for m in self._op.derivatives(alphas)]

    def derivative(self, alpha: Sequence[int]) -> sp.csr_matrix:
        """The operator d^alpha, (n, n_sources)."""
        return self.derivatives([alpha])[0]

    def gradient(self) -> list[sp.csr_matrix]:
        """The d first-derivative operators, (n, n_sources) each."""
        return [self._rows(m) for m in self._op.gradient()]

    def interpolation(self) -> sp.csr_matrix:
        """The interpolating kernel (at the particles: the identity), (rows, n_sources)."""
        return self._rows(self._op.interpolation())

    def interpolate(self, f: np.ndarray, bounded: bool = False, bc: Conditions | None = None,
                    t: float = 0.0) -> np.ndarray:
        """f given on this rank's particles (n,) at the collocation points (old set -> new set, see
        :meth:`arpy.DomainDCPSE.interpolate`): the nearest particles a point without a stencil (or,
        ``bounded``, a widely gathered row) takes its values from are the nearest of every rank, by
        (distance, key), and the median row's sources is that of every rank's rows.  Collective."""
        op, comm = self._op, self.comm
        fo = self._ordered(np.asarray(f, dtype=np.float64))
        ext = np.concatenate([fo, self.ghosts.refresh(comm, fo)])
        median, rows = None, op.failed
        if bounded:
            median = global_median(comm, np.diff(op.interpolation().indptr))
            rows = np.union1d(rows, op.clipped_rows(median))
        k = 2 * op.d if bounded else 1
        values = nearest_values(comm, self._x, self._keys, fo, self._domain, self._cx[rows], k)
        table = dict(zip(rows.tolist(), values))

        def near(at: np.ndarray, kk: int) -> np.ndarray:
            return np.array([table[int(r)][:kk] for r in at]).reshape(len(at), kk)

        out = op.interpolate(ext, bounded, bc, t, near=near, median=median)
        return out if self._back is None else out[self._back]


def _spliced(old, old_sources: np.ndarray, x: np.ndarray, eps: np.ndarray, spline: bool, make):
    """Operators built again after an answer to the repair requests brought more sources, only where those
    can change them: a row depends on the sources within its own stencil and its widest gather
    (:attr:`arpy.DomainDCPSE.wide_gathers`) alone (off the particles, ``spline``, also on their spline
    radii, half the distance to their nearest other source), so the rows of the points x (n, d) (core
    sizes eps (n,)) with no new source (and no source whose radius the new ones shrink) within that ball
    are ``old``'s (built over ``old_sources``, each among the new ones), and the others those of
    ``make(only)`` (a DomainDCPSE over every source at those points only): :meth:`arpy.DomainDCPSE.spliced`,
    bitwise the operator built afresh.  Where the old sources cannot be told among the new ones by their
    positions (two at one point), every row is built anew."""
    found: dict[str, np.ndarray] = {}

    def only(src_x: np.ndarray, src_eps: np.ndarray) -> np.ndarray:
        ids, old_ids = _point_ids(src_x), _point_ids(old_sources)
        order = np.argsort(ids, kind="stable")
        srt = ids[order]
        at = np.minimum(np.searchsorted(srt, old_ids), ids.size - 1)
        if np.any(srt[1:] == srt[:-1]) or not np.array_equal(srt[at], old_ids):
            return np.arange(x.shape[0])
        found["columns"] = order[at]
        new = np.ones(ids.size, bool)
        new[order[at]] = False
        if spline and new.any() and old_sources.shape[0] > 1:     # (the sources whose spline radius shrinks:
            before = nearest(old_sources, 2, y=old_sources)[0][:, 1]      # a new source nearer than their nearest)
            new[order[at]] = nearest(src_x[new], 1, y=old_sources)[0] < before
        if not new.any() or x.shape[0] == 0:
            return np.zeros(0, np.int64)
        g_rows, g_radius = old.wide_gathers
        ball = eps.copy()
        ball[g_rows] = np.maximum(ball[g_rows], g_radius)
        ball *= 1.0 + 1e-9                          # (covers the rounding of the lists' distance tests)
        hit = cross_neighbor_list(x, ball, src_x[new], np.full(int(new.sum()), ball.max()))
        return np.flatnonzero(np.diff(hit.offsets) > 0)

    sub = make(only)
    return sub if "columns" not in found else sub.spliced(old, found["columns"])


def _point_ids(x: np.ndarray) -> np.ndarray:
    """Each row of x (m, d) as one opaque value (its bytes): equal rows, equal values."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    return a.view(np.dtype((np.void, 8 * a.shape[1]))).ravel()


class Laplacian(DistributedDCPSE):
    """The distributed DC-PSE Laplacian (:class:`DistributedDCPSE` with the Laplacian alone), with
    ``matrix`` (n, n_sources) and :meth:`apply`: bitwise the same values for every rank count."""

    def __init__(self, comm: Comm, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray, *,
                 domain: Domain, order: int = 4, skin: float = 0.0, widen: int | None = None,
                 strict: bool = True) -> None:
        super().__init__(comm, dec, x, eps, keys, domain=domain, order=order, skin=skin, widen=widen, strict=strict)
        #: The rows of this rank's particles in their cache order (``apply`` puts the result back).
        self.matrix = self._op.laplacian()

    def apply(self, f: np.ndarray) -> np.ndarray:
        """The Laplacian of f (given on this rank's own particles) at them, shape (n,).  Collective."""
        values = self.matrix @ self.extend(f)
        if self._order is None:
            return values
        out = np.empty(self.n)
        out[self._order] = values
        return out


def nearest_values(comm: Comm, x: np.ndarray, keys: np.ndarray, f: np.ndarray, domain: Domain,
                   points: np.ndarray, k: int) -> np.ndarray:
    """The values (m, k) of the k particles of every rank nearest each of this rank's ``points`` (m, d),
    by (distance, key), distances by the minimum image (fewer columns where all ranks hold fewer than
    k particles).  Collective.

    A receiver-side k-nearest request: the k-th nearest of this rank's own particles bounds the
    distance of those that can count, so a point asks only the ranks whose particles' bounding box
    lies within it (every rank where this one holds fewer than k), and each answers with its own k + 2
    nearest."""
    d = x.shape[1]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, d)
    most = min(k + 2, x.shape[0])

    def answer(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not (len(q) and most):
            return np.zeros((len(q), 0)), np.zeros((len(q), 0), np.int64), np.zeros((len(q), 0))
        dist, j = nearest(x, most, y=q, domain=domain)
        dist, j = dist.reshape(len(q), most), j.reshape(len(q), most)
        return dist, keys[j], f[j]

    own = answer(pts)
    at: list[np.ndarray] = [np.arange(len(pts))]
    parts = [own]
    cols = own[0].shape[1]
    if comm.size > 1:
        bound = own[0][:, k - 1] * (1.0 + 1e-9) if most >= k and len(pts) else np.full(len(pts), np.inf)
        # (every rank's particles and their bounding box, NaN for none: 2 d + 1 numbers a rank)
        mine = np.concatenate([[x.shape[0]], *bounding_box(x)]) if x.shape[0] else np.full(2 * d + 1, np.nan)
        held = comm.gather_arrays(mine.astype(np.float64))[0].reshape(comm.size, 2 * d + 1)
        count = np.nan_to_num(held[:, 0]).astype(np.int64)
        cols = int(np.minimum(k + 2, count).sum())
        asks: list[np.ndarray | None] = [None] * comm.size
        others = [r for r in np.flatnonzero(count).tolist() if r != comm.rank]
        if others and len(pts):
            # (the ranks whose boxes can be near one of the points: O(P) array operations, then O(m) each)
            boxes = Decomposition(held[others, 1:d + 1], held[others, d + 1:])
            for i in boxes.reaching_points(pts, float(bound.max()), domain.period).tolist():
                near = np.flatnonzero(box_gap(pts, *boxes.box(i), domain.period) <= bound)
                asks[others[i]] = near if near.size else None
        got = comm.sparse_alltoall([None if a is None else pts[a] for a in asks])
        replies = comm.sparse_alltoall([None if q is None else answer(q) for q in got])
        for a, rep in zip(asks, replies):
            if a is not None and rep is not None:
                at.append(a)
                parts.append(rep)
    if len(pts) == 0:
        return np.zeros((0, k))
    which = np.concatenate([np.repeat(a, p[0].shape[1]) for a, p in zip(at, parts)])
    dist, key, val = (np.concatenate([p[i].ravel() for p in parts]) for i in range(3))
    order = np.lexsort((key, dist, which))
    first = np.searchsorted(which[order], np.arange(len(pts)))
    take = min(k, cols)
    return val[order[first[:, None] + np.arange(take)]]
