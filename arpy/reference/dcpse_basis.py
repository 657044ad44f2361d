"""The ingredients of the reference DC-PSE operators (:mod:`arpy.reference.dcpse`, where the formulation
is written out): the default constants, the monomial basis (multi-indices ``|k| < m``), the quartic
spline of the interpolating kernel, the distance of each source to its nearest other source, and the
operator specifications with their right-hand sides (Eqs. A.4, A.6).
"""

from __future__ import annotations

from itertools import combinations_with_replacement
from math import factorial
from typing import Sequence, Union

import numpy as np
import numpy.typing as npt

__all__ = ["DEFAULT_A_FACTOR", "DEFAULT_C", "DEFAULT_MAX_COND", "OperatorSpec", "monomial_exponents",
           "nearest_neighbour_distance", "quartic_spline"]

#: Default Gaussian parameter c in w(r) = exp(-c^2 r^2 / 2), for the paper's
#: convention eps_p = r_c,p (§2.3.1: "eps_p = r_c,p = D_p r*"), i.e. scaled
#: offsets ``|z| <= 1``.  The paper states no value.  c = 2 gives a kernel weight
#: w^2 = exp(-4) ~ 0.018 at the cutoff: well localized yet far from the
#: ill-conditioning that a very large c causes (neighbours near the cutoff then
#: drop out of A).  If a caller uses r_c = rho * eps, pass c / rho to get the
#: same kernel shape.
DEFAULT_C: float = 2.0

#: Default a_q = DEFAULT_A_FACTOR * (distance from source q to its nearest other
#: source) for the quartic-spline correction (Eq. A.11; the paper only
#: requires a_q < that distance).
DEFAULT_A_FACTOR: float = 0.5

#: Stencils with cond_2(A_p) above this are rejected as degenerate.
DEFAULT_MAX_COND: float = 1e12

#: Operator specification: a multi-index (sequence of d non-negative ints),
#: "laplacian", or "interp" (interpolating kernel zeta, form (a) only).
OperatorSpec = Union[Sequence[int], str]


def monomial_exponents(d: int, m: int) -> np.ndarray:
    """Exponents of all monomials of total degree < m in d variables.

    Ordering (part of the cross-validation contract): by total degree
    0, 1, ..., m-1; within a degree, lexicographically *descending* in
    (k_1, ..., k_d).  2D, m = 4:
    (0,0) (1,0) (0,1) (2,0) (1,1) (0,2) (3,0) (2,1) (1,2) (0,3).
    3D degree 2: (2,0,0) (1,1,0) (1,0,1) (0,2,0) (0,1,1) (0,0,2).

    Returns int64 array of shape (binom(m-1+d, d), d).
    """
    if int(d) != d or d < 1:
        raise ValueError(f"dimension d must be a positive integer, got {d!r}")
    if int(m) != m or m < 1:
        raise ValueError(f"order m must be a positive integer, got {m!r}")
    d, m = int(d), int(m)
    rows: list[tuple[int, ...]] = []
    for deg in range(m):
        # combinations_with_replacement of variable indices, in lexicographic
        # order of the variable tuple, gives descending exponents lexicographically
        for combo in combinations_with_replacement(range(d), deg):
            k = [0] * d
            for v in combo:
                k[v] += 1
            rows.append(tuple(k))
    return np.array(rows, dtype=np.int64).reshape(-1, d)


def quartic_spline(r: npt.ArrayLike) -> np.ndarray:
    """Quartic spline of unit support: 1 - 6r^2 + 8r^3 - 3r^4 for ``|r| <= 1``, else 0.

    Dimensionless; used as the Kronecker-delta correction of Eq. (A.11).
    """
    r = np.abs(np.asarray(r, dtype=np.float64))
    out = 1.0 - r * r * (6.0 - r * (8.0 - 3.0 * r))
    return np.where(r <= 1.0, out, 0.0)


def nearest_neighbour_distance(x: npt.ArrayLike) -> np.ndarray:
    """Distance from every point of x (n, d) to its nearest *other* point (n,).

    Uses scipy.spatial.cKDTree; raises ValueError for fewer than 2 points.
    Coincident points give 0.
    """
    from scipy.spatial import cKDTree

    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError("nearest_neighbour_distance needs an (n, d) array with n >= 2")
    dist, _ = cKDTree(x).query(x, k=2)
    return dist[:, 1]


def normalize_op(op: OperatorSpec, d: int, m: int, at_sources: bool):
    if isinstance(op, str):
        key = op.lower()
        if key in ("laplacian", "lap", "laplace"):
            if m <= 2:
                raise ValueError(f"the Laplacian needs order m >= 3, got m={m}")
            return "laplacian"
        if key in ("interp", "interpolation", "zeta"):
            if at_sources:
                raise ValueError("the interpolating kernel exists only in form (a) "
                                 "(at_sources=False); at the sources it is the identity")
            return "interp"
        raise ValueError(f"unknown operator {op!r}: use a multi-index, 'laplacian' or 'interp'")
    alpha = tuple(int(a) for a in op)
    if len(alpha) != d or any(a < 0 for a in alpha):
        raise ValueError(f"multi-index {op!r} must have {d} non-negative entries")
    if sum(alpha) >= m:
        raise ValueError(f"|alpha| = {sum(alpha)} must be < order m = {m} (multi-index {alpha})")
    if at_sources and sum(alpha) == 0:
        raise ValueError("alpha = 0 has no form-(b) operator (the (f_q - f_p) form "
                         "cannot represent f itself); use at_sources=False")
    return alpha


def op_order(op) -> int:
    if op == "laplacian":
        return 2
    if op == "interp":
        return 0
    return int(sum(op))


def rhs(op, exps: np.ndarray) -> np.ndarray:
    """Constant right-hand side b (n_mono,) for a derivative / Laplacian (Eqs. A.4, A.6)."""
    b = np.zeros(exps.shape[0])
    if op == "laplacian":
        for i in range(exps.shape[1]):
            k = np.zeros(exps.shape[1], dtype=np.int64)
            k[i] = 2
            b[np.flatnonzero((exps == k).all(axis=1))] = 2.0
        return b
    alpha = np.array(op, dtype=np.int64)
    j = np.flatnonzero((exps == alpha).all(axis=1))
    b[j] = float(np.prod([factorial(int(a)) for a in alpha]))
    return b
