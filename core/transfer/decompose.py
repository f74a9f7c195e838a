r"""Multi-scale decomposition of a mesh sequence (Xu et al. 2014 §3, eq. 1-4).

Every frame ``S_t`` splits into a smoothed mesh ``S̄_t`` (Taubin's λ|μ Laplacian filter,
~40 iterations) and a *Laplacian coating* ``ξ_t = δ(S_t) - δ(S̄_t)`` (eq. 1). The original is
recovered by one Poisson solve, ``S_t = L^{-1}(L S̄_t + ξ_t)`` (eq. 2).

Conventions
-----------
* ``L`` is a *fixed* linear operator per topology, positive semi-definite as in
  :mod:`core.geometry`: the graph Laplacian ``D - A`` (``kind="uniform"``, default; it depends
  on the topology only, so source and target — which share a topology after preprocessing —
  share one factorisation) or the cotangent Laplacian of a reference mesh
  (``kind="cotangent"``). Fixing ``L`` makes eq. 1-2 linear, so eq. 2 is exact.
* ``L`` annihilates translations of each connected component, so ``L^{-1}`` is defined up to
  one constant per component. :class:`PoissonReconstructor` fixes it by the per-component
  mean of the detail displacement ``S - S̄`` (zero unless given): with that mean, eq. 2
  recovers ``S_t`` exactly (tested).
* Smoothing is linear too: ``S̄ = P S`` with ``P = ((I + μU)(I + λU))^iterations`` and
  ``U = D^{-1}A - I`` the umbrella operator. :func:`factor_sequence` exploits it — a
  sequence of T frames that spans an r-dimensional space (a rig-driven sequence: r <= K + 1)
  is smoothed by filtering r basis vectors instead of T frames, exactly up to a truncation
  residual that is measured and reported.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.linalg import solve_triangular
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ..cores import free_cores
from ..geometry import cotangent_laplacian, uniform_laplacian, vertex_adjacency, vertex_components
from ._cholesky import SparseCholesky
from ._mesh import PinnedSolver, bbox_size, check_faces

__all__ = [
    "TaubinFilter",
    "taubin_smooth",
    "laplacian_operator",
    "laplacian_coating",
    "PoissonReconstructor",
    "FactoredSequence",
    "factor_sequence",
]


class TaubinFilter:
    r"""Taubin's λ|μ smoothing (Taubin 1995; Xu et al. 2014 §3, "filter about 40 times").

    One iteration is two umbrella steps,

    .. math:: x \leftarrow x + \lambda U x, \qquad x \leftarrow x + \mu U x,
              \qquad U = D^{-1}A - I,

    with ``λ > 0 > μ`` and ``|μ| > λ`` (shrink, then inflate: a low-pass filter without the
    shrinkage of plain Laplacian smoothing). The filter is linear in the positions, so it
    applies to any number of columns at once.

    Parameters
    ----------
    faces : (F, 3) int
    n_vertices : int
    iterations : int, default 40
    lam, mu : float, defaults 0.5 and -0.53 (Taubin's pass-band ``k_PB = 1/λ + 1/μ ≈ 0.11``)
    fixed : (m,) int, optional
        Vertices that do not move (e.g. a boundary to keep); default none.

    Raises
    ------
    ValueError
        ``iterations < 0``, ``lam <= 0``, ``mu >= 0`` or ``|mu| < lam``.
    """

    def __init__(self, faces, n_vertices: int, iterations: int = 40, lam: float = 0.5, mu: float = -0.53, fixed=None):
        if int(iterations) != iterations or iterations < 0:
            raise ValueError(f"iterations: expected an integer >= 0, got {iterations!r}")
        if not lam > 0 or not mu < 0 or abs(mu) < lam:
            raise ValueError(f"lam, mu: expected lam > 0 > mu with |mu| >= lam (Taubin 1995), got lam={lam}, mu={mu}")
        faces = check_faces(faces, n_vertices)
        A = vertex_adjacency(faces, n_vertices)
        deg = np.asarray(A.sum(axis=1)).ravel()
        inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
        if fixed is not None:
            inv[np.asarray(fixed, dtype=np.int64)] = 0.0
        # U = D^{-1}A - I on moving vertices, 0 on fixed and isolated ones
        W = sp.diags(inv) @ A
        U = (W - sp.diags((inv > 0).astype(np.float64))).tocsr()
        self.iterations = int(iterations)
        self.lam, self.mu = float(lam), float(mu)
        self.n = n_vertices
        # the two half-steps as matrices I + λU and I + μU
        I = sp.identity(n_vertices, format="csr")
        steps = ((I + self.lam * U).tocsr(), (I + self.mu * U).tocsr())
        # ... renumbered by reverse Cuthill-McKee so that a vertex's neighbours lie close in
        # memory (a Loop-subdivided mesh numbers new edge vertices after all the old ones): the
        # sparse products gather from cache, 35-40% faster on the 56K-vertex head. Each row keeps
        # its entries in their order, so every sum runs in the same order: bit-identical.
        self._order = reverse_cuthill_mckee(A, symmetric_mode=True).astype(np.int64)
        self._steps = tuple(_renumber(M, self._order) for M in steps)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Smooth (V,), (V, 3), (V, m) or (T, V, 3) positions; returns a new float64 array."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim == 3:
            T, V, c = x.shape
            y = self.apply(x.transpose(1, 0, 2).reshape(V, T * c))
            return y.reshape(V, T, c).transpose(1, 0, 2).copy()
        if x.shape[0] != self.n:
            raise ValueError(f"x: expected {self.n} vertices on axis 0, got shape {x.shape}")
        if x.ndim == 1:
            return self.apply(x[:, None])[:, 0]
        out = np.empty(x.shape)
        order = self._order
        # columns are independent: run all iterations on blocks of ~16 MB, which stay in cache
        # across the 2 * iterations sparse products (the same arithmetic, bit for bit, for any
        # width; 39 columns of a 56K-vertex head ran 25-30% faster than 18 on a loaded machine).
        # Not float32: its rounding noise in the smoothed meshes moves the transferred bases
        # 1e-4 of their size where Taubin flattens thin parts to needles (the Jeeliz tiger).
        # The blocks share the cores this process may use (the product kernel releases the GIL)
        m = max(x.shape[1], 1)
        n_blocks = -(-m // max(8, (1 << 21) // max(self.n, 1)))
        n_work = min(n_blocks, free_cores())
        n_blocks = max(n_work, n_work * round(n_blocks / n_work))  # a whole number of blocks per core
        width = -(-m // n_blocks)
        blocks = [slice(s, s + width) for s in range(0, m, width)]

        def run(cols):
            out[order, cols] = self._iterate(np.ascontiguousarray(x[order, cols]))

        if n_work <= 1:
            for cols in blocks:
                run(cols)
        else:
            with ThreadPoolExecutor(n_work) as pool:
                list(pool.map(run, blocks))
        return out

    def _iterate(self, y: np.ndarray) -> np.ndarray:
        """All iterations on one (V, w) block (renumbered): ``y <- B (A y)``."""
        A, B = self._steps
        _taubin_iterations(A.indptr, A.indices, A.data, B.indptr, B.indices, B.data, y, np.empty_like(y), self.iterations)
        return y


# Hand-written rather than scipy's ``A @ y``: the same sums in the same order (each row's
# entries in stored order, from 0: bit for bit scipy's csr_matvecs), but without the GIL, so
# that the column blocks of the filter run on two cores; all iterations in one call, so that a
# block needs the GIL once, not 80 times (another thread holding it -- a CHOLMOD factorisation
# -- stalled every product).
@numba.njit(cache=True, nogil=True)
def _csr_times(indptr, indices, data, y, out):  # pragma: no cover - compiled
    """``out = M y`` for CSR ``M`` (indptr, indices, data) and C-ordered (n, w) ``y``."""
    w = y.shape[1]
    for i in range(len(indptr) - 1):
        for c in range(w):
            out[i, c] = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            a, j = data[k], indices[k]
            for c in range(w):
                out[i, c] += a * y[j, c]


@numba.njit(cache=True, nogil=True)
def _taubin_iterations(ap, ai, ax, bp, bi, bx, y, z, iterations):  # pragma: no cover - compiled
    """``iterations`` times ``y <- B (A y)`` (``z``: scratch of y's shape)."""
    for _ in range(iterations):
        _csr_times(ap, ai, ax, y, z)
        _csr_times(bp, bi, bx, z, y)


def _renumber(M: sp.csr_matrix, order: np.ndarray) -> sp.csr_matrix:
    """``M[order][:, order]`` (CSR) with every row's entries kept in their stored order."""
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    lens = np.diff(M.indptr)[order]
    indptr = np.concatenate([[0], np.cumsum(lens)])
    src = np.repeat(M.indptr[order] - indptr[:-1], lens) + np.arange(indptr[-1])
    return sp.csr_matrix((M.data[src], inv[M.indices[src]], indptr), shape=M.shape)


def taubin_smooth(positions, faces, iterations: int = 40, lam: float = 0.5, mu: float = -0.53) -> np.ndarray:
    """Taubin λ|μ smoothing of (V, 3) or (T, V, 3) positions; see :class:`TaubinFilter`."""
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim not in (2, 3) or x.shape[-1] != 3:
        raise ValueError(f"positions: expected (V, 3) or (T, V, 3), got {x.shape}")
    return TaubinFilter(faces, x.shape[-2], iterations, lam, mu).apply(x)


def laplacian_operator(faces, n_vertices: int, kind: str = "uniform", positions=None) -> sp.csr_matrix:
    """The fixed Laplacian ``L`` of eq. 1-2 (PSD, rows summing to 0).

    ``kind="uniform"``: graph Laplacian ``D - A`` (topology only). ``kind="cotangent"``:
    cotangent Laplacian of ``positions`` (the reference mesh).
    """
    faces = check_faces(faces, n_vertices)
    if kind == "uniform":
        return uniform_laplacian(faces, n_vertices)
    if kind == "cotangent":
        if positions is None:
            raise ValueError("positions: the cotangent Laplacian needs the reference positions")
        return cotangent_laplacian(positions, faces)
    raise ValueError(f"kind: expected 'uniform' or 'cotangent', got {kind!r}")


def laplacian_coating(positions, smoothed, L: sp.spmatrix) -> np.ndarray:
    r"""Laplacian coating (Xu et al. 2014 eq. 1; Sorkine et al. 2004).

    .. math:: \xi^v = \delta_v - \bar\delta_v = (L S)_v - (L \bar S)_v

    Parameters
    ----------
    positions, smoothed : (V, 3) or (T, V, 3) float
    L : (V, V) sparse, the fixed operator of :func:`laplacian_operator`

    Returns
    -------
    (V, 3) or (T, V, 3) float64
    """
    d = np.asarray(positions, dtype=np.float64) - np.asarray(smoothed, dtype=np.float64)
    if d.shape[-2] != L.shape[0]:
        raise ValueError(f"positions: {d.shape[-2]} vertices, L is {L.shape}")
    if d.ndim == 2:
        return np.asarray(L @ d)
    T, V, _ = d.shape
    return np.asarray(L @ d.transpose(1, 0, 2).reshape(V, -1)).reshape(V, T, 3).transpose(1, 0, 2).copy()


class PoissonReconstructor:
    r"""Factorise ``L`` once, reconstruct many frames (Xu et al. 2014 eq. 2, 4, 5).

    .. math:: S = L^{-1}(L \bar S + \xi) = \bar S + L^{+}\xi + m

    where ``L^+ ξ`` is the zero-mean solution on every connected component and ``m`` the
    per-component mean of the detail displacement ``S - S̄`` (``mean``; zero by default).

    With ``screening = s > 0`` the solve is the screened Poisson equation

    .. math:: (L + \varepsilon I)\,y = \xi + \varepsilon\,y_{prior},
              \qquad \varepsilon = s \cdot \mathrm{mean}(\mathrm{diag}\,L)

    which returns ``y_prior`` exactly when ``ξ = L y_prior`` and damps only the lowest
    frequencies (below ~``s`` of the Laplacian spectrum; the coating is high-pass by
    construction). It keeps a coating that is not exactly a Laplacian — a rotated one
    (eq. 16) — from drifting the whole mesh: the response to a local coating change decays
    over ~``1/sqrt(s)`` edges instead of spreading like a Green's function.

    Parameters
    ----------
    faces : (F, 3) int
    n_vertices : int
    kind : {"uniform", "cotangent"}
    positions : (V, 3), the reference for ``kind="cotangent"``
    screening : float >= 0, relative screening weight (0: plain Poisson, the paper's eq. 2)
    """

    def __init__(self, faces, n_vertices: int, kind: str = "uniform", positions=None, screening: float = 0.0):
        faces = check_faces(faces, n_vertices)
        if screening < 0:
            raise ValueError(f"screening: expected >= 0, got {screening}")
        self.L = laplacian_operator(faces, n_vertices, kind, positions)
        ncomp, labels = vertex_components(faces, n_vertices)
        self.n = n_vertices
        self.labels = labels
        self.n_components = int(ncomp)
        self.screening = float(screening)
        counts = np.bincount(labels, minlength=ncomp).astype(np.float64)
        # (components, V) averaging operator of the gauge
        self.average = sp.csr_matrix((1.0 / counts[labels], (labels, np.arange(n_vertices))), shape=(ncomp, n_vertices))
        self._pinned = None
        self._screened = {}  # dtype -> SparseCholesky of L + εI
        self._lock = threading.Lock()  # one factorisation when threads ask at once
        if self.screening > 0:
            self.eps = self.screening * float(self.L.diagonal().mean())
            self._A = (self.L + self.eps * sp.identity(n_vertices)).tocsr()

    def __getstate__(self):  # picklable as before the lock (a lock is not)
        state = self.__dict__.copy()
        del state["_lock"]
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def solver(self) -> PinnedSolver:
        """The factorisation of the plain ``L`` (built on first use: the screened
        reconstruction never needs it)."""
        with self._lock:
            if self._pinned is None:
                self._pinned = PinnedSolver(self.L, self.labels, self.n_components)
        return self._pinned

    def component_mean(self, x: np.ndarray) -> np.ndarray:
        """(components, 3) per-component mean of (V, 3) ``x``."""
        return self.average @ np.asarray(x, dtype=np.float64)

    @property
    def screened_factor(self) -> SparseCholesky:
        """The float64 Cholesky factorisation of ``L + εI`` (built on first use: the
        decomposition needs only ``L``, the detail stage the solves)."""
        return self._screened_factor(np.float64)

    def _screened_factor(self, dtype) -> SparseCholesky:
        dtype = np.dtype(dtype)
        with self._lock:
            if dtype not in self._screened:
                self._screened[dtype] = SparseCholesky(self._A, dtype)
        return self._screened[dtype]

    def prepare(self, dtype=np.float64) -> None:
        """Factorise now what :meth:`solve` in ``dtype`` will use (else built on first use;
        thread-safe: a thread asking while another factorises waits for that factorisation)."""
        if self.screening == 0:
            self.solver
        else:
            self._screened_factor(dtype)

    def solve(self, B: np.ndarray, block: int | None = None, dtype=np.float64, out=None) -> np.ndarray:
        r"""Solve for (V, m) right-hand sides at once: ``(L + εI)^{-1} B`` when screened, else
        the zero-mean ``L^+ B`` (``B`` must then be orthogonal to the per-component constants).

        One sparse Cholesky factorisation, all m columns solved in blocks of ``block``: the
        screened operator's is :class:`~._cholesky.SparseCholesky` (its solves run without the
        GIL, in ``dtype``: float64, or float32 for the float32 detail stage; each precision
        factorised once, on first use), the plain one's :class:`~._mesh.PinnedSolver`, always
        float64.
        Returns (V, m) in that precision; the screened solve writes it into ``out`` when given
        (C-ordered (V, m) of that dtype).
        """
        B = np.asarray(B)
        if B.ndim != 2 or B.shape[0] != self.n:
            raise ValueError(f"B: expected ({self.n}, m), got {B.shape}")
        if self.screening == 0:
            return self.solver.solve(np.asarray(B, dtype=np.float64), None, block)
        return self._screened_factor(dtype).solve(B, block, out)

    def displacement(self, coating: np.ndarray, mean=None, prior=None) -> np.ndarray:
        """``L^+ ξ + m`` (or the screened solve with ``prior`` (V, 3)) for (V, 3) or (T, V, 3)
        coatings; ``mean`` is (components, 3) or None."""
        c = np.asarray(coating, dtype=np.float64)
        if c.shape[-2] != self.n or c.shape[-1] != 3:
            raise ValueError(f"coating: expected (..., {self.n}, 3), got {c.shape}")
        T = 1 if c.ndim == 2 else c.shape[0]
        b = c if c.ndim == 2 else c.transpose(1, 0, 2).reshape(self.n, T * 3)
        if self.screening > 0:
            if prior is not None:
                b = b + self.eps * np.tile(np.asarray(prior, dtype=np.float64), (1, T))
            y = self.solve(b)
        else:
            m = None if mean is None else np.tile(np.asarray(mean, dtype=np.float64), (1, T))
            y = self.solver.solve(b, m)
        return y if c.ndim == 2 else y.reshape(self.n, T, 3).transpose(1, 0, 2).copy()

    def reconstruct(self, smoothed: np.ndarray, coating: np.ndarray, mean=None, prior=None) -> np.ndarray:
        """Eq. 2: positions from smoothed positions and coating, (V, 3) or (T, V, 3)."""
        return np.asarray(smoothed, dtype=np.float64) + self.displacement(coating, mean, prior)


@dataclass(frozen=True)
class FactoredSequence:
    r"""A sequence as ``S_t = base + Σ_j coeffs[t, j] basis[j]`` (exact to ``residual_rms``).

    Attributes
    ----------
    base : (V, 3)  the first frame
    coeffs : (T, r)
    basis : (r, V, 3), orthonormal as r flattened vectors
    residual_rms : float, RMS per-vertex distance (metres) between the sequence and its factorisation
    """

    base: np.ndarray
    coeffs: np.ndarray
    basis: np.ndarray
    residual_rms: float

    @property
    def rank(self) -> int:
        return len(self.basis)

    @property
    def n_frames(self) -> int:
        return len(self.coeffs)

    def frames(self, idx=slice(None)) -> np.ndarray:
        """(t, V, 3) float64 frames for index/slice ``idx``."""
        c = np.atleast_2d(self.coeffs[idx])
        V = self.base.shape[0]
        return self.base + (c @ self.basis.reshape(self.rank, 3 * V)).reshape(len(c), V, 3)

    def map_basis(self, fn) -> "FactoredSequence":
        """Apply a *linear* map ``fn`` ((V, m) -> (V', m)) to base and basis (the basis is
        no longer orthonormal afterwards; ``residual_rms`` is kept, a bound when ``fn``
        has operator norm <= 1)."""
        V = self.base.shape[0]
        r = self.rank
        stacked = np.concatenate([self.base[:, :, None], self.basis.transpose(1, 2, 0)], axis=2)  # (V, 3, r+1)
        out = np.asarray(fn(stacked.reshape(V, 3 * (r + 1)))).reshape(-1, 3, r + 1)
        return FactoredSequence(out[:, :, 0].copy(), self.coeffs, out[:, :, 1:].transpose(2, 0, 1).copy(), self.residual_rms)


def _column_blocks(n_rows: int, n_cols: int, budget: int = 1 << 21):
    """Column slices of a (n_rows, n_cols) matrix with ~``budget`` entries each."""
    step = max(256, budget // max(n_rows, 1))
    return [slice(c, min(c + step, n_cols)) for c in range(0, n_cols, step)]


def _orthonormal_rows(Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Q, R)`` with ``Y = R^T Q`` for (k, n) ``Y``, k << n: ``Q`` (k, n) orthonormal rows, ``R``
    (k, k) upper triangular (the QR factorisation of ``Y^T``).

    Cholesky QR twice (CholQR2, Yamamoto et al. 2015): two (k, k) Gram matrices and triangular
    solves, BLAS-3 over the long axis, orthonormal to rounding while ``cond(Y) < ~1e7`` (the
    directions of :func:`factor_sequence` have ``cond <= sqrt(1e13)``). LAPACK's Householder QR
    of the (3V, k) transpose took 0.33 s of the 0.9 s factorisation on the 56K-vertex benchmark
    (k = 25), this 0.05 s. Falls back to Householder when a Gram matrix is not positive definite.
    """
    R = np.eye(len(Y))
    Q = Y
    try:
        for _ in range(2):
            Rc = np.linalg.cholesky(Q @ Q.T).T  # upper, Q Q^T = Rc^T Rc
            Q = solve_triangular(Rc, Q, trans="T", lower=False)  # Rc^{-T} Q
            R = Rc @ R
        return Q, R
    except np.linalg.LinAlgError:
        q, R = np.linalg.qr(Y.T)
        return q.T, R


def factor_sequence(sequence, rtol: float = 1e-6, max_rank: int | None = None, passes: int = 4,
                    base=None) -> FactoredSequence:
    r"""Factor a (T, V, 3) sequence through the span of its frames.

    ``X = [S_t - base]`` (T, 3V) (``base`` defaults to ``S_0``) is written as ``C Q`` with
    orthonormal rows ``Q`` (r, 3V) and ``C = X Q^T``, grown pass by pass from the dominant
    eigenvectors of the Gram matrix of the current residual ``R = X - C Q``,

    .. math:: R R^T = X X^T - C C^T \qquad (Q Q^T = I,\ C = X Q^T),

    until the RMS residual per vertex, ``sqrt(Σ_t ||X_t - C_t Q||² / (T V))``, is below
    ``rtol * size``. ``X X^T`` is formed once, in float64 (it resolves residual energies
    down to ~1e-13 of the total, far below any useful ``rtol``); every pass then costs one
    eigendecomposition of a (T, T) matrix and one product with ``X`` for the new directions
    (their coefficients ``X q^T`` follow from the Gram matrix and the QR factor of the new
    directions). ``X`` is streamed in column blocks and never held whole. The residual actually left is
    measured explicitly (one more pass over ``X``) and returned, never assumed.

    Parameters
    ----------
    sequence : (T, V, 3) float
    rtol : float
        Allowed RMS residual relative to the bounding-box diagonal of frame 0.
    max_rank : int, optional
    passes : int
        Refinement passes (each one eigendecomposition of the residual Gram matrix).
    base : (V, 3), optional
        The frame the displacements are taken from (e.g. the reference expression).

    Returns
    -------
    FactoredSequence

    Raises
    ------
    ValueError
        Wrong shape or non-finite values.
    """
    S = np.asarray(sequence)
    if S.ndim != 3 or S.shape[-1] != 3 or len(S) == 0:
        raise ValueError(f"sequence: expected (T, V, 3) with T >= 1, got {S.shape}")
    T, V, _ = S.shape
    base = np.array(S[0] if base is None else base, dtype=np.float64)
    if base.shape != (V, 3):
        raise ValueError(f"base: expected ({V}, 3), got {base.shape}")
    S2 = S.reshape(T, 3 * V)
    b = base.reshape(3 * V)
    blocks = _column_blocks(T, 3 * V)

    # two (T, c) buffers reused by every block: fresh 16 MB temporaries were an mmap and munmap
    # per block, which serialise with the page faults of any other thread of the process
    width = max(c.stop - c.start for c in blocks)
    buf, buf2 = np.empty((T, width)), np.empty((T, width))

    def X(cols):  # (T, c) float64 block of the displacements
        return np.subtract(S2[:, cols], b[cols], dtype=np.float64, out=buf[:, :cols.stop - cols.start])

    G = np.zeros((T, T))
    for cols in blocks:
        x = X(cols)
        if not np.isfinite(x).all():
            raise ValueError("sequence: contains NaN/inf")
        G += x @ x.T
    tol2 = (rtol * max(bbox_size(base), 1e-300)) ** 2 * T * V
    cap = T if max_rank is None else min(T, int(max_rank))
    Q = np.zeros((0, 3 * V))
    C = np.zeros((T, 0))
    top = None
    for _ in range(passes):
        Gr = G - C @ C.T  # Gram matrix of the residual
        if float(np.trace(Gr)) <= tol2 or len(Q) >= cap:
            break
        lam, U = np.linalg.eigh(Gr)
        lam, U = np.maximum(lam[::-1], 0.0), U[:, ::-1]
        tail = np.concatenate([np.cumsum(lam[::-1])[::-1], [0.0]])
        k = next(k for k in range(T + 1) if tail[k] <= tol2)
        # directions below float64 resolution of the Gram product are noise: relative to the
        # largest of the first pass (a later pass's own largest can be rounding noise, and its
        # coefficients, divided by a near-zero R, garbage)
        top = lam[0] if top is None else top
        k = min(k, int(np.sum(lam > 1e-13 * max(top, 1e-300))), cap - len(Q))
        if k == 0:
            break
        Uk = U[:, :k]
        new = np.empty((k, 3 * V))
        for cols in blocks:
            new[:, cols] = Uk.T @ X(cols)
        M = Uk.T @ C
        new -= M @ Q  # U_k^T R
        M2 = new @ Q.T
        new -= M2 @ Q  # re-orthogonalised against what we have
        qn, R = _orthonormal_rows(new)
        # new = U_k^T X - M Q and new^T = qn^T R, so the coefficients X qn^T come from the
        # Gram matrix without another pass over X: (G U_k - C M^T) R^{-1}
        Cn = solve_triangular(R, (G @ Uk - C @ (M + M2).T).T, trans="T", lower=False).T
        Q = np.concatenate([Q, qn])
        C = np.concatenate([C, Cn], axis=1)
    res2 = 0.0
    for cols in blocks:  # the residual, measured
        r = X(cols)
        r -= np.matmul(C, Q[:, cols], out=buf2[:, :cols.stop - cols.start])
        res2 += float(np.einsum("ij,ij->", r, r))
    r = len(Q)
    return FactoredSequence(base, C, Q.reshape(r, V, 3), float(np.sqrt(res2 / (T * V))))
