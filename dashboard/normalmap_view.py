"""Normal-map blending on the dashboard's target (Liu et al. 2011 §5).

Three views of the target rig at the dashboard's frame, side by side, one camera:

(a) the full-resolution rig playing the solved weights (vertex normals);
(b) a decimated copy (10 % of the triangles, :func:`core.normalmap.decimate`) with the
    normal map blended for the frame, ``N = normalize(N_0 + Σ_k B_k Σ_i u_ki (N_i − N_0))``
    (eq. 3 on normals, :func:`core.normalmap.blend_normal_maps`): regional weights and masks
    for the local method, the global weights (R = 1, B = 1) otherwise;
(c) the same decimated copy with its own vertex normals.

The per-shape maps N_i are baked once per rig and resolution (:func:`core.normalmap.
shape_normal_maps` on :func:`core.normalmap.uv_raster`) and kept in a small LRU shared by
all sessions, keyed by the rig's name, a hash of its arrays and the resolution. Per frame
only the blended map travels: H·W·3 bytes (ICT: 512×256 texels at 256/UV unit, 384 KB;
1024×512 at 512, 1.5 MB). The blend runs on the covered texels and the shapes with a
non-zero weight only (the other terms of the sum are zero), which is the same call to core
on smaller arrays.

A rig without UVs (Rocketbox, Jeeliz) gets a hint instead. Numerics stay in core; here:
packing (covered texels, texture coordinates normalised to the image, 8-bit encoding) and
filling texels no triangle covers with their nearest covered texel so bilinear filtering
and mipmaps at UV-island borders do not pull in undefined normals.
"""

from __future__ import annotations

import hashlib
import html
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import panel as pn
import param

from core.normalmap import blend_normal_maps, decimate, mask_maps, shape_normal_maps, uv_raster

from .viewer import MeshViewer, encode_normal_map

HINT = "normal-map blending needs a rig with UVs — choose ict_facekit.glb as the target"
VIEW_HEIGHT = 380
#: fraction of the triangles the decimation removes (keeps 10 %)
REDUCTION = 0.9
SYNC_GROUP = "normalmap"


# -- baked data, cached across sessions ----------------------------------------------------
@dataclass(frozen=True, eq=False)
class Bake:
    """Per-shape object-space normal maps of one rig at one resolution, packed for blending.

    Attributes
    ----------
    raster : core.normalmap.UVRaster
    maps : (K+1, 1, n, 3) float16, read-only
        N_0 (neutral) and N_i (``neutral + delta_i``) at the n covered texels, laid out as an
        image of height 1 so :func:`core.normalmap.blend_normal_maps` takes it as is.
    fill : (H, W) int
        For every texel, the index (into the n covered texels) of the nearest covered one.
    seconds : float
        Time the bake took.
    """

    raster: object
    maps: np.ndarray
    fill: np.ndarray
    seconds: float

    @property
    def shape(self) -> tuple:
        return self.raster.shape

    @property
    def n_covered(self) -> int:
        return int(self.maps.shape[2])


class _LRU:
    """A few large results (baked maps, decimated rigs) shared by all sessions."""

    def __init__(self, size: int = 4):
        self.size = size
        self.items: OrderedDict = OrderedDict()
        self.lock = threading.RLock()

    def get(self, key, make):
        with self.lock:  # one bake at a time; a second session asking for it waits and reuses it
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key]
            value = make()
            self.items[key] = value
            while len(self.items) > self.size:
                self.items.popitem(last=False)
            return value

    def clear(self):
        with self.lock:
            self.items.clear()


CACHE = _LRU(4)


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def rig_key(rig) -> tuple:
    """(name, BLAKE2 digest of neutral, faces, deltas, uvs): a content key (an uploaded rig may reuse a name)."""
    h = hashlib.blake2b(digest_size=16)
    for a in (rig.neutral, rig.faces, rig.deltas, rig.uvs):
        if a is not None:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype.str, a.shape)).encode())
            h.update(a.data)
    return (rig.name, h.hexdigest())


def bake(rig, resolution: int, key: tuple | None = None) -> Bake:
    """The rig's per-shape normal maps at ``resolution`` texels per UV unit (cached).

    Raises ValueError when the rig has no UVs.
    """
    if rig.uvs is None:
        raise ValueError(f"rig {rig.name!r} has no UVs; {HINT}")
    key = key or rig_key(rig)

    def make():
        from scipy import ndimage

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
        fill = lin[ii, jj]
        return Bake(ras, _readonly(maps), _readonly(fill), time.perf_counter() - t0)

    return CACHE.get(("bake", key, int(resolution)), make)


def decimated(rig, key: tuple | None = None):
    """:func:`core.normalmap.decimate` of ``rig`` keeping 10 % of its triangles (cached)."""
    key = key or rig_key(rig)
    return CACHE.get(("decimate", key, REDUCTION), lambda: decimate(rig, REDUCTION)[0])


def texture_coordinates(uvs, raster) -> np.ndarray:
    """The rig's UVs as coordinates in [0, 1] of the baked image: ``(u − u0)/(u1 − u0)``,
    ``(v − v0)/(v1 − v0)`` over the raster's extent (whole UDIM tiles; ICT's u spans [0, 2]).
    Row 0 of the image is v = v0, the viewer's (glTF's) convention. (V, 2) float32."""
    u0, u1, v0, v1 = raster.extent
    uv = np.asarray(uvs, dtype=np.float64)
    return ((uv - [u0, v0]) / [u1 - u0, v1 - v0]).astype(np.float32)


def mask_texels(b: Bake, faces, masks, key) -> np.ndarray:
    """Region masks B_k at the covered texels, (R, 1, n) float32 (cached by content)."""
    masks = np.asarray(masks, dtype=np.float64)
    h = hashlib.blake2b(np.ascontiguousarray(masks).data, digest_size=16).hexdigest()
    return CACHE.get(("masks", key, b.raster.resolution, h),
                     lambda: _readonly(np.ascontiguousarray(mask_maps(b.raster, faces, masks)[:, b.raster.covered][:, None],
                                                            dtype=np.float32)))


def frame_weights(snapshot: dict, frame: int):
    """The weights eq. 3 blends at ``frame``: ``(U (R, K), masks (R, V) or None, note)``.

    Local method (Liu 2011): the regional weights ``solve_info["region_weights"][frame]``
    placed into the target's K shapes (``solver_names``) with ``segment["masks"]``, as long
    as the shown weights are still their mask-area blend (spacetime edits change the global
    curves only; then the global weights are used and ``note`` says so). Otherwise the
    global weights of the frame as one region (R = 1, masks None = 1 everywhere).
    """
    W = np.asarray(snapshot["weights"], dtype=np.float64)
    f = int(np.clip(frame, 0, len(W) - 1))
    w = np.nan_to_num(W[f])
    rig = snapshot["target_rig"]
    seg = snapshot.get("segment")
    U = (snapshot.get("solve_info") or {}).get("region_weights")
    if snapshot.get("method") != "local" or not seg or U is None:
        return w[None], None, "global weights"
    from core.solvers.local import blend_weights

    masks = np.asarray(seg["masks"], dtype=np.float64)
    names = list(snapshot.get("solver_names") or rig.names)
    U = np.asarray(U, dtype=np.float64)
    if masks.shape[1] != rig.n_vertices or U.shape[1:] != (len(masks), len(names)) or len(U) != len(W):
        return w[None], None, "global weights (regional data does not match the target rig)"
    idx = [rig.index(n) for n in names]
    u = np.nan_to_num(U[f])
    shown = w[idx]
    if not np.allclose(blend_weights(u[None], masks)[0], shown, rtol=1e-6, atol=1e-6 * max(1.0, np.abs(shown).max())):
        return w[None], None, "global weights (edited: the regional weights no longer give the shown curves)"
    full = np.zeros((len(masks), rig.n_shapes))
    full[:, idx] = u
    return full, masks, f"{len(masks)} regions"


def blended_normal_map(b: Bake, U, masks_texels=None) -> np.ndarray:
    """Eq. 3 on normal maps for one frame, as the viewer's (H, W, 3) uint8 image.

    Parameters
    ----------
    b : Bake
    U : (R, K) regional (or, R = 1, global) weights of the frame
    masks_texels : (R, 1, n) masks at the covered texels (:func:`mask_texels`); None: R = 1, ones.
    """
    U = np.asarray(U, dtype=np.float64)
    K = b.maps.shape[0] - 1
    if U.ndim != 2 or U.shape[1] != K:
        raise ValueError(f"U: expected (R, {K}), got {U.shape}")
    act = np.flatnonzero(np.any(U != 0, axis=0))  # shapes with weight 0 add nothing to the sum
    if masks_texels is None:
        if len(U) != 1:
            raise ValueError(f"U: {len(U)} regions need masks_texels")
        masks_texels = np.ones((1, 1, b.n_covered))
    N = blend_normal_maps(b.maps[np.r_[0, act + 1]], U[:, act], masks_texels)[0]  # (n, 3)
    return encode_normal_map(N)[b.fill]


# -- the view ------------------------------------------------------------------------------
class NormalMapView(pn.viewable.Viewer):
    """Full resolution vs decimated + blended normal map vs decimated, at the dashboard's frame.

    Call :meth:`update` with the session snapshot and the frame (from ``DashboardApp._draw``
    and ``_on_frame``). While :attr:`active` is False (the tab is not shown) it only
    remembers them; becoming active draws the last ones. The view's own frame slider calls
    ``on_frame(frame)`` (e.g. to move the dashboard's slider) after drawing that frame.

    Parameters
    ----------
    on_frame : callable(int), optional
    **params : enabled, resolution, active, view_width
    """

    enabled = param.Boolean(default=True, doc="Blend and show the normal map on the decimated mesh (b).")
    resolution = param.Selector(default=256, objects=[256, 512], doc="Texels per UV unit of the baked and blended maps.")
    active = param.Boolean(default=True, doc="Draw on update; False: only remember the snapshot and frame.")
    view_width = param.Integer(default=None, allow_None=True, bounds=(100, None),
                               doc="Fixed width (px) of each 3D view; None: the three share the row. Fixed widths "
                                   "make the three renders line up pixel for pixel (same camera, same aspect).")

    def __init__(self, on_frame=None, **params):
        super().__init__(**params)
        self.on_frame = on_frame
        self._snap: dict | None = None
        self._frame = 0
        self._rig = None
        self._key = None
        self._track = None
        self._map_key = None
        self.full_viewer = self.mapped_viewer = self.plain_viewer = None
        self.last_map: np.ndarray | None = None
        self.info: dict = {}
        self.w_enabled = pn.widgets.Toggle.from_param(self.param.enabled, name="Normal map on/off", width=170)
        self.w_resolution = pn.widgets.Select.from_param(self.param.resolution, name="Map resolution (texels per UV unit)", width=230)
        # the dashboard's frame slider lives on another tab: this one scrubs here (on release, a
        # blend takes 0.1-0.5 s) and reports to ``on_frame(frame)`` so the app can follow
        self.w_frame = pn.widgets.IntSlider(label="Frame", start=0, end=1, value=0, sizing_mode="stretch_width")
        self.w_frame.param.watch(self._on_slider, "value_throttled")
        self.status = pn.pane.Markdown("", sizing_mode="stretch_width", margin=(0, 10))
        self.body = pn.Column(sizing_mode="stretch_width")
        self._layout = pn.Column(
            pn.pane.Markdown(
                "Per-expression object-space normal maps baked from the full-resolution rig, blended per frame with the "
                "solved weights (and region masks for the local method) — Liu et al. 2011 §5, eq. 3 on normals. "
                "The decimated mesh keeps 10 % of the triangles.", sizing_mode="stretch_width", margin=(0, 10)),
            pn.Row(self.w_enabled, self.w_resolution, self.w_frame, sizing_mode="stretch_width"),
            self.status, self.body, sizing_mode="stretch_width")

    def __panel__(self):
        return self._layout

    # -- inputs ----------------------------------------------------------------------------
    def update(self, snapshot: dict, frame: int) -> None:
        """Show ``snapshot`` (the session's) at ``frame``; cheap when only the frame changed."""
        self._snap, self._frame = snapshot, int(frame)
        if self.active and snapshot:
            self._draw()

    def _on_slider(self, event):
        if event.new is None or event.new == self._frame:
            return
        self._frame = int(event.new)
        if self.active and self._snap:
            self._draw()
        if self.on_frame is not None:
            self.on_frame(self._frame)

    @param.depends("active", "enabled", "resolution", watch=True)
    def _on_settings(self):
        if self.active and self._snap:
            self._draw()

    # -- drawing ---------------------------------------------------------------------------
    def _draw(self):
        snap = self._snap
        rig = snap["target_rig"]
        if rig.uvs is None:
            self._clear()
            self.status.object = ""
            self.body[:] = [pn.pane.Markdown(HINT, sizing_mode="stretch_width")]
            self.info = {"hint": HINT}
            return
        if rig is not self._rig:
            key = rig_key(rig)
            if key != self._key:
                self._build(rig, key, snap)
            self._rig = rig
        W = np.nan_to_num(np.asarray(snap["weights"], dtype=np.float32))
        if self._track is None or W.shape != self._track.shape or not np.array_equal(W, self._track):
            for v in self._viewers():
                v.set_track(W, fps=float(snap.get("fps", 30.0)))
            self._track = W
            self._map_key = None
        f = int(np.clip(self._frame, 0, len(W) - 1))
        self.w_frame.param.update(end=max(len(W) - 1, 1), value=f)
        for v in self._viewers():
            v.frame = f
        self._draw_map(rig, snap, f)

    def _viewers(self):
        return [v for v in (self.full_viewer, self.mapped_viewer, self.plain_viewer) if v is not None]

    def _clear(self):
        self.full_viewer = self.mapped_viewer = self.plain_viewer = None
        self._rig = self._key = self._track = self._map_key = None
        self.last_map = None

    def _build(self, rig, key, snap):
        t0 = time.perf_counter()
        low = decimated(rig, key)
        b = bake(rig, self.resolution, key)
        uv_low = texture_coordinates(low.uvs, b.raster)
        W = np.nan_to_num(np.asarray(snap["weights"], dtype=np.float32))
        lo, hi = rig.neutral.min(0), rig.neutral.max(0)
        size = dict(sizing_mode="stretch_width") if self.view_width is None else dict(width=self.view_width)
        common = dict(fps=float(snap.get("fps", 30.0)), sync_group=SYNC_GROUP, shading="standard", height=VIEW_HEIGHT,
                      frame_bounds=[float(x) for x in np.r_[lo, hi]], **size)
        self.full_viewer = MeshViewer.from_rig(rig, W, label=f"{rig.name} full resolution", **common)
        self.mapped_viewer = MeshViewer.from_rig(low, W, uvs=uv_low, label=f"{rig.name} decimated + normal map", **common)
        self.plain_viewer = MeshViewer.from_rig(low, W, label=f"{rig.name} decimated", **common)
        self._key, self._track, self._map_key = key, W, None
        self.info = {"decimated_vertices": low.n_vertices, "decimated_faces": int(len(low.faces)),
                     "faces": int(len(rig.faces)), "build_s": time.perf_counter() - t0}

        def col(title, v):
            return pn.Column(pn.pane.Markdown(title, margin=(0, 10)), v, **size)

        self.body[:] = [pn.Row(
            col(f"**(a) full resolution** — {len(rig.faces):,} triangles", self.full_viewer),
            col(f"**(b) decimated + blended normal map** — {len(low.faces):,} triangles", self.mapped_viewer),
            col(f"**(c) decimated** — {len(low.faces):,} triangles, vertex normals", self.plain_viewer),
            sizing_mode="stretch_width")]

    def _draw_map(self, rig, snap, f):
        if not self.enabled:
            self.mapped_viewer.set_normal_map(None)
            self._map_key = None
            self.last_map = None
            self.status.object = f"frame {f} · normal map off (b) shows the decimated mesh's own vertex normals"
            return
        b = bake(rig, self.resolution, self._key)
        U, masks, note = frame_weights(snap, f)
        map_key = (self.resolution, note, U.tobytes())  # frames with equal weights share the map
        if map_key == self._map_key:
            return
        t0 = time.perf_counter()
        mt = None if masks is None else mask_texels(b, rig.faces, masks, self._key)
        img = blended_normal_map(b, U, mt)
        ms = (time.perf_counter() - t0) * 1e3
        self.mapped_viewer.set_normal_map(img)
        self._map_key, self.last_map = map_key, img
        n_act = int(np.any(U != 0, axis=0).sum())
        H, Wd = b.shape
        self.info.update(blend_ms=ms, bake_s=b.seconds, active_shapes=n_act, note=note, map_shape=img.shape)
        self.status.object = html.escape(
            f"frame {f} · {note} · {n_act} shapes with non-zero weight · map {Wd}×{H} texels "
            f"({img.nbytes / 1024:.0f} KB per frame change) · blended in {ms:.0f} ms · maps baked once in {b.seconds:.1f} s")
