"""Domain decomposition for distributed runs: recursive coordinate bisection and ghost layers of
per-particle width.

The pieces of an SPMD run (one process per rank, particles exchanged between ranks): which rank owns
each particle, which particles a rank needs besides its own, and the exchanges that move them.  The
exchanges go through a :class:`Comm`: :class:`SerialComm` (one process: the serial path is the
parallel path with P = 1), :class:`MPIComm` (mpi4py, one process per rank) or :class:`ThreadComm`
(ranks as threads of one process, :func:`run_threads`, to check the exchanges in one process).

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
* :func:`migrate`: particles to the ranks whose boxes hold them after a move, with their fields.
* :func:`exchange_ghosts`: every rank's ghosts from every rank, in key order, with value refreshes.
* :class:`DistributedDCPSE` and :class:`Laplacian`: DC-PSE operators of fixed particles over owned
  particles and ghosts, rows in key order, failed stencils repaired over wider balls fetched from the
  other ranks: bitwise the same for every rank count, and the one-process operator's.
* :func:`exact_sum`: a global sum of doubles computed exactly and rounded once (mass, error norms):
  the same bits for every rank count and every spread of the terms.
* :func:`gather` and :func:`write_pvtu`: output, every rank's particles on every rank in key order
  (small runs), or one ``.vtu`` piece per rank and a ``.pvtu`` naming them (large runs).
* :func:`scatter` (the same set on every rank -> each rank's share) and :func:`h_min`: what
  :class:`arpy.Simulation` takes with ``comm=`` (time steps of particles that move but are not
  re-organized: operators at each stage's positions, migration after each step).
"""

from __future__ import annotations

import inspect
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np
import scipy.sparse as sp

from . import _core
from ._errors import raise_for_info
from ._validate import as_cutoffs, as_positions, column_extremes
from .boundary import Conditions
from .domain import Domain, h_min as one_process_h_min, nearest
from .neighbors import NeighborList, cache_order, neighbor_list
from .organize import Adapted, Confinement, Near, ParticleSet, Whole, adapt, int_seed, site_conflicts
from .organize import self_organize as one_process
from .resolution import SampledResolution

__all__ = ["Comm", "Decomposition", "DistributedDCPSE", "GhostLayer", "Laplacian", "MPIComm", "RankResolution",
           "SerialComm", "ThreadComm", "bisect", "exchange_ghosts", "exact_sum", "field_resolution", "gather",
           "graded_on_ranks", "h_min", "halo", "key_ordered", "launched_comm", "migrate", "organize_set", "organized",
           "run_threads", "scatter", "self_organize", "write_pvtu"]


class Comm(Protocol):
    """What the distributed functions need of a communicator (an mpi4py communicator wrapped, one
    process alone, or threads standing for ranks).  Collectives: every rank calls them in the same
    order.  Sums are of integers (exact, so independent of the rank count)."""

    rank: int
    size: int

    def allgather(self, value: Any) -> list[Any]: ...

    def alltoall(self, values: Sequence[Any]) -> list[Any]: ...

    def sum(self, value: int) -> int: ...

    def min(self, value: np.ndarray) -> np.ndarray: ...

    def max(self, value: np.ndarray) -> np.ndarray: ...


class _Collectives:
    """sum/min/max from allgather (in rank order; exact for integers, minima and maxima)."""

    size: int

    def allgather(self, value: Any) -> list[Any]:
        raise NotImplementedError

    def _per_rank(self, values: Sequence[Any]) -> list[Any]:
        """The values of an alltoall, checked: one per rank."""
        if len(values) != self.size:
            raise ValueError(f"alltoall needs one value per rank ({self.size}), got {len(values)}")
        return list(values)

    def sum(self, value: int) -> int:
        return int(sum(int(v) for v in self.allgather(int(value))))

    def min(self, value: np.ndarray) -> np.ndarray:
        return np.minimum.reduce([np.asarray(v, dtype=np.float64) for v in self.allgather(value)])

    def max(self, value: np.ndarray) -> np.ndarray:
        return np.maximum.reduce([np.asarray(v, dtype=np.float64) for v in self.allgather(value)])


class SerialComm(_Collectives):
    """One process alone: every collective is the identity, so serial runs take the parallel path
    with P = 1."""

    rank, size = 0, 1

    def allgather(self, value: Any) -> list[Any]:
        return [value]

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return self._per_rank(values)


class MPIComm(_Collectives):
    """An mpi4py communicator (default ``MPI.COMM_WORLD``; the ``mpi`` extra), one process per rank:
    ``mpiexec -n P python script.py``."""

    def __init__(self, comm: Any = None) -> None:
        if comm is None:
            from mpi4py import MPI

            comm = MPI.COMM_WORLD
        self._comm, self.rank, self.size = comm, int(comm.Get_rank()), int(comm.Get_size())

    def allgather(self, value: Any) -> list[Any]:
        return list(self._comm.allgather(value))

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return list(self._comm.alltoall(self._per_rank(values)))


#: Environment variables an MPI launcher sets in the processes it starts (Open MPI; MPICH's Hydra and
#: Intel MPI; PMIx launchers).
LAUNCHER_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK")


def launched_comm() -> MPIComm | None:
    """``MPIComm()`` (MPI.COMM_WORLD) when this process was started by an MPI launcher (``mpiexec``,
    ``mpirun``: one of :data:`LAUNCHER_VARIABLES` is set), else None."""
    if not any(v in os.environ for v in LAUNCHER_VARIABLES):
        return None
    try:
        import mpi4py  # noqa: F401
    except ImportError as exc:
        raise RuntimeError("this process was started by mpiexec, but mpi4py is missing: "
                           "pip install 'arpy-particles[mpi]'") from exc
    return MPIComm()


class _Group:
    def __init__(self, size: int, timeout: float) -> None:
        self.size = size
        self.barrier = threading.Barrier(size, timeout=timeout)
        self.slots: list[Any] = [None] * size


class ThreadComm(_Collectives):
    """Ranks as threads of one process (:func:`run_threads`): the exchanges of a distributed run,
    checked without MPI.  The core releases the GIL, so the ranks also compute at once."""

    def __init__(self, group: _Group, rank: int) -> None:
        self._group, self.rank, self.size = group, rank, group.size

    def allgather(self, value: Any) -> list[Any]:
        g = self._group
        g.slots[self.rank] = value
        g.barrier.wait()
        out = list(g.slots)
        g.barrier.wait()
        return out

    def alltoall(self, values: Sequence[Any]) -> list[Any]:
        return [row[self.rank] for row in self.allgather(self._per_rank(values))]


def run_threads(size: int, fn: Callable[[ThreadComm], Any], timeout: float = 120.0) -> list[Any]:
    """Run ``fn(comm)`` on ``size`` ranks, one thread each; returns their results in rank order.  An
    error on any rank breaks every rank's waiting collective and is raised here (no deadlock)."""
    group = _Group(int(size), timeout)
    results: list[Any] = [None] * size
    errors: list[BaseException] = []

    def target(rank: int) -> None:
        try:
            results[rank] = fn(ThreadComm(group, rank))
        except BaseException as exc:              # (a rank's failure ends the others' collectives)
            errors.append(exc)
            group.barrier.abort()

    threads = [threading.Thread(target=target, args=(r,)) for r in range(size)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        first = next((e for e in errors if not isinstance(e, threading.BrokenBarrierError)), errors[0])
        raise first
    return results


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
        out to -+infinity along the ``open`` axes.  (lo, hi), each (d,)."""
        lo, hi = self.lo[r], self.hi[r]
        if self.open is None:
            return lo, hi
        return (np.where(self.open & (lo == self.lo.min(axis=0)), -np.inf, lo),
                np.where(self.open & (hi == self.hi.max(axis=0)), np.inf, hi))

    def locate(self, x: np.ndarray) -> np.ndarray:
        """The rank owning each point, int64 (n,); -1 outside the decomposed box (along an axis that is
        not ``open``)."""
        xs = as_positions(x)
        top = self.hi.max(axis=0)
        out = np.full(xs.shape[0], -1, np.int64)
        for r in range(self.parts):
            lo, hi = self.box(r)
            upper = (xs < hi) | ((hi == top) & (xs <= top))
            inside = np.all((xs >= lo) & upper, axis=1) & (out < 0)
            out[inside] = r
        return out


def _order_key(v: np.ndarray) -> np.ndarray:
    """Doubles as int64 in the same order (-0.0 before +0.0): for exact bisection over values."""
    b = np.ascontiguousarray(v, dtype=np.float64).view(np.int64)
    return np.where(b < 0, np.int64(-(2 ** 63)) - b - 1, b)


def _from_key(k: int) -> float:
    b = k if k >= 0 else -(2 ** 63) - k - 1
    return float(np.array([b], dtype=np.int64).view(np.float64)[0])


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
    if int(parts) != parts or parts < 1:
        raise ValueError(f"parts must be an integer >= 1, got {parts!r}")
    w = np.ones(n, np.int64) if weights is None else np.asarray(weights)
    if w.shape != (n,) or not np.issubdtype(w.dtype, np.integer) or np.any(w < 0):
        raise ValueError(f"weights must be non-negative integers with shape ({n},)")
    w = w.astype(np.int64)
    if domain is not None and domain.for_dim(d).bounded:
        dom = domain.for_dim(d)
        assert dom.lo is not None and dom.hi is not None
        lo0, hi0 = dom.lo.astype(np.float64), dom.hi.astype(np.float64)
    else:
        mins, maxs = _bounding_box(xs)
        lo0, hi0 = comm.min(mins), comm.max(maxs)
        lo0, hi0 = np.where(np.isfinite(lo0), lo0, 0.0), np.where(np.isfinite(hi0), hi0, 0.0)
    box_lo, box_hi = np.zeros((int(parts), d)), np.zeros((int(parts), d))
    owner = np.zeros(n, np.int64)

    def split(idx: np.ndarray, lo: np.ndarray, hi: np.ndarray, p: int, first: int) -> None:
        if p == 1:
            box_lo[first], box_hi[first] = lo, hi
            owner[idx] = first
            return
        axis = int(np.argmax(hi - lo))
        v, wi = xs[idx, axis], w[idx]
        target = comm.sum(int(wi.sum())) * (p // 2)           # the lower share, times p (integers)
        keys = _order_key(v)
        a, b = int(_order_key(np.array([lo[axis]]))[0]), int(_order_key(np.array([hi[axis]]))[0])
        while a < b:                                          # the least key with p * W(x <= key) >= target
            mid = a + (b - a) // 2
            if comm.sum(int(wi[keys <= mid].sum())) * p >= target:
                b = mid
            else:
                a = mid + 1
        v0 = _from_key(a)
        above = v[v > v0]
        cut = float(comm.min(np.array([above.min() if above.size else np.inf]))[0])
        if not np.isfinite(cut):
            cut = hi[axis]
            low = np.ones(idx.size, bool)
        else:
            low = v < cut
        left_hi, right_lo = hi.copy(), lo.copy()
        left_hi[axis], right_lo[axis] = cut, cut
        split(idx[low], lo, left_hi, p // 2, first)
        split(idx[~low], right_lo, hi, p - p // 2, first + p // 2)

    split(np.arange(n, dtype=np.int64), lo0.copy(), hi0.copy(), int(parts), 0)
    flags = domain.for_dim(d).periodic if domain is not None else ()
    periodic = np.asarray(flags, bool) if len(flags) else np.zeros(d, bool)
    return Decomposition(box_lo, box_hi, ~periodic), owner


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
    images = [(np.zeros(d), xs)]                               # (shift, shifted positions), unshifted first
    if domain is not None and domain.for_dim(d).any_periodic:
        period = domain.for_dim(d).period
        images += [(g * period, xs + g * period) for g in domain.for_dim(d).image_shifts()]
    out = []
    r2 = reach * reach
    for r in range(dec.parts):
        idx, sh = [], []
        for i, (s, y) in enumerate(images):
            near = _gap2(y, *dec.box(r)) <= r2
            if i == 0:
                near &= own != r                               # a rank's own particles are no ghosts there
            q = np.flatnonzero(near)
            idx.append(q)
            sh.append(np.broadcast_to(s, (q.size, d)))
        out.append((np.concatenate(idx), np.concatenate(sh)))
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
    sends = []
    for r in range(comm.size):
        sel = dest == r
        sends.append((xs[sel], k[sel], {f: v[sel] for f, v in fields.items()}))
    got = comm.alltoall(sends)
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
    order : int array (g,)
        The received ghosts, concatenated by source rank, put into the layer's order.
    """

    x: np.ndarray
    rc: np.ndarray
    keys: np.ndarray
    shift: np.ndarray
    sends: list[np.ndarray]
    order: np.ndarray

    def refresh(self, comm: Comm, values: np.ndarray) -> np.ndarray:
        """The ghosts' values of a field given on this rank's own particles (one ``alltoall``; the
        ghosts of the same particle, images included, get its value)."""
        got = comm.alltoall([np.asarray(values)[g] for g in self.sends])
        return np.concatenate(got)[self.order]


def exchange_ghosts(comm: Comm, dec: Decomposition, x: np.ndarray, rc: float | np.ndarray, keys: np.ndarray, *,
                    skin: float = 0.0, domain: Domain | None = None) -> GhostLayer:
    """The ghosts of this rank from every rank (:func:`halo` on each rank's own particles, sent with
    ``alltoall``), in the order (shift, key), which does not depend on the rank count; their
    fields follow with :meth:`GhostLayer.refresh`."""
    xs = as_positions(x)
    rcs = as_cutoffs(rc, xs.shape[0])
    sends = halo(xs, rcs, dec, np.full(xs.shape[0], comm.rank, np.int64), skin=skin, domain=domain)
    return _send_ghosts(comm, xs, rcs, keys, sends, domain)


def _send_ghosts(comm: Comm, x: np.ndarray, rc: np.ndarray, keys: np.ndarray,
                 sends: list[tuple[np.ndarray, np.ndarray]], domain: Domain | None) -> GhostLayer:
    """The layer made by sending each rank r the own particles ``sends[r]`` (indices, shifts)."""
    xg, rg, kg, sg, order = _fetch(comm, x, rc, keys, sends, domain)
    return GhostLayer(xg, rg, kg, sg, [g for g, _ in sends], order)


def _image_shifts(x: np.ndarray, reach: np.ndarray, dom: Domain) -> tuple[np.ndarray, np.ndarray]:
    """The particles and the shifts (whole periods) of their periodic images by the serial rule
    (:meth:`arpy.Domain.images`): imaged by s in {-1, 0, 1}^d when within ``reach`` of the low face
    along every +1 axis and of the high face along every -1 axis.  Returns (indices, shifts (m, d))."""
    n, d = x.shape
    period = dom.period
    assert dom.lo is not None and dom.hi is not None
    near_lo, near_hi = (x - dom.lo) <= reach[:, None], (dom.hi - x) <= reach[:, None]
    idx, sh = [], []
    for g in dom.image_shifts():
        ok = np.all(np.where(g > 0, near_lo, True) & np.where(g < 0, near_hi, True), axis=1)
        q = np.flatnonzero(ok)
        idx.append(q)
        sh.append(np.broadcast_to(g * period, (q.size, d)))
    if not idx:
        return np.zeros(0, np.int64), np.zeros((0, d))
    return np.concatenate(idx), np.concatenate(sh)


#: Relative margin of the particles sent for a stencil repair (a superset: the gather decides).
_ASK_MARGIN = 2.0 ** -30


def _repair_sends(comm: Comm, x: np.ndarray, rc: np.ndarray, points: np.ndarray, radius: np.ndarray,
                  dom: Domain, skin: float, sends: list[tuple[np.ndarray, np.ndarray]]
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``sends`` and, for each rank, this rank's particles and periodic images (serial rule, reach
    rc + skin) within ``radius`` of the points that rank asks about (its stencils to repair): a
    receiver-side request, each (index, shift) sent once."""
    from .arcells import cross_neighbor_list

    n, d = x.shape
    img, shift = _image_shifts(x, rc + skin, dom) if dom.any_periodic else (np.zeros(0, np.int64), np.zeros((0, d)))
    cand = np.concatenate([np.arange(n), img])
    cshift = np.concatenate([np.zeros((n, d)), shift])
    cpos = x[cand] + cshift
    out = []
    for r, (pts, rad) in enumerate(comm.allgather((points, radius))):
        idx, sh = sends[r]
        if len(pts) and len(cand):
            wide = np.asarray(rad) * (1 + _ASK_MARGIN)
            hit = np.unique(cross_neighbor_list(pts, wide, cpos, np.full(len(cand), wide.max())).indices)
            if r == comm.rank:
                hit = hit[hit >= n]                            # (own particles are no ghosts of their rank)
            both = np.unique(np.column_stack([np.concatenate([idx, cand[hit]]),
                                              np.concatenate([sh, cshift[hit]])]), axis=0)
            idx, sh = both[:, 0].astype(np.int64), both[:, 1:]
        out.append((idx, sh))
    return out


def scatter(comm: Comm, x: np.ndarray, fields: dict[str, np.ndarray] | None = None, *,
            domain: Domain | None = None) -> tuple[Decomposition, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The same particle set on every rank -> each rank's share: keys are the indices into ``x``; the
    ranks take every P-th particle, bisect (:func:`bisect`) and migrate (:func:`migrate`).  Returns
    (decomposition, this rank's x, keys and fields, in key order)."""
    xs = as_positions(x)
    mine = np.arange(comm.rank, xs.shape[0], comm.size)
    dec, _ = bisect(xs[mine], comm.size, domain=domain, comm=comm)
    xo, ko, fo = migrate(comm, dec, xs[mine], mine.astype(np.int64), {k: np.asarray(v)[mine]
                                                                      for k, v in (fields or {}).items()})
    return dec, xo, ko, fo


def h_min(comm: Comm, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray,
          domain: Domain | None = None) -> float:
    """The smallest distance between two particles of all ranks (minimum image along periodic axes),
    the same for every rank count: the nearest of each own particle among own particles and ghosts
    (reach eps); exact when that minimum is at most the smallest core size (the closest pair then
    lies within each other's reach), else from the whole set gathered.  Collective."""
    xs = as_positions(x)
    layer = exchange_ghosts(comm, dec, xs, eps, keys, domain=domain)
    ext = np.concatenate([xs, layer.x])
    local = nearest(ext, xs, 2)[0][:, 1].min() if xs.shape[0] and ext.shape[0] > 1 else np.inf
    h = float(comm.min(np.array([local]))[0])
    if h <= float(comm.min(np.array([np.min(eps, initial=np.inf)]))[0]):
        return h
    return one_process_h_min(gather(comm, keys, xs)[1], domain)


def key_ordered(nl: NeighborList, keys: np.ndarray) -> NeighborList:
    """The list with each row's entries in the order of their keys: the order of sums over a row
    then does not depend on how the particles are spread over ranks."""
    k = np.asarray(keys, dtype=np.int64)
    rank = np.empty(k.size, np.int64)
    rank[np.argsort(k, kind="stable")] = np.arange(k.size)
    return nl.ordered_by(rank)


class DistributedDCPSE:
    """DC-PSE operators at this rank's own particles over its own particles and ghosts (particles
    fixed while it is used): :class:`arpy.DomainDCPSE` with the ghosts from the other ranks as
    sources and each row's sources in the order one process sums them over the whole set numbered by
    key (``DomainDCPSE(keys=)``), so every operator gives bitwise the same values for every rank
    count, and those of the one-process operator (without ``keys`` when the keys are the indices).

    Stencils are repaired as in a simulation (:data:`arpy.stencils.REPAIR`): a row whose moment
    conditions fail is rebuilt over every source within a wider ball, up to ``1.5**widen`` times its
    core size, which may reach beyond the ghost layer; the rank then asks the others for their
    particles (and periodic images) within that ball of the row's particle, and they send them as
    extra ghosts (a receiver-side request, made only when some rank has a failed row).

    The methods are those of :class:`arpy.DomainDCPSE` (so :class:`arpy.operators.Operators` takes
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
        Repair rounds of failed rows, and the Lebesgue constant above which a row off the particles is
        rebuilt (defaults: :data:`arpy.stencils.REPAIR`'s).
    strict : bool
        Raise ValueError if a row still has no valid stencil; False: its row is zero.
    operators : sequence, optional
        The operators assembled with the stencils (see :class:`arpy.DCPSE`); default: the Laplacian
        at the particles, the interpolating kernel off them.
    reorder : bool
        Work on the particles in cache order (:func:`arpy.cache_order`; the matrices' rows are put
        back in the order given, which costs a copy of each); False: the particles are in cache
        order already, or should be taken as given.

    Attributes
    ----------
    failed : int array
        Rows (this rank's particles, or collocation points) without a valid stencil after the repair.
    repaired : int64 array
        Keys of this rank's particles (collocation points: their indices) whose rows were rebuilt.
    """

    def __init__(self, comm: Comm, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray,
                 col_x: np.ndarray | None = None, col_eps: float | np.ndarray | None = None, *,
                 domain: Domain, order: int = 4, skin: float = 0.0, widen: int | None = None,
                 max_lebesgue: float | None = None, strict: bool = True,
                 operators: Sequence[object] | None = None, reorder: bool = True) -> None:
        from .stencils import MILD_LEBESGUE, REPAIR, DomainDCPSE, lebesgue_constants

        xs = as_positions(x)
        n, d = xs.shape
        if domain is None or not domain.for_dim(d).bounded:
            raise ValueError("distributed DC-PSE needs a box (a Domain with walls or periodic axes)")
        dom = domain.for_dim(d)
        widen = REPAIR["widen"] if widen is None else int(widen)
        max_lebesgue = REPAIR["max_lebesgue"] if max_lebesgue is None else max_lebesgue
        self.comm, self.n = comm, n
        # the own particles in cache order (they arrive in key order, which is no order in memory);
        # rows and sums go by key, so every operator is bitwise that of any other order
        self._order = cache_order(xs, domain=domain) if reorder else np.arange(n)
        self._back: np.ndarray | None = np.argsort(self._order) if col_x is None and reorder else None
        xo, eo = xs[self._order], as_cutoffs(eps, n)[self._order]
        ko = np.asarray(keys, dtype=np.int64)[self._order]
        cx = xo if col_x is None else as_positions(col_x)
        if cx.shape[1] != d:
            raise ValueError(f"collocation points must have d = {d} columns, got {cx.shape}")
        if col_x is None:
            ce = eo
        elif col_eps is None:                # the core size of the nearest particle of any rank
            ce = _nearest_values(comm, xo, ko, eo, dom, cx, 1)[:, 0]
        else:
            ce = as_cutoffs(col_eps, cx.shape[0])
        sends = halo(xo, eo, dec, np.full(n, comm.rank, np.int64), skin=skin, domain=domain)
        self.ghosts = _send_ghosts(comm, xo, eo, ko, sends, dom)
        wanted = (["laplacian"] if col_x is None else ["interpolation"]) if operators is None else list(operators)

        def build(w: int, lebesgue: float | None) -> DomainDCPSE:
            return DomainDCPSE(xo, eo, None if col_x is None else cx, None if col_x is None else ce, domain=dom,
                               order=order, strict=False, widen=w, max_lebesgue=lebesgue, operators=wanted,
                               ghosts=(self.ghosts.x, self.ghosts.rc, self.ghosts.shift),
                               keys=np.concatenate([ko, self.ghosts.keys]))

        # a first build without repair shows the rows a repair will rebuild, and over how wide a ball:
        # failed rows up to 1.5^widen times their core size (off the particles one round more, a
        # widened row may still be wild), rows whose Lebesgue constant is above MILD_LEBESGUE 1.5 times
        op = build(0, None)
        rows, radius = op.failed, ce[op.failed] * 1.5 ** (widen + (col_x is not None))
        if col_x is not None and max_lebesgue is not None:
            wild = np.setdiff1d(np.flatnonzero(lebesgue_constants(op) > min(MILD_LEBESGUE, max_lebesgue)), rows)
            rows, radius = np.concatenate([rows, wild]), np.concatenate([radius, 1.5 * ce[wild]])
        if comm.sum(rows.size):
            wider = _repair_sends(comm, xo, eo, cx[rows], radius, dom, skin, sends)
            self.ghosts = _send_ghosts(comm, xo, eo, ko, wider, dom)
            if rows.size:                  # (a rank without such rows received no more ghosts)
                op = build(widen, max_lebesgue)
        self._rank_of = rank_of = self._order if col_x is None else np.arange(cx.shape[0])
        self.failed = np.sort(rank_of[op.failed])
        self.repaired = np.sort(ko[op.widened]) if col_x is None else np.sort(op.widened)
        if strict and self.failed.size:
            where = f"the particle of key {ko[op.failed[0]]}" if col_x is None else f"point {op.failed[0]}"
            raise ValueError(f"no valid DC-PSE stencil at {where}")
        self._op = op
        self._x, self._keys, self._domain, self._cx = xo, ko, dom, cx

    def _rows(self, mat: sp.csr_matrix) -> sp.csr_matrix:
        return mat if self._back is None else mat[self._back]

    @property
    def unrepaired(self) -> np.ndarray:
        """Rows (this rank's particles, or collocation points) without a valid stencil of their own,
        before any repair (:attr:`arpy.DomainDCPSE.unrepaired`)."""
        return np.sort(self._rank_of[self._op.unrepaired])

    @property
    def sources(self) -> np.ndarray:
        """Positions of the sources: own particles (in cache order), ghosts, mirror images."""
        return self._op.sources

    def extend(self, f: np.ndarray, bc: Conditions | None = None, t: float = 0.0) -> np.ndarray:
        """Values on this rank's particles (n,) -> values on the sources (the ghosts' from their
        ranks; mirror images by ``bc``, see :meth:`arpy.DomainDCPSE.extend`).  Collective."""
        fo = np.asarray(f, dtype=np.float64)[self._order]
        return self._op.extend(np.concatenate([fo, self.ghosts.refresh(self.comm, fo)]), bc, t)

    def laplacian(self) -> sp.csr_matrix:
        """The Laplacian, (n, n_sources), unit 1 / length^2."""
        return self._rows(self._op.laplacian())

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
        fo = np.asarray(f, dtype=np.float64)[self._order]
        ext = np.concatenate([fo, self.ghosts.refresh(comm, fo)])
        median, rows = None, op.failed
        if bounded:
            median = _global_median(comm, np.diff(op.interpolation().indptr))
            rows = np.union1d(rows, op.clipped_rows(median))
        k = 2 * op.d if bounded else 1
        values = _nearest_values(comm, self._x, self._keys, fo, self._domain, self._cx[rows], k)
        table = dict(zip(rows.tolist(), values))

        def near(at: np.ndarray, kk: int) -> np.ndarray:
            return np.array([table[int(r)][:kk] for r in at]).reshape(len(at), kk)

        out = op.interpolate(ext, bounded, bc, t, near=near, median=median)
        return out if self._back is None else out[self._back]


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
        out = np.empty(self.n)
        out[self._order] = self.matrix @ self.extend(f)
        return out


def _global_median(comm: Comm, counts: np.ndarray) -> float:
    """np.median of non-negative integers spread over the ranks (exact: from their histogram)."""
    hist = [np.asarray(h) for h in comm.allgather(np.bincount(np.asarray(counts, np.int64)))]
    total = np.zeros(max((h.size for h in hist), default=0), np.int64)
    for h in hist:
        total[:h.size] += h
    n = int(total.sum())
    if n == 0:
        return float("nan")
    cum = np.cumsum(total)
    lo, hi = int(np.searchsorted(cum, (n - 1) // 2 + 1)), int(np.searchsorted(cum, n // 2 + 1))
    return (lo + hi) / 2


def _nearest_values(comm: Comm, x: np.ndarray, keys: np.ndarray, f: np.ndarray, domain: Domain,
                    points: np.ndarray, k: int) -> np.ndarray:
    """The values (m, k) of the k particles of every rank nearest each of this rank's ``points``, by
    (distance, key), distances by the minimum image (a receiver-side k-nearest request; each rank
    answers with its own k + 2 nearest).  Collective."""
    d = x.shape[1]
    answers = []
    for pts in comm.allgather(np.asarray(points, dtype=np.float64).reshape(-1, d)):
        m = min(k + 2, x.shape[0])
        if len(pts) and m:
            dist, j = nearest(x, pts, m, domain=domain)
            dist, j = dist.reshape(len(pts), m), j.reshape(len(pts), m)
            answers.append((dist, keys[j], f[j]))
        else:
            answers.append((np.zeros((len(pts), 0)), np.zeros((len(pts), 0), np.int64), np.zeros((len(pts), 0))))
    got = comm.alltoall(answers)
    if len(points) == 0:
        return np.zeros((0, k))
    dist, key, val = (np.concatenate([g[i] for g in got], axis=1) for i in range(3))
    pick = np.lexsort((key, dist), axis=1)[:, :k]
    return np.take_along_axis(val, pick, axis=1)


#: Terms per block of the exact sum: 512 integer mantissas (< 2^53) add up below 2^62 in int64.
_SUM_BLOCK = 512


def exact_sum(comm: Comm, values: np.ndarray) -> float:
    """The sum over all ranks of ``values`` (finite doubles), exact and rounded once to the nearest
    double: each term is an integer mantissa times a power of two, the mantissas are added exactly
    (as integers, grouped by exponent) and the ranks' integer sums are added exactly too.  The result
    equals ``math.fsum`` of all the terms, whatever the rank count and the order of the terms."""
    from fractions import Fraction

    v = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if not np.all(np.isfinite(v)):
        raise ValueError("exact_sum needs finite values")
    m, e = np.frexp(v)
    mant = (m * 2.0 ** 53).astype(np.int64)                   # exact: |m| < 1
    expo = e.astype(np.int64) - 53
    low = int(comm.min(np.array([expo.min() if v.size else 0], dtype=np.float64))[0])
    total = 0
    for x in np.unique(expo):
        block = mant[expo == x]
        pad = (-block.size) % _SUM_BLOCK
        parts = np.concatenate([block, np.zeros(pad, np.int64)]).reshape(-1, _SUM_BLOCK).sum(axis=1)
        total += sum(int(p) for p in parts) << int(x - low)
    grand = sum(comm.allgather(total))
    return float(Fraction(grand) * Fraction(2) ** low)


def gather(comm: Comm, keys: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every rank's particles on every rank, in key order (output at small scale): (keys, then each
    array with its rows put in that order).  Collective; arrays have one row per key."""
    k = np.asarray(keys, dtype=np.int64)
    parts = comm.allgather((k, [np.asarray(a) for a in arrays]))
    all_keys = np.concatenate([p[0] for p in parts])
    order = np.argsort(all_keys, kind="stable")
    out = [np.concatenate([p[1][i] for p in parts])[order] for i in range(len(arrays))]
    return (all_keys[order], *out)


def write_pvtu(comm: Comm, path: str | Path, x: np.ndarray, **point_data: np.ndarray) -> Path:
    """Write the particles of every rank as one parallel VTK file (output at large scale): each rank
    writes its own piece ``<stem>/<stem>_<rank>.vtu`` (:func:`arpy.io.write_vtu`, with the array
    ``rank``), and rank 0 writes ``path`` (``.pvtu``) naming the pieces and their arrays, which
    ParaView and VisIt open as one data set.  Collective.

    Parameters
    ----------
    comm : Comm
    path : str or Path
        The ``.pvtu`` file.
    x : array (n, 2) or (n, 3)
        This rank's positions.
    **point_data : arrays (n,) or (n, k)
        This rank's particle quantities (the same names on every rank).

    Returns
    -------
    Path
        ``path``.
    """
    from xml.etree import ElementTree as ET

    from .io import write_vtu

    path = Path(path)
    x = np.asarray(x, dtype=np.float64)
    data = {**{k: np.asarray(v, dtype=np.float64) for k, v in point_data.items()},
            "rank": np.full(x.shape[0], float(comm.rank))}
    layout = sorted((k, 1 if v.ndim == 1 else int(v.shape[1])) for k, v in data.items())
    if any(other != layout for other in comm.allgather(layout)):
        raise ValueError("write_pvtu: every rank must give the same arrays with the same components")
    piece_dir = path.parent / path.stem
    if comm.rank == 0:
        piece_dir.mkdir(parents=True, exist_ok=True)
    comm.allgather(None)                                       # the directory exists before any piece
    write_vtu(piece_dir / f"{path.stem}_{comm.rank}.vtu", x, **data)
    comm.allgather(None)                                       # every piece is written
    if comm.rank == 0:
        root = ET.Element("VTKFile", type="PUnstructuredGrid", version="0.1", byte_order="LittleEndian")
        grid = ET.SubElement(root, "PUnstructuredGrid", GhostLevel="0")
        pdata = ET.SubElement(grid, "PPointData")
        for name, comps in layout:
            ET.SubElement(pdata, "PDataArray", type="Float64", Name=name, NumberOfComponents=str(comps))
        pts = ET.SubElement(grid, "PPoints")
        ET.SubElement(pts, "PDataArray", type="Float64", NumberOfComponents="3")
        for r in range(comm.size):
            ET.SubElement(grid, "Piece", Source=f"{path.stem}/{path.stem}_{r}.vtu")
        ET.ElementTree(root).write(path, xml_declaration=True, encoding="utf-8")
    comm.allgather(None)
    return path


def _gap_images(y: np.ndarray, lo: np.ndarray, hi: np.ndarray, period: np.ndarray) -> np.ndarray:
    """Distance from points y (m, d) to the box [lo, hi], over the periodic images along periodic axes."""
    g2 = np.zeros(y.shape[0])
    for i in range(y.shape[1]):
        shifts = (-period[i], 0.0, period[i]) if period[i] > 0 else (0.0,)
        g = np.min([np.maximum(np.maximum(lo[i] - (y[:, i] + s), (y[:, i] + s) - hi[i]), 0.0) for s in shifts], axis=0)
        g2 = g2 + g * g
    return np.sqrt(g2)


#: The self-organization bisects the domain anew when a rank's box holds more than this times the
#: mean particle count (insertion and fusion concentrate particles where the resolution is fine).
REBALANCE = 1.1


class RankView(Whole):
    """The self-organization's view of one rank's particles (:class:`arpy.organize.Whole` on one
    process): the particles within reach come from the other ranks by their own cutoffs (``near``) or
    by this rank's request (``around``), unshifted along periodic axes (the kernels take the minimum
    image, as on one process) and each once; sums are exact, fusion candidates and new insertion
    sites are gathered and decided the same way on every rank."""

    def __init__(self, conf: Confinement, comm: Comm, dec: Decomposition) -> None:
        super().__init__(conf)
        self.comm, self.dec = comm, dec
        self.lo, self.hi = dec.box(comm.rank)

    def _exchange(self, x: np.ndarray, keys: np.ndarray, picks: list[np.ndarray],
                  values: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
        """Own particles picks[r] to rank r; returns the own arrays followed by the received particles
        not owned here, each once, in key order: (x, keys, values...)."""
        got = self.comm.alltoall([(x[g], keys[g], [v[g] for v in values]) for g in picks])
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
        return [np.unique(idx) for idx, _ in out]

    def near(self, x: np.ndarray, D: np.ndarray, keys: np.ndarray, rc: np.ndarray, skin: float = 0.0) -> Near:
        n = x.shape[0]
        xe, ke, De, rce = self._exchange(x, keys, self._picks(x, rc + skin), [D, rc])
        full = neighbor_list(xe, rce, method="auto", symmetric=False, domain=self.conf.domain)
        off = np.concatenate([full.offsets[: n + 1], np.full(xe.shape[0] - n, full.offsets[n])])
        own_rows = NeighborList(off, full.indices[: full.offsets[n]], False)
        return Near(xe, De, ke, n, key_ordered(own_rows, ke))

    def around(self, x: np.ndarray, keys: np.ndarray, width: float | Callable[[], float],
               *values: np.ndarray) -> tuple[np.ndarray, ...]:
        widths = self.comm.allgather(float(width() if callable(width) else width))
        period = self.conf.domain.period
        picks = [np.zeros(0, np.int64) if r == self.comm.rank else
                 np.flatnonzero(_gap_images(x, *self.dec.box(r), period) <= w)
                 for r, w in enumerate(widths)]
        xe, _, *ve = self._exchange(x, keys, picks, list(values))
        return (xe, *ve)

    def fsum(self, values: np.ndarray) -> float:
        return exact_sum(self.comm, np.ravel(values))

    def gsum(self, value: int) -> int:
        return int(self.comm.sum(int(value)))

    def gmin(self, value: float) -> float:
        return float(self.comm.min(np.array([value], dtype=np.float64))[0])

    def gmax(self, value: float) -> float:
        return float(self.comm.max(np.array([value], dtype=np.float64))[0])

    def gap(self, points: np.ndarray) -> np.ndarray:
        return _gap_images(points, self.lo, self.hi, self.conf.domain.period)

    def gather(self, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
        parts = self.comm.allgather([np.asarray(a) for a in arrays])
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(len(arrays)))

    def sites(self, sites: np.ndarray, Ds: np.ndarray, parent_keys: np.ndarray) -> np.ndarray:
        parts = self.comm.allgather((sites, Ds, parent_keys))
        xs = np.concatenate([p[0] for p in parts]).reshape(-1, sites.shape[1])
        ds, pk = np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])
        order = np.argsort(pk, kind="stable")
        kept = np.empty(pk.size, bool)
        kept[order] = site_conflicts(xs[order], ds[order])
        start = sum(len(p[2]) for p in parts[: self.comm.rank])
        return kept[start: start + parent_keys.size]

    def new_keys(self, parent_keys: np.ndarray, next_key: int) -> tuple[np.ndarray, int]:
        everyone = np.sort(np.concatenate(self.comm.allgather(np.asarray(parent_keys, np.int64))))
        return next_key + np.searchsorted(everyone, parent_keys).astype(np.int64), next_key + everyone.size

    def migrate(self, x: np.ndarray, keys: np.ndarray, *values: np.ndarray) -> tuple[bool, tuple[np.ndarray, ...]]:
        """Migration to the owners; when the largest rank holds more than REBALANCE times the mean
        count, the boxes are bisected anew first (the result does not depend on the boxes)."""
        comm = self.comm
        dest = self.dec.locate(x)
        counts = comm.allgather(np.bincount(dest[dest >= 0], minlength=comm.size))
        totals = np.sum(counts, axis=0)
        if totals.max() > REBALANCE * totals.sum() / comm.size:
            self.dec, _ = bisect(x, comm.size, domain=self.conf.domain, comm=comm)
            self.lo, self.hi = self.dec.box(comm.rank)
        elif all(c[r] == c.sum() for r, c in enumerate(counts)):        # every rank keeps all of its own
            return False, (x, keys, *values)
        xm, km, f = migrate(comm, self.dec, x, keys, {str(i): v for i, v in enumerate(values)})
        return True, (xm, km, *(f[str(i)] for i in range(len(values))))


def self_organize(comm: Comm, dec: Decomposition, x: np.ndarray, keys: np.ndarray,
                  resolution: Callable[[np.ndarray], np.ndarray] | None = None, *, domain: Domain,
                  seed: int = 0, **options: Any) -> Adapted:
    """:func:`arpy.self_organize` over the ranks: each rank passes the particles its box owns (after
    :func:`migrate`) with their global keys; the result is each rank's particles of the adapted set
    (x, D, keys in key order), the decomposition that owns them (``decomposition``) and the global log.  The set, gathered by key, is bitwise the same for
    every rank count (and equals the one-process result when the keys are the input order).

    Parameters
    ----------
    comm, dec : Comm, Decomposition
        The ranks and their boxes (:func:`bisect`); particles migrate as they move, and the boxes
        are bisected anew when one holds more than :data:`REBALANCE` times the mean count.
    x, keys : arrays (n, d), (n,) int64
        This rank's particles and their keys (distinct over all ranks).
    resolution : callable, optional
        The target D~ (or give ``grad_f=`` and ``D0=`` in ``options``), as in :func:`arpy.self_organize`.
    domain : Domain
        A box (walls or periodic axes), or free space (then usually with a ``region`` in ``options``:
        the boxes of the ranks bisect the particles' bounding box and reach on beyond it).
    seed : int
        The insertion seed (an int, the same on every rank).
    **options
        The other keywords of :func:`arpy.self_organize` (D0, Dmin, grad_f, potential, d_c, order,
        n_star, reach, adapt_number, max_iter, tol, max_particles, progress).
    """
    if isinstance(resolution, SampledResolution):
        raise NotImplementedError("distributed self-organization of a SampledResolution (old particles on the ranks) "
                                  "is not available yet")
    seed = int_seed(seed, "an int >= 0, the same on every rank")
    xs, k = as_positions(x).copy(), np.asarray(keys, dtype=np.int64)
    order = np.argsort(k, kind="stable")
    # the keywords of the one-process self_organize, with its defaults
    kw: dict[str, Any] = {name: p.default for name, p in inspect.signature(one_process).parameters.items()
                          if p.kind is p.KEYWORD_ONLY and name not in ("domain", "seed")}
    unknown = set(options) - set(kw)
    if unknown:
        raise TypeError(f"unknown options {sorted(unknown)}")
    kw.update(options)
    kw["progress"] = bool(kw["progress"]) and comm.rank == 0
    views: list[RankView] = []

    def view(conf: Confinement) -> RankView:
        views.append(RankView(conf, comm, dec))
        return views[-1]

    out = adapt(xs[order], k[order], view, resolution=resolution, domain=domain, seed=seed, **kw)
    out.decomposition = views[0].dec
    return out


def organized(x: np.ndarray, resolution: Callable[[np.ndarray], np.ndarray] | None = None, *,
              comm: Comm | None = None, **options: Any) -> ParticleSet:
    """:func:`arpy.self_organize` of x, over the ranks of ``comm`` if given (:func:`organize_set`: the
    same particles on every rank, bitwise the one-process result)."""
    if comm is None:
        return one_process(x, resolution, **options)
    return organize_set(comm, x, resolution, **options)


def organize_set(comm: Comm, x: np.ndarray, resolution: Callable[[np.ndarray], np.ndarray] | None = None, *,
                 domain: Domain, seed: int = 0, **options: Any) -> ParticleSet:
    """:func:`arpy.self_organize` of the same particles ``x`` given on every rank, computed over the
    ranks (:func:`scatter`, :func:`self_organize`) and gathered on every rank: bitwise the
    one-process result.  Collective."""
    dec, xs, ks, _ = scatter(comm, x, domain=domain)
    out = self_organize(comm, dec, xs, ks, resolution, domain=domain, seed=seed, **options)
    _, xa, Da = gather(comm, out.keys, out.x, out.D)
    return ParticleSet(x=xa, D=Da, rstar=out.rstar, n_star=out.n_star, domain=out.domain, log=out.log,
                       converged=out.converged)


# ---------------------------------------------------------------- resolution of an old set on the ranks
def _fetch(comm: Comm, x: np.ndarray, values: np.ndarray, keys: np.ndarray, sends: list[tuple[np.ndarray, np.ndarray]],
           domain: Domain | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Send ``sends`` (indices, shifts) with their values and keys; returns what this rank received,
    (positions, values, keys, shift ids), in the order (shift id, key): the order in which a process
    holding every particle numbered by key lists them and their periodic images; and that order (the
    received arrays, concatenated by source rank, -> this order)."""
    k = np.asarray(keys, dtype=np.int64)
    dom = domain.for_dim(x.shape[1]) if domain is not None and domain.for_dim(x.shape[1]).bounded else None

    def ids(sh: np.ndarray) -> np.ndarray:
        return dom.image_ids(sh) if dom is not None else np.full(sh.shape[0], -1, np.int64)

    got = comm.alltoall([(x[g] + sh, values[g], k[g], ids(sh)) for g, sh in sends])
    xg = np.concatenate([g[0] for g in got]).reshape(-1, x.shape[1])
    vg, kg, sg = (np.concatenate([g[i] for g in got]) for i in (1, 2, 3))
    order = np.lexsort((kg, sg))
    return xg[order], vg[order], kg[order], sg[order], order


def graded_on_ranks(comm: Comm, x: np.ndarray, d_tilde: np.ndarray, keys: np.ndarray, rstar: float,
                    domain: Domain, reading: str = "implicit") -> np.ndarray:
    """:func:`arpy.resolution.graded_resolution` (Eq. 2.9) of the particles spread over the ranks: each
    rank asks the others for their particles (and periodic images) within r* times its largest D~ of
    its own particles' bounding box, then scans them as one process does
    (:func:`arpy.resolution.grade`).  Bitwise the one-process result.  Collective."""
    from .resolution import check_reading, grade

    check_reading(reading)
    xs, target = as_positions(x), np.asarray(d_tilde, dtype=np.float64)
    n, d = xs.shape
    if reading == "pointwise":
        return target.copy()
    dom = domain.for_dim(d)
    width = rstar * float(target.max(initial=0.0))
    lo, hi = _bounding_box(xs)
    sends = _box_sends(comm, xs, np.zeros(n), lo - width, hi + width, dom)
    xg, dg, _, _, _ = _fetch(comm, xs, target, np.asarray(keys, np.int64), sends, dom)
    if n == 0:
        return target.copy()
    return grade(xs, target, np.concatenate([xs, xg]), np.concatenate([target, dg]), rstar, reading)


def _bounding_box(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the points x (n, d); an empty box (lo = inf, hi = -inf) without points."""
    d = x.shape[1]
    return column_extremes(x) if x.shape[0] else (np.full(d, np.inf), np.full(d, -np.inf))


def _box_sends(comm: Comm, x: np.ndarray, reach: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               domain: Domain) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per rank, this rank's particles (and periodic images) within ``reach`` of the box [lo, hi] that
    rank asks about (:func:`halo` with the asked boxes; not this rank's own particles to itself)."""
    asks = comm.allgather((lo, hi))
    boxes = Decomposition(np.array([a[0] for a in asks]), np.array([a[1] for a in asks]))
    return halo(x, reach, boxes, np.full(x.shape[0], comm.rank, np.int64), domain=domain)


class RankResolution:
    """:class:`arpy.resolution.SampledResolution` of an old particle set spread over the ranks: D_p
    at any points, by the same Shepard interpolation, each rank asking the others for the old
    particles (and periodic images) whose reach r* D_q meets its points' bounding box; the sums run
    in the order of one process holding the whole old set numbered by key (old particles by key, then
    images by shift and key), so the values are bitwise the one-process ones.  A point no old particle
    reaches takes the D of the nearest (a k-nearest request).  Calls are collective (every rank calls
    it the same number of times, as :func:`self_organize` does).

    Parameters
    ----------
    comm : Comm
    x, D, keys : arrays (n, d), (n,), (n,)
        This rank's old particles, their D_p (graded) and keys.
    rstar : float
        Cutoff factor: old particle q reaches r* D_q.
    domain : Domain
        The box.
    """

    #: Its values are D_p already graded by Eq. 2.9 (:func:`self_organize` takes them as they are).
    graded = True

    def __init__(self, comm: Comm, x: np.ndarray, D: np.ndarray, keys: np.ndarray, rstar: float,
                 domain: Domain) -> None:
        self.comm, self.x = comm, as_positions(x)
        self.d = self.x.shape[1]
        self.D, self.keys = as_cutoffs(D, self.x.shape[0]), np.asarray(keys, dtype=np.int64)
        self.rstar, self.domain = float(rstar), domain.for_dim(self.d)
        self.degenerate = 0

    def __call__(self, y: np.ndarray) -> np.ndarray:
        ys = as_positions(y)
        n, m, d = self.x.shape[0], ys.shape[0], ys.shape[1]
        if d != self.d:
            raise ValueError(f"points must have d = {self.d} columns, got {ys.shape}")
        lo, hi = _bounding_box(ys)
        sends = _box_sends(self.comm, self.x, self.rstar * self.D, lo, hi, self.domain)
        own = sends[self.comm.rank]                             # own particles: to itself unshifted too
        sends[self.comm.rank] = (np.concatenate([np.arange(n), own[0]]), np.concatenate([np.zeros((n, d)), own[1]]))
        xl, Dl, _, _, _ = _fetch(self.comm, self.x, self.D, self.keys, sends, self.domain)
        out, ok = np.empty(m), np.zeros(m, bool)
        if m and xl.shape[0]:                  # (in the one-process order: SampledResolution's sums)
            out, ok = SampledResolution(xl, Dl, self.rstar).shepard(ys)
        out[~ok] = _nearest_values(self.comm, self.x, self.keys, self.D, self.domain, ys[~ok], 1)[:, 0]
        return out


def field_resolution(comm: Comm, dec: Decomposition, x: np.ndarray, f: np.ndarray, D: np.ndarray, keys: np.ndarray, *,
                     D0: float, Dmin: float | None = None, order: int = 4, domain: Domain, widen: int | None = None,
                     max_lebesgue: float | None = None, reach: float = 1.0, monitor: str = "gradient",
                     bc: Sequence[Conditions | None] | None = None, t: float = 0.0,
                     reading: str = "implicit") -> RankResolution:
    """:func:`arpy.field_resolution` of an old particle set spread over the ranks (each rank's own
    particles x (n, d) with their fields f (n,) or (n, k), D_p and keys): the monitor from
    :class:`DistributedDCPSE` derivatives, Eq. 2.9 by :func:`graded_on_ranks`, the result a
    :class:`RankResolution`, bitwise the one-process one.  ``degenerate``: the particles without a
    stencil, over all ranks.  Collective."""
    from .resolution import check_monitor, check_reach, monitor_target, n_star_for, r_star

    xs = as_positions(x)
    n, d = xs.shape
    fields = np.asarray(f, dtype=np.float64).reshape(n, -1)
    bcs = [None] * fields.shape[1] if bc is None else list(bc)
    check_reach(reach)
    check_monitor(monitor, order)
    dom = domain.for_dim(d)

    def build(eps: np.ndarray, m: int, operators: list, wild: bool) -> DistributedDCPSE:
        return DistributedDCPSE(comm, dec, xs, eps, keys, domain=dom, order=m, strict=False, widen=widen,
                                max_lebesgue=max_lebesgue if wild else None, operators=operators, reorder=False)

    op, target = monitor_target(build, fields, D, d=d, D0=D0, Dmin=Dmin, order=order, domain=dom, monitor=monitor,
                                bcs=bcs, t=t)
    rs = r_star(d, n_star_for(order, d))
    field = RankResolution(comm, xs, graded_on_ranks(comm, xs, target, keys, reach * rs, dom, reading), keys, rs, dom)
    field.degenerate = comm.sum(int(op.failed.size))
    return field
