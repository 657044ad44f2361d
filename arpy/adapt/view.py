"""The particles as the self-organization sees them, on one process or on many: :class:`View`.

The adaptation (:mod:`arpy.adapt.organize`) works on this rank's own particles and asks its view for
what lies beyond them: the particles within reach on other ranks (``near``, ``around``), global sums,
minima and maxima, the decisions taken over every rank's candidates (fusion pairs, insertion sites, new
keys), and migration to the boxes of the decomposition.  One process is P = 1: its view exchanges
nothing, and the adaptation runs the same code at every rank count, with the same result.
:class:`Confinement` says where the particles may go; :class:`Near` is what ``near`` returns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Sequence, cast

import numpy as np

from ..distributed.balance import CostBalance
from ..distributed.comm import Comm
from ..distributed.decomposition import Decomposition, bisect, box_gap
from ..distributed.ghosts import halo, migrate
from ..distributed.reductions import Reductions, key_ordered, key_places
from ..distributed.share import Sharing
from ..domain import Domain
from ..lists.neighborlist import NeighborList
from ..lists.search import cross_neighbor_list, neighbor_list, source_rows

__all__ = ["EDGE_LAYER", "Confinement", "Near", "View", "greedy_matching", "site_conflicts"]

#: Thickness (in units of D_p) of the sparser outermost layer at a free-space region's
#: edge: particles whose neighbourhood ball (radius r_c) comes closer than this to
#: the edge are exempt from the neighbour requirement.  (Insertions for particles
#: just inside that layer drift into it and the requirement is never met.)
EDGE_LAYER = 0.5


class Confinement:
    """Where the particles of :func:`self_organize` may go: a :class:`arpy.Domain` (free space, walls,
    periodic axes) and, optionally, a region (a callable mask) they must stay in.

    Parameters
    ----------
    domain : Domain
        Where the particles live.
    region : callable or None
        (m, d) points -> (m,) bool: where the particles must stay.
    rstar : float
        The cutoff factor, r_c = r* D (for the exemption at the region's edge).
    """

    def __init__(self, domain: Domain, region: Callable[[np.ndarray], np.ndarray] | None,
                 rstar: float = 1.0) -> None:
        if region is not None and not callable(region):
            raise TypeError("region must be a callable mapping (m, d) points to an (m,) boolean mask")
        self.domain, self.region, self.rstar, self.d = domain, region, float(rstar), domain.d

    def inside(self, x: np.ndarray) -> np.ndarray:
        """Within the walls and the region, (m,) bool."""
        ok = self.domain.contains(x)
        if self.region is not None:
            mask = np.asarray(self.region(x), dtype=bool)
            if mask.shape != (x.shape[0],):
                raise ValueError("region(x) must return a boolean mask of shape (m,)")
            ok &= mask
        return ok

    def lists(self, x: np.ndarray, rc: np.ndarray) -> NeighborList:
        """Full lists under the min rule (minimum image along periodic axes), each row ascending
        (:meth:`arpy.NeighborList.canonical`; the particles are kept in key order, so rows are in
        key order): the energy, the gradient and the scan do not depend on the list method."""
        if self.domain.any_periodic:
            return neighbor_list(x, rc, method="auto", full=True, domain=self.domain).canonical()
        return source_rows(x, rc, x.shape[0], itself=False)       # (walls do not change the lists)

    def mirror_counts(self, x: np.ndarray, rc: np.ndarray) -> np.ndarray:
        """Neighbours p gains from the mirror images of the particles across the walls (method of
        images; a particle's own image is not counted); zeros without walls."""
        n = x.shape[0]
        if not self.domain.has_walls or n == 0:
            return np.zeros(n, np.int64)
        xm, src = self.domain.mirrors(x, rc)
        if src.size == 0:
            return np.zeros(n, np.int64)
        # an image lies beyond the plane of a wall it was mirrored across: only a particle within
        # its cutoff of a wall (or outside the walls) can reach one
        lo, hi, w = self.domain.lo, self.domain.hi, self.domain.walls
        assert lo is not None and hi is not None
        gap = np.minimum(x[:, w] - lo[w], hi[w] - x[:, w]).min(axis=1)
        near = np.flatnonzero(~(gap > rc))
        nl = cross_neighbor_list(x[near], rc[near], xm, rc[src])
        rows = near[nl.rows()]
        keep = src[nl.indices] != rows
        return np.bincount(rows[keep], minlength=n)

    def near_edge(self, x: np.ndarray, rc: np.ndarray) -> np.ndarray:
        """Particles within about r_c + EDGE_LAYER D_p of the region's edge (probes along
        the axes and diagonals)."""
        if self.region is None or x.shape[0] == 0:
            return np.zeros(x.shape[0], bool)
        assert self.d is not None           # (a domain of given dimension: for_dim)
        dirs = np.array([v for v in np.ndindex(*([3] * self.d)) if any(c != 1 for c in v)], float) - 1.0
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        reach = rc * (1.0 + EDGE_LAYER / self.rstar)
        probes = (x[:, None, :] + reach[:, None, None] * dirs[None]).reshape(-1, self.d)
        return cast(np.ndarray, ~np.asarray(self.region(probes), bool).reshape(x.shape[0], -1).all(axis=1))


def _conflict_pairs(sites: np.ndarray, Ds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (a, b), a < b, of sites (m, d) closer than half the smaller of their D (m,), in free
    space (no periodic image), found by the min rule of an AR list at 0.5 D (a kd-tree query at the
    largest D would compare every pair of fine sites when the resolutions span decades).  Whether a
    pair conflicts depends on the two sites alone (every list method tests a pair alike), so a subset
    of the sites has the pairs of the whole set among its members."""
    a, b = neighbor_list(sites, 0.5 * Ds, method="auto").pairs(sort=False)
    a, b = np.minimum(a, b), np.maximum(a, b)
    hit = np.linalg.norm(sites[a] - sites[b], axis=1) < 0.5 * np.minimum(Ds[a], Ds[b])
    return a[hit], b[hit]


def site_conflicts(sites: np.ndarray, Ds: np.ndarray) -> np.ndarray:
    """Which new sites stay (bool mask), sites in their parents' key order: neighbouring parents may
    pick the same hole, and of sites closer than half their parents' D (:func:`_conflict_pairs`), a
    site goes when an earlier site still kept is that close."""
    drop = np.zeros(sites.shape[0], bool)
    if sites.shape[0] > 1:
        a, b = _conflict_pairs(sites, Ds)
        order = np.lexsort((a, b))                  # by the later site: earlier decisions are final
        for i, j in zip(a[order], b[order]):
            if not drop[i]:
                drop[j] = True
    return ~drop


def greedy_matching(rho: np.ndarray, ka: np.ndarray, kb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fusion's matching: the candidate pairs (ka < kb, keys) visited in the order of (rho = r / D_pq,
    ka, kb), each taken when neither particle is in a pair taken before.  Returns the taken pairs
    (ka, kb) in that order.  Equal to the locally dominant matching, which the ranks find in rounds
    without gathering the pairs (:meth:`View.fusion`)."""
    order = np.lexsort((kb, ka, rho))
    used: set[int] = set()
    take = []
    for i in order.tolist():
        a, b = int(ka[i]), int(kb[i])
        if a not in used and b not in used:
            used.update((a, b))
            take.append(i)
    t = np.asarray(take, dtype=np.int64)
    return ka[t], kb[t]


#: An item's state in the rounds of :meth:`View.sites` and :meth:`View.fusion` (sites; fusion pairs):
#: not decided yet, kept (taken), dropped.
_OPEN, _KEPT, _DROPPED = 0, 1, 2


def _settle(state: list[int], todo: list[int], off: list[int], earlier: list[int]) -> list[int]:
    """One pass of a greedy (:func:`site_conflicts`, :func:`greedy_matching`) over the undecided items
    ``todo`` (ascending in the greedy's order), each item's earlier conflicting items
    ``earlier[off[j]:off[j + 1]]``: an item is dropped when one of them is kept, kept when all of them
    are dropped, else left open (the states of items outside ``todo`` are given).  Updates ``state``;
    returns the items left open."""
    left = []
    for j in todo:
        verdict = _KEPT
        for i in earlier[off[j]:off[j + 1]]:
            if state[i] == _KEPT:
                verdict = _DROPPED
                break
            if state[i] == _OPEN:
                verdict = _OPEN
        state[j] = verdict
        if verdict == _OPEN:
            left.append(j)
    return left


def _match_pass(state: list[int], here: list[bool], a: list[int], b: list[int]) -> list[int]:
    """One pass of :func:`greedy_matching` over every pair (a, b) (particle numbers) in the greedy's
    order, deciding the open pairs ``here`` the way :func:`_settle` does with their earlier pairs
    sharing a particle: a particle is free while every pair at it so far is dropped, taken once one is
    kept, and unknown while one is open; a pair is dropped at a taken particle, kept when both are
    free, else left open.  Updates ``state``; returns the pairs here left open."""
    mark = bytearray(max(max(a, default=-1), max(b, default=-1)) + 1)    # 0 free, 1 taken, 2 unknown
    left = []
    for t, (i, j) in enumerate(zip(a, b)):
        s = state[t]
        if s == _OPEN and here[t]:
            if mark[i] == 1 or mark[j] == 1:
                s = _DROPPED
            elif mark[i] == 0 and mark[j] == 0:
                s = _KEPT
            else:
                left.append(t)
            state[t] = s
        if s == _KEPT:
            mark[i] = mark[j] = 1
        elif s == _OPEN:
            if mark[i] == 0:
                mark[i] = 2
            if mark[j] == 0:
                mark[j] = 2
    return left


def places(keys: np.ndarray, k: np.ndarray, by_key: np.ndarray | None = None) -> np.ndarray:
    """The place of each key k (any shape) in ``keys`` (unique; integers or records), -1 where it is not
    there; ``by_key``: ``np.argsort(keys)`` if the caller has it."""
    if not keys.size:
        return np.full(np.shape(k), -1, np.int64)
    by_key = np.argsort(keys, kind="stable") if by_key is None else by_key
    at = by_key[np.minimum(np.searchsorted(keys, k, sorter=by_key), keys.size - 1)]
    return np.where(keys[at] == k, at, -1)


@dataclass(eq=False)
class Near:
    """A process's own particles (the first ``n`` of the arrays) and the particles within their reach
    (none on one process), with full lists whose rows (the own particles'; the others' are empty)
    are in key order.  x (m, d), D (m,), keys (m,) int64; ``sent[r]``: the own particles (indices,
    ascending) rank r holds as particles within reach (one array per rank; none on one process)."""

    x: np.ndarray
    D: np.ndarray
    keys: np.ndarray
    n: int
    nl: NeighborList
    sent: tuple[np.ndarray, ...] = ()



class View(Reductions):
    """The self-organization's view of this rank's particles (one process: P = 1, all of them): the
    particles within reach come from the other ranks by their own cutoffs (``near``) or by this rank's
    request (``around``), unshifted along periodic axes (the kernels take the minimum image) and each
    once; sums are exact, fusion pairs are decided by the ranks holding their particles, each rank
    holding the candidates at the particles within its reach only (:meth:`fusion`), and new insertion
    sites are decided where they lie, each rank holding copies of only the sites that can conflict with
    those in its box (:meth:`sites`).  On one rank nothing is exchanged."""

    def __init__(self, conf: Confinement, comm: Comm, dec: Decomposition) -> None:
        self.conf, self.comm, self.dec = conf, comm, dec
        self.lo, self.hi = dec.box(comm.rank)
        #: The phases whose items are shared between the ranks by their measured cost (the insertion's
        #: scoring of sites, the grade of Eq. 2.9; and any other Sharing of the ranks, such as a sampled
        #: resolution's interpolation); the boxes are cut by the cost of the rest.
        self.sharing = Sharing(comm, conf.domain.period)
        self.balance = CostBalance(comm, work=lambda: comm.work() - self.sharing.spent)
        #: The farthest any rank's own particle lies outside its box (:meth:`hold`; 0 after a migration):
        #: :meth:`near` and :meth:`around` reach that much further.
        self.slack = 0.0

    def _exchange(self, x: np.ndarray, keys: np.ndarray, picks: list[np.ndarray],
                  values: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
        """Own particles picks[r] to rank r; returns the own arrays followed by the received particles
        not owned here, each once, in key order: (x, keys, values...)."""
        got = [g for g in self.comm.sparse_alltoall([(x[g], keys[g], [v[g] for v in values]) if len(g) else None
                                                     for g in picks]) if g is not None]
        got = got or [(x[:0], keys[:0], [v[:0] for v in values])]
        xg = np.concatenate([g[0] for g in got]).reshape(-1, x.shape[1])
        kg = np.concatenate([g[1] for g in got]).astype(np.int64)
        kg_unique, first = np.unique(kg, return_index=True)
        keep = first[~np.isin(kg_unique, keys)]
        out = [np.concatenate([x, xg[keep]]), np.concatenate([keys, kg[keep]])]
        for i, v in enumerate(values):
            out.append(np.concatenate([v, np.concatenate([g[2][i] for g in got])[keep]]))
        return tuple(out)

    def _picks(self, x: np.ndarray, reach: np.ndarray) -> list[np.ndarray]:
        out = halo(x, reach, self.dec, np.full(x.shape[0], self.comm.rank, np.int64), domain=self.conf.domain)
        return [np.unique(idx) if idx.size else idx for idx, _ in out]

    def near(self, x: np.ndarray, D: np.ndarray, keys: np.ndarray, rc: np.ndarray, skin: float = 0.0) -> Near:
        """The own particles and those of other ranks within their cutoffs rc (+ skin) of this rank's
        box, with full lists under the min rule whose own rows are in key order."""
        n = x.shape[0]
        if self.comm.size == 1:                               # (nothing to exchange)
            return Near(x, D, keys, n, self.conf.lists(x, rc))
        picks = self._picks(x, rc + skin + self.slack)
        xe, ke, De, rce = self._exchange(x, keys, picks, [D, rc])
        m = xe.shape[0]
        if self.conf.domain.any_periodic:
            full = neighbor_list(xe, rce, method="auto", full=True, domain=self.conf.domain)
            off, idx = full.offsets[: n + 1], full.indices[: full.offsets[n]]
        else:
            # the own rows ascending (source_rows; walls do not change the lists): the own particles and
            # the received ones each in key order, so that the key order below moves few entries
            rows = source_rows(xe, rce, n, itself=False)
            off, idx = rows.offsets, rows.indices
        off = np.concatenate([off, np.full(m - n, off[n])])
        own_rows = NeighborList(off, idx, full=True, x=xe, domain=self.conf.domain)
        picks[self.comm.rank] = picks[self.comm.rank][:0]     # (images of its own: nothing another rank holds)
        return Near(xe, De, ke, n, key_ordered(own_rows, ke), tuple(picks))

    def around(self, x: np.ndarray, keys: np.ndarray, width: float | Callable[[], float],
               *values: np.ndarray) -> tuple[np.ndarray, ...]:
        """(positions, values...) of the own particles followed by every other rank's particle within
        ``width`` (or ``width()``, evaluated only where there are other ranks) of this rank's box."""
        if self.comm.size == 1:
            return (x, *values)
        widths = self.comm.gather_arrays(np.array([float(width() if callable(width) else width) + self.slack]))[0]
        period = self.conf.domain.period
        widest = float(np.fmax.reduce(widths, initial=0.0))
        near = set(self.dec.reaching_points(x, widest, period).tolist()) - {self.comm.rank}
        none = np.zeros(0, np.int64)
        picks = [np.flatnonzero(box_gap(x, *self.dec.box(r), period) <= widths[r]) if r in near else none
                 for r in range(self.comm.size)]
        xe, _, *ve = self._exchange(x, keys, picks, list(values))
        return (xe, *ve)

    def hold(self, x: np.ndarray) -> None:
        """Keep the own particles, now at ``x`` (n, d), on this rank until the next :meth:`migrate`, some of
        them outside its box: :attr:`slack` becomes the farthest any rank's own particle lies outside its
        box, and :meth:`near` and :meth:`around` reach that much further, so that they bring every
        particle within reach of the own ones wherever these lie (the lists, sums and decisions do not
        depend on which rank owns a particle).  Saves a migration and the ghost exchange of a new
        :meth:`near` where one follows soon anyway.  Collective."""
        if self.comm.size > 1:
            self.slack = self.gmax(float(self.gap(x).max(initial=0.0)))

    def gap(self, points: np.ndarray) -> np.ndarray:
        """Distance of each point from this rank's box (zero inside it)."""
        return box_gap(points, self.lo, self.hi, self.conf.domain.period)

    def gather(self, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
        """The arrays of every rank, concatenated in rank order."""
        parts = self.comm.allgather([np.asarray(a) for a in arrays])
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(len(arrays)))

    def sites(self, sites: np.ndarray, Ds: np.ndarray, parent_keys: np.ndarray) -> np.ndarray:
        """Which new sites stay: :func:`site_conflicts` over the sites of every rank in the order of
        their parents' keys (ties by rank, then by place on the rank), as a mask (n,) bool of this
        rank's sites (n, d) with their parents' D (n,) and keys (n,).  Collective.

        On several ranks nothing is gathered.  The greedy keeps the lexicographically first maximal
        set of sites without conflicts, which the ranks find in rounds (:func:`_settle`): a site is
        dropped once an earlier site it conflicts with is kept, kept once all of those are dropped.
        Each site is decided by the rank whose box holds it (its home), which holds a copy of every
        site that can conflict with it (:meth:`_site_copies`); after each round the ranks send the
        states they decided to the ranks holding a copy and to the owner, until no site is open
        anywhere.  The earliest open site has its earlier ones decided, so every round decides one at
        least: there are as many rounds as the longest chain of conflicting sites alternating between
        homes needs."""
        comm, me = self.comm, self.comm.rank
        if comm.size == 1:
            order = np.argsort(parent_keys, kind="stable")
            kept = np.empty(parent_keys.size, bool)
            kept[order] = site_conflicts(sites[order], Ds[order])
            return kept
        gid, xs, ds, pk, home, outside = self._site_copies(sites, Ds, parent_keys)
        order = np.lexsort((gid, pk))               # every rank's sites in (parent key, rank, place) order
        gid, xs, ds, home = gid[order], xs[order], ds[order], home[order]
        here = np.flatnonzero(home == me)
        # each site decided here, with its earlier conflicting sites
        a, b = _conflict_pairs(xs, ds) if gid.size > 1 else (here[:0], here[:0])
        a, b = a[home[b] == me], b[home[b] == me]
        by_later = np.argsort(b, kind="stable")
        off = np.searchsorted(b[by_later], np.arange(gid.size + 1))
        # the ranks holding a copy of a site decided here: those it was sent to, and its owner
        tell = {r: here[at] for r, at in self._site_holders(xs[here], ds[here], outside).items()}
        for q in np.unique(gid[here] >> 32).tolist():
            if q != me:
                tell[q] = np.union1d(tell.get(q, here[:0]), here[gid[here] >> 32 == q])
        off_, earlier = off.tolist(), a[by_later].tolist()
        state = self._rounds(gid, here, lambda st, todo: _settle(st, todo, off_, earlier), tell)
        return state[np.argsort(order)[: parent_keys.size]] == _KEPT         # (the own sites come first)

    def _rounds(self, ids: np.ndarray, here: np.ndarray, settle: Callable[[list[int], list[int]], list[int]],
                tell: dict[int, np.ndarray]) -> np.ndarray:
        """The rounds of :meth:`sites` and :meth:`fusion` over the items ``ids`` (in the greedy's order; ids
        of any dtype NumPy sorts, the same on every rank holding the item) of which this rank decides
        ``here``, by ``settle(state, todo)`` (:func:`_settle` or :func:`_match_pass`: decides what it can of
        the open items ``todo`` here, returns those left open), and tells rank r the state of each item
        ``tell[r]`` once it knows it (decided here or told): the states of all of them (m,) int8, once no
        rank holds an open item.  Collective."""
        by_id = np.argsort(ids)
        state, todo = [_OPEN] * ids.size, here.tolist()
        told, was = np.zeros(ids.size, bool), -1
        while True:
            left = settle(state, todo)
            st = np.array(state, np.int8)
            known = st != _OPEN
            news = [tell[r][known[tell[r]] & ~told[tell[r]]] if r in tell else here[:0] for r in range(self.comm.size)]
            told |= known
            for u in self.comm.sparse_alltoall([(ids[j], st[j]) if j.size else None for j in news]):
                if u is not None:
                    at = places(ids, u[0], by_id)
                    if np.any(at < 0):
                        raise RuntimeError("View: a rank was told the state of an item it does not hold")
                    if np.any((st[at] != _OPEN) & (st[at] != u[1])):
                        raise RuntimeError("View: ranks decided an item differently")
                    for j, v in zip(at.tolist(), u[1].tolist()):
                        state[j] = v
            todo = [j for j in left if state[j] == _OPEN]
            open_ = self.total(state.count(_OPEN))
            if not open_:
                return np.array(state, np.int8)
            if open_ == was:            # (never: the earliest open item has its earlier ones decided)
                raise RuntimeError("View: a round decided no item")
            was = open_

    def fusion(self, near: Near, rho: np.ndarray, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pairs that fuse: :func:`greedy_matching` of every rank's candidate pairs, as the keys (ka, kb)
        of the taken pairs at the particles of ``near`` (all of them on one process), in the greedy's
        order.  Each rank gives the candidates at its own particles, each once: their rho = r / D_pq (c,)
        and the places in ``near`` of their particles, p (c,) its own, q (c,) an own one of larger key or
        another rank's.  Collective.

        On several ranks nothing is gathered.  The greedy takes a pair when every earlier pair sharing a
        particle with it is not taken, and not when one is, which the ranks find in rounds
        (:func:`_match_pass`).  A rank holds every pair at the particles of its ``near``: it lists those at
        its own particles, the owner of another particle sends it those at that one (the ranks holding
        a particle within reach, ``near.sent``).  So it decides every pair whose two particles it holds
        (both owners of a pair decide it, the same way), and after each round it tells the ranks holding
        its particles the states of the pairs at them it has learnt, until no rank holds an open pair.
        The rounds grow with the times a chain of pairs, each waiting for the one before, crosses
        between boxes beyond the ranks' reach (the pulse's self-organization takes one a call)."""
        keys = near.keys
        if self.comm.size == 1:
            return greedy_matching(rho, keys[p], keys[q])
        comm, n = self.comm, near.n
        lower = keys[p] < keys[q]
        ia, ib = np.where(lower, p, q), np.where(lower, q, p)          # (ka < kb)
        ka, kb = keys[ia], keys[ib]
        sends: dict[int, np.ndarray] = {}
        for r, held in enumerate(near.sent):             # the pairs at own particles that rank r holds
            if not held.size:
                continue
            mark = np.zeros(keys.size, bool)
            mark[held] = True
            at = np.flatnonzero(mark[ia] | mark[ib])
            if at.size:
                sends[r] = at
        got = [g for g in comm.sparse_alltoall([(ka[sends[r]], kb[sends[r]], rho[sends[r]]) if r in sends else None
                                                for r in range(comm.size)]) if g is not None]
        pairs = np.empty(ka.size + sum(g[0].size for g in got), dtype=[("a", np.int64), ("b", np.int64)])
        pairs["a"] = np.concatenate([ka] + [g[0] for g in got])
        pairs["b"] = np.concatenate([kb] + [g[1] for g in got])
        ratios = np.concatenate([rho] + [g[2] for g in got])
        ids, first, inv = np.unique(pairs, return_index=True, return_inverse=True)    # (the own ones first)
        if not np.array_equal(ratios, ratios[first][inv]):
            raise RuntimeError("View.fusion: two ranks found a pair at different r / D_pq")
        a, b, r_ = ids["a"], ids["b"], ratios[first]
        listed = first < ka.size                      # (the others are at other ranks' particles only)
        ends = np.empty((2, a.size), np.int64)           # the places of the pairs' particles here, or -1
        ends[:, listed] = np.stack([ia[first[listed]], ib[first[listed]]])
        ends[:, ~listed] = places(keys, np.stack([a[~listed], b[~listed]]))
        if np.any((ends[:, ~listed] >= 0) & (ends[:, ~listed] < n)):
            raise RuntimeError("View.fusion: a rank sent a pair at a particle of this rank that it does not list")
        order = np.lexsort((b, a, r_))                  # the greedy's order
        at_order = np.empty(a.size, np.int64)
        at_order[order] = np.arange(a.size)
        here: np.ndarray = np.all(ends[:, order] >= 0, axis=0)      # the pairs with both particles here
        numbers = np.unique(np.stack([a[order], b[order]]), return_inverse=True)[1].reshape(2, -1)
        pa, pb, held = numbers[0].tolist(), numbers[1].tolist(), here.tolist()    # (particles numbered 0, 1, ..)
        tell = {r: np.sort(at_order[inv[at]]) for r, at in sends.items()}
        taken = self._rounds(ids[order], np.flatnonzero(here), lambda st, _: _match_pass(st, held, pa, pb),
                             tell) == _KEPT
        return a[order][taken], b[order][taken]

    def _site_copies(self, sites: np.ndarray, Ds: np.ndarray, parent_keys: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """This rank's sites followed by the copies of the other ranks' sites it needs: (ids, rank
        << 32 | place on the rank; sites; Ds; parent keys; homes; G).  A site's home is the rank of
        the box nearest to it (the first one holding it), G the farthest any site lies from its home
        box (zero where the boxes hold every site, as they do the sites inside the domain: the boxes
        tile its periodic axes and reach on to infinity along the others).  Site a conflicts with b
        only within 0.5 D_b of it, in free space (:func:`site_conflicts` takes no periodic image),
        and a lies within G of its home's box, so b is sent to every rank whose box lies within
        0.5 D_b + G of it (:meth:`_site_holders`): the home of a site holds every site that can
        conflict with it.  Collective."""
        comm, free = self.comm, np.zeros(sites.shape[1])
        home, best = np.zeros(parent_keys.size, np.int64), np.full(parent_keys.size, np.inf)

        def nearest(at: np.ndarray, ranks: Iterable[int]) -> None:
            for r in ranks:                          # (ascending: the first of equally near boxes)
                gap = box_gap(sites[at], *self.dec.box(r), free)
                closer = gap < best[at]
                home[at[closer]], best[at[closer]] = r, gap[closer]

        # the boxes meeting the sites' bounding box hold every site that lies in a box; a site outside
        # every box is compared with every box
        nearest(np.arange(parent_keys.size), self.dec.reaching_points(sites).tolist())
        outer = np.flatnonzero(best > 0)
        home[outer], best[outer] = 0, np.inf
        nearest(outer, range(comm.size) if outer.size else ())
        outside = self.gmax(float(best.max(initial=0.0)))
        picks = self._site_holders(sites, Ds, outside)
        place = np.arange(parent_keys.size, dtype=np.int64)
        got = comm.sparse_alltoall([tuple(v[picks[r]] for v in (sites, Ds, parent_keys, place, home))
                                    if r in picks else None for r in range(comm.size)])
        src = [(q, g) for q, g in enumerate(got) if g is not None]
        gid = np.concatenate([(comm.rank << 32) + place] + [(q << 32) + g[3] for q, g in src])
        xs, ds, pk, hs = (np.concatenate([v] + [g[i] for _, g in src])
                          for i, v in ((0, sites), (1, Ds), (2, parent_keys), (4, home)))
        return gid, xs.reshape(-1, sites.shape[1]), ds, pk, hs, outside

    def _site_holders(self, points: np.ndarray, Ds: np.ndarray, outside: float) -> dict[int, np.ndarray]:
        """{rank r other than this one: the sites (indices, ascending) within 0.5 D + G (``outside``)
        of r's box, in free space} for the ranks with such sites (a margin of 1e-9 of the reach covers
        the rounding of the distances)."""
        free, out, reach = np.zeros(points.shape[1]), {}, (0.5 * Ds + outside) * (1.0 + 1e-9)
        for r in self.dec.reaching_points(points, float(np.fmax.reduce(reach, initial=0.0))).tolist():
            if r != self.comm.rank:
                at = np.flatnonzero(box_gap(points, *self.dec.box(r), free) <= reach)
                if at.size:
                    out[r] = at
        return out

    def new_keys(self, parent_keys: np.ndarray, next_key: int) -> tuple[np.ndarray, int]:
        """Keys of the kept new sites: next_key on, in the order of their parents' keys over every
        rank (:func:`~arpy.distributed.reductions.key_places`).  Returns (this rank's keys, the next free key)."""
        return next_key + key_places(self.comm, parent_keys), next_key + self.total(np.size(parent_keys))

    def migrate(self, x: np.ndarray, keys: np.ndarray, *values: np.ndarray, balance: bool = False
                ) -> tuple[bool, tuple[np.ndarray, ...]]:
        """Own particles (with values) to the ranks that own their positions now, in key order:
        (whether anything changed, (x, keys, values...)).  With ``balance`` (once an iteration, so that
        each measurement spans one at least): when the largest box's predicted work exceeds the mean
        by more than :data:`arpy.distributed.balance.REBALANCE` (each rank's particles costing what the
        rank measured per particle since the boxes were last cut: :class:`CostBalance`), the boxes are
        bisected anew with those costs as weights first (the result does not depend on the boxes)."""
        comm = self.comm
        if comm.size == 1:                                    # (one box holds everything)
            return False, (x, keys, *values)
        self.slack = 0.0                                      # (after it every own particle lies in its box)
        dest = self.dec.locate(x)
        moving = self.balance.survey(np.bincount(dest[dest >= 0], minlength=comm.size))
        if balance and self.balance.due():
            self.dec, _ = bisect(x, comm.size, weights=self.balance.weights(x.shape[0]), domain=self.conf.domain,
                                 comm=comm)
            self.lo, self.hi = self.dec.box(comm.rank)
            self.balance.cut()
        elif not moving:                                      # every rank keeps all of its own
            return False, (x, keys, *values)
        xm, km, f = migrate(comm, self.dec, x, keys, {str(i): v for i, v in enumerate(values)})
        return True, (xm, km, *(f[str(i)] for i in range(len(values))))
