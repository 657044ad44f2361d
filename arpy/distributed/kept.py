"""Ghost layers and neighbour rows kept across the operators of moving particles (Verlet lists with a
skin over the ranks): :class:`KeptGhosts`, what :class:`arpy.distributed.DistributedDCPSE` reuses
with ``lists=`` (and :class:`arpy.Simulation` with ``verlet_skin`` in a box, at every rank count).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .. import _bridge
from ..domain import Domain
from ..lists.reuse import ReusedLists
from ..lists.neighborlist import NeighborList
from ..lists.search import cross_neighbor_list, source_rows
from .comm import Comm
from .decomposition import Decomposition
from .ghosts import GhostLayer, halo, send_ghosts

__all__ = ["KeptGhosts", "reused_lists"]


class KeptGhosts:
    """A rank's ghost layer and the rows of its particles over their sources, kept while the
    particles move a little (Verlet lists with a skin, over the ranks).

    A build takes a skin L = ``skin`` times the smallest core size of every rank: the ghost layer
    reaches L further (:func:`arpy.distributed.halo` with skin ``reach + L``) and the rows of the own
    particles over the own particles and ghosts are built with every cutoff widened by L.  Later
    calls reuse both while no particle of any rank has moved more than L / 2 since the build, and
    every rank has the particles (keys, core sizes, in the same order) and boxes of its build; the
    decision is one reduction, so the ranks build again together.  Between builds a call sends the
    ghosts' new positions (to the ranks of the layer, by one buffer exchange) and keeps of the wide
    rows the entries within the min rule now (the list builders' test); mirror images at walls are
    made afresh by the operator and their rows found by a cross list.  The rows hold exactly the
    sources a fresh build finds, and the operators sum them in key order: results are bitwise those
    without reuse, whenever the builds happen.

    Parameters
    ----------
    skin : float
        The skin as a fraction of the smallest core size (> 0).
    """

    _layer: GhostLayer
    _sends: list[tuple[np.ndarray, np.ndarray]]
    _wide: NeighborList

    def __init__(self, skin: float) -> None:
        if not (np.isfinite(skin) and skin > 0):
            raise ValueError(f"skin must be a finite number > 0, got {skin!r}")
        self.skin = float(skin)
        #: How many times the layer and rows were built.
        self.builds = 0
        self._keys: np.ndarray | None = None

    def forget(self) -> None:
        """Build afresh at the next call (the particles were replaced).  Every rank calls it."""
        self._keys = None

    def _holds(self, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray) -> bool:
        """Whether this rank's build still holds for its particles x, eps, keys in the boxes dec."""
        if self._keys is None or not np.array_equal(self._keys, keys) or not np.array_equal(self._eps, eps):
            return False
        if not (np.array_equal(self._lo, dec.lo) and np.array_equal(self._hi, dec.hi)):
            return False
        return bool(np.sqrt(((x - self._x0) ** 2).sum(axis=1).max(initial=0.0)) <= 0.5 * self._length)

    def layer(self, comm: Comm, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray,
              domain: Domain, reach: float) -> tuple[GhostLayer, list[tuple[np.ndarray, np.ndarray]]]:
        """The ghost layer of this rank's particles x (n, d) with core sizes eps and keys, which may
        lie up to ``reach`` outside its box, at their current positions, and what this rank sends to
        each rank (indices, shifts; as :func:`arpy.distributed.halo` gives them).  Collective."""
        if comm.sum(0 if self._holds(dec, x, eps, keys) else 1) == 0:
            shifted = {r: x[g] + sh for r, (g, sh) in enumerate(self._sends) if len(g)}
            return replace(self._layer, x=self._layer.swap(comm, shifted, (x.shape[1],), np.dtype(np.float64))), \
                self._sends
        self._length = self.skin * float(comm.min(np.array([eps.min(initial=np.inf)]))[0])
        self._sends = halo(x, eps, dec, np.full(x.shape[0], comm.rank, np.int64), skin=reach + self._length,
                           domain=domain)
        self._layer = send_ghosts(comm, x, eps, keys, self._sends, domain)
        self._x0, self._eps, self._keys = x.copy(), eps.copy(), np.array(keys, dtype=np.int64)
        self._lo, self._hi = dec.lo.copy(), dec.hi.copy()
        base_x = np.concatenate([x, self._layer.x])
        self._wide = source_rows(base_x, np.concatenate([eps, self._layer.rc]) + self._length, x.shape[0])
        self.builds += 1
        return self._layer, self._sends

    def rows(self, x: np.ndarray, eps: np.ndarray, src_x: np.ndarray, src_eps: np.ndarray) -> NeighborList:
        """The rows of the particles x (n, d) (core sizes eps) over the sources src_x, src_eps: the own
        particles and the ghosts of the last :meth:`layer` at their current positions, then any
        sources made from them (mirror images); each source within the min rule, as
        :func:`arpy.lists.search.source_rows` finds them (rows in no particular order)."""
        n = x.shape[0]
        n_base = n + self._layer.keys.size
        wide = self._wide
        off, idx = _bridge.filter_rows(x, eps, src_x[:n_base], src_eps[:n_base], wide.offsets, wide.indices,
                                       context="KeptGhosts")
        counts, idx = np.diff(off), idx[:off[-1]]
        if src_x.shape[0] > n_base:                     # the rows' entries among the mirror images
            more = cross_neighbor_list(x, eps, src_x[n_base:], src_eps[n_base:])
            row = np.concatenate([np.repeat(np.arange(n), counts), np.repeat(np.arange(n), np.diff(more.offsets))])
            order = np.argsort(row, kind="stable")
            idx = np.concatenate([idx.astype(np.int64), more.indices.astype(np.int64) + n_base])[order]
            counts = counts + np.diff(more.offsets)
            idx = idx.astype(np.int32)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return NeighborList(offsets, np.ascontiguousarray(idx), full=True, n_ref=src_x.shape[0], x=x, x_ref=src_x)


def reused_lists(domain: Domain, skin: float, over_ghosts: bool) -> KeptGhosts | ReusedLists | None:
    """Fresh lists for a simulation's operators at the particles with a Verlet skin of ``skin`` times the
    smallest core size (None: skin 0): :class:`KeptGhosts` for operators over ghosts (in a box, bitwise
    those of new lists), else :class:`arpy.lists.reuse.ReusedLists`."""
    if skin == 0:
        return None
    return KeptGhosts(skin) if over_ghosts else ReusedLists(domain, skin)
