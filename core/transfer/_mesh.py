"""Private mesh helpers for the transfer package.

Only what no other package needs (mesh operators others use are public in
:mod:`core.geometry`: weld_vertices, normals, frames, incidence, cross products):

* :func:`to_local` / :func:`to_world` change coordinates to and from the per-vertex frames
  of :func:`core.geometry.vertex_frames` (Xu 2014 §5.1);
* :class:`CholeskyFactor` the sparse Cholesky factorisation of a symmetric positive-definite
  mesh operator (CHOLMOD, through ``cholespy``), in float64, solved for many right-hand sides
  at once: the eq. 9 system and the plain Laplacian (the detail stage's screened Laplacian is
  :class:`core.transfer._cholesky.SparseCholesky`'s);
* :class:`PinnedSolver` one factorisation of a symmetric positive semi-definite mesh
  operator whose null space is the per-component constants (Laplacians), used for every
  Poisson / deformation-transfer solve with many right-hand sides.
"""

from __future__ import annotations

import cholespy
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


def bbox_size(positions: np.ndarray) -> float:
    """Bounding-box diagonal of (..., V, 3) positions (the first frame when a sequence)."""
    p = np.asarray(positions)
    p = p.reshape(-1, p.shape[-2], 3)[0]
    return float(np.linalg.norm(p.max(0) - p.min(0))) if len(p) else 0.0


def check_positions(x, name: str, n: int | None = None) -> np.ndarray:
    """float64 copy of (V, 3) positions; ValueError naming ``name`` otherwise."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and len(a) != n):
        want = f"({n if n is not None else 'V'}, 3)"
        raise ValueError(f"{name}: expected positions of shape {want}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN/inf")
    return a


def check_faces(f, n: int, name: str = "faces") -> np.ndarray:
    a = np.asarray(f)
    if a.ndim != 2 or a.shape[1] != 3 or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name}: expected integer triangles of shape (F, 3), got {a.shape} {a.dtype}")
    if a.size and (a.min() < 0 or a.max() >= n):
        raise ValueError(f"{name}: indices must lie in [0, {n}), got [{a.min()}, {a.max()}]")
    return a.astype(np.int64)


def to_local(frames: tuple, x: np.ndarray) -> np.ndarray:
    """World vectors (..., V, 3) -> local coordinates ``F^T x`` for frames ``(t, b, n)``."""
    return np.stack([np.einsum("...i,...i->...", f, x) for f in frames], axis=-1)


def to_world(frames: tuple, x: np.ndarray) -> np.ndarray:
    """Local coordinates (..., V, 3) -> world vectors ``F x`` for frames ``(t, b, n)``."""
    t, b, n = frames
    return t * x[..., 0:1] + b * x[..., 1:2] + n * x[..., 2:3]


class CholeskyFactor:
    r"""Sparse Cholesky factorisation ``A = L L^T`` of a symmetric positive-definite (n, n)
    matrix, factorised once, solved for any number of right-hand sides in float64.

    CHOLMOD through ``cholespy`` (a simplicial factorisation in METIS's nested-dissection
    ordering; every solve converts its block to a column-major float64 copy and holds the GIL).
    Blocks of 16 columns were fastest on a 56K-vertex head (2.1-2.3 ms per column for 1,089
    columns of the screened Laplacian, against 3-5 ms for SuperLU and 7.7 ms for CHOLMOD given
    all 1,089 at once). The detail stage's many solves use
    :class:`~core.transfer._cholesky.SparseCholesky` instead (float32, without the GIL); this
    one factorises the eq. 9 system and the plain Laplacian, which the naive per-frame
    reference shares.

    Parameters
    ----------
    A : (n, n) sparse, symmetric positive definite (both triangles given; not checked)

    Raises
    ------
    ValueError
        ``A`` not square, or not positive definite (CHOLMOD's verdict).
    """

    #: right-hand sides per CHOLMOD call (see above)
    BLOCK = 16

    def __init__(self, A: sp.spmatrix):
        A = sp.csr_matrix(A, dtype=np.float64)
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"A: expected a square matrix, got {A.shape}")
        A.sum_duplicates()
        A.sort_indices()
        self.n = A.shape[0]
        self.dtype = np.dtype(np.float64)
        self._chol = cholespy.CholeskySolverD(self.n, A.indptr.astype(np.int32), A.indices.astype(np.int32),
                                              np.ascontiguousarray(A.data), cholespy.MatrixType.CSR)

    def solve(self, b: np.ndarray, block: int | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """``A^{-1} b`` for (n,) or (n, m) ``b``; in the factor's dtype, a new C-ordered array
        (or written into ``out``, C-ordered (n, m) of that dtype, for 2-d ``b``)."""
        b = np.asarray(b, dtype=self.dtype)
        if b.shape[0] != self.n or b.ndim not in (1, 2):
            raise ValueError(f"b: expected ({self.n},) or ({self.n}, m), got {b.shape}")
        if b.ndim == 1:
            return self.solve(b[:, None], block)[:, 0]
        block = block or self.BLOCK
        m = b.shape[1]
        if out is not None and (out.shape != b.shape or out.dtype != self.dtype or not out.flags.c_contiguous):
            raise ValueError(f"out: expected a C-ordered {b.shape} {self.dtype} array")
        x = np.empty((self.n, m), dtype=self.dtype) if out is None else out
        if m <= block:
            self._chol.solve(np.ascontiguousarray(b), x)
            return x
        xb = np.empty((self.n, block), dtype=self.dtype)
        for s in range(0, m, block):
            w = min(block, m - s)
            if w < block:
                xb = np.empty((self.n, w), dtype=self.dtype)
            self._chol.solve(np.ascontiguousarray(b[:, s:s + w]), xb)
            x[:, s:s + w] = xb
        return x


class PinnedSolver:
    """Factorisation of a symmetric PSD operator ``A`` whose null space is the constants on
    each connected component (a graph or cotangent Laplacian, plus any PSD edge terms).

    One vertex per component is pinned (its row and column removed), the remaining SPD
    block is factorised once (:class:`CholeskyFactor`), and :meth:`solve` returns the solution of ``A x = b`` whose per-component
    mean equals ``mean`` (default 0): the gauge is fixed *after* the solve, so it never
    biases the result. ``b`` must be (numerically) orthogonal to the null space, which it
    is whenever it is ``A`` applied to something or a divergence (``G^T w``).

    ``factor``: the class that factorises the block, :class:`CholeskyFactor` (default) or
    :class:`core.transfer._cholesky.SparseCholesky` (float64; factorises and solves without
    the GIL).
    """

    def __init__(self, A: sp.spmatrix, labels: np.ndarray | None = None, n_components: int | None = None,
                 factor=None):
        A = sp.csr_matrix(A, dtype=np.float64)
        n = A.shape[0]
        if labels is None:
            n_components, labels = connected_components(A, directed=False)
        self.n = n
        self.labels = labels
        self.n_components = int(n_components)
        pins = np.zeros(self.n_components, dtype=np.int64)
        seen = np.zeros(self.n_components, dtype=bool)
        for i, c in enumerate(labels):  # first vertex of each component (loop ends early)
            if not seen[c]:
                seen[c] = True
                pins[c] = i
                if seen.all():
                    break
        keep = np.ones(n, dtype=bool)
        keep[pins] = False
        self.keep = np.flatnonzero(keep)
        self.pins = pins
        self.factor = (factor or CholeskyFactor)(A[self.keep][:, self.keep])
        self.counts = np.bincount(labels, minlength=self.n_components).astype(np.float64)
        # (components, n) averaging operator for the gauge shift
        self.average = sp.csr_matrix((1.0 / self.counts[labels], (labels, np.arange(n))), shape=(self.n_components, n))

    def solve(self, b: np.ndarray, mean: np.ndarray | None = None, block: int | None = None) -> np.ndarray:
        """Solve for (n,) or (n, m) ``b``; ``mean`` is (n_components, m) or None (zero mean);
        ``block``: right-hand sides per factor solve (default :attr:`CholeskyFactor.BLOCK`)."""
        b = np.asarray(b, dtype=np.float64)
        vec = b.ndim == 1
        B = b[:, None] if vec else b
        m = B.shape[1]
        x = np.zeros((self.n, m))
        x[self.keep] = self.factor.solve(B[self.keep], block)
        # gauge: shift each component to the requested mean
        cur = self.average @ x
        want = np.zeros_like(cur) if mean is None else np.asarray(mean, dtype=np.float64).reshape(self.n_components, m)
        x += (want - cur)[self.labels]
        return x[:, 0] if vec else x
