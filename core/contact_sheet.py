"""A contact sheet: the source and the target side by side at a take's most expressive frames.

An animator judges a retarget at a glance from a few frames far apart in expression (jaw open,
smile, blink, brows) and the frame where it is worst. :func:`sheet_frames` picks them: the worst
frame by error first, then farthest-point sampling in the source's expression
(:func:`core.stages.methods.suggested_frames`, the frames the ``auto`` method asks to pose, with the
worst frame counted as chosen so the others are far from it). :func:`contact_sheet` renders each
frame's source and target meshes and :meth:`ContactSheet.png` lays them out as one PNG.

Rendering is a z-buffered triangle rasteriser in numpy (:func:`rasterize`), front view, orthographic,
Lambert shading from interpolated vertex normals. Hand-written on purpose: the project's other
renderer (pyvista/VTK, in :mod:`core.report`) needs an OpenGL context (EGL or OSMesa) and is not
safe from the dashboard's worker threads, and matplotlib's ``Poly3DCollection`` sorts whole
triangles (painter's algorithm: wrong where lips and eyelids overlap, and seconds for a 50k-triangle
head). This one has no context, is deterministic (the same PNG bytes every run) and draws a tile of a
head in tens of milliseconds.

Conventions: rigs are glTF-like (+Y up, the face looks along +Z); the camera looks along -Z.
Frames are solve frames (0 = the range's first frame) unless named ``take_frames``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .geometry import face_vertices, vertex_normals
from .retarget import marker_rig
from .stages.methods import suggested_frames

#: frames on a sheet (the worst one included)
SHEET_FRAMES = 8
#: one face's tile, pixels (width, height)
TILE = (180, 220)
#: cells (a source + target pair) per row of the sheet
COLUMNS = 4
#: pixels under a cell for its caption, and between cells
CAPTION, GAP = 34, 8
#: light direction (towards the light), camera space: from the upper left, in front
LIGHT = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])
SOURCE_RGB, TARGET_RGB, WORST_RGB = (150, 175, 205), (215, 180, 150), (200, 30, 30)


def sheet_size(n: int) -> tuple:
    """(width, height) in pixels of the PNG of a sheet of ``n`` frames."""
    cols, rows = min(n, COLUMNS), -(-n // COLUMNS)
    return cols * (2 * TILE[0] + GAP) + GAP, rows * (TILE[1] + CAPTION + GAP) + GAP


def rasterize(V, faces, size, box) -> np.ndarray:
    """Shading of the mesh ``(V, faces)`` seen from the front: (H, W) in [0, 1], NaN where no triangle is.

    Each pixel centre p inside a projected triangle (a, b, c) gets barycentrics (l0, l1, l2); the
    nearest triangle there (largest interpolated z, the z-buffer) wins and the pixel's shading is
    ``sum_i l_i |n_i . L|`` (n_i the vertex normals, L :data:`LIGHT`; the absolute value keeps a mesh
    wound the other way lit). The projection is orthographic: ``box`` = (x0, x1, y0, y1) in the mesh's
    units is fitted into ``size`` = (W, H) keeping the aspect.

    Parameters
    ----------
    V : (V, 3) float positions; faces : (F, 3) int; size : (W, H) int; box : (4,) float

    Returns
    -------
    (H, W) float64
    """
    W, H = size
    V = np.asarray(V, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    x0, x1, y0, y1 = box
    s = min(W / max(x1 - x0, 1e-12), H / max(y1 - y0, 1e-12))
    X = (V[:, 0] - 0.5 * (x0 + x1)) * s + 0.5 * W
    Y = 0.5 * H - (V[:, 1] - 0.5 * (y0 + y1)) * s
    shade = np.abs(vertex_normals(V, faces) @ LIGHT)
    ax, bx, cx = X[faces].T
    ay, by, cy = Y[faces].T
    d = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
    # pixel centres (i + 0.5) each triangle's bounding box holds
    lo_x = np.maximum(np.ceil(np.minimum(np.minimum(ax, bx), cx) - 0.5), 0).astype(np.int64)
    hi_x = np.minimum(np.floor(np.maximum(np.maximum(ax, bx), cx) - 0.5), W - 1).astype(np.int64)
    lo_y = np.maximum(np.ceil(np.minimum(np.minimum(ay, by), cy) - 0.5), 0).astype(np.int64)
    hi_y = np.minimum(np.floor(np.maximum(np.maximum(ay, by), cy) - 0.5), H - 1).astype(np.int64)
    nx, ny = np.maximum(hi_x - lo_x + 1, 0), np.maximum(hi_y - lo_y + 1, 0)
    keep = np.flatnonzero((nx * ny > 0) & (np.abs(d) > 1e-12))
    img = np.full((H, W), np.nan)
    if not len(keep):
        return img
    count = nx[keep] * ny[keep]
    t = np.repeat(keep, count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    w = nx[t]
    px, py = lo_x[t] + local % w, lo_y[t] + local // w
    qx, qy = px + (0.5 - cx[t]), py + (0.5 - cy[t])
    inv = 1.0 / d[t]
    l0 = ((by - cy)[t] * qx + (cx - bx)[t] * qy) * inv
    l1 = ((cy - ay)[t] * qx + (ax - cx)[t] * qy) * inv
    l2 = 1.0 - l0 - l1
    inside = np.flatnonzero((l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9))
    t, pid, l0, l1, l2 = t[inside], py[inside] * W + px[inside], l0[inside], l1[inside], l2[inside]
    f = faces[t]
    Z = V[:, 2]
    z = l0 * Z[f[:, 0]] + l1 * Z[f[:, 1]] + l2 * Z[f[:, 2]]
    # per pixel, the nearest first: one sort of pixel id + a depth rank in [0, 1)
    zn = (z - Z.min()) / max(float(np.ptp(Z)), 1e-300)
    order = np.argsort(pid + 0.5 * (1.0 - zn), kind="stable")
    first = order[np.r_[True, pid[order][1:] != pid[order][:-1]]]
    f = f[first]
    img.ravel()[pid[first]] = l0[first] * shade[f[:, 0]] + l1[first] * shade[f[:, 1]] + l2[first] * shade[f[:, 2]]
    return img


def _colour(shading: np.ndarray, rgb) -> np.ndarray:
    """(H, W, 3) uint8: ``rgb`` lit by ``shading`` (ambient 0.3), white where it is NaN."""
    lit = (0.3 + 0.7 * np.nan_to_num(shading, nan=0.0))[..., None] * np.asarray(rgb, dtype=np.float64)
    return np.where(np.isnan(shading)[..., None], 255.0, lit).round().clip(0, 255).astype(np.uint8)


def _box(points, pad: float = 0.08) -> tuple:
    """(x0, x1, y0, y1) around ``points`` (N, 3), padded by ``pad`` of the larger side."""
    lo, hi = np.nanmin(points[:, :2], axis=0), np.nanmax(points[:, :2], axis=0)
    p = pad * float(max(hi - lo))
    return lo[0] - p, hi[0] + p, lo[1] - p, hi[1] + p


def _face_box(rig, layout=None) -> tuple:
    """The frame of a rig's face: around its markers (``layout``: the 41 markers span brows to
    chin on every rig, so both faces are framed alike), else its moving vertices, else the mesh."""
    if layout is not None and layout.n_markers >= 3:
        return _box(layout.points(rig.neutral), pad=0.22)
    moving = face_vertices(rig.deltas) if rig.n_shapes else np.zeros(rig.n_vertices, dtype=bool)
    return _box(rig.neutral[moving] if moving.sum() >= 3 else rig.neutral, pad=0.12)


def sheet_frames(inputs, worst: int, n: int = SHEET_FRAMES) -> list:
    """Solve frames of a sheet: ``worst`` first, then ``n - 1`` far apart in expression from it and
    from each other (:func:`core.stages.methods.suggested_frames` with ``worst`` counted as posed).

    ``inputs``: the pipeline's ``frames`` and ``stabilize`` results."""
    first = inputs["frames"]["first"]
    more = suggested_frames(inputs, max(n - 1, 0), posed=[{"frame": first + int(worst)}])
    return [int(worst)] + [f - first for f in more if f - first != int(worst)]


@dataclass
class ContactSheet:
    """Rendered frames of a result. ``frames``: solve frames (``frames[0]`` is ``worst``);
    ``take_frames``: the same as frames of the take; ``captions``: a line per frame;
    ``tiles``: (TILE[1], 2 TILE[0], 3) uint8 per frame, source left, target right."""

    frames: list
    take_frames: list
    captions: list
    worst: int
    tiles: list = field(repr=False)

    def tile_png(self, i: int) -> bytes:
        """Frame ``i``'s source | target tile as PNG bytes."""
        buf = io.BytesIO()
        Image.fromarray(self.tiles[i]).save(buf, format="PNG")
        return buf.getvalue()

    def png(self) -> bytes:
        """The whole sheet as PNG bytes, :func:`sheet_size` pixels: :data:`COLUMNS` cells a row, each
        the source | target tile over its caption (the worst frame's in red)."""
        W, H = sheet_size(len(self.frames))
        sheet = Image.new("RGB", (W, H), (255, 255, 255))
        draw = ImageDraw.Draw(sheet)
        font = ImageFont.load_default(size=12)
        for i, (tile, caption) in enumerate(zip(self.tiles, self.captions)):
            r, c = divmod(i, COLUMNS)
            x, y = GAP + c * (2 * TILE[0] + GAP), GAP + r * (TILE[1] + CAPTION + GAP)
            sheet.paste(Image.fromarray(tile), (x, y))
            colour = WORST_RGB if i == 0 else (40, 40, 40)
            draw.rectangle([x - 1, y - 1, x + 2 * TILE[0], y + TILE[1]], outline=colour)
            draw.line([x + TILE[0], y, x + TILE[0], y + TILE[1] - 1], fill=(220, 220, 220))
            draw.text((x + 4, y + 3), "source", fill=(90, 90, 90), font=font)
            draw.text((x + TILE[0] + 4, y + 3), "target", fill=(90, 90, 90), font=font)
            for k, line in enumerate(caption.split("\n")[:2]):
                draw.text((x + 2, y + TILE[1] + 3 + 15 * k), line, fill=colour, font=font)
        buf = io.BytesIO()
        sheet.save(buf, format="PNG")
        return buf.getvalue()


def contact_sheet(inputs, weights, worst: int, n: int = SHEET_FRAMES, error_mm=None,
                  error_label: str = "marker RMS") -> ContactSheet:
    """Render the source and the target at :func:`sheet_frames`.

    The source is the source rig driven by the take's curves, or (a capture, a mesh sequence) its
    stabilised markers on their triangulated surface (:func:`core.retarget.marker_rig`); the target is
    ``neutral + w_t @ deltas`` with ``weights`` (T, K) of the target rig's shapes.

    Parameters
    ----------
    inputs : the pipeline's ``load``, ``frames`` and ``stabilize`` results
    weights : (T, K) float, the result on the solve frames (NaN: no data, drawn at 0)
    worst : the solve frame where the result is worst (it is on the sheet, first)
    error_mm : (T,) float, optional — an error per frame for the captions
    error_label : what ``error_mm`` is, in the captions ("frame 963 · worst · marker RMS 5.1 mm"):
        the default, the RMS over the markers (:func:`core.evaluate.worst_frame`'s measure)

    Raises
    ------
    ValueError when ``weights`` is not (T, K) of the target rig or ``worst`` is not a frame of it.
    """
    ld = inputs["load"]
    rig, src_rig = ld["target_rig"], ld["source_rig"]
    st, first = inputs["stabilize"]["source"], inputs["frames"]["first"]
    W = np.nan_to_num(np.asarray(weights, dtype=np.float64))
    if W.ndim != 2 or W.shape[1] != rig.n_shapes:
        raise ValueError(f"weights: expected (T, {rig.n_shapes}) for rig {rig.name!r}, got {W.shape}")
    if not 0 <= int(worst) < len(W):
        raise ValueError(f"worst: frame {worst} outside 0..{len(W) - 1}")
    frames = sheet_frames(inputs, worst, n)
    curves = src_rig is not None and st.source_weights is not None and src_rig.n_shapes == np.shape(st.source_weights)[1]
    if curves:
        S = np.nan_to_num(np.asarray(st.source_weights, dtype=np.float64))
        src_box = _face_box(src_rig, ld.get("source_layout"))
    else:
        mrig, _ = marker_rig(st.positions)
        P = np.asarray(st.positions, dtype=np.float64)
        src_box = _box(P.reshape(-1, 3), pad=0.1)
    tgt_box = _face_box(rig, ld.get("target_layout"))
    tiles, captions = [], []
    for i, t in enumerate(frames):
        if curves:
            src = _colour(rasterize(src_rig.evaluate(S[t]), src_rig.faces, TILE, src_box), SOURCE_RGB)
            k = int(np.argmax(S[t]))
            what = f"{src_rig.names[k]} {S[t, k]:.2f}"
        else:
            X = np.where(np.isfinite(P[t]), P[t], mrig.neutral)
            src = _colour(rasterize(X, mrig.faces, TILE, src_box), SOURCE_RGB)
            k = int(np.argmax(W[t]))
            what = f"target {rig.names[k]} {W[t, k]:.2f}"
        tgt = _colour(rasterize(rig.evaluate(W[t]), rig.faces, TILE, tgt_box), TARGET_RGB)
        tiles.append(np.concatenate([src, tgt], axis=1))
        err = f" · {error_label} {error_mm[t]:.1f} mm" if error_mm is not None and np.isfinite(error_mm[t]) else ""
        head = f"frame {first + t}" + (" · worst" if i == 0 else "") + err
        captions.append(f"{head}\n{what}")
    return ContactSheet(frames, [first + f for f in frames], captions, int(worst), tiles)
