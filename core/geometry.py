"""The one mesh layer: Laplacians, mass matrices, normals and frames, weld, alignment, registration.

libigl/gpytoolbox style: short noun names, ``(V, F)`` arguments, scipy.sparse outputs. Every
method that needs one of these operators calls the function here (one implementation per
algorithm, its variants as explicit options):

* operators: :func:`cotangent_laplacian`, :func:`gradient`, :func:`massmatrix`,
  :func:`uniform_laplacian`, :func:`vertex_adjacency`, :func:`vertex_face_incidence`;
* normals and frames: :func:`face_normals`, :func:`vertex_normals` (one mesh or a batch of
  poses, optionally across UV seams), :func:`vertex_frames` (Xu et al. 2014 §5.1);
* topology: :func:`weld_vertices` (UV-seam copies merged), :func:`boundary_loops`, :func:`edges`,
  :func:`vertex_components`, :func:`largest_component` (the skin); :func:`flipped_faces`
  (fold-overs); :func:`face_vertices` (what the shapes move); :func:`farthest_points`
  (virtual markers);
* alignment: :func:`procrustes` (Kabsch / Umeyama, weighted, batched), :func:`nonrigid_icp`
  with the schedule :func:`nricp_steps` (Amberg et al. 2007: trimesh's loop, faster, coarse to
  fine, with progress); :class:`ClosestPoints` (exact closest points on a mesh, KD-trees),
  :func:`closest_on_triangles`, :func:`harmonic_extension`;
* construction: :func:`marker_triangulation` (the mesh over a face's markers),
  :func:`decimate` (quadric, through pyvista).

Sign conventions (used everywhere in this package)
--------------------------------------------------
* :func:`cotangent_laplacian` and :func:`uniform_laplacian` are **positive semi-definite**
  (as gpytoolbox's ``cotangent_laplacian``; the negative of libigl's ``cotmatrix``):
  off-diagonal entries are ``-w_ij <= 0`` (for non-obtuse meshes), the diagonal is
  ``sum_j w_ij >= 0``, every row sums to 0, and ``x^T L x = 1/2 sum_ij w_ij (x_i - x_j)^2``
  is the Dirichlet energy. ``L @ V`` points *outwards* on a convex surface
  (``L V = -2 A H n`` with A the vertex area, H the mean curvature, n the outward normal).
* Faces are counter-clockwise seen from the side their normal points to (right-hand rule):
  ``n = (v1 - v0) x (v2 - v0) / |...|``.
* Degenerate triangles (area below ``eps * size**2`` with ``size`` the bounding-box diagonal)
  contribute nothing to the Laplacians or mass matrices instead of an inf/NaN cotangent; a
  vertex whose area-weighted normal sum is below the same bound has no normal (zero, or the
  ``fallback`` of :func:`vertex_normals`).
* Tolerances are relative to the model: ``DEGENERATE_EPS * size**2`` for areas,
  ``WELD_TOL * size`` for coincident vertices.
* Rigid motions act on row vectors as ``x -> s x R^T + t`` (``s R x + t`` per point), with
  ``R`` a proper rotation (``det R = +1``, never a reflection).

References
----------
.. [1] Pinkall & Polthier 1993, "Computing discrete minimal surfaces and their conjugates".
.. [2] Meyer, Desbrun, Schroeder, Barr 2003, "Discrete differential-geometry operators for
       triangulated 2-manifolds" (mixed Voronoi areas).
.. [3] Ribera et al. 2017, eq. 11 and 16 use the cotangent Laplacian of [1].
.. [4] Xu et al. 2014, "Controllable high-fidelity facial performance transfer", §5.1
       (per-vertex frames).
.. [5] Kabsch 1976, "A solution for the best rotation to relate two sets of vectors";
       Umeyama 1991, "Least-squares estimation of transformation parameters between two
       point patterns", eq. 40-42 (the similarity, with the reflection fix).
.. [6] Amberg, Romdhani & Vetter 2007, "Optimal step nonrigid ICP algorithms for surface
       registration".
.. [7] Garland & Heckbert 1997, "Surface simplification using quadric error metrics".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

#: relative area below which a triangle counts as degenerate (times size**2)
DEGENERATE_EPS = 1e-14
#: relative distance below which two vertices are one in :func:`weld_vertices` (times size)
WELD_TOL = 1e-9
#: face vertices: those some shape moves by more than this fraction of the largest move
FACE_FRACTION = 0.01


def _check_mesh(V, F, name="V"):
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] not in (2, 3):
        raise ValueError(f"{name}: expected vertex positions of shape (n, 3) or (n, 2), got {V.shape}")
    if V.shape[1] == 2:
        V = np.column_stack([V, np.zeros(len(V))])
    F = _check_faces(F, len(V))
    return V, F


def _check_faces(F, n=None):
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"F: expected triangle indices of shape (F, 3), got {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        if F.size and not np.all(F == np.round(F)):
            raise ValueError("F: expected integer vertex indices")
    F = F.astype(np.int64)
    if F.size and F.min() < 0:
        raise ValueError(f"F: vertex indices must be >= 0, got {F.min()}")
    if n is not None and F.size and F.max() >= n:
        raise ValueError(f"F: vertex index {F.max()} out of range for n={n} vertices")
    return F


def _size(V):
    return float(np.linalg.norm(V.max(0) - V.min(0))) if len(V) else 0.0


def doublearea(V, F):
    """Twice the area of every triangle, ``|(v1 - v0) x (v2 - v0)|``.

    Parameters
    ----------
    V : (n, 3) or (n, 2) float
    F : (F, 3) int

    Returns
    -------
    (F,) float64
    """
    V, F = _check_mesh(V, F)
    return np.linalg.norm(face_cross(V, F), axis=1)


def _cotangents(V, F):
    """(F, 3) cot of the angle at corner i of each triangle; 0 for degenerate faces.

    cot(angle at i) = (a . b) / |a x b| with a, b the edges leaving corner i.
    """
    cots = np.zeros((len(F), 3))
    cross2 = doublearea(V, F)
    ok = cross2 > DEGENERATE_EPS * max(_size(V), 1e-300) ** 2
    for i in range(3):
        a = V[F[:, (i + 1) % 3]] - V[F[:, i]]
        b = V[F[:, (i + 2) % 3]] - V[F[:, i]]
        cots[ok, i] = np.einsum("ij,ij->i", a[ok], b[ok]) / cross2[ok]
    return cots


def cotangent_laplacian(V, F):
    r"""Cotangent Laplacian, positive semi-definite.

    .. math:: L_{ij} = -\tfrac12(\cot\alpha_{ij} + \cot\beta_{ij}),\quad L_{ii} = -\sum_{j\ne i} L_{ij}

    with :math:`\alpha_{ij}, \beta_{ij}` the angles opposite edge ij (Pinkall & Polthier 1993;
    the operator of Ribera et al. 2017 eq. 11 and 16). ``L = G^T diag(A) G`` with G the
    per-face gradient (:func:`gradient`) and A the face areas.

    Parameters
    ----------
    V : (n, 3) or (n, 2) float
        Vertex positions.
    F : (F, 3) int
        Triangles.

    Returns
    -------
    L : (n, n) scipy.sparse.csr_matrix, float64, symmetric, rows summing to 0.

    Raises
    ------
    ValueError
        When ``V`` or ``F`` has the wrong shape or ``F`` indexes past ``V``.
    """
    V, F = _check_mesh(V, F)
    n = len(V)
    C = _cotangents(V, F)
    # the angle at corner i is opposite edge (i+1, i+2)
    I = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    J = np.concatenate([F[:, 2], F[:, 0], F[:, 1]])
    w = 0.5 * np.concatenate([C[:, 0], C[:, 1], C[:, 2]])
    W = sp.coo_matrix((w, (I, J)), shape=(n, n)).tocsr()
    W = W + W.T
    L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
    return L.tocsr()


def gradient(V, F):
    r"""Per-face gradient of a piecewise-linear function on the mesh.

    ``(G @ u)`` stacks the x, y, z components of the gradient on every face:
    rows ``[0, F)`` are d/dx, ``[F, 2F)`` d/dy, ``[2F, 3F)`` d/dz (gpytoolbox layout).
    On face (i, j, k) with unit normal n and double area 2A,
    :math:`\nabla u = \sum_i u_i\, (n \times e_i) / 2A` with :math:`e_i` the edge opposite i.

    Parameters
    ----------
    V : (n, 3) or (n, 2) float
    F : (F, 3) int

    Returns
    -------
    G : (3F, n) scipy.sparse.csr_matrix; zero rows on degenerate faces.
    """
    V, F = _check_mesh(V, F)
    n, m = len(V), len(F)
    N = face_cross(V, F)
    dbl = np.linalg.norm(N, axis=1)
    ok = dbl > DEGENERATE_EPS * max(_size(V), 1e-300) ** 2
    # hat-function gradients: grad phi_i = (n x e_i) / (2A), e_i = v_{i+2} - v_{i+1}
    scale = np.zeros(m)
    scale[ok] = 1.0 / dbl[ok] ** 2  # n/2A = N/|N|^2
    rows, cols, vals = [], [], []
    for i in range(3):
        e = V[F[:, (i + 2) % 3]] - V[F[:, (i + 1) % 3]]
        g = np.cross(N, e) * scale[:, None]
        for c in range(3):
            rows.append(np.arange(m) + c * m)
            cols.append(F[:, i])
            vals.append(g[:, c])
    G = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * m, n))
    return G.tocsr()


def massmatrix(V, F, kind="voronoi"):
    r"""Lumped (diagonal) mass matrix: the area each vertex stands for.

    * ``"barycentric"``: :math:`M_{ii} = \sum_{f \ni i} A_f / 3`.
    * ``"voronoi"``: mixed Voronoi area of Meyer et al. 2003 (Fig. 4): on a non-obtuse
      triangle the circumcentric Voronoi share
      :math:`\tfrac18\sum (|e|^2 \cot)`, on an obtuse one A/2 to the obtuse corner and A/4
      to the others. Both kinds sum to the total surface area.

    Parameters
    ----------
    V : (n, 3) or (n, 2) float
    F : (F, 3) int
    kind : {"voronoi", "barycentric"}

    Returns
    -------
    M : (n, n) scipy.sparse.dia_matrix (diagonal), float64.

    Raises
    ------
    ValueError
        Unknown ``kind`` or bad shapes.
    """
    if kind not in ("voronoi", "barycentric"):
        raise ValueError(f"kind: expected 'voronoi' or 'barycentric', got {kind!r}")
    V, F = _check_mesh(V, F)
    n = len(V)
    area = 0.5 * doublearea(V, F)
    if kind == "barycentric":
        per = np.repeat(area[:, None] / 3.0, 3, axis=1)
    else:
        C = _cotangents(V, F)
        sq = np.stack([np.sum((V[F[:, (i + 2) % 3]] - V[F[:, (i + 1) % 3]]) ** 2, axis=1) for i in range(3)], axis=1)
        # sq[:, i] = squared length of the edge opposite corner i
        per = np.zeros((len(F), 3))
        for i in range(3):
            j, k = (i + 1) % 3, (i + 2) % 3
            # Voronoi share of corner i: edges (i,j) and (i,k), weighted by cot of the opposite angles
            per[:, i] = (sq[:, k] * C[:, k] + sq[:, j] * C[:, j]) / 8.0
        obtuse = C < 0  # cot < 0 <=> angle > 90 degrees
        any_obtuse = obtuse.any(axis=1)
        per[any_obtuse] = np.where(obtuse[any_obtuse], 0.5, 0.25) * area[any_obtuse, None]
        degenerate = area <= 0.5 * DEGENERATE_EPS * max(_size(V), 1e-300) ** 2
        per[degenerate] = 0.0
    d = np.bincount(F.ravel(), weights=per.ravel(), minlength=n)
    return sp.diags(d).todia()


def edges(F):
    """Unique undirected edges ``(E, 2)`` with ``e[:, 0] < e[:, 1]``, sorted."""
    F = _check_faces(F)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    if not len(e):
        return np.zeros((0, 2), np.int64)
    e = np.sort(e, axis=1).astype(np.int64)
    # unique rows through one int64 key per edge (lexicographic order = key order): a 1-D
    # unique, about twice as fast as np.unique(axis=0)'s sort of structured rows
    m = int(e.max()) + 1
    key = np.unique(e[:, 0] * m + e[:, 1])
    return np.stack([key // m, key % m], axis=1)


def vertex_adjacency(F, n=None):
    """Symmetric 0/1 vertex adjacency: ``A_ij = 1`` when i and j share an edge.

    Parameters
    ----------
    F : (F, 3) int
    n : int, optional
        Vertex count (default ``F.max() + 1``); isolated vertices get empty rows.

    Returns
    -------
    A : (n, n) scipy.sparse.csr_matrix, float64, zero diagonal.
    """
    F = _check_faces(F, n)
    if n is None:
        n = int(F.max()) + 1 if F.size else 0
    # every half-edge both ways; the CSR conversion sums the duplicates (one pass, no unique of
    # the edge list), then each edge counts once (a face's repeated corner: 2 on the diagonal,
    # as (A + A^T) of the unique edges gave it)
    i = F.T.ravel()
    j = F[:, [1, 2, 0]].T.ravel()
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
    A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    A.sum_duplicates()
    A.data[:] = 1.0
    A.data[np.repeat(np.arange(n), np.diff(A.indptr)) == A.indices] = 2.0
    return A


def uniform_laplacian(F, n=None):
    r"""Graph (umbrella) Laplacian ``L = D - A``, positive semi-definite.

    :math:`L_{ii} = \deg(i)`, :math:`L_{ij} = -1` for every mesh edge ij; rows sum to 0.

    Parameters
    ----------
    F : (F, 3) int
    n : int, optional
        Vertex count (default ``F.max() + 1``).

    Returns
    -------
    L : (n, n) scipy.sparse.csr_matrix, float64.
    """
    A = vertex_adjacency(F, n)
    return (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()


def face_normals(V, F):
    """Unit face normals by the right-hand rule, ``(v1 - v0) x (v2 - v0)`` normalised.

    Parameters
    ----------
    V : (n, 3) float
    F : (F, 3) int

    Returns
    -------
    (F, 3) float64; a zero vector on a degenerate face.
    """
    V, F = _check_mesh(V, F)
    N = face_cross(V, F)
    nrm = np.linalg.norm(N, axis=1)
    ok = nrm > DEGENERATE_EPS * max(_size(V), 1e-300) ** 2
    out = np.zeros_like(N)
    out[ok] = N[ok] / nrm[ok, None]
    return out


def cross(a, b) -> np.ndarray:
    """Cross product over the last axis of (..., 3) arrays, in their dtype.

    The arithmetic of ``np.cross`` (same bits), without its axis-moving copies: ~3x faster on
    (T, F, 3) batches, which the transfer's per-frame normals and frames are.
    """
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    np.multiply(a1, b2, out=out[..., 0])
    out[..., 0] -= a2 * b1
    np.multiply(a2, b0, out=out[..., 1])
    out[..., 1] -= a0 * b2
    np.multiply(a0, b1, out=out[..., 2])
    out[..., 2] -= a1 * b0
    return out


def face_cross(V, F) -> np.ndarray:
    """Un-normalised face normals ``(v1 - v0) x (v2 - v0)`` of (n, 3) or (..., n, 3) positions.

    Their length is twice the triangle area. No validation (an inner kernel: the public
    functions validate); (..., F, 3) in the dtype of ``V``.
    """
    V = np.asarray(V)
    p0 = V[..., F[:, 0], :]
    return cross(V[..., F[:, 1], :] - p0, V[..., F[:, 2], :] - p0)


def flipped_faces(reference, positions, F) -> np.ndarray:
    r"""Fold-overs: triangles whose normal points against the reference's.

    .. math:: n_f(\text{positions}) \cdot n_f(\text{reference}) < 0

    with un-normalised normals (:func:`face_cross`), i.e. the normal turned by more than 90°;
    a degenerate (zero-area) triangle is never flipped. Compare against a reference in the same
    orientation (the neutral of a rig, the similarity-aligned source of a registration).

    Parameters
    ----------
    reference : (n, 3) float
    positions : (n, 3) or (..., n, 3) float, one mesh or a batch of poses
    F : (F, 3) int

    Returns
    -------
    (F,) or (..., F) bool
    """
    F = _check_faces(F)
    n0 = face_cross(np.asarray(reference, dtype=np.float64), F)
    n = face_cross(np.asarray(positions, dtype=np.float64), F)
    return np.einsum("...fi,fi->...f", n, n0) < 0


def vertex_face_incidence(F, n=None) -> sp.csr_matrix:
    """(n, F) 0/1 vertex-face incidence: ``I_vf = 1`` when face f has corner v.

    Parameters
    ----------
    F : (F, 3) int
    n : int, optional
        Vertex count (default ``F.max() + 1``).

    Returns
    -------
    (n, F) scipy.sparse.csr_matrix, float64; row v lists v's faces in increasing order.
    """
    F = _check_faces(F, n)
    if n is None:
        n = int(F.max()) + 1 if F.size else 0
    cols = np.repeat(np.arange(len(F)), 3)
    inc = sp.csr_matrix((np.ones(3 * len(F)), (F.ravel(), cols)), shape=(n, len(F)))
    inc.data[:] = 1.0  # a face listing a vertex twice is still one incidence
    return inc


def _check_poses(V, name="V"):
    """Positions (n, 3) or a batch (..., n, 3) as a floating array (its dtype kept)."""
    V = np.asarray(V)
    if not np.issubdtype(V.dtype, np.floating):
        V = V.astype(np.float64)
    if V.ndim == 2 and V.shape[1] == 2:
        V = np.concatenate([V, np.zeros((len(V), 1), V.dtype)], axis=1)
    if V.ndim < 2 or V.shape[-1] != 3:
        raise ValueError(f"{name}: expected vertex positions of shape (n, 3) or a batch (..., n, 3), got {V.shape}")
    return V


def vertex_normals(V, F, *, weld_index=None, fallback=None, incidence=None) -> np.ndarray:
    r"""Area-weighted unit vertex normals of one mesh or a batch of poses.

    .. math:: n_v = \frac{\sum_{f \ni v} N_f}{\|\sum_{f \ni v} N_f\|},
              \qquad N_f = (v_1 - v_0) \times (v_2 - v_0),\ |N_f| = 2 A_f

    so each face counts with its area. With ``weld_index`` the sum runs over every face of
    every vertex with the same welded id: the copies of a vertex along a UV seam get the one
    normal of the surface without the seam (shading and normal maps show no seam).

    One sparse product with the vertex-face incidence per chunk of poses (a few poses at a
    time keep the (F, chunk, 3) face normals cache-sized; a loop pose by pose or one product
    over all poses were both ~2x slower on ICT's 54 poses). The sums are those of a plain
    per-face loop in face order, so the result does not depend on the batch or its chunks.

    Parameters
    ----------
    V : (n, 3) or (..., n, 3) float
        Positions of one mesh, or a batch (T frames, K+1 poses) sharing ``F``. A floating
        dtype is kept (float32 stays float32: the transfer's per-frame work); others become
        float64.
    F : (F, 3) int
    weld_index : (n,) int, optional
        Welded id of every vertex (``weld_vertices(V, F).index``): normals computed across seams.
    fallback : (3,) float, optional
        The normal of a vertex that has none: on no face, on degenerate faces only, or where
        its faces cancel (sum below ``DEGENERATE_EPS * size**2``). Default the zero vector;
        glTF needs unit normals and writes +Z (:func:`core.io.gltf.write_rig`).
    incidence : (n, F) sparse, optional
        :func:`vertex_face_incidence` of ``F``, to reuse across calls.

    Returns
    -------
    (n, 3) or (..., n, 3), the dtype of ``V``.

    Raises
    ------
    ValueError
        Bad shapes, ``F`` indexing past ``V``, ``weld_index`` not (n,).
    """
    V = _check_poses(V)
    n = V.shape[-2]
    F = _check_faces(F, n)
    batch = V.shape[:-2]
    X = V.reshape((-1, n, 3))
    inc = vertex_face_incidence(F, n) if incidence is None else incidence
    if weld_index is not None:
        wi = np.asarray(weld_index)
        if wi.shape != (n,):
            raise ValueError(f"weld_index: expected ({n},) welded ids, one per vertex, got {wi.shape}")
        nw = int(wi.max()) + 1 if n else 0
        inc = (sp.csr_matrix((np.ones(n), (wi, np.arange(n))), shape=(nw, n)) @ inc).tocsr()
        inc.sort_indices()
        inc.data[:] = 1.0
    inc = inc.astype(X.dtype)
    size = float(np.linalg.norm(X.max(axis=(0, 1)) - X.min(axis=(0, 1)))) if X.size else 0.0
    small = DEGENERATE_EPS * max(size, 1e-300) ** 2
    out = np.empty_like(X)
    chunk = max(1, (1 << 17) // max(len(F), 1))
    for s in range(0, len(X), chunk):
        xt = X[s:s + chunk].transpose(1, 0, 2)  # (n, c, 3): face gathers copy whole rows
        p0 = xt[F[:, 0]]
        N = cross(xt[F[:, 1]] - p0, xt[F[:, 2]] - p0)  # (F, c, 3), |N| = 2A
        acc = (inc @ N.reshape(len(F), -1)).reshape(inc.shape[0], -1, 3)
        if weld_index is not None:
            acc = acc[wi]
        # |acc| summed in component order, as np.linalg.norm: the same bits as a per-pose loop
        nrm = np.sqrt(acc[..., 0] * acc[..., 0] + acc[..., 1] * acc[..., 1] + acc[..., 2] * acc[..., 2])[..., None]
        ok = nrm > small
        res = np.divide(acc, nrm, out=np.zeros_like(acc), where=ok)
        if fallback is not None:
            res = np.where(ok, res, np.asarray(fallback, dtype=X.dtype))
        out[s:s + chunk] = res.transpose(1, 0, 2)
    return out.reshape(batch + (n, 3))


def first_neighbour(F, n=None) -> np.ndarray:
    """(n,) one edge-neighbour per vertex, the lowest-index one; -1 for an isolated vertex."""
    F = _check_faces(F, n)
    if n is None:
        n = int(F.max()) + 1 if F.size else 0
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    e = e[np.lexsort((e[:, 1], e[:, 0]))]
    first = np.full(n, -1, dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, e[1:, 0] != e[:-1, 0]]) if len(e) else np.zeros(0, np.int64)
    first[e[starts, 0]] = e[starts, 1]
    return first


def _unit(x):
    n = np.sqrt(np.einsum("...i,...i->...", x, x))[..., None]
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def vertex_frames(V, F, neighbour=None, incidence=None):
    r"""Per-vertex orthonormal frames ``(t, b, n)`` (Xu et al. 2014 §5.1 [4]).

    ``n`` is the area-weighted unit normal (:func:`vertex_normals`) and ``t`` the edge to a
    fixed neighbour projected onto the tangent plane, normalised — "determined by its normal
    and a tangent vector, which is generated by projecting an edge originating from the vertex
    to its tangent plane" —; ``b = n x t``, so ``[t, b, n]`` is right-handed. Where the edge is
    (nearly) along the normal, below ``1e-6`` of the longest projected edge, or the vertex is
    isolated, ``t`` is the x (or y) axis projected instead.

    Parameters
    ----------
    V : (n, 3) or (..., n, 3) float (dtype kept, as :func:`vertex_normals`)
    F : (F, 3) int
    neighbour : (n,) int, optional
        The neighbour of each vertex; default :func:`first_neighbour`.
    incidence : (n, F) sparse, optional
        :func:`vertex_face_incidence`, to reuse.

    Returns
    -------
    t, b, n : each the shape and dtype of ``V``; ``np.stack((t, b, n), -1)`` is the matrix
    with ``world = frame @ local``.
    """
    x = _check_poses(V)
    n_v = x.shape[-2]
    F = _check_faces(F, n_v)
    nb = first_neighbour(F, n_v) if neighbour is None else np.asarray(neighbour)
    n = vertex_normals(x, F, incidence=incidence)
    nbi = np.where(nb < 0, np.arange(n_v), nb)
    t = x[..., nbi, :] - x
    t -= np.einsum("...i,...i->...", t, n)[..., None] * n
    tn = np.sqrt(np.einsum("...i,...i->...", t, t))
    bad = tn <= 1e-6 * (tn.max() if tn.size else 1.0)
    if bad.any():
        alt = np.where(np.abs(n[..., :1]) < 0.9, np.array([1.0, 0, 0], x.dtype), np.array([0, 1.0, 0], x.dtype))
        alt = alt - np.einsum("...i,...i->...", alt, n)[..., None] * n
        t = np.where(bad[..., None], alt, t)
    t = _unit(t)
    return t, cross(n, t), n


@dataclass(frozen=True, eq=False)
class Weld:
    """Result of :func:`weld_vertices`; unpacks as ``index, first, faces``.

    Attributes
    ----------
    index : (n,) int64     welded id of every input vertex
    first : (m,) int64     one input vertex per welded id, its first occurrence
                           (``V[first]`` are the welded positions)
    faces : (F', 3) int64  the faces in welded ids, faces that collapsed dropped
    kept : (F,) bool       the input faces that did not collapse (``faces = index[F][kept]``)
    """

    index: np.ndarray
    first: np.ndarray
    faces: np.ndarray
    kept: np.ndarray

    @property
    def n(self) -> int:
        """Number of welded vertices."""
        return len(self.first)

    def __iter__(self):
        # ``index, first, faces = weld_vertices(V, F)``, the form most callers take
        return iter((self.index, self.first, self.faces))


def weld_vertices(V, F, tol=None, *, attributes=None) -> Weld:
    r"""Merge coincident vertices: the copies a rig makes along its UV seams.

    A UV seam cuts the mesh into islands joined by nothing; every Laplacian, adjacency,
    normal and connected-component computation that should see one surface runs on the
    welded mesh. Vertices i and j are one when

    .. math:: \operatorname{round}(x_i / \mathrm{tol}) = \operatorname{round}(x_j / \mathrm{tol})

    for their positions and, when given, their ``attributes`` (a grid of spacing ``tol``:
    seam copies, equal to the last bit, always merge; two distinct vertices closer than
    ``tol`` may stay apart when they straddle a cell). ``tol=0`` asks for bit-identical
    values (``-0.0`` and ``0.0`` are equal). Welded ids follow the first occurrence, so a
    mesh without duplicates keeps its numbering.

    Parameters
    ----------
    V : (n, 3) float
    F : (F, 3) int
    tol : float, optional
        Default ``WELD_TOL * size`` (bounding-box diagonal); 0 for exact equality.
    attributes : (..., n, c) float, optional
        Values that must agree too, in the units of ``V`` (blendshape deltas (K, n, 3):
        closed lips touch at rest but move apart, so they stay two vertices).

    Returns
    -------
    Weld(index, first, faces, kept)

    Raises
    ------
    ValueError
        Bad shapes, a negative tolerance, ``attributes`` without n rows.
    """
    V, F = _check_mesh(V, F)
    n = len(V)
    tol = WELD_TOL * max(_size(V), 1e-300) if tol is None else float(tol)
    if not tol >= 0:
        raise ValueError(f"tol: expected a distance >= 0, got {tol}")
    key = V
    if attributes is not None:
        a = np.asarray(attributes, dtype=np.float64)
        if a.ndim < 2 or a.shape[-2] != n:
            raise ValueError(f"attributes: expected (..., {n}, c) values per vertex, got {a.shape}")
        key = np.concatenate([V, np.moveaxis(a, -2, 0).reshape(n, -1)], axis=1)
    if tol > 0:
        key = np.round(key / tol).astype(np.int64)
    else:
        key = np.ascontiguousarray(key + 0.0)  # -0.0 -> 0.0
    # one row as one opaque value (its bytes): equal rows are equal keys
    rows = key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # welded ids by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse.ravel()].astype(np.int64)
    wf = index[F]
    ok = (wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 0] != wf[:, 2])
    return Weld(index, first[order].astype(np.int64), wf[ok], ok)


def vertex_components(F, n=None) -> tuple[int, np.ndarray]:
    """Connected components of the mesh's vertex graph (``scipy.sparse.csgraph``).

    Parameters
    ----------
    F : (F, 3) int
    n : int, optional
        Vertex count (default ``F.max() + 1``); an isolated vertex is a component of its own.

    Returns
    -------
    count : int, labels : (n,) int32 component of every vertex
    """
    F = _check_faces(F, n)
    if n is None:
        n = int(F.max()) + 1 if F.size else 0
    rows = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    cols = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return connected_components(A, directed=False)


def largest_component(V, F) -> np.ndarray:
    """(F,) bool: the triangles of the mesh's largest connected part (most triangles), after
    merging the UV-seam copies (:func:`weld_vertices`, default tolerance) — the skin of a head, without
    its separate eyeballs, teeth, tongue, hair cards or jewellery. Triangles that collapse in
    the weld are not part of it.

    Parameters
    ----------
    V : (n, 3) float, F : (F, 3) int

    Returns
    -------
    (F,) bool
    """
    w = weld_vertices(V, F)
    out = np.zeros(len(w.kept), dtype=bool)
    if not len(w.faces):
        return out
    _, label = vertex_components(w.faces, w.n)
    face_label = label[w.faces[:, 0]]
    out[np.flatnonzero(w.kept)[face_label == np.bincount(face_label).argmax()]] = True
    return out


def face_vertices(deltas, fraction: float = FACE_FRACTION) -> np.ndarray:
    r"""(V,) bool: the face, the vertices some shape moves by more than ``fraction`` of the
    largest move,

    .. math:: \max_k \|d_{kv}\| > \text{fraction} \cdot \max_{k, u} \|d_{ku}\|

    (the skull, neck and eyeball interiors that no shape moves are left out).

    Parameters
    ----------
    deltas : (K, V, 3) float, a rig's blendshape deltas
    fraction : float in [0, 1), default :data:`FACE_FRACTION`

    Returns
    -------
    (V,) bool, True on the face

    Raises
    ------
    ValueError
        ``deltas`` not (K, V, 3).
    """
    d = np.asarray(deltas)
    if d.ndim != 3 or d.shape[2] != 3:
        raise ValueError(f"deltas: expected blendshape deltas of shape (K, V, 3), got {d.shape}")
    move = np.linalg.norm(d, axis=2).max(0)
    return move > fraction * move.max()


def boundary_loops(F):
    """Ordered boundary loops (holes: eyes, mouth, the neck cut), longest first.

    A boundary edge is an undirected edge used by exactly one face. Each loop follows the
    boundary edges in the direction the faces give them, so a loop runs with the surface on
    its left seen from the normal side (an outer rim is walked counter-clockwise, a hole's
    rim clockwise). Where a vertex has several outgoing boundary edges (a non-manifold
    "bow tie" vertex) the walk takes them in index order; every boundary edge ends up in
    exactly one loop.

    Parameters
    ----------
    F : (F, 3) int

    Returns
    -------
    list of (m_i,) int64 arrays, vertex indices in order, the first vertex not repeated.
    """
    F = _check_faces(F)
    if not len(F):
        return []
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.sort(directed, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    bd = directed[counts[inv.ravel()] == 1]
    # hand-written walk: trimesh's outline() gives unordered Path entities and loses the
    # face orientation; following next-pointers is a few lines
    nxt = {}
    for a, b in bd:
        nxt.setdefault(int(a), []).append(int(b))
    for v in nxt:
        nxt[v].sort(reverse=True)
    loops = []
    for start in sorted(nxt):
        while nxt.get(start):
            loop = [start]
            cur = nxt[start].pop()
            while cur != start:
                loop.append(cur)
                if not nxt.get(cur):
                    break  # open chain on a malformed mesh: keep what we walked
                cur = nxt[cur].pop()
            loops.append(np.array(loop, dtype=np.int64))
    loops.sort(key=len, reverse=True)
    return loops


def farthest_points(points, n: int, start=0) -> np.ndarray:
    """Indices of ``n`` well-spread points by greedy farthest-point sampling from ``start``.

    Each next point maximises its distance to the points chosen so far (Gonzalez 1985, a
    2-approximation of the k-centre problem). Used to place virtual markers on a mesh and to
    suggest the frames to pose (:func:`core.examples.suggest_poses`, points in expression space).

    Parameters
    ----------
    points : (N, D) float
    n : int, 1 <= n <= N — how many indices in all, ``start`` included
    start : index of the first point, or a sequence of indices already chosen (returned first)

    Returns
    -------
    (n,) int
    """
    P = np.asarray(points, dtype=np.float64)
    chosen = [int(i) for i in np.atleast_1d(start)]
    if not max(1, len(chosen)) <= n <= len(P):
        raise ValueError(f"farthest_points: n must lie in [{max(1, len(chosen))}, {len(P)}], got {n}")
    d = np.full(len(P), np.inf)
    for c in chosen:
        d = np.minimum(d, np.linalg.norm(P - P[c], axis=1))
    for _ in range(n - len(chosen)):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(P - P[i], axis=1))
    return np.asarray(chosen)


# ---------------------------------------------------------------------------------------------
# alignment
# ---------------------------------------------------------------------------------------------


def procrustes(src, dst, weights=None, *, scale=False):
    r"""Least-squares rigid (Kabsch) or similarity (Umeyama) alignment, weighted and batched.

    .. math:: \min_{s > 0,\, R \in SO(3),\, t} \sum_i w_i \|s R p_i + t - q_i\|^2

    Closed form [5]: with the weighted centroids :math:`\bar p, \bar q`, the cross-covariance
    :math:`\Sigma = \sum_i w_i (q_i - \bar q)(p_i - \bar p)^T / \sum_i w_i = U S V^T` and
    :math:`D = \operatorname{diag}(1, 1, \det U \det V)`:

    .. math:: R = U D V^T, \quad s = \frac{\operatorname{tr}(S D)}{\sigma_p^2}, \quad
              t = \bar q - s R \bar p, \qquad
              \sigma_p^2 = \sum_i w_i \|p_i - \bar p\|^2 / \sum_i w_i

    (Umeyama 1991 eq. 40-42; ``scale=False`` is Kabsch 1976, s = 1). D keeps R a rotation
    when the best orthogonal map would be a reflection.

    Hand-written: trimesh's and scipy's versions align one point set per call and the
    stabilisation aligns every frame of a take (T up to 10^4) in one batched SVD.

    Parameters
    ----------
    src : (N, 3) or (..., N, 3) float
        Points to move (a shared reference broadcasts against a batch of ``dst``).
    dst : (N, 3) or (..., N, 3) float
        Their targets; may be NaN where the weight is 0 (a missing marker).
    weights : (N,) or (..., N) float >= 0, optional
        Default all 1. A batch item whose weights sum to 0 gets ``R = I``, ``t = 0``.
    scale : bool
        Fit the scale (similarity) instead of s = 1 (rigid).

    Returns
    -------
    s : float or (...) float64 (1 when ``scale=False`` or the source has no spread)
    R : (3, 3) or (..., 3, 3), ``det R = +1``
    t : (3,) or (..., 3)

    Raises
    ------
    ValueError
        ``src``/``dst`` not point sets of N >= 3 (or not broadcasting), bad ``weights``.
    """
    p = np.asarray(src, dtype=np.float64)
    q = np.asarray(dst, dtype=np.float64)
    try:
        shape = np.broadcast_shapes(p.shape, q.shape)
    except ValueError:
        shape = None
    if shape is None or p.ndim < 2 or q.ndim < 2 or shape[-1] != 3 or shape[-2] < 3 or p.shape[-2:] != q.shape[-2:]:
        raise ValueError(f"procrustes: src and dst must be (N>=3, 3) point sets (or batches (..., N, 3) that broadcast), "
                         f"got {p.shape} and {q.shape}")
    w = np.ones(shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    try:
        w = np.broadcast_to(w, shape[:-1])
    except ValueError:
        raise ValueError(f"weights: expected {shape[:-1]} (one per point), got {w.shape}") from None
    if (w < 0).any():
        raise ValueError("weights: must be >= 0")
    q = np.where(w[..., None] > 0, q, 0.0)
    wn = w / np.maximum(w.sum(-1, keepdims=True), 1e-300)
    mp = np.einsum("...n,...nc->...c", wn, np.broadcast_to(p, shape))
    mq = np.einsum("...n,...nc->...c", wn, q)
    a = p - mp[..., None, :]
    b = q - mq[..., None, :]
    cov = np.einsum("...n,...ni,...nj->...ij", wn, b, a)
    U, S, Vt = np.linalg.svd(cov)
    d = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)
    D = np.ones(d.shape + (3,))
    D[..., 2] = d
    R = np.einsum("...ij,...j,...jk->...ik", U, D, Vt)
    if scale:
        var = np.einsum("...n,...n->...", wn, (a * a).sum(-1))
        s = np.where(var > 0, (S * D).sum(-1) / np.where(var > 0, var, 1.0), 1.0)
    else:
        s = np.ones(d.shape)
    t = mq - s[..., None] * np.einsum("...ij,...j->...i", R, mp)
    return (float(s) if s.ndim == 0 else s), R, t


#: the stiffness, landmark and normal weights of the four steps of :func:`nricp_steps`
_NRICP_STIFFNESS = (0.02, 0.007, 0.002)
_NRICP_LANDMARK = (10.0, 5.0, 2.5, 1.0)
_NRICP_NORMAL = 0.5


def nricp_steps(iterations=10, final_stiffness: float = 5e-4, final_normal: float = 0.0) -> tuple:
    r"""The stiff-to-supple schedule of :func:`nonrigid_icp`: four ``(ws, wl, wn, max_iter)``.

    Stiffness ``ws`` = 0.02, 0.007, 0.002, ``final_stiffness`` (almost affine, then supple),
    landmark weight ``wl`` = 10, 5, 2.5, 1, normal weight ``wn`` = 0.5 and ``final_normal``
    in the last step, in the frame :func:`nonrigid_icp` works in (the source at unit
    bounding-box diagonal), tuned on the bundled rigs.

    The callers' variants:

    * layout transfer (:func:`core.registration.transfer_layout`): ``iterations=(6, 6, 6, 4)``,
      ``final_stiffness=7e-4`` — a few seconds per rig pair on a decimated face region;
    * dense correspondence (:func:`core.transfer.correspond.register`): the defaults, and
      ``final_normal=0.5`` for a cropped face (the last, supple step keeps the normal term so
      the face is not pulled onto target surface that faces another way).

    Parameters
    ----------
    iterations : int or 4 ints
        Maximum iterations per step (a step also ends when the error stops decreasing).
    final_stiffness, final_normal : float
        ``ws`` and ``wn`` of the last step.

    Returns
    -------
    tuple of 4 tuples (ws, wl, wn, max_iter)
    """
    it = (iterations,) * 4 if np.ndim(iterations) == 0 else tuple(iterations)
    if len(it) != 4:
        raise ValueError(f"iterations: expected one count or 4 (one per step), got {iterations!r}")
    ws = _NRICP_STIFFNESS + (final_stiffness,)
    wn = (_NRICP_NORMAL,) * 3 + (final_normal,)
    return tuple((ws[k], _NRICP_LANDMARK[k], wn[k], int(it[k])) for k in range(4))


def closest_on_triangles(P, A, B, C):
    r"""Closest point of each point ``P[i]`` on triangle ``(A[i], B[i], C[i])``, with its
    barycentric coordinates (Ericson 2005, "Real-Time Collision Detection" §5.1.5).

    Vectorised over (n, 3) arrays: the seven Voronoi regions of the triangle (three vertices,
    three edges, the face) are tested in order and the first that holds gives the answer.
    Degenerate triangles fall into a vertex or edge region (no division by a zero area).

    Returns
    -------
    points : (n, 3), barycentric : (n, 3) float64 (rows sum to 1, the weights of A, B, C)
    """
    P, A, B, C = (np.asarray(x, dtype=np.float64) for x in (P, A, B, C))
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = P - B
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = P - C
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    bary = np.zeros((len(P), 3))
    done = np.zeros(len(P), bool)

    def take(mask, u, v, w):
        m = mask & ~done
        bary[m, 0], bary[m, 1], bary[m, 2] = u[m], v[m], w[m]
        done[m] = True

    one, zero = np.ones(len(P)), np.zeros(len(P))
    with np.errstate(divide="ignore", invalid="ignore"):
        take((d1 <= 0) & (d2 <= 0), one, zero, zero)                          # vertex A
        take((d3 >= 0) & (d4 <= d3), zero, one, zero)                         # vertex B
        t = d1 / (d1 - d3)
        take((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, zero)              # edge AB
        take((d6 >= 0) & (d5 <= d6), zero, zero, one)                         # vertex C
        t = d2 / (d2 - d6)
        take((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, zero, t)              # edge AC
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        take((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), zero, 1 - t, t)    # edge BC
        den = va + vb + vc
        v, w = vb / den, vc / den
        take(np.isfinite(v) & np.isfinite(w), 1 - v - w, v, w)                # face
    take(np.ones(len(P), bool), one, zero, zero)  # nothing held (NaN input): vertex A
    pts = bary[:, :1] * A + bary[:, 1:2] * B + bary[:, 2:] * C
    return pts, bary


class ClosestPoints:
    r"""Exact closest points on a triangle mesh for many query points, by KD-trees.

    For a query ``q`` the triangles around its nearest mesh vertex give a first closest
    point at distance ``d_0`` (an upper bound). A triangle with a point within ``d_0`` of
    ``q`` has its centroid ``c_f`` within ``d_0 + R_f`` of ``q``, ``R_f`` its largest
    centroid-to-corner distance; so the nearest centroids up to that radius hold the closest
    triangle, and the exact closest point on each (:func:`closest_on_triangles`) decides.
    Triangles are grouped by ``R`` (powers of two), one centroid tree per group, so one large
    triangle does not widen every query; each group is queried for the k nearest centroids,
    k doubled for the queries whose k-th centroid is still inside the radius.

    Hand-written because ``trimesh.proximity.closest_point`` (an R-tree query per point and
    Python-level candidate lists) took 0.45 s per call for the 14K ICT vertices on the 4.5K
    Rocketbox triangles, 4 s of every registration, and missed the closest triangle of 2 %
    of the points (by up to 0.03 mm); this one is exact (tested against brute force).

    Parameters
    ----------
    V : (n, 3) float, F : (F, 3) int
        The mesh; only vertices that some triangle uses count.
    """

    def __init__(self, V, F):

        V, F = _check_mesh(V, F)
        if len(F) == 0:
            raise ValueError("F: the mesh to find closest points on has no triangles")
        self.V, self.F = V, F
        self._fn = None  # unit face normals, when a query filters by normal
        used = np.unique(F)
        self._vtree = cKDTree(V[used])
        # the triangles around each used vertex (CSR rows of the incidence)
        self._ring = vertex_face_incidence(F, len(V))[used].tocsr()
        tri = V[F]
        c = tri.mean(axis=1)
        R = np.linalg.norm(tri - c[:, None], axis=2).max(axis=1)
        level = np.floor(np.log2(np.maximum(R, 1e-300) / max(R.max(), 1e-300))).clip(-60, 0)
        self._groups = []
        for lv in np.unique(level)[::-1]:
            ids = np.flatnonzero(level == lv)
            self._groups.append((ids, cKDTree(c[ids]), R[ids]))

    def _best(self, P, q, f, best, normals=None, min_dot=0.0):
        """Closest points of the pairs (query q (sorted), triangle f); keep the better one per query."""
        if normals is not None and len(q):
            ok = np.einsum("ij,ij->i", self._fn[f], normals[q]) >= min_dot
            q, f = q[ok], f[ok]
        if len(q) == 0:
            return
        d2b, fb, bb, pb = best
        T = self.F[f]
        pts, b = closest_on_triangles(P[q], self.V[T[:, 0]], self.V[T[:, 1]], self.V[T[:, 2]])
        d2 = ((pts - P[q]) ** 2).sum(1)
        # q is sorted: the first smallest entry of each run of equal q
        start = np.flatnonzero(np.r_[True, q[1:] != q[:-1]])
        seg = np.repeat(np.arange(len(start)), np.diff(np.r_[start, len(q)]))
        at = np.flatnonzero(d2 == np.minimum.reduceat(d2, start)[seg])
        first = at[np.r_[True, seg[at][1:] != seg[at][:-1]]]
        qq = q[first]
        better = d2[first] < d2b[qq]
        qq, first = qq[better], first[better]
        d2b[qq], fb[qq], bb[qq], pb[qq] = d2[first], f[first], b[first], pts[first]

    def query(self, P, max_distance: float = np.inf, normals=None, min_dot: float = 0.0):
        """Closest points of ``P`` (m, 3) on the mesh.

        Parameters
        ----------
        P : (m, 3) float
        max_distance : float
            Points farther than this from the surface get ``distance = inf``, ``triangle =
            -1`` and themselves as the closest point.
        normals : (m, 3) float, optional
            Unit normals of the queries: only triangles whose unit normal ``n_f`` has
            ``n_f · normal >= min_dot`` count (the closest point on the sheet facing the same
            way: upper and lower lips in contact are told apart). Give a finite
            ``max_distance`` with it: a query whose nearby triangles all face away searches
            up to there.

        Returns
        -------
        points (m, 3), distance (m,), triangle (m,) int, barycentric (m, 3)
        """
        P = np.asarray(P, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3:
            raise ValueError(f"P: expected query points of shape (m, 3), got {P.shape}")
        m = len(P)
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float64)
            if normals.shape != P.shape:
                raise ValueError(f"normals: expected {P.shape} (one per query point), got {normals.shape}")
            if self._fn is None:
                self._fn = face_normals(self.V, self.F)
        best = (np.full(m, np.inf), np.full(m, -1, np.int64), np.zeros((m, 3)), P.copy())
        _, nv = self._vtree.query(P)
        ring = self._ring[nv]
        self._best(P, np.repeat(np.arange(m), np.diff(ring.indptr)), ring.indices, best, normals, min_dot)
        bound = np.minimum(np.sqrt(best[0]), max_distance) * (1 + 1e-12)
        for ids, tree, R in self._groups:
            rows = np.arange(m)
            k, lo = min(8, len(ids)), 0
            while len(rows):
                dd, ii = tree.query(P[rows], k=k)
                dd, ii = dd.reshape(len(rows), k)[:, lo:], ii.reshape(len(rows), k)[:, lo:]
                r_hit, c_hit = np.nonzero(dd <= bound[rows, None] + R[ii])
                self._best(P, rows[r_hit], ids[ii[r_hit, c_hit]], best, normals, min_dot)
                if k >= len(ids):
                    break
                rows = rows[dd[:, -1] <= bound[rows] + R.max()]
                k, lo = min(2 * k, len(ids)), k
        d2, f, b, pts = best
        dist = np.sqrt(d2)
        far = dist > max_distance
        dist[far], f[far], b[far], pts[far] = np.inf, -1, 0.0, P[far]
        return pts, dist, f, b


def closest_points(P, V, F, max_distance: float = np.inf):
    """Closest points of ``P`` on the mesh ``(V, F)``: :class:`ClosestPoints`\\ ``(V, F).query(P)``."""
    return ClosestPoints(V, F).query(P, max_distance)


def harmonic_extension(values, mask, F, n: Optional[int] = None) -> np.ndarray:
    r"""Harmonic extension of per-vertex ``values`` given on ``mask`` to every vertex.

    .. math:: L_{ff}\, y_f = -L_{fc}\, y_c, \qquad y_c = \text{values}

    with the graph Laplacian ``L = D - A`` (:func:`uniform_laplacian`; each free vertex the
    mean of its neighbours): by the maximum principle every component stays within the range
    of the given values. A ``1e-9`` ridge gives 0 on parts not connected to ``mask``.

    Parameters
    ----------
    values : (|mask|, c) float, the values on ``mask``'s vertices in increasing vertex order
    mask : (n,) bool
    F : (F, 3) int
    n : int, optional (default ``len(mask)``)

    Returns
    -------
    (n, c) float64
    """

    mask = np.asarray(mask, bool)
    n = len(mask) if n is None else n
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or len(values) != int(mask.sum()):
        raise ValueError(f"values: expected ({int(mask.sum())}, c), one row per masked vertex, got {values.shape}")
    L = uniform_laplacian(F, n)
    free = np.flatnonzero(~mask)
    out = np.zeros((n, values.shape[1]))
    out[mask] = values
    if len(free) == 0:
        return out
    Lf = L[free]
    Lff = Lf[:, free] + 1e-9 * sp.eye(len(free), format="csr")
    out[free] = spla.splu(Lff.tocsc()).solve(np.asarray(-(Lf[:, np.flatnonzero(mask)] @ values)))
    return out


def _coarse_subset(V, F, n_coarse: int, keep) -> tuple:
    """A coarse mesh on a subset of ``V``'s vertices: the quadric decimation
    (:func:`decimate`) to about ``n_coarse`` vertices, each decimated vertex replaced by a
    distinct nearest vertex of ``V``, the ``keep`` vertices (landmarks) always among them.
    Returns ``(ids (m,) int into V, faces (F', 3) into ids)``."""

    Vd, Fd, _ = decimate(V, F, max_vertices=n_coarse)
    tree = cKDTree(V)
    kk = min(16, len(V))
    dd, cand = tree.query(Vd, k=kk)
    ids = np.full(len(Vd), -1, np.int64)
    taken = np.zeros(len(V), bool)
    keep = np.unique(np.asarray(keep, dtype=np.int64))
    # landmarks first: each takes the decimated vertex nearest to it
    if len(keep):
        _, near = cKDTree(Vd).query(V[keep], k=min(8, len(Vd)))
        for v, row in zip(keep, np.atleast_2d(near)):
            free = [j for j in np.atleast_1d(row) if ids[j] < 0]
            if free:
                ids[free[0]] = v
                taken[v] = True
    for j in np.argsort(dd[:, 0], kind="stable"):
        if ids[j] >= 0:
            continue
        for c in cand[j]:
            if not taken[c]:
                ids[j], taken[c] = c, True
                break
    ok = ids >= 0
    remap = np.cumsum(ok) - 1
    Fc = remap[Fd[ok[Fd].all(1)]]
    Fc = Fc[(Fc[:, 0] != Fc[:, 1]) & (Fc[:, 1] != Fc[:, 2]) & (Fc[:, 0] != Fc[:, 2])]
    return ids[ok], Fc


def _block_pcg(A, B, X0, precond, rtol: float, maxiter: int):
    """Preconditioned conjugate gradients for ``A X = B`` with several right-hand sides
    (independent per column, one preconditioner call for all columns: scipy's ``cg`` takes
    one column at a time). Returns X, or None when a column's relative residual is still
    above ``rtol`` after ``maxiter`` iterations."""
    X = np.array(X0, dtype=np.float64)
    R = B - A @ X
    bn = np.maximum(np.linalg.norm(B, axis=0), 1e-300)
    if (np.linalg.norm(R, axis=0) <= rtol * bn).all():
        return X
    Z = precond(R)
    Pd = Z.copy()
    rz = (R * Z).sum(0)
    for _ in range(maxiter):
        AP = A @ Pd
        alpha = rz / np.where((Pd * AP).sum(0) != 0, (Pd * AP).sum(0), 1.0)
        X += alpha * Pd
        R -= alpha * AP
        if (np.linalg.norm(R, axis=0) <= rtol * bn).all():
            return X
        Z = precond(R)
        rz_new = (R * Z).sum(0)
        Pd = Z + (rz_new / np.where(rz != 0, rz, 1.0)) * Pd
        rz = rz_new
    return None


def _nicp_loop(Vn, F, target, tnormals, TF, lm, steps, X, threshold, eps, report, trimesh_normals):
    """The iterations of :func:`nonrigid_icp` in the unit frame; returns the maps X (n, 4, 3)."""

    n = len(Vn)
    lm_v, lm_r, lm_p = lm
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    w_e = 1.0 / np.maximum(np.linalg.norm(Vn[E[:, 0]] - Vn[E[:, 1]], axis=1), 1e-300)
    rows = np.arange(len(E))
    Minc = sp.csr_matrix((np.r_[w_e, -w_e], (np.r_[rows, rows], np.r_[E[:, 0], E[:, 1]])), shape=(len(E), n))
    K = sp.kron((Minc.T @ Minc).tocsr(), sp.identity(4, format="csr"), format="csr")
    bi = np.repeat(np.arange(4 * n).reshape(n, 4), 4, axis=1).ravel()
    bj = np.tile(np.arange(4 * n).reshape(n, 4), (1, 4)).ravel()
    Dh = np.hstack([Vn, np.ones((n, 1))])
    lm_blocks = np.zeros((n, 4, 4))
    np.add.at(lm_blocks, lm_v, lm_r[:, :, None] * lm_r[:, None, :])
    lm_rhs = np.zeros((n, 4, 3))
    np.add.at(lm_rhs, lm_v, lm_r[:, :, None] * lm_p[:, None, :])
    if trimesh_normals:

        DN = np.hstack([trimesh.Trimesh(Vn, F, process=False).vertex_normals, np.ones((n, 1))])
    inc = vertex_face_incidence(F, n)
    current = np.einsum("ni,nic->nc", Dh, X)
    for k, (ws, wl, wn, max_iter) in enumerate(steps):
        last_error, error = np.finfo(np.float32).max, np.finfo(np.float16).max
        it, lu = 0, None
        while last_error - error > eps and (max_iter is None or it < max_iter):
            u, dist, tid, bary = target.query(current, max_distance=threshold)
            weight = (dist <= threshold).astype(np.float64)
            if wn > 0:
                tn = np.einsum("ij,ijk->ik", bary, tnormals[TF[np.maximum(tid, 0)]])
                sn = np.einsum("ni,nic->nc", DN, X) if trimesh_normals else vertex_normals(current, F, incidence=inc)
                weight *= np.clip(np.einsum("ij,ij->i", sn, tn), 0, 1) ** wn
            w2 = weight ** 2
            blocks = w2[:, None, None] * Dh[:, :, None] * Dh[:, None, :] + wl ** 2 * lm_blocks
            A = ws ** 2 * K + sp.csr_matrix((blocks.ravel(), (bi, bj)), shape=(4 * n, 4 * n))
            rhs = (w2[:, None, None] * Dh[:, :, None] * u[:, None, :] + wl ** 2 * lm_rhs).reshape(4 * n, 3)
            # a 1e-12 relative ridge towards the current maps: a part without matches or
            # landmarks keeps its maps instead of making the system singular
            ridge = 1e-12 * float(A.diagonal().mean())
            A = A + ridge * sp.identity(4 * n, format="csr")
            rhs += ridge * X.reshape(4 * n, 3)
            # symmetric positive definite: no pivoting, a minimum-degree ordering of A^T + A.
            # Within a step only the data weights change: the step's first factorisation
            # preconditions conjugate gradients for the later iterations (warm-started at the
            # current maps), refactored when they do not converge
            X_new = None
            if lu is not None:
                X_new = _block_pcg(A, rhs, X.reshape(4 * n, 3), lu.solve, rtol=1e-10, maxiter=40)
            if X_new is None:
                lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options=dict(SymmetricMode=True))
                X_new = lu.solve(rhs)
            X = X_new.reshape(n, 4, 3)
            current = np.einsum("ni,nic->nc", Dh, X)
            last_error = error
            error = float((np.linalg.norm(u - current, axis=1) * weight).mean())
            it += 1
            report(k, it, max_iter, error)
    return X


def nonrigid_icp(V, F, target_V, target_F, landmarks=None, landmark_positions=None, steps=None,
                 distance_threshold: float = 0.1, progress=None, eps: float = 1e-4, coarse: Optional[int] = None,
                 fine_iterations: int = 4, normals: str = "trimesh") -> np.ndarray:
    r"""Deform a mesh onto a target surface by optimal-step non-rigid ICP [6].

    Per-vertex affine maps :math:`X_i` (4x3) minimise, for each step's stiffness
    :math:`\alpha` (``ws``) and landmark weight :math:`\beta` (``wl``),

    .. math:: E(X) = \sum_i w_i^2 \|X_i^T \tilde v_i - u_i\|^2
              + \alpha^2 \sum_{(i,j)} \|X_i - X_j\|_F^2 / \ell_{ij}^2
              + \beta^2 \sum_l \|X_l^T \tilde v_l - p_l\|^2

    (Amberg et al. 2007 eq. 12, G = I₄) with :math:`\tilde v = (v, 1)`, :math:`u_i` the
    closest target point, :math:`w_i` 0 for matches farther than ``distance_threshold`` and
    :math:`\cos^{wn}` of the angle between source and target normals (clipped at 0), the sum
    over the directed edges of every face (an interior edge counts twice), :math:`\ell_{ij}`
    its rest length. Each step iterates closest points and the sparse normal equations

    .. math:: \big(\alpha^2 (M^T M \otimes I_4) + \mathrm{blockdiag}_i(w_i^2 \tilde v_i \tilde v_i^T)
              + \beta^2 \mathrm{blockdiag}_l(\tilde v_l \tilde v_l^T)\big) X = D^T W^2 U + \beta^2 D_l^T P

    until the mean weighted match error falls by less than ``eps`` or ``max_iter`` is
    reached. This is the loop of ``trimesh.registration.nricp_amberg`` (equal to it to
    5e-8 of the unit frame when both use exact closest points; tested), written here
    because that one (a) has no progress callback, (b) factors the symmetric positive
    definite 4n x 4n system with a general LU (``spsolve``, COLAMD; here SuperLU in
    symmetric mode with a minimum-degree ordering: 1.7x faster, 35 % less fill on ICT) and
    builds its right-hand side as a ``lil_matrix`` (0.4 s per iteration on ICT), and (c)
    finds closest points through an R-tree that misses some (:class:`ClosestPoints`).

    ``normals="trimesh"`` (default) is trimesh's source normal: the rest normal ``(n, 1)``
    times the affine map (the map's translation added to it). ``"deformed"`` uses the
    normals of the current deformed surface. Measured on ICT → Rocketbox / tiger /
    triceratops, trimesh's gives fewer folded triangles after resampling (236 / 324 / 602
    against 284 / 437 / 747; the rest normals 271 / 346 / 587), so it stays the default.

    **Coarse to fine** (``coarse``): the schedule runs on a coarse mesh over about
    ``coarse`` of the source's own vertices (quadric decimation, each new vertex moved to a
    distinct nearest source vertex, the landmarks kept), the maps ``X`` found there are
    carried to every vertex by :func:`harmonic_extension` (12 values per vertex: a vertex
    between coarse ones gets the blend of their affine maps, so fine geometry is mapped,
    not only moved), and ``fine_iterations`` iterations of the last step run on the full
    mesh from there. A mesh of fewer than ``2 * coarse`` vertices runs at full resolution (the
    coarse stage, extension and fine iterations cost more than they save there). On ICT (14K
    vertices) → Rocketbox, 3,000 coarse vertices take the whole registration from 13-18 s (this
    loop at full resolution) to 5-6 s, with landmarks 0.15 / 0.88 mm instead of 0.26 / 1.30
    mean / max and the same surface p95 (docs/transfer.md).

    Barycentric landmarks ``(faces, barycentric)`` follow trimesh: each corner k of the
    landmark's triangle gets the row :math:`b_k \tilde v_k^T X_k = p - \sum_{j \ne k} b_j v_j`
    (the other corners at their rest positions). On the coarse mesh a barycentric landmark
    pulls the corner of its largest weight by the same offset.

    Like trimesh, the source is moved to its area-weighted centroid and scaled to unit
    bounding-box diagonal first (the target with it): ``steps`` and ``distance_threshold``
    are read in that frame, so they are relative to the source's size whatever its units.

    Parameters
    ----------
    V : (n, 3) float, F : (F, 3) int
        The source mesh.
    target_V : (m, 3) float, target_F : (F', 3) int
        The target surface.
    landmarks : (L,) int vertex ids, or ((L,) int faces, (L, 3) barycentric), optional
    landmark_positions : (L, 3) float, optional
        Where the landmarks go.
    steps : sequence of (ws, wl, wn, max_iter), optional
        Default :func:`nricp_steps`\ ``()``.
    distance_threshold : float
        In units of the source's bounding-box diagonal (see above).
    progress : ``(fraction, message) -> None``, optional
        Called after every iteration with the fraction of the schedule's iterations done (a
        step may end early) and the step and match error (mm if the input is in metres); the
        time left is the caller's to say, for its whole run (:class:`core.progress.TimeLeft`).
    eps : float
        A step ends when its mean weighted match error falls by less than this (unit frame;
        trimesh's default).
    coarse : int, optional
        Run the schedule on about this many vertices first (see above); None: full mesh.
    fine_iterations : int
        Iterations of the last step on the full mesh after the coarse stage.
    normals : "trimesh" | "deformed"

    Returns
    -------
    (n, 3) float64 registered source positions.

    Raises
    ------
    ValueError
        Bad shapes, landmarks without positions (or the reverse) or of different lengths,
        an unknown ``normals``.
    """

    V, F = _check_mesh(V, F, "V")
    T, TF = _check_mesh(target_V, target_F, "target_V")
    if (landmarks is None) != (landmark_positions is None):
        raise ValueError("landmarks, landmark_positions: give both or neither")
    if normals not in ("trimesh", "deformed"):
        raise ValueError(f"normals: expected 'trimesh' or 'deformed', got {normals!r}")
    steps = nricp_steps() if steps is None else [tuple(x) for x in steps]
    n = len(V)
    # the unit frame of trimesh's _normalize_by_source
    area = 0.5 * doublearea(V, F)
    tri_c = V[F].mean(axis=1)
    centroid = (area @ tri_c) / area.sum() if area.sum() > 0 else tri_c.mean(0)
    scale = float(np.linalg.norm(np.ptp(V[np.unique(F)], axis=0))) or 1.0
    Vn = (V - centroid) / scale
    Tn = (T - centroid) / scale
    # landmark rows (block-diagonal): vertex v, row r (4,), target (3,)
    lm = (np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 3)))
    lm_coarse = None  # (vertex ids, targets) for the coarse stage
    if landmarks is not None:
        pos = (np.asarray(landmark_positions, dtype=np.float64) - centroid) / scale
        if isinstance(landmarks, tuple):
            tid = np.asarray(landmarks[0], dtype=np.int64)
            bc = np.asarray(landmarks[1], dtype=np.float64)
            if pos.shape != (len(tid), 3) or bc.shape != (len(tid), 3):
                raise ValueError(f"landmark_positions: expected ({len(tid)}, 3) for {len(tid)} landmarks, got {pos.shape}")
            corners = F[tid]  # (L, 3)
            on = np.einsum("lk,lkc->lc", bc, Vn[corners])
            lm = (corners.ravel(),
                  (np.concatenate([Vn[corners], np.ones(corners.shape + (1,))], axis=2) * bc[:, :, None]).reshape(-1, 4),
                  (pos[:, None, :] - (on[:, None, :] - bc[:, :, None] * Vn[corners])).reshape(-1, 3))
            top = corners[np.arange(len(tid)), np.argmax(bc, axis=1)]
            lm_coarse = (top, pos + Vn[top] - on)
        else:
            ids = np.asarray(landmarks, dtype=np.int64).ravel()
            if pos.shape != (len(ids), 3):
                raise ValueError(f"landmark_positions: expected ({len(ids)}, 3) for {len(ids)} landmarks, got {pos.shape}")
            if ids.size and (ids.min() < 0 or ids.max() >= n):
                raise ValueError(f"landmarks: vertex ids must lie in [0, {n})")
            lm = (ids, np.hstack([Vn[ids], np.ones((len(ids), 1))]), pos)
            lm_coarse = (ids, pos)
    target = ClosestPoints(Tn, TF)

    tnormals = np.asarray(trimesh.Trimesh(Tn, TF, process=False).vertex_normals)  # trimesh's (angle-weighted)
    use_coarse = coarse is not None and n > 2 * coarse
    total = [sum(int(s[3]) for s in steps) + (fine_iterations if use_coarse else 0)]
    done = [0]

    def report(stage):
        def f(k, it, max_iter, error):
            done[0] += 1
            if progress is None:
                return
            left = max(total[0] - done[0], 0)
            # no time left of its own: a run that registers says one for the whole run (progress.TimeLeft)
            progress(done[0] / max(done[0] + left, 1),
                     f"non-rigid ICP{stage} step {k + 1}/{len(steps)} iteration {it}: match error "
                     f"{error * scale * 1000:.3g} mm")
        return f

    X0 = np.tile(np.vstack([np.eye(3), np.zeros((1, 3))]), (n, 1)).reshape(n, 4, 3)
    tm = normals == "trimesh"
    if not use_coarse:
        X = _nicp_loop(Vn, F, target, tnormals, TF, lm, steps, X0, distance_threshold, eps, report(""), tm)
        return np.einsum("ni,nic->nc", np.hstack([Vn, np.ones((n, 1))]), X) * scale + centroid
    keep = lm_coarse[0] if lm_coarse is not None else np.zeros(0, np.int64)
    sub, Fc = _coarse_subset(Vn, F, int(coarse), keep)
    local = np.full(n, -1, np.int64)
    local[sub] = np.arange(len(sub))
    lmc = (np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 3)))
    if lm_coarse is not None:
        lv = local[lm_coarse[0]]
        lmc = (lv, np.hstack([Vn[lm_coarse[0]], np.ones((len(lv), 1))]), lm_coarse[1])
    Xc = _nicp_loop(Vn[sub], Fc, target, tnormals, TF, lmc, steps, X0[sub], distance_threshold, eps,
                    report(f" (coarse, {len(sub)} vertices)"), tm)
    # a step ended early leaves iterations unused: the estimate counts only the fine ones now
    total[0] = done[0] + fine_iterations
    mask = np.zeros(n, bool)
    mask[sub] = True
    X = harmonic_extension(Xc.reshape(len(sub), 12)[np.argsort(sub)], mask, F, n).reshape(n, 4, 3)
    if fine_iterations > 0:
        last = steps[-1]
        X = _nicp_loop(Vn, F, target, tnormals, TF, lm, [(last[0], last[1], last[2], int(fine_iterations))], X,
                       distance_threshold, 0.0, report(" (full mesh)"), tm)
    return np.einsum("ni,nic->nc", np.hstack([Vn, np.ones((n, 1))]), X) * scale + centroid


# ---------------------------------------------------------------------------------------------
# construction
# ---------------------------------------------------------------------------------------------


def _cylinder_uv(points, up, forward):
    """Unroll points on a vertical cylinder behind the face: u = R·angle, v = height.

    The axis runs along ``up`` through the centroid moved back by R along ``forward``, with
    R half the points' width; a face is about that round, so cheeks at the side spread out
    instead of folding onto the front as a plane projection would fold them.
    """
    up = np.asarray(up, float) / np.linalg.norm(up)
    fwd = np.asarray(forward, float)
    fwd = fwd - (fwd @ up) * up
    fwd /= np.linalg.norm(fwd)
    right = np.cross(up, fwd)
    c = points.mean(axis=0)
    x = (points - c) @ right
    R = max(0.5 * (x.max() - x.min()), 1e-12)
    z = (points - c) @ fwd + R
    return np.column_stack([R * np.arctan2(x, z), (points - c) @ up])


def _angles_edges(P, F):
    """(F, 3) corner angles in degrees and (F, 3) lengths of the opposite edges."""
    a, b, c = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    e = np.stack([np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1), np.linalg.norm(a - b, axis=1)], 1)
    cosang = np.stack([
        np.einsum("ij,ij->i", b - a, c - a), np.einsum("ij,ij->i", a - b, c - b), np.einsum("ij,ij->i", a - c, b - c)
    ], 1) / np.maximum(np.stack([e[:, 1] * e[:, 2], e[:, 2] * e[:, 0], e[:, 0] * e[:, 1]], 1), 1e-300)
    return np.degrees(np.arccos(np.clip(cosang, -1, 1))), e


def marker_triangulation(points, up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0), min_angle: float = 10.0,
                         max_edge: float = 3.0, unroll: str = "cylinder") -> np.ndarray:
    """Triangulate face markers in a 2-D parameterisation (Ribera et al. 2017 §4.4).

    The markers are flattened and Delaunay-triangulated there (scipy.spatial.Delaunay):

    * ``unroll="cylinder"``: on a cylinder around the head's vertical axis (u = R·azimuth,
      v = height; the face looks down ``forward`` with ``up`` up, glTF's +Z/+Y by default),
      so cheeks at the side spread out;
    * ``unroll="plane"``: onto the markers' best-fit plane (their two principal axes), which
      needs no head frame — for captured markers in whatever frame the capture has (a face's
      marker set is a height field over that plane).

    The convex hull of a face has long thin triangles along its rim; boundary triangles are
    peeled off while they have a 3-D angle below ``min_angle`` degrees or an edge longer
    than ``max_edge`` times the median edge length.

    Parameters
    ----------
    points : (M, 3) float
        Neutral marker positions, M >= 3.
    up, forward : (3,) float
        Head frame: the cylinder's axis, and the side the faces are oriented to.
    min_angle : float
        Degrees.
    max_edge : float
        Relative to the median edge length.
    unroll : {"cylinder", "plane"}

    Returns
    -------
    faces : (F, 3) int64, each oriented so its normal points along ``forward``.

    Raises
    ------
    ValueError
        Fewer than 3 markers, non-finite positions, all markers on a line, unknown ``unroll``.
    """

    if unroll not in ("cylinder", "plane"):
        raise ValueError(f"unroll: expected 'cylinder' or 'plane', got {unroll!r}")
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points: expected marker positions of shape (M, 3), got {P.shape}")
    if len(P) < 3 or not np.isfinite(P).all():
        raise ValueError(f"points: need at least 3 finite marker positions, got {len(P)} rows")
    if unroll == "cylinder":
        uv = _cylinder_uv(P, up, forward)
    else:
        c = P - P.mean(0)
        uv = c @ np.linalg.svd(c, full_matrices=False)[2][:2].T
    try:
        F = Delaunay(uv).simplices.astype(np.int64)
    except QhullError as e:
        raise ValueError(f"points: cannot triangulate the markers (collinear?): {str(e).splitlines()[0]}") from None
    _, e0 = _angles_edges(P, F)
    med = np.median(e0)
    while len(F) > 1:
        ang, e = _angles_edges(P, F)
        bad = (ang.min(axis=1) < min_angle) | (e.max(axis=1) > max_edge * med)
        und = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        _, inv, cnt = np.unique(und, axis=0, return_inverse=True, return_counts=True)
        on_rim = (cnt[inv.ravel()] == 1).reshape(3, -1).T.any(axis=1)
        drop = bad & on_rim
        if not drop.any():
            break
        F = F[~drop]
    flip = face_normals(P, F) @ np.asarray(forward, float) < 0
    F[flip] = F[flip][:, ::-1]
    return F


def decimate(V, F, reduction: Optional[float] = None, *, max_vertices: Optional[int] = None, uvs=None):
    """Quadric edge-collapse decimation [7] (VTK's vtkQuadricDecimation through pyvista).

    Edges are collapsed in order of the quadric error of the merged vertex until the
    requested fraction of triangles is gone. With ``uvs`` the texture coordinates are part
    of the error metric and carried to the new vertices.

    Parameters
    ----------
    V : (n, 3) float, F : (F, 3) int
    reduction : float in (0, 1), optional
        Fraction of the triangles to remove.
    max_vertices : int, optional
        Instead of ``reduction``: about this many vertices remain
        (``reduction = 1 - max_vertices / n``); a mesh with no more is returned as it is.
    uvs : (n, 2) float, optional
        Texture coordinates to carry.

    Returns
    -------
    V' : (m, 3) float64, F' : (F', 3) int64, uvs' : (m, 2) float64 or None

    Raises
    ------
    ValueError
        Neither or both of ``reduction`` and ``max_vertices``, a reduction outside (0, 1),
        ``uvs`` not (n, 2).
    """
    V, F = _check_mesh(V, F)
    if (reduction is None) == (max_vertices is None):
        raise ValueError("decimate: give one of reduction (fraction of triangles to remove) or max_vertices")
    if uvs is not None:
        uvs = np.asarray(uvs)
        if uvs.shape != (len(V), 2):
            raise ValueError(f"uvs: expected ({len(V)}, 2) texture coordinates, got {uvs.shape}")
    if max_vertices is not None:
        if len(V) <= max_vertices:
            return V, F, (None if uvs is None else np.asarray(uvs, dtype=np.float64))
        reduction = 1.0 - max_vertices / len(V)
    if not 0 < reduction < 1:
        raise ValueError(f"reduction: expected a fraction in (0, 1), got {reduction}")
    import pyvista as pv

    mesh = pv.PolyData(V.copy(), np.hstack([np.full((len(F), 1), 3), F]).ravel())
    if uvs is not None:
        mesh.active_texture_coordinates = uvs.astype(np.float32)
    low = mesh.decimate(reduction, **({"tcoords": True} if uvs is not None else {}))
    out_uv = None if uvs is None else np.asarray(low.active_texture_coordinates, dtype=np.float64)
    return (np.asarray(low.points, dtype=np.float64), np.asarray(low.faces).reshape(-1, 4)[:, 1:].astype(np.int64),
            out_uv)
