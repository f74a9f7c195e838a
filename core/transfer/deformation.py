r"""Feature-preserving deformation transfer of blendshape bases (Xu et al. 2014 §4.2, eq. 9-11).

Each source basis ``b_i`` (a deformed copy of the smoothed source reference ``S̄_0``) is
carried to the target by matching deformation gradients (Sumner & Popović 2004):

.. math:: E_{b'_i} = \sum_f a_f \|J_f(b'_i) - D^f_i P'_f\|_F^2
                   + \alpha \sum_l \frac{\|(b'_{i,q} - b'_{i,p}) - D^l_i e'_l\|^2}{\|e'_l\|^2}
   \qquad (9)

* ``D^f_i`` (eq. 10) maps the source reference triangle frame ``(e0, e1, e2)`` to the
  deformed one; ``e2`` is the normal scaled to unit length² per Sumner & Popović
  (``e0 x e1 / sqrt|e0 x e1|``) so that ``D`` is a similarity for a similar triangle.
* ``J_f(x)`` is the per-face gradient of the target positions (:func:`core.geometry.gradient`
  on the target reference ``T̄_0``), ``P'_f = I - n n^T`` the projector onto the target
  reference triangle's plane: the target triangle's edges must follow ``D^f_i``. This is the
  vertex-only ("normal-frame") form of the deformation-transfer energy: its normal matrix is
  the cotangent Laplacian ``G^T diag(a) G`` of ``T̄_0`` (Botsch et al. 2006), the same for
  every basis, so it is factorised once and all K bases are K x 3 right-hand sides.
* ``a_f = A_f / mean(A)`` (face areas of ``T̄_0``) makes the face term dimensionless per
  triangle; the feature-line term (eq. 11) is divided by ``|e'_l|²`` so ``α = 100`` weighs
  one feature edge like 100 average triangles.
* ``D^l_i`` (eq. 11) maps the source reference feature edge ``e0_0`` to the deformed
  ``e0_i`` with the virtual vectors ``e1 = e0_i x e0_0``, ``e2 = e0 x e1``: a rotation about
  ``e1`` and a scale along the edge.

Translations are free in eq. 9; the gauge is fixed so that the mean displacement of every
connected component of the target equals the source's, scaled by ``size(T̄_0) / size(S̄_0)``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

from ..cores import free_cores
from ..geometry import cross, face_cross, gradient, uniform_laplacian, vertex_components
from ._mesh import PinnedSolver, bbox_size, check_faces, check_positions

__all__ = ["triangle_frames", "deformation_gradients", "line_gradients", "DeformationTransfer", "deformation_transfer"]


def triangle_frames(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., F, 3, 3) frames ``[e0, e1, e2]`` as columns (eq. 10) with the Sumner–Popović normal."""
    p = np.asarray(positions, dtype=np.float64)
    p0 = p[..., faces[:, 0], :]
    e0 = p[..., faces[:, 1], :] - p0
    e1 = p[..., faces[:, 2], :] - p0
    c = cross(e0, e1)
    n = np.linalg.norm(c, axis=-1, keepdims=True)
    e2 = c / np.sqrt(np.maximum(n, 1e-300))
    return np.stack([e0, e1, e2], axis=-1)


def _safe_inv(M: np.ndarray) -> np.ndarray:
    """Inverse of (..., 3, 3) frames; degenerate (zero-area) triangles get a zero matrix."""
    det = np.linalg.det(M)
    scale = np.einsum("...ij,...ij->...", M, M) ** 1.5
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    out = np.zeros_like(M)
    out[ok] = np.linalg.inv(M[ok])
    return out


def deformation_gradients(reference, deformed, faces) -> np.ndarray:
    r"""Per-triangle deformation gradients (Xu et al. 2014 eq. 10; Sumner & Popović 2004).

    .. math:: D^f = (e0^f_i, e1^f_i, e2^f_i)(e0^f_0, e1^f_0, e2^f_0)^{-1}

    Parameters
    ----------
    reference : (V, 3)
    deformed : (V, 3) or (K, V, 3)
    faces : (F, 3) int

    Returns
    -------
    (F, 3, 3) or (K, F, 3, 3) float64; identity-free zero on degenerate reference triangles.
    """
    faces = np.asarray(faces, dtype=np.int64)
    inv0 = _safe_inv(triangle_frames(reference, faces))
    return triangle_frames(deformed, faces) @ inv0


def line_gradients(reference, deformed, edges) -> np.ndarray:
    r"""Per-feature-edge deformation gradients (Xu et al. 2014 eq. 11).

    .. math:: D^l = (e0^l_i, e1^l, e2^l_i)(e0^l_0, e1^l, e2^l_0)^{-1},\quad
              e1^l = e0^l_i \times e0^l_0,\ e2 = e0 \times e1

    When ``e0_i`` and ``e0_0`` are parallel the cross product vanishes; any unit vector
    orthogonal to ``e0_0`` then serves as ``e1`` (the map is the pure scale along the edge).

    Parameters
    ----------
    reference : (V, 3)
    deformed : (V, 3) or (K, V, 3)
    edges : (E, 2) int

    Returns
    -------
    (E, 3, 3) or (K, E, 3, 3) float64; ``D e0_0 = e0_i`` exactly.
    """
    edges = np.asarray(edges, dtype=np.int64)
    r = np.asarray(reference, dtype=np.float64)
    d = np.asarray(deformed, dtype=np.float64)
    a0 = r[edges[:, 1]] - r[edges[:, 0]]
    ai = d[..., edges[:, 1], :] - d[..., edges[:, 0], :]
    a0b = np.broadcast_to(a0, ai.shape)
    e1 = np.cross(ai, a0b)
    n1 = np.linalg.norm(e1, axis=-1, keepdims=True)
    scale = np.linalg.norm(a0b, axis=-1, keepdims=True) * np.linalg.norm(ai, axis=-1, keepdims=True)
    bad = (n1 <= 1e-9 * np.maximum(scale, 1e-300))[..., 0]
    if bad.any():
        alt = np.where(np.abs(a0b[..., :1]) < 0.9 * np.linalg.norm(a0b, axis=-1, keepdims=True),
                       np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
        alt = np.cross(a0b, alt)
        e1 = np.where(bad[..., None], alt, e1)
    e1 = e1 / np.maximum(np.linalg.norm(e1, axis=-1, keepdims=True), 1e-300)
    M0 = np.stack([a0b, e1, np.cross(a0b, e1)], axis=-1)
    Mi = np.stack([ai, e1, np.cross(ai, e1)], axis=-1)
    return Mi @ _safe_inv(M0)


class DeformationTransfer:
    """Precomputed, factorised deformation transfer from ``source_ref`` to ``target_ref``
    (same topology), eq. 9-11; :meth:`transfer` maps any number of deformed source meshes.

    Parameters
    ----------
    source_ref, target_ref : (V, 3)   smoothed references ``S̄_0``, ``T̄_0``
    faces : (F, 3) int
    feature_edges : (E, 2) int, optional   the feature lines as vertex pairs
    alpha : float, default 100             weight of the feature-line term
    regularization : float, default 1e-9
        Weight, relative to the face term, of ``||x - T̄_0||²`` in the graph-Laplacian
        (Dirichlet) norm. It only matters where target triangles are degenerate (a
        closest-point resampling can collapse some): their vertices then follow their
        neighbours instead of making the system singular. Identity stays exact.
    factor : the class of the factorisation (:class:`~._mesh.PinnedSolver`'s ``factor``):
        default ``cholespy``'s CHOLMOD, which holds the GIL (~0.4 s to factorise a 56K-vertex
        head); :class:`~._cholesky.SparseCholesky` does not.
    """

    def __init__(self, source_ref, target_ref, faces, feature_edges=None, alpha: float = 100.0,
                 regularization: float = 1e-9, factor=None):
        S0 = check_positions(source_ref, "source_ref")
        V = len(S0)
        T0 = check_positions(target_ref, "target_ref", V)
        faces = check_faces(faces, V)
        if alpha < 0:
            raise ValueError(f"alpha: expected >= 0, got {alpha}")
        E = np.zeros((0, 2), np.int64) if feature_edges is None else np.asarray(feature_edges, dtype=np.int64).reshape(-1, 2)
        if E.size and (E.min() < 0 or E.max() >= V):
            raise ValueError(f"feature_edges: indices must lie in [0, {V})")
        self.S0, self.T0, self.faces, self.edges, self.alpha = S0, T0, faces, E, float(alpha)
        self.V, self.F = V, len(faces)
        self._inv0 = _safe_inv(triangle_frames(S0, faces))
        # target gradient operator and per-face weights a_f = A_f / mean(A)
        area = 0.5 * np.linalg.norm(face_cross(T0, faces), axis=1)
        mean_area = area[area > 0].mean() if (area > 0).any() else 1.0
        self.a = area / mean_area
        G = gradient(T0, faces)  # (3F, V)
        self.G = G
        self.Ga = (G.T @ sp.diags(np.tile(self.a, 3))).tocsr()  # G^T diag(a), (V, 3F)
        n = face_cross(T0, faces)
        nn = np.linalg.norm(n, axis=1, keepdims=True)
        n = np.divide(n, nn, out=np.zeros_like(n), where=nn > 0)
        self.P = np.eye(3)[None] - n[:, :, None] * n[:, None, :]  # (F, 3, 3)
        A = (self.Ga @ G).tocsr()
        if len(E):
            el = T0[E[:, 1]] - T0[E[:, 0]]
            self.e_t = el
            wl = 1.0 / np.maximum(np.einsum("ij,ij->i", el, el), 1e-300)
            self.wl = self.alpha * wl
            Bm = sp.csr_matrix((np.r_[-np.ones(len(E)), np.ones(len(E))],
                                (np.r_[np.arange(len(E)), np.arange(len(E))], np.r_[E[:, 0], E[:, 1]])), shape=(len(E), V))
            self.Bw = (Bm.T @ sp.diags(self.wl)).tocsr()  # B^T diag(w), (V, E)
            A = (A + self.Bw @ Bm).tocsr()

        Lu = uniform_laplacian(faces, V)
        self.reg = float(regularization) * A.diagonal().sum() / max(Lu.diagonal().sum(), 1e-300)
        self.reg_rhs = self.reg * np.asarray(Lu @ T0)  # (V, 3)
        A = (A + self.reg * Lu).tocsr()
        ncomp, labels = vertex_components(faces, V)
        self.solver = PinnedSolver(A, labels, ncomp, factor)
        self.scale = bbox_size(T0) / max(bbox_size(S0), 1e-300)

    def rhs(self, deformed: np.ndarray) -> np.ndarray:
        """(V, 3K) right-hand side of the normal equations for (K, V, 3) deformed sources."""
        K = len(deformed)
        D = triangle_frames(deformed, self.faces) @ self._inv0  # (K, F, 3, 3)
        J = D @ self.P  # desired target gradients (K, F, 3, 3): J[c, d] = d x_c / d d
        # stack as G's layout: row d*F + f, column (k, c)
        Jt = J.transpose(3, 1, 0, 2).reshape(3 * self.F, K * 3)  # [d, f] x [k, c]
        b = self.Ga @ Jt
        if len(self.edges):
            Dl = line_gradients(self.S0, deformed, self.edges)  # (K, E, 3, 3)
            tl = np.einsum("keij,ej->kei", Dl, self.e_t)  # (K, E, 3)
            b = b + self.Bw @ tl.transpose(1, 0, 2).reshape(len(self.edges), K * 3)
        return b

    def transfer(self, deformed) -> np.ndarray:
        """Target meshes (K, V, 3) for deformed source meshes (K, V, 3) or (V, 3) (eq. 9)."""
        d = np.asarray(deformed, dtype=np.float64)
        single = d.ndim == 2
        if single:
            d = d[None]
        if d.shape[1:] != (self.V, 3):
            raise ValueError(f"deformed: expected (K, {self.V}, 3), got {d.shape}")
        K = len(d)
        # one mesh at a time: the (K, F, 3, 3) temporaries of a batch outgrow the cache (10
        # bases of the 56K-vertex benchmark: 0.61 s at once, 0.39 s one by one); on two threads
        # when a core is free (numpy's stacked products run without the GIL; each mesh's
        # right-hand side is the same either way)
        if K > 1 and free_cores() > 1:
            with ThreadPoolExecutor(2) as pool:
                parts = list(pool.map(lambda k: self.rhs(d[k:k + 1]), range(K)))
        else:
            parts = [self.rhs(d[k:k + 1]) for k in range(K)]
        b = np.concatenate(parts, axis=1) + np.tile(self.reg_rhs, (1, K))
        # gauge: mean displacement per component = source's, scaled to the target's size
        src_mean = np.stack([self.solver.average @ (dk - self.S0) for dk in d])  # (K, C, 3)
        tgt_mean = self.solver.average @ self.T0  # (C, 3)
        mean = (tgt_mean[None] + self.scale * src_mean).transpose(1, 0, 2).reshape(-1, K * 3)
        x = self.solver.solve(b, mean)
        out = x.reshape(self.V, K, 3).transpose(1, 0, 2).copy()
        return out[0] if single else out


def deformation_transfer(source_ref, target_ref, faces, deformed, feature_edges=None, alpha: float = 100.0) -> np.ndarray:
    """One-call form of :class:`DeformationTransfer` (eq. 9): ``(K, V, 3)`` target meshes."""
    return DeformationTransfer(source_ref, target_ref, faces, feature_edges, alpha).transfer(deformed)
