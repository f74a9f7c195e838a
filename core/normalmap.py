"""Normal-map blending in texture space (Liu et al. 2011, §5).

The paper blends per-expression normal maps "according the corresponding blendshape weights
and masks, in a way that is identical to Equation 3", with normals in place of positions:

    N(p) = normalize( N_0(p) + Σ_k B_k(p) Σ_i u_{k,i} (N_i(p) − N_0(p)) )

for every texel p, where N_i is the normal map of pose i (0 = neutral), B_k(p) the region
masks rasterised to texture space and u_k the regional delta weights. We have no
photometric-stereo scans, so each N_i is *baked from the rig's full-resolution geometry*:
area-weighted vertex normals of ``neutral + delta_i`` (on the seam-welded mesh, so UV seams
do not crease them), interpolated barycentrically over each triangle in UV space. Maps are
**object space** (the rig's frame): blending is then literally eq. 3 on vectors; a tangent
-space map would need a tangent frame per deformed mesh for no gain here.

Pieces:

* :func:`uv_raster` rasterises a UV layout once (triangle id + barycentrics per texel,
  numpy, vectorised over all candidate texels -- no library rasterises barycentrics for us
  without a GL context).
* :func:`bake` interpolates any per-vertex field into texture space with it.
* :func:`shape_normal_maps`, :func:`mask_maps`, :func:`blend_normal_maps`.
* :func:`decimate` builds a low-resolution rig (:func:`core.geometry.decimate`, VTK quadric
  decimation through pyvista, deltas and masks sampled at each new vertex's closest point on
  the full mesh) -- the coarse geometry on which the blended maps restore detail.
* :func:`sample` reads a map at UV points (bilinear), :func:`angle_deg` compares normals.
* :func:`bake_rig` packs a rig's maps for per-frame blending (covered texels only, float16, the
  nearest covered texel of every texel for filling), :func:`frame_blend_weights` chooses what
  eq. 3 blends at a frame (regional weights and masks of the local method, else the global
  weights as one region), :func:`frame_normal_map` blends one frame into an 8-bit image —
  the pipeline's ``normalmap_*`` stages and the dashboard's normal-map view use these.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from .geometry import closest_points, decimate as quadric_decimation, vertex_normals
from .model import Rig
from .segment import welded_graph
from .solvers.local import blend_weights


@dataclass(frozen=True, eq=False)
class UVRaster:
    """Which triangle covers each texel, and where.

    Attributes
    ----------
    face : (H, W) int — triangle index, -1 where no triangle covers the texel centre
    bary : (H, W, 3) float — barycentric coordinates of the texel centre in that triangle
    extent : (u0, u1, v0, v1) — the UV rectangle the image spans (whole UDIM tiles)
    resolution : int — texels per UV unit

    Texel (row i, column j) has its centre at ``u = u0 + (j + ½)/res``, ``v = v0 + (i + ½)/res``:
    row 0 is v = v0, the top of the image in glTF's convention (UV origin at the top-left),
    so the array can be written to an image file as is.
    """

    face: np.ndarray
    bary: np.ndarray
    extent: tuple
    resolution: int

    @property
    def covered(self) -> np.ndarray:
        return self.face >= 0

    @property
    def shape(self) -> tuple:
        return self.face.shape


def uv_raster(uvs: np.ndarray, faces: np.ndarray, resolution: int = 256) -> UVRaster:
    """Rasterise the UV layout: for every texel centre, its triangle and barycentrics.

    Parameters
    ----------
    uvs : (V, 2) float
    faces : (F, 3) int
    resolution : int
        Texels per UV unit; the image covers the whole UDIM tiles the layout touches (ICT:
        u in [0, 2], so 2·res × res).

    Returns
    -------
    UVRaster

    Raises
    ------
    ValueError
        Bad shapes, non-finite UVs, resolution < 2.
    """
    uvs = np.asarray(uvs, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if uvs.ndim != 2 or uvs.shape[1] != 2:
        raise ValueError(f"uvs: expected (V, 2), got {uvs.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and (faces.min() < 0 or faces.max() >= len(uvs))):
        raise ValueError(f"faces: expected (F, 3) indices into {len(uvs)} uvs, got shape {faces.shape}")
    if not np.isfinite(uvs).all():
        raise ValueError("uvs: contain NaN/inf")
    res = int(resolution)
    if res < 2:
        raise ValueError(f"resolution: expected >= 2 texels per UV unit, got {resolution}")
    u0, v0 = np.floor(uvs.min(0))
    u1, v1 = np.ceil(uvs.max(0))
    u1, v1 = max(u1, u0 + 1), max(v1, v0 + 1)
    W, Hh = int(round((u1 - u0) * res)), int(round((v1 - v0) * res))
    # texel (row i, col j) centre: u = u0 + (j + .5)/res, v = v0 + (i + .5)/res (glTF: v down)
    X = (uvs[:, 0] - u0) * res - 0.5  # continuous column coordinate
    Y = (uvs[:, 1] - v0) * res - 0.5  # continuous row coordinate
    A, B, C = faces[:, 0], faces[:, 1], faces[:, 2]
    xa, ya = X[A], Y[A]
    e1x, e1y = X[B] - xa, Y[B] - ya
    e2x, e2y = X[C] - xa, Y[C] - ya
    det = e1x * e2y - e1y * e2x
    ok = np.abs(det) > 1e-12
    xs = np.stack([X[A], X[B], X[C]], 1)
    ys = np.stack([Y[A], Y[B], Y[C]], 1)
    jmin = np.clip(np.ceil(xs.min(1)), 0, W - 1).astype(np.int64)
    jmax = np.clip(np.floor(xs.max(1)), 0, W - 1).astype(np.int64)
    imin = np.clip(np.ceil(ys.min(1)), 0, Hh - 1).astype(np.int64)
    imax = np.clip(np.floor(ys.max(1)), 0, Hh - 1).astype(np.int64)
    nx = np.where(ok, jmax - jmin + 1, 0).clip(0)
    ny = np.where(ok, imax - imin + 1, 0).clip(0)
    cnt = nx * ny
    face = np.full((Hh, W), -1, dtype=np.int64)
    bary = np.zeros((Hh, W, 3))
    total = int(cnt.sum())
    if total == 0:
        return UVRaster(face, bary, (float(u0), float(u1), float(v0), float(v1)), res)
    # all candidate texels of all triangles at once (bounding boxes, flattened)
    tri = np.repeat(np.arange(len(faces)), cnt)
    off = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    j = jmin[tri] + off % nx[tri]
    i = imin[tri] + off // nx[tri]
    px, py = j - xa[tri], i - ya[tri]
    d = det[tri]
    b1 = (px * e2y[tri] - py * e2x[tri]) / d
    b2 = (e1x[tri] * py - e1y[tri] * px) / d
    b0 = 1.0 - b1 - b2
    tol = -1e-9
    inside = (b0 >= tol) & (b1 >= tol) & (b2 >= tol)
    tri, i, j = tri[inside], i[inside], j[inside]
    face[i, j] = tri
    bary[i, j] = np.stack([b0[inside], b1[inside], b2[inside]], 1)
    return UVRaster(face, bary, (float(u0), float(u1), float(v0), float(v1)), res)


def bake_matrix(raster: UVRaster, faces: np.ndarray, n_vertices: int):
    """Sparse (n_covered, V) operator with ``bake(values)[covered] = S @ values``.

    Build once per rig and raster when many fields are baked (one row per covered texel,
    three barycentric entries).
    """

    faces = np.asarray(faces, dtype=np.int64)
    cov = raster.covered
    tri = faces[raster.face[cov]]
    n = len(tri)
    rows = np.repeat(np.arange(n), 3)
    return sp.csr_matrix((raster.bary[cov].ravel(), (rows, tri.ravel())), shape=(n, n_vertices))


def bake(raster: UVRaster, faces: np.ndarray, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
    """Interpolate per-vertex ``values`` (V, C) into texture space: (H, W, C).

    ``out(p) = Σ_j bary_j(p) values[faces[face(p), j]]``; ``fill`` where nothing covers p.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        return bake(raster, faces, values[:, None], fill)[..., 0]
    faces = np.asarray(faces, dtype=np.int64)
    out = np.full(raster.shape + (values.shape[1],), fill, dtype=np.float64)
    cov = raster.covered
    tri = faces[raster.face[cov]]  # (n, 3)
    out[cov] = np.einsum("nj,njc->nc", raster.bary[cov], values[tri])
    return out


def vertex_normals_seamless(rig: Rig, positions: Optional[np.ndarray] = None) -> np.ndarray:
    """Area-weighted unit vertex normals computed on the seam-welded mesh, (V, 3).

    ``positions`` (V, 3) defaults to the neutral; seam copies of a vertex get one normal
    (:func:`core.geometry.vertex_normals` with the ``weld_index`` of :func:`core.segment.welded_graph`).
    """
    g = welded_graph(rig)
    P = rig.neutral if positions is None else np.asarray(positions, dtype=np.float64)
    if P.shape != rig.neutral.shape:
        raise ValueError(f"positions: expected {rig.neutral.shape}, got {P.shape}")
    return vertex_normals(P, rig.faces, weld_index=g.index)


def shape_normal_maps(rig: Rig, raster: UVRaster, dtype=np.float32) -> np.ndarray:
    """Object-space normal maps N_0 (neutral) and N_i (``neutral + delta_i``): (K+1, H, W, 3).

    Per-vertex normals of each pose, baked with :func:`bake` and renormalised per texel;
    zero where no triangle covers a texel.
    """
    if rig.uvs is None:
        raise ValueError(f"rig {rig.name!r} has no UVs; normal maps need texture coordinates")
    g = welded_graph(rig)
    S = bake_matrix(raster, rig.faces, rig.n_vertices)
    cov = raster.covered
    maps = np.zeros((rig.n_shapes + 1,) + raster.shape + (3,), dtype=dtype)
    poses = np.concatenate([rig.neutral[None], rig.neutral + rig.deltas])
    normals = vertex_normals(poses, rig.faces, weld_index=g.index)  # (K+1, V, 3), one pass
    for i in range(rig.n_shapes + 1):
        N = S @ normals[i]
        n = np.linalg.norm(N, axis=-1, keepdims=True)
        maps[i][cov] = np.where(n > 0, N / np.where(n > 0, n, 1), 0.0)
    return maps


def mask_maps(raster: UVRaster, faces: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Region masks B_k in texture space: (R, V) → (R, H, W), summing to 1 on covered texels."""
    masks = np.asarray(masks, dtype=np.float64)
    return np.moveaxis(bake(raster, faces, masks.T), -1, 0)


def blend_normal_maps(maps: np.ndarray, region_weights: np.ndarray, masks_uv: np.ndarray) -> np.ndarray:
    """Eq. 3 on normal maps: ``normalize(N_0 + Σ_k B_k Σ_i u_{k,i} (N_i − N_0))``.

    Parameters
    ----------
    maps : (K+1, H, W, 3) — :func:`shape_normal_maps`
    region_weights : (R, K) — one frame's regional delta weights (global: R = 1)
    masks_uv : (R, H, W) — :func:`mask_maps` (global: ones)

    Returns
    -------
    (H, W, 3) float64 unit normals (zero where the neutral map is zero).
    """
    maps = np.asarray(maps)
    U = np.asarray(region_weights, dtype=np.float64)
    Bm = np.asarray(masks_uv, dtype=np.float64)
    K = maps.shape[0] - 1
    if U.ndim != 2 or U.shape[1] != K:
        raise ValueError(f"region_weights: expected (R, {K}), got {U.shape}")
    if Bm.shape != (U.shape[0],) + maps.shape[1:3]:
        raise ValueError(f"masks_uv: expected {(U.shape[0],) + maps.shape[1:3]}, got {Bm.shape}")
    N0 = maps[0].astype(np.float64)
    # per-texel shape weights: c_i(p) = Σ_k B_k(p) u_{k,i}
    c = np.einsum("rhw,ri->ihw", Bm, U)
    N = N0 + np.einsum("ihw,ihwc->hwc", c, maps[1:].astype(np.float64) - N0[None], optimize=True)
    n = np.linalg.norm(N, axis=-1, keepdims=True)
    return np.where(n > 0, N / np.where(n > 0, n, 1), 0.0)


def sample(image: np.ndarray, raster: UVRaster, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``image`` (H, W, C) at UV points (n, 2) → (n, C)."""
    img = np.asarray(image, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    u0, u1, v0, v1 = raster.extent
    res = raster.resolution
    x = (uv[:, 0] - u0) * res - 0.5
    y = (uv[:, 1] - v0) * res - 0.5
    Hh, W = img.shape[:2]
    x0 = np.clip(np.floor(x).astype(np.int64), 0, W - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, Hh - 2)
    fx = np.clip(x - x0, 0, 1)[:, None]
    fy = np.clip(y - y0, 0, 1)[:, None]
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between corresponding vectors (..., 3) (robust near 0 and 180)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...c,...c->...", a, b)))


def decimate(rig: Rig, reduction: float = 0.9, masks: Optional[np.ndarray] = None):
    """A low-resolution copy of ``rig`` for showing what the blended maps restore.

    The neutral is decimated by :func:`core.geometry.decimate` (VTK's quadric decimation) with
    the UVs in the error metric, so texture coordinates are carried to the new vertices. Every new
    vertex takes the deltas (and ``masks``) of its closest point on the full neutral mesh
    (:func:`core.geometry.closest_points`, barycentric interpolation).

    Parameters
    ----------
    rig : Rig with UVs
    reduction : float in (0, 1) — fraction of triangles to remove
    masks : (R, V) float, optional — region masks to carry over

    Returns
    -------
    low : Rig
    low_masks : (R, V_low) or None
    """
    if not 0 < reduction < 1:
        raise ValueError(f"reduction: expected a fraction in (0, 1), got {reduction}")
    if rig.uvs is None:
        raise ValueError(f"rig {rig.name!r} has no UVs")
    P, F, uv = quadric_decimation(rig.neutral, rig.faces, reduction, uvs=rig.uvs)
    closest, _, tri, bc = closest_points(P, rig.neutral, rig.faces)
    vid = rig.faces[tri]  # (n, 3)
    deltas = np.einsum("nj,knjc->knc", bc, rig.deltas[:, vid])
    low_rig = Rig(closest, F, deltas, rig.names, uv, rig.units, rig.name + "_low")
    low_masks = None
    if masks is not None:
        m = np.asarray(masks, dtype=np.float64)
        low_masks = np.einsum("nj,rnj->rn", bc, m[:, vid])
        low_masks = low_masks / low_masks.sum(0, keepdims=True)
    return low_rig, low_masks


# -- packed maps for per-frame blending (the pipeline's normal-map stages) ----------------------
@dataclass(frozen=True, eq=False)
class Bake:
    """Per-shape object-space normal maps of one rig at one resolution, packed for blending.

    Attributes
    ----------
    raster : UVRaster
    maps : (K+1, 1, n, 3) float16
        N_0 (neutral) and N_i (``neutral + delta_i``) at the n covered texels, laid out as an
        image of height 1 so :func:`blend_normal_maps` takes it as is.
    fill : (H, W) int
        For every texel, the index (into the n covered texels) of the nearest covered one: a
        texel no triangle covers takes its nearest covered texel's normal, so bilinear filtering
        and mipmaps at UV-island borders do not pull in undefined normals.
    seconds : float
        Time the bake took.
    """

    raster: UVRaster
    maps: np.ndarray
    fill: np.ndarray
    seconds: float

    @property
    def shape(self) -> tuple:
        return self.raster.shape

    @property
    def n_covered(self) -> int:
        return int(self.maps.shape[2])


def bake_rig(rig: Rig, resolution: int = 256) -> Bake:
    """:func:`shape_normal_maps` of ``rig`` at ``resolution`` texels per UV unit, packed (see
    :class:`Bake`). Raises ValueError for a rig without UVs."""

    if rig.uvs is None:
        raise ValueError(f"rig {rig.name!r} has no UVs; normal maps need texture coordinates")
    t0 = time.perf_counter()
    ras = uv_raster(rig.uvs, rig.faces, int(resolution))
    cov = ras.covered
    full = shape_normal_maps(rig, ras, dtype=np.float16)  # (K+1, H, W, 3)
    maps = np.ascontiguousarray(full[:, cov][:, None])
    del full
    # nearest covered texel of every texel (distance transform to the covered set)
    ii, jj = ndimage.distance_transform_edt(~cov, return_distances=False, return_indices=True)
    lin = np.full(ras.shape, -1, dtype=np.int64)
    lin[cov] = np.arange(int(cov.sum()))
    return Bake(ras, maps, lin[ii, jj], time.perf_counter() - t0)


def texture_coordinates(uvs, raster: UVRaster) -> np.ndarray:
    """UVs as coordinates in [0, 1] of the baked image: ``(u − u0)/(u1 − u0)``,
    ``(v − v0)/(v1 − v0)`` over the raster's extent (whole UDIM tiles; ICT's u spans [0, 2]).
    Row 0 of the image is v = v0, glTF's convention. (V, 2) float32."""
    u0, u1, v0, v1 = raster.extent
    uv = np.asarray(uvs, dtype=np.float64)
    return ((uv - [u0, v0]) / [u1 - u0, v1 - v0]).astype(np.float32)


def mask_texels(b: Bake, faces, masks) -> np.ndarray:
    """Region masks B_k (R, V) at the covered texels of ``b``: (R, 1, n) float32."""
    m = mask_maps(b.raster, faces, np.asarray(masks, dtype=np.float64))
    return np.ascontiguousarray(m[:, b.raster.covered][:, None], dtype=np.float32)


def frame_blend_weights(weights, frame: int, shape_names, region_weights=None, masks=None, solver_names=None) -> tuple:
    """What eq. 3 blends at ``frame``: ``(U (R, K), use_masks, note)``.

    With regional weights ``region_weights`` (T, R, K_solver) and ``masks`` (R, V) (the local
    method, Liu 2011), ``U`` holds them placed into the rig's K shapes (``solver_names``), as long
    as the shown weights ``weights`` (T, K) are still their mask-area blend (an edit changes the
    global curves only: then the global weights are used and ``note`` says so). Otherwise the
    frame's global weights as one region (R = 1, ``use_masks`` False: the mask is 1 everywhere).
    """
    W = np.asarray(weights, dtype=np.float64)
    f = int(np.clip(frame, 0, len(W) - 1))
    w = np.nan_to_num(W[f])
    if region_weights is None or masks is None:
        return w[None], False, "global weights"

    masks = np.asarray(masks, dtype=np.float64)
    names = list(shape_names)
    sub = list(solver_names or names)
    U = np.asarray(region_weights, dtype=np.float64)
    if U.shape[1:] != (len(masks), len(sub)) or len(U) != len(W):
        return w[None], False, "global weights (regional data does not match the target rig)"
    idx = [names.index(n) for n in sub]
    u = np.nan_to_num(U[f])
    shown = w[idx]
    if not np.allclose(blend_weights(u[None], masks)[0], shown, rtol=1e-6, atol=1e-6 * max(1.0, np.abs(shown).max())):
        return w[None], False, "global weights (edited: the regional weights no longer give the shown curves)"
    full = np.zeros((len(masks), len(names)))
    full[:, idx] = u
    return full, True, f"{len(masks)} regions"


def frame_normal_map(b: Bake, U, masks_texels=None) -> np.ndarray:
    """Eq. 3 on normal maps for one frame, as an (H, W, 3) uint8 image (normals ``(n+1)/2``,
    uncovered texels filled from the nearest covered one).

    Parameters
    ----------
    b : Bake
    U : (R, K) regional (or, R = 1, global) weights of the frame
    masks_texels : (R, 1, n) masks at the covered texels (:func:`mask_texels`); None: R = 1, ones.

    The blend runs on the shapes with a non-zero weight only (the other terms of the sum are zero).
    """
    U = np.asarray(U, dtype=np.float64)
    K = b.maps.shape[0] - 1
    if U.ndim != 2 or U.shape[1] != K:
        raise ValueError(f"U: expected (R, {K}), got {U.shape}")
    act = np.flatnonzero(np.any(U != 0, axis=0))
    if masks_texels is None:
        if len(U) != 1:
            raise ValueError(f"U: {len(U)} regions need masks_texels")
        masks_texels = np.ones((1, 1, b.n_covered))
    N = blend_normal_maps(b.maps[np.r_[0, act + 1]], U[:, act], masks_texels)[0]  # (n, 3)
    return encode_normal_map(N)[b.fill]


def encode_normal_map(normals) -> np.ndarray:
    """RGB bytes of unit normals: (..., 3) -> (..., 3) uint8.

    ``rgb = round(255 (n + 1) / 2)``, the inverse of a shader's ``n = 2 rgb / 255 - 1`` (up
    to 1/255). Components are clipped to [-1, 1]; zero vectors (texels no triangle covers)
    come out as (128, 128, 128), i.e. no direction: fill them before display. Raises
    ValueError for a last axis other than 3 or NaN.
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim < 1 or n.shape[-1] != 3:
        raise ValueError(f"normals: expected shape (..., 3), got {n.shape}")
    if not np.isfinite(n).all():
        raise ValueError("normals: contain NaN/inf")
    return np.rint((np.clip(n, -1, 1) + 1) * 127.5).astype(np.uint8)
