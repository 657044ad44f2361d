"""Pure-NumPy reference of the self-organization potentials and energy (Reboux et al. 2012, §2.3.2, §3.1).

Written from the paper for cross-validation of the Fortran core:
V1(r) = 0.8 * 2.5^(1 - 5r) - 2.5^(-4r) (Eq. 2.12), V2(r) = r^-2/2 + r^-6/6
(Eq. 2.13), both replaced below r = 0.5 by the line V(r) = 2 r V(0.5);
V_pq = D_pq^2 V(r_pq / D_pq) with D_pq = min(D_p, D_q) (Eq. 2.10) and
W = sum_p sum_{q in N_p} V_pq (Eq. 2.11).
"""

from __future__ import annotations

import numpy as np

__all__ = ["potential", "energy", "resolution", "scan", "shepard"]

_LN25 = np.log(2.5)
#: pairs closer than RFUSED D_pq have fused: no pair force
RFUSED = 1e-3


def _raw(r: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    if kind == "V1":
        a, b = 0.8 * 2.5 ** (1 - 5 * r), 2.5 ** (-4 * r)
        return a - b, -5 * _LN25 * a + 4 * _LN25 * b
    if kind == "V2":
        return 0.5 / r ** 2 + 1 / (6 * r ** 6), -1 / r ** 3 - 1 / r ** 7
    raise ValueError(kind)


def potential(r: np.ndarray, kind: str = "V2") -> tuple[np.ndarray, np.ndarray]:
    """V(r) and V'(r), with the linear core below r = 0.5 ("V1", "V2"), or
    without it ("V1-pure", "V2-pure"; r taken as at least RFUSED)."""
    r = np.asarray(r, dtype=np.float64)
    kind = kind.upper()
    if kind.endswith("-PURE"):
        return _raw(np.maximum(r, RFUSED), kind[:2])
    v, dv = _raw(np.maximum(r, 0.5), kind)
    v05, _ = _raw(np.array(0.5), kind)
    core = r < 0.5
    return np.where(core, 2 * r * v05, v), np.where(core, 2 * v05, dv)


def energy(x: np.ndarray, D: np.ndarray, i: np.ndarray, j: np.ndarray, kind: str = "V2",
           grad_D: np.ndarray | None = None, period: np.ndarray | None = None,
           cutoff: float | None = None) -> tuple[float, np.ndarray]:
    """W and dW/dx for the unordered pairs (i, j) (each once; W counts both orders).
    period: box edges of a periodic box (minimum image), None for none;
    cutoff: pairs use V(r) - V(cutoff)."""
    x = np.asarray(x, dtype=np.float64)
    dpq = np.minimum(D[i], D[j])
    diff = x[i] - x[j]
    if period is not None:
        diff -= period * np.round(diff / period)
    rpq = np.sqrt((diff ** 2).sum(axis=1))
    r = rpq / dpq
    v, dv = potential(r, kind)
    if cutoff is not None:
        v = v - potential(np.array(cutoff), kind)[0]
    W = 2.0 * np.sum(dpq ** 2 * v)
    e = np.divide(diff, rpq[:, None], out=np.zeros_like(diff), where=r[:, None] > RFUSED)
    g = np.zeros_like(x)
    f = (2 * dpq * dv)[:, None] * e
    np.add.at(g, i, f)
    np.add.at(g, j, -f)
    if grad_D is not None:
        dterm = 2 * dpq * (2 * v - r * dv)
        pi, qj = D[i] < D[j], D[j] < D[i]
        np.add.at(g, i[pi], dterm[pi][:, None] * grad_D[i[pi]])
        np.add.at(g, j[qj], dterm[qj][:, None] * grad_D[j[qj]])
    return float(W), g


def resolution(x: np.ndarray, d_tilde: np.ndarray, rstar: float, iters: int = 80,
               rows: np.ndarray | None = None) -> np.ndarray:
    """Eq. 2.9, D_p = min of D~ within r* D_p, by bisection on each particle:
    the largest D in (0, D~_p] with ``min { D~_q : |x_q - x_p| <= r* D } >= D``
    (brute-force distances; O(n^2)).  ``rows``: only these particles (default all);
    returns one value per row."""
    x = np.asarray(x, dtype=np.float64)
    rows = np.arange(len(x)) if rows is None else np.asarray(rows)
    out = np.empty(len(rows))
    for k, p in enumerate(rows):
        dist = np.sqrt(((x - x[p]) ** 2).sum(axis=1))
        lo, hi = 0.0, float(d_tilde[p])
        if d_tilde[dist <= rstar * hi].min() >= hi:
            out[k] = hi
            continue
        for _ in range(iters):
            mid = 0.5 * (lo + hi)
            if d_tilde[dist <= rstar * mid].min() >= mid:
                lo = mid
            else:
                hi = mid
        out[k] = lo
    return out


def scan(x: np.ndarray, D: np.ndarray, rstar: float, period: np.ndarray | None = None, rcount: float = np.inf
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, int]:
    """The adaptation bookkeeping of a particle set, from every pair (brute force, O(n^2)): the
    neighbours under the min rule ``r_pq <= rstar D_pq`` (D_pq = min(D_p, D_q)), max D_pq / r_pq
    over them (inf for coincident particles), fusion as a greedy matching of the pairs p < q closer
    than D_pq / 2 visited in the order of (r_pq / D_pq, p, q) (a pair fuses when neither particle
    has; p moves to the midpoint, q dies), and the neighbours among the survivors with
    ``r_pq <= rcount D_pq``.  Returns (x_fused, alive, counts, counts_alive, ratio, n_fused)."""
    x = np.array(x, dtype=np.float64)
    n = len(x)
    p, q = np.triu_indices(n, k=1)

    def sep(a, b):
        e = a - b
        return e if period is None else e - period * np.round(e / period)

    dpq = np.minimum(D[p], D[q])
    rho = np.sqrt((sep(x[p], x[q]) ** 2).sum(axis=1)) / dpq
    near = rho <= rstar
    cnt = np.bincount(p[near], minlength=n) + np.bincount(q[near], minlength=n)
    lowest = rho[near].min() if near.any() else np.inf
    ratio = np.inf if lowest == 0 else float(1.0 / lowest)
    xo, alive, fused = x.copy(), np.ones(n, bool), np.zeros(n, bool)
    nf = 0
    for k in np.lexsort((q, p, rho)):
        a, b = p[k], q[k]
        if rho[k] >= 0.5:
            break
        if not (fused[a] or fused[b]):
            xo[a] = x[a] - 0.5 * sep(x[a], x[b])
            fused[a] = fused[b] = True
            alive[b] = False
            nf += 1
    both = near & alive[p] & alive[q] & (rho <= rcount)
    cnt_alive = np.bincount(p[both], minlength=n) + np.bincount(q[both], minlength=n)
    return xo, alive, cnt, cnt_alive, ratio, nf


def shepard(x: np.ndarray, D: np.ndarray, rc: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """D interpolated to the points y (m, d) from the particles x (n, d) with values D and cutoffs rc
    (§3.2.2 step 4(e)iv, first order): sum_q w_q D_q / sum_q w_q with w_q = max(1 - s_q^2 / rc_q^2, 0)^2,
    s_q the distance from y to x_q, over every particle q in index order (those out of reach add exact
    zeros).  Returns (values, reached); values are 0 where no particle reaches."""
    num, den = np.zeros(len(y)), np.zeros(len(y))
    for q in range(len(x)):
        diff = y - x[q]
        s2 = diff[:, 0] * diff[:, 0]
        for a in range(1, y.shape[1]):
            s2 = s2 + diff[:, a] * diff[:, a]
        w = np.maximum(1.0 - s2 / (rc[q] * rc[q]), 0.0)
        w = w * w
        num = num + w * D[q]
        den = den + w
    reached = den > 0
    return np.where(reached, num / np.where(reached, den, 1.0), 0.0), reached
