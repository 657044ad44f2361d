"""Row-wise measures and limits of assembled DC-PSE operators: the Lebesgue constant of each
interpolation row (:func:`lebesgue_constants`) and the matrix product held to each row's range of
values (:func:`bounded_apply`)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import scipy.sparse as sp

__all__ = ["bounded_apply", "lebesgue_constants"]


class _Interpolating(Protocol):
    def interpolation(self) -> sp.csr_matrix: ...


def lebesgue_constants(op: _Interpolating) -> np.ndarray:
    """Per collocation point of an operator set (anything with ``interpolation()``), the sum of
    ``|interpolation weights|``, shape (n_col,): >= 1 for a consistent row; large values mean the
    stencil amplifies data errors."""
    w = op.interpolation().tocsr()
    # (from the arrays: scipy's abs() sorts a matrix's rows in place, which would change the order
    # its rows are summed in, e.g. by key)
    rows = np.repeat(np.arange(w.shape[0]), np.diff(w.indptr))
    return np.bincount(rows, weights=np.abs(w.data), minlength=w.shape[0])


def bounded_apply(mat: sp.spmatrix, f: np.ndarray) -> np.ndarray:
    """``mat @ f`` with every row's result limited to the range of the values it reads.

    A local min/max limiter for interpolation across steep fronts: row i of the result lies in
    [min f_j, max f_j] over the columns j of row i's non-zero entries (its stencil), so an
    interpolated field makes no new extrema.  Rows without entries give 0.

    Parameters
    ----------
    mat : sparse matrix (m, n)
    f : array (n,)

    Returns
    -------
    array (m,)
    """
    m = sp.csr_matrix(mat, copy=True)
    m.eliminate_zeros()
    f = np.asarray(f, dtype=np.float64)
    out = m @ f
    rows = np.flatnonzero(np.diff(m.indptr))
    if rows.size:
        vals = f[m.indices]
        start = m.indptr[rows]
        out[rows] = np.clip(out[rows], np.minimum.reduceat(vals, start), np.maximum.reduceat(vals, start))
    return out
