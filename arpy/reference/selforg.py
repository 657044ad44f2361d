"""Pure-NumPy reference of the self-organization potentials and energy (Reboux et al. 2012, §2.3.2, §3.1).

Written from the paper for cross-validation of the Fortran core:
V1(r) = 0.8 * 2.5^(1 - 5r) - 2.5^(-4r) (Eq. 2.12), V2(r) = r^-2/2 + r^-6/6
(Eq. 2.13), both replaced below r = 0.5 by the line V(r) = 2 r V(0.5);
V_pq = D_pq^2 V(r_pq / D_pq) with D_pq = min(D_p, D_q) (Eq. 2.10) and
W = sum_p sum_{q in N_p} V_pq (Eq. 2.11).
"""

from __future__ import annotations

import numpy as np

__all__ = ["potential", "energy"]

_LN25 = np.log(2.5)


def _raw(r: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    if kind == "V1":
        a, b = 0.8 * 2.5 ** (1 - 5 * r), 2.5 ** (-4 * r)
        return a - b, -5 * _LN25 * a + 4 * _LN25 * b
    if kind == "V2":
        return 0.5 / r ** 2 + 1 / (6 * r ** 6), -1 / r ** 3 - 1 / r ** 7
    raise ValueError(kind)


def potential(r: np.ndarray, kind: str = "V2") -> tuple[np.ndarray, np.ndarray]:
    """V(r) and V'(r), with the linear core below r = 0.5."""
    r = np.asarray(r, dtype=np.float64)
    v, dv = _raw(np.maximum(r, 0.5), kind)
    v05, _ = _raw(np.array(0.5), kind)
    core = r < 0.5
    return np.where(core, 2 * r * v05, v), np.where(core, 2 * v05, dv)


def energy(x: np.ndarray, D: np.ndarray, i: np.ndarray, j: np.ndarray, kind: str = "V2",
           grad_D: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """W and dW/dx for the unordered pairs (i, j) (each once; W counts both orders)."""
    x = np.asarray(x, dtype=np.float64)
    dpq = np.minimum(D[i], D[j])
    diff = x[i] - x[j]
    rpq = np.sqrt((diff ** 2).sum(axis=1))
    r = rpq / dpq
    v, dv = potential(r, kind)
    W = 2.0 * np.sum(dpq ** 2 * v)
    e = np.divide(diff, rpq[:, None], out=np.zeros_like(diff), where=rpq[:, None] > 0)
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
