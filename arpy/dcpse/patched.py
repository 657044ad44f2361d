"""Operators of a DC-PSE set with some rows replaced by those of another: :class:`Patched`, the form every
repair of :class:`arpy.dcpse.domain.DomainDCPSE` (one-sided rows by Dirichlet faces, widened and rebuilt
rows) takes."""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np
import scipy.sparse as sp

__all__ = ["SPLICE_ROWS", "Patched", "Renumbered", "Rows"]

#: Up to this many patched rows, :meth:`Patched._merge` splices them in (else it gathers every entry).
SPLICE_ROWS = 64


class Rows(Protocol):
    """What :class:`Patched` reads of the operators whose rows it takes (a DCPSE, a Patched, ...)."""

    d: int
    n_col: int
    n_src: int
    failed: np.ndarray
    widened: np.ndarray

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]: ...

    def gradient(self) -> list[sp.csr_matrix]: ...

    def laplacian(self) -> sp.csr_matrix: ...

    def interpolation(self) -> sp.csr_matrix: ...


class Patched:
    """Operators of a DCPSE whose rows ``rows`` are replaced by rows ``take`` (default: all, in
    order) of a second one.  ``widened``: the second one's stencils are wider and those rows join
    ``self.widened``; else they are the points' own stencils and leave it.

    Each call merges the two sets' matrices afresh (linear in their entries) and hands the result to
    the caller alone: no layer keeps a copy (the repairs and the ranks' splices stack layers, and each
    kept copy was a whole operator besides the caller's)."""

    def __init__(self, base: Rows, fix: Rows, rows: np.ndarray, widened: bool = False,
                 take: np.ndarray | None = None) -> None:
        take = np.arange(fix.n_col) if take is None else np.asarray(take)
        self.base, self.fix, self.rows = base, fix, rows
        self.d: int = base.d
        self.n_col: int = base.n_col
        self.n_src: int = base.n_src
        self.failed: np.ndarray = np.union1d(np.setdiff1d(base.failed, rows), rows[np.isin(take, fix.failed)])
        self.widened: np.ndarray = np.union1d(base.widened, rows) if widened else np.setdiff1d(base.widened, rows)
        self._from_fix = np.zeros(base.n_col, dtype=bool)
        self._from_fix[rows] = True
        self._patched = np.flatnonzero(self._from_fix)             # (ascending)
        self._fix_row = np.zeros(base.n_col, dtype=np.int64)
        self._fix_row[rows] = take

    def _merge(self, a: sp.csr_matrix, b: sp.csr_matrix) -> sp.csr_matrix:
        """Rows of a, those ``rows`` from b, each row's entries in the order they are stored (a row's
        sum then runs in its list's order, e.g. by key), exact zeros dropped."""
        a, b = a.tocsr(), b.tocsr()
        n, fix, brow = a.shape[0], self._from_fix, self._fix_row
        length = np.where(fix, b.indptr[brow + 1] - b.indptr[brow], np.diff(a.indptr))
        # (the index arrays in the type scipy keeps them in, so that it need not scan and convert them)
        small = max(int(a.indptr[-1]) + int(b.indptr[-1]), *a.shape) < 2 ** 31
        indptr = np.zeros(n + 1, dtype=np.int32 if small else np.int64)
        np.cumsum(length, out=indptr[1:])
        patched = self._patched
        if patched.size <= SPLICE_ROWS:
            # a few rows: a's entries in runs between them, each patched row's from b in its place
            pieces, at = [], 0
            for r, r_fix in zip(patched, brow[patched]):
                pieces += [(a, slice(at, a.indptr[r])), (b, slice(b.indptr[r_fix], b.indptr[r_fix + 1]))]
                at = a.indptr[r + 1]
            pieces.append((a, slice(at, a.indptr[-1])))
            data = np.concatenate([m.data[sl] for m, sl in pieces])
            indices = np.concatenate([m.indices[sl] for m, sl in pieces]).astype(indptr.dtype, copy=False)
        else:
            # the entries of a, then those of b, in one array each; every row of the result is a run of it
            na = a.indptr[-1]
            start = np.where(fix, na + b.indptr[brow], a.indptr[:-1])
            pos = np.arange(indptr[-1]) + np.repeat(start - indptr[:-1], length)
            data = np.concatenate([a.data[:na], b.data[:b.indptr[-1]]])[pos]
            indices = np.concatenate([a.indices[:na], b.indices[:b.indptr[-1]]])[pos].astype(indptr.dtype, copy=False)
        out = sp.csr_matrix((data, indices, indptr), shape=a.shape)
        out.eliminate_zeros()
        return out

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]:
        return [self._merge(a, b) for a, b in zip(self.base.derivatives(alphas), self.fix.derivatives(alphas))]

    def gradient(self) -> list[sp.csr_matrix]:
        return [self._merge(a, b) for a, b in zip(self.base.gradient(), self.fix.gradient())]

    def laplacian(self) -> sp.csr_matrix:
        return self._merge(self.base.laplacian(), self.fix.laplacian())

    def interpolation(self) -> sp.csr_matrix:
        return self._merge(self.base.interpolation(), self.fix.interpolation())


class Renumbered:
    """Operators (:class:`Rows`) with their columns renumbered: ``columns`` (n_src of ``op``,) int64 the
    new number of each source, ``n_src`` the new count; each row's entries in the order they are stored."""

    def __init__(self, op: Rows, columns: np.ndarray, n_src: int) -> None:
        self.op, self.columns = op, columns
        self.d, self.n_col, self.n_src, self.failed, self.widened = op.d, op.n_col, n_src, op.failed, op.widened

    def _mat(self, m: sp.csr_matrix) -> sp.csr_matrix:
        m = m.tocsr()
        return sp.csr_matrix((m.data, self.columns[m.indices], m.indptr), shape=(m.shape[0], self.n_src))

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]:
        return [self._mat(m) for m in self.op.derivatives(alphas)]

    def gradient(self) -> list[sp.csr_matrix]:
        return [self._mat(m) for m in self.op.gradient()]

    def laplacian(self) -> sp.csr_matrix:
        return self._mat(self.op.laplacian())

    def interpolation(self) -> sp.csr_matrix:
        return self._mat(self.op.interpolation())
