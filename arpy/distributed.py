"""Domain decomposition for distributed runs: recursive coordinate bisection and ghost layers of
per-particle width.

These are the geometric pieces of an SPMD run (one process per rank, particles exchanged with MPI):
which rank owns each particle, and which particles a rank needs besides its own.  They are plain
NumPy and need no communicator, so every rule can be checked against the serial lists in one process.

* :func:`bisect`: recursive coordinate bisection weighted by particle count (or any weight), no
  minimum box size.  Each cut splits the longest edge of the current box; a particle on a cut plane
  belongs to the upper side (on the upper face of the box, to the box below), so ownership is a
  property of the boxes (:meth:`Decomposition.locate`).
* :func:`halo`: the ghosts of each rank.  A particle goes to a rank when it lies within its own reach
  (cutoff + skin) of that rank's box, tested against every box, not only neighbouring ones (balanced
  cuts may be thinner than the largest cutoff); along periodic axes against the box shifted by whole
  periods.  Under the min rule ``|x_p - x_q| <= min(rc_p, rc_q) + skin`` this is exact: every
  neighbour of an owned particle reaches the owner's box, so a rank's lists over its own particles and
  its ghosts hold the serial rows of its own particles.  The test is evaluated with the list builders'
  arithmetic (squared gaps summed axis by axis), so ties at the cutoff are decided the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validate import as_cutoffs, as_positions
from .domain import Domain

__all__ = ["Decomposition", "bisect", "halo"]


@dataclass(frozen=True)
class Decomposition:
    """Boxes of the ranks: rank r owns the points with ``lo[r] <= x < hi[r]`` along every axis (``<=``
    at the upper face of the decomposed box; where boxes share that face, the first rank).

    Attributes
    ----------
    lo, hi : array (P, d)
        The boxes' lower and upper corners; together they tile ``[lo.min(0), hi.max(0)]``.
    """

    lo: np.ndarray
    hi: np.ndarray

    @property
    def parts(self) -> int:
        """The number of ranks P."""
        return int(self.lo.shape[0])

    def locate(self, x: np.ndarray) -> np.ndarray:
        """The rank owning each point, int64 (n,); -1 outside the decomposed box."""
        xs = as_positions(x)
        top = self.hi.max(axis=0)
        out = np.full(xs.shape[0], -1, np.int64)
        for r in range(self.parts):
            upper = (xs < self.hi[r]) | ((self.hi[r] == top) & (xs <= top))
            inside = np.all((xs >= self.lo[r]) & upper, axis=1) & (out < 0)
            out[inside] = r
        return out


def bisect(x: np.ndarray, parts: int, *, weights: np.ndarray | None = None,
           keys: np.ndarray | None = None, domain: Domain | None = None) -> tuple[Decomposition, np.ndarray]:
    """Recursive coordinate bisection of particles into ``parts`` boxes of about equal weight.

    Parameters
    ----------
    x : array (n, d)
        Positions.
    parts : int
        The number of ranks P >= 1 (any integer; a box of p ranks is cut into p // 2 and p - p // 2,
        with the weight split in that proportion).
    weights : array (n,), optional
        Cost per particle (default: 1, balancing by count).
    keys : int array (n,), optional
        Global keys: among particles at the same coordinate the order of the cut (default: the index).
    domain : Domain, optional
        The box to decompose (default: the particles' bounding box).

    Returns
    -------
    (Decomposition, array (n,))
        The boxes and the owner of each particle (the same as ``Decomposition.locate(x)``).
    """
    xs = as_positions(x)
    n, d = xs.shape
    if int(parts) != parts or parts < 1:
        raise ValueError(f"parts must be an integer >= 1, got {parts!r}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"weights must be finite and >= 0 with shape ({n},)")
    k = np.arange(n, dtype=np.int64) if keys is None else np.asarray(keys, dtype=np.int64)
    if k.shape != (n,):
        raise ValueError(f"keys must have shape ({n},)")
    if domain is not None and domain.for_dim(d).bounded:
        dom = domain.for_dim(d)
        assert dom.lo is not None and dom.hi is not None
        lo0, hi0 = dom.lo.astype(np.float64), dom.hi.astype(np.float64)
    else:
        lo0 = xs.min(axis=0) if n else np.zeros(d)
        hi0 = xs.max(axis=0) if n else np.zeros(d)
    box_lo, box_hi = np.zeros((parts, d)), np.zeros((parts, d))
    owner = np.zeros(n, np.int64)

    def split(idx: np.ndarray, lo: np.ndarray, hi: np.ndarray, p: int, first: int) -> None:
        if p == 1:
            box_lo[first], box_hi[first] = lo, hi
            owner[idx] = first
            return
        axis = int(np.argmax(hi - lo))
        order = idx[np.lexsort((k[idx], xs[idx, axis]))]
        left_parts = p // 2
        cum = np.cumsum(w[order])
        s = int(np.searchsorted(cum, cum[-1] * left_parts / p)) if order.size else 0
        s = min(s + 1, order.size)                              # the left side takes the particle reaching its share
        cut = xs[order[s], axis] if s < order.size else hi[axis]
        if cut >= hi[axis]:                                     # the upper face belongs to the box below it
            s, cut = order.size, hi[axis]
        else:
            s = int(np.searchsorted(xs[order, axis], cut))      # every particle on the cut plane goes up
        cut = min(max(cut, lo[axis]), hi[axis])
        left_hi, right_lo = hi.copy(), lo.copy()
        left_hi[axis], right_lo[axis] = cut, cut
        split(order[:s], lo, left_hi, left_parts, first)
        split(order[s:], right_lo, hi, p - left_parts, first + left_parts)

    split(np.arange(n, dtype=np.int64), lo0.copy(), hi0.copy(), int(parts), 0)
    return Decomposition(box_lo, box_hi), owner


def _gap2(y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Squared distance from points y (m, d) to the box [lo, hi], summed axis by axis from 0 (the
    list builders' order)."""
    g2 = np.zeros(y.shape[0])
    for i in range(y.shape[1]):
        g = np.maximum(np.maximum(lo[i] - y[:, i], y[:, i] - hi[i]), 0.0)
        g2 = g2 + g * g
    return g2


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
        The boxes and the owners (from :func:`bisect`).
    skin : float
        Verlet skin added to every cutoff.
    domain : Domain, optional
        Periodic axes add the images shifted by whole periods (cutoffs + skin must stay below half
        of each period, as for the serial lists).

    Returns
    -------
    list of (array (g,), array (g, d)), one per rank
        The ghosts' particle indices and the shifts to add to their positions (0 but along periodic
        axes), ordered by (shift, index).
    """
    xs = as_positions(x)
    n, d = xs.shape
    reach = as_cutoffs(rc, n) + float(skin)
    own = np.asarray(owner, dtype=np.int64)
    shifts = [np.zeros(d)]
    if domain is not None and domain.for_dim(d).any_periodic:
        period = domain.for_dim(d).period
        axes = [(-1, 0, 1) if period[i] > 0 else (0,) for i in range(d)]
        grid = np.array(np.meshgrid(*axes, indexing="ij")).reshape(d, -1).T
        shifts = [g * period for g in grid if np.any(g != 0)]
        shifts.insert(0, np.zeros(d))
    out = []
    r2 = reach * reach
    for r in range(dec.parts):
        idx, sh = [], []
        for s in shifts:
            y = xs + s if np.any(s != 0) else xs
            near = _gap2(y, dec.lo[r], dec.hi[r]) <= r2
            if not np.any(s != 0):
                near &= own != r
            q = np.flatnonzero(near)
            idx.append(q)
            sh.append(np.broadcast_to(s, (q.size, d)))
        out.append((np.concatenate(idx), np.concatenate(sh)))
    return out
