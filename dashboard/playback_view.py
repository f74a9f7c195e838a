"""The Retarget tab's two 3D views and their playback: the source (the driven source rig, or the
captured markers on a triangulated marker mesh) and the target rig side by side, one frame
slider and a play toggle linked to the source view (both views share a clock), the target's
colouring (plain, the marker error map, the segmentation's regions) and the regions' legend.

Views hold no numerics: the arrays come from the session's snapshot (and its per-snapshot
``derived`` values), the error field from :func:`core.evaluate.marker_error_field`.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np
import panel as pn

from core.evaluate import marker_error_field
from core.gaps import gap_ranges
from core.retarget import marker_rig
from dashboard.session import derived
from dashboard.viewer import MeshViewer, error_colors

VIEW_HEIGHT = 430
#: Category20-like palette for region maps (RGB in 0..1)
REGION_COLORS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75],
                          [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207], [174, 199, 232], [255, 187, 120],
                          [152, 223, 138], [255, 152, 150], [197, 176, 213], [196, 156, 148]], dtype=np.float32) / 255


def _frozen_rig(rig, track):
    """``(rig, track)`` with the rig's arrays read-only (shared by the pages, see derived())."""
    for a in (rig.neutral, rig.deltas):
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    return rig, track


def error_legend(field) -> str:
    """The error map's legend (HTML): :func:`dashboard.viewer.error_colors`' scale from 0 to the
    largest value of ``field`` (V,) in millimetres (each marker's RMS error over the take), and blue for vertices without data."""
    finite = np.isfinite(field)
    top = float(np.max(field[finite])) if finite.any() else 0.0
    return ("<div style='display:flex;align-items:center;gap:8px;font-size:12px'>"
            "<span>marker error on the target (RMS over the take, blended between markers):</span><span>0 mm</span>"
            "<span style='display:inline-block;width:160px;height:10px;background:linear-gradient(to right, "
            "rgb(217,209,204), rgb(255,153,26), rgb(217,13,13))'></span>"
            f"<span>{top:.1f} mm</span><span style='display:inline-block;width:10px;height:10px;"
            "background:rgb(51,89,230);margin-left:10px'></span><span>no marker nearby</span></div>")


class PlaybackView(pn.viewable.Viewer):
    """The source and target views, the frame slider, play and the target's colouring.

    ``picking``: whether a click on the target picks a vertex now (the marker card's "move
    markers"); ``on_target_pick``: called with the target viewer's ``picked`` events.
    ``rows`` are the objects the page stacks (headings, the two views, the controls);
    ``region_box`` holds the regions' legend (the page puts it under the Edit card)."""

    def __init__(self, session, picking: Callable[[], bool] = lambda: False,
                 on_target_pick: Optional[Callable] = None, **params):
        super().__init__(**params)
        self.s = session
        self._picking = picking
        self._on_target_pick = on_target_pick
        self._viewer_keys = {"source": None, "target": None}
        self._links: list = []
        self.source_viewer: Optional[MeshViewer] = None
        self.target_viewer: Optional[MeshViewer] = None
        # frame control: one slider + play, linked to the source viewer; both viewers share a clock
        self.w_frame = pn.widgets.IntSlider(name="Frame", start=0, end=1, value=0, sizing_mode="stretch_width")
        self.w_play = pn.widgets.Toggle(name="▶ Play / ❚❚ Pause", button_type="success", width=150)
        self.w_heat = pn.widgets.RadioButtonGroup(name="Target colouring", options=["plain", "error map", "regions"],
                                                  value="plain", button_type="light", width=260)
        self.w_heat.param.watch(lambda e: self.draw_heat(), "value")
        self.w_frame.param.watch(self._frame_to_target, "value")
        self.source_box = pn.Column(sizing_mode="stretch_width", min_height=VIEW_HEIGHT)
        self.target_box = pn.Column(sizing_mode="stretch_width", min_height=VIEW_HEIGHT)
        self.region_box = pn.Column(sizing_mode="stretch_width")
        # the two headings in one pane over the two equal halves (not a column + heading per view)
        heads = pn.pane.HTML("<div style='display:flex;font-weight:bold;margin:0 10px'><span style='flex:1'>Source</span>"
                             "<span style='flex:1'>Target</span></div>",
                             sizing_mode="stretch_width", margin=(5, 0, 0, 0))
        # the error map's scale: what the colours mean, in millimetres (shown with the map only)
        self.w_legend = pn.pane.HTML("", visible=False, sizing_mode="stretch_width", margin=(0, 10))
        self.rows = [heads, pn.Row(self.source_box, self.target_box, sizing_mode="stretch_width"),
                     pn.Row(self.w_play, self.w_frame, self.w_heat, sizing_mode="stretch_width"), self.w_legend]

    def __panel__(self):
        return pn.Column(*self.rows, sizing_mode="stretch_width")

    def set_stale(self, stale: bool) -> None:
        """Grey the views out (they show the last good result, not the current selection)."""
        for box in (self.source_box, self.target_box):
            box.css_classes = ["fr-stale"] if stale else []

    def forget_target(self) -> None:
        """The next draw makes a new target view (e.g. its markers moved)."""
        self._viewer_keys["target"] = None

    def draw(self, snap: dict) -> None:
        """The frame range and the two views of the snapshot ``snap`` (a view is made anew only
        when its rig or take changed; the target otherwise just takes the new weights)."""
        T = len(snap["times"])
        self.w_frame.end = max(T - 1, 1)
        if self.w_frame.value > T - 1:
            self.w_frame.value = 0
        fps = snap["fps"]
        # a view made now starts at the slider's frame (the link below carries only later changes):
        # a shot opened at frame 440 showed "Frame: 440" over views at frame 0
        # frames without data (tracking loss) are marked in the views' labels
        gaps = [list(g) for g in gap_ranges(snap["valid"])] if snap.get("valid") is not None else []
        now = dict(frame=int(self.w_frame.value), gaps=gaps)
        # source: the driven source rig, or the captured markers on a triangulated marker mesh
        key = (id(snap["source_rig"]), snap["source_weights"] is None, len(snap["times"]), self.s.source)
        if key != self._viewer_keys["source"]:
            if snap["source_rig"] is not None and snap["source_weights"] is not None:
                rig = snap["source_rig"]
                v = MeshViewer.from_rig(rig, derived(snap, "source_track", lambda: np.nan_to_num(snap["source_weights"])),
                                        fps=fps, layout=snap["source_layout"],
                                        label=rig.name, sync_group="dash", height=VIEW_HEIGHT, sizing_mode="stretch_width",
                                        **now)
            else:
                mrig, track = derived(snap, "marker_rig", lambda: _frozen_rig(*marker_rig(snap["source_markers"])))
                v = MeshViewer.from_rig(mrig, track, fps=fps,
                                        marker_track=derived(snap, "marker_track", lambda: np.nan_to_num(snap["source_markers"])),
                                        label="captured markers", sync_group="dash", height=VIEW_HEIGHT, sizing_mode="stretch_width",
                                        **now)
            self._link_frame(v)
            self.source_box[:] = [v]
            self._viewer_keys["source"] = key
        key = id(snap["target_rig"])
        track = derived(snap, "target_track", lambda: np.nan_to_num(snap["weights"]))
        if key != self._viewer_keys["target"]:
            rig = snap["target_rig"]
            self.target_viewer = MeshViewer.from_rig(rig, track, fps=fps, layout=snap["target_layout"], label=rig.name,
                                                     sync_group="dash", height=VIEW_HEIGHT, sizing_mode="stretch_width",
                                                     pick_mode="vertex" if self._picking() else "off", **now)
            if self._on_target_pick is not None:
                self.target_viewer.param.watch(self._on_target_pick, "picked")
            self.target_box[:] = [self.target_viewer]
            self._viewer_keys["target"] = key
        else:
            self.target_viewer.set_track(track, fps=fps)
        for v in (self.source_viewer, self.target_viewer):
            if v is not None and v.gaps != gaps:
                v.gaps = gaps

    def _frame_to_target(self, event) -> None:
        """A frame set from Python (a shot opened at its frame, a seek) reaches the target view
        too: the two views share one clock in the browser, which the first view to load sets from
        its own ``frame``; with only the source linked, a target made at frame 0 and loaded first
        kept both at 0 under a slider at 440. While playing, the browser drives the frame."""
        v = self.target_viewer
        if v is not None and not self.w_play.value and v.frame != event.new:
            v.frame = int(event.new)

    def _link_frame(self, viewer):
        for link in self._links:
            link.unlink() if hasattr(link, "unlink") else None
        self.source_viewer = viewer
        self._links = [self.w_frame.link(viewer, value="frame", bidirectional=True),
                       self.w_play.link(viewer, value="playing", bidirectional=True)]

    def draw_heat(self) -> None:
        """Colour the target as ``w_heat`` says: plain, the per-vertex marker error, or the regions."""
        snap = self.s.snapshot
        if not snap or self.target_viewer is None:
            return
        mode = self.w_heat.value
        self.w_legend.visible = mode == "error map"
        if mode == "error map":
            field = marker_error_field(snap["target_rig"], snap["target_layout"], snap["evaluate"]["marker_error_per_marker_mm"])
            self.target_viewer.set_colors(error_colors(field))
            self.w_legend.object = error_legend(field)
        elif mode == "regions" and snap.get("segment"):
            labels = snap["segment"]["labels"]
            self.target_viewer.set_colors(REGION_COLORS[labels % len(REGION_COLORS)])
        else:
            self.target_viewer.set_colors(None)

    def draw_regions(self) -> None:
        """The regions' legend: each region's colour and share of the vertices (empty without a
        segmentation)."""
        seg = self.s.snapshot.get("segment")
        if not seg:
            if len(self.region_box):
                self.region_box[:] = []
            return
        sizes = np.bincount(seg["labels"], minlength=len(seg["masks"]))
        swatches = "".join(
            f"<span style='display:inline-block;width:12px;height:12px;margin:0 3px 0 8px;background:rgb"
            f"{tuple(int(255 * c) for c in REGION_COLORS[r % len(REGION_COLORS)])}'></span>{100 * n / sizes.sum():.0f}%"
            for r, n in enumerate(sizes))
        self.region_box[:] = [pn.pane.HTML(f"<b>{len(sizes)} regions</b> (share of vertices; choose <i>regions</i> "
                                           f"colouring to see them on the target)<br>{swatches}", sizing_mode="stretch_width")]
