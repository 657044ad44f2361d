"""Which particles a rank needs besides its own, and the exchanges that move particles between ranks.

* :func:`halo`: the ghosts of each rank.  A particle goes to a rank when it lies within its own reach
  (cutoff + skin) of that rank's box, tested against every box, not only neighbouring ones (balanced
  cuts may be thinner than the largest cutoff); along periodic axes against the box shifted by whole
  periods.  Under the min rule ``|x_p - x_q| <= min(rc_p, rc_q) + skin`` this is exact: every
  neighbour of an owned particle reaches the owner's box, so a rank's lists over its own particles and
  its ghosts hold the serial rows of its own particles.  The test is evaluated with the list builders'
  arithmetic (squared gaps summed axis by axis), so ties at the cutoff are decided the same way.
* :func:`migrate`: particles to the ranks whose boxes hold them after a move, with their fields.
* :func:`exchange_ghosts`: every rank's ghosts from every rank, in key order, with value refreshes
  (:class:`GhostLayer`); :func:`fetch` and :func:`repair_sends`: particles (and periodic images) a
  rank asks the others for.
* :func:`scatter`: the same set on every rank -> each rank's share.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from .. import _bridge
from .._validate import as_cutoffs, as_positions
from ..domain import Domain, as_domain
from ..lists.neighborlist import pairs_increasing
from ..lists.search import cross_neighbor_list
from .comm import Comm
from .inputs import agree
from .decomposition import Decomposition, bisect, box_gap2

if TYPE_CHECKING:
    from ..dcpse.boundary import Conditions

__all__ = ["GhostLayer", "dealt_share", "exchange_ghosts", "fetch", "halo", "migrate", "owned", "periodic_images", "repair_sends", "scatter",
           "send_ghosts"]


def halo(x: np.ndarray, rc: float | np.ndarray, dec: Decomposition, owner: np.ndarray, *, skin: float = 0.0,
         domain: Domain | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ghosts of every rank under the min rule: particle q is a ghost of rank r when it (or its
    periodic image) lies within ``rc_q + skin`` of r's box and r does not own it there.

    Parameters
    ----------
    x : array (n, d)
        Positions (inside the domain).
    rc : float or array (n,)
        Cutoff radii.
    dec, owner : Decomposition, array (n,)
        The boxes and the owners (from :func:`bisect`; on a rank of a distributed run, its own
        particles, all owned by it).
    skin : float
        Verlet skin added to every cutoff.
    domain : Domain, optional
        Periodic axes add the images shifted by whole periods (cutoffs + skin must stay below half
        of each period, as for the serial lists).

    Returns
    -------
    list of (array (g,), array (g, d)), one per rank
        The ghosts' particle indices (into ``x``) and the shifts to add to their positions (0 but
        along periodic axes), ordered by (shift, index).
    """
    xs = as_positions(x)
    n, d = xs.shape
    reach = as_cutoffs(rc, n) + float(skin)
    own = np.asarray(owner, dtype=np.int64)
    r2 = reach * reach
    images = np.zeros((0, d))                                  # the shifts of the periodic images
    edge = np.zeros(0, np.int64)
    dom = as_domain(domain, d)
    if dec.parts == 1 and not dom.any_periodic and not np.any(own):
        return [(np.zeros(0, np.int64), np.zeros((0, d)))]     # (one box owning all, no images: no ghosts)
    if dom.any_periodic:
        assert dom.lo is not None and dom.hi is not None
        per = np.asarray(dom.periodic)
        if dec.parts == 1 and np.array_equal(dec.lo[0][per], dom.lo[per]) and np.array_equal(dec.hi[0][per], dom.hi[per]):
            # one box spanning the periodic axes: its ghosts are the particles' own periodic images
            # within reach of the faces (along several axes a superset of the images within reach
            # of the box, which changes no list)
            return [periodic_images(xs, reach, dom)]
        images = dom.image_shifts() * dom.period
        # the image shifted by +L (-L) along a periodic axis reaches a box only from a particle within
        # the widest reach of the highest box face minus L (the lowest plus L) there: for boxes that
        # tile the domain, of its low (high) face
        widest = float(reach.max(initial=0.0))
        edge = np.flatnonzero(np.any(((xs <= dec.hi.max(axis=0) - dom.period + widest)
                                      | (xs >= dec.lo.min(axis=0) + dom.period - widest)) & dom.periodic, axis=1))
    shifted = xs[edge][None, :, :] + images[:, None, :]        # (shifts, edge particles, d)
    near_ranks = set(dec.reaching_points(np.concatenate([xs, shifted.reshape(-1, d)]),
                                         float(reach.max(initial=0.0))).tolist())     # (the others have no ghost)
    # (one empty entry for the ranks out of reach, so that a call costs little per rank of a large run)
    out: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(0, np.int64), np.zeros((0, d)))] * dec.parts
    for r in sorted(near_ranks):
        lo, hi = dec.box(r)
        mine = np.flatnonzero(own != r)                        # a rank's own particles are no ghosts there
        idx = [mine[box_gap2(xs[mine], lo, hi) <= r2[mine]]]
        near = box_gap2(shifted.reshape(-1, d), lo, hi).reshape(len(images), edge.size) <= r2[edge]
        idx += [edge[row] for row in near]
        counts = [len(i) for i in idx]
        out[r] = (np.concatenate(idx), np.repeat(np.vstack([np.zeros(d), images]), counts, axis=0))
    return out


def migrate(comm: Comm, dec: Decomposition, x: np.ndarray, keys: np.ndarray,
            fields: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Send each particle of this rank to the rank whose box holds it now (after the particles
    moved); returns this rank's particles (x, keys, fields) in key order.  Nothing is lost or
    duplicated: every particle inside the decomposed box has exactly one owner."""
    xs = as_positions(x)
    k = np.asarray(keys, dtype=np.int64)
    fields = fields or {}
    dest = dec.locate(xs)
    if np.any(dest < 0):
        bad = int(np.flatnonzero(dest < 0)[0])
        raise ValueError(f"particle of key {k[bad]} at {xs[bad]} is outside the decomposed box")
    sends: list[Any] = [None] * comm.size
    for r in np.unique(dest).tolist():                     # (the ranks that get particles)
        sel = dest == r
        sends[r] = (xs[sel], k[sel], {f: v[sel] for f, v in fields.items()})
    got = [g for g in comm.sparse_alltoall(sends) if g is not None]
    got = got or [(xs[:0], k[:0], {f: v[:0] for f, v in fields.items()})]
    x_new = np.concatenate([g[0] for g in got]).reshape(-1, xs.shape[1])
    k_new = np.concatenate([g[1] for g in got])
    order = np.argsort(k_new, kind="stable")
    return x_new[order], k_new[order], {f: np.concatenate([g[2][f] for g in got])[order] for f in fields}


@dataclass(frozen=True)
class GhostLayer:
    """This rank's ghosts and how to refresh their values (:func:`exchange_ghosts`).

    Attributes
    ----------
    x : array (g, d)
        Ghost positions (periodic images shifted), in the order (shift, key).
    rc : array (g,)
        Their cutoffs.
    keys : int64 array (g,)
        Their keys.
    shift : int64 array (g,)
        Of a periodic image, its shift's place among {-1, 0, 1}^d (first axis slowest); -1 for none.
    sends : list of int arrays, one per rank
        This rank's particles that are ghosts of each rank (indices into its own arrays).
    order : int array (g,) or None
        The received ghosts, concatenated by source rank, put into the layer's order; None: they come
        in that order.
    received : list of int, one per rank
        How many of the ghosts came from each rank.
    """

    x: np.ndarray
    rc: np.ndarray
    keys: np.ndarray
    shift: np.ndarray
    sends: list[np.ndarray]
    order: np.ndarray | None
    received: list[int]

    def refresh(self, comm: Comm, values: np.ndarray) -> np.ndarray:
        """The ghosts' values of a field given on this rank's own particles, an array (n, ...) of one
        dtype on every rank: the ghosts of the same particle, images included, get its value.  Only
        the ranks whose boxes touch (within the reach) exchange, by buffers (:meth:`Comm.exchange`)."""
        v = np.asarray(values)
        return self.swap(comm, {r: v[g] for r, g in enumerate(self.sends) if len(g)}, v.shape[1:], v.dtype)

    def swap(self, comm: Comm, sends: dict[int, np.ndarray], shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        """The ghosts' rows of arrays this rank sends to the ranks of :attr:`sends`, one row per particle
        sent, in their order (e.g. the values of a field, or positions with their periodic shifts
        added), each row of ``shape`` and ``dtype``: the exchange of :meth:`refresh`.  Collective."""
        recv = {r: np.empty((c, *shape), dtype) for r, c in enumerate(self.received) if c}
        comm.exchange(sends, recv)
        if not recv:
            return np.empty((0, *shape), dtype)
        got = recv[min(recv)] if len(recv) == 1 else np.concatenate([recv[r] for r in sorted(recv)])
        return got if self.order is None else got[self.order]


def exchange_ghosts(comm: Comm, dec: Decomposition, x: np.ndarray, rc: float | np.ndarray, keys: np.ndarray, *,
                    skin: float = 0.0, domain: Domain | None = None) -> GhostLayer:
    """The ghosts of this rank from every rank (:func:`halo` on each rank's own particles, sent with
    ``alltoall``), in the order (shift, key), which does not depend on the rank count; their
    fields follow with :meth:`GhostLayer.refresh`."""
    xs = as_positions(x)
    rcs = as_cutoffs(rc, xs.shape[0])
    sends = halo(xs, rcs, dec, np.full(xs.shape[0], comm.rank, np.int64), skin=skin, domain=domain)
    return send_ghosts(comm, xs, rcs, keys, sends, domain)


def send_ghosts(comm: Comm, x: np.ndarray, rc: np.ndarray, keys: np.ndarray,
                 sends: list[tuple[np.ndarray, np.ndarray]], domain: Domain | None) -> GhostLayer:
    """The layer made by sending each rank r the own particles ``sends[r]`` (indices, shifts)."""
    xg, rg, kg, sg, order, received = fetch(comm, x, rc, keys, sends, domain)
    return GhostLayer(xg, rg, kg, sg, [g for g, _ in sends], order, received)


def periodic_images(x: np.ndarray, reach: np.ndarray, dom: Domain) -> tuple[np.ndarray, np.ndarray]:
    """The periodic images of the particles x (n, d) within ``reach`` (n,) of the faces of the box
    ``dom`` (the rule of :meth:`arpy.Domain.images`, by the core: imaged by s in {-1, 0, 1}^d when
    within reach of the low face along every +1 axis and of the high face along every -1 axis; the
    particles may lie beside the box, as at a stage of a step), by shift, then particle.  Returns
    (their particles' indices, the shifts in whole periods (m, d))."""
    assert dom.lo is not None and dom.hi is not None
    per = np.asarray(dom.periodic)
    m = _bridge.images_count(x, reach, dom.lo, dom.hi, per)
    xg, src = _bridge.images(x, reach, dom.lo, dom.hi, per, m, context="periodic images")
    src = src.astype(np.int64)
    return src, dom.whole_periods(xg - x[src])


#: Relative margin of the particles sent for a stencil repair (a superset: the gather decides).
ASK_MARGIN = 2.0 ** -30


def repair_sends(comm: Comm, x: np.ndarray, rc: np.ndarray, points: np.ndarray, radius: np.ndarray,
                  dom: Domain, skin: float, sends: list[tuple[np.ndarray, np.ndarray]],
                  walls: "Conditions | None" = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """``sends`` and, for each rank, this rank's particles and periodic images (serial rule, reach
    rc + skin) within ``radius`` of the points that rank asks about (its stencils to repair): a
    receiver-side request, each (index, shift) sent once.  With ``walls`` (a field's conditions with
    Dirichlet faces), also those whose boundary particles (projections onto the faces,
    :meth:`~arpy.dcpse.boundary.Conditions.projections`) lie within ``radius``: the asking rank makes
    them itself."""
    n, d = x.shape
    img, shift = periodic_images(x, rc + skin, dom) if dom.any_periodic else (np.zeros(0, np.int64), np.zeros((0, d)))
    cand = np.concatenate([np.arange(n), img])
    cshift = np.concatenate([np.zeros((n, d)), shift])
    cpos = x[cand] + cshift
    if walls is not None:
        pw, pj, _ = walls.projections(cpos, rc[cand])
        cand, cshift, cpos = np.concatenate([cand, cand[pj]]), np.concatenate([cshift, cshift[pj]]), \
            np.concatenate([cpos, pw])
    own = np.all(cshift == 0, axis=1)
    out = []
    # (every rank's points and radii, d + 1 numbers a point, in one buffer)
    asked, at = comm.gather_arrays(np.column_stack([np.reshape(points, (-1, d)), np.ravel(radius)]).astype(np.float64))
    for r in range(comm.size):
        ask = asked[at[r]:at[r + 1]].reshape(-1, d + 1)
        pts, rad = ask[:, :d], ask[:, d]
        idx, sh = sends[r]
        if len(pts) and len(cand):
            wide = np.asarray(rad) * (1 + ASK_MARGIN)
            hit = np.unique(cross_neighbor_list(pts, wide, cpos, np.full(len(cand), wide.max())).indices)
            if r == comm.rank:
                hit = hit[~own[hit]]                           # (own particles are no ghosts of their rank)
            both = np.unique(np.column_stack([np.concatenate([idx, cand[hit]]),
                                              np.concatenate([sh, cshift[hit]])]), axis=0)
            idx, sh = both[:, 0].astype(np.int64), both[:, 1:]
        out.append((idx, sh))
    return out


def owned(comm: Comm, domain: Domain, x: np.ndarray, keys: np.ndarray, dec: Decomposition | None,
          fields: dict[str, np.ndarray] | None = None
          ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], Decomposition]:
    """A rank's particles (x, keys, fields) as a distributed function takes them: in the boxes ``dec``
    that own them.  dec None: the particles (confined to the domain) are bisected and migrated to their
    owners; given: every rank's particles must lie in its own box, else every rank raises ValueError.
    Returns (x, keys, fields, the boxes).  Collective."""
    fields = fields or {}
    if dec is None:
        xs = domain.confine(x)
        dec = bisect(xs[np.all(np.isfinite(xs), axis=1)], comm.size, domain=domain, comm=comm)[0]
        if comm.size > 1:
            xs, keys, fields = migrate(comm, dec, xs, keys, fields)
        return xs, keys, fields, dec
    stray = int(np.count_nonzero(dec.locate(domain.confine(x)) != comm.rank))
    if comm.sum(stray):
        raise ValueError(f"{comm.sum(stray)} particles lie outside the box of the rank that gives them: with "
                         "decomposition=, each rank gives the particles its box owns (arpy.distributed.migrate)")
    return x, keys, fields, dec


def dealt_share(comm: Comm, n: int) -> np.ndarray:
    """The indices (int64, increasing) of the particles of a set of ``n`` given whole on every rank
    that this rank takes when the set is dealt: every P-th from the rank's number (:func:`scatter`'s
    default deal)."""
    return np.arange(comm.rank, n, comm.size, dtype=np.int64)


def scatter(comm: Comm, x: np.ndarray, fields: dict[str, np.ndarray] | None = None, *,
            domain: Domain | None = None, deal: np.ndarray | None = None, same: Mapping[str, Any] | None = None
            ) -> tuple[Decomposition, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The same particle set on every rank -> each rank's share: keys are the indices into ``x``; the
    ranks take the particles ``deal`` gives them (the rank of each particle, int (n,), the same on
    every rank; default every P-th from the rank's number), bisect (:func:`bisect`) and migrate
    (:func:`migrate`).  Returns (decomposition, this rank's x, keys and fields, in key order).

    First checks that the ranks were given the same set, fields, domain and deal, and the caller's
    ``same`` (name -> value: other inputs that must be global), in one collective
    (:func:`~arpy.distributed.inputs.agree`: ValueError on every rank, naming what differs)."""
    xs = as_positions(x)
    agree(comm, "the particle set given to every rank (scatter)", x=xs, domain=domain, deal=deal,
          **{f"field {k!r}": v for k, v in (fields or {}).items()}, **(same or {}))
    n = xs.shape[0]
    if deal is None:
        mine = dealt_share(comm, n)
    else:
        deal = np.asarray(deal)
        if deal.shape != (n,) or not np.issubdtype(deal.dtype, np.integer) or np.any((deal < 0) | (deal >= comm.size)):
            raise ValueError(f"deal must give each of the {n} particles a rank 0 .. {comm.size - 1}")
        mine = np.flatnonzero(deal == comm.rank)
    dec, _ = bisect(xs[mine], comm.size, domain=domain, comm=comm)
    xo, ko, fo = migrate(comm, dec, xs[mine], mine.astype(np.int64), {k: np.asarray(v)[mine]
                                                                      for k, v in (fields or {}).items()})
    return dec, xo, ko, fo


def fetch(comm: Comm, x: np.ndarray, values: np.ndarray, keys: np.ndarray, sends: list[tuple[np.ndarray, np.ndarray]],
          domain: Domain | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, list[int]]:
    """Send ``sends`` (indices, shifts) with their values and keys, only to the ranks that get some
    (:meth:`Comm.sparse_alltoall`); returns what this rank received, (positions, values, keys, shift
    ids), in the order (shift id, key): the order in which a process holding every particle numbered
    by key lists them and their periodic images; that order (the received arrays, concatenated by
    source rank, -> this order; None: they came in it); and how many came from each rank."""
    k = np.asarray(keys, dtype=np.int64)
    d = x.shape[1]
    dom = domain.for_dim(d) if domain is not None and domain.for_dim(d).bounded else None

    def ids(sh: np.ndarray) -> np.ndarray:
        return dom.image_ids(sh) if dom is not None and sh.shape[0] else np.full(sh.shape[0], -1, np.int64)

    v = np.asarray(values)
    if comm.size == 1 and not any(len(g) for g, _ in sends):     # (one rank sending itself nothing: no ghosts)
        return x[:0], v[:0], k[:0], ids(np.zeros((0, d))), None, [0]
    got = comm.sparse_alltoall([(x[g] + sh, v[g], k[g], ids(sh)) if len(g) else None for g, sh in sends])
    received = [0 if g is None else len(g[2]) for g in got]
    parts = [g for g in got if g is not None] or [(x[:0], v[:0], k[:0], ids(np.zeros((0, d))))]
    if len(parts) == 1:                   # (from one rank: as it sent them)
        xg, vg, kg, sg = parts[0]
        xg = xg.reshape(-1, d)
    else:
        xg = np.concatenate([g[0] for g in parts]).reshape(-1, d)
        vg, kg, sg = (np.concatenate([g[i] for g in parts]) for i in (1, 2, 3))
    if pairs_increasing(sg, kg):          # (in the order (shift id, key) already: e.g. one rank's images)
        return xg, vg, kg, sg, None, received
    order = np.lexsort((kg, sg))
    return xg[order], vg[order], kg[order], sg[order], order, received
