"""Balance by cost: when the ranks' boxes are cut anew, and with which weights (:class:`CostBalance`).

A box's work is not its particle count.  In the self-organization most of it goes where particles are
inserted (each parent tries many candidate sites) and where the lists are dear, and that place moves
as the resolution refines: the ranks of the 2D pulse held the same number of particles, and the same
number of neighbour pairs, while one computed twice as long as the other.  So the cost is measured:
each rank's CPU time outside its exchanges (:meth:`arpy.distributed.Comm.work`) since the boxes were
last cut, per particle it holds, is the modelled cost of each of its particles (a rank's density).
The predicted work of a box is the sum of these costs over the particles it would own; when the
largest box's exceeds :data:`REBALANCE` times the mean, the boxes are bisected anew with the costs as
weights (:func:`arpy.distributed.bisect`, integer weights, :data:`WEIGHT_UNIT` for the mean particle).
Every rank takes the decision from the same gathered numbers, so they take it together.

Only who owns what changes: every result of arpy is the same for any boxes, so a run balanced by
cost is bitwise the run balanced by count and the one-process run.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .comm import Comm

__all__ = ["REBALANCE", "WEIGHT_UNIT", "CostBalance"]

#: The boxes are cut anew when the largest box's predicted work exceeds this times the mean.
REBALANCE = 1.02
#: The integer weight of a particle of the mean measured cost (:func:`arpy.distributed.bisect` takes
#: integers; a particle costs at least 1).
WEIGHT_UNIT = 1000


class CostBalance:
    """The measured cost of the particles of each rank, and the decision to cut the boxes anew.

    Collective: every rank calls :meth:`survey` at the same points (it is one allgather).  On one rank
    there is nothing to balance (P = 1).

    Parameters
    ----------
    comm : Comm
        The ranks.
    threshold : float
        Cut anew when the largest box's predicted work exceeds ``threshold`` times the mean.
    measured : bool
        True: each rank's particles cost what the rank measured per particle; False: every particle
        costs the same (the model of a phase whose cost per particle is even, as a time step's on an
        adapted set, whose particles have about N* neighbours each).
    work : callable or None
        The rank's work so far, seconds (default :meth:`Comm.work`): a caller whose phases are shared
        between the ranks by :class:`~arpy.distributed.share.Sharing` leaves them out (sharing evens
        them out whatever the boxes; the boxes are to even out the rest).
    """

    def __init__(self, comm: Comm, threshold: float = REBALANCE, measured: bool = True,
                 work: Callable[[], float] | None = None) -> None:
        self.comm, self.threshold, self.measured = comm, float(threshold), bool(measured)
        self.work = comm.work if work is None else work
        self.mark = self.work()
        #: The measured cost of a particle of each rank over the mean particle's (P,), from the last
        #: survey (ones before one).
        self.density = np.ones(comm.size)
        #: The predicted work of each box (P,) at the last survey, in units of the mean particle.
        self.loads = np.zeros(comm.size)

    def survey(self, counts: np.ndarray) -> bool:
        """Gather every rank's particles by the box that will own them (``counts``, int (P,); only the
        boxes it has particles for travel, so a survey carries O(P) numbers to each rank, not P x P) and
        its work since the boxes were last cut.  Sets :attr:`density` and :attr:`loads`.  Returns whether
        any rank has particles for a box other than its own.  Collective."""
        P = self.comm.size
        c = np.asarray(counts, np.int64)
        to = np.flatnonzero(c)
        # each rank: its work (the bits of the double), then its boxes, then its counts for them
        spent = np.array([self.work() - self.mark]).view(np.int64)
        got, at = self.comm.gather_arrays(np.concatenate([spent, to, c[to]]))
        k = (np.diff(at) - 1) // 2                            # (the boxes each rank has particles for)
        rank = np.repeat(np.arange(P), k)
        place = np.arange(rank.size) - np.repeat(np.cumsum(k) - k, k)     # (each entry's place in its rank's)
        boxes, count = got[at[:-1][rank] + 1 + place], got[at[:-1][rank] + 1 + k[rank] + place]
        if self.measured:
            self.density = densities(np.bincount(rank, weights=count, minlength=P), got[at[:-1]].view(np.float64))
        self.loads = np.bincount(boxes, weights=self.density[rank] * count, minlength=P).astype(np.float64)
        return bool(np.any(boxes != rank))

    def due(self) -> bool:
        """Whether the largest box's predicted work (:attr:`loads`) exceeds the threshold times the
        mean (the same answer on every rank)."""
        return bool(self.loads.max() > self.threshold * self.loads.mean()) if self.loads.sum() > 0 else False

    def weights(self, n: int) -> np.ndarray:
        """The integer weights of this rank's ``n`` particles for :func:`arpy.distributed.bisect`: its
        density in units of :data:`WEIGHT_UNIT`, at least 1.  int64 (n,)."""
        return np.full(int(n), max(1, int(round(WEIGHT_UNIT * self.density[self.comm.rank]))), np.int64)

    def cut(self) -> None:
        """The boxes were cut anew: measure from here."""
        self.mark = self.work()


def densities(counts: np.ndarray, spent: np.ndarray) -> np.ndarray:
    """The measured cost of a particle of each rank over the mean particle's: ``spent[r] / counts[r]``
    (rank r's seconds over its particles) divided by ``spent.sum() / counts.sum()``; a rank without
    particles (or no time measured anywhere) counts as the mean.  (P,) float."""
    counts, spent = np.asarray(counts, np.float64), np.maximum(np.asarray(spent, np.float64), 0.0)
    if counts.sum() == 0 or spent.sum() <= 0:
        return np.ones(counts.size)
    mean = spent.sum() / counts.sum()
    return np.where(counts > 0, spent / np.maximum(counts, 1) / mean, 1.0)
