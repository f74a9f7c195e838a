"""Normal-map blending on the dashboard's target (Liu et al. 2011 §5).

Three views of the target rig at the dashboard's frame, side by side, one camera:

(a) the full-resolution rig playing the solved weights (vertex normals);
(b) a decimated copy (10 % of the triangles) with the normal map blended for the frame,
    ``N = normalize(N_0 + Σ_k B_k Σ_i u_ki (N_i − N_0))`` (eq. 3 on normals): regional weights
    and masks for the local method, the global weights (R = 1, B = 1) otherwise;
(c) the same decimated copy with its own vertex normals.

Everything numeric is core's, and cached by the pipeline: the per-shape maps are the
``normalmap_bake`` stage (per rig content and resolution, shared by all sessions), the decimated
rig ``normalmap_decimate``, the local method's masks in texture space ``normalmap_masks``; per
frame the view calls :func:`core.normalmap.frame_blend_weights` and
:func:`core.normalmap.frame_normal_map`, and only the blended map travels: H·W·3 bytes (ICT:
512×256 texels at 256/UV unit, 384 KB; 1024×512 at 512, 1.5 MB).

A rig without UVs (Rocketbox, Jeeliz) gets a hint instead.
"""

from __future__ import annotations

import html
import time

import numpy as np
import panel as pn
import param

from core.normalmap import frame_blend_weights, frame_normal_map, texture_coordinates

from .viewer import MeshViewer

HINT = "normal-map blending needs a rig with UVs — choose ict_facekit.glb as the target"
VIEW_HEIGHT = 380
SYNC_GROUP = "normalmap"


# -- the view ------------------------------------------------------------------------------
class NormalMapView(pn.viewable.Viewer):
    """Full resolution vs decimated + blended normal map vs decimated, at the dashboard's frame.

    Call :meth:`update` with the session snapshot and the frame (from ``DashboardApp._draw``
    and ``_on_frame``). While :attr:`active` is False (the tab is not shown) it only
    remembers them; becoming active draws the last ones. The view's own frame slider calls
    ``on_frame(frame)`` (e.g. to move the dashboard's slider) after drawing that frame.

    Parameters
    ----------
    pipeline : core.pipeline.Pipeline whose results the snapshots come from (its normal-map
        stages bake the maps; its ``normalmap_resolution`` is the resolution widget)
    on_frame : callable(int), optional
    **params : enabled, active, view_width
    """

    enabled = param.Boolean(default=True, doc="Blend and show the normal map on the decimated mesh (b).")
    active = param.Boolean(default=True, doc="Draw on update; False: only remember the snapshot and frame.")
    view_width = param.Integer(default=None, allow_None=True, bounds=(100, None),
                               doc="Fixed width (px) of each 3D view; None: the three share the row. Fixed widths "
                                   "make the three renders line up pixel for pixel (same camera, same aspect).")

    def __init__(self, pipeline, on_frame=None, **params):
        super().__init__(**params)
        self.pipeline = pipeline
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
        bake = pipeline.normalmap_bake
        self.w_resolution = pn.widgets.Select.from_param(bake.param.normalmap_resolution, name="Map resolution (texels per UV unit)", width=230)
        bake.param.watch(lambda e: self._on_settings(), "normalmap_resolution")
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

    @param.depends("active", "enabled", watch=True)
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
            key = self.pipeline.key("target_face")
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

    def _stage(self, name):
        return self.pipeline.results([name])[name]

    def _build(self, rig, key, snap):
        t0 = time.perf_counter()
        low = self._stage("normalmap_decimate")["rig"]
        b = self._stage("normalmap_bake")["bake"]
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
        b = self._stage("normalmap_bake")["bake"]
        seg = snap.get("segment") if snap.get("method") == "local" else None
        U, use_masks, note = frame_blend_weights(snap["weights"], f, rig.names, (snap.get("solve_info") or {}).get("region_weights"),
                                                 seg["masks"] if seg else None, snap.get("solver_names"))
        map_key = (b.raster.resolution, note, U.tobytes())  # frames with equal weights share the map
        if map_key == self._map_key:
            return
        t0 = time.perf_counter()
        mt = self._stage("normalmap_masks")["masks"] if use_masks else None
        img = frame_normal_map(b, U, mt)
        ms = (time.perf_counter() - t0) * 1e3
        self.mapped_viewer.set_normal_map(img)
        self._map_key, self.last_map = map_key, img
        n_act = int(np.any(U != 0, axis=0).sum())
        H, Wd = b.shape
        self.info.update(blend_ms=ms, bake_s=b.seconds, active_shapes=n_act, note=note, map_shape=img.shape)
        self.status.object = html.escape(
            f"frame {f} · {note} · {n_act} shapes with non-zero weight · map {Wd}×{H} texels "
            f"({img.nbytes / 1024:.0f} KB per frame change) · blended in {ms:.0f} ms · maps baked once in {b.seconds:.1f} s")
