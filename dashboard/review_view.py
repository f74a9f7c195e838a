"""The page's shared-review controls: who is here, follow the presenter, notes at frames.

:class:`ReviewPanel` lays out what :class:`dashboard.review.Mirror` and :class:`~dashboard.review.Hub`
hold; :class:`NameBox` keeps the reviewer's name in the browser (asked once, ``localStorage``);
:func:`landing` is the page without a shot: create one, or open a recent one.
"""

from __future__ import annotations

import html
from typing import Callable, Optional

import panel as pn
import param

from dashboard import session as sessions
from dashboard.upload_guard import UploadGuard
from dashboard.widgets import ruled_heading


class NameBox(pn.custom.JSComponent):
    """The reviewer's name, kept in the browser's ``localStorage`` (asked once, then remembered)."""

    value = param.String(default="", doc="The name (empty until the browser said or the user typed it)")

    _esm = """
    export function render({ model, el }) {
      const key = "face-retarget-reviewer";
      const box = document.createElement("input");
      box.type = "text"; box.placeholder = "your name (kept in this browser)";
      box.style.width = "100%"; box.style.padding = "4px"; box.style.boxSizing = "border-box";
      box.className = "fr-name";
      const saved = window.localStorage.getItem(key) || "";
      box.value = model.value || saved;
      if (saved && !model.value) { model.value = saved; }
      box.addEventListener("change", () => {
        const v = box.value.trim(); window.localStorage.setItem(key, v); model.value = v;
      });
      model.on("value", () => { if (box.value !== model.value) box.value = model.value; });
      el.appendChild(box);
    }
    """


class ReviewPanel:
    """Participants, presenter/follow, notes (see the module docstring).

    Parameters
    ----------
    mirror : dashboard.review.Mirror
    frame_widget, play_widget : the page's frame slider and play toggle
    time_of : frame -> seconds (for the notes' times)
    on_notes : called with the notes after they change (e.g. to mark them on the curve plot)
    """

    def __init__(self, mirror, frame_widget, play_widget, time_of: Callable, on_notes: Optional[Callable] = None):
        self.mirror, self.hub = mirror, mirror.hub
        self._rows: dict = {}  # note state -> its row, kept between redraws (draw_notes)
        self.w_frame, self.w_play, self.time_of, self.on_notes = frame_widget, play_widget, time_of, on_notes
        self.w_name = NameBox(value=mirror.name if mirror.name != "someone" else "", sizing_mode="stretch_width", height=34)
        self.w_name.param.watch(self._on_name, "value")
        self.w_people = pn.pane.Markdown("", sizing_mode="stretch_width", css_classes=["fr-status"])
        self.w_present = pn.widgets.Toggle(name="Present: the others follow my frame", button_type="light",
                                           sizing_mode="stretch_width")
        self.w_follow = pn.widgets.Toggle(name="Follow the presenter", value=True, button_type="light", sizing_mode="stretch_width")
        # the link and the name's heading in one pane (each Panel object costs every page ~30 KB)
        self.w_link = pn.pane.Markdown(f"<span style='color:#666;font-size:0.86em'>Share this page: `?shot={self.hub.shot_id}`</span>\n\n"
                                       "**Your name**", sizing_mode="stretch_width")
        self.w_note = pn.widgets.TextAreaInput(placeholder="a note at this frame…", height=60, sizing_mode="stretch_width")
        self.w_note_range = pn.widgets.IntInput(name="…until frame (0: this frame only)", value=0, start=0,
                                                sizing_mode="stretch_width")
        self.w_add_note = pn.widgets.Button(name="Add note at this frame", button_type="primary", sizing_mode="stretch_width")
        self.w_add_note.on_click(lambda e: self.add_note())
        self.w_show_resolved = pn.widgets.Toggle(name="Show resolved notes", value=False, button_type="light",
                                                 sizing_mode="stretch_width")
        self.w_show_resolved.param.watch(lambda e: self.draw_notes(), "value")
        self.w_notes = pn.Column(sizing_mode="stretch_width")
        # the whole review as one file (shot, notes, history and the files it uses): mail it, keep it
        # in version control, open it on another server's landing page
        self.w_export = pn.widgets.FileDownload(callback=self._export_bytes, filename=f"review-{self.hub.shot_id}.zip",
                                                label="Download the review (.zip)", button_type="light",
                                                sizing_mode="stretch_width")
        self.card = pn.Card(
            self.w_link, self.w_name, self.w_people, self.w_present, self.w_follow,
            pn.pane.HTML(ruled_heading("Notes"), sizing_mode="stretch_width"),
            self.w_note, self.w_note_range, self.w_add_note, self.w_show_resolved, self.w_notes, self.w_export,
            title="Shared review", collapsed=False, sizing_mode="stretch_width")
        doc = mirror.doc
        def run(f):  # a dormant page (dashboard.warm) draws the people and the frame when it wakes
            if mirror.dormant:
                return
            if doc is not None:
                doc.add_next_tick_callback(f)
            else:
                f()

        self._hub_watchers = [
            self.hub.param.watch(lambda e: run(self.draw_people), ["participants", "presenter"]),
            self.hub.param.watch(lambda e: run(self._follow), ["frame", "playing"]),
        ]
        self.w_frame.param.watch(self._on_own_frame, "value")
        self.w_play.param.watch(self._on_own_frame, "value")
        self.draw_people()
        self.draw_notes()

    # -- people ---------------------------------------------------------------------------------
    def _on_name(self, event):
        self.mirror.name = event.new or "someone"
        self.hub.join(self.mirror.session_id, self.mirror.name)

    def draw_people(self):
        names = sorted(set(self.hub.participants.values()))
        pres = self.hub.presenter
        self.w_people.object = (f"Here now: {html.escape(', '.join(names)) or 'just you'}"
                                + (f" · presenting: **{html.escape(pres)}**" if pres else ""))

    # -- presenter and followers ----------------------------------------------------------------
    def _on_own_frame(self, *events):
        if self._following:
            return
        if self.w_present.value:
            self.hub.presenter = self.mirror.name
            self.hub.seek(int(self.w_frame.value), bool(self.w_play.value), self.mirror.name)

    _following = False

    def _follow(self):
        if not self.w_follow.value or self.w_present.value or self.hub.presenter in ("", self.mirror.name):
            return
        self._following = True
        try:
            if int(self.w_frame.value) != self.hub.frame:
                self.w_frame.value = int(min(self.hub.frame, self.w_frame.end))
            if bool(self.w_play.value) != self.hub.playing:
                self.w_play.value = self.hub.playing
        finally:
            self._following = False

    # -- notes ----------------------------------------------------------------------------------
    def add_note(self) -> bool:
        text = (self.w_note.value or "").strip()
        if not text:
            return False
        f = int(self.w_frame.value)
        end = int(self.w_note_range.value) or None
        ok = self.mirror.add_note(f, text, end if end is not None and end > f else None)
        if ok:
            self.w_note.value = ""
            self.draw_notes()  # this page's own note shows at once (the others get it from the hub)
        return ok

    def notes(self) -> list:
        return list(self.mirror.session.pipeline.notes)

    _drawn = None

    def _note_row(self, n: dict):
        f, end = int(n.get("frame", 0)), n.get("frame_end")
        where = f"frame {f}" + (f"–{end}" if end else "")
        jump = pn.widgets.Button(name="↦", width=34, button_type="light", description=f"jump to {where}")
        jump.on_click(lambda e, f=f: setattr(self.w_frame, "value", f))
        done = bool(n.get("resolved"))
        tick = pn.widgets.Button(name="reopen" if done else "resolve", width=70, button_type="light")
        tick.on_click(lambda e, nid=n.get("id"), done=done: self.mirror.set_note(nid, not done) and self.draw_notes())
        text = f"**{html.escape(n.get('author', '') or '?')}** · {where}: {html.escape(n.get('text', ''))}"
        return pn.Row(pn.pane.Markdown(("~~" + text + "~~") if done else text, margin=(2, 5), sizing_mode="stretch_width"),
                      jump, tick, sizing_mode="stretch_width")

    def draw_notes(self):
        notes = self.notes()
        key = (repr(notes), self.w_show_resolved.value)
        if key == self._drawn:
            return  # unchanged: no new rows for the browser to lay out
        self._drawn = key
        rows, cache = [], {}
        for n in sorted(notes, key=lambda n: n.get("frame", 0)):
            if n.get("resolved") and not self.w_show_resolved.value:
                continue
            # a row is made once per note state and kept: a new note sends the browser one new
            # row, not the whole list again (20 pages x 100 notes made the server crawl)
            k = (n.get("id"), bool(n.get("resolved")), n.get("text"), n.get("frame"), n.get("frame_end"), n.get("author"))
            cache[k] = self._rows.get(k) or self._note_row(n)
            rows.append(cache[k])
        self._rows = cache
        self.w_notes[:] = rows or [pn.pane.Markdown("*no notes yet*", css_classes=["fr-muted"])]
        if self.on_notes is not None:
            self.on_notes([n for n in notes if not n.get("resolved")])

    def _export_bytes(self):
        import io

        buf = io.BytesIO()
        self.hub.store.export(self.hub.shot_id, buf)
        buf.seek(0)
        return buf

    def close(self):
        for w in self._hub_watchers:
            self.hub.param.unwatch(w)


def _start(server, make_shot: Callable, label: str, recent_n: int = 20) -> list:
    """The widgets that start a shared shot (from ``make_shot()``), import a review .zip, or open a
    recent shot: a new shot's page is opened in this tab."""
    from urllib.parse import quote

    status = pn.pane.Markdown("", sizing_mode="stretch_width")
    w_title = pn.widgets.TextInput(name="Title of the new shot", value="review", sizing_mode="stretch_width")
    w_new = pn.widgets.Button(name=label, button_type="primary", sizing_mode="stretch_width")

    def go(sid: str, said: str) -> None:
        status.object = f"{said}: [open it](?shot={quote(sid)})"
        if pn.state.location is not None:
            pn.state.location.search = f"?shot={quote(sid)}"
            pn.state.location.reload = True

    w_new.on_click(lambda event: go(server.create(make_shot(), title=w_title.value or "review", author=""), "Shot created"))
    w_import = pn.widgets.FileInput(accept=".zip", sizing_mode="stretch_width")

    def import_(*events):
        if not w_import.value:
            return
        import io

        try:
            sid = server.store.import_(io.BytesIO(w_import.value), author="import")
        except ValueError as e:  # named, plain words (core.store)
            status.object = f"**Error:** {html.escape(str(w_import.filename))}: {html.escape(str(e))}"
            return
        go(sid, "Imported")

    w_import.param.watch(import_, "value")

    def refused(name: str, size: int) -> None:
        status.object = f"**Error:** {html.escape(sessions.too_large(name, size, sessions.largest_message_file(), ' for a review'))}"

    # a review holds the files it uses: as large as the websocket takes
    import_box = UploadGuard(w_import, max_bytes=sessions.largest_message_file(), on_refused=refused,
                             sizing_mode="stretch_width")
    rows = []
    for r in server.store.recent(recent_n):
        sid = r["id"] if isinstance(r, dict) else r[0]
        t = (r.get("title") if isinstance(r, dict) else "") or sid
        when = r.get("updated", "") if isinstance(r, dict) else ""
        rows.append(f"- [{html.escape(str(t))}](?shot={quote(sid)}) <span class='fr-muted'>{html.escape(str(when))}</span>")
    recent = pn.pane.Markdown("**Recent shots**\n\n" + ("\n".join(rows) if rows else "*none yet*"), sizing_mode="stretch_width")
    return [w_title, w_new, pn.pane.Markdown("…or open a review someone sent you (the .zip of *Download the review*):",
                                             css_classes=["fr-muted"]), import_box, status, recent]


def landing(server, make_shot: Callable, title: str = "face-retarget") -> pn.viewable.Viewable:
    """A page of its own for starting a shared shot from ``make_shot()``, or opening a recent one."""
    return pn.Column(
        pn.pane.Markdown(f"# {title}", css_classes=["fr-title"]),
        pn.pane.Markdown("Shared review: everyone with the link sees the same shot — settings, edits, the frame "
                         "and notes — and nothing is lost when the server restarts.", css_classes=["fr-muted"]),
        *_start(server, make_shot, "New shared shot (the bundled sample)"), width=520, margin=30)


def review_start(server, make_shot: Callable) -> pn.Card:
    """The sidebar card of a page of its own (no ``?shot=``) on a review server: share what this
    page shows as a new shot, import a review, or open a recent one."""
    return pn.Card(
        pn.pane.Markdown("Share what this page shows: everyone with the link sees the same shot — settings, "
                         "edits, the frame and notes — and it is kept on the server.", css_classes=["fr-muted"]),
        *_start(server, make_shot, "New shared shot from this page", recent_n=8),
        title="Shared review", collapsed=False, sizing_mode="stretch_width")
