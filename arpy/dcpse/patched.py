"""Operators of a DC-PSE set with some rows replaced by those of another: :class:`Patched`, the form every
repair of :class:`arpy.dcpse.domain.DomainDCPSE` (one-sided rows by Dirichlet faces, widened and rebuilt
rows) takes."""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np
import scipy.sparse as sp

from ..lists.neighborlist import row_blocks

__all__ = ["MERGE_BLOCK", "SPLICE_ROWS", "Patched", "Renumbered", "Rows"]

#: Up to this many patched rows, :meth:`Patched._merge` splices them in (else it gathers every entry).
SPLICE_ROWS = 64

#: :meth:`Patched._merge` copies the base's rows in blocks of whole rows of about this many entries.
MERGE_BLOCK = 1 << 20


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

    A Patched base (or a :class:`Renumbered` one) is flattened: the repairs and the ranks' splices stack
    layers, and the set keeps, for every row, the set it is read from (the innermost base, its rows in
    place, or one of the layers' second sets) and the row there, so that each call merges every set's
    matrix once into the result, which the caller alone holds (no layer keeps a copy, and no layer's
    merge is held while the next one runs)."""

    def __init__(self, base: Rows, fix: Rows, rows: np.ndarray, widened: bool = False,
                 take: np.ndarray | None = None) -> None:
        take = np.arange(fix.n_col) if take is None else np.asarray(take)
        self.d: int = base.d
        self.n_col: int = base.n_col
        self.n_src: int = base.n_src
        self.failed: np.ndarray = np.union1d(np.setdiff1d(base.failed, rows), rows[np.isin(take, fix.failed)])
        self.widened: np.ndarray = np.union1d(base.widened, rows) if widened else np.setdiff1d(base.widened, rows)
        # row p is row _row[p] of _sets[_set[p]]
        self._sets: list[Rows]
        self._set: np.ndarray
        self._row: np.ndarray
        inner = base.op if isinstance(base, Renumbered) else base
        if isinstance(inner, Patched):
            # (a renumbered Patched: each of its sets renumbered, so that one merge reads them all)
            sets = inner._sets if not isinstance(base, Renumbered) else [
                Renumbered(s, base.columns, base.n_src) for s in inner._sets]
            self._sets = [*sets, fix]
            self._set, self._row = inner._set.copy(), inner._row.copy()
        else:
            self._sets = [base, fix]
            self._set, self._row = np.zeros(base.n_col, np.int32), np.arange(base.n_col, dtype=np.int64)
        self._set[rows] = len(self._sets) - 1
        self._row[rows] = take

    def _merge(self, mats: Sequence[sp.csr_matrix]) -> sp.csr_matrix:
        """Row p of ``mats[_set[p]]``'s row ``_row[p]`` (one matrix per set), each row's entries in the
        order they are stored (a row's sum then runs in its list's order, e.g. by key), exact zeros
        dropped."""
        mats = [m.tocsr() for m in mats]
        base, which, row = mats[0], self._set, self._row
        patched = np.flatnonzero(which)                             # (ascending)
        length = np.diff(base.indptr).astype(np.int64)
        of = [patched[which[patched] == k] for k in range(len(mats))]
        for k in range(1, len(mats)):
            q = row[of[k]]
            length[of[k]] = mats[k].indptr[q + 1] - mats[k].indptr[q]
        # (the index arrays in the type scipy keeps them in, so that it need not scan and convert them)
        small = max(sum(int(m.indptr[-1]) for m in mats), *base.shape) < 2 ** 31
        indptr = np.zeros(self.n_col + 1, dtype=np.int32 if small else np.int64)
        np.cumsum(length, out=indptr[1:])
        if patched.size <= SPLICE_ROWS:
            # a few rows: the base's entries in runs between them, each patched row's in its place
            pieces, at = [], 0
            for r in patched.tolist():
                m, q = mats[which[r]], row[r]
                pieces += [(base, slice(at, base.indptr[r])), (m, slice(m.indptr[q], m.indptr[q + 1]))]
                at = base.indptr[r + 1]
            pieces.append((base, slice(at, base.indptr[-1])))
            data = np.concatenate([m.data[sl] for m, sl in pieces])
            indices = np.concatenate([m.indices[sl] for m, sl in pieces]).astype(indptr.dtype, copy=False)
        else:
            # the base's rows by masks over its entries and the result's (a byte per entry), each other
            # set's rows by the positions of their entries
            data = np.empty(int(indptr[-1]), np.result_type(*(m.data for m in mats)))
            indices = np.empty(int(indptr[-1]), indptr.dtype)
            own = which == 0
            for first, last in row_blocks(base.indptr, MERGE_BLOCK):
                # (in blocks of whole rows: no mask or gathered copy of every entry at once)
                a, b = int(indptr[first]), int(indptr[last])
                c, e = int(base.indptr[first]), int(base.indptr[last])
                into = np.repeat(own[first:last], length[first:last])
                keep = np.repeat(own[first:last], np.diff(base.indptr[first:last + 1]))
                data[a:b][into] = base.data[c:e][keep]
                indices[a:b][into] = base.indices[c:e][keep]
            for k in range(1, len(mats)):
                if of[k].size:
                    n_k = length[of[k]]
                    first = np.cumsum(n_k) - n_k                    # (each row's first entry among them)
                    step = np.arange(int(n_k.sum())) - np.repeat(first, n_k)
                    at = np.repeat(indptr[of[k]].astype(np.int64), n_k) + step
                    src = np.repeat(mats[k].indptr[row[of[k]]].astype(np.int64), n_k) + step
                    data[at], indices[at] = mats[k].data[src], mats[k].indices[src]
        out = sp.csr_matrix((data, indices, indptr), shape=base.shape)
        out.eliminate_zeros()
        return out

    def derivatives(self, alphas: Sequence[Sequence[int]]) -> list[sp.csr_matrix]:
        return [self._merge(ms) for ms in zip(*(s.derivatives(alphas) for s in self._sets))]

    def gradient(self) -> list[sp.csr_matrix]:
        return [self._merge(ms) for ms in zip(*(s.gradient() for s in self._sets))]

    def laplacian(self) -> sp.csr_matrix:
        return self._merge([s.laplacian() for s in self._sets])

    def interpolation(self) -> sp.csr_matrix:
        return self._merge([s.interpolation() for s in self._sets])


class Renumbered:
    """Operators (:class:`Rows`) with their columns renumbered: ``columns`` (n_src of ``op``,) integers the
    new number of each source, ``n_src`` the new count; each row's entries in the order they are stored
    (the matrices' column indices int32 where ``n_src`` allows, as scipy keeps them)."""

    def __init__(self, op: Rows, columns: np.ndarray, n_src: int) -> None:
        self.op = op
        self.columns = np.asarray(columns, np.int32 if n_src < 2 ** 31 else np.int64)
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
