"""The face-retarget dashboard: pick a capture and a rig, tune the solver, scrub and play.

Serve with ``face-retarget serve`` (or ``panel serve dashboard/app.py --plugins dashboard.assets``).
Widgets are generated from the pipeline's stage settings; a change re-runs only the stale
stages (core.pipeline) and the views redraw from the session's snapshot. Views hold no
numerics: they only place arrays into panes.

:class:`DashboardApp` is the page: it composes the views and wires them together. The Retarget
tab's views are :class:`~dashboard.retarget_sidebar.RetargetSidebar` (files, solver settings,
status, the shot download, timings), :class:`~dashboard.marker_layout_view.MarkerLayoutView`
(markers on the target rig), :class:`~dashboard.playback_view.PlaybackView` (the two 3D views,
frame slider, play, colouring), :class:`~dashboard.curves_view.CurvesView` (weight curves and
errors), :class:`~dashboard.pose_edit_view.PoseEditView` (the Edit card),
:class:`~dashboard.summary_view.SummaryView` (summary and downloads),
:class:`~dashboard.contact_sheet_view.ContactSheetView` (the contact sheet; links that jump to a frame) and
:class:`~dashboard.shape_controls_view.ShapeControlsView` (per-shape controls); the other tabs
are views of their own, made when first opened.
"""

from __future__ import annotations

import html
import io
import logging
import os
import sys
import uuid
from pathlib import Path
from urllib.parse import quote

import numpy as np
import panel as pn

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from dashboard.batch_view import BatchView  # noqa: E402
from dashboard.connection_view import ConnectionWatch  # noqa: E402
from dashboard.contact_sheet_view import ContactSheetView  # noqa: E402
from dashboard.curves_view import CurvesView  # noqa: E402
from dashboard.live_view import LiveView  # noqa: E402
from dashboard.marker_layout_view import MarkerLayoutView  # noqa: E402
from dashboard.normalmap_view import NormalMapView  # noqa: E402
from dashboard.personalize_view import PersonalizeView  # noqa: E402
from dashboard.playback_view import PlaybackView  # noqa: E402
from dashboard.pose_edit_view import PoseEditView  # noqa: E402
from dashboard.retarget_sidebar import RetargetSidebar  # noqa: E402
from dashboard.review import Mirror, on_page  # noqa: E402
from dashboard.review_view import ReviewPanel  # noqa: E402
from dashboard import review as shared  # noqa: E402 (the review server: shared.SERVER)
from dashboard import session as sessions  # noqa: E402
from dashboard import warm  # noqa: E402
from dashboard.session import Session  # noqa: E402
from dashboard.shape_controls_view import ShapeControlsView  # noqa: E402
from dashboard.summary_view import SummaryView  # noqa: E402
from dashboard.transfer_view import TransferView  # noqa: E402

log = logging.getLogger("face_retarget.dashboard")

CSS = """
.fr-stale {opacity: 0.35; filter: grayscale(1);}
.fr-title h1 {font-size: 1.35em; margin: 4px 0 0 0;}
.fr-muted {color: #666; font-size: 0.86em;}
.fr-status {font-size: 0.86em;}
"""

#: the tabs after "Retarget", in order (their views are made when first opened)
TAB_VIEWS = ("transfer", "normalmap", "personalize", "batch", "live")


class DashboardApp(pn.viewable.Viewer):
    """One browser session's page; a Panel object, so it also displays in a notebook cell
    (``pn.extension()``, then the app as a cell's value) sharing ``session.pipeline`` with code.

    It is the views' ``host``: they reach the session (``s``), the pipeline (``pipe``), the
    current ``frame``, :meth:`notify`, :meth:`refresh` and :meth:`changed` through it."""

    def __init__(self, session: Session | None = None, hub=None, reviewer: str = "", dormant: bool = False, **params):
        super().__init__(**params)
        self.s = session or Session()
        self.pipe = self.s.pipeline
        self.mirror = self.review = None
        self._shown_files = ""
        self._tab_views: dict = {}  # the other tabs' views, made when first opened (see _tab_view)
        self._tab_boxes = {n: pn.Column(sizing_mode="stretch_width") for n in TAB_VIEWS}
        # errors: a banner in the page (Panel's toast area rendered without its text outside a template)
        self.w_alert = pn.pane.Alert("", alert_type="danger", visible=False, sizing_mode="stretch_width", css_classes=["fr-error"])
        # a rig just uploaded is offered at once, in its note (see notify)
        self._offered = None
        self.w_use_target = pn.widgets.Button(name="Use as target", button_type="primary", width=150)
        self.w_use_source_rig = pn.widgets.Button(name="Use as source rig", button_type="light", width=150)
        self.w_use_target.on_click(lambda e: self.use_rig("target_rig"))
        self.w_use_source_rig.on_click(lambda e: self.use_rig("source_rig"))
        self.w_offer = pn.Row(self.w_use_target, self.w_use_source_rig, visible=False, margin=(0, 10, 5, 10))
        self.markers = MarkerLayoutView(self)
        self.sidebar = RetargetSidebar(self, self.markers.card)
        self.playback = PlaybackView(self.s, picking=self.markers.moving, on_target_pick=self.markers.on_target_pick)
        self.playback.w_frame.param.watch(self._on_frame, "value")
        self.curves = CurvesView(self.s, on_seek=self.seek, time_of=self.time_of, frame=lambda: self.frame)
        self.edits = PoseEditView(self)
        self.summary = SummaryView(self.s, notify=self.notify)
        self.contact = ContactSheetView(self)
        self.shape_controls = ShapeControlsView(self.s, frame=lambda: self.frame, notify=self.notify)
        self.s.param.watch(lambda e: self.changed(), ["source", "source_rig", "target_rig"])
        if hub is not None:
            self._join(hub, reviewer, dormant)
        self._build_layout()
        self.refresh()
        if self.review is not None and self.pipe.frame:
            self.playback.w_frame.value = int(min(self.pipe.frame, self.playback.w_frame.end))

    @property
    def frame(self) -> int:
        """The frame the page shows (its frame slider's value)."""
        return self.playback.w_frame.value

    # -- shared review ----------------------------------------------------------------------
    def _join(self, hub, reviewer: str, dormant: bool = False) -> None:
        """Join the hub of a shared shot (dashboard.review): this page's pipeline mirrors it. A
        ``dormant`` page (built ahead, :mod:`dashboard.warm`) joins when :meth:`wake` hands it out."""
        doc = pn.state.curdoc
        self.mirror = Mirror(hub, self.s, reviewer or "someone", on_change=self._remote_change, notify=self.notify, doc=doc,
                             on_own=self.sidebar.resend_settings, dormant=dormant)
        self.mirror.session_id = uuid.uuid4().hex
        if not dormant:
            hub.join(self.mirror.session_id, self.mirror.name)
        self.review = ReviewPanel(self.mirror, self.playback.w_frame, self.playback.w_play, self.time_of,
                                  on_notes=self._draw_note_marks)
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

    def _remote_change(self, change: dict) -> None:
        """Another page changed the shot: the page shows it (on this page's event loop)."""
        self.sidebar.follow_settings()
        if self.review is not None:
            self.review.draw_notes()
        who = change.get("author") or "someone"
        said = f"{who} changed the shot ({change.get('kind')}, version {change.get('version')})"
        doc = self.mirror.doc if self.mirror is not None else None
        if change.get("kind") == "frame":  # the presenter's cursor: the follow toggle moves ours
            return
        if change.get("kind") == "note":  # nothing to recompute: the notes were drawn above
            self.sidebar.w_status.object = html.escape(said)
            return
        if doc is None:
            self.refresh()
            self.sidebar.w_status.object = html.escape(said)
            return
        # the changed widgets reach the browser first (alone: every change costs the browser a
        # layout), the recompute's result right after
        self._said = said
        if self._refresh_due:
            return  # changes that came in quick succession: one refresh shows the last of them
        self._refresh_due = True

        def later():
            self._refresh_due = False
            with on_page(doc):
                self.refresh()
                self.sidebar.w_status.object = html.escape(self._said)

        doc.add_timeout_callback(later, 15)

    _refresh_due = False  # a refresh for other pages' changes is scheduled

    def _draw_note_marks(self, notes) -> None:
        self.curves.set_notes([self.time_of(int(n.get("frame", 0))) for n in notes],
                              [str(n.get("text", ""))[:60] for n in notes])

    # -- the other tabs: made when first opened ----------------------------------------------
    def _tab_view(self, name: str):
        """The view of tab ``name`` (made on first use, then shown in its tab and kept up to date)."""
        if name not in self._tab_views:
            if name == "transfer":
                v = TransferView(self.s)
            elif name == "normalmap":
                v = NormalMapView(self.pipe, active=False, on_frame=lambda f: setattr(self.playback.w_frame, "value", f))
            elif name == "batch":
                v = BatchView(self.s)
            elif name == "live":
                v = LiveView(self.pipe, on_take=self.s.add_upload, notify=self.notify)
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
            v.update(snap, self.frame)
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
    live_view = property(lambda self: self._tab_view("live"), doc="The Live tab's view")

    def _build_layout(self):
        sidebar = self.sidebar.layout
        if self.review is not None:
            # a page opened at ?shot= is the shot's: its review card (people, notes) heads the
            # sidebar. (Below the settings, a page built ahead (dashboard.warm) kept a second,
            # never rendered view of the Method select, which threw in the browser when the shot
            # re-sent the method: tests/browser/test_review_browser.py's warm-page test.)
            sidebar.insert(1, self.review.card)
        main = pn.Column(
            self.w_alert, self.w_offer,
            *self.playback.rows,
            *self.summary.rows,
            self.contact.card,
            self.contact.links,
            pn.Row(self.curves.layout, pn.Column(self.edits.card, self.playback.region_box, width=330,
                                                 css_classes=["fr-edit-column"]),
                   sizing_mode="stretch_width"),
            self.shape_controls.card,
            sizing_mode="stretch_width",
        )
        # dynamic: a tab's views reach the browser when it is opened (a page of a shared shot costs
        # the server only what it shows)
        self.tabs = pn.Tabs(("Retarget", main), ("Dense transfer (Xu 2014)", self._tab_boxes["transfer"]),
                            sizing_mode="stretch_width", dynamic=True)
        self.tabs.append(("Normal maps (Liu 2011 §5)", self._tab_boxes["normalmap"]))
        self.tabs.append(("Actor ROM alignment (Ribera 2017 §4)", self._tab_boxes["personalize"]))
        self.tabs.append(("Batch", self._tab_boxes["batch"]))
        self.tabs.append(("Live", self._tab_boxes["live"]))
        self._normalmap_tab = 2
        self.tabs.param.watch(self._on_tab, "active")
        # ConnectionWatch: "Connection lost" over the page when its server is gone (whichever tab is open)
        # the handles the layout test measures the page by (tests/browser/test_first_page.py)
        sidebar.css_classes = [*sidebar.css_classes, "fr-sidebar"]
        self.curves.layout.css_classes = [*self.curves.layout.css_classes, "fr-curves"]
        self.summary.w_summary.css_classes = [*self.summary.w_summary.css_classes, "fr-summary"]
        self.edits.card.css_classes = [*self.edits.card.css_classes, "fr-edit"]
        self.shape_controls.card.css_classes = [*self.shape_controls.card.css_classes, "fr-shapes"]
        self.layout = pn.Row(sidebar, self.tabs, ConnectionWatch(), sizing_mode="stretch_both")

    # -- events -----------------------------------------------------------------------------
    def changed(self):
        """A setting or file changed on this page: recompute now if auto-update is on."""
        if self.mirror is not None and self.mirror._applying:
            return  # another page's change: _remote_change shows the widgets first, then recomputes
        if not self.s.auto_update:
            return
        doc = self.mirror.doc if self.mirror is not None else None
        if doc is not None:
            # a shared shot: the other pages' updates (queued by the mirror) go out first
            doc.add_next_tick_callback(self.refresh)
        else:
            self.refresh()

    def _on_frame(self, event):
        self.pipe.frame = int(event.new)  # the review state the shot carries
        self.curves.set_time(self.time_of(event.new))
        self.edits.sync_value()
        if "normalmap" in self._tab_views:
            self.normalmap_view.update(self.s.snapshot, event.new)
        self.shape_controls.follow_frame(event.new)  # the "now" column follows the frame

    def seek(self, time_s: float):
        """Show the frame at ``time_s`` seconds (a tap on the curves)."""
        snap = self.s.snapshot
        if not snap:
            return
        self.playback.w_frame.value = int(np.clip(np.searchsorted(snap["times"], time_s), 0, len(snap["times"]) - 1))

    def time_of(self, frame: int) -> float:
        """The time of ``frame`` in seconds (0 without a result)."""
        times = self.s.snapshot.get("times")
        return float(times[min(frame, len(times) - 1)]) if times is not None and len(times) else 0.0

    def notify(self, kind: str, msg: str, rig: str | None = None):
        """Errors and notices as a banner at the top of the page (never a stack trace); ``rig``
        (the list label of a rig just uploaded) adds *Use as target* / *Use as source rig* under it."""
        log.info("%s: %s", kind, msg)
        self.w_alert.param.update(object=f"**{'Error' if kind == 'error' else 'Note'}:** {html.escape(msg)}",
                                  alert_type="danger" if kind == "error" else "info", visible=True)
        self._offered = rig
        if self.w_offer.visible != (rig is not None):
            self.w_offer.visible = rig is not None

    def clear_note(self) -> None:
        """Take the note (and a rig's offer) off the page: a new upload's comes next."""
        self._offered = None
        if self.w_alert.visible:
            self.w_alert.visible = False
        if self.w_offer.visible:
            self.w_offer.visible = False

    def use_rig(self, role: str) -> None:
        """The rig offered in the note becomes the target (``role="target_rig"``) or the source rig;
        either without a marker layout gets its markers placed automatically (the Markers card
        shows the progress and the markers that landed badly), never the previous rig's."""
        label = self._offered
        if label is None or label not in self.s.files["rigs"]:
            return
        self.w_offer.visible = False
        self._offered = None
        setattr(self.s, role, label)  # recomputes (auto-update)
        name = label.removeprefix(sessions.UPLOAD)
        which, what = ("target", "target") if role == "target_rig" else ("source", "source rig")
        if self.s.missing_layout(which):
            self.notify("info", f"{name} is the {what}: placing its markers automatically (see the Markers card)")
            self.markers.card.collapsed = False
            self.markers.place(roles=[which])
        elif not self.s.error:
            self.notify("info", f"{name} is the {what}")

    # -- shared shots: this page becomes one ----------------------------------------------
    def open_shared(self, sid: str) -> None:
        """This page joins the shared shot ``sid`` in place (just made from it, or imported): the
        page shows the shot, its Shared review card the people and the notes, and the address bar
        ``?shot=<id>`` (the history API: no reload; a reload opens the same shot)."""
        if self.mirror is not None or shared.SERVER is None:
            return
        hub = shared.SERVER.hub(sid)
        self._join(hub, getattr(pn.state, "user", None) or "")
        self.sidebar.review_slot[:] = [self.review.card]
        if pn.state.location is not None:
            pn.state.location.search = f"?shot={quote(sid)}"
        self._keep_warm(sid, hub)
        self._drawn = None
        self.refresh()

    def _keep_warm(self, sid: str, hub) -> None:
        """Pages of the new shot are built ahead (:mod:`dashboard.warm`), as for a page opened at
        ``?shot=<id>``: the people the link is sent to open it at once. On the document's event
        loop (this runs in a click's callback, maybe on a worker thread)."""
        doc, pool = pn.state.curdoc, warm.POOL
        if pool is not None and doc is not None and getattr(doc, "session_context", None) is not None:
            doc.add_next_tick_callback(lambda: pool.want_made_here(sid, hub))

    def open_review_archive(self, name: str, data: bytes) -> None:
        """A review someone sent (the .zip of *Download the review*): imported into this server's
        review store and opened on this page (:meth:`open_shared`)."""
        if shared.SERVER is None:
            self.notify("error", f"{name} is a review (.zip): open it on a review server (face-retarget serve "
                                 "keeps reviews unless started with --no-review)")
            return
        if self.mirror is not None:
            self.notify("error", f"{name} is a review: this page shows a shared shot already; open it from a new page")
            return
        if not data:
            self.notify("error", f"{name} is empty: upload the file again (the upload may have been cut off)")
            return
        try:
            sid = shared.SERVER.store.import_(io.BytesIO(data), author="import")
        except ValueError as e:  # named, plain words (core.store)
            self.notify("error", f"{name}: {e}")
            return
        self.open_shared(sid)
        self.notify("info", f"review {name} opened as a shared shot")

    # -- redraw -----------------------------------------------------------------------------
    def refresh(self):
        """Recompute what is stale and redraw; an error is shown once (the banner), and the views
        say they belong to the last good result (greyed) until the next good one."""
        ok = self.s.recompute()
        self.markers.follow()
        if not ok:
            self.notify("error", self.s.error)
            self.sidebar.w_status.object = "error — see the message at the top of the page"
            self.summary.show_stale(self._shown_files)
            self.playback.set_stale(True)
            self._drawn = None  # the summary says the views are stale: the next good result is drawn
            return
        self.w_alert.visible = False
        self.playback.set_stale(False)
        self._shown_files = f"{self.s.source} → {self.s.target_rig}"
        drawn = (self.s.package, self.s.source, self.s.target_rig)  # what _draw shows: the results and the files' names
        if self._drawn is not None and drawn[0] is self._drawn[0] and drawn[1:] == self._drawn[1:]:
            return  # shown already (e.g. a shared shot's change this page had drawn)
        self._draw()
        self._drawn = drawn

    _drawn = None  # (package, source, target) last drawn

    def _draw(self):
        snap = self.s.snapshot
        self.playback.draw(snap)
        self.curves.draw(snap)
        self.edits.set_shapes(snap["target_names"], snap["weights"])
        self.playback.draw_heat()
        self.edits.draw()
        self.playback.draw_regions()
        self.summary.draw(snap)
        self.contact.draw(snap)
        for name in self._tab_views:
            self._update_tab(name)
        self.edits.sync_value()  # the edit slider shows the new result's weight at this frame
        self.shape_controls.draw()
        self.sidebar.draw_timings(snap)

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
        app.sidebar.review_slot[:] = [review_start(review.SERVER, app.s.shot, on_open=app.open_shared)]
        if warm.is_warming(pn.state.curdoc):  # the first page built ahead (dashboard.warm): nothing to wake
            warm.POOL.apps[pn.state.curdoc.session_context.id] = app
        return app.layout
    from core.store import UnknownShot

    try:
        hub = review.SERVER.hub(sid)
    except (UnknownShot, ValueError):
        return pn.pane.Markdown(f"## No shot {html.escape(sid)!s}\n\n[Start or open a shot](?)", margin=30)
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
