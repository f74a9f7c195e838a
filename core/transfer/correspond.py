"""Preprocessing: bring the target reference to the source topology (Xu et al. 2014 §3).

"We manually identify a small number of corresponding points on the reference meshes and
use them to deform the reference source mesh to the reference target mesh via non-rigid
ICP ... The corresponding points of the remaining vertices of the source mesh are obtained
by searching for the closest points on the target mesh ... we resample the target mesh
using the topology of the source mesh."

1. :func:`similarity_align`: scale + rotation + translation of the source landmarks onto the
   target landmarks (Umeyama 1991), so the non-rigid stage starts close;
2. non-rigid ICP of the aligned source onto the target surface with the landmarks as soft
   constraints (:func:`trimesh.registration.nricp_amberg`, Amberg et al. 2007 — the optimal
   step NICP that Huang et al. 2011 build on);
3. closest-point resampling: every registered source vertex within ``max_distance`` of the
   target surface is moved onto it; the rest (parts the target does not have, e.g. a mouth
   bag or eye sockets) keep the registered position and are reported.

The registration residual (vertex-to-surface distances, landmark residuals, in mm) comes back
with the result: it is the honest measure of how well the two faces correspond.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._mesh import bbox_size, check_faces, check_positions

__all__ = ["similarity_align", "Registration", "register", "resample_onto", "barycentric_map", "landmarks_from_shapes"]


def similarity_align(source_points, target_points) -> tuple[float, np.ndarray, np.ndarray]:
    r"""Least-squares similarity ``x -> s R x + t`` taking ``source_points`` onto ``target_points``.

    .. math:: \min_{s, R \in SO(3), t} \sum_i \|s R p_i + t - q_i\|^2

    (Umeyama 1991, closed form by SVD with the reflection fix).

    Returns
    -------
    s : float, R : (3, 3), t : (3,)

    Raises
    ------
    ValueError
        Fewer than 3 points or mismatched shapes.
    """
    p = np.asarray(source_points, dtype=np.float64)
    q = np.asarray(target_points, dtype=np.float64)
    if p.shape != q.shape or p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"source_points, target_points: expected two (M, 3) arrays with M >= 3, got {p.shape}, {q.shape}")
    mp, mq = p.mean(0), q.mean(0)
    P, Q = p - mp, q - mq
    U, S, Vt = np.linalg.svd(Q.T @ P / len(p))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (P ** 2).sum() / len(p)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    t = mq - s * R @ mp
    return s, R, t


def barycentric_map(points, mesh_positions, mesh_faces):
    """Closest point of each of ``points`` (n, 3) on a triangle mesh.

    Returns
    -------
    triangles : (n,) int, barycentric : (n, 3), distance : (n,), closest : (n, 3)
    """
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(mesh_positions, dtype=np.float64), np.asarray(mesh_faces), process=False)
    closest, dist, tri = trimesh.proximity.closest_point(mesh, np.asarray(points, dtype=np.float64))
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    return tri, bary, dist, closest


def resample_onto(values, faces, triangles, barycentric) -> np.ndarray:
    """Interpolate per-vertex ``values`` (..., V, c) at barycentric points -> (..., n, c)."""
    v = np.asarray(values)
    corners = v[..., np.asarray(faces)[triangles], :]  # (..., n, 3, c)
    return np.einsum("...nkc,nk->...nc", corners, barycentric)


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register` (all positions in the target's frame, metres).

    Attributes
    ----------
    aligned : (V, 3)      source after the similarity alignment
    registered : (V, 3)   source after non-rigid ICP
    resampled : (V, 3)    the target reference in the source topology
    projected : (V,) bool vertices moved onto the target surface
    distance : (V,)       registered vertex -> target surface distance
    landmark_residual : (M,) distance of each landmark after ICP
    scale : float         similarity scale source -> target
    report : dict         summary in millimetres
    """

    aligned: np.ndarray
    registered: np.ndarray
    resampled: np.ndarray
    projected: np.ndarray
    distance: np.ndarray
    landmark_residual: np.ndarray
    scale: float
    report: dict = field(default_factory=dict)


def register(source_ref, source_faces, target_ref, target_faces, source_landmarks, target_landmarks,
             steps=None, max_distance: float | None = None, icp: bool = True) -> Registration:
    """Deform the source reference onto the target reference and resample the target (§3).

    Parameters
    ----------
    source_ref : (V, 3), source_faces : (F, 3) int
    target_ref : (V', 3), target_faces : (F', 3) int
    source_landmarks : (M,) int vertex ids on the source
    target_landmarks : (M, 3) positions on the target (e.g. a layout's marker points)
    steps : list of (ws, wl, wn, max_iter), optional
        Non-rigid ICP schedule (stiffness, landmark weight, normal weight, iterations);
        default a stiff-to-soft schedule of 4 steps.
    max_distance : float, optional
        Project only vertices closer than this to the target surface (default 2% of the
        target's bounding-box diagonal).
    icp : bool
        False stops after the similarity alignment (for tests and coarse previews).

    Returns
    -------
    Registration

    Raises
    ------
    ValueError
        Bad shapes, landmark ids out of range, fewer than 3 landmarks.
    """
    import trimesh

    S = check_positions(source_ref, "source_ref")
    Fs = check_faces(source_faces, len(S), "source_faces")
    Tt = check_positions(target_ref, "target_ref")
    Ft = check_faces(target_faces, len(Tt), "target_faces")
    lm = np.asarray(source_landmarks, dtype=np.int64).ravel()
    q = np.asarray(target_landmarks, dtype=np.float64)
    if q.shape != (len(lm), 3):
        raise ValueError(f"target_landmarks: expected ({len(lm)}, 3) for {len(lm)} source landmarks, got {q.shape}")
    if len(lm) < 3:
        raise ValueError("source_landmarks: need at least 3 landmarks")
    if lm.min() < 0 or lm.max() >= len(S):
        raise ValueError(f"source_landmarks: ids must lie in [0, {len(S)})")
    size = bbox_size(Tt)
    s, R, t = similarity_align(S[lm], q)
    aligned = s * S @ R.T + t
    target = trimesh.Trimesh(Tt, Ft, process=False)
    if icp:
        if steps is None:
            steps = [[0.02, 10, 0.5, 10], [0.007, 5, 0.5, 10], [0.002, 2.5, 0.5, 10], [0.0005, 1, 0.0, 10]]
        src = trimesh.Trimesh(aligned, Fs, process=False)
        registered = np.asarray(trimesh.registration.nricp_amberg(
            src, target, source_landmarks=lm, target_positions=q, steps=steps,
            distance_threshold=0.1 * size), dtype=np.float64)
    else:
        registered = aligned
    closest, dist, _ = trimesh.proximity.closest_point(target, registered)
    max_distance = 0.02 * size if max_distance is None else float(max_distance)
    projected = dist <= max_distance
    resampled = np.where(projected[:, None], closest, registered)
    lres = np.linalg.norm(registered[lm] - q, axis=1)
    mm = 1000.0
    report = {
        "scale": s,
        "surface_distance_mm_median": float(np.median(dist) * mm),
        "surface_distance_mm_p95": float(np.percentile(dist, 95) * mm),
        "surface_distance_mm_max": float(dist.max() * mm),
        "projected_fraction": float(projected.mean()),
        "landmark_residual_mm_mean": float(lres.mean() * mm),
        "landmark_residual_mm_max": float(lres.max() * mm),
        "max_distance_mm": max_distance * mm,
    }
    return Registration(aligned, registered, resampled, projected, dist, lres, float(s), report)


def landmarks_from_shapes(source_deltas, source_names, target_deltas, target_names, pairs):
    """Corresponding landmarks from blendshapes that mean the same thing on two rigs.

    For each ``(source shape, target shape)`` pair, the vertex that moves most in that shape
    (an eyelid centre for a blink, the chin for jaw-open, a mouth corner for a smile) is a
    landmark on each rig. A fallback for rigs without a marker layout (the Jeeliz animals);
    it is only as good as the shapes are alike.

    Parameters
    ----------
    source_deltas : (K, V, 3), source_names : K names
    target_deltas : (K', V', 3), target_names : K' names
    pairs : list of (source name, target name)

    Returns
    -------
    source_vertices : (M,) int, target_vertices : (M,) int

    Raises
    ------
    KeyError naming a shape that a rig does not have.
    """
    sn, tn = list(source_names), list(target_names)
    src, tgt = [], []
    for a, b in pairs:
        if a not in sn:
            raise KeyError(f"pairs: source has no shape {a!r}")
        if b not in tn:
            raise KeyError(f"pairs: target has no shape {b!r}")
        src.append(int(np.argmax(np.linalg.norm(np.asarray(source_deltas[sn.index(a)]), axis=1))))
        tgt.append(int(np.argmax(np.linalg.norm(np.asarray(target_deltas[tn.index(b)]), axis=1))))
    return np.asarray(src, dtype=np.int64), np.asarray(tgt, dtype=np.int64)
