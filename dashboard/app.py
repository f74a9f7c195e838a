"""The face-retarget dashboard: pick a capture and a rig, tune the solver, scrub and play.

Serve with ``face-retarget serve`` (or ``panel serve dashboard/app.py --plugins dashboard.assets``).
Widgets are generated from the pipeline's stage settings; a change re-runs only the stale
stages (core.pipeline) and the views redraw from the session's snapshot. Views hold no
numerics: they only place arrays into panes.
"""

from __future__ import annotations

import html
import logging
import os
import sys
import traceback
from pathlib import Path

import numpy as np
import panel as pn
import param

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.evaluate import marker_error_field  # noqa: E402
from core.retarget import marker_rig  # noqa: E402
from dashboard.curves import CurvePlot, DiagnosticsPlot, curve_columns  # noqa: E402
from dashboard.lazy import lazy_card  # noqa: E402
from dashboard.upload_guard import UploadGuard  # noqa: E402
from dashboard import session as sessions  # noqa: E402  (MAX_UPLOAD is read when a page is made)
from dashboard.session import NONE, Session, derived  # noqa: E402
from dashboard.normalmap_view import NormalMapView  # noqa: E402
from dashboard.personalize_view import PersonalizeView  # noqa: E402
from dashboard.transfer_view import TransferView  # noqa: E402
from dashboard.viewer import MeshViewer, error_colors  # noqa: E402
from dashboard import widgets  # noqa: E402
from dashboard.widgets import param_widgets, ruled_heading  # noqa: E402

log = logging.getLogger("face_retarget.dashboard")

SIDEBAR_WIDTH = 330
#: Category20-like palette for region maps (RGB in 0..1)
REGION_COLORS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75],
                          [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207], [174, 199, 232], [255, 187, 120],
                          [152, 223, 138], [255, 152, 150], [197, 176, 213], [196, 156, 148]], dtype=np.float32) / 255
VIEW_HEIGHT = 430
CSS = """
.fr-stale {opacity: 0.35; filter: grayscale(1);}
.fr-title h1 {font-size: 1.35em; margin: 4px 0 0 0;}
.fr-muted {color: #666; font-size: 0.86em;}
.fr-status {font-size: 0.86em;}
"""

#: the heading of the sidebar's timings, above the table refresh() puts under it
TIMINGS_HEAD = ruled_heading("Timings", "(server, last change)")

#: the sidebar's setting cards: (title, stage groups, collapsed); which stages belong to a group
#: and which of their settings show is declared by the stages (core.stages), not here
SIDEBAR_CARDS = [("Solver", ("solve",), False), ("Source & calibration", ("source", "calibrate"), True),
                 ("Actor personalisation (Ribera 2017)", ("personalize",), True)]


def visible_settings(stage, cfg) -> list:
    """The settings of ``stage`` a user can change now: the ones that matter in this
    configuration (``stage.relevant``), without the edit lists (they have their own controls)
    — for an inactive stage (e.g. segmentation with a global method) none."""
    if not stage.active(cfg):
        return []
    keep = stage.relevant(cfg)
    names = stage.setting_names() if keep is None else [n for n in stage.setting_names() if n in set(keep)]
    return [n for n in names if not isinstance(stage.param[n], (param.List, param.Dict))]


def stage_params(pipe, groups, cfg=None) -> list:
    """``[(stage, [setting names])]`` of the stages in ``groups`` with something to show now
    (``cfg``: the pipeline's config, when the caller has it)."""
    cfg = pipe.config() if cfg is None else cfg
    out = []
    for st in pipe.stages.values():
        if type(st).group in groups:
            names = visible_settings(st, cfg)
            if names:
                out.append((st, names))
    return sorted(out, key=lambda p: p[0].stage_name != "solve")  # the method choice first


#: the tabs after "Retarget", in order (their views are made when first opened)
TAB_VIEWS = ("transfer", "normalmap", "personalize", "batch")


def _frozen_rig(rig, track):
    """``(rig, track)`` with the rig's arrays read-only (shared by the pages, see derived())."""
    for a in (rig.neutral, rig.deltas):
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    return rig, track


def _shown(pipe) -> tuple:
    cfg = pipe.config()  # one snapshot for the three cards (a deep copy of every setting)
    return tuple(tuple((st.stage_name, tuple(n)) for st, n in stage_params(pipe, groups, cfg)) for _, groups, _ in SIDEBAR_CARDS)


class DashboardApp(pn.viewable.Viewer):
    """One browser session's page; a Panel object, so it also displays in a notebook cell
    (``pn.extension()``, then the app as a cell's value) sharing ``session.pipeline`` with code."""

    def __init__(self, session: Session | None = None, hub=None, reviewer: str = "", dormant: bool = False, **params):
        super().__init__(**params)
        self.s = session or Session()
        self.pipe = self.s.pipeline
        self._viewer_keys = {"source": None, "target": None}
        self._doc = pn.state.curdoc  # the page's document (None outside a server)
        self._shown_files = ""
        self._marker_report = None
        self._build_widgets()
        self._tab_views: dict = {}  # the other tabs' views, made when first opened (see _tab_view)
        self._tab_boxes = {n: pn.Column(sizing_mode="stretch_width") for n in TAB_VIEWS}
        self.mirror = self.review = None
        if hub is not None:
            self._join(hub, reviewer, dormant)
        self._build_layout()
        self.refresh()
        if self.review is not None and self.pipe.frame:
            self.w_frame.value = int(min(self.pipe.frame, self.w_frame.end))

    # -- shared review ----------------------------------------------------------------------
    def _join(self, hub, reviewer: str, dormant: bool = False) -> None:
        """Join the hub of a shared shot (dashboard.review): this page's pipeline mirrors it. A
        ``dormant`` page (built ahead, :mod:`dashboard.warm`) joins when :meth:`wake` hands it out."""
        import uuid

        from dashboard.review import Mirror
        from dashboard.review_view import ReviewPanel

        doc = pn.state.curdoc
        self.mirror = Mirror(hub, self.s, reviewer or "someone", on_change=self._remote_change, notify=self._notify, doc=doc,
                             on_own=self._resend_settings, dormant=dormant)
        self.mirror.session_id = uuid.uuid4().hex
        if not dormant:
            hub.join(self.mirror.session_id, self.mirror.name)
        self.review = ReviewPanel(self.mirror, self.w_frame, self.w_play, self._time_of, on_notes=self._draw_note_marks)
        if doc is not None and pn.state.curdoc is not None:
            def gone(ctx, mirror=self.mirror, review=self.review):
                review.close()
                mirror.close()
                hub.leave(mirror.session_id)

            pn.state.on_session_destroyed(gone)

    def wake(self, reviewer: str = "") -> None:
        """A dormant page is handed to its reviewer (:mod:`dashboard.warm`): it joins the shot
        and catches up with every change since it was built, the frame of a presenter included."""
        m = self.mirror
        if m is None or not m.dormant:
            return
        if reviewer:
            m.name = reviewer
        m.dormant = False
        m.hub.join(m.session_id, m.name)
        if m.version != m.hub.version:
            m._schedule_pull()
        self.review.draw_people()
        self.review._follow()

    def catch_up(self) -> None:
        """A dormant page pulls the shot's changes now (while the server is idle), so that it is
        current when handed out (:mod:`dashboard.warm`)."""
        m = self.mirror
        if m is not None and m.dormant:
            m._pull()  # a no-op when it has the hub's version

    def _resend_settings(self, names) -> None:
        """Send this page's widgets of ``names`` their values again (the shot took the page's
        change). A remote change that reached the browser after the user moved a widget but
        before the server read that move leaves the browser showing the remote value while the
        shot has the user's; Bokeh sends nothing for a value the server's model already has, so
        the change is re-announced."""
        from panel.io.document import unlocked

        with unlocked():  # may run in Panel's lock-free event task (see dashboard.curves._page_safe)
            for st, pane in getattr(self, "_setting_panes", []):
                for n in names:
                    w = pane._widgets.get(n)
                    if w is None or getattr(st, n) != w.value:
                        continue
                    for model, _ in list(w._models.values()):
                        prop = "active" if hasattr(model, "active") and not hasattr(model, "value") else "value"
                        if hasattr(model, prop) and model.document is not None:
                            v = getattr(model, prop)
                            model.trigger(prop, v, v)

    def _remote_change(self, change: dict) -> None:
        """Another page changed the shot: the page shows it (on this page's event loop)."""
        if _shown(self.pipe) != self._shown:
            self._show_settings()
        if self.review is not None:
            self.review.draw_notes()
        who = change.get("author") or "someone"
        said = f"{who} changed the shot ({change.get('kind')}, version {change.get('version')})"
        doc = self.mirror.doc if self.mirror is not None else None
        if change.get("kind") == "frame":  # the presenter's cursor: the follow toggle moves ours
            return
        if change.get("kind") == "note":  # nothing to recompute: the notes were drawn above
            self.w_status.object = html.escape(said)
            return
        if doc is None:
            self.refresh()
            self.w_status.object = html.escape(said)
            return
        # the changed widgets reach the browser first (alone: every change costs the browser a
        # layout), the recompute's result right after
        self._said = said
        if self._refresh_due:
            return  # changes that came in quick succession: one refresh shows the last of them
        self._refresh_due = True

        def later():
            from dashboard.review import on_page

            self._refresh_due = False
            with on_page(doc):
                self.refresh()
                self.w_status.object = html.escape(self._said)

        doc.add_timeout_callback(later, 15)

    _refresh_due = False  # a refresh for other pages' changes is scheduled

    def _draw_note_marks(self, notes) -> None:
        self.curves.set_notes([self._time_of(int(n.get("frame", 0))) for n in notes],
                              [str(n.get("text", ""))[:60] for n in notes])

    # -- widgets ----------------------------------------------------------------------------
    def _build_widgets(self):
        s = self.s
        self.w_source = pn.widgets.Select.from_param(s.param.source, name="Source performance", sizing_mode="stretch_width")
        self.w_source_rig = pn.widgets.Select.from_param(s.param.source_rig, name="Source rig (for weight curves)", sizing_mode="stretch_width")
        self.w_target = pn.widgets.Select.from_param(s.param.target_rig, name="Target rig", sizing_mode="stretch_width")
        self.w_upload = pn.widgets.FileInput(accept=".csv,.trc,.c3d,.glb,.gltf,.json", multiple=False, sizing_mode="stretch_width")
        self.w_upload.param.watch(self._on_upload, ["value", "filename"], onlychanged=False)
        # a file over the limit is refused in the browser with a message (sent whole, over twice
        # the limit it would close the page's connection: dashboard.upload_guard)
        self.w_upload_box = UploadGuard(self.w_upload, max_bytes=sessions.MAX_UPLOAD, sizing_mode="stretch_width",
                                        on_refused=lambda n, b: self._notify("error", sessions.too_large(Path(n).name, b)))
        self.settings_box = pn.Column(sizing_mode="stretch_width")
        self.w_auto = pn.widgets.Toggle.from_param(s.param.auto_update, name="Auto-update on every change", button_type="light", sizing_mode="stretch_width")
        self.w_apply = pn.widgets.Button(name="Apply", button_type="primary", sizing_mode="stretch_width")
        self.w_apply.on_click(lambda e: self.refresh())
        self.w_progress = pn.indicators.Progress(value=0, max=100, sizing_mode="stretch_width", height=12, bar_color="primary")
        # the texts every change rewrites on every page of a shot: updates send the text alone
        self.w_status = widgets.Markdown("", css_classes=["fr-status"], sizing_mode="stretch_width")
        self.w_timings = widgets.HTML(TIMINGS_HEAD, sizing_mode="stretch_width")
        self.w_summary = widgets.Markdown("", sizing_mode="stretch_width")
        # errors: a banner in the page (Panel's toast area rendered without its text outside a template)
        self.w_alert = pn.pane.Alert("", alert_type="danger", visible=False, sizing_mode="stretch_width", css_classes=["fr-error"])
        # frame control: one slider + play, linked to the source viewer; both viewers share a clock
        self.w_frame = pn.widgets.IntSlider(name="Frame", start=0, end=1, value=0, sizing_mode="stretch_width")
        self.w_play = pn.widgets.Toggle(name="▶ Play / ❚❚ Pause", button_type="success", width=150)
        self.w_frame.param.watch(self._on_frame, "value")
        self.w_shapes = pn.widgets.MultiChoice(name="Curves shown (empty: the 8 most active)", options=[], sizing_mode="stretch_width")
        self.w_shapes.param.watch(lambda e: self._draw_curves(), "value")
        self.curves = CurvePlot(on_seek=self._seek)
        self.diag = DiagnosticsPlot(x_range=self.curves.fig.x_range)
        self.w_heat = pn.widgets.RadioButtonGroup(name="Target colouring", options=["plain", "error map", "regions"],
                                                  value="plain", button_type="light", width=260)
        self.w_heat.param.watch(lambda e: self._draw_heat(), "value")
        # spacetime edits (Seol 2012 §6)
        self.w_edit_shape = pn.widgets.Select(name="Shape", options=[], sizing_mode="stretch_width")
        self.w_edit_value = pn.widgets.FloatSlider(name="Weight at this frame", start=-0.5, end=1.5, step=0.01, value=0.0, sizing_mode="stretch_width")
        self.w_edit_shape.param.watch(self._on_edit_shape, "value")
        self.w_edit_window = pn.widgets.IntSlider(name="Propagation half-window (frames, 0: whole take)", start=0, end=120, value=12, sizing_mode="stretch_width")
        self.w_edit_add = pn.widgets.Button(name="Set pose at this frame", button_type="primary")
        self.w_edit_add.on_click(self._add_edit)
        self.w_undo = pn.widgets.Button(name="Undo", width=70)
        self.w_redo = pn.widgets.Button(name="Redo", width=70)
        self.w_undo.on_click(lambda e: self._undo(1))
        self.w_redo.on_click(lambda e: self._undo(-1))
        self.w_edits = pn.Column(sizing_mode="stretch_width")
        self.w_shot = pn.widgets.FileDownload(callback=self._shot_bytes, filename="shot.json", label="Download shot",
                                              button_type="light", sizing_mode="stretch_width")
        # results out of the browser (a browser user cannot reach the server's disk)
        self.w_glb = pn.widgets.FileDownload(callback=lambda: self._download("glb"), filename="result.glb",
                                             label="Download GLB", button_type="light", width=140)
        self.w_csv = pn.widgets.FileDownload(callback=lambda: self._download("csv"), filename="result.csv",
                                             label="Download CSV", button_type="light", width=140)
        # markers on a rig without a layout (a user's own character), and the per-shape controls:
        # their widgets are made when the card is first opened (_shape_widgets, _marker_widgets)
        self.shape_card = lazy_card(build=self._shape_widgets, title="Shapes (per-shape controls)", collapsed=True,
                                    sizing_mode="stretch_width")
        # while collapsed the table is not kept up to date (a frame change would patch it): opened, it shows now
        self.shape_card.param.watch(self._on_shape_card, "collapsed")
        self.marker_card = lazy_card(build=self._marker_widgets, title="Markers on the target rig", collapsed=True,
                                     sizing_mode="stretch_width")
        self._marker_pick = None
        self.source_box = pn.Column(sizing_mode="stretch_width", min_height=VIEW_HEIGHT)
        self.target_box = pn.Column(sizing_mode="stretch_width", min_height=VIEW_HEIGHT)
        self.region_box = pn.Column(sizing_mode="stretch_width")
        s.param.watch(self._on_busy, ["busy", "progress", "status"])
        s.param.watch(lambda e: self._changed(), ["source", "source_rig", "target_rig"])
        self._shown = None
        groups = {g for _, gs, _ in SIDEBAR_CARDS for g in gs}
        for st in self.pipe.stages.values():
            if type(st).group in groups:
                # after the review mirror's watcher (precedence 0): other pages hear of a change
                # before this page spends time recomputing it
                st.param.watch(self._on_setting, st.setting_names(), precedence=1)
        self._build_settings()

    def _shot_bytes(self):
        import io

        return io.BytesIO(self.s.shot().to_json().encode("utf-8"))

    # -- per-shape controls -------------------------------------------------------------------
    def _shape_widgets(self) -> list:
        """The shape card's contents, made when it is first opened: a sortable table of the
        per-shape controls (core.controls), edits go into the shot's solve settings."""
        if getattr(self, "w_shape_table", None) is None:
            self.w_shape_table = pn.widgets.Tabulator(
                self._shape_frame(), show_index=False, height=320, sizing_mode="stretch_width", pagination=None,
                layout="fit_data_table", selectable=False, disabled=False,
                editors={"shape": None, "now": None, "lower": {"type": "number", "step": 0.05},
                         "upper": {"type": "number", "step": 0.05}, "gain": {"type": "number", "step": 0.1},
                         "offset": {"type": "number", "step": 0.05}, "active": {"type": "tickCross"}})
            self.w_shape_table.on_edit(self._on_shape_edit)
            self.w_controls_dl = pn.widgets.FileDownload(callback=self._controls_bytes, filename="controls.json",
                                                         label="Download controls", button_type="light", width=160)
            self.w_controls_reset = pn.widgets.Button(name="Reset controls", button_type="light", width=130)
            self.w_controls_reset.on_click(lambda e: self.pipe.configure(controls={}))
        return [pn.pane.Markdown("Per shape: its range (lower…upper, inside the solve), a gain and offset applied "
                                 "after it (clamped to the range), and whether the solver may use it. Sort by a "
                                 "column; *now* is the weight at the current frame. Upload a controls .json to "
                                 "load a table.", css_classes=["fr-muted"]),
                self.w_shape_table, pn.Row(self.w_controls_dl, self.w_controls_reset)]

    def _on_shape_card(self, event):
        if not event.new and self.s.snapshot and getattr(self, "w_shape_table", None) is not None:
            self.w_shape_table.value = self._shape_frame()

    def _shape_frame(self):
        """The shape table's rows: the target's shapes, the current frame's weight, the controls."""
        import pandas as pd

        snap = getattr(self, "s", None) and self.s.snapshot
        if not snap:
            return pd.DataFrame({c: [] for c in ("shape", "now", "lower", "upper", "gain", "offset", "active")})
        from core.controls import default_table, merge_table

        names = snap["target_names"]
        lo, hi = self.pipe.solve.lower, self.pipe.solve.upper
        table = merge_table(self.pipe.solve.controls or {}, default_table(names, lo, hi, symmetry=False))["shapes"]
        f = min(self.w_frame.value, len(snap["weights"]) - 1)
        return pd.DataFrame({"shape": names, "now": np.round(np.nan_to_num(snap["weights"][f]), 3),
                             "lower": [table[n]["lower"] for n in names], "upper": [table[n]["upper"] for n in names],
                             "gain": [table[n]["gain"] for n in names], "offset": [table[n]["offset"] for n in names],
                             "active": [bool(table[n]["active"]) for n in names]})

    def _on_shape_edit(self, event):
        """A cell of the shape table changed: that shape's control goes into the solve settings."""
        import copy

        row = self.w_shape_table.value.iloc[event.row]
        table = copy.deepcopy(self.pipe.solve.controls or {})
        entry = table.setdefault("shapes", {}).setdefault(row["shape"], {})
        entry[event.column] = bool(event.value) if event.column == "active" else float(event.value)
        try:
            from core.controls import validate_table

            validate_table(table, self.s.snapshot["target_names"])
        except ValueError as e:
            self._notify("error", str(e))
            self.w_shape_table.value = self._shape_frame()
            return
        self.pipe.configure(controls=table)

    def _controls_bytes(self):
        import io
        import json

        from core.controls import FORMAT

        table = {"format": FORMAT, "version": 1, **(self.pipe.solve.controls or {})}
        return io.BytesIO(json.dumps(table, indent=1).encode("utf-8"))

    def _mirror_edit(self, i: int):
        from core.controls import mirror_edit

        e = self.pipe.edit.edits[i]
        self.pipe.add_edit("spacetime", mirror_edit(e, self.s.snapshot["solver_names"]))
        self.refresh()

    def _download(self, kind: str):
        import io

        try:
            return io.BytesIO(self.s.result_bytes(kind))
        except Exception as e:  # noqa: BLE001 - shown on the page
            self._notify("error", self.s.readable(e))
            return None

    def _layout_bytes(self):
        import io

        try:
            return io.BytesIO(self.s.layout_json())
        except Exception as e:  # noqa: BLE001 - shown on the page
            self._notify("error", self.s.readable(e))
            return None

    # -- markers on the target rig ----------------------------------------------------------
    def _marker_widgets(self) -> list:
        """The marker card's contents, made on first use (a page that never opens the card never
        pays for them; DashboardApp.w_place & co. exist from then on)."""
        if getattr(self, "w_place", None) is None:
            self.w_place = pn.widgets.Button(name=self._place_label(), button_type="primary", sizing_mode="stretch_width")
            self.w_place.on_click(lambda e: self.place_markers())
            self.w_edit_markers = pn.widgets.Toggle(name="Move markers: click a marker, then where it goes",
                                                    button_type="light", sizing_mode="stretch_width")
            self.w_edit_markers.param.watch(lambda e: self._marker_mode(), "value")
            self.w_layout_dl = pn.widgets.FileDownload(callback=self._layout_bytes, filename="layout.json",
                                                       label="Download layout", button_type="light",
                                                       sizing_mode="stretch_width")
            self.w_marker_progress = pn.indicators.Progress(value=0, max=100, height=10, sizing_mode="stretch_width",
                                                            visible=False)
            self.w_marker_info = pn.pane.Markdown("", sizing_mode="stretch_width", css_classes=["fr-status"])
        return [pn.pane.Markdown("The 41 markers the solvers compare both faces at. A rig of your own needs them "
                                 "once: place them automatically, then move any that landed badly.",
                                 css_classes=["fr-muted"]),
                self.w_place, self.w_marker_progress, self.w_marker_info, self.w_edit_markers, self.w_layout_dl]

    def _place_label(self) -> str:
        return "Place markers automatically" if self.s.needs_layout else "Place the markers again (automatically)"

    def _moving_markers(self) -> bool:
        """Whether the "move markers" toggle is on (off while its card was never opened)."""
        w = getattr(self, "w_edit_markers", None)
        return bool(w is not None and w.value)

    def place_markers(self, block: bool = False) -> None:
        """Place the markers automatically on the chosen target rig (a worker thread unless
        ``block``), with progress; the page recomputes with them."""
        import threading

        self._marker_widgets()  # (called from code, the card may never have been opened)

        def job():
            t0 = __import__("time").perf_counter()
            self.w_marker_progress.param.update(visible=True, value=5)

            def prog(f, m):
                self.w_marker_progress.value = int(100 * min(max(f, 0.0), 1.0))
                self.w_marker_info.object = html.escape(f"{m} ({__import__('time').perf_counter() - t0:.0f} s)")

            try:
                report = self.s.place_markers(progress=prog)
                self.w_marker_info.object = html.escape(report["message"])
                self._marker_report = report
                # the redraw touches Bokeh models (the curve plot), which only the document's own
                # thread may change: hand it to the event loop
                if doc is not None and not block:
                    doc.add_next_tick_callback(self.refresh)
                else:
                    self.refresh()
            except Exception as e:  # noqa: BLE001 - shown on the page
                log.warning("placing markers failed", exc_info=True)
                self.w_marker_info.object = "⚠ " + html.escape(self.s.readable(e))
            finally:
                self.w_marker_progress.visible = False

        doc = pn.state.curdoc
        self.w_place.disabled = True
        try:
            if block:
                job()
            else:
                threading.Thread(target=job, name="place-markers", daemon=True).start()
        finally:
            self.w_place.disabled = False

    def _marker_mode(self):
        v = getattr(self, "target_viewer", None)
        if v is None:
            return
        v.pick_mode = "vertex" if self._moving_markers() else "off"
        self._marker_pick = None
        if self._moving_markers():
            self.w_marker_info.object = "Click a marker on the target, then the place it should be."

    def _on_target_pick(self, event):
        p = event.new
        if not p or not self._moving_markers():
            return
        snap = self.s.snapshot
        layout, rig = snap["target_layout"], snap["target_rig"]
        v = int(p["vertex"])
        if self._marker_pick is None:
            pts = layout.points(rig.neutral)
            i = int(np.argmin(np.linalg.norm(pts - rig.neutral[v], axis=1)))
            if np.linalg.norm(pts[i] - rig.neutral[v]) > 0.05 * rig.size:
                self.w_marker_info.object = "No marker there: click on one of the markers (the small spheres)."
                return
            self._marker_pick = layout.names[i]
            self.target_viewer.set_highlight([v])
            self.w_marker_info.object = f"Marker **{html.escape(self._marker_pick)}**: now click where it should be."
            return
        name, self._marker_pick = self._marker_pick, None
        self.target_viewer.set_highlight([])
        self.s.move_marker(name, v)
        self.w_marker_info.object = f"Marker **{html.escape(name)}** moved to vertex {v}; the result follows."
        self._viewer_keys["target"] = None  # the markers moved: a new target view
        self.refresh()

    def _build_settings(self):
        """The sidebar's setting cards, generated from the stages' settings: every widget is made
        once, and only those that matter for the current method and switches are visible
        (:meth:`_show_settings`) — a method change toggles visibility instead of sending new
        widgets to the browser (that rebuild took seconds to reach the other pages of a review)."""
        rom = {"(the source itself)": ""} | dict(self.s.files["performances"])
        extra = {"rom": {"type": pn.widgets.Select, "options": rom}}
        cfg = self.pipe.config()
        cards, self._setting_panes, self._setting_cards = [], [], []

        def panes_of(groups):
            panes = []
            for st in self.pipe.stages.values():
                if type(st).group not in groups:
                    continue
                names = [n for n in st.setting_names() if not isinstance(st.param[n], (param.List, param.Dict))]
                if not names:
                    continue
                pane = pn.Param(st, parameters=names, widgets=param_widgets(st, names, extra), show_name=False,
                                sizing_mode="stretch_width")
                for n in names:  # the handle _set_visible hides it by
                    w = pane._widgets[n]
                    w.css_classes = [*w.css_classes, f"fr-setting-{n}"]
                panes.append(pane)
                self._setting_panes.append((st, pane))
            panes.sort(key=lambda p: p.object.stage_name != "solve")  # the method choice first
            return panes

        def built(groups):  # a collapsed card's panes, made when it is first opened
            def build():
                panes = panes_of(groups)
                self._set_visible(self.pipe.config())
                return panes
            return build

        for title, groups, collapsed in SIDEBAR_CARDS:
            if title == "Solver":
                cards.extend(panes_of(groups))
            else:
                open_ = title.startswith("Actor") and self.pipe.personalize.personalize
                card = lazy_card(build=built(groups), title=title, collapsed=collapsed and not open_,
                                 sizing_mode="stretch_width")
                self._setting_cards.append((card, groups))
                cards.append(card)
        self.settings_box[:] = cards
        self._show_settings(cfg)

    def _show_settings(self, cfg=None):
        """Show the settings that matter now (:func:`visible_settings`), hide the others — in one
        message to the browser (each visibility change sent alone re-lays the page out: ~0.3 s
        each in Chromium here)."""
        from dashboard.review import on_page

        with on_page(self._doc):
            self._set_visible(cfg or self.pipe.config())

    def _set_visible(self, cfg):
        # hidden by one stylesheet per stage, not by each widget's `visible`: BokehJS lays the
        # whole page out again, synchronously, for every change of a layout's `visible`,
        # `stylesheets` or `css_classes` (LayoutDOMView.invalidate_layout: 0.15-0.2 s each in
        # Chromium here; a method change toggles ten widgets). A stage with nothing to show hides
        # itself in the same stylesheet (`:host`), not by `visible` on top: one change per stage
        # (a method switch was three relayouts, a 0.35-0.46 s long task on every page)
        for st, pane in self._setting_panes:
            keep = set(visible_settings(st, cfg))
            hide = sorted(n for n in pane._widgets if n != "_title" and n not in keep)
            if not keep:
                sheet = [":host { display: none !important; }"]
            elif hide:
                sheet = [", ".join(f".fr-setting-{n}" for n in hide) + " { display: none !important; }"]
            else:
                sheet = []
            if pane.layout.stylesheets != sheet:
                pane.layout.stylesheets = sheet
        for card, groups in self._setting_cards:  # its panes may not be made yet
            card.visible = any(visible_settings(st, cfg) for st in self.pipe.stages.values() if type(st).group in groups)
        self._shown = _shown(self.pipe)

    # -- the other tabs: made when first opened ----------------------------------------------
    def _tab_view(self, name: str):
        """The view of tab ``name`` (made on first use, then shown in its tab and kept up to date)."""
        if name not in self._tab_views:
            if name == "transfer":
                v = TransferView(self.s)
            elif name == "normalmap":
                v = NormalMapView(self.pipe, active=False, on_frame=lambda f: setattr(self.w_frame, "value", f))
            elif name == "batch":
                from dashboard.batch_view import BatchView

                v = BatchView(self.s)
            else:
                v = PersonalizeView()
            self._tab_views[name] = v
            self._tab_boxes[name][:] = [v]
            self._update_tab(name)
        return self._tab_views[name]

    def _update_tab(self, name: str) -> None:
        snap = self.s.snapshot
        if not snap:
            return
        v = self._tab_views[name]
        if name == "normalmap":
            v.update(snap, self.w_frame.value)
        else:
            v.update(snap)

    def _on_tab(self, event):
        name = TAB_VIEWS[event.new - 1] if 0 < event.new <= len(TAB_VIEWS) else None
        if name is not None:
            self._tab_view(name)
        if "normalmap" in self._tab_views:
            self.normalmap_view.active = name == "normalmap"

    transfer_view = property(lambda self: self._tab_view("transfer"), doc="The dense-transfer tab's view")
    normalmap_view = property(lambda self: self._tab_view("normalmap"), doc="The normal-map tab's view")
    personalize_view = property(lambda self: self._tab_view("personalize"), doc="The ROM-alignment tab's view")
    batch_view = property(lambda self: self._tab_view("batch"), doc="The Batch tab's view")

    def _build_layout(self):
        sidebar = pn.Column(
            pn.pane.Markdown("# face-retarget", css_classes=["fr-title"]),
            *([self.review.card] if self.review is not None else []),
            pn.pane.Markdown("Transfer a captured face performance onto another character's blendshape rig. "
                             "Pick a capture and a target, press play, tune the solver.", css_classes=["fr-muted"]),
            self.w_source, self.w_source_rig, self.w_target,
            pn.pane.Markdown("Upload a take (.csv/.trc/.c3d), a rig (.glb/.usd), or a .json shot, marker layout or name map", css_classes=["fr-muted"], margin=(0, 10)),
            self.w_upload_box,
            self.marker_card,
            pn.pane.HTML(ruled_heading("Solver"), sizing_mode="stretch_width"),
            self.settings_box,
            self.w_auto, self.w_apply, self.w_progress, self.w_status,
            pn.pane.Markdown("Everything this page shows (files, settings, edits) is one shot file: download it to "
                             "reproduce the result with `face-retarget retarget --shot shot.json`, upload it to come back.",
                             css_classes=["fr-muted"], margin=(0, 10)),
            self.w_shot,
            self.w_timings,
            width=SIDEBAR_WIDTH, sizing_mode="stretch_height", scroll=True,
        )
        edit_card = pn.Card(
            pn.pane.Markdown("Set a weight at the current frame; the change propagates over the window by movement "
                             "matching (Seol 2012 §6).", css_classes=["fr-muted"]),
            self.w_edit_shape, self.w_edit_value, self.w_edit_window,
            pn.Row(self.w_edit_add, self.w_undo, self.w_redo), self.w_edits,
            title="Edit (spacetime propagation, any method)", collapsed=False, sizing_mode="stretch_width")
        # the two headings in one pane over the two equal halves (not a column + heading per view)
        heads = pn.pane.HTML("<div style='display:flex;font-weight:bold;margin:0 10px'><span style='flex:1'>Source</span>"
                             "<span style='flex:1'>Target</span></div>",
                             sizing_mode="stretch_width", margin=(5, 0, 0, 0))
        views = pn.Row(self.source_box, self.target_box, sizing_mode="stretch_width")
        main = pn.Column(
            self.w_alert,
            heads,
            views,
            pn.Row(self.w_play, self.w_frame, self.w_heat, sizing_mode="stretch_width"),
            pn.Row(self.w_glb, self.w_csv, sizing_mode="stretch_width"),
            self.w_summary,
            pn.Row(pn.Column(self.w_shapes, pn.pane.Bokeh(self.curves.fig, sizing_mode="stretch_width"),
                             pn.pane.Bokeh(self.diag.fig, sizing_mode="stretch_width"), sizing_mode="stretch_width"),
                   pn.Column(edit_card, self.region_box, width=330), sizing_mode="stretch_width"),
            self.shape_card,
            sizing_mode="stretch_width",
        )
        # dynamic: a tab's views reach the browser when it is opened (a page of a shared shot costs
        # the server only what it shows)
        self.tabs = pn.Tabs(("Retarget", main), ("Dense transfer (Xu 2014)", self._tab_boxes["transfer"]),
                            sizing_mode="stretch_width", dynamic=True)
        self.tabs.append(("Normal maps (Liu 2011 §5)", self._tab_boxes["normalmap"]))
        self.tabs.append(("Actor ROM alignment (Ribera 2017 §4)", self._tab_boxes["personalize"]))
        self.tabs.append(("Batch", self._tab_boxes["batch"]))
        self._normalmap_tab = 2
        self.tabs.param.watch(self._on_tab, "active")
        self.layout = pn.Row(sidebar, self.tabs, sizing_mode="stretch_both")

    # -- events -----------------------------------------------------------------------------
    def _on_setting(self, *events):
        if getattr(self, "mirror", None) is not None and self.mirror._applying:
            return  # another page's change: _remote_change shows the widgets first, then recomputes
        # a new method (or switch) shows its own widgets before the (possibly long) recompute starts
        if _shown(self.pipe) != self._shown:
            self._show_settings()
        self._changed()

    def _changed(self):
        if getattr(self, "mirror", None) is not None and self.mirror._applying:
            return  # another page's change: _remote_change shows the widgets first, then recomputes
        if not self.s.auto_update:
            return
        doc = self.mirror.doc if getattr(self, "mirror", None) is not None else None
        if doc is not None:
            # a shared shot: the other pages' updates (queued by the mirror) go out first
            doc.add_next_tick_callback(self.refresh)
        else:
            self.refresh()

    def _on_busy(self, *events):
        self.w_progress.value = self.s.progress
        self.w_status.object = html.escape(self.s.status)

    def _on_upload(self, *events):
        if not self.w_upload.filename:
            return
        try:
            # an empty file arrives as no value at all: add_upload says it is empty
            msg = self.s.add_upload(self.w_upload.filename, self.w_upload.value or b"")
            if not self.s.error:  # selecting it may already have failed to load: keep that error in view
                self._notify("info", msg)
        except ValueError as e:
            self._notify("error", str(e))
        except Exception as e:  # a reader's bug must not leave the page silent: the trace goes to the log
            log.warning("upload %s failed: %s", self.w_upload.filename, traceback.format_exc())
            self._notify("error", f"{Path(str(self.w_upload.filename)).name} could not be read ({type(e).__name__}); "
                                  "if the file opens elsewhere, please report it")

    def _on_frame(self, event):
        self.pipe.frame = int(event.new)  # the review state the shot carries
        t = self._time_of(event.new)
        self.curves.set_time(t)
        self.diag.set_time(t)
        self._sync_edit_value()
        if "normalmap" in self._tab_views:
            self.normalmap_view.update(self.s.snapshot, event.new)
        if not self.shape_card.collapsed and self.s.snapshot:  # the "now" column follows the frame
            f = min(int(event.new), len(self.s.snapshot["weights"]) - 1)
            now = list(np.round(np.nan_to_num(self.s.snapshot["weights"][f]), 3))
            # (an explicit slice: Panel's patch reads slice(None).start as a row index and fails)
            self.w_shape_table.patch({"now": [(slice(0, len(now)), now)]})

    def _seek(self, time_s: float):
        snap = self.s.snapshot
        if not snap:
            return
        self.w_frame.value = int(np.clip(np.searchsorted(snap["times"], time_s), 0, len(snap["times"]) - 1))

    def _time_of(self, frame: int) -> float:
        times = self.s.snapshot.get("times")
        return float(times[min(frame, len(times) - 1)]) if times is not None and len(times) else 0.0

    def _notify(self, kind: str, msg: str):
        """Errors and notices as a banner at the top of the page (never a stack trace)."""
        log.info("%s: %s", kind, msg)
        self.w_alert.param.update(object=f"**{'Error' if kind == 'error' else 'Note'}:** {html.escape(msg)}",
                                  alert_type="danger" if kind == "error" else "info", visible=True)

    # -- edits ------------------------------------------------------------------------------
    def _on_edit_shape(self, event=None):
        self._sync_edit_value()

    def _sync_edit_value(self):
        snap = self.s.snapshot
        shape = self.w_edit_shape.value
        if snap:
            lo, hi = snap.get("edit_bounds", (None, None))
            lo, hi = (-0.5 if lo is None else float(np.min(lo))), (1.5 if hi is None else float(np.max(hi)))
            if (self.w_edit_value.start, self.w_edit_value.end) != (lo, hi):
                self.w_edit_value.param.update(start=lo, end=hi, value=float(np.clip(self.w_edit_value.value, lo, hi)))
        if snap and shape in snap["target_names"]:
            w = snap["weights"][min(self.w_frame.value, len(snap["weights"]) - 1), snap["target_names"].index(shape)]
            self.w_edit_value.value = float(np.clip(np.nan_to_num(w), self.w_edit_value.start, self.w_edit_value.end))

    def _add_edit(self, event=None):
        snap = self.s.snapshot
        if not snap or not self.w_edit_shape.value:
            return
        f, r, T = self.w_frame.value, self.w_edit_window.value, len(snap["times"])
        window = None if r == 0 else [max(0, f - r), min(T - 1, f + r)]
        if window is not None and (window[0] == f or window[1] == f):
            self._notify("warning", "the window must extend on both sides of the frame; choose a frame away from the ends")
            return
        edit = {"frame": int(f), "weights": {self.w_edit_shape.value: round(float(self.w_edit_value.value), 4)}, "window": window}
        self.pipe.add_edit("spacetime", edit)
        self.refresh()

    def _remove_edit(self, i: int):
        self.pipe.remove_edit("spacetime", i)
        self.refresh()

    def _undo(self, direction: int):
        if self.pipe.undo("spacetime") if direction > 0 else self.pipe.redo_edit("spacetime"):
            self.refresh()

    _edits_drawn = None

    def _draw_edits(self):
        self.w_undo.disabled = not self.pipe.edit.edits
        self.w_redo.disabled = not self.pipe.redo["spacetime"]
        key = repr(self.pipe.edit.edits)
        if key == self._edits_drawn:
            return  # unchanged: new children would make Bokeh walk the page's models again (~50 ms)
        self._edits_drawn = key
        rows = []
        for i, e in enumerate(self.pipe.edit.edits):
            (shape, value), = e["weights"].items()
            win = "whole take" if not e["window"] else f"{e['window'][0]}–{e['window'][1]}"
            b = pn.widgets.Button(name="✕", width=34, button_type="light", description="remove this edit")
            b.on_click(lambda ev, i=i: self._remove_edit(i))
            m = pn.widgets.Button(name="⇄", width=34, button_type="light", description="the same edit on the other side")
            m.on_click(lambda ev, i=i: self._mirror_edit(i))
            rows.append(pn.Row(pn.pane.Markdown(f"frame {e['frame']}: `{shape}` = {value:g} ({win})", margin=(2, 5)), m, b))
        self.w_edits[:] = rows or [pn.pane.Markdown("*no edits*", css_classes=["fr-muted"])]

    # -- redraw -----------------------------------------------------------------------------
    def refresh(self):
        """Recompute what is stale and redraw; an error is shown once (the banner), and the views
        say they belong to the last good result (greyed) until the next good one."""
        ok = self.s.recompute()
        needs = self.s.needs_layout
        self.marker_card.collapsed = not needs and self.marker_card.collapsed
        if getattr(self, "w_place", None) is not None:
            self.w_place.name = self._place_label()
        if not ok:
            self._notify("error", self.s.error)
            self.w_status.object = "error — see the message at the top of the page"
            last = self._shown_files
            self.w_summary.object = (f"The views show the last good result ({html.escape(last)}), not the current "
                                     "selection." if last else "No result yet.")
            for box in (self.source_box, self.target_box):
                box.css_classes = ["fr-stale"]
            self._drawn = None  # the summary says the views are stale: the next good result is drawn
            if needs:
                self.marker_card.collapsed = False
            return
        self.w_alert.visible = False
        for box in (self.source_box, self.target_box):
            box.css_classes = []
        self._shown_files = f"{self.s.source} → {self.s.target_rig}"
        drawn = (self.s.package, self.s.source, self.s.target_rig)  # what _draw shows: the results and the files' names
        if self._drawn is not None and drawn[0] is self._drawn[0] and drawn[1:] == self._drawn[1:]:
            return  # shown already (e.g. a shared shot's change this page had drawn)
        self._draw()
        self._drawn = drawn

    _drawn = None  # (package, source, target) last drawn

    def _draw(self):
        snap = self.s.snapshot
        T = len(snap["times"])
        self.w_frame.end = max(T - 1, 1)
        if self.w_frame.value > T - 1:
            self.w_frame.value = 0
        self._draw_viewers()
        names = snap["target_names"]
        if self.w_shapes.options != names:
            self.w_shapes.param.update(options=names, value=[v for v in self.w_shapes.value if v in names])
            keep = self.w_edit_shape.value if self.w_edit_shape.value in names else names[int(np.nanargmax(np.ptp(snap["weights"], axis=0)))]
            self.w_edit_shape.param.update(options=names, value=keep)
        self._draw_curves()
        ev = snap["evaluate"]
        self.diag.update(snap["times"], ev["marker_error_mm"], ev["velocity_error_mm_per_frame"])
        self._draw_heat()
        self._draw_edits()
        self._draw_regions()
        self.w_summary.object = (
            f"**{self.s.source}** → **{self.s.target_rig}** · {T} frames @ {snap['fps']:g} fps · "
            f"{len(snap['marker_names'])} markers · method **{snap['method']}** · marker error RMS "
            f"**{ev['marker_rms_mm']:.2f} mm** (max {ev['marker_max_mm']:.1f}) · velocity error "
            f"{ev['velocity_error_mean_mm_per_frame'] or float('nan'):.3f} mm per frame (RMS per marker, Seol 2012 eq. 2) · weights in [{ev['weight_low']:.2f}, {ev['weight_high']:.2f}] "
            f"({100 * ev['outside_01']:.1f}% outside 0..1)")
        notes = list(dict.fromkeys(snap.get("warnings", [])))  # data-quality notes stay on the page, not as toasts
        if notes:
            self.w_summary.object += "\n\n" + "\n".join(f"ℹ {html.escape(n)}" for n in notes[:4])
        rows = "".join(f"<tr><td>{k}</td><td style='text-align:right'>{v:.1f} ms</td></tr>" for k, v in snap["timings"].items() if v > 0.05)
        for name in self._tab_views:
            self._update_tab(name)
        self._sync_edit_value()  # the edit slider shows the new result's weight at this frame
        if not self.shape_card.collapsed and getattr(self, "w_shape_table", None) is not None:
            self.w_shape_table.value = self._shape_frame()
        self.w_timings.object = (f"{TIMINGS_HEAD}<table style='font-size:0.85em;width:100%'>{rows}<tr><td><b>server total</b></td>"
                                 f"<td style='text-align:right'><b>{snap['server_ms']:.1f} ms</b></td></tr></table>")

    def _draw_curves(self):
        snap = self.s.snapshot
        if snap:
            self.curves.update(snap["times"], snap["weights"], snap["target_names"], list(self.w_shapes.value),
                               columns=derived(snap, "curve_columns", lambda: curve_columns(snap["weights"])))
            self.curves.set_time(self._time_of(self.w_frame.value))

    def _draw_viewers(self):
        snap = self.s.snapshot
        fps = snap["fps"]
        # source: the driven source rig, or the captured markers on a triangulated marker mesh
        key = (id(snap["source_rig"]), snap["source_weights"] is None, len(snap["times"]), self.s.source)
        if key != self._viewer_keys["source"]:
            if snap["source_rig"] is not None and snap["source_weights"] is not None:
                rig = snap["source_rig"]
                v = MeshViewer.from_rig(rig, derived(snap, "source_track", lambda: np.nan_to_num(snap["source_weights"])),
                                        fps=fps, layout=snap["source_layout"],
                                        label=rig.name, sync_group="dash", height=VIEW_HEIGHT, sizing_mode="stretch_width")
            else:
                mrig, track = derived(snap, "marker_rig", lambda: _frozen_rig(*marker_rig(snap["source_markers"])))
                v = MeshViewer.from_rig(mrig, track, fps=fps,
                                        marker_track=derived(snap, "marker_track", lambda: np.nan_to_num(snap["source_markers"])),
                                        label="captured markers", sync_group="dash", height=VIEW_HEIGHT, sizing_mode="stretch_width")
            self._link_frame(v)
            self.source_box[:] = [v]
            self._viewer_keys["source"] = key
        key = id(snap["target_rig"])
        track = derived(snap, "target_track", lambda: np.nan_to_num(snap["weights"]))
        if key != self._viewer_keys["target"]:
            rig = snap["target_rig"]
            self.target_viewer = MeshViewer.from_rig(rig, track, fps=fps, layout=snap["target_layout"], label=rig.name,
                                                     sync_group="dash", height=VIEW_HEIGHT, sizing_mode="stretch_width",
                                                     pick_mode="vertex" if self._moving_markers() else "off")
            self.target_viewer.param.watch(self._on_target_pick, "picked")
            self.target_box[:] = [self.target_viewer]
            self._viewer_keys["target"] = key
        else:
            self.target_viewer.set_track(track, fps=fps)

    def _link_frame(self, viewer):
        if getattr(self, "_links", None):
            for link in self._links:
                link.unlink() if hasattr(link, "unlink") else None
        self.source_viewer = viewer
        self._links = [self.w_frame.link(viewer, value="frame", bidirectional=True),
                       self.w_play.link(viewer, value="playing", bidirectional=True)]

    def _draw_heat(self):
        snap = self.s.snapshot
        if not snap or not hasattr(self, "target_viewer"):
            return
        mode = self.w_heat.value
        if mode == "error map":
            field = marker_error_field(snap["target_rig"], snap["target_layout"], snap["evaluate"]["marker_error_per_marker_mm"])
            self.target_viewer.set_colors(error_colors(field))
        elif mode == "regions" and snap.get("segment"):
            labels = snap["segment"]["labels"]
            self.target_viewer.set_colors(REGION_COLORS[labels % len(REGION_COLORS)])
        else:
            self.target_viewer.set_colors(None)

    def _draw_regions(self):
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

    def __panel__(self):
        return self.layout


def create_app():
    """The page: on a review server (``face-retarget serve --data-dir``) ``?shot=<id>`` joins that
    shared shot and a page without one offers to create a shot or open a recent one; otherwise a
    page of its own."""
    pn.extension("tabulator", raw_css=[CSS])
    # The page's Location is made from its request now, before any pane: making it empties the
    # document's stylesheet cache (panel.io.location.Location._sync_pathname), and Panel makes it
    # only after building the page — every HTML/Markdown pane's first update then got new
    # stylesheet objects, and each of those made Bokeh walk the whole document's ~230 models
    # again (~50 ms a pane; ~0.15 s a page on its first shared change, 3 s over 20 pages).
    _ = pn.state.location
    from dashboard import review

    if review.SERVER is None and os.environ.get("FACE_RETARGET_REVIEW_DIR"):  # `panel serve dashboard/app.py` with a store
        review.configure(os.environ["FACE_RETARGET_REVIEW_DIR"])
    if review.SERVER is None:
        return DashboardApp().layout
    args = pn.state.session_args or {}
    sid = (args.get("shot") or [b""])[0].decode(errors="replace").strip()
    if not sid:  # the dashboard on the sample, a page of its own, with a card to share it as a review
        from dashboard.review_view import review_start

        app = DashboardApp()
        app.layout[0].insert(1, review_start(review.SERVER, app.s.shot))
        return app.layout
    from core.store import UnknownShot

    try:
        hub = review.SERVER.hub(sid)
    except (UnknownShot, ValueError):
        return pn.pane.Markdown(f"## No shot {html.escape(sid)!s}\n\n[Start or open a shot](?)", margin=30)
    from dashboard import warm

    session = Session()
    session.open_shot(hub.shot, name=sid, locate=review.SERVER.store.locate)
    user = getattr(pn.state, "user", None) or ""
    dormant = warm.is_warming(pn.state.curdoc)  # built ahead of its reviewer (dashboard.warm)
    app = DashboardApp(session, hub=hub, reviewer=user, dormant=dormant)
    if dormant:
        warm.POOL.apps[pn.state.curdoc.session_context.id] = app
    return app.layout


if __name__.startswith("bokeh"):  # panel serve dashboard/app.py --plugins dashboard.assets
    create_app().servable(title="face-retarget")
