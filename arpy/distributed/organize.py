"""Self-organization over the ranks: :class:`RankView` (the adaptation's view of one rank's particles),
:func:`self_organize` of each rank's share, and :func:`organized` / :func:`organize_set` of the
same particles given on every rank (bitwise the one-process result).
"""

from __future__ import annotations

import inspect
from typing import Any, Callable, Sequence

import numpy as np

from .._validate import as_positions
from ..adapt.organize import Adapted, Confinement, Near, ParticleSet, Whole, adapt, int_seed, site_conflicts
from ..adapt.organize import self_organize as one_process
from ..adapt.resolution import SampledResolution
from ..domain import Domain
from ..lists.neighborlist import NeighborList
from ..lists.search import neighbor_list
from .comm import Comm
from .decomposition import Decomposition, bisect
from .ghosts import halo, migrate, scatter
from .reductions import exact_sum, gather, key_ordered

__all__ = ["REBALANCE", "RankView", "organize_set", "organized", "self_organize"]


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
    """The self-organization's view of one rank's particles (:class:`arpy.adapt.organize.Whole` on one
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
