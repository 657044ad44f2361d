"""Work shared between ranks by its measured cost: :class:`Sharing`.

Some phases cost more per particle in one part of the domain than in another: the scoring of insertion
sites where the set still refines, the grade of Eq. 2.9 where the target resolution is finest, the
interpolation of a sampled resolution where the old particles are dense.  One cut of the boxes evens
out their sum (:mod:`~arpy.distributed.balance`), not each phase, and ranks that take turns being slow
wait for each other at every exchange.  Such a phase is a map: the result of each of a rank's items (an
insertion parent, a particle) depends on the item and on the sources (particles) within its reach
alone.  :meth:`Sharing.map` evens out what the ranks compute after handing items out.  Each rank
measures its cost per item at the phase's last call (:meth:`arpy.distributed.Comm.work`); when the
largest predicted work exceeds :data:`SHARE` times the mean, the ranks above the mean hand items to
those below it: a slab of items at one end of the giver's (along the axis they spread most), with every
source within their reach, is computed by the taker and the results are sent back.  The sources travel
with the items, so an item's result is the one its giver would compute: sharing changes who computes,
never what.
"""

from __future__ import annotations

import weakref
from typing import Any, Callable, Sequence

import numpy as np

from .comm import Comm
from .decomposition import bounding_box, box_gap

__all__ = ["MIN_ITEMS", "SHARE", "Sharing", "transfers"]

#: Items are shared when the largest rank's predicted work exceeds this times the mean.
SHARE = 1.02
#: A rank hands another at least this many items (fewer are not worth a message).
MIN_ITEMS = 64

class _Measured:
    """What the Sharings of one communicator measured on this rank: the cost per item of each phase
    (:attr:`Sharing.rates`, :attr:`Sharing.units`) and the work spent in their maps (:attr:`Sharing.spent`)."""

    def __init__(self) -> None:
        self.rates: dict[str, float] = {}
        self.units: dict[str, float] = {}
        self.spent = 0.0


#: Each communicator's measurements, kept while it lives: a phase called again by another Sharing of the
#: same ranks (the next self-organization, the next re-organization's grade) is planned from its last
#: call, and every shared phase is left out of the cost the boxes are cut by.
_MEASURED: "weakref.WeakKeyDictionary[Any, _Measured]" = weakref.WeakKeyDictionary()


def transfers(loads: np.ndarray, units: np.ndarray, counts: np.ndarray, least: int = MIN_ITEMS
              ) -> list[tuple[int, int, int]]:
    """Which rank hands how many items to which: (giver, taker, items), givers and takers each in rank
    order.  ``loads`` (P,): each rank's predicted work; ``units`` (P,): the work of an item it hands
    out; ``counts`` (P,): its items.  Each rank above the mean load gives its surplus (in items of its
    unit) to the ranks below it, as much as each one lacks; a transfer of fewer than ``least`` items is
    left out.  The same list on every rank."""
    P = loads.size
    mean = loads.sum() / P
    surplus = [[r, loads[r] - mean] for r in range(P) if loads[r] > mean and units[r] > 0]
    deficit = [[r, mean - loads[r]] for r in range(P) if loads[r] < mean]
    out: list[tuple[int, int, int]] = []
    left = {r: int(counts[r]) for r, _ in surplus}
    i = j = 0
    while i < len(surplus) and j < len(deficit):
        g, t = surplus[i][0], deficit[j][0]
        amount = min(surplus[i][1], deficit[j][1])
        items = min(int(amount / units[g]), left[g])
        if items >= max(least, 1):
            out.append((g, t, items))
            left[g] -= items
        surplus[i][1] -= amount
        deficit[j][1] -= amount
        if surplus[i][1] <= 0:
            i += 1
        if deficit[j][1] <= 0:
            j += 1
    return out


class Sharing:
    """The measured cost per item of each phase on this rank (kept for the communicator), and the map
    that shares a phase's items between the ranks by it.  Collective: every rank calls :meth:`map` for
    the same phases in the same order.  On one rank it computes everything itself (P = 1).

    Parameters
    ----------
    comm : Comm
        The ranks.
    period : array (d,) or None
        The domain's periods (0 along an axis that is not periodic): reaches wrap around periodic axes.
    threshold : float or None
        Share when the largest rank's predicted work exceeds this times the mean (None: :data:`SHARE`).
    least : int or None
        The fewest items a rank hands another (None: :data:`MIN_ITEMS`).
    """

    def __init__(self, comm: Comm, period: np.ndarray | None, threshold: float | None = None,
                 least: int | None = None) -> None:
        self.comm, self.period = comm, period
        self.threshold = SHARE if threshold is None else float(threshold)
        self.least = MIN_ITEMS if least is None else int(least)
        #: Work (:meth:`Comm.work`, seconds) per item of this rank for each phase at its last call, on
        #: whichever rank the item was computed (handing items out left out); and per item it handed out
        #: (at the ranks that took it).  Shared by every Sharing of the same communicator.
        try:
            self._measured = _MEASURED.setdefault(comm, _Measured())
        except TypeError:           # (a communicator that cannot be referenced weakly: measured here alone)
            self._measured = _Measured()
        self.rates, self.units = self._measured.rates, self._measured.units
        #: Items of each phase this rank handed to other ranks, and computed for them, so far.
        self.given: dict[str, int] = {}
        self.taken: dict[str, int] = {}

    @property
    def spent(self) -> float:
        """Work (seconds) this rank has spent in the maps of every Sharing of its communicator, outside
        their exchanges: its items, handing them out and the items it computed for others."""
        return self._measured.spent

    def map(self, phase: str, work: Callable[..., Sequence[np.ndarray]], items: Sequence[np.ndarray],
            centres: np.ndarray, reach: np.ndarray | Callable[[], np.ndarray], sources: Sequence[np.ndarray]
            ) -> tuple[np.ndarray, ...]:
        """``work(*items, *sources)`` for this rank's items, some of them computed by other ranks.

        ``items``: arrays whose first axis (n) runs over the items; ``centres`` (n, d) and ``reach``
        (n,) (or a function returning it, called only where there are other ranks): each item's result
        depends on the sources within ``reach`` of its centre alone (the minimum image along periodic
        axes), every one of which is among ``sources``, arrays whose first axis (m) runs over the
        sources, positions (m, d) first.  ``work`` returns arrays whose first axis runs over the items
        it was given.  Returns the result arrays (first axis n) in the order of the items.  Collective."""
        comm, n = self.comm, int(centres.shape[0])
        if comm.size == 1:
            return tuple(work(*items, *sources))
        # (each rank's items, cost per item and per item handed out: NaN where not measured yet)
        every = comm.gather_arrays(np.array([n, self.rates.get(phase, np.nan), self.units.get(phase, np.nan)],
                                            np.float64))[0].reshape(comm.size, 3)
        t0 = comm.work()
        counts, rated = every[:, 0], ~np.isnan(every[:, 1])
        typical = float(np.mean(every[rated, 1])) if rated.any() else 1.0
        rates = np.where(rated, every[:, 1], typical)
        units = np.where(np.isnan(every[:, 2]), rates, every[:, 2])
        loads = counts * rates
        plan: list[tuple[int, int, int]] = []
        if loads.sum() > 0 and loads.max() > self.threshold * loads.mean():
            plan = transfers(loads, units, counts, self.least)
        handed: list[tuple[int, np.ndarray]] = []
        sends: list[Any] = [None] * comm.size
        kept: np.ndarray | slice = slice(None)
        mine = [(t, c) for g, t, c in plan if g == comm.rank]
        if mine:
            # slabs of items from the low end of the axis they spread most along, one per taker; the
            # sources within reach of a slab are within it of the slab's extent along that axis
            lo, hi = bounding_box(centres)
            axis = int(np.argmax(hi - lo))
            along = centres[:, axis]
            ends = np.cumsum([c for _, c in mine])
            slab = np.full(n, len(mine))
            part = np.argpartition(along, ends - 1)
            for j in range(len(mine)):
                slab[part[(ends[j - 1] if j else 0):ends[j]]] = j
            rc = np.asarray(reach() if callable(reach) else reach, np.float64)
            period = None if self.period is None else self.period[axis:axis + 1]
            for j, (t, _) in enumerate(mine):
                idx = np.flatnonzero(slab == j)
                near = box_gap(sources[0][:, axis:axis + 1], along[idx].min(keepdims=True), along[idx].max(keepdims=True),
                               period) <= float(rc[idx].max()) * (1.0 + 1e-9)
                sends[t] = (tuple(a[idx] for a in items), tuple(v[near] for v in sources))
                handed.append((t, idx))
            kept = np.flatnonzero(slab == len(mine))
            self.given[phase] = self.given.get(phase, 0) + int(ends[-1])
        got = comm.sparse_alltoall(sends) if plan else [None] * comm.size
        # the plan evens out what the ranks compute after the exchange: handing items out comes before it
        # (the takers wait for it there in any case) and is left out of the cost of the items
        t1 = comm.work()
        local = tuple(work(*(a[kept] for a in items), *sources))
        own = comm.work() - t1
        replies: list[Any] = [None] * comm.size
        for giver, g in enumerate(got):
            if g is not None:
                start = comm.work()
                replies[giver] = (tuple(work(*g[0], *g[1])), comm.work() - start)
                self.taken[phase] = self.taken.get(phase, 0) + len(g[0][0])
        self._measured.spent += comm.work() - t0
        if not plan:
            if n:
                self.rates[phase] = own / n
            return local
        back = comm.sparse_alltoall(replies)
        out = []
        for i, v in enumerate(local):
            full = np.empty((n, *v.shape[1:]), v.dtype)
            full[kept] = v
            for t, idx in handed:
                full[idx] = back[t][0][i]
            out.append(full)
        # the cost of this rank's items wherever they were computed, and of one it hands out
        elsewhere = sum(back[t][1] for t, _ in handed)
        if n:
            self.rates[phase] = (own + elsewhere) / n
        if handed:
            self.units[phase] = elsewhere / sum(idx.size for _, idx in handed)
        return tuple(out)
