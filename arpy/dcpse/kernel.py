"""DC-PSE operators on adaptive particles (Reboux et al. 2012, Appendix A).

Discretization-corrected particle strength exchange (DC-PSE) approximates a
derivative at a point x_p from values on nearby source particles q::

    (D f)(x_p) ~ sum_q  eta_q(x_p) f_q          off-particle form (Eqs. A.5, A.7)
    (D f)(x_p) ~ sum_q  eta_q(x_p) (f_q - f_p)  at source particles (Eq. A.8)

The kernel eta is a Gaussian-weighted polynomial whose coefficients make the
discrete moments match those of the derivative, so every polynomial of degree
< m (the order) is differentiated exactly.  The interpolating kernel (Eqs.
A.9-A.11) adds a quartic-spline correction so that it reproduces source values
exactly at the sources (Kronecker property).  Each collocation point's
moment matrix is assembled and factored (Cholesky) once in the Fortran core,
for all requested operators together: by the core's own loops up to 56
unknowns (m <= 10 in 2D, m <= 6 in 3D), in one fixed order on every
processor, and by LAPACK above.

Conventions: the core size eps_p of a collocation point scales offsets,
``z = (x_q - x_p) / eps_p``, and the Gaussian weight is ``exp(-c^2 |z|^2 / 2)`` with
c = 2 by default (the paper gives no value; c = 2 for eps = r_c keeps the
moment matrices well conditioned, cond ~ 1e3, with weight e^-4 at the
cutoff).  Neighbours: source q serves point p if ``|x_p - x_q| <= min(eps_p, eps_q)``
(the paper's eps = r_c), unless a NeighborList is given.
"""

from __future__ import annotations

from math import comb
from typing import Sequence, cast

import numpy as np
import scipy.sparse as sp

from .. import _bridge
from .._bridge import lengths_exponent, scaled
from .._codes import DCPSE_FORMS, DCPSE_OPERATORS, STENCIL_STATUS
from .._validate import as_cutoffs, as_positions, column_extremes
from ..domain import nearest
from ..lists.neighborlist import NeighborList, check_layout
from ..lists.search import cross_neighbor_list, near_box, neighbor_list

__all__ = ["DCPSE", "DEFAULT_C", "DEFAULT_MAX_COND", "DegenerateStencilError", "MAX_ORDER", "gradient_indices",
           "n_unknowns"]

#: Default Gaussian parameter c (for eps = r_c): see the module docstring.
DEFAULT_C = 2.0
#: Stencils whose moment matrix has a 1-norm condition number (upper bound) above this fail.
DEFAULT_MAX_COND = 1e12
#: Highest order m accepted: 78 unknowns per point in 2D, 364 in 3D.  Beyond it the
#: moment matrices of any practical stencil exceed DEFAULT_MAX_COND anyway.
MAX_ORDER = 12
_OP_DERIV, _OP_LAPLACIAN, _OP_INTERP = (DCPSE_OPERATORS[k] for k in ("derivative", "laplacian", "interpolation"))
_FORM_A, _FORM_B = DCPSE_FORMS["a"], DCPSE_FORMS["b"]


class DegenerateStencilError(ValueError):
    """Raised when some collocation points have no valid DC-PSE stencil.

    Attributes
    ----------
    points : int array
        Indices of the failing collocation points.
    status : int array
        Why each failed: 1 too few neighbours, 2 singular, 3 ill-conditioned.
    n_neighbors, cond : arrays
        Usable neighbours and condition number of each of those points.
    """

    def __init__(self, message: str, points: np.ndarray, status: np.ndarray, n_neighbors: np.ndarray,
                 cond: np.ndarray) -> None:
        super().__init__(message)
        self.points, self.status, self.n_neighbors, self.cond = points, status, n_neighbors, cond


class DCPSE:
    """DC-PSE operators from source particles to collocation points.

    Parameters
    ----------
    src_x : array (n_src, d)
        Source particle positions (d = 2 or 3).
    src_eps : float or array (n_src,)
        Core sizes (= cutoff radii) of the sources, same length unit.
    col_x : array (n_col, d) or None
        Collocation points.  None: the sources themselves, with the operators
        in the form of Eq. A.8, ``sum_q eta_q (f_q - f_p)`` (the usual choice for
        right-hand sides on particles).  Otherwise the off-particle form
        (old set -> new set), ``sum_q eta_q f_q``.
    col_eps : float or array (n_col,) or None
        Core sizes of the collocation points; default: that of the nearest source.
    order : int
        m: derivatives of order ``|alpha|`` are exact on polynomials of degree
        < m; convergence ``m - |alpha|`` (interpolation m, gradient m - 1,
        Laplacian m - 2).  m = 4 by default; 2 <= m <= :data:`MAX_ORDER`.
    neighbors : NeighborList or None
        Rows = collocation points, indices = sources.  Default: the min rule
        ``|x_p - x_q| <= min(eps_p, eps_q)``, via the AR cell lists, each row in ascending source
        order (:meth:`NeighborList.canonical`).  Moments and operator rows are summed in row order:
        lists in one canonical order give weights that do not depend on how the lists were built.
    c : float
        Gaussian weight parameter (finite, > 0).
    a : array (n_src,) or None
        Radii of the quartic-spline correction of the interpolating kernel;
        default half of each source's nearest-neighbour distance.
    max_cond : float
        Points whose moment matrix is worse conditioned fail (> 1, may be inf).
    strict : bool
        True: any failing point raises :class:`DegenerateStencilError` naming
        them.  False: their rows are zero and they are listed in ``failed``.
    operators : sequence or None
        The operators assembled at construction, with one factorisation per
        point: "laplacian", "interpolation" or multi-indices alpha.  None: the
        gradient, the Laplacian (order >= 3) and, off the sources, the
        interpolating kernel.  Any other operator is assembled (with a second
        factorisation) when first asked for; the weights do not depend on which
        operators share a factorisation.

    Attributes
    ----------
    n_neighbors : int array (n_col,)
        Usable neighbours per point.
    cond : float array (n_col,)
        1-norm condition number of each moment matrix (an upper bound, at most ~1.5-n times the
        true value).
    failed : int array
        Points without a valid stencil (``strict=False``).
    neighbors : NeighborList
        The lists used.

    Examples
    --------
    Operators of order 4 from 2000 random particles to 100 new points; they are exact on
    polynomials of degree < 4:

    >>> import numpy as np
    >>> import arpy
    >>> rng = np.random.default_rng(0)
    >>> src = rng.random((2000, 2))
    >>> eps = np.full(len(src), 4.0 / np.sqrt(len(src)))
    >>> new = 0.2 + 0.6 * rng.random((100, 2))
    >>> op = arpy.DCPSE(src, eps, new)
    >>> op.interpolation().shape
    (100, 2000)
    >>> def f(p):
    ...     return p[:, 0] ** 2 + p[:, 0] * p[:, 1]
    >>> bool(np.allclose(op.interpolation() @ f(src), f(new)))
    True
    >>> bool(np.allclose(op.laplacian() @ f(src), 2.0))
    True
    >>> d_dx, d_dy = op.gradient()
    >>> bool(np.allclose(d_dy @ f(src), new[:, 0]))
    True

    At the particles themselves (``col_x=None``), in the form ``sum_q eta_q (f_q - f_p)``:

    >>> at = arpy.DCPSE(src, eps)
    >>> bool(np.allclose(at.laplacian() @ f(src), 2.0))
    True
    """

    def __init__(self, src_x: np.ndarray, src_eps: float | np.ndarray, col_x: np.ndarray | None = None,
                 col_eps: float | np.ndarray | None = None, *, order: int = 4,
                 neighbors: NeighborList | None = None, c: float = DEFAULT_C, a: float | np.ndarray | None = None,
                 max_cond: float = DEFAULT_MAX_COND, strict: bool = True,
                 operators: Sequence[object] | None = None) -> None:
        self.src_x = as_positions(src_x)
        n_src, d = self.src_x.shape
        if n_src == 0:
            raise ValueError("DCPSE needs at least one source particle")
        self.src_eps = as_cutoffs(src_eps, n_src)
        if isinstance(order, (bool, np.bool_)) or not isinstance(order, (int, np.integer)) \
                or not 2 <= order <= MAX_ORDER:
            raise ValueError(f"order must be an integer in [2, {MAX_ORDER}], got {order!r}")
        c, max_cond = float(c), float(max_cond)
        if not (np.isfinite(c) and c > 0):
            raise ValueError(f"the Gaussian parameter c must be a finite number > 0, got {c}")
        if not max_cond > 1:
            raise ValueError(f"max_cond must be a number > 1 (inf: no limit), got {max_cond}")
        self.order, self.d, self.n_src = int(order), d, n_src
        self.c, self.max_cond, self.strict = c, max_cond, bool(strict)
        self.at_sources = col_x is None
        if col_x is None:
            if col_eps is not None:
                raise ValueError("col_eps is only meaningful with col_x")
            self.col_x, self.col_eps = self.src_x, self.src_eps
        else:
            self.col_x = as_positions(col_x)
            if self.col_x.shape[1] != d:
                raise ValueError(f"collocation points must have d = {d} columns, got {self.col_x.shape}")
            bad = np.flatnonzero(~np.all(np.isfinite(self.col_x), axis=1))
            if bad.size:
                raise ValueError(f"DCPSE: position of collocation point {bad[0]} is not finite (NaN or Inf)")
            if col_eps is None:
                _, near = nearest(self.src_x, y=self.col_x)
                self.col_eps = self.src_eps[near]
            else:
                self.col_eps = as_cutoffs(col_eps, self.col_x.shape[0])
        self.n_col = self.col_x.shape[0]
        if not self.at_sources:
            bad = np.flatnonzero(~(np.isfinite(self.col_eps) & (self.col_eps > 0)))
            if bad.size:
                raise ValueError(f"DCPSE: core size of collocation point {bad[0]} is not a finite positive number")
        self.neighbors = self._neighbors(neighbors)
        self._a = None if a is None else as_cutoffs(a, n_src)
        self._ops: dict[object, np.ndarray] = {}
        self._diag: dict[object, np.ndarray] = {}
        self._mats: dict[object, sp.csr_matrix] = {}
        if operators is None:       # one factorisation for the standard set: gradient, Laplacian, interpolation
            standard: list[object] = list(gradient_indices(d))
            if self.order >= 3:
                standard.append("laplacian")
            if not self.at_sources:
                standard.append("interpolation")
            operators = standard
        keys = [self._check(op) for op in operators]
        # at the sources the interpolating kernel is the identity: nothing to assemble
        self._compute([k for k in dict.fromkeys(keys) if not (k == "interpolation" and self.at_sources)])

    def __repr__(self) -> str:
        form = "at the sources" if self.at_sources else f"{self.n_col} collocation points"
        return (f"DCPSE(order={self.order}, d={self.d}, {self.n_src} sources, {form}, "
                f"{len(self.neighbors)} neighbour entries, {self.failed.size} failed)")

    # ------------------------------------------------------------ set-up
    def _neighbors(self, neighbors: NeighborList | None) -> NeighborList:
        """The given lists, or the default ones with each row ascending (:meth:`NeighborList.canonical`):
        moments and operator rows are summed in row order."""
        if neighbors is None:
            if self.at_sources:
                return neighbor_list(self.src_x, self.src_eps, method="auto", full=True).canonical()
            return cross_neighbor_list(self.col_x, self.col_eps, self.src_x, self.src_eps).canonical()
        if not isinstance(neighbors, NeighborList):
            raise TypeError("neighbors must be an arpy.NeighborList (rows = collocation points)")
        if neighbors.n != self.n_col:
            raise ValueError(f"neighbors has {neighbors.n} rows, expected one per collocation point ({self.n_col})")
        if not neighbors.full and len(neighbors):
            raise ValueError("DC-PSE needs every neighbour in every row: pass a full (full=True) list")
        if len(neighbors) and (neighbors.indices.min() < 0 or neighbors.indices.max() >= self.n_src):
            raise ValueError("neighbors indices must index the source particles")
        check_layout(neighbors, self.n_src, "DCPSE")
        return neighbors

    @property
    def a(self) -> np.ndarray:
        """Quartic-spline radii of the interpolating kernel (n_src,)."""
        if self._a is None:
            if self.n_src < 2:
                raise ValueError("the interpolating kernel needs at least two sources (for its default radii)")
            self._a = self._half_spacing(np.arange(self.n_src))
        return self._a

    def _half_spacing(self, which: np.ndarray) -> np.ndarray:
        """Half the distance from each of the sources ``which`` to the nearest other source: the
        default spline radius.  For a few of many sources, the search runs over those within the
        largest of their core sizes of their bounding box; a source whose nearest other one lies
        farther (its distance above that reach, less a margin over rounding) is searched again over
        all of them: the distances are those of the whole set."""
        points = self.src_x[which]
        dist = np.zeros(which.size)
        again = np.arange(which.size)
        if which.size and 2 * which.size < self.n_src:
            reach = float(self.src_eps[which].max())
            near = near_box(self.src_x, *column_extremes(points), reach)
            if 2 * near.size < self.n_src:
                found = nearest(self.src_x[near], 2, y=points)[0][:, 1] if near.size >= 2 else np.full(
                    which.size, np.inf)
                sure = found * (1.0 + 1e-6) <= reach
                dist[sure] = found[sure]
                again = np.flatnonzero(~sure)
        if again.size:
            dist[again] = nearest(self.src_x, 2, y=points[again])[0][:, 1]
        if np.any(dist <= 0):
            raise ValueError("coincident source particles: the interpolating kernel is undefined")
        return 0.5 * dist

    def _radii(self, nl: NeighborList) -> np.ndarray:
        """The spline radii the rows of ``nl`` read: :attr:`a` when it is known or most sources
        are read; else only the sources read (a few repaired rows), the others set to the smallest
        of those (never read; they keep the lengths' range that of the radii read)."""
        if self._a is not None:
            return self._a
        used = np.flatnonzero(np.bincount(nl.indices, minlength=self.n_src))
        if 2 * used.size >= self.n_src or self.n_src < 2:
            return self.a
        a = np.ones(self.n_src)
        if used.size:
            read = self._half_spacing(used)
            a[:] = read.min()
            a[used] = read
        return a

    @staticmethod
    def _key(op) -> object:
        if isinstance(op, str):
            name = op.lower()
            if name not in ("laplacian", "interpolation"):
                raise ValueError(f"unknown operator {op!r}")
            return name
        return tuple(int(v) for v in op)

    def _check(self, op) -> object:
        """The key of an operator this DCPSE can build (ValueError naming what is wrong)."""
        key = self._key(op)
        if key == "laplacian" and self.order < 3:
            raise ValueError("the Laplacian needs order >= 3")
        if isinstance(key, tuple):
            if len(key) != self.d or min(key) < 0:
                raise ValueError(f"alpha must be {self.d} non-negative integers, got {key}")
            if sum(key) >= self.order:
                raise ValueError(f"|alpha| = {sum(key)} must be below the order m = {self.order}")
            if self.at_sources and sum(key) == 0:
                raise ValueError("alpha = 0 at the source particles is the identity; use interpolation()")
        return key

    def _compute(self, ops: Sequence[object]) -> None:
        """Assemble and factor every point once; weights of all `ops`."""
        kinds, alphas = [], []
        for op in ops:
            if op == "laplacian":
                kinds.append(_OP_LAPLACIAN)
                alphas.append((0,) * self.d)
            elif op == "interpolation":
                kinds.append(_OP_INTERP)
                alphas.append((0,) * self.d)
            else:
                kinds.append(_OP_DERIV)
                alphas.append(op)
        nl = self.neighbors
        a = self._radii(nl) if _OP_INTERP in kinds else np.ones(self.n_src)
        # lengths reach the core scaled by 2**k where they must (see lengths_exponent); a weight of
        # a derivative of order |alpha| scales as length**-|alpha|: times 2**(k |alpha|) back
        # (points without sources need no offsets: their lengths are left out, and 0 and 1 sent)
        lonely = nl.stored_counts() == 0
        some_lonely = bool(lonely.any())
        col_x, col_eps = self.col_x, self.col_eps
        held = ~lonely if some_lonely else slice(None)        # (all of them: views, not copies)
        k = lengths_exponent([self.src_x, col_x[held]], [self.src_eps, col_eps[held], a])
        if self.n_col == 0:
            data, diag = np.zeros((0, len(ops))), np.zeros((0, len(ops)))
            nnb, rcond, status = np.zeros(0, np.int32), np.zeros(0), np.zeros(0, np.int32)
        else:
            src_x, a, col_x, col_eps = (scaled(k, v) for v in (self.src_x, a, col_x, col_eps))
            if some_lonely:
                col_x, col_eps = np.array(col_x), np.array(col_eps)      # (copies: these are changed)
                col_x[lonely], col_eps[lonely] = 0.0, 1.0
            data, diag, nnb, rcond, status = _bridge.dcpse(
                src_x, a, col_x, col_eps, nl.offsets, nl.indices, self.order, self.c,
                _FORM_B if self.at_sources else _FORM_A, kinds, alphas, self.max_cond, context="DCPSE")
        if k:
            ords = np.array([2 if kd == _OP_LAPLACIAN else sum(al) for kd, al in zip(kinds, alphas)])
            with np.errstate(over="ignore"):          # reported when such an operator is asked for
                data, diag = np.ldexp(data, k * ords), np.ldexp(diag, k * ords)
        self.n_neighbors = nnb
        with np.errstate(divide="ignore"):
            self.cond = np.where(rcond > 0, 1.0 / rcond, np.inf)
        failed = np.flatnonzero(status)
        self.failed = failed
        self.widened = np.zeros(0, dtype=np.int64)      # rows rebuilt on wider stencils (arpy.dcpse.domain)
        if failed.size and self.strict:
            counts = {name: int(np.sum(status[failed] == code)) for code, name in STENCIL_STATUS.items()}
            listed = ", ".join(f"{p} ({STENCIL_STATUS[int(status[p])]}, {nnb[p]} neighbours, cond {self.cond[p]:.2g})"
                               for p in failed[:10])
            need = n_unknowns(self.d, self.order, self.at_sources)
            raise DegenerateStencilError(
                f"DC-PSE: {failed.size} of {self.n_col} collocation points have no valid stencil "
                f"({', '.join(f'{v} {k}' for k, v in counts.items() if v)}; {need} unknowns need at least "
                f"{need} neighbours in general position): {listed}{' ...' if failed.size > 10 else ''}",
                failed, status[failed], nnb[failed], self.cond[failed])
        for i, op in enumerate(ops):
            self._ops[op] = data[:, i]
            self._diag[op] = diag[:, i]

    def _matrix(self, op) -> sp.csr_matrix:
        """The operator as a CSR matrix (built once per operator, cached; its raw weights are then
        dropped: the matrix holds them)."""
        key = self._key(op)
        if key not in self._mats:
            if key not in self._ops:
                self._compute([key])
            if not (np.all(np.isfinite(self._ops[key])) and np.all(np.isfinite(self._diag[key]))):
                raise ValueError(f"DCPSE: the weights of operator {key!r} overflow the double range at these "
                                 f"length scales (core sizes down to {self.col_eps.min():.3g}); rescale the "
                                 "coordinates")
            nl = self.neighbors
            shape = (self.n_col, self.n_src)
            # scipy may reorder its arrays in place: the list's arrays are copied, the weights its own
            mat = sp.csr_matrix((np.ascontiguousarray(self._ops.pop(key)), nl.indices.copy(), nl.offsets.copy()),
                                shape=shape)
            diag = self._diag.pop(key)
            if self.at_sources:
                mat = (mat + sp.csr_matrix((diag, (np.arange(self.n_col), np.arange(self.n_col))), shape=shape)).tocsr()
            self._mats[key] = mat
        return self._mats[key]

    # ------------------------------------------------------------ operators
    def derivative(self, alpha: Sequence[int]) -> sp.csr_matrix:
        """The operator d^alpha (multi-index of d non-negative ints, ``|alpha| < order``), (n_col, n_src).

        Unit: ``length^-|alpha|``.  At source particles ``|alpha| >= 1``.
        """
        return self.derivatives([alpha])[0]

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]:
        """The operators d^alpha of several multi-indices (see :meth:`derivative`),
        those not yet built assembled in one factorisation per point."""
        keys = [self._check(tuple(alpha)) for alpha in alphas]
        missing = [k for k in dict.fromkeys(keys) if k not in self._ops and k not in self._mats]
        if missing:
            self._compute(missing)
        return [self._matrix(k) for k in keys]

    def gradient(self) -> list[sp.csr_matrix]:
        """The d first-derivative operators [d/dx_1, ..., d/dx_d]."""
        return self.derivatives(gradient_indices(self.d))

    def laplacian(self) -> sp.csr_matrix:
        """The Laplacian (Eq. A.6), unit length^-2; needs order >= 3."""
        return self._matrix(self._check("laplacian"))

    def interpolation(self) -> sp.csr_matrix:
        """The interpolating kernel zeta (Eqs. A.9-A.11): source values -> collocation points.

        Exact on polynomials of degree < order and equal to the source value at a
        source position.  At the sources themselves it is the identity.
        """
        if self.at_sources:
            return sp.identity(self.n_src, format="csr")
        return self._matrix("interpolation")

    def apply(self, op: str | Sequence[int], f: np.ndarray) -> np.ndarray:
        """Apply an operator ("laplacian", "interpolation" or a multi-index) to values f (n_src[, k])."""
        key = self._key(op)
        mat = self.interpolation() if key == "interpolation" else (
            self.laplacian() if key == "laplacian" else self.derivative(cast(Sequence[int], key)))
        return mat @ np.asarray(f, dtype=np.float64)


def gradient_indices(d: int) -> list[tuple[int, ...]]:
    """The multi-indices of the d first derivatives, d/dx_1 .. d/dx_d."""
    return [tuple(int(i == j) for j in range(d)) for i in range(d)]


def n_unknowns(d: int, m: int, at_sources: bool) -> int:
    """Unknowns of a DC-PSE stencil of order m in d dimensions: the monomials of degree < m, less the
    constant one in the at-particle form (which differences f_q - f_p)."""
    return comb(m - 1 + d, d) - int(at_sources)
