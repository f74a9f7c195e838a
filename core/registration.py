"""Move a marker layout to a rig of any topology by non-rigid registration.

The layout's markers sit on the source rig's neutral. To put them on a target rig we

1. **align** the source face to the target with a similarity transform ``x -> s R x + t``:
   from landmark markers whose target positions are given (Umeyama 1991, least squares), else
   automatically — bounding boxes of the two heads, refined by the motion centres of the eye-close
   and jaw-open shapes when both rigs have them — then similarity ICP of the source face onto the
   target surface (Besl & McKay 1992);
2. **register** non-rigidly: the source face region (decimated to ~2,500 vertices) is deformed
   onto the target surface, pulled by the landmarks or the eye/jaw motion centres, with
   optimal-step non-rigid ICP (Amberg, Romdhani & Vetter 2007, :func:`core.geometry.nonrigid_icp`
   on ``trimesh.registration.nricp_amberg``), which minimises per-vertex affine transforms X_i under

   ``E(X) = E_d(X) + alpha E_s(X) + beta E_l(X)``,
   ``E_d = sum_i w_i || X_i v_i - u_i ||^2`` (closest target points u_i),
   ``E_s = sum_{(i,j) in edges} || (X_i - X_j) G ||_F^2`` (stiffness, G = diag(1, 1, 1, gamma)),
   ``E_l = sum_l || X_l v_l - p_l ||^2`` (landmarks), for decreasing stiffness alpha;
3. **project**: each registered marker goes to the closest point of the target's skin (its
   largest connected component, so eyeballs, teeth and hair cards are never chosen), stored as a
   face + barycentric marker.

Everything is done in a normalised frame (source face region centred, unit bounding-box
diagonal) so the registration weights do not depend on the rigs' units or size.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Mapping, Optional, Sequence, Union

import numpy as np
import trimesh

from .geometry import (
    closest_points, decimate, face_vertices, largest_component, nonrigid_icp, nricp_steps, procrustes, weld_vertices)
from .io.layout import default_layout_path, layouts_dir, read_layout, sidecar_layout_path, write_layout
from .io.performance import read_performance
from .io.rigs import NoLayoutError, load_rig, load_rig as read_rig
from .io.sequence import read_mesh_sequence, topology_rig
from .model import MarkerLayout, Rig
from .progress import report as say

#: registration schedule (ws stiffness, wl landmark weight, wn normal weight, max iterations):
#: the shared stiff-to-supple schedule with fewer iterations and a stiffer last step, tuned on
#: the bundled rigs for a few seconds per pair (see scripts/layout_report.py)
DEFAULT_STEPS = nricp_steps(iterations=(6, 6, 6, 4), final_stiffness=7e-4)

#: shapes that locate the eyes and the jaw, by canonical ARKit name and known aliases
_FEATURE_SHAPES = {
    "eyeBlinkLeft": ("eyeBlinkLeft", "eyeBlink_L", "AK_09_EyeBlinkLeft", "EyeBlinkLeft", "eyeLeftClose"),
    "eyeBlinkRight": ("eyeBlinkRight", "eyeBlink_R", "AK_10_EyeBlinkRight", "EyeBlinkRight", "eyeRightClose"),
    "jawOpen": ("jawOpen", "AK_25_JawOpen", "JawOpen", "mouthOpen"),
}


# ---------------------------------------------------------------------------------------------
# small geometric helpers
def _apply(s, R, t, p):
    return s * np.asarray(p) @ R.T + t


def merged_mesh(rig: Rig, mask_faces: Optional[np.ndarray] = None):
    """Merge the rig's UV-seam duplicates (identical positions) into one vertex
    (:func:`core.geometry.weld_vertices`, default tolerance).

    Returns (positions (Vm, 3), faces (Fm, 3) merged ids, merged_of (V,) original -> merged,
    face_index (Fm,) original face of each merged face). Degenerate merged faces are dropped.
    Merged ids follow the first occurrence of each position.
    """
    fidx = np.arange(len(rig.faces)) if mask_faces is None else np.flatnonzero(mask_faces)
    w = weld_vertices(rig.neutral, rig.faces[fidx])
    return rig.neutral[w.first], w.faces, w.index, fidx[w.kept]


def _feature_points(rig: Rig) -> Optional[np.ndarray]:
    """(3, 3) motion centres of the left eye-close, right eye-close and jaw-open shapes
    (displacement-weighted mean of the vertices that move > 50 % of the maximum), or None."""
    pts = []
    for key, aliases in _FEATURE_SHAPES.items():
        name = next((n for n in aliases if n in rig.names), None)
        if name is None:
            return None
        d = np.linalg.norm(rig.deltas[rig.index(name)], axis=1)
        if d.max() <= 0:
            return None
        m = d > 0.5 * d.max()
        pts.append((d[m, None] * rig.neutral[m]).sum(0) / d[m].sum())
    return np.array(pts)


# ---------------------------------------------------------------------------------------------
def transfer_layout(
    layout: MarkerLayout,
    source_rig: Rig,
    target_rig: Rig,
    landmarks: Union[None, Sequence[str], Mapping[str, object], MarkerLayout] = None,
    steps: Optional[Sequence[Sequence[float]]] = None,
    region: float = 1.35,
    max_vertices: int = 2500,
    feature_landmarks: bool = True,
    target_layout_name: Optional[str] = None,
):
    """Transfer ``layout`` from ``source_rig`` to ``target_rig`` (any topology).

    Similarity alignment (Umeyama 1991) + similarity ICP, then non-rigid ICP (Amberg et al. 2007,
    ``E = E_d + alpha E_s + beta E_l``, see the module docstring) of the source face region onto the
    target surface, then closest-point projection of each registered marker onto the target skin.

    Parameters
    ----------
    layout : MarkerLayout on ``source_rig`` (M markers)
    source_rig, target_rig : Rig
    landmarks : optional
        Markers whose target positions are known: a dict ``name -> (3,) position (m) | vertex id``,
        a MarkerLayout on the target rig (its markers shared with ``layout`` are used), or None
        for automatic alignment. Needs >= 3 names for the similarity; they also pull the
        registration (``wl`` in ``steps``) and are placed exactly.
    steps : sequence of (ws, wl, wn, max_iter), optional
        :func:`core.geometry.nonrigid_icp` schedule (unit face-region diagonal); default
        :data:`DEFAULT_STEPS`. ``[]`` skips the non-rigid stage (similarity + ICP only).
    region : float
        The source face region registered: vertices within ``region`` x the markers' bounding
        radius of their centroid.
    feature_landmarks : bool
        Without ``landmarks``, pull the registration with the motion centres of the eye-close and
        jaw-open shapes (when both rigs have them): ICT -> Rocketbox median error 4.3 -> 3.5 mm,
        ICT -> tiger 15.9 -> 12.1 mm (docs/layouts/transfer_report.md).
    max_vertices : int
        The region is decimated (quadric decimation) to about this many vertices before the
        non-rigid registration; markers follow the decimated surface at their closest point.

    Returns
    -------
    layout : MarkerLayout on ``target_rig``: face + barycentric markers
        (``extras["faces"]`` holds each marker's face index).
    info : dict
        ``residual_mm`` (median, p90, max distance of the registered region to the target
        surface, mm), ``residual_rel`` (median / target size), ``snap_mm`` (M,) distance from each
        registered marker to its projection, ``similarity_transform`` (s, R, t), ``n_region`` vertices,
        ``seconds``, ``steps``.

    Raises
    ------
    ValueError
        The layout does not fit ``source_rig`` (index out of range), landmark names unknown or
        fewer than 3, a landmark vertex out of range.
    """

    t_start = time.perf_counter()
    layout.check(source_rig)
    steps = DEFAULT_STEPS if steps is None else [tuple(s) for s in steps]
    src_markers = layout.points(source_rig.neutral)

    # -- landmarks ---------------------------------------------------------------------------
    lm_names, lm_target = _landmarks(landmarks, layout, target_rig)

    # -- normalised frame: source face region centred, unit diagonal ---------------------------
    centre = src_markers.mean(0)
    radius = np.linalg.norm(src_markers - centre, axis=1).max()
    P, F, merged_of, _ = merged_mesh(source_rig, largest_component(source_rig.neutral, source_rig.faces))
    keep = np.linalg.norm(P - centre, axis=1) < region * radius
    keep[merged_of[layout.vertices.ravel()]] = True  # marker triangles always in the region
    fkeep = keep[F].all(1)
    used = np.unique(F[fkeep])
    remap = -np.ones(len(P), np.int64)
    remap[used] = np.arange(len(used))
    RV, RF = P[used], remap[F[fkeep]]
    if (remap[merged_of[layout.vertices]] < 0).any():
        raise ValueError("transfer_layout: a marker's triangle is not on the source skin; is the layout on an eyeball or teeth?")
    # decimate the region so nricp stays at a few seconds (ICT's face region has ~12k vertices);
    # markers ride the decimated surface at their closest point (face + barycentric)
    if max_vertices is not None:
        RV, RF, _ = decimate(RV, RF, max_vertices=max_vertices)
    diag = np.linalg.norm(RV.max(0) - RV.min(0))
    norm = lambda x: (np.asarray(x) - centre) / diag  # noqa: E731
    denorm = lambda x: np.asarray(x) * diag + centre  # noqa: E731
    src_n = norm(RV)
    _, _, mk_face, mk_bary = closest_points(src_markers, RV, RF)
    mk_tri = RF[mk_face]

    # -- target skin ---------------------------------------------------------------------------
    # the target's skin: its largest connected part, so eyeballs, teeth and hair cards are never chosen
    tskin = largest_component(target_rig.neutral, target_rig.faces)
    skin_ids = np.flatnonzero(tskin)
    T_all = target_rig.neutral
    T_skin = target_rig.faces[skin_ids]

    fs_ft = (_feature_points(source_rig), _feature_points(target_rig))
    fs_ft = None if fs_ft[0] is None or fs_ft[1] is None else fs_ft
    # -- 1. similarity ----------------------------------------------------------------------------
    if len(lm_names) >= 3:
        idx = [layout.names.index(n) for n in lm_names]
        s, R, t = procrustes(src_markers[idx], lm_target, scale=True)
        how = f"landmarks {list(lm_names)}"
    else:
        s, R, t = _auto_alignment(source_rig, target_rig, fs_ft)
        how = "automatic (bounding boxes)" if fs_ft is None else "automatic (bounding boxes + eye/jaw shape centres)"
    # target geometry near the aligned source face, in the normalised frame
    aligned = _apply(s, R, t, RV)
    lo, hi = aligned.min(0), aligned.max(0)
    pad = 0.25 * np.linalg.norm(hi - lo)
    near_face = tskin & (((T_all[target_rig.faces] > lo - pad) & (T_all[target_rig.faces] < hi + pad)).all(2).all(1))
    if near_face.sum() < 10:
        near_face = tskin
    tmesh = trimesh.Trimesh(norm(_inv(s, R, t, T_all)), target_rig.faces[near_face], process=False)
    # the target in the *source's* normalised frame (inverse similarity), so the stiffness and
    # thresholds are relative to the source face region
    src_init = src_n.copy()
    if len(lm_names) < 3:
        # similarity ICP of the region onto the target (both in the normalised source frame)
        M, moved, cost = trimesh.registration.icp(src_init, tmesh, max_iterations=30, reflection=False, scale=True)
        src_init = moved
        Mfull = _frame_matrix(M, diag, centre)
        # fold the ICP transform into (s, R, t): x_target = s R (T_icp x) + t
        A = Mfull[:3, :3]
        si = float(np.cbrt(np.linalg.det(A)))
        R2, t2 = A / si, Mfull[:3, 3]
        s, R, t = s * si, R @ R2, s * R @ t2 + t
        # re-express the target in the refined frame
        tmesh = trimesh.Trimesh(norm(_inv(s, R, t, T_all)), target_rig.faces[near_face], process=False)
        src_init = src_n.copy()

    # -- 2. non-rigid registration -------------------------------------------------------------
    if steps:
        kw = {}
        if len(lm_names):
            idx = [layout.names.index(n) for n in lm_names]
            kw = dict(landmarks=(mk_face[idx], mk_bary[idx]), landmark_positions=norm(_inv(s, R, t, lm_target)))
        elif feature_landmarks and fs_ft is not None:
            # the eye-close and jaw-open motion centres pull the registration (surface points
            # nearest them on both rigs)
            fs, ft = fs_ft
            _, _, lf, lb = closest_points(fs, RV, RF)
            ft_on = closest_points(ft, T_all, T_skin)[0]
            kw = dict(landmarks=(lf, lb), landmark_positions=norm(_inv(s, R, t, ft_on)))
        # threshold 0.1 of the face region's diagonal (the source is at unit diagonal here)
        registered = nonrigid_icp(src_init, RF, tmesh.vertices, tmesh.faces, steps=steps, distance_threshold=0.1, **kw)
    else:
        registered = src_init
    # -- residual: registered region -> target surface (in metres, target frame) -------------
    reg_world = _apply(s, R, t, denorm(registered))
    dist = closest_points(reg_world, T_all, T_skin)[1]
    # -- 3. project markers --------------------------------------------------------------------
    mk_world = np.einsum("mjc,mj->mc", reg_world[mk_tri], mk_bary)
    if len(lm_names):
        for n, p in zip(lm_names, lm_target):
            mk_world[layout.names.index(n)] = p
    _, snap, on_skin, bary = closest_points(mk_world, T_all, T_skin)
    fid = skin_ids[on_skin]
    out = MarkerLayout(
        layout.names,
        target_rig.faces[fid],
        bary,
        target_layout_name or f"{target_rig.name}.glb",
        {"faces": fid, "notes": f"transferred from {layout.rig or source_rig.name} by face-retarget transfer_layout ({how})"},
    )
    info = dict(
        residual_mm=(float(np.median(dist) * 1e3), float(np.percentile(dist, 90) * 1e3), float(dist.max() * 1e3)),
        residual_rel=float(np.median(dist) / target_rig.size),
        snap_mm=snap * 1e3,
        similarity_transform=(s, R, t),
        alignment=how,
        n_region=len(RV),
        seconds=time.perf_counter() - t_start,
        steps=[tuple(x) for x in steps],
    )
    return out, info


# ---------------------------------------------------------------------------------------------
def _inv(s, R, t, p):
    """Inverse similarity: target -> source frame."""
    return (np.asarray(p) - t) @ R / s


def _frame_matrix(M, diag, centre):
    """A 4x4 map in the normalised frame -> the same map in world coordinates."""
    N = np.eye(4)
    N[:3, :3] /= diag
    N[:3, 3] = -centre / diag
    Ninv = np.eye(4)
    Ninv[:3, :3] *= diag
    Ninv[:3, 3] = centre
    return Ninv @ M @ N


def _auto_alignment(source: Rig, target: Rig, fs_ft):
    """The eye/jaw shape centres' similarity (3-point Umeyama) when both rigs have them
    (``fs_ft``), else a bounding-box similarity (no rotation: both rigs are glTF, +Y up, facing +Z)."""
    if fs_ft is not None:
        return procrustes(*fs_ft, scale=True)
    # bounding boxes of the heads: scale by the width (x extent, least affected by necks and
    # collars), centre the fronts
    smin, smax = source.neutral.min(0), source.neutral.max(0)
    tmin, tmax = target.neutral.min(0), target.neutral.max(0)
    s = float((tmax[0] - tmin[0]) / (smax[0] - smin[0]))
    t = 0.5 * (tmin + tmax) - s * 0.5 * (smin + smax)
    return s, np.eye(3), t


def _landmarks(landmarks, layout: MarkerLayout, target: Rig):
    """(names, (L, 3) target positions) from the ``landmarks`` argument."""
    if landmarks is None:
        return (), np.zeros((0, 3))
    if isinstance(landmarks, MarkerLayout):
        names = [n for n in landmarks.names if n in layout.names]
        landmarks.check(target)
        pos = landmarks.points(target.neutral)
        return tuple(names), np.array([pos[landmarks.names.index(n)] for n in names])
    if not isinstance(landmarks, Mapping):
        raise ValueError("transfer_layout: landmarks must be a dict name -> position/vertex, a MarkerLayout, or None")
    names, pos = [], []
    for n, p in landmarks.items():
        if n not in layout.names:
            raise ValueError(f"transfer_layout: landmark {n!r} is not a marker of the layout (markers: {list(layout.names)[:6]}...)")
        if isinstance(p, (int, np.integer)):
            if not 0 <= p < target.n_vertices:
                raise ValueError(f"transfer_layout: landmark {n!r} vertex {p} out of range for rig {target.name} ({target.n_vertices} vertices)")
            p = target.neutral[p]
        p = np.asarray(p, dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"transfer_layout: landmark {n!r} must be a vertex id or a finite (3,) position, got shape {p.shape}")
        names.append(n)
        pos.append(p)
    if 0 < len(names) < 3:
        raise ValueError(f"transfer_layout: need at least 3 landmarks for the alignment, got {len(names)}")
    return tuple(names), np.array(pos).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
def _layout_target(path: Path):
    """The rig a layout is made for: a rig file/folder, or a mesh sequence's own topology (a folder
    of per-frame meshes, a USD mesh with time-sampled points), so ``--source-layout`` can be made
    for a dense sequence source."""

    is_seq = path.is_dir() and not (path / "neutral.obj").exists()
    if not is_seq and path.suffix.lower() in (".usd", ".usda", ".usdc", ".usdz"):
        from .io.usd import has_blendshapes

        is_seq = not has_blendshapes(path)
    return topology_rig(read_mesh_sequence(path)) if is_seq else load_rig(path)


def place_markers(rig: Rig, from_layout=None, source_rig: Optional[Rig] = None, progress=None):
    """Markers on a rig that has no layout, automatically, and a check of where they landed.

    The bundled ICT layout (or ``from_layout`` on ``source_rig``) is transferred by
    :func:`transfer_layout` (similarity + non-rigid ICP + closest point). A marker is flagged
    when it lands

    * **off the face**: it moves on the source (more than 10 % of the source markers' largest
      move) but none of the rig's shapes moves its triangle (more than 1 % of the largest move) —
      on a stylised or animal head the ears, scalp or frill rather than the brow or muzzle (a
      marker that is still on the source too, e.g. the bridge of the nose, is fine);
    * **off the surface**: its registered point was more than 2 % of the rig's size from the
      surface it was snapped to.

    Returns
    -------
    layout : MarkerLayout on ``rig``
    report : dict — ``seconds``, ``residual_mm`` (median, p90, max), ``snap_mm`` {name: mm},
        ``off_face`` [names], ``off_surface`` [names], ``message`` (plain words for the page)
    """

    if from_layout is None:
        from_layout = layouts_dir() / "ict_facekit.json"
        source_rig = source_rig or read_rig(layouts_dir().parent / "rigs" / "ict_facekit.glb")
    layout = from_layout if isinstance(from_layout, MarkerLayout) else read_layout(from_layout, rig=source_rig)
    if rig.n_shapes == 0:
        raise ValueError(f"rig {rig.name!r} has no blend shapes: markers are placed where its shapes move the face")
    say(progress, 0.05, f"placing {layout.n_markers} markers on {rig.name} (registration, a few seconds)")
    out, info = transfer_layout(layout, source_rig, rig, target_layout_name=f"{rig.name}")
    say(progress, 0.9, "checking where the markers landed")
    moving = face_vertices(rig.deltas)
    src_move = np.linalg.norm(layout.points(source_rig.deltas), axis=2).max(0)
    expressive = src_move > 0.1 * src_move.max()
    off_face = [n for n, tri, e in zip(out.names, out.vertices, expressive) if e and not moving[tri].any()]
    limit = 0.02 * rig.size * 1e3
    snap = {n: float(d) for n, d in zip(out.names, info["snap_mm"])}
    off_surface = [n for n, d in snap.items() if d > limit]
    parts = [f"Placed {out.n_markers} markers on {rig.name} in {info['seconds']:.0f} s."]
    if off_face:
        parts.append(f"{len(off_face)} landed where none of the rig's shapes moves the face — they need a hand: "
                     f"{', '.join(off_face)}. Drag each onto the part of the face it stands for (a muzzle, a beak, "
                     f"the brows) before retargeting.")
    if off_surface:
        parts.append(f"{len(off_surface)} are far from where the registration put them (more than {limit:.0f} mm): "
                     f"{', '.join(off_surface)}.")
    if not off_face and not off_surface:
        parts.append("All of them are on the moving face; check the eyes and mouth corners and drag any that are off.")
    say(progress, 1.0, "markers placed")
    return out, {"seconds": info["seconds"], "residual_mm": info["residual_mm"], "snap_mm": snap,
                 "off_face": off_face, "off_surface": off_surface, "message": " ".join(parts)}


#: frames of a mesh sequence that stand in for its shapes when markers are placed on it
SEQUENCE_SHAPES = 64


def sequence_rig(perf) -> Rig:
    """A mesh sequence as a rig :func:`place_markers` can read: its own topology
    (:func:`core.io.sequence.topology_rig`) with up to :data:`SEQUENCE_SHAPES` evenly spaced frames
    with data as shapes, ``deltas[k] = frame_k - neutral`` (the flag "no shape moves here" then
    means "this part of the face never moves in the take").

    Raises ValueError as :func:`topology_rig` does (not a mesh sequence, no faces, no data).
    """
    rig = topology_rig(perf)
    ok = np.flatnonzero(perf.valid)
    pick = ok[np.unique(np.linspace(0, len(ok) - 1, min(SEQUENCE_SHAPES, len(ok))).round().astype(int))]
    deltas = perf.data[pick].astype(np.float64) - rig.neutral
    return Rig(rig.neutral, rig.faces, deltas, [f"frame_{f}" for f in pick], None, rig.units, rig.name)


def place_missing_layouts(settings: Mapping, place: bool = True, progress=None) -> tuple:
    """Marker layouts for the rigs of a run that have none, placed by :func:`place_markers` (what the
    page's *Place markers automatically* does) and written beside each rig as its sidecar
    (``<rig>.layout.json``, :func:`core.io.layout.sidecar_layout_path`: the rig finds it by default
    next time, and a user can edit it); in the temporary folder when the rig's folder is read-only.

    Looked at: the target rig (``target_rig`` without ``target_layout``, no sidecar, none bundled),
    the source rig (likewise), and a mesh-sequence ``source`` without ``source_rig`` or
    ``source_layout`` (its sidecar is used when it exists; else markers are placed on its own
    topology, :func:`sequence_rig`).

    Parameters
    ----------
    settings : mapping of pipeline settings (``source``, ``source_kind``, ``source_fps``,
        ``source_rig``, ``source_layout``, ``target_rig``, ``target_layout``); missing keys are empty.
    place : False to refuse instead (``--no-auto-markers``).

    Returns
    -------
    updates : dict setting -> layout path to configure (``{"target_layout": ".../x.layout.json"}``)
    reports : list of (what, path written, report of :func:`place_markers`)

    Raises
    ------
    NoLayoutError when ``place`` is False and a layout is missing (the message says how to make one).
    """
    get = lambda k: settings.get(k) or ""  # noqa: E731
    todo = []  # (setting, file it belongs to, loader)
    for role in ("target", "source"):
        rig_path = get(f"{role}_rig")
        if rig_path and not get(f"{role}_layout") and default_layout_path(rig_path) is None:
            todo.append((f"{role}_layout", rig_path, lambda p=rig_path: read_rig(p)))
    updates = {}
    src = get("source")
    if src and not get("source_rig") and not get("source_layout"):
        side = sidecar_layout_path(src)
        if side.exists():
            updates["source_layout"] = str(side)
        else:
            perf = read_performance(src, kind=get("source_kind") or "auto", fps=settings.get("source_fps") or None)
            if perf.kind == "meshes":
                todo.append(("source_layout", src, lambda perf=perf: sequence_rig(perf)))
    if todo and not place:
        what, path, _ = todo[0]
        flag = "--" + what.replace("_", "-")
        raise NoLayoutError(
            f"no marker layout for {Path(path).name} (--no-auto-markers): pass {flag}, or make one with "
            f"`face-retarget layout --from data/layouts/ict_facekit.json --rig {path} --out {sidecar_layout_path(path)}`", path)
    reports = []
    for what, path, load in todo:
        rig = load()
        layout, report = place_markers(rig, progress=progress)
        out = sidecar_layout_path(path)
        notes = "placed by face-retarget (automatic), check the flagged markers"
        try:
            write_layout(out, layout, Path(path).name, notes=notes)
        except OSError:
            out = Path(tempfile.mkdtemp(prefix="face-retarget-")) / sidecar_layout_path(path).name
            write_layout(out, layout, Path(path).name, notes=notes)
        updates[what] = str(out)
        reports.append((what, out, report))
    return updates, reports


def layout_command(from_path, rig_path, out_path, source_rig_path=None, steps=None) -> str:
    """File-level transfer for the CLI: ``face-retarget layout --from A.json --rig B.glb --out C.json``.

    The source rig is ``source_rig_path`` or, when None, the file the layout names (its
    ``"rig"`` field) looked up next to the layout, then in the bundled ``data/rigs``.

    Returns a summary (markers, residual, time, where it was written).

    Raises
    ------
    FileNotFoundError when the source rig cannot be found (the message lists where it looked).
    """

    from_path, rig_path, out_path = Path(from_path), Path(rig_path), Path(out_path)
    src_layout = read_layout(from_path)
    if source_rig_path is None:
        rig_file = Path(src_layout.rig).name
        tried = [from_path.parent / rig_file, layouts_dir().parent / "rigs" / rig_file]
        source_rig_path = next((p for p in tried if p.exists()), None)
        if source_rig_path is None:
            raise FileNotFoundError(
                f"layout {from_path.name} names rig {rig_file!r}; not found at {', '.join(map(str, tried))}; pass the source rig explicitly"
            )
    source = read_rig(source_rig_path)
    src_layout = read_layout(from_path, rig=source)
    target = _layout_target(rig_path)
    new, info = transfer_layout(src_layout, source, target, steps=steps, target_layout_name=rig_path.name)
    write_layout(out_path, new, rig_path.name)
    med, p90, mx = info["residual_mm"]
    return (
        f"transferred {new.n_markers} markers from {from_path.name} ({source.name}) to {target.name}: "
        f"registration residual median {med:.2f} mm, p90 {p90:.2f} mm, max {mx:.2f} mm; "
        f"marker snap median {np.median(info['snap_mm']):.2f} mm; {info['seconds']:.1f} s; wrote {out_path}"
    )
