"""Automatic segmentation of a blendshape rig into R soft regions (Liu et al. 2011, §3.2.1).

Steps, each a pure function below, chained by :func:`segment` (or :class:`Segmenter`):

1. **Weld** (:func:`welded_graph`, on :func:`core.geometry.weld_vertices`): rigs with UVs split vertices along
   seams (ICT: 14,629 vertices, 14,062 distinct). Every graph operation runs on the welded mesh
   so a seam is not a cut.
2. **Principal directions** (:func:`principal_directions`): for vertex v, PCA of its K+1
   positions ``{n_v} ∪ {n_v + d_kv}`` (neutral and every shape): the eigenvector of the
   3x3 scatter matrix ``C_v = Σ_k (p_kv - p̄_v)(p_kv - p̄_v)^T`` with the largest eigenvalue.
   Vertices that move less than ``still_tol`` times the rig's largest displacement in every
   shape are *still*: their direction is noise and they get no direction (zero vector).
3. **Sign coordination** (:func:`coordinate_signs`): an eigenvector's sign is arbitrary. The
   paper minimises, per vertex, "the sum of dot products of the principal components between
   its neighbors" -- read literally that would make neighbours point apart; what it means
   (Fig. 1b) is that neighbours should agree. We minimise over signs s ∈ {±1}^V

       E(s) = Σ_{edges ij} ½‖s_i d_i − s_j d_j‖² = Σ_{ij} (1 − s_i s_j d_i·d_j)   (moving pairs)

   i.e. maximise Σ_ij s_i s_j d_i·d_j, an Ising/max-cut-type problem (NP-hard in general). We
   solve it by sign propagation along a maximum spanning tree of |d_i·d_j| (exact on the
   tree: every tree edge gets s_i s_j d_i·d_j = |d_i·d_j|), then greedy local flips that
   never increase E (an independent set of improving vertices flipped per sweep). E before,
   after the tree and after the flips is reported.
4. **k-means** (:func:`scipy.cluster.vq.kmeans2`, k-means++ seeding, fixed seed) on the
   coordinated directions of the moving vertices, optionally with positions appended
   (``position_weight``; 0 is the paper). Still vertices take the label of the nearest moving
   vertex along the mesh (multi-source Dijkstra), or in space where no path exists.
5. **Split and merge**: every label is split into connected components; then, as in the
   paper, the region with the fewest vertices is merged into its adjacent region with the
   fewest vertices while any region is below ``min_size``. Unlike the paper (whose §7 asks for
   it) R is a direct parameter: merging continues until R regions remain; if fewer than R
   remain, the largest region is bisected geodesically (two far-apart seeds, nearest-seed
   cells along the mesh) until R is reached. R is met exactly whenever R ≤ number of welded
   vertices; ``min_size`` is honoured when ``R * min_size ≤ V`` and the mesh allows.
6. **Soft masks**: one-hot masks smoothed by ``smooth_iters`` steps of uniform Laplacian
   smoothing ``X ← (1−α) X + α D⁻¹ A X`` (α = ½) on the welded mesh (the paper uses a
   Gaussian filter in texture space; on the mesh there are no UV seams to blur across), then
   normalised so the R masks sum to 1 at every vertex. The operator is row-stochastic, so
   the masks stay in [0, 1].

:func:`marker_weights` then gives the paper's r(B_k, q): the mean of mask k over marker q's
geodesic Voronoi cell, normalised over regions (the diagonal of M_k in eq. 2).
"""

from __future__ import annotations

import heapq
import time
import warnings
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import scipy.sparse as sp
from scipy.cluster.vq import kmeans2
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from .geometry import weld_vertices
from .model import MarkerLayout, Rig


# ----------------------------------------------------------------------------------------
# welded mesh graph
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class WeldedGraph:
    """The rig's mesh with seam duplicates merged.

    Attributes
    ----------
    index : (V,) int
        Welded id of every rig vertex.
    first : (n,) int
        One rig vertex per welded id (the first).
    faces : (F', 3) int
        Faces in welded ids (faces that collapsed dropped).
    adjacency : (n, n) csr_matrix
        0/1 edge adjacency of the welded mesh.
    lengths : (n, n) csr_matrix
        Neutral edge lengths on the same pattern (metres).
    """

    index: np.ndarray
    first: np.ndarray
    faces: np.ndarray
    adjacency: sp.csr_matrix
    lengths: sp.csr_matrix

    @property
    def n(self) -> int:
        return len(self.first)


def welded_graph(rig: Rig) -> WeldedGraph:
    """The rig's welded mesh graph: :func:`core.geometry.weld_vertices` of vertices with bit-identical
    neutral position *and* deltas (UV-seam copies), plus its adjacency and edge lengths.

    Requiring identical deltas too keeps apart distinct vertices that merely touch at rest
    (e.g. closed lips zipped at one position).

    Returns
    -------
    WeldedGraph
    """
    _check_rig(rig)
    w = weld_vertices(rig.neutral, rig.faces, tol=0, attributes=rig.deltas)
    index, first, fg, n = w.index, w.first, w.faces, w.n
    # 0/1 adjacency straight from the face edges (core.geometry.vertex_adjacency gives the
    # same matrix via np.unique(axis=0), which is ~10x slower on 28k faces)
    i = np.concatenate([fg[:, 0], fg[:, 1], fg[:, 2]])
    j = np.concatenate([fg[:, 1], fg[:, 2], fg[:, 0]])
    A = sp.csr_matrix((np.ones(2 * len(i)), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))
    A.sum_duplicates()
    A.data[:] = 1.0
    A.sort_indices()
    Ac = A.tocoo()
    P = rig.neutral[first]
    d = np.linalg.norm(P[Ac.row] - P[Ac.col], axis=1)
    # Dijkstra treats stored zeros as missing edges; a zero-length edge gets a tiny length
    d = np.maximum(d, 1e-12 * max(rig.size, 1e-300))
    Lg = sp.csr_matrix((d, (Ac.row, Ac.col)), shape=(n, n))
    return WeldedGraph(index, first, fg, A, Lg)


def _check_rig(rig):
    if not isinstance(rig, Rig):
        raise TypeError(f"rig: expected a core.model.Rig, got {type(rig).__name__}")
    if rig.n_shapes == 0:
        raise ValueError(f"rig {rig.name!r}: has no blendshapes to segment")
    if len(rig.faces) == 0:
        raise ValueError(f"rig {rig.name!r}: has no faces; segmentation needs the mesh graph")


# ----------------------------------------------------------------------------------------
# step 2: principal directions
# ----------------------------------------------------------------------------------------
def principal_directions(neutral: np.ndarray, deltas: np.ndarray, still_tol: float = 1e-2):
    """Per-vertex first principal direction of its positions over the shapes.

    PCA of the K+1 points ``{n_v, n_v + d_1v, ..., n_v + d_Kv}`` (Liu et al. 2011, §3.2.1):
    the unit eigenvector of ``C_v = Σ_k (p_kv − p̄_v)(p_kv − p̄_v)^T`` with the largest
    eigenvalue. Its sign is fixed deterministically (largest-magnitude component positive);
    :func:`coordinate_signs` then coordinates signs across the mesh.

    Parameters
    ----------
    neutral : (V, 3) float
    deltas : (K, V, 3) float
    still_tol : float
        A vertex is *still* when ``max_k ‖d_kv‖ ≤ still_tol · max_{k,v} ‖d_kv‖``; its direction
        is returned as the zero vector.

    Returns
    -------
    directions : (V, 3) float64, unit or zero
    explained : (V,) float64
        Fraction of the scatter along the first direction, ``λ1 / (λ1+λ2+λ3)`` (0 if still).
    moving : (V,) bool
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    deltas = np.asarray(deltas, dtype=np.float64)
    if neutral.ndim != 2 or neutral.shape[1] != 3:
        raise ValueError(f"neutral: expected (V, 3), got {neutral.shape}")
    if deltas.ndim != 3 or deltas.shape[1:] != neutral.shape:
        raise ValueError(f"deltas: expected (K, {len(neutral)}, 3), got {deltas.shape}")
    if not still_tol >= 0:
        raise ValueError(f"still_tol: expected >= 0, got {still_tol}")
    K = len(deltas)
    # positions relative to the neutral: the neutral is the point 0 among the K+1
    mean = deltas.sum(0) / (K + 1)  # (V, 3)
    C = np.einsum("kvi,kvj->vij", deltas, deltas) - (K + 1) * np.einsum("vi,vj->vij", mean, mean)
    lam, vec = np.linalg.eigh(C)  # ascending
    d = vec[:, :, 2].copy()
    big = np.argmax(np.abs(d), axis=1)
    d *= np.sign(d[np.arange(len(d)), big])[:, None]
    disp = np.sqrt((deltas**2).sum(2)).max(0)
    moving = disp > still_tol * max(disp.max(), 1e-300)
    d[~moving] = 0.0
    tot = np.clip(lam, 0, None).sum(1)
    explained = np.where(moving & (tot > 0), lam[:, 2] / np.where(tot > 0, tot, 1), 0.0)
    return d, explained, moving


# ----------------------------------------------------------------------------------------
# step 3: sign coordination
# ----------------------------------------------------------------------------------------
def _edge_dots(A: sp.csr_matrix, d: np.ndarray) -> sp.csr_matrix:
    Ac = A.tocoo()
    c = np.einsum("ij,ij->i", d[Ac.row], d[Ac.col])
    return sp.csr_matrix((c, (Ac.row, Ac.col)), shape=A.shape)


def sign_energy(A: sp.csr_matrix, d: np.ndarray, s: np.ndarray) -> float:
    """E(s) = Σ_{edges ij, both moving} (1 − s_i s_j d_i·d_j) = Σ ½‖s_i d_i − s_j d_j‖².

    ``A`` is the symmetric adjacency (each edge stored twice; counted once here).
    """
    Ac = sp.triu(A, k=1).tocoo()
    both = (np.abs(d[Ac.row]).sum(1) > 0) & (np.abs(d[Ac.col]).sum(1) > 0)
    r, c = Ac.row[both], Ac.col[both]
    return float(np.sum(1.0 - s[r] * s[c] * np.einsum("ij,ij->i", d[r], d[c])))


def coordinate_signs(A: sp.csr_matrix, d: np.ndarray, max_sweeps: int = 1000, restarts: int = 0, seed: int = 0):
    """Signs s ∈ {±1}^n minimising :func:`sign_energy` (heuristic; the problem is NP-hard).

    1. Maximum spanning tree of the weights |d_i·d_j| (``minimum_spanning_tree`` of
       ``2 − |d_i·d_j| > 0``, so zero dot products stay edges), then propagation from one
       root per tree: ``s_j = s_i · sign(d_i·d_j)`` along tree edges (by pointer jumping,
       vectorised). Every tree edge then contributes its best value.
    2. Local moves that never increase E, alternated until neither improves: single-vertex
       flips (an independent set of improving vertices per sweep) and block flips (the
       components of the satisfied-edge graph, whose boundary edges are all unsatisfied,
       so flipping a block satisfies its whole boundary).
    3. Optionally ``restarts`` more runs from spanning trees of randomly perturbed weights
       ``|d_i·d_j| · exp(0.5 ξ)`` (seeded); the lowest final energy wins.

    Parameters
    ----------
    A : (n, n) sparse symmetric adjacency
    d : (n, 3) directions (zero rows are ignored)
    max_sweeps : int
    restarts : int >= 0
    seed : int

    Returns
    -------
    signs : (n,) float64 of ±1
    info : dict with ``energy_initial`` (all +1, i.e. the canonical eigenvector signs),
        ``energy_tree`` (exact maximum spanning tree, before local moves), ``energy_final``,
        ``flips``, ``block_flips``, ``sweeps`` (of the winning run), ``energy_runs``.
    """
    n = A.shape[0]
    Cd = _edge_dots(A, d)
    e0 = sign_energy(A, d, np.ones(n))
    rng = np.random.default_rng(seed)
    best = None
    runs = []
    for run in range(restarts + 1):
        w = np.abs(Cd.data) if run == 0 else np.abs(Cd.data) * np.exp(0.5 * rng.normal(size=Cd.nnz))
        s = _tree_signs(A, d, Cd, w)
        e_tree = sign_energy(A, d, s) if run == 0 else None
        s, moves = _local_moves(A, Cd, s, max_sweeps)
        e = sign_energy(A, d, s)
        runs.append(e)
        if run == 0:
            e1 = e_tree
        if best is None or e < best[0] - 1e-12:
            best = (e, s, moves)
    e2, s, moves = best
    return s, {"energy_initial": e0, "energy_tree": e1, "energy_final": e2, "energy_runs": runs, **moves}


def _tree_signs(A, d, Cd, w):
    """Signs propagated along a maximum spanning tree of the edge weights ``w`` (Cd's pattern)."""
    n = A.shape[0]
    # maximum spanning tree of w (as a minimum spanning tree of (max w + 1) - w > 0)
    Wt = Cd.copy()
    Wt.data = (w.max(initial=0.0) + 1.0) - w
    Wt = (Wt + Wt.T) * 0.5  # perturbed weights must stay symmetric
    Tm = csgraph.minimum_spanning_tree(Wt)
    Tm = (Tm + Tm.T).tocsr()
    ncomp, comp = csgraph.connected_components(Tm, directed=False)
    pred = np.arange(n)  # a root (or isolated vertex) is its own predecessor
    for r in np.unique(comp, return_index=True)[1]:
        if Tm.indptr[r + 1] == Tm.indptr[r]:
            continue
        _, p = csgraph.breadth_first_order(Tm, r, directed=False, return_predecessors=True)
        members = np.flatnonzero(p >= 0)
        pred[members] = p[members]
    idx = np.arange(n)
    edge_sign = np.sign(np.einsum("ij,ij->i", d[pred], d))
    edge_sign[(edge_sign == 0) | (pred == idx)] = 1.0
    return _path_signs(pred, edge_sign)


def _local_moves(A, Cd, s, max_sweeps):
    """Single-vertex and block flips until neither lowers the energy (see coordinate_signs)."""
    n = A.shape[0]
    # local moves, alternated until neither improves:
    #  a) single flips. Flipping i alone changes E by 2 s_i (C s)_i with C_ij = d_i.d_j on
    #     edges, so its energy decrease is g_i = -2 s_i (C s)_i. Each sweep flips every
    #     improving vertex whose gain beats all its improving neighbours' (an independent
    #     set, so the gains add up exactly).
    #  b) block flips. Cut the satisfied edges (s_i s_j C_ij > 0) into connected blocks;
    #     every edge between two blocks is unsatisfied, so flipping a block satisfies all of
    #     its boundary at once (a strict decrease when the boundary has nonzero weight). A
    #     set of pairwise non-adjacent blocks is flipped together.
    flips = sweeps = block_flips = 0
    scale = max(float(np.abs(Cd.data).max()) if Cd.nnz else 0.0, 1e-300)
    tie = (np.arange(n) + 1) * (1e-9 * scale / max(n, 1))
    Cu = sp.triu(Cd, k=1).tocoo()
    Cu = sp.coo_matrix((Cu.data, (Cu.row, Cu.col)), shape=Cd.shape)
    nz = np.abs(Cu.data) > 1e-12 * scale
    er, ec, ed = Cu.row[nz], Cu.col[nz], Cu.data[nz]
    while sweeps < max_sweeps:
        sweeps += 1
        g = -2.0 * s * (Cd @ s)
        cand = g > 1e-12 * scale
        if cand.any():
            key = np.where(cand, g + tie, 0.0)  # distinct keys: ties broken by index
            nb = A.multiply(key[None, :]).tocsr().max(axis=1).toarray().ravel()
            pick = cand & (key > nb)  # no two picked vertices are neighbours
            s = np.where(pick, -s, s)
            flips += int(pick.sum())
            continue
        sat = s[er] * s[ec] * ed > 0
        nblk, blk = csgraph.connected_components(
            sp.csr_matrix((np.ones(sat.sum()), (er[sat], ec[sat])), shape=(n, n)), directed=False)
        br, bc = blk[er[~sat]], blk[ec[~sat]]
        if len(br) == 0:
            break
        # greedy independent set of blocks, smallest first (fewest vertices flipped)
        size = np.bincount(blk, minlength=nblk)
        nbrs = [set() for _ in range(nblk)]
        for a_, b_ in zip(br.tolist(), bc.tolist()):
            if a_ != b_:
                nbrs[a_].add(b_)
                nbrs[b_].add(a_)
        chosen, blocked = [], np.zeros(nblk, bool)
        for c in np.argsort(size, kind="stable"):
            if nbrs[c] and not blocked[c]:
                chosen.append(c)
                blocked[c] = True
                blocked[list(nbrs[c])] = True
        if not chosen:
            break
        s = np.where(np.isin(blk, chosen), -s, s)
        block_flips += len(chosen)
    return s, {"flips": flips, "block_flips": block_flips, "sweeps": sweeps}


def _path_signs(pred: np.ndarray, edge_sign: np.ndarray) -> np.ndarray:
    """Product of ``edge_sign`` along the predecessor path from every vertex to its root.

    Pointer jumping: after round r every vertex knows the product over its first 2^r hops;
    O(log depth) vectorised rounds instead of a Python loop over the BFS order.
    """
    acc = np.asarray(edge_sign, dtype=np.float64).copy()
    ptr = np.asarray(pred).copy()
    acc[ptr == np.arange(len(ptr))] = 1.0
    # invariant: acc[v] = product of the edge signs on the path from v up to (excluding) ptr[v]
    while not np.array_equal(ptr[ptr], ptr):
        acc = acc * acc[ptr]
        ptr = ptr[ptr]
    return acc


# ----------------------------------------------------------------------------------------
# steps 4-6: clustering, split/merge to R regions, soft masks
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Segmentation:
    """Result of :func:`segment`.

    Attributes
    ----------
    labels : (V,) int
        Hard region of every rig vertex, 0..R-1 (regions ordered top to bottom by centroid).
    masks : (R, V) float64
        Soft masks B_k in [0, 1], summing to 1 at every vertex (Liu et al. 2011, eq. 3).
    directions : (V, 3) float64
        Sign-coordinated first principal directions (zero at still vertices).
    moving : (V,) bool
    explained : (V,) float64
        λ1 / Σλ of each vertex's PCA.
    graph : WeldedGraph
    info : dict
        Diagnostics: sign energies, k-means and merge counts, region sizes, timings (s).
    """

    labels: np.ndarray
    masks: np.ndarray
    directions: np.ndarray
    moving: np.ndarray
    explained: np.ndarray
    graph: WeldedGraph
    info: dict = field(default_factory=dict)

    @property
    def n_regions(self) -> int:
        return len(self.masks)


def _components(A: sp.csr_matrix, labels: np.ndarray):
    """Split every label into connected components: returns component ids (n,)."""
    Ac = A.tocoo()
    same = labels[Ac.row] == labels[Ac.col]
    G = sp.csr_matrix((np.ones(same.sum()), (Ac.row[same], Ac.col[same])), shape=A.shape)
    return csgraph.connected_components(G, directed=False)[1]


def _nearest_labels(graph: WeldedGraph, P: np.ndarray, labelled: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Give every unlabelled vertex the label of the nearest labelled one: along the mesh
    (multi-source Dijkstra), in space where no mesh path exists."""
    out = labels.copy()
    src = np.flatnonzero(labelled)
    if len(src) == 0:
        raise ValueError("no labelled vertex to propagate labels from")
    if labelled.all():
        return out
    _, _, nearest = csgraph.dijkstra(graph.lengths, directed=False, indices=src, min_only=True, return_predecessors=True)
    todo = ~labelled
    reach = todo & (nearest >= 0)
    out[reach] = labels[nearest[reach]]
    rest = np.flatnonzero(todo & (nearest < 0))
    if len(rest):
        _, j = cKDTree(P[src]).query(P[rest])
        out[rest] = labels[src[j]]
    return out


def _merge_and_split(graph: WeldedGraph, P: np.ndarray, comp: np.ndarray, R: int, min_size: int, counted: np.ndarray):
    """Paper's merge rule, then merge/bisect to exactly R regions. Returns labels and counts.

    A region's size is its number of ``counted`` (moving) vertices.
    """
    n = len(comp)
    counted = np.asarray(counted, dtype=bool)
    ncomp = int(comp.max()) + 1
    members = {c: set() for c in range(ncomp)}
    for v, c in enumerate(comp):
        members[c].add(v)
    Ac = sp.triu(graph.adjacency, k=1).tocoo()
    cr, cc = comp[Ac.row], comp[Ac.col]
    diff = cr != cc
    nbrs = {c: set() for c in range(ncomp)}
    for a, b in zip(cr[diff].tolist(), cc[diff].tolist()):
        nbrs[a].add(b)
        nbrs[b].add(a)
    csize = np.bincount(comp, weights=counted, minlength=ncomp).astype(np.int64)
    size = {c: int(csize[c]) for c in members}
    heap = [(s, c) for c, s in size.items()]
    heapq.heapify(heap)
    merges = 0

    def spatial_neighbour(c):
        # an isolated piece (no shared edge): the region owning the nearest vertex in space
        inside = np.fromiter(members[c], dtype=np.int64)
        outside = np.setdiff1d(np.arange(n), inside)
        _, j = cKDTree(P[outside]).query(P[inside])
        owner = {}
        for v in outside[np.unique(j)]:
            for k, m in members.items():
                if v in m:
                    owner[k] = size[k]
                    break
        return min(owner, key=lambda k: (owner[k], k))

    def merge_smallest():
        nonlocal merges
        while True:
            s, c = heapq.heappop(heap)
            if c in size and size[c] == s:
                break
        if nbrs[c]:
            t = min(nbrs[c], key=lambda k: (size[k], k))
        else:
            t = spatial_neighbour(c)
        members[t] |= members.pop(c)
        size[t] += size.pop(c)
        for k in nbrs.pop(c):
            nbrs[k].discard(c)
            if k != t:
                nbrs[k].add(t)
                nbrs[t].add(k)
        nbrs[t].discard(t)
        heapq.heappush(heap, (size[t], t))
        merges += 1

    def smallest_size():
        while heap and not (heap[0][1] in size and size[heap[0][1]] == heap[0][0]):
            heapq.heappop(heap)
        return heap[0][0]

    while len(size) > 1 and smallest_size() < min_size:
        merge_smallest()
    while len(size) > R:
        merge_smallest()
    splits = 0
    next_id = ncomp
    while len(size) < R:
        c = max(size, key=lambda k: (size[k], len(members[k]), -k))
        if len(members[c]) < 2:
            break
        a_part, b_part = _bisect(graph, np.fromiter(sorted(members[c]), dtype=np.int64))
        for part, cid in ((a_part, c), (b_part, next_id)):
            members[cid] = set(part.tolist())
            size[cid] = int(counted[part].sum())
        # recompute neighbour sets of the two halves
        lab = np.full(n, -1)
        for k, m in members.items():
            lab[np.fromiter(m, dtype=np.int64)] = k
        nbrs = {k: set() for k in members}
        ra, rb = lab[Ac.row], lab[Ac.col]
        dd = ra != rb
        for a, b in zip(ra[dd].tolist(), rb[dd].tolist()):
            nbrs[a].add(b)
            nbrs[b].add(a)
        heap = [(s, k) for k, s in size.items()]
        heapq.heapify(heap)
        next_id += 1
        splits += 1
    labels = np.empty(n, dtype=np.int64)
    for i, (k, m) in enumerate(sorted(members.items())):
        labels[np.fromiter(m, dtype=np.int64)] = i
    return labels, merges, splits


def _bisect(graph: WeldedGraph, verts: np.ndarray):
    """Split a vertex set in two geodesic halves: seeds a, b far apart (double sweep),
    every vertex to the nearer seed along the mesh restricted to the set."""
    sub = graph.lengths[verts][:, verts]
    d0 = csgraph.dijkstra(sub, directed=False, indices=0)
    d0[~np.isfinite(d0)] = -1
    a = int(np.argmax(d0))
    da = csgraph.dijkstra(sub, directed=False, indices=a)
    da[~np.isfinite(da)] = -1
    b = int(np.argmax(da))
    if b == a:
        b = (a + 1) % len(verts)
    _, _, src = csgraph.dijkstra(sub, directed=False, indices=[a, b], min_only=True, return_predecessors=True)
    to_b = src == b
    return verts[~to_b], verts[to_b]


def smooth_masks(A: sp.csr_matrix, onehot: np.ndarray, iterations: int, alpha: float = 0.5) -> np.ndarray:
    """``iterations`` steps of ``X ← (1−α) X + α D⁻¹ A X`` (uniform Laplacian smoothing).

    Parameters
    ----------
    A : (n, n) sparse 0/1 adjacency
    onehot : (n, R) float
    iterations : int >= 0
    alpha : float in (0, 1]

    Returns
    -------
    (n, R) float64, rows normalised to sum to 1 (the operator is row-stochastic, so values
    stay in [0, 1]).
    """
    if iterations < 0:
        raise ValueError(f"smooth_iters: expected >= 0, got {iterations}")
    if not 0 < alpha <= 1:
        raise ValueError(f"alpha: expected in (0, 1], got {alpha}")
    deg = np.asarray(A.sum(axis=1)).ravel()
    inv = np.where(deg > 0, 1.0 / np.where(deg > 0, deg, 1), 0.0)
    P = sp.diags(inv) @ A
    keep = np.where(deg > 0, 1.0 - alpha, 1.0)[:, None]
    X = np.asarray(onehot, dtype=np.float64).copy()
    for _ in range(iterations):
        X = keep * X + alpha * (P @ X)
    X = np.clip(X, 0.0, None)
    return X / X.sum(1, keepdims=True)


def segment(
    rig: Rig,
    n_regions: int = 12,
    min_size: Optional[int] = None,
    smooth_iters: int = 10,
    position_weight: float = 0.0,
    still_tol: float = 1e-2,
    kmeans_iter: int = 30,
    seed: int = 0,
    sign_restarts: int = 0,
) -> Segmentation:
    """Segment ``rig`` into ``n_regions`` soft regions by motion (Liu et al. 2011, §3.2.1).

    See the module docstring for what each step minimises.

    Parameters
    ----------
    rig : Rig
    n_regions : int
        R, met exactly (merge smallest-into-smallest-neighbour, or geodesic bisection of the
        largest region) when 1 ≤ R ≤ number of distinct vertices.
    min_size : int, optional
        Paper's vertex threshold ("Vtx. thres." in Table 1), counted on welded *moving*
        vertices (still ones do not count, so a large static scalp or neck does not win
        regions of its own). Default ``n_moving // (4 R)``.
    smooth_iters : int
        Uniform-Laplacian smoothing steps for the masks (overlap width grows like
        √iterations edges).
    position_weight : float
        0 clusters on directions only (the paper). w > 0 appends ``w · (p − p̄) / size`` to
        the features (``size`` = bounding-box diagonal), trading motion similarity for
        spatial compactness.
    still_tol : float
        Relative displacement under which a vertex counts as still (see
        :func:`principal_directions`).
    kmeans_iter : int
        Lloyd iterations of ``scipy.cluster.vq.kmeans2`` (k-means++ seeding).
    seed : int
        Seeds k-means (and sign restarts); equal seeds give equal results.
    sign_restarts : int
        Extra randomised sign-coordination runs (see :func:`coordinate_signs`). A lower
        sign energy did not mean lower retargeting error on ICT, so the default is the
        single exact-spanning-tree run.

    Returns
    -------
    Segmentation

    Raises
    ------
    ValueError
        R < 1 or larger than the number of distinct vertices; negative settings; a rig
        without shapes or faces; no vertex moves.
    TypeError
        ``rig`` is not a Rig.
    """
    t0 = time.perf_counter()
    graph = welded_graph(rig)
    n = graph.n
    R = int(n_regions)
    if not 1 <= R <= n:
        raise ValueError(f"n_regions: expected 1 <= R <= {n} (distinct vertices of rig {rig.name!r}), got {n_regions}")
    if min_size is not None and min_size < 0:
        raise ValueError(f"min_size: expected >= 0, got {min_size}")
    if position_weight < 0:
        raise ValueError(f"position_weight: expected >= 0, got {position_weight}")
    P = rig.neutral[graph.first]
    D = rig.deltas[:, graph.first]
    d, explained, moving = principal_directions(P, D, still_tol)
    if not moving.any():
        raise ValueError(f"rig {rig.name!r}: no vertex moves in any shape (all deltas ~0); nothing to segment")
    if min_size is None:
        min_size = max(1, int(moving.sum()) // (4 * R))
    t1 = time.perf_counter()
    s, sign_info = coordinate_signs(graph.adjacency, d, restarts=sign_restarts, seed=seed)
    dc = d * s[:, None]
    t2 = time.perf_counter()
    feats = dc[moving]
    if position_weight > 0:
        feats = np.concatenate([feats, position_weight * (P[moving] - P[moving].mean(0)) / max(rig.size, 1e-300)], axis=1)
    k = min(R, int(moving.sum()))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # kmeans2 warns about empty clusters; split/merge handles any count
        _, km = kmeans2(feats, k, iter=kmeans_iter, minit="++", seed=np.random.default_rng(seed))
    lab = np.full(n, -1, dtype=np.int64)
    lab[moving] = km
    lab = _nearest_labels(graph, P, moving, lab)
    comp = _components(graph.adjacency, lab)
    n_components = int(comp.max()) + 1
    t3 = time.perf_counter()
    labels_w, merges, splits = _merge_and_split(graph, P, comp, R, min_size, moving)
    # order regions top to bottom (then left to right) by centroid, for stable display
    Rf = int(labels_w.max()) + 1
    cent = np.stack([P[labels_w == r].mean(0) for r in range(Rf)])
    order = np.lexsort((cent[:, 0], -cent[:, 1]))
    rank = np.empty(Rf, dtype=np.int64)
    rank[order] = np.arange(Rf)
    labels_w = rank[labels_w]
    t4 = time.perf_counter()
    X = smooth_masks(graph.adjacency, np.eye(Rf)[labels_w], smooth_iters)
    t5 = time.perf_counter()
    sizes = np.bincount(labels_w, weights=moving, minlength=Rf).astype(np.int64)
    Au = sp.triu(graph.adjacency, k=1).tocoo()
    cut = float(np.mean(labels_w[Au.row] != labels_w[Au.col])) if Au.nnz else 0.0
    info = dict(sign_info)
    info.update(
        n_welded=n, n_moving=int(moving.sum()), kmeans_k=k, n_components=n_components, merges=merges,
        splits=splits, min_size=int(min_size), sizes=sizes.tolist(), cut_edge_fraction=cut,
        mean_explained=float(explained[moving].mean()),
        seconds={"weld_pca": t1 - t0, "signs": t2 - t1, "kmeans_split": t3 - t2, "merge": t4 - t3, "smooth": t5 - t4, "total": t5 - t0},
    )
    directions = dc[graph.index]
    return Segmentation(
        labels=labels_w[graph.index], masks=np.ascontiguousarray(X[graph.index].T), directions=directions,
        moving=moving[graph.index], explained=explained[graph.index], graph=graph, info=info,
    )


class Segmenter:
    """scikit-learn-style wrapper of :func:`segment` (same parameters).

    ``fit(rig)`` returns self and sets ``labels_`` (V,), ``masks_`` (R, V), ``directions_``
    (V, 3), ``info_`` (dict), ``result_`` (:class:`Segmentation`).
    """

    def __init__(self, n_regions=12, min_size=None, smooth_iters=10, position_weight=0.0, still_tol=1e-2, kmeans_iter=30, seed=0,
                 sign_restarts=0):
        self.n_regions = n_regions
        self.min_size = min_size
        self.smooth_iters = smooth_iters
        self.position_weight = position_weight
        self.still_tol = still_tol
        self.kmeans_iter = kmeans_iter
        self.seed = seed
        self.sign_restarts = sign_restarts

    def get_params(self) -> dict:
        return {k: getattr(self, k) for k in ("n_regions", "min_size", "smooth_iters", "position_weight", "still_tol", "kmeans_iter", "seed",
                                                "sign_restarts")}

    def fit(self, rig: Rig) -> "Segmenter":
        res = segment(rig, **self.get_params())
        self.result_ = res
        self.labels_ = res.labels
        self.masks_ = res.masks
        self.directions_ = res.directions
        self.info_ = res.info
        return self


# ----------------------------------------------------------------------------------------
# marker weights r(B_k, q)
# ----------------------------------------------------------------------------------------
def voronoi_cells(graph: WeldedGraph, sources: np.ndarray, limit: float = np.inf) -> np.ndarray:
    """Geodesic Voronoi cells on the mesh edge graph (multi-source Dijkstra).

    Parameters
    ----------
    graph : WeldedGraph
    sources : (S,) int
        Welded vertex ids (duplicates allowed: equal sources share a cell).
    limit : float
        Vertices farther than ``limit`` (metres along edges) from every source get -1.

    Returns
    -------
    (n,) int: position in ``sources`` of the nearest source, -1 when none within ``limit``.
    """
    sources = np.asarray(sources, dtype=np.int64)
    uniq, first = np.unique(sources, return_index=True)
    dist, _, nearest = csgraph.dijkstra(graph.lengths, directed=False, indices=uniq, min_only=True, return_predecessors=True, limit=limit)
    pos = np.full(graph.n, -1, dtype=np.int64)
    ok = nearest >= 0
    # map the nearest source vertex back to its first position in ``sources``
    lookup = dict(zip(uniq.tolist(), first.tolist()))
    pos[ok] = np.array([lookup[v] for v in nearest[ok].tolist()], dtype=np.int64) if ok.any() else pos[ok]
    return pos


def marker_weights(rig: Rig, layout: MarkerLayout, masks: np.ndarray, radius: Optional[float] = None,
                   graph: Optional[WeldedGraph] = None) -> np.ndarray:
    """Per-region marker importances: the diagonals of M_k (Liu et al. 2011, §3.2.2).

    ``m_kq = r(B_k, q) / Σ_k' r(B_k', q)`` with r(B_k, q) the mean of mask k over marker q's
    Voronoi cell. The paper takes cells in texture space; we take geodesic cells on the
    mesh (Dijkstra over edges from each marker's dominant vertex), clipped to ``radius``
    so a marker's cell does not run over the back of the head.

    Parameters
    ----------
    rig : Rig
    layout : MarkerLayout
        M markers on ``rig``.
    masks : (R, V) float
        Soft masks (e.g. ``segment(rig).masks``).
    radius : float, optional
        Cell radius in metres along the mesh; default the median distance from a marker to
        its nearest other marker (in space), i.e. about one marker spacing.
    graph : WeldedGraph, optional
        Reuse a ``welded_graph(rig)`` result.

    Returns
    -------
    (R, M) float64, non-negative, every column summing to 1. Row k scaled per coordinate
    (repeated three times) is the diagonal of M_k.

    Raises
    ------
    ValueError
        Masks of the wrong shape, a layout that does not fit the rig.
    """
    layout.check(rig)
    masks = np.asarray(masks, dtype=np.float64)
    if masks.ndim != 2 or masks.shape[1] != rig.n_vertices:
        raise ValueError(f"masks: expected (R, {rig.n_vertices}) for rig {rig.name!r}, got {masks.shape}")
    if (masks < -1e-12).any():
        raise ValueError("masks: expected non-negative values")
    graph = graph or welded_graph(rig)
    M = layout.n_markers
    dom = layout.vertices[np.arange(M), np.argmax(layout.weights, axis=1)]
    src = graph.index[dom]
    if radius is None:
        if M > 1:
            P = layout.points(rig.neutral)
            dd, _ = cKDTree(P).query(P, k=2)
            radius = float(np.median(dd[:, 1]))
        radius = radius if (radius is not None and radius > 0) else np.inf
    cells = voronoi_cells(graph, src, limit=radius)
    mw = masks[:, graph.first]  # (R, n)
    ok = cells >= 0
    cnt = np.bincount(cells[ok], minlength=M).astype(np.float64)
    R = len(masks)
    r = np.empty((R, M))
    for k in range(R):
        r[k] = np.bincount(cells[ok], weights=mw[k, ok], minlength=M)
    # markers sharing a source vertex: copy the shared cell's values
    uniq_first = np.unique(src, return_index=True)
    share = {int(v): int(i) for v, i in zip(*uniq_first)}
    for q in range(M):
        j = share[int(src[q])]
        if j != q:
            r[:, q], cnt[q] = r[:, j], cnt[j]
    r = r / np.maximum(cnt, 1)[None, :]
    tot = r.sum(0, keepdims=True)
    if (tot <= 0).any():  # a cell with zero mask mass everywhere: fall back to the vertex's masks
        bad = np.flatnonzero(tot[0] <= 0)
        r[:, bad] = masks[:, dom[bad]]
        tot = r.sum(0, keepdims=True)
    return r / tot
