"""Rows of DC-PSE operators: the absolute sums of their rows, what they say about a stencil, and a
product limited row by row.

* :func:`abs_row_sums`: ``sum_q |w_pq|`` per row of a sparse operator.  Of the interpolating kernel, it is
  the row's Lebesgue constant (:func:`lebesgue_constants`); of an operator at the particles, the radius
  of the row's Gershgorin disc, whose largest value bounds the operator's spectrum (the time step's
  stability bound, :class:`arpy.Simulation`).
* :func:`weight_scales`: of the Laplacian, ``eps_p^2 sum_q |L_pq|``, its weights in units of the point's
  own core size (of a first derivative ``eps_p sum_q |G_pq|``).  A DC-PSE row whose moments are well
  posed has weights of order 1 / eps^2: on the cases' self-organized particles (2D, m = 4) the median
  scale is 14-22 and 99.9 % of the rows lie below 60 (``benchmarks/row_scales.py``), but single sound
  rows reach 275 (the pulse) and 486 (a coarse five-spot set), where a stencil holds barely as many
  sources as the moments need.  A stencil whose moment matrix is close to singular, such as one that has
  just lost the source that held it together (a source near the cutoff that a flow carried out of it at
  an RK stage), solves for large weights of either sign: issue 54's row went from 34 to 744.
* :func:`wild_rows`: the rows of a right-hand side's Laplacian whose Gershgorin radius alone lies above
  a limit; a simulation gives ``STABILITY / (nu dt)`` (:data:`arpy.equations.STABILITY`), so the rows it
  finds are those that would make its step unstable (a row at scale s shrinks the stable step to
  ``STABILITY eps^2 / (nu s)``), whatever their scale: :class:`arpy.DomainDCPSE` repairs them at the
  particles as it repairs wild interpolation rows off them.  A fixed scale cannot tell such rows from
  sound ones (the sound 486 against the wild 744); the step can: a sound row of a heavy scale sits at a
  coarse particle, or in a run whose diffusion is weak, and stays inside the stable step.

The repair policy that acts on what these find (:data:`REPAIR`, :data:`WIDEN`, :data:`LEBESGUE_MAX` and the
gather limits) is :mod:`arpy.dcpse.domain`'s; its constants live here, beside the row tests they set.
"""

from __future__ import annotations

from typing import Callable, Protocol, Sequence, TypedDict

import numpy as np
import scipy.sparse as sp

from ..lists.neighborlist import row_blocks

__all__ = ["LEBESGUE_MAX", "MAX_GATHER", "MILD_GATHER", "MILD_LEBESGUE", "NO_REPAIR", "REPAIR", "Repair", "WIDEN",
           "WIDE_GATHER", "abs_row_sums", "bounded_apply", "lebesgue_constants", "weight_scales", "wild_rows"]

#: :func:`abs_row_sums` sums the rows of a matrix in blocks of about this many entries (its buffer).
ROW_SUM_BLOCK = 1 << 20
#: Repair rounds for failed stencils in a simulation.
WIDEN = 3
#: Rows whose Lebesgue constant exceeds this are rebuilt wider, then at order m - 1 (simulation policy).
LEBESGUE_MAX = 4.0


class Repair(TypedDict):
    """Keyword arguments of :class:`arpy.DomainDCPSE` (and :func:`arpy.field_resolution`) that set how
    stencils are repaired."""

    widen: int
    max_lebesgue: float | None


#: The repair policy of every DC-PSE operator of a simulation (keyword arguments of :class:`arpy.DomainDCPSE`).
REPAIR: Repair = {"widen": WIDEN, "max_lebesgue": LEBESGUE_MAX}
#: No repair: a failed row stays zero (the operators of the paper's rule, after
#: :func:`~arpy.dcpse.displace.displace_until_valid`).
NO_REPAIR: Repair = {"widen": 0, "max_lebesgue": None}
#: A wider gather holding more than MAX_GATHER x 1.5^d x (own neighbours) sources floods (see :mod:`arpy.dcpse.domain`).
MAX_GATHER = 4.0
#: Rows with Lebesgue constants in (MILD_LEBESGUE, max_lebesgue] are mildly wild; their wider gather
#: must hold at most MILD_GATHER x 1.5^d x (own neighbours) sources to replace them.
MILD_LEBESGUE = 2.5
MILD_GATHER = 2.0
#: With ``bounded`` interpolation, a widened row that gathered more than WIDE_GATHER times the median
#: row's sources is also held to the range of the nearest old values (see :meth:`arpy.DomainDCPSE.interpolate`).
WIDE_GATHER = 4


class _Interpolating(Protocol):
    def interpolation(self) -> sp.csr_matrix: ...


class _Derivatives(Protocol):
    @property
    def d(self) -> int: ...

    def laplacian(self) -> sp.csr_matrix: ...

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]: ...


def abs_row_sums(mat: sp.spmatrix) -> np.ndarray:
    """``sum_q |w_pq|`` for every row p of a sparse matrix, shape (n_rows,) (0 for an empty row).  Read
    from its arrays: scipy's abs() sorts a matrix's rows in place, which would change the order its
    rows are summed in (e.g. by key)."""
    m = mat if isinstance(mat, sp.csr_matrix) else sp.csr_matrix(mat)
    n, ptr = m.shape[0], m.indptr
    sums = np.zeros(n)
    # in blocks of whole rows of about ROW_SUM_BLOCK entries, each row's |w| summed by one reduceat
    # segment as over the whole matrix at once (the last row with a closing 0.0: reduceat takes the
    # index nnz of empty last rows); a block's trailing empty rows, starting at its end, are left out
    for first, last in row_blocks(ptr, ROW_SUM_BLOCK):
        a, b = int(ptr[first]), int(ptr[last])
        terms = np.abs(m.data[a:b]) if last < n else np.append(np.abs(m.data[a:b]), 0.0)
        starts = ptr[first:last] - a
        held = int(np.searchsorted(starts, terms.size))
        sums[first:first + held] = np.add.reduceat(terms, starts[:held])
    sums[ptr[:-1] == ptr[1:]] = 0.0                       # (reduceat gives an empty row one entry)
    return sums


def lebesgue_constants(op: _Interpolating) -> np.ndarray:
    """Per collocation point of an operator set (anything with ``interpolation()``), the sum of
    ``|interpolation weights|``, shape (n_col,): >= 1 for a consistent row; large values mean the
    stencil amplifies data errors."""
    return abs_row_sums(op.interpolation())


def weight_scales(op: _Derivatives, eps: np.ndarray, key: str | tuple[int, ...] = "laplacian") -> np.ndarray:
    """Per row of an operator of an operator set (anything with ``laplacian()`` and ``derivatives()``),
    the Laplacian by default or ``d^alpha`` (``key`` alpha), ``eps^|alpha| sum_q |w_pq|`` with eps
    (n_rows,) the rows' own core sizes: the weights in units of ``1 / eps^|alpha|``, shape (n_rows,)."""
    m = op.laplacian() if isinstance(key, str) else op.derivatives([key])[0]
    return abs_row_sums(m) * np.asarray(eps, dtype=np.float64) ** _order(key)


def wild_rows(op: _Derivatives, operators: Sequence[object] | None, max_sum: float,
              sums: Callable[[_Derivatives], np.ndarray] | None = None) -> np.ndarray | None:
    """Which rows of an operator set at the particles are wild, bool (n_rows,): those whose Laplacian
    has ``sum_q |L_pq| > max_sum`` (unit 1 / length^2: the Gershgorin radius of the row); None where
    nothing is weighed, a set without the Laplacian among its ``operators`` (None: the standard set,
    which has it; e.g. a monitor's gradient is not weighed).  The check assembles nothing.  ``sums(op)``:
    those sums (default :func:`abs_row_sums` of ``op.laplacian()``; e.g. kept for later use)."""
    if operators is not None and not any(isinstance(o, str) and o.lower() == "laplacian" for o in operators):
        return None
    return (abs_row_sums(op.laplacian()) if sums is None else sums(op)) > max_sum


def _order(key: str | tuple[int, ...]) -> int:
    """The order ``|alpha|`` of an operator's derivatives (the Laplacian: 2)."""
    return 2 if isinstance(key, str) else sum(key)


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
