r"""Pure-NumPy reference implementation of (interpolating) DC-PSE operators.

This module implements the discretization-corrected particle strength exchange
(DC-PSE) operators of Reboux, Schrader & Sbalzarini, *A self-organizing
Lagrangian particle method for adaptive-resolution advection-diffusion
simulations*, J. Comput. Phys. 231 (2012), §2.2 and Appendices A and B
(equation numbers below refer to that paper).  It exists to cross-validate the
Fortran DC-PSE assembly of ``arpy``; it favours clarity and a faithful,
fully documented formulation over speed (it is nevertheless batched over
collocation points grouped by neighbour count: 5000 points take about 0.5 s
in 2D and about 1 s in 3D, m = 4).

Vocabulary
----------
*source particles* ``src_x`` (n_src, d) carry the function values ``f``.
*collocation points* ``col_x`` (n_col, d) are where an operator is evaluated.
The caller supplies, for every collocation point ``p``, its neighbour list in
CSR form: the sources ``indices[offsets[p]:offsets[p+1]]`` (typically all
``q`` with ``|x_p - x_q| <= r_c,p``).  All lengths are in the caller's length
unit; ``col_eps`` (n_col,) is the core size ε_p in the same unit.  An operator
of derivative order ``|α|`` has weights in unit ``length^-|α|``.

Output: weights ``data`` aligned with ``indices`` (one array per operator), so
that the discrete operator is

* form (a), "off-particle" / vanishing zeroth moment (Eqs. A.5, A.7)::

      (L f)_p = Σ_k data[k] · f[indices[k]],        k in offsets[p]:offsets[p+1]

* form (b), "at source particles" / general DC-PSE (Eqs. A.8, B.10)::

      (L f)_p = Σ_k data[k] · (f[indices[k]] − f[p])
              = Σ_k data[k] · f[indices[k]] + diag[p] · f[p],
      diag[p] = −Σ_k data[k]   (computed explicitly, not assumed).

  In form (b) collocation point p *is* source particle s = col_src[p]
  (default col_src = arange(n_src); a subset, e.g. real particles without
  their ghosts, is allowed), and "f[p]" above means f[col_src[p]].  The self
  entry q == s, if the caller's list contains it, gets weight exactly 0 (see
  below), so the lists may or may not contain the particle itself.

:meth:`DCPSEWeights.matrix` returns ``scipy.sparse.csr_matrix`` (n_col × n_src):
``L = csr((data, indices, offsets))`` plus, in form (b), ``diag[p]`` at
(p, col_src[p]); duplicates are summed.

Formulation (Appendix A)
------------------------
Multi-indices.  For order of accuracy m (≥ 2) the basis is the complete set of
monomials ``z^k = z_1^k_1 ⋯ z_d^k_d`` with ``|k| < m`` (m = 4: 10 monomials in 2D, 20
in 3D, equal to N* of §2.3.4).  Ordering: see :func:`monomial_exponents`
(graded, then lexicographically descending, e.g. 2D: 1, x, y, x², xy, y², …).
(The text after Eq. A.1 writes ``|k| ≤ m`` and Eq. B.7 "a polynomial of degree m";
the moment conditions of Eq. A.2 are ``|k| < m``, and a square system needs the
basis to match them: degree < m.)

Scaled offsets.  For collocation point x_p with core size ε_p and neighbour q::

      z_pq = (x_q − x_p) / ε_p                      (Eqs. A.2, B.9)

(offset *from the collocation point to the source*, scaled by the
collocation point's ε).

Weight function.  w(r) = exp(−c² r² / 2) (text below Eq. A.1), applied to
``r = |z_pq|``.  The kernel carries w², i.e. ``exp(−c²|z|²) = exp(−|c z|²)``, which is
the Gaussian of Eq. B.7.  The paper gives no numerical value of c; see
``DEFAULT_C`` for the default chosen here and why.

Kernel.   ``φ(x_q; x_p) = w²(|z_pq|) · p(z_pq) · c_p``          (Eq. A.1)
with p(z) the row vector of monomials and c_p the coefficient column vector.

Moment conditions (Eq. A.2):  ``Σ_q z_pq^k φ(x_q; x_p) = b_k``  for ``|k| < m``,
i.e. the linear system (Eq. A.3)::

      A_p c_p = b,     A_p = (W_p V_p)ᵀ (W_p V_p),

with V_p[q, k] = z_pq^k (scaled Vandermonde matrix, one row per neighbour, one
column per monomial) and ``W_p = diag(w(|z_pq|))``.  A_p is symmetric positive
definite iff W_p V_p has full column rank; it is solved here exactly as the
Fortran code will: explicit A_p, Cholesky factor A_p = L Lᵀ, two triangular
solves.  Mathematically, φ = W² V (VᵀW²V)⁻¹ b is the minimum-norm solution of
the moment conditions in the norm Σ_q φ_q² / w_q².

Right-hand side for a derivative ∂^α (Eq. A.4):  ``b = ∂^α p(z)|_{z=0}``, i.e.::

      b_k = α! δ_{k,α},       α! = α_1! ⋯ α_d!.

Then by Taylor expansion ``f(x_q) = Σ_k ε_p^{|k|} z_pq^k ∂^k f(x_p) / k!``, and::

      ∂^α f(x_p) ≈ ε_p^{−|α|} Σ_q f_q φ(x_q; x_p)                 (Eq. A.5)

The reported weights are ``data = ε_p^{−|α|} φ(x_q; x_p)``.

About the ``(−1)^{|α|} α!`` of Eq. B.4:  Appendix B (following the original DC-PSE
paper) writes the moment condition as ``Z^k = (−1)^{|α|} α! δ_{k,α}``.  That sign
belongs to the *opposite* offset convention z' = (x_p − x_q)/ε_p = −z: since
``z'^k = (−1)^{|k|} z^k``, the system in z' is A' = S A S, b' = S b with
``S = diag((−1)^{|k|})``, whose solution gives the *same* kernel values.  Using
``(−1)^{|α|} α!`` together with z = (x_q − x_p)/ε (as Eqs. B.4 and B.9 literally
combine) flips the sign of every odd-order derivative; we use the consistent
pair (z = (x_q − x_p)/ε, b_k = α! δ_{k,α}).  A test checks the equivalence.

Laplacian (Eqs. A.6, A.7):  ``b = Δp(z)|_{z=0}``: b_k = 2 for k = 2e_i, i = 1..d,
0 otherwise, and ∆f(x_p) ≈ ε_p^{−2} Σ_q f_q φ(x_q; x_p).

Gradient: the d operators α = e_i (b_k = δ_{k,e_i}), scaled by ε_p^{−1}.  (The
paper's alternative "∇_h f(x_q) = ε^{−2} Σ_p f_p (x_q − x_p) η_q(x_p)" built from
the Laplacian kernel is, with the kernel of Eq. A.7, equal to −2∇f + O(h²), i.e.
it is missing a factor −1/2 and is only of order m − 2; it is not used.)

Form (a): vanishing zeroth moment (b_0 = 0 for every derivative, ``|α| ≥ 1``; the
text below Eq. A.2).  Only f_q of the neighbours enter, so the operator can be
evaluated at any point x_p, also between particles (old set → new set).

Form (b): general DC-PSE at source particles (Eq. A.8, Eqs. B.5–B.11): the
zeroth moment is *free*.  We realize this by removing the constant monomial
from both the kernel polynomial and the moment conditions (basis ``1 ≤ |k| < m``,
N − 1 unknowns); then ``Σ_q (f_q − f_p) φ_q = ε^{|α|} ∂^α f + O(ε^m)`` (Eq. B.5), and
the −f_p term is the diagonal diag[p] = −Σ_q data_pq.  Every basis monomial
vanishes at z = 0, so a self entry contributes nothing to A and has weight 0.
(If instead one kept b_0 = 0 as the phrase "with the same η_p as in Eq. (A.7)"
suggests, Σ_q (f_q − f_p) φ_q would equal Σ_q f_q φ_q identically, i.e. form
(a); that choice is available simply as ``at_sources=False``.)

Interpolating kernel (Eqs. A.9–A.11, form (a) only)::

      ζ_q(x_p) = φ(x_q; x_p) + ζ̂_q(x_p),     ζ̂_q(x) = ϕ̂(|x − x_q| / a_q),

with ϕ̂ the quartic spline of unit support (as in RKPM / Wang et al.)

      ϕ̂(r) = 1 − 6r² + 8r³ − 3r⁴  for 0 ≤ r ≤ 1,   0 for r > 1,

(ϕ̂(0) = 1, ϕ̂(1) = ϕ̂'(1) = ϕ̂''(1) = 0, ϕ̂'(0) = 0) and a_q < distance from
source q to its nearest other source (default a_q = 0.5 × that distance), so
ϕ̂((x_s − x_q)/a_q) = δ_sq.  φ solves A_p c_p = b with (Eq. A.10)

      b = p(0) − Σ_q p(z_pq) ζ̂_q(x_p),    p(0) = e_0 (the constant monomial),

using the *same* A_p as the derivative operators of form (a) and the same z
as the moments (Eq. A.10 prints p((x − x_q)/ε) = p(−z): that opposite sign is
inconsistent with Eq. A.2 for odd monomials; the consistent sign is used).  Then
``Σ_q z_pq^k ζ_q(x_p) = δ_{k,0}`` for ``|k| < m`` (polynomial reproduction), and when
x_p coincides with source s, b = 0 exactly, φ ≡ 0 and ζ_q(x_s) = δ_sq exactly.
The caller's list must contain every source q with ``|x_p − x_q| < a_q`` (always
true when r_c ≥ nearest-neighbour distance, e.g. a list with ``|x_p − x_q| ≤ r_c``).

Degenerate stencils: a point with fewer usable neighbours than unknowns, or
with cond₂(A_p) > ``max_cond``, makes :func:`dcpse_weights` raise ValueError
naming how many and which collocation points (cond₂ is evaluated exactly from
the singular values of W_p V_p: cond₂(A) = (σ_max/σ_min)²).

Error behaviour (Appendix B, Eqs. 2.5, 2.7, B.12): with ε_p ∝ h_p the
interpolant has error O(h^m) and ∂^α has ``O(h^{m−|α|})``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .dcpse_basis import (DEFAULT_A_FACTOR, DEFAULT_C, DEFAULT_MAX_COND, OperatorSpec, monomial_exponents,
                          nearest_neighbour_distance, normalize_op, op_order, quartic_spline, rhs)

__all__ = ["DCPSEWeights", "moment_matrices", "dcpse_weights"]


@dataclass
class DCPSEWeights:
    """Kernel weights of one or more DC-PSE operators on a CSR neighbour list.

    Attributes
    ----------
    data : ndarray, shape (n_ops, nnz)
        ``data[i, k]`` is the weight of source ``indices[k]`` in operator ``i``
        (unit ``length^-|alpha|``).
    diag : ndarray, shape (n_ops, n_col)
        Weight of the collocation particle itself: ``-sum_k data[i, k]`` over
        its row in form (b); zeros in form (a).
    offsets, indices : ndarray
        The caller's CSR neighbour list (int64 copies).
    n_src : int
        Number of source particles (column count of the matrices).
    ops : list
        Normalized operator specs (tuples or strings), one per row of ``data``.
    at_sources : bool
        True for form (b).
    n_neighbours : ndarray, shape (n_col,)
        Usable neighbours per point (form (b): excluding zero offsets).
    cond : ndarray, shape (n_col,)
        cond_2(A_p) per collocation point.
    a : ndarray (n_src,) or None
        Quartic-spline radii a_q used for ``"interp"``.
    col_src : ndarray (n_col,) or None
        Form (b): source index of each collocation point (the column of the
        diagonal term).
    """

    data: np.ndarray
    diag: np.ndarray
    offsets: np.ndarray
    indices: np.ndarray
    n_src: int
    ops: list
    at_sources: bool
    n_neighbours: np.ndarray
    cond: np.ndarray
    a: np.ndarray | None = field(default=None)
    col_src: np.ndarray | None = field(default=None)

    def matrix(self, i: int = 0) -> sp.csr_matrix:
        """Operator ``i`` as a csr_matrix of shape (n_col, n_src)."""
        n_col = self.offsets.size - 1
        mat = sp.csr_matrix(
            (self.data[i].copy(), self.indices.copy(), self.offsets.copy()),
            shape=(n_col, self.n_src),
        )
        if self.at_sources:
            mat = mat + sp.csr_matrix(
                (self.diag[i], (np.arange(n_col), self.col_src)), shape=(n_col, self.n_src))
        mat = sp.csr_matrix(mat)
        mat.sum_duplicates()
        return mat

    def apply(self, f: npt.ArrayLike, i: int = 0) -> np.ndarray:
        """Evaluate operator ``i`` on source values ``f`` (n_src,) -> (n_col,)."""
        f = np.asarray(f, dtype=np.float64)
        rows = np.repeat(np.arange(self.offsets.size - 1), np.diff(self.offsets))
        out = np.bincount(rows, weights=self.data[i] * f[self.indices],
                          minlength=self.offsets.size - 1)
        if self.at_sources:
            out = out + self.diag[i] * f[self.col_src]
        return out


# --------------------------------------------------------------------------
# small building blocks
# --------------------------------------------------------------------------

def _check_inputs(src_x, col_x, col_eps, offsets, indices, at_sources, col_src=None):
    src_x = np.ascontiguousarray(src_x, dtype=np.float64)
    if src_x.ndim != 2 or src_x.shape[1] < 1:
        raise ValueError(f"src_x must have shape (n_src, d), got {src_x.shape}")
    n_src, d = src_x.shape
    if not at_sources and col_src is not None:
        raise ValueError("col_src is only meaningful with at_sources=True (form (b))")
    if at_sources:
        if col_src is None:
            col_src = np.arange(n_src, dtype=np.int64)
        col_src = np.asarray(col_src)
        if col_src.ndim != 1 or not (np.issubdtype(col_src.dtype, np.integer)
                                     or col_src.size == 0):
            raise ValueError("col_src must be a 1-D integer array of source indices")
        col_src = col_src.astype(np.int64)
        if col_src.size and (col_src.min() < 0 or col_src.max() >= n_src):
            raise ValueError(f"col_src must lie in [0, {n_src})")
        if col_x is not None:
            col_x = np.asarray(col_x, dtype=np.float64)
            if col_x.shape != (col_src.size, d) or not np.array_equal(col_x, src_x[col_src]):
                raise ValueError("at_sources=True (form (b)) requires the collocation points "
                                 "to be source particles: pass col_x=None (and col_src, the "
                                 "source index of each collocation point, default all)")
        col_x = src_x[col_src]
    if col_x is None:
        raise ValueError("col_x is required unless at_sources=True")
    col_x = np.ascontiguousarray(col_x, dtype=np.float64)
    if col_x.ndim != 2 or col_x.shape[1] != d:
        raise ValueError(f"col_x must have shape (n_col, {d}), got {col_x.shape}")
    n_col = col_x.shape[0]
    col_eps = np.ascontiguousarray(col_eps, dtype=np.float64)
    if col_eps.shape != (n_col,):
        raise ValueError(f"col_eps must have shape ({n_col},), got {col_eps.shape}")
    if not (np.all(np.isfinite(src_x)) and np.all(np.isfinite(col_x))):
        raise ValueError("positions contain NaN or inf")
    if not np.all(np.isfinite(col_eps)) or np.any(col_eps <= 0):
        bad = np.flatnonzero(~(np.isfinite(col_eps) & (col_eps > 0)))
        raise ValueError(f"col_eps must be finite and > 0; {bad.size} bad entries, "
                         f"e.g. at indices {bad[:10].tolist()}")
    offsets = np.asarray(offsets)
    indices = np.asarray(indices)
    if offsets.shape != (n_col + 1,) or not np.issubdtype(offsets.dtype, np.integer):
        raise ValueError(f"offsets must be an integer array of shape ({n_col + 1},), "
                         f"got {offsets.dtype} {offsets.shape}")
    if indices.ndim != 1 or not (np.issubdtype(indices.dtype, np.integer) or indices.size == 0):
        raise ValueError("indices must be a 1-D integer array")
    offsets = offsets.astype(np.int64)
    indices = indices.astype(np.int64)
    if offsets[0] != 0 or offsets[-1] != indices.size or np.any(np.diff(offsets) < 0):
        raise ValueError("offsets must start at 0, be non-decreasing and end at len(indices)")
    if indices.size and (indices.min() < 0 or indices.max() >= n_src):
        raise ValueError(f"indices must lie in [0, {n_src})")
    return src_x, col_x, col_eps, offsets, indices, col_src


# --------------------------------------------------------------------------
# batched assembly
# --------------------------------------------------------------------------

def _chunks(counts: np.ndarray, n_mono: int, budget: int = 2_000_000):
    """Yield groups of collocation indices sorted by neighbour count, sized so
    that a padded (n, K, n_mono) block has about `budget` entries."""
    order = np.argsort(counts, kind="stable")
    start = 0
    n = order.size
    while start < n:
        kmax = max(int(counts[order[min(n - 1, start)]]), 1)
        # grow the chunk while the padded size stays within budget
        size = max(1, budget // (kmax * n_mono))
        stop = min(n, start + size)
        kmax = max(int(counts[order[stop - 1]]), 1)
        size = max(1, budget // (kmax * n_mono))
        stop = min(stop, start + size)
        yield order[start:stop]
        start = stop


def _assemble(src_x, col_x, col_eps, offsets, indices, exps, c, rows):
    """Padded scaled offsets, weights and Vandermonde rows for collocation rows.

    Returns pos (n, K) CSR positions (clipped), mask (n, K), z (n, K, d),
    w (n, K) = ``w(|z|)`` (0 on padding), V (n, K, n_mono).
    """
    counts = offsets[rows + 1] - offsets[rows]
    K = max(int(counts.max()) if counts.size else 0, 1)
    ar = np.arange(K)
    mask = ar[None, :] < counts[:, None]
    pos = offsets[rows][:, None] + ar[None, :]
    pos = np.where(mask, pos, 0 if indices.size == 0 else np.minimum(pos, indices.size - 1))
    nb = indices[pos] if indices.size else np.zeros_like(pos)
    z = (src_x[nb] - col_x[rows][:, None, :]) / col_eps[rows][:, None, None]
    z[~mask] = 0.0
    r2 = np.einsum("nkd,nkd->nk", z, z)
    w = np.exp(-0.5 * c * c * r2) * mask
    # monomials via a power table P[..., i, e] = z_i^e (repeated products, no pow)
    deg = int(exps.max()) + 1 if exps.size else 1
    zt = np.moveaxis(z, 2, 0)                      # (d, n, K)
    P = np.empty((deg,) + zt.shape)                # (deg, d, n, K)
    P[0] = 1.0
    for e in range(1, deg):
        P[e] = P[e - 1] * zt
    Vt = P[exps[:, 0], 0]                          # (N, n, K)
    for i in range(1, z.shape[2]):
        Vt = Vt * P[exps[:, i], i]
    V = np.ascontiguousarray(np.moveaxis(Vt, 0, 2))  # (n, K, N)
    return pos, mask, z, w, V, r2


def moment_matrices(
    src_x: npt.ArrayLike,
    col_x: npt.ArrayLike | None,
    col_eps: npt.ArrayLike,
    offsets: npt.ArrayLike,
    indices: npt.ArrayLike,
    order: int = 4,
    c: float = DEFAULT_C,
    at_sources: bool = False,
    col_src: npt.ArrayLike | None = None,
) -> np.ndarray:
    """The moment matrices A_p = (W_p V_p)^T (W_p V_p) of Eq. (A.3).

    Dimensionless, shape (n_col, n_mono, n_mono) with the basis of
    :func:`monomial_exponents` (form (b): without the constant monomial, i.e.
    rows/columns 1: of that basis).  Intended for cross-validating the Fortran
    assembly step.
    """
    src_x, col_x, col_eps, offsets, indices, col_src = _check_inputs(
        src_x, col_x, col_eps, offsets, indices, at_sources, col_src)
    exps = monomial_exponents(src_x.shape[1], order)
    if at_sources:
        exps = exps[1:]
    n_col = col_x.shape[0]
    out = np.zeros((n_col, exps.shape[0], exps.shape[0]))
    counts = np.diff(offsets)
    for rows in _chunks(counts, exps.shape[0]):
        _, _, _, w, V, _ = _assemble(src_x, col_x, col_eps, offsets, indices, exps, c, rows)
        WV = w[:, :, None] * V
        out[rows] = np.matmul(WV.transpose(0, 2, 1), WV)
    return out


def _fmt_points(idx: np.ndarray, extra: dict[str, np.ndarray], limit: int = 20) -> str:
    parts = []
    for j in range(min(limit, idx.size)):
        desc = ", ".join(f"{k}={v[j]:.3g}" if isinstance(v[j], (float, np.floating))
                         else f"{k}={v[j]}" for k, v in extra.items())
        parts.append(f"{int(idx[j])} ({desc})")
    more = "" if idx.size <= limit else f", ... ({idx.size - limit} more)"
    return "; ".join(parts) + more


def _spline_radii(src_x: np.ndarray, a: npt.ArrayLike | None, a_factor: float) -> np.ndarray:
    """Radii a_q of the quartic-spline correction of the interpolating kernel (Eq. A.11): given, or
    ``a_factor`` times each source's nearest-neighbour distance."""
    n_src = src_x.shape[0]
    if a is None:
        if not (0 < a_factor < 1):
            raise ValueError(f"a_factor must lie in (0, 1), got {a_factor!r}")
        nn = nearest_neighbour_distance(src_x)
        if np.any(nn <= 0):
            bad = np.flatnonzero(nn <= 0)
            raise ValueError(f"{bad.size} source particles coincide with another "
                             f"(indices {bad[:20].tolist()}): no Kronecker-delta kernel")
        return a_factor * nn
    a_arr = np.asarray(a, dtype=np.float64)
    if a_arr.shape != (n_src,) or not np.all(np.isfinite(a_arr)) or np.any(a_arr <= 0):
        raise ValueError(f"a must be a finite positive array of shape ({n_src},)")
    return a_arr


def _solve_rows(rows, src_x, col_x, col_eps, offsets, indices, exps, c, at_sources, max_cond, const_b, op_deg,
                interp_cols, a_arr, data, n_nb, cond) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The weights of the collocation points ``rows`` (Eqs. A.1-A.3, A.9-A.11) written into ``data``,
    their usable neighbours into ``n_nb`` and condition numbers into ``cond``.  Returns the points
    with too few neighbours and those with a singular or ill-conditioned moment matrix."""
    n_mono = exps.shape[0]
    few_pts: list[np.ndarray] = []
    bad_pts: list[np.ndarray] = []
    pos, mask, z, w, V, r2 = _assemble(src_x, col_x, col_eps, offsets, indices,
                                       exps, c, rows)
    usable = mask & (r2 > 0) if at_sources else mask
    n_nb[rows] = usable.sum(axis=1)
    WV = w[:, :, None] * V                                # (n, K, N)
    sv = np.linalg.svd(WV, compute_uv=False)              # (n, min(K, N))
    if sv.shape[1] < n_mono:
        cnd = np.full(rows.size, np.inf)
    else:
        smin = sv[:, -1]
        with np.errstate(divide="ignore"):
            cnd = np.where(smin > 0, (sv[:, 0] / np.where(smin > 0, smin, 1.0)) ** 2,
                           np.inf)
    cond[rows] = cnd
    few = n_nb[rows] < n_mono
    bad = ~few & ~(cnd <= max_cond)
    if few.any():
        few_pts.append(rows[few])
    if bad.any():
        bad_pts.append(rows[bad])
    ok = ~(few | bad)
    if not ok.any():
        return few_pts, bad_pts
    rows_ok = rows[ok]
    pos, mask, z, w, V, WV = pos[ok], mask[ok], z[ok], w[ok], V[ok], WV[ok]

    A = np.matmul(WV.transpose(0, 2, 1), WV)              # (n, N, N), Eq. A.3
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:                          # pragma: no cover
        # cond check should prevent this; find the culprits one by one
        for j in range(A.shape[0]):
            try:
                np.linalg.cholesky(A[j])
            except np.linalg.LinAlgError:
                bad_pts.append(rows_ok[j:j + 1])
        return few_pts, bad_pts

    B = np.broadcast_to(const_b, (rows_ok.size,) + const_b.shape).copy()
    if interp_cols:
        # zeta-hat_q(x_p) = quartic(|x_p - x_q| / a_q)  (Eq. A.11)
        nb = indices[pos]
        dx = src_x[nb] - col_x[rows_ok][:, None, :]
        dist = np.sqrt(np.einsum("nkd,nkd->nk", dx, dx))
        zhat = quartic_spline(dist / a_arr[nb]) * mask
        # b = p(0) - sum_q p(z_q) zhat_q   (Eq. A.10, consistent sign)
        b_int = -np.einsum("nkj,nk->nj", V, zhat)
        b_int[:, 0] += 1.0
        for i in interp_cols:
            B[:, :, i] = b_int
    Y = np.linalg.solve(L, B)                              # L y = b
    C = np.linalg.solve(L.transpose(0, 2, 1), Y)           # L^T c = y
    phi = (w * w)[:, :, None] * np.matmul(V, C)            # (n, K, n_ops), Eq. A.1
    scale = col_eps[rows_ok][:, None] ** (-op_deg[None, :].astype(np.float64))
    phi = phi * scale[:, None, :]
    if interp_cols:
        for i in interp_cols:
            phi[:, :, i] += zhat
    phi[~mask] = 0.0
    flat = pos[mask]
    vals = phi[mask]                                        # (nnz_chunk, n_ops)
    data[:, flat] = vals.T
    return few_pts, bad_pts


def _degenerate_message(few_pts, bad_pts, n_col, n_mono, order, d, at_sources, max_cond, n_nb, cond) -> str:
    """The error message naming the collocation points without a valid stencil."""
    problems = []
    if few_pts:
        idx = np.sort(np.concatenate(few_pts))
        what = "neighbours at non-zero distance" if at_sources else "neighbours"
        problems.append(
            f"{idx.size} of {n_col} collocation points have fewer than {n_mono} {what} "
            f"(order m={order}, d={d}{', form (b)' if at_sources else ''}): "
            + _fmt_points(idx, {"neighbours": n_nb[idx]}))
    if bad_pts:
        idx = np.sort(np.concatenate(bad_pts))
        problems.append(
            f"{idx.size} of {n_col} collocation points have a singular or ill-conditioned "
            f"moment matrix (cond2(A) > {max_cond:.3g}; e.g. collinear/coplanar "
            f"neighbours): " + _fmt_points(idx, {"neighbours": n_nb[idx], "cond": cond[idx]}))
    return "degenerate DC-PSE stencil(s): " + " | ".join(problems)


def dcpse_weights(
    src_x: npt.ArrayLike,
    col_x: npt.ArrayLike | None,
    col_eps: npt.ArrayLike,
    offsets: npt.ArrayLike,
    indices: npt.ArrayLike,
    ops: Sequence[OperatorSpec],
    order: int = 4,
    c: float = DEFAULT_C,
    at_sources: bool = False,
    a: npt.ArrayLike | None = None,
    a_factor: float = DEFAULT_A_FACTOR,
    max_cond: float = DEFAULT_MAX_COND,
    col_src: npt.ArrayLike | None = None,
) -> DCPSEWeights:
    """DC-PSE kernel weights for several operators sharing one moment matrix.

    Parameters
    ----------
    src_x : (n_src, d) float
        Source particle positions [length].
    col_x : (n_col, d) float or None
        Collocation points [length].  Form (b) (``at_sources=True``): pass
        None; the points are then ``src_x[col_src]``.
    col_eps : (n_col,) float
        Core size ε_p of each collocation point [length]; offsets are scaled
        by it (Eq. A.2).  The paper uses ε_p = r_c,p.
    offsets : (n_col + 1,) int;  indices : (nnz,) int
        CSR neighbour list: sources of point p are
        ``indices[offsets[p]:offsets[p+1]]``.
    ops : sequence
        Operators: multi-indices α (``|α| < order``; form (b) needs ``|α| ≥ 1``),
        ``"laplacian"``, or ``"interp"`` (interpolating kernel ζ, form (a)).
    order : int
        Order of accuracy m ≥ 2 (basis: monomials of degree < m).
    c : float
        Gaussian parameter of w(r) = exp(-c² r²/2), ``r = |x_q - x_p| / ε_p``.
    at_sources : bool
        False: form (a), (L f)_p = Σ_k data[k] f[indices[k]] (vanishing zeroth
        moment, valid anywhere).  True: form (b),
        (L f)_p = Σ_k data[k] (f[indices[k]] - f[p]) (free zeroth moment).
    a : (n_src,) float or None
        Radii a_q [length] of the quartic-spline correction (only for
        ``"interp"``); default ``a_factor`` × nearest-neighbour distance.
    max_cond : float
        Reject stencils with cond₂(A_p) > max_cond.
    col_src : (n_col,) int or None
        Form (b) only: source index of each collocation point (default: all
        sources, in order).  Lets one evaluate form (b) on a subset, e.g. on
        real particles when ghosts are appended to the sources.

    Returns
    -------
    DCPSEWeights
        ``data`` (n_ops, nnz) aligned with ``indices``; ``diag`` (n_ops, n_col).

    Raises
    ------
    ValueError
        On malformed input, and when some collocation points have too few
        neighbours or an ill-conditioned / singular moment matrix (the message
        lists how many and which points).
    """
    src_x, col_x, col_eps, offsets, indices, col_src = _check_inputs(
        src_x, col_x, col_eps, offsets, indices, at_sources, col_src)
    n_src, d = src_x.shape
    n_col = col_x.shape[0]
    if int(order) != order or order < 2:
        raise ValueError(f"order m must be an integer >= 2, got {order!r}")
    order = int(order)
    if not (np.isfinite(c) and c > 0):
        raise ValueError(f"Gaussian parameter c must be finite and > 0, got {c!r}")
    if len(ops) == 0:
        raise ValueError("ops must name at least one operator")
    ops_n = [normalize_op(op, d, order, at_sources) for op in ops]

    exps_full = monomial_exponents(d, order)
    exps = exps_full[1:] if at_sources else exps_full
    n_mono = exps.shape[0]
    const_b = np.stack([rhs(op, exps) if op != "interp" else np.zeros(n_mono)
                        for op in ops_n], axis=1)            # (n_mono, n_ops)
    op_deg = np.array([op_order(op) for op in ops_n])
    interp_cols = [i for i, op in enumerate(ops_n) if op == "interp"]

    a_arr = _spline_radii(src_x, a, a_factor) if interp_cols else None

    nnz = indices.size
    data = np.zeros((len(ops_n), nnz))
    diag = np.zeros((len(ops_n), n_col))
    n_nb = np.zeros(n_col, dtype=np.int64)
    cond = np.full(n_col, np.inf)

    counts = np.diff(offsets)
    few_pts: list[np.ndarray] = []
    bad_pts: list[np.ndarray] = []
    for rows in _chunks(counts, n_mono):
        few, bad = _solve_rows(rows, src_x, col_x, col_eps, offsets, indices, exps, c, at_sources, max_cond,
                               const_b, op_deg, interp_cols, a_arr, data, n_nb, cond)
        few_pts += few
        bad_pts += bad

    if few_pts or bad_pts:
        raise ValueError(_degenerate_message(few_pts, bad_pts, n_col, n_mono, order, d, at_sources, max_cond,
                                             n_nb, cond))

    if at_sources:
        rows_of = np.repeat(np.arange(n_col), counts)
        for i in range(len(ops_n)):
            diag[i] = -np.bincount(rows_of, weights=data[i], minlength=n_col)

    return DCPSEWeights(data=data, diag=diag, offsets=offsets, indices=indices,
                        n_src=n_src, ops=ops_n, at_sources=at_sources,
                        n_neighbours=n_nb, cond=cond, a=a_arr, col_src=col_src)
