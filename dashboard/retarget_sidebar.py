"""The Retarget tab's sidebar: the files (capture, rigs, uploads), the solver's setting cards,
the auto-update switch and Apply, progress and status, the shot download and the timings.

The setting cards are generated from the stages' settings (core.stages declares which stages
belong to a card and which of their settings matter for the current method); every widget is
made once and only the ones that matter now are shown. The sidebar talks to the page through
its ``host`` (:class:`dashboard.app.DashboardApp`): ``host.s`` (the session), ``host.pipe``,
``host.mirror`` (a shared shot's, or None), ``host.notify``, ``host.refresh`` and
``host.changed`` (a setting or file changed: recompute when auto-update is on).
"""

from __future__ import annotations

import html
import io
import logging
import traceback
from pathlib import Path

import panel as pn
from panel.io.document import unlocked

from dashboard import session as sessions  # (MAX_UPLOAD is read when a page is made)
from dashboard import widgets
from dashboard.lazy import lazy_card
from dashboard.review import on_page
from dashboard.upload_guard import UploadGuard
from dashboard.widgets import param_widgets, ruled_heading

log = logging.getLogger("face_retarget.dashboard")

SIDEBAR_WIDTH = 330

#: what the one upload box takes: takes, rigs, .json (shot, marker layout, name map, controls), a review .zip
UPLOAD_ACCEPT = ".csv,.trc,.c3d,.glb,.gltf,.vrm,.usd,.usda,.usdc,.usdz,.json,.zip"
UPLOAD_HINT = ("Drop a file anywhere on the page, or choose it here: a take (.csv/.trc/.c3d), a rig (.glb/.vrm/.usd), "
               "a .json shot, marker layout or name map, or a review (.zip)")

#: the heading of the sidebar's timings, above the table draw_timings() puts under it
TIMINGS_HEAD = ruled_heading("Timings", "(server, last change)")

#: the sidebar's setting cards: (title, stage groups, collapsed); which stages belong to a group
#: and which of their settings show is declared by the stages (core.stages), not here
SIDEBAR_CARDS = [("Solver", ("solve",), False), ("Source & calibration", ("source", "calibrate"), True),
                 ("Actor personalisation (Ribera 2017)", ("personalize",), True)]


def visible_settings(stage, cfg) -> list:
    """The settings of ``stage`` a user can change now: the ones that matter in this
    configuration (``stage.declared``) and are not decided by it (``stage.derived``: e.g. the
    correspondence under ``auto``) nor of no use in it (``stage.hidden``: bounds a method
    ignores), without the edit lists and tables (they have their own controls) — for an
    inactive stage (e.g. segmentation with a global method) none."""
    if not stage.active(cfg):
        return []
    shown = set(stage.declared(cfg)) - set(stage.derived(cfg)) - set(stage.hidden(cfg))
    return [n for n in stage.tunable_names() if n in shown]


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


def shown_settings(pipe) -> tuple:
    """Which settings of which stages the sidebar's cards show now (compared to know whether a
    change needs the cards redrawn)."""
    cfg = pipe.config()  # one snapshot for the three cards (a deep copy of every setting)
    return tuple(tuple((st.stage_name, tuple(n)) for st, n in stage_params(pipe, groups, cfg)) for _, groups, _ in SIDEBAR_CARDS)


class RetargetSidebar(pn.viewable.Viewer):
    """The sidebar of the Retarget tab (files, solver settings, status, shot download, timings).

    ``marker_card``: the "Markers on the target rig" card, placed under the uploads.
    ``layout`` is the sidebar's column; the page puts its Shared review card into ``review_slot``."""

    def __init__(self, host, marker_card, **params):
        super().__init__(**params)
        self.host = host
        self.s, self.pipe = host.s, host.pipe
        self.doc = pn.state.curdoc  # the page's document (None outside a server)
        s = self.s
        self.w_source = pn.widgets.Select.from_param(s.param.source, name="Source performance", sizing_mode="stretch_width")
        self.w_source_rig = pn.widgets.Select.from_param(s.param.source_rig, name="Source rig (for weight curves)", sizing_mode="stretch_width")
        self.w_target = pn.widgets.Select.from_param(s.param.target_rig, name="Target rig", sizing_mode="stretch_width")
        # one upload box for every kind of file, and the whole page a drop target for it: each file
        # goes where it belongs by its content (Session.upload), a review .zip to the review store
        self.w_upload = pn.widgets.FileInput(accept=UPLOAD_ACCEPT, multiple=False, sizing_mode="stretch_width")
        self.w_upload.param.watch(self._on_upload, ["value", "filename"], onlychanged=False)
        # a file over the limit is refused in the browser with a message (sent whole, over twice
        # the limit it would close the page's connection: dashboard.upload_guard); a review holds
        # the files it uses: as large as the websocket takes
        self.w_upload_box = UploadGuard(self.w_upload, max_bytes=sessions.MAX_UPLOAD, page_drop=True,
                                        max_bytes_by_suffix={".zip": sessions.largest_message_file()},
                                        sizing_mode="stretch_width", on_refused=self._refused, on_start=self._starting)
        #: where the page puts its Shared review card (below the task, the uploads and the markers)
        self.review_slot = pn.Column(sizing_mode="stretch_width", margin=0)
        self.settings_box = pn.Column(sizing_mode="stretch_width")
        self.w_auto = pn.widgets.Toggle.from_param(s.param.auto_update, name="Auto-update on every change", button_type="light", sizing_mode="stretch_width")
        self.w_apply = pn.widgets.Button(name="Apply", button_type="primary", sizing_mode="stretch_width")
        self.w_apply.on_click(lambda e: host.refresh())
        self.w_progress = pn.indicators.Progress(value=0, max=100, sizing_mode="stretch_width", height=12, bar_color="primary")
        # the texts every change rewrites on every page of a shot: updates send the text alone
        self.w_status = widgets.Markdown("", css_classes=["fr-status"], sizing_mode="stretch_width")
        self.w_timings = widgets.HTML(TIMINGS_HEAD, sizing_mode="stretch_width")
        self.w_shot = pn.widgets.FileDownload(callback=self._shot_bytes, filename="shot.json", label="Download shot",
                                              button_type="light", sizing_mode="stretch_width")
        s.param.watch(self._on_busy, ["busy", "progress", "status"])
        self._shown = None
        groups = {g for _, gs, _ in SIDEBAR_CARDS for g in gs}
        for st in self.pipe.stages.values():
            if type(st).group in groups:
                # after the review mirror's watcher (precedence 0): other pages hear of a change
                # before this page spends time recomputing it
                st.param.watch(self._on_setting, st.setting_names(), precedence=1)
        self._build_settings()
        # the task first: what to retarget onto what, and how; then the files of one's own, the
        # markers, the shared review; the shot file and the timings last
        self.layout = pn.Column(
            pn.pane.Markdown("# face-retarget", css_classes=["fr-title"]),
            pn.pane.Markdown("Transfer a captured face performance onto another character's blendshape rig. "
                             "Pick a capture and a target, press play, tune the solver.", css_classes=["fr-muted"]),
            self.w_source, self.w_source_rig, self.w_target,
            pn.pane.HTML(ruled_heading("Solver"), sizing_mode="stretch_width"),
            self.settings_box,
            self.w_auto, self.w_apply, self.w_progress, self.w_status,
            pn.pane.HTML(ruled_heading("Your files"), sizing_mode="stretch_width"),
            pn.pane.Markdown(UPLOAD_HINT, css_classes=["fr-muted"], margin=(0, 10)),
            self.w_upload_box,
            marker_card,
            self.review_slot,
            pn.pane.Markdown("Everything this page shows (files, settings, edits) is one shot file: download it to "
                             "reproduce the result with `face-retarget retarget --shot shot.json`, upload it to come back.",
                             css_classes=["fr-muted"], margin=(0, 10)),
            self.w_shot,
            self.w_timings,
            width=SIDEBAR_WIDTH, sizing_mode="stretch_height", scroll=True,
        )

    def __panel__(self):
        return self.layout

    # -- files ------------------------------------------------------------------------------
    def _refused(self, name: str, size: int) -> None:
        if Path(name).suffix.lower() == ".zip":
            self.host.notify("error", sessions.too_large(Path(name).name, size, sessions.largest_message_file(), " for a review"))
        else:
            self.host.notify("error", sessions.too_large(Path(name).name, size))

    def _starting(self, name: str) -> None:
        """The browser starts sending a file (:class:`dashboard.upload_guard.UploadGuard` says so
        before the file's content): the previous file's note goes, and this name is awaited."""
        self._expected = Path(str(name).replace("\\", "/")).name
        self.host.clear_note()

    _expected = None  # the name of the file the browser said it is sending, until it is read

    def _on_upload(self, *events):
        """The browser sends an upload's content, then its name (then its type), as separate
        messages, which a loaded server may read apart: content that came before its name waits for
        it, or it would be read under the previous file's name (its note shown again). A page
        without the guard's script (no name announced) reads whatever came."""
        name = Path(str(self.w_upload.filename or "").replace("\\", "/")).name
        if self._expected is not None and name != self._expected:
            return  # the name comes next
        self._expected = None
        self._take_upload()

    def _take_upload(self):
        if not self.w_upload.filename:
            return
        name = Path(str(self.w_upload.filename).replace("\\", "/")).name
        data = self.w_upload.value or b""
        if name.lower().endswith(".zip"):  # a review (shot, notes, history and its files): the page opens it
            self.host.open_review_archive(name, data)
            return
        try:
            # an empty file arrives as no value at all: Session.upload says it is empty
            up = self.s.upload(name, data)
            if not self.s.error:  # selecting it may already have failed to load: keep that error in view
                self.host.notify("info", up.message, rig=up.label if up.kind == "rig" else None)
        except ValueError as e:
            self.host.notify("error", str(e))
        except Exception as e:  # a reader's bug must not leave the page silent: the trace goes to the log
            log.warning("upload %s failed: %s", name, traceback.format_exc())
            self.host.notify("error", f"{name} could not be read ({type(e).__name__}); "
                                      "if the file opens elsewhere, please report it")

    def _shot_bytes(self):
        return io.BytesIO(self.s.shot().to_json().encode("utf-8"))

    # -- status -----------------------------------------------------------------------------
    def _on_busy(self, *events):
        self.w_progress.value = self.s.progress
        self.w_status.object = html.escape(self.s.status)

    def draw_timings(self, snap: dict) -> None:
        """The table of the last change's stage timings (server side)."""
        rows = "".join(f"<tr><td>{k}</td><td style='text-align:right'>{v:.1f} ms</td></tr>" for k, v in snap["timings"].items() if v > 0.05)
        self.w_timings.object = (f"{TIMINGS_HEAD}<table style='font-size:0.85em;width:100%'>{rows}<tr><td><b>server total</b></td>"
                                 f"<td style='text-align:right'><b>{snap['server_ms']:.1f} ms</b></td></tr></table>")

    # -- settings ---------------------------------------------------------------------------
    def _on_setting(self, *events):
        mirror = self.host.mirror
        if mirror is not None and mirror._applying:
            return  # another page's change: the page shows the widgets first, then recomputes
        # a new method (or switch) shows its own widgets before the (possibly long) recompute starts
        self.follow_settings()
        self.host.changed()

    def follow_settings(self) -> None:
        """Show the settings that matter now, if that is not what the cards show."""
        if shown_settings(self.pipe) != self._shown:
            self.show_settings()

    def _build_settings(self):
        """The setting cards, generated from the stages' settings: every widget is made once, and
        only those that matter for the current method and switches are visible
        (:meth:`show_settings`) — a method change toggles visibility instead of sending new
        widgets to the browser (that rebuild took seconds to reach the other pages of a review)."""
        rom = {"(the source itself)": ""} | dict(self.s.files["performances"])
        extra = {"rom": {"type": pn.widgets.Select, "options": rom}}
        cfg = self.pipe.config()
        cards, self.setting_panes, self.setting_cards = [], [], []

        def panes_of(groups):
            panes = []
            for st in self.pipe.stages.values():
                if type(st).group not in groups:
                    continue
                names = st.tunable_names()
                if not names:
                    continue
                pane = pn.Param(st, parameters=names, widgets=param_widgets(st, names, extra), show_name=False,
                                sizing_mode="stretch_width")
                for n in names:  # the handle _set_visible hides it by
                    w = pane._widgets[n]
                    w.css_classes = [*w.css_classes, f"fr-setting-{n}"]
                panes.append(pane)
                self.setting_panes.append((st, pane))
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
                self.setting_cards.append((card, groups))
                cards.append(card)
        self.settings_box[:] = cards
        self.show_settings(cfg)

    def show_settings(self, cfg=None):
        """Show the settings that matter now (:func:`visible_settings`), hide the others — in one
        message to the browser (each visibility change sent alone re-lays the page out: ~0.3 s
        each in Chromium here)."""
        with on_page(self.doc):
            self._set_visible(cfg or self.pipe.config())

    def _set_visible(self, cfg):
        # hidden by one stylesheet per stage, not by each widget's `visible`: BokehJS lays the
        # whole page out again, synchronously, for every change of a layout's `visible`,
        # `stylesheets` or `css_classes` (LayoutDOMView.invalidate_layout: 0.15-0.2 s each in
        # Chromium here; a method change toggles ten widgets). A stage with nothing to show hides
        # itself in the same stylesheet (`:host`), not by `visible` on top: one change per stage
        # (a method switch was three relayouts, a 0.35-0.46 s long task on every page)
        for st, pane in self.setting_panes:
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
        for card, groups in self.setting_cards:  # its panes may not be made yet
            card.visible = any(visible_settings(st, cfg) for st in self.pipe.stages.values() if type(st).group in groups)
        self._shown = shown_settings(self.pipe)

    def resend_settings(self, names) -> None:
        """Send this page's widgets of ``names`` their values again (the shot took the page's
        change). A remote change that reached the browser after the user moved a widget but
        before the server read that move leaves the browser showing the remote value while the
        shot has the user's; Bokeh sends nothing for a value the server's model already has, so
        the change is re-announced."""
        with unlocked():  # may run in Panel's lock-free event task (see dashboard.curves._page_safe)
            for st, pane in self.setting_panes:
                for n in names:
                    w = pane._widgets.get(n)
                    if w is None or getattr(st, n) != w.value:
                        continue
                    for model, _ in list(w._models.values()):
                        prop = "active" if hasattr(model, "active") and not hasattr(model, "value") else "value"
                        if hasattr(model, prop) and model.document is not None:
                            v = getattr(model, prop)
                            model.trigger(prop, v, v)
