"""Candidate pairs and the neighbour test of the reference AR lists (:mod:`arpy.reference.ar`): pairs
expanded from cell ranges in chunks, the gather rule evaluated exactly like the Fortran brute force,
CSR rows, and the checks of cutoffs and skin.
"""

from __future__ import annotations

from typing import Iterator, Tuple

import numpy as np

__all__ = ["CHUNK", "check_cutoffs", "check_skin", "expand_ranges", "to_csr", "within"]

#: Number of candidate pairs processed at once (memory bound, not a limit).
CHUNK = 1 << 21


def expand_ranges(p: np.ndarray, a: np.ndarray, b: np.ndarray
                   ) -> Iterator[Tuple[np.ndarray, np.ndarray]]:
    """Yield chunks of candidate pairs ``(p_i, q)`` for ``q in range(a_i, b_i)``."""
    cnt = np.maximum(b - a, 0)
    keep = cnt > 0
    p, a, cnt = p[keep], a[keep], cnt[keep]
    if p.size == 0:
        return
    csum = np.cumsum(cnt)
    lo = 0
    while lo < p.size:
        base = 0 if lo == 0 else csum[lo - 1]
        hi = int(np.searchsorted(csum, base + CHUNK, side="right"))
        hi = max(hi, lo + 1)
        c = cnt[lo:hi]
        tot = int(c.sum())
        starts = np.cumsum(c) - c
        pp = np.repeat(p[lo:hi], c)
        qq = np.repeat(a[lo:hi] - starts, c) + np.arange(tot, dtype=np.int64)
        yield pp, qq
        lo = hi


def within(xp: np.ndarray, rp: np.ndarray, xq: np.ndarray, rq: np.ndarray,
            skin: float = 0.0) -> np.ndarray:
    """The neighbour rule, evaluated exactly like the Fortran brute force."""
    r2 = np.zeros(xp.shape[0])
    for i in range(xp.shape[1]):
        dx = xq[:, i] - xp[:, i]
        r2 = r2 + dx * dx
    rm = np.minimum(rp, rq) + skin
    return r2 <= rm * rm


def to_csr(rows: np.ndarray, cols: np.ndarray, n: int) -> Tuple[np.ndarray, np.ndarray]:
    """CSR (offsets (n+1,), indices) with each row sorted ascending."""
    rows = np.asarray(rows, np.int64)
    cols = np.asarray(cols, np.int64)
    perm = np.lexsort((cols, rows))
    rows, cols = rows[perm], cols[perm]
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=offsets[1:])
    return offsets, cols


def check_cutoffs(rc: np.ndarray, n: int, name: str) -> np.ndarray:
    rc = np.ascontiguousarray(rc, dtype=np.float64)
    if rc.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {rc.shape}")
    if not np.all(np.isfinite(rc)) or np.any(rc <= 0.0):
        raise ValueError(f"{name}: every cutoff must be finite and > 0")
    return rc


def check_skin(skin: float) -> float:
    skin = float(skin)
    if not np.isfinite(skin) or skin < 0.0:
        raise ValueError(f"skin must be finite and >= 0, got {skin}")
    return skin
