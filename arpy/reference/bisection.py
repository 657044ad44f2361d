"""Recursive coordinate bisection by weight, written plainly (sorting, cumulative sums) as the
reference of :func:`arpy.distributed.bisect`, which finds its cuts by a search over the bits of the
coordinates with global sums, so that it runs on any number of ranks.

Each box of p parts is cut across its longest edge at the weighted median of its particles' coordinates
along it: with v0 the smallest coordinate at which the particles at or below it carry at least
(p // 2) / p of the box's weight (the box's lower face if that share is zero), the cut is the next
particle coordinate above v0 (the box's upper face if there is none, all particles then below it); the
lower box takes p // 2 parts, the upper one the rest.
"""

from __future__ import annotations

import numpy as np

__all__ = ["weighted_bisection"]


def weighted_bisection(x: np.ndarray, parts: int, weights: np.ndarray, lo: np.ndarray, hi: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of about equal weight: (lower corners (parts, d), upper corners (parts, d), the box of
    each particle (n,)), for points x (n, d) in the box [lo, hi] with non-negative integer weights (n,)."""
    x, w = np.asarray(x, np.float64), np.asarray(weights, np.int64)
    d = x.shape[1]
    box_lo, box_hi = np.zeros((parts, d)), np.zeros((parts, d))
    owner = np.zeros(x.shape[0], np.int64)
    stack = [(np.arange(x.shape[0]), np.asarray(lo, np.float64), np.asarray(hi, np.float64), parts, 0)]
    while stack:
        idx, blo, bhi, p, first = stack.pop()
        if p == 1:
            box_lo[first], box_hi[first], owner[idx] = blo, bhi, first
            continue
        axis = int(np.argmax(bhi - blo))
        v = x[idx, axis]
        order = np.argsort(v, kind="stable")
        below = p * np.cumsum(w[idx][order])                  # p times the weight at or below each value
        need = int(w[idx].sum()) * (p // 2)
        v0 = blo[axis] if need == 0 else v[order][np.flatnonzero(below >= need)[0]]
        above = v[v > v0]
        cut = above.min() if above.size else bhi[axis]
        low = v < cut if above.size else np.ones(idx.size, bool)
        upper_lo, lower_hi = blo.copy(), bhi.copy()
        upper_lo[axis] = lower_hi[axis] = cut
        stack.append((idx[low], blo, lower_hi, p // 2, first))
        stack.append((idx[~low], upper_lo, bhi, p - p // 2, first + p // 2))
    return box_lo, box_hi, owner
