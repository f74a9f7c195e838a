"""Preprocessing: bring the target reference to the source topology (Xu et al. 2014 §3).

"We first build the correspondences between the two reference meshes in a semi-automatic
manner ... we manually identify a small number of corresponding points on the reference
meshes and use them to deform the reference source mesh to the reference target mesh via
non-rigid ICP ... The corresponding points of the remaining vertices of the source mesh are
obtained by searching for the closest points on the target mesh ... we resample the target
mesh using the topology of the source mesh."

1. the similarity transform (:func:`core.geometry.procrustes`, ``scale=True``): scale + rotation
   + translation of the source landmarks onto the target landmarks (Umeyama 1991), so the
   non-rigid stage starts close;
2. non-rigid ICP of the aligned source onto the target surface with the landmarks as soft
   constraints (:func:`core.geometry.nonrigid_icp`, trimesh's ``nricp_amberg`` loop made fast
   and coarse to fine, Amberg et al. 2007 — the optimal step NICP that Huang et al. 2011
   build on);
3. closest-point resampling: every registered source vertex within ``max_distance`` of the
   target surface is moved onto it, unless the move would fold a triangle over; the rest keep
   the registered position and are reported.

When the target is a face and the source a whole head (ICT -> the Jeeliz animals), steps 2-3
run on the source's face region only (:func:`face_crop`, from the hand-placed landmarks), and
the rest of the head (neck, back of head, eye sockets, mouth bag) follows the face smoothly
(harmonic extension of the displacement) instead of being projected onto whatever target
surface is nearest. See ``crop`` of :func:`register`.

The registration residual (vertex-to-surface distances, landmark residuals, in mm) and the
number of folded-over triangles come back with the result: they are the honest measure of
how well the two faces correspond.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence, Union

import numpy as np
import trimesh
from scipy.interpolate import RBFInterpolator
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError

from ..geometry import (
    ClosestPoints, flipped_faces, harmonic_extension, largest_component, nonrigid_icp, nricp_steps, procrustes,
    vertex_adjacency, vertex_normals)
from ..progress import report as report_progress
from ._mesh import bbox_size, check_faces, check_positions

__all__ = ["Registration", "register", "resample_onto", "landmarks_from_shapes", "face_crop"]


def resample_onto(values, faces, triangles, barycentric) -> np.ndarray:
    """Interpolate per-vertex ``values`` (..., V, c) at barycentric points -> (..., n, c)."""
    v = np.asarray(values)
    corners = v[..., np.asarray(faces)[triangles], :]  # (..., n, 3, c)
    return np.einsum("...nkc,nk->...nc", corners, barycentric)


def face_crop(positions, faces, landmarks, margin: float = 0.06, depth: float = 0.05,
              covered: bool = True) -> np.ndarray:
    r"""The face region of a head: where the landmarks are, on the outer skin (V,) bool.

    The landmarks (hand-placed markers on the face skin) define the face's frame: their
    centre ``c``, their best-fit plane (axes ``a, b``) and its normal ``n``, oriented to the
    side the landmark vertex normals face. With ``u = ((x - c)·a, (x - c)·b)`` the position
    in the plane, ``h = (x - c)·n`` the height above it, and ``H(u)`` the thin-plate spline
    through the landmarks' ``(u, h)`` (a smooth "shell" over the face), a vertex is kept when

    .. math:: \operatorname{dist}(u, \operatorname{hull}(u_{lm})) \le \text{margin}\cdot D,
              \qquad H(u) - h \le \text{depth}\cdot D

    and (``covered=True``) the ray ``x + τ n, τ > 0`` hits no triangle of the mesh. ``D`` is
    the landmarks' bounding-box diagonal; the hull distance is 0 inside the 2-D convex hull.

    * the hull test bounds the face sideways: no back of head, neck or ears;
    * the depth test drops what lies well behind the skin the landmarks sit on — the eye
      sockets, seen through the open lids, lie 15–30 mm behind the shell on the ICT head,
      the skin inside the hull within ±10 mm of it;
    * the ray test drops what the face itself covers seen from the front: the inside of the
      lips and the front of the mouth bag (behind closed lips, only 0–12 mm deep), the
      nostrils, the lid margins — parts an animal face has no counterpart for, which the
      non-rigid ICP would otherwise crush onto the target's mouth crease.

    Last, only connected parts that contain a landmark are kept; landmark vertices always are.

    Parameters
    ----------
    positions : (V, 3), faces : (F, 3) int
    landmarks : (M,) int, M >= 4, vertex ids of face markers (spread over the face)
    margin, depth : float >= 0, fractions of ``D``; the defaults (≈ 14 mm and 12 mm on ICT)
        give the crop drawn in docs/transfer.md
    covered : bool, apply the ray test

    Returns
    -------
    (V,) bool

    Raises
    ------
    ValueError
        Fewer than 4 landmarks, ids out of range, negative margin/depth, landmarks that
        all lie on a line.
    """


    S = check_positions(positions, "positions")
    F = check_faces(faces, len(S))
    lm = np.unique(np.asarray(landmarks, dtype=np.int64).ravel())
    if len(lm) < 4:
        raise ValueError(f"landmarks: the face crop needs at least 4 distinct landmark vertices, got {len(lm)}")
    if lm.min() < 0 or lm.max() >= len(S):
        raise ValueError(f"landmarks: ids must lie in [0, {len(S)})")
    if not (margin >= 0 and depth >= 0):
        raise ValueError(f"margin, depth: expected non-negative fractions of the landmark spread, got {margin}, {depth}")
    P = S[lm]
    c = P.mean(0)
    _, sv, Vt = np.linalg.svd(P - c, full_matrices=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise ValueError("landmarks: they lie on a line; a face crop needs landmarks spread over the face")
    n = Vt[2]
    if vertex_normals(S, F)[lm].sum(0) @ n < 0:
        n = -n
    D = float(np.linalg.norm(P.max(0) - P.min(0)))
    uv = (S - c) @ Vt[:2].T
    h = (S - c) @ n
    shell = RBFInterpolator(uv[lm], h[lm], kernel="thin_plate_spline")(uv)
    try:
        eq = ConvexHull(uv[lm]).equations
    except QhullError as e:  # pragma: no cover - collinear in the plane, caught above
        raise ValueError(f"landmarks: no 2-D hull ({e})") from None
    outside = np.max(uv @ eq[:, :2].T + eq[:, 2], axis=1)
    keep = (outside <= margin * D) & (shell - h <= depth * D)
    if covered and keep.any():

        cand = np.flatnonzero(keep)
        mesh = trimesh.Trimesh(S, F, process=False)
        # start a hair in front of the vertex so the ray does not hit the vertex's own triangles
        hit = mesh.ray.intersects_any(S[cand] + 1e-4 * D * n, np.broadcast_to(n, (len(cand), 3)))
        keep[cand[hit]] = False
    keep[lm] = True
    idx = np.flatnonzero(keep)
    A = vertex_adjacency(F, len(S))[idx][:, idx]
    _, label = connected_components(A, directed=False)
    with_lm = np.unique(label[np.searchsorted(idx, lm)])
    out = np.zeros(len(S), bool)
    out[idx[np.isin(label, with_lm)]] = True
    return out


def _crop_mask(crop, n: int, crop_index) -> np.ndarray:
    """A user's crop (mask or ids, in ``crop_index`` numbering if given) -> (n,) bool."""
    a = np.asarray(crop)
    if crop_index is not None:
        ci = np.asarray(crop_index, dtype=np.int64).ravel()
        if ci.size and (ci.min() < 0 or ci.max() >= n):
            raise ValueError(f"crop_index: values must lie in [0, {n})")
        n_in = len(ci)
    else:
        n_in = n
    if a.ndim != 1:
        raise ValueError(f"crop: expected 'auto', 'face', 'none', a ({n_in},) bool mask or 1-D vertex ids; got shape {a.shape}")
    if a.dtype == bool:
        if len(a) != n_in:
            raise ValueError(f"crop: a boolean mask needs one entry per source vertex ({n_in},), got ({len(a)},)")
        ids = np.flatnonzero(a)
    elif np.issubdtype(a.dtype, np.integer) or a.size == 0:
        ids = a.astype(np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= n_in):
            raise ValueError(f"crop: vertex ids must lie in [0, {n_in}), got [{ids.min()}, {ids.max()}]")
    else:
        raise ValueError(f"crop: expected a bool mask or integer vertex ids, got dtype {a.dtype}")
    mask = np.zeros(n, bool)
    mask[ci[ids] if crop_index is not None else ids] = True
    return mask


def _extend(values, mask, faces, n: int) -> np.ndarray:
    r"""Harmonic extension of per-vertex ``values`` (|mask|, c) given on ``mask`` to all vertices
    (:func:`core.geometry.harmonic_extension`: graph Laplacian, each free vertex the mean of its
    neighbours). By the maximum principle every component stays within the range of the given
    values, so the extension never overshoots (a biharmonic one, C¹ at the rim, extrapolated the
    face's shrinking into a long thin neck and flipped 5x more triangles on ICT -> tiger)."""

    return harmonic_extension(values, mask, faces, n)


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register` (all positions in the target's frame, metres).

    Attributes
    ----------
    aligned : (V, 3)      source after the similarity alignment
    registered : (V, 3)   source after non-rigid ICP (outside the crop: its smooth extension)
    resampled : (V, 3)    the target reference in the source topology
    projected : (V,) bool vertices moved onto the target surface
    distance : (V,)       registered vertex -> target surface distance
    landmark_residual : (M,) distance of each landmark after ICP
    scale : float         similarity scale source -> target
    report : dict         summary in millimetres
    crop : (V,) bool or None   the source vertices registered to the target; None = all
    """

    aligned: np.ndarray
    registered: np.ndarray
    resampled: np.ndarray
    projected: np.ndarray
    distance: np.ndarray
    landmark_residual: np.ndarray
    scale: float
    report: dict = field(default_factory=dict)
    crop: Optional[np.ndarray] = None


#: the non-rigid ICP schedule (stiffness, landmark weight, normal weight, iterations): the shared
#: schedule of :func:`core.geometry.nricp_steps`, 10 iterations per step
DEFAULT_STEPS = nricp_steps()
#: the schedule of a cropped registration: the last, supple step keeps the normal term, so the
#: face is not pulled onto target surface that faces another way (ICT -> tiger: 334 instead of
#: 417 folded triangles, landmarks 0.13 / 1.25 instead of 0.14 / 1.43 mm mean / max; the
#: triceratops 606 instead of 819, 0.20 / 1.76 instead of 0.22 / 2.0 mm; in exchange the crop's
#: surface distance p95 grows from 0.03 to 0.34 mm on the tiger, 0.11 to 2.7 mm on the triceratops)
CROP_STEPS = nricp_steps(final_normal=0.5)
#: the non-rigid ICP runs coarse to fine on about this many vertices when the registered part
#: of the source has more than twice as many (:func:`core.geometry.nonrigid_icp`)
COARSE_VERTICES = 3000
#: ``crop="auto"`` crops when fewer than this fraction of the source vertices outside the face
#: crop have target surface within ``AUTO_CROP_TOLERANCE`` x the landmark spread after the similarity
AUTO_CROP_COVERAGE = 0.9
AUTO_CROP_TOLERANCE = 0.1
_CROP_WORDS = ("auto", "face", "none")


def register(source_ref, source_faces, target_ref, target_faces, source_landmarks, target_landmarks,
             steps=None, max_distance: float | None = None, icp: bool = True,
             crop: Union[str, None, np.ndarray, Sequence[int]] = "auto", crop_index=None,
             coarse: Optional[int] = COARSE_VERTICES, progress=None) -> Registration:
    """Deform the source reference onto the target reference and resample the target (§3).

    The paper's semi-automatic correspondence: hand-placed landmarks, then non-rigid ICP,
    then closest points. When the target lacks most of what the source head has (an animal
    head without neck, a face mask) only the source's face region takes part (``crop``):

    1. the similarity transform ``x -> s R x + t`` from the landmarks (Umeyama 1991,
       :func:`core.geometry.procrustes` with ``scale=True``);
    2. non-rigid ICP of the crop's triangles onto the target's skin (its largest connected
       part, so eyeballs and whiskers never attract the face), landmarks as soft constraints;
    3. closest-point resampling of the crop's vertices within ``max_distance``, except
       vertices whose move would flip a triangle the ICP left the right way up (they keep
       the registered position, ``report["kept_off_surface"]``);
    4. every vertex outside the crop (back of head, neck, eye sockets, mouth bag) follows
       the crop: its displacement from the aligned source is the harmonic extension of the
       crop's (graph Laplacian, :func:`_extend`), instead of being projected onto whatever
       target surface is nearest — the fold-overs of the uncropped registration.

    Parameters
    ----------
    source_ref : (V, 3), source_faces : (F, 3) int
    target_ref : (V', 3), target_faces : (F', 3) int
    source_landmarks : (M,) int vertex ids on the source
    target_landmarks : (M, 3) positions on the target (e.g. a layout's marker points)
    steps : list of (ws, wl, wn, max_iter), optional
        Non-rigid ICP schedule (stiffness, landmark weight, normal weight, iterations);
        default :data:`DEFAULT_STEPS`, a stiff-to-soft schedule of 4 steps, or
        :data:`CROP_STEPS` (normal term kept to the end) for a cropped registration.
    max_distance : float, optional
        Project only vertices closer than this to the target surface (default 2% of the
        target's bounding-box diagonal).
    icp : bool
        False stops after the similarity alignment (for tests and coarse previews).
    crop : "auto" | "face" | "none" | None | (V,) bool | (n,) int
        ``"face"``: :func:`face_crop` of the source around its landmarks; ``"none"`` (or
        None): the whole source (every vertex may be projected); a mask or vertex ids: that
        region. ``"auto"`` (default) is ``"face"`` when the target lacks the rest of the
        source head — fewer than :data:`AUTO_CROP_COVERAGE` of the source vertices outside
        the face crop have target surface within :data:`AUTO_CROP_TOLERANCE` × the landmark
        spread after the similarity (Rocketbox 0.98: not cropped; the Jeeliz tiger 0.65 and
        triceratops 0.80: cropped) — else ``"none"``.
    crop_index : (V0,) int, optional
        When ``crop`` is a mask or ids over another numbering of the source (e.g. before
        seam welding), the row of ``source_ref`` of each of those vertices.

    Returns
    -------
    Registration; ``report`` holds, in mm, the landmark residuals, the surface distance of
    the crop's registered vertices, the projected fractions and the fold-overs
    (``flipped_triangles``: triangles of ``resampled`` whose normal flips against
    ``aligned``'s, :func:`core.geometry.flipped_faces`).

    Raises
    ------
    ValueError
        Bad shapes, landmark ids out of range, fewer than 3 landmarks, an unknown crop word,
        a crop mask of the wrong length or ids out of range, a crop that leaves out a
        landmark or holds no whole triangle.
    """
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
    word = crop if crop is None or isinstance(crop, str) else None
    if isinstance(word, str) and word not in _CROP_WORDS:
        raise ValueError(f"crop: expected one of {', '.join(map(repr, _CROP_WORDS))}, a bool mask or vertex ids; got {crop!r}")
    if isinstance(crop, (bool, np.bool_)):
        raise ValueError("crop: expected 'auto', 'face' or 'none' (not a bool), or a mask / vertex ids")
    mask = None if word is not None else _crop_mask(crop, len(S), crop_index)
    size = bbox_size(Tt)
    s, R, t = procrustes(S[lm], q, scale=True)
    aligned = s * S @ R.T + t
    target = ClosestPoints(Tt, Ft)
    max_distance = 0.02 * size if max_distance is None else float(max_distance)
    report = {"scale": s}

    if word in ("auto", "face"):
        face = face_crop(S, Fs, lm)
        if word == "auto":
            rest = np.flatnonzero(~face)
            spread = s * float(np.linalg.norm(np.ptp(S[np.unique(lm)], 0)))
            cover = 1.0
            if len(rest):
                _, d_rest, _, _ = target.query(aligned[rest], max_distance=AUTO_CROP_TOLERANCE * spread)
                cover = float(np.mean(d_rest <= AUTO_CROP_TOLERANCE * spread))
            report["auto_crop_coverage"] = cover
            mask = face if cover < AUTO_CROP_COVERAGE else None
        else:
            mask = face
    report["crop"] = "none" if mask is None else (word if word in ("auto", "face") else "given")
    if steps is None:
        steps = DEFAULT_STEPS if mask is None else CROP_STEPS
    steps = [list(x) for x in steps]

    # matches farther than ICP_DISTANCE x the target's diagonal take no part; nonrigid_icp
    # reads its threshold in units of the (registered part of the) source's diagonal
    def icp_threshold(part):
        return _threshold(size, bbox_size(part))

    def icp_progress(f, msg):
        report_progress(progress, 0.02 + 0.93 * f, msg)

    if mask is None:  # the whole source: every vertex is registered and may be projected
        if icp:
            registered = nonrigid_icp(aligned, Fs, Tt, Ft, lm, q, steps, distance_threshold=icp_threshold(aligned),
                                      coarse=coarse, progress=icp_progress)
        else:
            registered = aligned
        closest, dist, _, _ = target.query(registered)
        near = dist <= max_distance
        resampled, projected = _snap(aligned, registered, closest, near, Fs)
        inside = np.ones(len(S), bool)
    else:
        outside_lm = lm[~mask[lm]]
        if len(outside_lm):
            raise ValueError(f"crop: landmark vertices {np.unique(outside_lm)[:10].tolist()} lie outside the crop; "
                             "the crop must contain every landmark")
        fmask = mask[Fs].all(1)
        if not fmask.any():
            raise ValueError("crop: selects no whole triangle of source_faces; give a connected face region")
        inside = np.zeros(len(S), bool)
        inside[Fs[fmask].ravel()] = True
        inside[lm] = True
        ids = np.flatnonzero(inside)
        local = np.full(len(S), -1, np.int64)
        local[ids] = np.arange(len(ids))
        skin = largest_component(Tt, Ft)
        target = ClosestPoints(Tt, Ft[skin])
        if icp:
            reg_in = nonrigid_icp(aligned[ids], local[Fs[fmask]], Tt, Ft[skin], local[lm], q, steps,
                                  distance_threshold=icp_threshold(aligned[ids]), coarse=coarse, progress=icp_progress)
        else:
            reg_in = aligned[ids]
        closest, d_in, _, _ = target.query(reg_in)
        near = np.zeros(len(S), bool)
        near[ids] = d_in <= max_distance
        res_in, proj_in = _snap(aligned[ids], reg_in, closest, near[ids], local[Fs[fmask]])
        disp = _extend(np.hstack([reg_in - aligned[ids], res_in - aligned[ids]]), inside, Fs, len(S))
        registered = aligned + disp[:, :3]
        resampled = aligned + disp[:, 3:]
        registered[ids], resampled[ids] = reg_in, res_in
        projected = np.zeros(len(S), bool)
        projected[ids] = proj_in
        dist = np.empty(len(S))
        dist[ids] = d_in
        if len(ids) < len(S):
            dist[~inside] = target.query(registered[~inside])[1]
    lres = np.linalg.norm(registered[lm] - q, axis=1)
    mm = 1000.0
    d_crop = dist[inside]
    in_faces = inside[Fs].all(1)
    flipped = flipped_faces(aligned, resampled, Fs)
    report.update({
        "surface_distance_mm_median": float(np.median(d_crop) * mm),
        "surface_distance_mm_p95": float(np.percentile(d_crop, 95) * mm),
        "surface_distance_mm_max": float(d_crop.max() * mm),
        "projected_fraction": float(projected.mean()),
        "landmark_residual_mm_mean": float(lres.mean() * mm),
        "landmark_residual_mm_max": float(lres.max() * mm),
        "max_distance_mm": max_distance * mm,
        "crop_fraction": float(inside.mean()),
        "crop_projected_fraction": float(projected[inside].mean()),
        "kept_off_surface": int((near & ~projected).sum()),
        "flipped_triangles": int(flipped.sum()),
        "flipped_triangles_crop": int(flipped[in_faces].sum()),
    })
    return Registration(aligned, registered, resampled, projected, dist, lres, float(s), report,
                        None if mask is None else inside)


#: matches farther than this fraction of the target's bounding-box diagonal take no part in the
#: non-rigid ICP (see :func:`_threshold`)
ICP_DISTANCE = 0.1


def _threshold(target_size: float, source_size: float) -> float:
    """The non-rigid ICP's distance threshold, ``ICP_DISTANCE`` x the target's diagonal, in
    the units :func:`core.geometry.nonrigid_icp` reads it in: the registered source's diagonal.

    Until this was written the caller passed ``0.1 x target diagonal in metres`` as is, which
    trimesh read as a fraction of the source's diagonal: 25.7 mm on ICT -> Rocketbox (4.5 %
    of the target), 4.6 mm on the tiger (1.8 %), 6.5 mm on the triceratops (2.0 %), and a
    number that changed with the units. With the intended 57 / 25 / 32 mm the animals fit
    better on every measure (tiger: folded 336 -> 316, crop surface p95 0.34 -> 0.09 mm,
    projected 0.92 -> 0.95; triceratops: 608 -> 584, 2.7 -> 0.49 mm, 0.85 -> 0.91) and
    Rocketbox is unchanged (242 -> 237 folded)."""
    return ICP_DISTANCE * target_size / max(source_size, 1e-300)


def _snap(reference, registered, closest, near, faces, max_rounds: int = 20):
    """Closest-point resampling that adds no fold-over: vertices in ``near`` move to
    ``closest`` except those whose move would flip a triangle (against ``reference``) that
    the registered surface has the right way up; they keep their registered position.

    The ICP result already lies on the target almost everywhere (ICT -> tiger: 0.03-0.3 mm
    p95), and the plain snap of the last few percent onto concave creases of the coarse
    target flipped ~150 more triangles there (ICT -> Rocketbox: 247). Returns (positions
    (n, 3), projected (n,) bool).
    """
    was = flipped_faces(reference, registered, faces)
    proj = near.copy()
    for _ in range(max_rounds):
        out = np.where(proj[:, None], closest, registered)
        bad = flipped_faces(reference, out, faces) & ~was
        bad &= proj[faces].any(1)
        if not bad.any():
            break
        proj[faces[bad].ravel()] = False
    return np.where(proj[:, None], closest, registered), proj


def landmarks_from_shapes(source_deltas, source_names, target_deltas, target_names, pairs):
    """Corresponding landmarks from blendshapes that mean the same thing on two rigs.

    For each ``(source shape, target shape)`` pair, the vertex that moves most in that shape
    (an eyelid centre for a blink, the chin for jaw-open, a mouth corner for a smile) is a
    landmark on each rig. A fallback for rigs without a marker layout (the bundled Jeeliz
    animals have one now: :func:`core.transfer.performance.shared_landmarks`); it is only as
    good as the shapes are alike (ICT -> tiger: 6.8 mm mean landmark residual, against 0.14 mm
    with the layouts and the face crop).

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
