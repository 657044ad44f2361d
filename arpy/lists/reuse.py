"""Neighbour lists kept across calls: the sources and lists of DC-PSE operators at moving
particles (:class:`ReusedLists`, Verlet lists with a skin), rebuilt only when a particle has moved
more than half the skin.
"""

from __future__ import annotations

import numpy as np

from .. import _bridge
from ..domain import Domain, as_domain
from .neighborlist import NeighborList
from .search import neighbor_list, source_rows

__all__ = ["ReusedLists"]


class ReusedLists:
    """The sources and neighbour lists of DC-PSE operators at moving particles, kept across calls
    (Verlet lists with a skin, the AR paper's skin).

    Built with every cutoff widened by a skin (``skin`` times the smallest core size at the build);
    reused while no particle has moved more than half the skin since (and the particles and their
    core sizes are the same); each call keeps of the stored entries those within the min rule at the
    current positions, by the test of the list builders.  Ghosts (periodic images, mirror images
    across walls) are those of the build, moved with their particles.  Rows are in the canonical
    order (ascending sources), so the operators equal those from fresh lists over the same sources
    put in that order (:meth:`arpy.NeighborList.canonical`), whenever the lists are rebuilt.

    Parameters
    ----------
    domain : Domain
    skin : float
        The skin as a fraction of the smallest core size (> 0).
    """

    _src: np.ndarray | None        # the real particle of each ghost (None: no ghosts, free space)

    def __init__(self, domain: Domain, skin: float) -> None:
        if not (np.isfinite(skin) and skin > 0):
            raise ValueError(f"skin must be a finite number > 0, got {skin!r}")
        self.domain, self.skin = as_domain(domain), float(skin)
        self.builds = 0
        self._x0: np.ndarray | None = None
        self._eps: np.ndarray | None = None

    def _build(self, x: np.ndarray, eps: np.ndarray) -> None:
        dom = self.domain.for_dim(x.shape[1])
        self._x0, self._eps, self._length = x.copy(), eps.copy(), self.skin * float(eps.min())
        wide = eps + self._length
        if dom.bounded:
            xg, src = dom.ghosts(x, wide)
            # each ghost is sign * x[src] + shift per axis: mirrored (-1) across walls, translated (+1)
            flip = dom.beyond_walls(xg)
            self._sign = np.where(flip, -1.0, 1.0)
            self._shift = xg - self._sign * x[src]
            self._src, self._mirror = src, flip.any(axis=1)
            src_x = np.concatenate([x, self._ghosts(x)])
            nl = source_rows(src_x, np.concatenate([wide, wide[src]]), x.shape[0])
        else:
            self._src = None
            nl = neighbor_list(x, wide, method="auto", full=True)
        self._nl = nl.canonical()
        self.builds += 1

    def _ghosts(self, x: np.ndarray) -> np.ndarray:
        return self._sign * x[self._src] + self._shift

    def _holds(self, dom: Domain, x: np.ndarray, eps: np.ndarray):
        """(x moved back by whole periods to within half a period of the build positions, the ghosts
        there) if the build still holds for particles at x with core sizes eps, else None: the same
        particles and core sizes, none moved more than half the skin, and no particle mirrored at the
        build now outside the box or on the wall it is mirrored across (not mirrored when built there)."""
        if self._x0 is None or self._eps is None or self._x0.shape != x.shape or not np.array_equal(self._eps, eps):
            return None
        xu = x - dom.whole_periods(x - self._x0) if dom.any_periodic else x
        if np.sqrt(((xu - self._x0) ** 2).sum(axis=1).max(initial=0.0)) > 0.5 * self._length:
            return None
        if self._src is None:
            return xu, None
        xg = self._ghosts(xu)
        mirrored = self._src[self._mirror]
        if mirrored.size and (np.any(~dom.contains(xu[mirrored])) or np.any(np.all(xg == xu[self._src], axis=1))):
            return None
        return xu, xg

    def __call__(self, x: np.ndarray, eps: np.ndarray
                 ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, NeighborList]:
        """(ghost sources or None, source positions, source core sizes, the lists) at positions x
        with core sizes eps.  The sources begin with the particles themselves, at x moved back by
        whole periods to within half a period of where they were at the build (a particle that
        crossed a periodic face keeps its neighbours and images); without ghosts the lists are
        full lists at the particles."""
        dom = self.domain.for_dim(x.shape[1])
        kept = self._holds(dom, x, eps)
        if kept is None:
            self._build(x, eps)
            kept = x, (None if self._src is None else self._ghosts(x))
        xu, xg = kept
        if xg is None:
            src_x, src_eps = xu, eps
        else:
            src_x, src_eps = np.concatenate([xu, xg]), np.concatenate([eps, eps[self._src]])
        nl = self._nl
        off, idx = _bridge.filter_rows(xu, eps, src_x, src_eps, nl.offsets, nl.indices, context="ReusedLists")
        lists = NeighborList(off, idx[:off[-1]].copy(), full=True, n_ref=None if xg is None else src_x.shape[0],
                             x=xu, x_ref=None if xg is None else src_x)
        return self._src, src_x, src_eps, lists
