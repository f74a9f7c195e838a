"""Mesh operators shared by the methods: Laplacians, mass matrices, normals, boundaries.

libigl/gpytoolbox style: short noun names, ``(V, F)`` arguments, scipy.sparse outputs.

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
  contribute nothing to the Laplacians or mass matrices instead of an inf/NaN cotangent.

References
----------
.. [1] Pinkall & Polthier 1993, "Computing discrete minimal surfaces and their conjugates".
.. [2] Meyer, Desbrun, Schroeder, Barr 2003, "Discrete differential-geometry operators for
       triangulated 2-manifolds" (mixed Voronoi areas).
.. [3] Ribera et al. 2017, eq. 11 and 16 use the cotangent Laplacian of [1].
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

#: relative area below which a triangle counts as degenerate (times size**2)
DEGENERATE_EPS = 1e-14


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
    return np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


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
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
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
    e = np.sort(e, axis=1)
    return np.unique(e, axis=0) if len(e) else np.zeros((0, 2), np.int64)


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
    e = edges(F)
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    return (A + A.T).tocsr()


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
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    nrm = np.linalg.norm(N, axis=1)
    ok = nrm > DEGENERATE_EPS * max(_size(V), 1e-300) ** 2
    out = np.zeros_like(N)
    out[ok] = N[ok] / nrm[ok, None]
    return out


def vertex_normals(V, F):
    """Area-weighted vertex normals: ``normalize(sum_{f ni i} 2 A_f n_f)``.

    Parameters
    ----------
    V : (n, 3) float
    F : (F, 3) int

    Returns
    -------
    (n, 3) float64; a zero vector at a vertex no (non-degenerate) face touches.
    """
    V, F = _check_mesh(V, F)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # |N| = 2A
    acc = np.zeros_like(V)
    for c in range(3):
        np.add.at(acc, F[:, c], N)
    nrm = np.linalg.norm(acc, axis=1)
    ok = nrm > 0
    acc[ok] /= nrm[ok, None]
    acc[~ok] = 0.0
    return acc


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


def farthest_points(points, n: int, start: int = 0) -> np.ndarray:
    """Indices of ``n`` well-spread points by greedy farthest-point sampling from ``start``.

    Each next point maximises its distance to the points chosen so far (Gonzalez 1985, a
    2-approximation of the k-centre problem). Used to place virtual markers on a mesh.

    Parameters
    ----------
    points : (N, 3) float
    n : int, 1 <= n <= N
    start : index of the first point

    Returns
    -------
    (n,) int
    """
    P = np.asarray(points, dtype=np.float64)
    if not 1 <= n <= len(P):
        raise ValueError(f"farthest_points: n must lie in [1, {len(P)}], got {n}")
    chosen = [int(start)]
    d = np.linalg.norm(P - P[chosen[0]], axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(P - P[i], axis=1))
    return np.asarray(chosen)
