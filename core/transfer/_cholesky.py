r"""Sparse Cholesky factorisation whose solves run without the GIL, in float32 or float64.

``A = L L^T`` of a symmetric positive-definite (n, n) matrix in a METIS nested-dissection
ordering (``pymetis``), factorised up-looking row by row (Davis, *Direct Methods for Sparse
Linear Systems*, 2006, ch. 4: elimination tree, row patterns by ``ereach``, ``cs_chol``) in
float64 and kept in the working precision.

Hand-written rather than ``cholespy`` (which :class:`~._mesh.CholeskyFactor` uses) for the
detail stage of the dense transfer, whose 1,089 right-hand sides on the 56K-vertex benchmark
were the longest single piece of it: ``cholespy`` holds the GIL through every call, so the
solves could not share the two cores with the right-hand sides being formed, and it solves in
float64 through a column-major copy of every block (its float32 class converts). Here the
solves are one compiled call without the GIL on a block of right-hand sides in place
(C-ordered (n, m)); each row of the block is contiguous, so every entry of ``L`` updates ``m``
values at once (SIMD over the right-hand sides).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

__all__ = ["SparseCholesky", "nested_dissection"]


def nested_dissection(A: sp.spmatrix) -> np.ndarray:
    """METIS's fill-reducing nested-dissection ordering of the graph of symmetric ``A``:
    ``perm`` such that ``A[perm][:, perm]`` is the matrix to factorise."""
    import pymetis  # the ordering is the only use

    A = sp.csr_matrix(A)
    n = A.shape[0]
    G = (A - sp.diags(A.diagonal())).tocsr()
    G.eliminate_zeros()
    if G.nnz == 0:
        return np.arange(n, dtype=np.int64)
    perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(G.indptr.astype(np.int64), G.indices.astype(np.int64)))
    return np.asarray(perm, dtype=np.int64)


class SparseCholesky:
    """``A = L L^T``, factorised once, solved for blocks of right-hand sides without the GIL.

    Parameters
    ----------
    A : (n, n) sparse, symmetric positive definite (both triangles given; not checked)
    dtype : np.float32 or np.float64, the precision of the stored factor and of the solves
        (the factorisation itself always runs in float64)

    Raises
    ------
    ValueError
        ``A`` not square, not positive definite, or another ``dtype``.
    """

    def __init__(self, A: sp.spmatrix, dtype=np.float64):
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.float64, np.float32):
            raise ValueError(f"dtype: expected float64 or float32, got {self.dtype}")
        A = sp.csr_matrix(A, dtype=np.float64)
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"A: expected a square matrix, got {A.shape}")
        self.n = n = A.shape[0]
        self.perm = nested_dissection(A)
        C = A[self.perm][:, self.perm].tocsc()  # symmetric: column k is row k
        C.sum_duplicates()
        C.sort_indices()
        Cp, Ci = C.indptr.astype(np.int64), C.indices.astype(np.int64)
        parent = _etree(Cp, Ci, n)
        counts = _column_counts(Cp, Ci, parent, n)
        self.Lp = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts, out=self.Lp[1:])
        Li, Lx, bad = _factorise(Cp, Ci, C.data, parent, self.Lp, n)
        if bad >= 0:
            raise ValueError(f"A: not positive definite (pivot {int(bad)} of the ordered matrix)")
        self.Li, self.Lx = Li, Lx.astype(self.dtype)

    @property
    def nnz(self) -> int:
        """Entries of ``L`` (diagonal included)."""
        return int(self.Lp[-1])

    #: right-hand sides solved together: every entry of ``L`` read updates this many values
    #: (float32 on the 56K-vertex head, ms per column: 1.39 for 16, 0.89 for 32, 0.55 for 96;
    #: CHOLMOD through cholespy, 1.55-1.6)
    BLOCK = 96

    def solve(self, b: np.ndarray, block: int | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """``A^{-1} b`` for (n,) or (n, m) ``b``, in the factor's dtype; written into ``out``
        (C-ordered (n, m) of that dtype) when given. The columns are solved ``block`` at a time
        (default :attr:`BLOCK`). Runs without the GIL."""
        b = np.asarray(b)
        if b.shape[:1] != (self.n,) or b.ndim not in (1, 2):
            raise ValueError(f"b: expected ({self.n},) or ({self.n}, m), got {b.shape}")
        if b.ndim == 1:
            return self.solve(b[:, None], block)[:, 0]
        if out is None:
            out = np.empty(b.shape, dtype=self.dtype)
        elif out.shape != b.shape or out.dtype != self.dtype or not out.flags.c_contiguous:
            raise ValueError(f"out: expected a C-ordered {b.shape} {self.dtype} array")
        b = np.ascontiguousarray(b, dtype=self.dtype)
        work = np.empty((self.n, max(1, min(block or self.BLOCK, b.shape[1]))), dtype=self.dtype)
        _solve_blocks(self.Lp, self.Li, self.Lx, self.perm, b, out, work)
        return out


@numba.njit(cache=True, nogil=True)
def _etree(Cp, Ci, n):  # pragma: no cover - compiled
    """Elimination tree of symmetric C (Davis 2006, ``cs_etree``): ``parent`` (n,), -1 at roots."""
    parent = np.full(n, -1, dtype=np.int64)
    ancestor = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        for p in range(Cp[k], Cp[k + 1]):
            i = Ci[p]
            while i != -1 and i < k:  # from i up to the root, compressing the path to k
                nxt = ancestor[i]
                ancestor[i] = k
                if nxt == -1:
                    parent[i] = k
                i = nxt
    return parent


@numba.njit(cache=True, nogil=True)
def _ereach(Cp, Ci, k, parent, stack, mark):  # pragma: no cover - compiled
    """Pattern of row k of L (Davis 2006, ``cs_ereach``): ``stack[top:n]`` in topological
    order; returns ``top``. ``mark`` (n,) holds k at the visited nodes."""
    n = len(parent)
    top = n
    mark[k] = k
    for p in range(Cp[k], Cp[k + 1]):
        i = Ci[p]
        if i > k:
            continue
        ln = 0
        while mark[i] != k:  # up the tree to a visited node
            stack[ln] = i
            ln += 1
            mark[i] = k
            i = parent[i]
        while ln > 0:  # push the path onto the output stack
            top -= 1
            ln -= 1
            stack[top] = stack[ln]
    return top


@numba.njit(cache=True, nogil=True)
def _column_counts(Cp, Ci, parent, n):  # pragma: no cover - compiled
    """Entries of each column of L, diagonal included (from every row's pattern: O(|L|))."""
    counts = np.ones(n, dtype=np.int64)
    stack = np.empty(n, dtype=np.int64)
    mark = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        top = _ereach(Cp, Ci, k, parent, stack, mark)
        for q in range(top, n):
            counts[stack[q]] += 1
    return counts


@numba.njit(cache=True, nogil=True)
def _factorise(Cp, Ci, Cx, parent, Lp, n):  # pragma: no cover - compiled
    """Up-looking Cholesky (Davis 2006, ``cs_chol``): L in CSC (``Lp`` given, diagonal first in
    every column). Returns ``(Li, Lx, bad)``, ``bad`` the first non-positive pivot or -1."""
    Li = np.empty(Lp[n], dtype=np.int64)
    Lx = np.empty(Lp[n], dtype=np.float64)
    nxt = Lp[:n].copy()  # next free slot of each column
    x = np.zeros(n)
    stack = np.empty(n, dtype=np.int64)
    mark = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        top = _ereach(Cp, Ci, k, parent, stack, mark)
        for p in range(Cp[k], Cp[k + 1]):  # scatter the upper part of column k
            if Ci[p] <= k:
                x[Ci[p]] += Cx[p]
        d = x[k]
        x[k] = 0.0
        for q in range(top, n):  # L(k, i) for i in the row pattern, in topological order
            i = stack[q]
            lki = x[i] / Lx[Lp[i]]
            x[i] = 0.0
            for p in range(Lp[i] + 1, nxt[i]):
                x[Li[p]] -= Lx[p] * lki
            d -= lki * lki
            p = nxt[i]
            nxt[i] += 1
            Li[p] = k
            Lx[p] = lki
        if d <= 0.0:
            return Li, Lx, k
        p = nxt[k]
        nxt[k] += 1
        Li[p] = k
        Lx[p] = np.sqrt(d)
    return Li, Lx, -1


@numba.njit(cache=True, nogil=True)
def _solve_blocks(Lp, Li, Lx, perm, b, out, work):  # pragma: no cover - compiled
    """``out = A^{-1} b`` for (n, m) ``b``, ``w = work.shape[1]`` columns at a time: gathered
    into ``work`` in the factor's order, ``L y = P b`` forward by columns of L, ``L^T z = y``
    backward, scattered back."""
    n, m = b.shape
    w = work.shape[1]
    for s in range(0, m, w):
        e = min(s + w, m)
        c = e - s
        for i in range(n):
            r = perm[i]
            for j in range(c):
                work[i, j] = b[r, s + j]
        for col in range(n):  # forward: L y = P b
            d = Lx[Lp[col]]
            for j in range(c):
                work[col, j] /= d
            for p in range(Lp[col] + 1, Lp[col + 1]):
                i = Li[p]
                l = Lx[p]
                for j in range(c):
                    work[i, j] -= l * work[col, j]
        for col in range(n - 1, -1, -1):  # backward: L^T z = y
            for p in range(Lp[col] + 1, Lp[col + 1]):
                i = Li[p]
                l = Lx[p]
                for j in range(c):
                    work[col, j] -= l * work[i, j]
            d = Lx[Lp[col]]
            for j in range(c):
                work[col, j] /= d
        for i in range(n):
            r = perm[i]
            for j in range(c):
                out[r, s + j] = work[i, j]
