"""Collective reductions of a distributed run, each the same for every rank count: :func:`exact_sum`
(a global sum of doubles computed exactly and rounded once: mass, error norms), :func:`gather`
(every rank's particles on every rank in key order), :func:`h_min` (the smallest particle distance),
:func:`global_median`, :func:`exact_median` and :func:`exact_quantile` (NumPy's, with nothing
gathered), and :func:`key_ordered` (list rows in key order, so sums over a row do not depend on how the
particles are spread over ranks).
"""

from __future__ import annotations

import math
from typing import Iterator, Sequence

import numpy as np

from .. import _bridge
from .._validate import as_positions
from ..domain import Domain, h_min as one_process_h_min
from ..lists.neighborlist import NeighborList
from .comm import Comm, order_keys
from .decomposition import Decomposition
from .ghosts import exchange_ghosts

__all__ = ["Reductions", "exact_median", "exact_quantile", "exact_sum", "gather", "global_median", "h_min", "key_chunks", "key_ordered",
           "key_places", "order_statistic", "order_statistics"]


def h_min(comm: Comm, dec: Decomposition, x: np.ndarray, eps: np.ndarray, keys: np.ndarray,
          domain: Domain | None = None) -> float:
    """The smallest distance between two particles of all ranks (minimum image along periodic axes),
    the same for every rank count: the least distance between two of a rank's own particles and
    ghosts (reach eps; periodic images are ghosts too, so a pair across a periodic face is there as
    it is on one rank), found by the core's pair scan; exact when that minimum is at most the smallest
    core size (the closest pair then lies within each other's reach), else from the whole set
    gathered.  (A pair of ghosts, or a particle and an image of another, is a distance between two
    particles too, never less than the closest pair's.)  Collective."""
    xs = as_positions(x)
    layer = exchange_ghosts(comm, dec, xs, eps, keys, domain=domain)
    local = one_process_h_min(np.concatenate([xs, layer.x])) if xs.shape[0] else np.inf
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


def global_median(comm: Comm, counts: np.ndarray) -> float:
    """np.median of non-negative integers spread over the ranks (exact: from their histogram)."""
    mine = np.bincount(np.asarray(counts, np.int64))
    size = int(comm.max(np.array([mine.size], np.float64))[0])
    total = comm.add(np.pad(mine, (0, size - mine.size)))
    n = int(total.sum())
    if n == 0:
        return float("nan")
    cum = np.cumsum(total)
    lo, hi = int(np.searchsorted(cum, (n - 1) // 2 + 1)), int(np.searchsorted(cum, n // 2 + 1))
    return (lo + hi) / 2


#: Terms per block of the exact sum: 512 integer mantissas (< 2^53) add up below 2^62 in int64.
_SUM_BLOCK = 512


def exact_sum(comm: Comm | None, values: np.ndarray) -> float:
    """The sum over all ranks of ``values`` (doubles, any shape), exact and rounded once to the
    nearest double: ``math.fsum`` of all the terms, whatever the rank count and the order of the terms
    (comm None: this process's values alone).  Each process sums in the core (Shewchuk's exact
    partials); on several ranks math.fsum adds every rank's partials, exactly.  Where a rank's
    partials overflow, each term is an integer mantissa times a power of two, the mantissas are added
    exactly (as integers, grouped by exponent) and the ranks' integer sums are added exactly too.  With
    a term that is not finite (or a partial sum that overflows) the result is math.fsum's (inf or nan).
    Collective."""
    from fractions import Fraction

    v = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if comm is None or comm.size == 1:
        s, ok = _bridge.exact_sum(v)
        return s if ok else math.fsum(v.tolist())
    parts, ok = _bridge.exact_partials(v)
    got, at = comm.gather_arrays(np.concatenate([[1.0 if ok else 0.0], parts]))     # (each rank: ok, its partials)
    if np.all(got[at[:-1]] == 1.0):
        first = np.zeros(got.size, bool)
        first[at[:-1]] = True
        try:
            return math.fsum(got[~first].tolist())
        except OverflowError:                  # (the ranks' partials overflow together: the integers below)
            pass
    wild = comm.allgather(v[~np.isfinite(v)])
    if any(len(w) for w in wild):
        return math.fsum(np.concatenate(wild).tolist())
    m, e = np.frexp(v)
    mant = (m * 2.0 ** 53).astype(np.int64)                   # exact: |m| < 1
    expo = e.astype(np.int64) - 53
    low = int(comm.min(np.array([expo.min() if v.size else 0], dtype=np.float64))[0])
    # the mantissas grouped by exponent (one sort), each group summed in blocks of _SUM_BLOCK in int64
    order = np.argsort(expo, kind="stable")
    mant, expo = mant[order], expo[order]
    groups = np.flatnonzero(np.diff(expo, prepend=expo[:1] - 1)) if v.size else np.zeros(0, np.int64)
    ends = np.append(groups[1:], v.size)
    starts = np.concatenate([np.arange(a, b, _SUM_BLOCK) for a, b in zip(groups.tolist(), ends.tolist())] or
                            [np.zeros(0, np.int64)])
    sums = np.add.reduceat(mant, starts) if starts.size else np.zeros(0, np.int64)
    total = sum(int(p) << int(x - low) for p, x in zip(sums.tolist(), expo[starts].tolist()))
    grand = sum(comm.allgather(total))
    return float(Fraction(grand) * Fraction(2) ** low)


def order_statistic(comm: Comm | None, values: np.ndarray, k: int) -> float:
    """The k-th smallest (from 0) of the doubles ``values`` of all ranks, without NaN: ``np.sort(all)[k]``
    (:func:`order_statistics` of one k).  Collective (comm None: this process's values alone)."""
    return order_statistics(comm, values, [k])[0]


def order_statistics(comm: Comm | None, values: np.ndarray, ks: Sequence[int]) -> list[float]:
    """The ``ks``-th smallest (from 0) of the doubles ``values`` of all ranks, without NaN:
    ``np.sort(all)[ks]``, found without gathering them by bisecting over their bits, every k at once (64
    rounds, each one sum over the ranks of the exact counts of their values below each k's trial; -0.0
    counts below 0.0).  Collective (comm None: this process's values alone)."""
    keys = np.sort(order_keys(np.ravel(values)))
    comm = comm or _one_process()
    if comm.size == 1:                  # (every key here: the k-th is the one the bisection would find)
        return [float(v) for v in order_keys(keys[np.asarray(ks, dtype=np.int64)], back=True)]
    want = [int(k) + 1 for k in ks]
    lo, hi = [-(1 << 63)] * len(want), [(1 << 63) - 1] * len(want)
    while any(a < b for a, b in zip(lo, hi)):           # the least key t with at least k + 1 keys <= t
        mid = [(a + b) // 2 for a, b in zip(lo, hi)]
        below = np.searchsorted(keys, np.array(mid, dtype=np.int64), side="right").astype(np.int64)
        total = comm.add(below)
        for i, m in enumerate(mid):
            if lo[i] < hi[i]:
                lo[i], hi[i] = (lo[i], m) if total[i] >= want[i] else (m + 1, hi[i])
    return [float(v) for v in order_keys(np.array(lo, dtype=np.int64), back=True)]


def exact_median(comm: Comm | None, values: np.ndarray) -> float:
    """``np.median`` of the doubles ``values`` of all ranks, bit for bit and the same for any rank count,
    without gathering them (:func:`order_statistics`): the middle value, or the mean (a + b) / 2 of the
    two middle ones; NaN if any value is NaN or there is none.  Collective (comm None: this process's
    values alone)."""
    counted = _counted(comm, values)
    if counted is None:
        return float("nan")
    comm, v, n = counted
    a, b = (np.float64(s) for s in order_statistics(comm, v, [(n - 1) // 2, n // 2]))
    return float(a if n % 2 else (a + b) / 2)


def exact_quantile(comm: Comm | None, values: np.ndarray, q: float) -> float:
    """``np.quantile(all, q)`` (its default "linear" method) of the doubles ``values`` of all ranks, bit for
    bit and the same for any rank count, without gathering them (:func:`order_statistics`): the order
    statistics a and b at floor((n - 1) q) and the next, and NumPy's interpolation between them by
    g = (n - 1) q - floor((n - 1) q): ``a + (b - a) g``, or ``b - (b - a) (1 - g)`` when g >= 0.5; NaN
    if any value is NaN or there is none.  Collective (comm None: this process's values alone)."""
    counted = _counted(comm, values)
    if counted is None:
        return float("nan")
    comm, v, n = counted
    at = (n - 1) * float(q)
    lo = min(max(int(np.floor(at)), 0), n - 1)
    a, b = (np.float64(s) for s in order_statistics(comm, v, [lo, min(lo + 1, n - 1)]))
    g = np.float64(at - lo)
    return float(b - (b - a) * (1 - g) if g >= 0.5 else a + (b - a) * g)


def _counted(comm: Comm | None, values: np.ndarray) -> tuple[Comm, np.ndarray, int] | None:
    """(the communicator, this rank's ``values`` as float64 (m,), their number over all ranks), or None
    if there is none or any is NaN (the statistic is then NaN): one collective."""
    v = np.ravel(np.asarray(values, dtype=np.float64))
    comm = comm or _one_process()
    counts = comm.add(np.array([v.size, np.count_nonzero(np.isnan(v))], dtype=np.int64))
    n, nans = int(counts[0]), int(counts[1])
    return None if n == 0 or nans else (comm, v, n)


def _one_process() -> Comm:
    from .comm import SerialComm

    return SerialComm()


def gather(comm: Comm, keys: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every rank's particles on every rank, in key order (output at small scale): (keys, then each
    array with its rows put in that order).  Collective; arrays have one row per key."""
    k = np.asarray(keys, dtype=np.int64)
    parts = comm.allgather((k, [np.asarray(a) for a in arrays]))
    all_keys = np.concatenate([p[0] for p in parts])
    order = np.argsort(all_keys, kind="stable")
    out = [np.concatenate([p[1][i] for p in parts])[order] for i in range(len(arrays))]
    return (all_keys[order], *out)


#: Beyond this many ranks, each rank sends this many samples of its keys (at random places) for
#: :func:`key_places`' splitters, not P: P of them would bring P^2 keys to every rank (800 MB at P =
#: 10^4).  Drawn so, the largest range held 1.50 N / P at P = 10^4 (1,000 random keys a rank), 1.46 N / P
#: at P = 1,024; P regularly spaced samples hold it below 2 N / P, but fewer cluster (32 of them: 187 N / P).
KEY_SAMPLES = 64


def key_places(comm: Comm, keys: np.ndarray) -> np.ndarray:
    """The place of each of this rank's keys among every rank's keys, int64 (n,): the index the whole
    set gathered in key order (:func:`gather`) gives it (a repeated key: the number of keys below it).  No rank holds more than its share
    of the keys: a sample sort.  Every rank sends samples of its sorted keys to all (P regularly spaced
    ones, or beyond :data:`KEY_SAMPLES` ranks that many at random places); P - 1 splitters cut the key
    line into one range per rank; each rank sends each of its keys to the rank of its range, which sorts
    what it got, and sends back the places (the keys below its range, from the counts per rank, plus
    each key's index in its range).  A rank then holds about N / P keys (the samples of each rank, its
    own keys and those of its range); the places are exact whatever the splitters.  Collective."""
    k = np.asarray(keys, dtype=np.int64)
    mine = np.sort(k)
    if comm.size == 1:
        return np.searchsorted(mine, k)
    p = comm.size
    if p <= KEY_SAMPLES:                # (P regularly spaced samples: every range holds at most 2 N / P keys)
        samples = mine[(np.arange(p) * mine.size) // p] if mine.size else mine
    else:                               # (KEY_SAMPLES at random places: regular ones would cluster)
        samples = mine if mine.size <= KEY_SAMPLES else \
            mine[np.sort(np.random.default_rng([comm.rank, p]).integers(0, mine.size, KEY_SAMPLES))]
    pooled = np.sort(comm.gather_arrays(samples)[0])
    if not pooled.size:                                          # (no rank has a key)
        return np.zeros(0, np.int64)
    splitters = pooled[(np.arange(1, p) * pooled.size) // p]
    cuts = np.searchsorted(mine, splitters)                      # (the keys below each splitter: rank 0's range)
    ranged, sizes = comm.alltoall_arrays(mine, np.diff(np.concatenate([[0], cuts, [mine.size]])))
    got = np.sort(ranged)
    below = int(comm.gather_arrays(np.array([got.size], np.int64))[0][:comm.rank].sum())
    places, _ = comm.alltoall_arrays(below + np.searchsorted(got, ranged), sizes)     # (in the order they came)
    out = np.empty(k.size, np.int64)
    out[np.argsort(k, kind="stable")] = places
    return out


def key_chunks(comm: Comm, keys: np.ndarray, array: np.ndarray, rows: int) -> Iterator[np.ndarray]:
    """The rows of ``array`` (one per key; the keys of all ranks are 0 .. N - 1) of every rank, in key
    order, ``rows`` at a time, on every rank: their concatenation is the whole array :func:`gather` gives,
    with no rank holding more than one chunk of it.  Collective: every rank iterates to the end."""
    k = np.asarray(keys, dtype=np.int64)
    order = np.argsort(k, kind="stable")
    k, a = k[order], np.asarray(array)[order]
    n = int(comm.sum(int(k.size)))
    for start in range(0, n, rows):
        lo, hi = np.searchsorted(k, [start, start + rows])
        parts = comm.allgather((k[lo:hi], a[lo:hi]))
        got = np.concatenate([p[0] for p in parts])
        yield np.concatenate([p[1] for p in parts])[np.argsort(got, kind="stable")]


class Reductions:
    """Reductions over the ranks of ``self.comm``, each the same for every rank count: the methods of
    the classes that hold a rank's share of a set (:class:`arpy.particles.Particles`, the
    self-organization's :class:`arpy.adapt.view.View`).  Each is collective."""

    comm: Comm

    def total(self, count: int) -> int:
        """An integer summed over the ranks (exact).  Collective."""
        return int(self.comm.sum(int(count)))

    def gmin(self, value: float) -> float:
        """The smallest of the ranks' values.  Collective."""
        return float(self.comm.min(np.array([value], dtype=np.float64))[0])

    def gmax(self, value: float) -> float:
        """The largest of the ranks' values.  Collective."""
        return float(self.comm.max(np.array([value], dtype=np.float64))[0])

    def gmedian(self, values: np.ndarray) -> float:
        """``np.median`` of every rank's values, bit for bit, with none gathered
        (:func:`exact_median`).  Collective."""
        return exact_median(self.comm, values)

    def fsum(self, values: np.ndarray) -> float:
        """The exact, once-rounded sum of every rank's values (any shape; the same bits for any rank
        count).  Collective."""
        return exact_sum(self.comm, np.ravel(values))
