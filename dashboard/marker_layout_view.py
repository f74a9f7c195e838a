"""The sidebar's "Markers on the target rig" card: the 41 markers the solvers compare both faces
at, for a rig without a layout of its own (a user's own character): place them automatically
(:meth:`dashboard.session.Session.place_markers`, on a worker thread with progress; on the source
rig too when it has none), move any
that landed badly by clicking a marker on the target view and then its new place
(:meth:`dashboard.session.Session.move_marker`; one move, then move mode is off again, and the
last move can be undone), download the layout.

It talks to the page through its ``host`` (:class:`dashboard.app.DashboardApp`): ``host.s``,
``host.refresh`` and ``host.playback`` (the target view it picks on).
"""

from __future__ import annotations

import html
import io
import logging
import threading
import time

import numpy as np
import panel as pn

from dashboard.lazy import lazy_card

log = logging.getLogger("face_retarget.dashboard")


class MarkerLayoutView(pn.viewable.Viewer):
    """The marker card; its widgets are made on first use (a page that never opens the card never
    pays for them)."""

    def __init__(self, host, **params):
        super().__init__(**params)
        self.host = host
        self.s = host.s
        self.report = None  # the last automatic placement's report
        self._pick = None  # the marker picked to move
        self._last_move = None  # (name, vertices, weights) the last moved marker had before
        self.w_place = self.w_move = self.w_undo = self.w_download = self.w_progress = self.w_info = None
        self.card = lazy_card(build=self._widgets, title="Markers on the target rig", collapsed=True,
                              sizing_mode="stretch_width")

    def __panel__(self):
        return self.card

    def _widgets(self) -> list:
        """The card's contents, made on first use (from then on ``w_place`` & co. exist)."""
        if self.w_place is None:
            self.w_place = pn.widgets.Button(name=self._place_label(), button_type="primary", sizing_mode="stretch_width")
            self.w_place.on_click(lambda e: self.place())
            self.w_move = pn.widgets.Toggle(name="Move markers: click a marker, then where it goes",
                                            button_type="light", sizing_mode="stretch_width")
            self.w_move.param.watch(lambda e: self._move_mode(), "value")
            self.w_undo = pn.widgets.Button(name="Undo the last marker move", button_type="light", disabled=True,
                                            sizing_mode="stretch_width")
            self.w_undo.on_click(lambda e: self.undo_move())
            self.w_download = pn.widgets.FileDownload(callback=self._layout_bytes, filename="layout.json",
                                                      label="Download layout", button_type="light",
                                                      sizing_mode="stretch_width")
            self.w_progress = pn.indicators.Progress(value=0, max=100, height=10, sizing_mode="stretch_width",
                                                     visible=False)
            self.w_info = pn.pane.Markdown("", sizing_mode="stretch_width", css_classes=["fr-status"])
        return [pn.pane.Markdown("The 41 markers the solvers compare both faces at. A rig of your own needs them "
                                 "once: place them automatically, then move any that landed badly.",
                                 css_classes=["fr-muted"]),
                self.w_place, self.w_progress, self.w_info, self.w_move, self.w_undo, self.w_download]

    def _missing(self) -> list:
        """The rigs ("target", "source") that have no markers yet."""
        return [role for role in ("target", "source") if self.s.missing_layout(role)]

    def _place_label(self) -> str:
        return "Place markers automatically" if self._missing() else "Place the markers again (automatically)"

    def follow(self) -> None:
        """After a recompute: the card opens when a rig (the target, or the source rig) needs
        markers, and the place button says whether they are there."""
        self.card.collapsed = not self._missing() and self.card.collapsed
        if self.w_place is not None:
            self.w_place.name = self._place_label()

    def moving(self) -> bool:
        """Whether the "move markers" toggle is on (off while its card was never opened)."""
        return bool(self.w_move is not None and self.w_move.value)

    def _layout_bytes(self):
        try:
            return io.BytesIO(self.s.layout_json())
        except Exception as e:  # noqa: BLE001 - shown on the page
            self.host.notify("error", self.s.readable(e))
            return None

    def place(self, block: bool = False, roles=None) -> None:
        """Place the markers automatically (a worker thread unless ``block``), with progress, on
        ``roles`` ("target", "source"; default: the rigs that have none, else the target again);
        the page recomputes with them."""
        self._widgets()  # (called from code, the card may never have been opened)
        roles = list(roles or self._missing() or ["target"])

        def job():
            t0 = time.perf_counter()
            self.w_progress.param.update(visible=True, value=5)

            def prog(f, m):
                self.w_progress.value = int(100 * min(max(f, 0.0), 1.0))
                self.w_info.object = html.escape(f"{m} ({time.perf_counter() - t0:.0f} s)")

            try:
                said = []
                for role in roles:
                    report = self.s.place_markers(progress=prog, role=role)
                    said.append(("" if roles == ["target"] else f"{role.capitalize()} rig: ") + report["message"])
                self.w_info.object = html.escape(" ".join(said))
                self.report = report
                # the redraw touches Bokeh models (the curve plot), which only the document's own
                # thread may change: hand it to the event loop (auto-update off: Apply recomputes)
                if not self.s.auto_update:
                    pass
                elif doc is not None and not block:
                    doc.add_next_tick_callback(self.host.refresh)
                else:
                    self.host.refresh()
            except Exception as e:  # noqa: BLE001 - shown on the page
                log.warning("placing markers failed", exc_info=True)
                self.w_info.object = "⚠ " + html.escape(self.s.readable(e))
            finally:
                self.w_progress.visible = False

        doc = pn.state.curdoc
        block = block or doc is None  # outside a server (a notebook, a test): at once
        self.w_place.disabled = True
        try:
            if block:
                job()
            else:
                threading.Thread(target=job, name="place-markers", daemon=True).start()
        finally:
            self.w_place.disabled = False

    def _move_mode(self):
        v = self.host.playback.target_viewer
        if v is None:
            return
        v.pick_mode = "vertex" if self.moving() else "off"
        self._pick = None
        if self.moving():
            self.w_info.object = "Click a marker on the target, then the place it should be."

    def on_target_pick(self, event):
        """A click on the target view: the first picks a marker, the second moves it there."""
        p = event.new
        if not p or not self.moving():
            return
        snap = self.s.snapshot
        layout, rig = snap["target_layout"], snap["target_rig"]
        viewer = self.host.playback.target_viewer
        v = int(p["vertex"])
        if self._pick is None:
            pts = layout.points(rig.neutral)
            i = int(np.argmin(np.linalg.norm(pts - rig.neutral[v], axis=1)))
            if np.linalg.norm(pts[i] - rig.neutral[v]) > 0.05 * rig.size:
                self.w_info.object = "No marker there: click on one of the markers (the small spheres)."
                return
            self._pick = layout.names[i]
            viewer.set_highlight([v])
            self.w_info.object = f"Marker **{html.escape(self._pick)}**: now click where it should be."
            return
        name, self._pick = self._pick, None
        viewer.set_highlight([])
        was = self.s.move_marker(name, v)
        self._last_move = (name, *was)
        self.w_undo.disabled = False
        self.w_move.value = False  # one move per switch: a stray click later moves nothing
        self.w_info.object = f"Marker **{html.escape(name)}** moved to vertex {v}; the result follows."
        self.host.playback.forget_target()  # the markers moved: a new target view
        self.host.refresh()

    def undo_move(self) -> None:
        """Put the last moved marker back where it was (one step: the undo is not itself undone)."""
        if self._last_move is None:
            return
        name, vertices, weights = self._last_move
        self._last_move = None
        self.w_undo.disabled = True
        self.s.move_marker(name, vertices, weights)
        self.w_info.object = f"Marker **{html.escape(name)}** is back where it was; the result follows."
        self.host.playback.forget_target()
        self.host.refresh()
