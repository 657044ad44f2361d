"""Pure-NumPy neighbour searches used to cross-validate the Fortran core.

They apply the rule ``|x_p - x_q| <= min(rc_p, rc_q) + skin`` (the brute-force
searches also ``max(rc_p, rc_q) + skin`` and ``(rc_p + rc_q) + skin``: the
``rule`` "max" and "sum") and return every unordered pair once as ``(i, j)``
with ``i < j`` (cross pairs: query ``i``, particle ``j``), sorted
lexicographically, exactly like :meth:`arpy.NeighborList.pairs`.  The reach
is evaluated in that order, as the core does, and compared with the squared
distance.

They are written for clarity, not speed: use them on up to a few 10^4
particles.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["RULES", "brute_force_cross_pairs", "brute_force_pairs", "cell_list_pairs", "morton_order", "pair_reach"]

#: The cutoff rules the brute-force searches know.
RULES = ("min", "max", "sum")


def pair_reach(ra: np.ndarray, rb: np.ndarray, skin: float = 0.0, rule: str = "min") -> np.ndarray:
    """The reach of pairs with cutoffs ra and rb (broadcast) under ``rule``: ``min(ra, rb) + skin``,
    ``max(ra, rb) + skin`` or ``(ra + rb) + skin`` (same length unit as the cutoffs)."""
    if rule == "min":
        return np.minimum(ra, rb) + skin
    if rule == "max":
        return np.maximum(ra, rb) + skin
    if rule == "sum":
        return (ra + rb) + skin
    raise ValueError(f"unknown rule {rule!r}; choose one of {RULES}")


def _prepare(x: np.ndarray, rc: float | np.ndarray, skin: float) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError("x must have shape (n, d)")
    r = np.broadcast_to(np.asarray(rc, dtype=np.float64), (x.shape[0],)) + float(skin)
    return x, np.ascontiguousarray(r)


def _accept(x: np.ndarray, r: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the candidate pairs (i, j) that satisfy the min rule; sort them."""
    d2 = ((x[j] - x[i]) ** 2).sum(axis=1)
    rm = np.minimum(r[i], r[j])
    keep = d2 <= rm * rm
    i, j = i[keep], j[keep]
    order = np.lexsort((j, i))
    return i[order].astype(np.int64), j[order].astype(np.int64)


def _checked_pairs(xa: np.ndarray, ra: np.ndarray, xb: np.ndarray, rb: np.ndarray, upper: bool,
                   period: np.ndarray | None, skin: float = 0.0,
                   rule: str = "min") -> tuple[np.ndarray, np.ndarray]:
    """Every (a, b) with ``|xa_a - xb_b| <= pair_reach(ra_a, rb_b, skin, rule)``, checked one by one
    (O(na nb) time, blocked memory); ``upper``: only b > a (one set against itself); sorted by
    (a, b)."""
    na, nb = xa.shape[0], xb.shape[0]
    out_i, out_j = [], []
    block = max(1, 1_000_000 // max(nb, 1))
    for start in range(0, na, block):
        rows = np.arange(start, min(na, start + block))
        # every pair of these rows: squared distance against the squared min cutoff
        e = xb[None, :, :] - xa[rows, None, :]
        if period is not None:                   # minimum image along the axes with a period > 0
            periodic = period > 0
            e -= np.where(periodic, period * np.round(e / np.where(periodic, period, 1.0)), 0.0)
        d2 = (e ** 2).sum(axis=2)
        rm = pair_reach(ra[rows, None], rb[None, :], skin, rule)
        within = d2 <= rm * rm
        if upper:
            within &= np.arange(nb)[None, :] > rows[:, None]
        i, j = np.nonzero(within)
        out_i.append(rows[i])
        out_j.append(j)
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j = np.concatenate(out_i).astype(np.int64), np.concatenate(out_j).astype(np.int64)
    order = np.lexsort((j, i))
    return i[order], j[order]


def brute_force_pairs(x: np.ndarray, rc: float | np.ndarray, skin: float = 0.0,
                      period: np.ndarray | None = None, rule: str = "min") -> tuple[np.ndarray, np.ndarray]:
    """All pairs within reach under ``rule`` by checking every pair (O(n^2) time, blocked memory).

    Parameters
    ----------
    x : array (n, d)
        Positions.
    rc : float or array (n,)
        Cutoffs.
    skin : float
        Added to the reach of every pair.
    period : array (d,) or None
        Edges of a periodic box, for the minimum-image distance (reaches below half an edge), 0
        along axes that are not periodic; None in free space.
    rule : {"min", "max", "sum"}
        The cutoff rule (:func:`pair_reach`).

    Returns
    -------
    (i, j) : int64 arrays, i < j, lexicographically sorted.
    """
    x, r = _prepare(x, rc, 0.0)
    return _checked_pairs(x, r, x, r, True, None if period is None else np.asarray(period, dtype=np.float64),
                          float(skin), rule)


def brute_force_cross_pairs(x_query: np.ndarray, rc_query: float | np.ndarray, x: np.ndarray,
                            rc: float | np.ndarray, skin: float = 0.0, period: np.ndarray | None = None,
                            rule: str = "min") -> tuple[np.ndarray, np.ndarray]:
    """Cross pairs: query i and particle q with ``|x_query_i - x_q| <= pair_reach(rc_query_i, rc_q,
    skin, rule)`` (the minimum image along the axes with ``period`` > 0), by checking every pair, as
    :meth:`arpy.NeighborList.pairs` of a cross list.

    Returns
    -------
    (i, q) : int64 arrays, lexicographically sorted.
    """
    x_query, r_query = _prepare(x_query, rc_query, 0.0)
    x, r = _prepare(x, rc, 0.0)
    return _checked_pairs(x_query, r_query, x, r, False,
                          None if period is None else np.asarray(period, dtype=np.float64), float(skin), rule)


def cell_list_pairs(x: np.ndarray, rc: float | np.ndarray, skin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pairs by a uniform cell list with the full 3^d stencil (an independent construction).

    Cells have edge ``max(rc) + skin`` (slightly enlarged against rounding);
    every particle is compared with all particles in its own and the 3^d - 1
    surrounding cells, and pairs are kept once with i < j.
    """
    x, r = _prepare(x, rc, skin)
    n, d = x.shape
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    h = r.max() * (1.0 + 1e-9)
    ci = np.floor((x - x.min(axis=0)) / h).astype(np.int64)
    nc = ci.max(axis=0) + 1
    strides = np.cumprod(np.concatenate(([1], nc[:-1])))
    key = ci @ strides
    order = np.argsort(key, kind="stable")
    sorted_keys = key[order]
    out_i, out_j = [], []
    for off in itertools.product((-1, 0, 1), repeat=d):
        nb = ci + np.asarray(off)
        valid = np.all((nb >= 0) & (nb < nc), axis=1)
        p = np.nonzero(valid)[0]
        nkey = nb[valid] @ strides
        lo = np.searchsorted(sorted_keys, nkey, side="left")
        hi = np.searchsorted(sorted_keys, nkey, side="right")
        cnt = hi - lo
        i = np.repeat(p, cnt)
        # positions lo[k] .. hi[k]-1 of the sorted order, flattened
        first = np.repeat(lo - np.concatenate(([0], np.cumsum(cnt)[:-1])), cnt)
        j = order[first + np.arange(cnt.sum())]
        upper = j > i
        out_i.append(i[upper])
        out_j.append(j[upper])
    return _accept(x, r, np.concatenate(out_i), np.concatenate(out_j))


def morton_order(x: np.ndarray, lo: np.ndarray, s: float, bits: int) -> np.ndarray:
    """The order of points along the Morton curve of a grid: cell c_i = floor((x_i - lo_i) s)
    clamped to [0, 2**bits - 1], the code interleaving the bits of c with axis 0 the most
    significant, ties by index.  Returns the permutation (n,) int64."""
    x = np.asarray(x, dtype=np.float64)
    n, d = x.shape
    top = 2 ** bits - 1
    u = (x - np.asarray(lo, np.float64)) * float(s)
    c = np.where(u <= 0, 0, np.where(u >= top, top, np.floor(np.clip(u, 0, top)))).astype(np.uint64)
    code = np.zeros(n, dtype=np.uint64)
    for b in range(bits):                     # bit b of axis a goes to bit d*b + (d - 1 - a)
        for a in range(d):
            code |= ((c[:, a] >> np.uint64(b)) & np.uint64(1)) << np.uint64(d * b + d - 1 - a)
    return np.lexsort((np.arange(n), code)).astype(np.int64)
