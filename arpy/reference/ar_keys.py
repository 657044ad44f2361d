"""The cells of the reference AR cell list as integers: levels, level-order indices J(c), Morton
codes, the root's edge, and the ``cells`` table's lookup (:mod:`arpy.reference.ar`).

Level-order index J(c).  The root is ``J = 1``.  The children of cell J are
``J * 2^d + l - 2^d + 2`` for ``l = 0 .. 2^d - 1`` (Op3), the parent of J > 1 is
``(J + 2^d - 2) // 2^d`` (Op4).  The child number ``l`` follows Algorithm 2's
partition order (dimension 1 first): ``l = sum_i b_i * 2^(d-1-i)`` with
``b_i = 1`` iff ``x_i >= m_i`` (i = 0 .. d-1, axis 0 = most significant bit).
Closed form for a level-k cell with integer coordinates ``c = (c_0, .., c_{d-1})``,
``0 <= c_i < 2^k``::

    J = F(k) + M_k(c),   F(k) = (2^(d k) - 1) / (2^d - 1) + 1,
    M_k(c) = sum_{b=0}^{k-1} sum_{i=0}^{d-1} bit_b(c_i) * 2^(d b + d - 1 - i)

(F(k) = first index on level k; M_k = Morton/Z-order code, axis 0 most
significant within each group of d bits).  Indices on a level are contiguous
and increasing with the level, so sorting by J sorts by (level, Morton code).
The largest index on level k is ``(2^(d(k+1)) - 1)/(2^d - 1)``; we allow
k <= 30 in 2D and k <= 20 in 3D (both < 2^63) and raise ``ValueError`` beyond.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Dict, Tuple

import numpy as np

__all__ = ["MAX_LEVEL", "in_sorted", "level_first_index", "level_of_index", "morton_decode", "morton_encode",
           "root_edge"]

#: Deepest level whose level-order indices fit (with their neighbours) in int64.
MAX_LEVEL: Dict[int, int] = {2: 30, 3: 20}


def root_edge(extent: float, rc: np.ndarray, d: int) -> float:
    """The root's edge D_m for a box of largest extent ``extent`` and cutoffs ``rc``: ``r * 2^K``
    with ``r`` the double just above ``min(rc)`` and ``K >= 0`` the fewest doublings that reach
    ``extent``, so that the smallest cutoffs sit on level K in cells ``r`` wide; if K would exceed
    ``MAX_LEVEL[d]``, the extent itself (the paper's footnote 1; ``max(rc)`` if it is 0)."""
    edge, k = float(np.nextafter(rc.min(), np.inf)), 0
    while edge < extent and k <= MAX_LEVEL[d]:
        edge, k = edge * 2.0, k + 1
    if k > MAX_LEVEL[d]:
        edge = extent if extent > 0.0 else float(rc.max())
    return edge


@lru_cache(maxsize=None)
def level_first_index(k: int, d: int) -> int:
    """First level-order index on level ``k``: ``F(k) = (2^(dk) - 1)/(2^d - 1) + 1``."""
    return ((1 << (d * k)) - 1) // ((1 << d) - 1) + 1


def morton_encode(c: np.ndarray, k: int, d: int) -> np.ndarray:
    """Morton code ``M_k(c)`` of integer cell coordinates ``c`` (m, d), 0 <= c < 2^k."""
    code = np.zeros(c.shape[0], dtype=np.int64)
    for b in range(k):
        for i in range(d):
            code |= ((c[:, i] >> b) & 1) << (d * b + d - 1 - i)
    return code


@lru_cache(maxsize=1 << 16)
def level_of_index(J: int, d: int) -> int:
    """Level k with F(k) <= J < F(k+1)."""
    k = 0
    while level_first_index(k + 1, d) <= J:
        k += 1
    return k


def morton_decode(code: int, k: int, d: int) -> Tuple[int, ...]:
    """Inverse of :func:`morton_encode` for one code (Python ints)."""
    c = [0] * d
    for b in range(k):
        for i in range(d):
            c[i] |= ((code >> (d * b + d - 1 - i)) & 1) << b
    return tuple(c)


def in_sorted(keys: np.ndarray, values: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Hash-table lookup emulated on a sorted key array.

    Returns ``(found, pos)``: ``found[i]`` iff ``values[i]`` is in ``keys`` and then
    ``keys[pos[i]] == values[i]``.
    """
    if keys.size == 0:
        return np.zeros(values.shape, bool), np.zeros(values.shape, np.int64)
    pos = np.searchsorted(keys, values)
    pos = np.minimum(pos, keys.size - 1)
    return keys[pos] == values, pos
