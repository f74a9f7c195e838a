"""The page's shared-review controls: who is here, follow the presenter, notes at frames.

:class:`ReviewPanel` lays out what :class:`dashboard.review.Mirror` and :class:`~dashboard.review.Hub`
hold; :class:`NameBox` keeps the reviewer's name in the browser (asked once, ``localStorage``);
:func:`landing` is the page without a shot: create one, or open a recent one.
"""

from __future__ import annotations

import html
import time
from collections import Counter
from typing import Callable, Optional

import panel as pn
import param

from dashboard import session as sessions
from dashboard.lazy import lazy_card
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


class NotesList(pn.custom.JSComponent):
    """The shot's notes as one model: a row per note (who, where, the text; ↦ jumps to its frame,
    *resolve* / *reopen*), drawn in the browser from :attr:`notes`. A note is a property change,
    not new Panel rows: four Panel objects a note made every page of the shot add models, and a
    new list of children made Bokeh walk the whole document again (~40 ms a page per note; the
    load test's 14 notes cost 20 pages 12 s of server time). The text goes in as text (never
    HTML): a note cannot inject markup into another reviewer's page."""

    notes = param.List(default=[], doc="Rows shown, in order: {id, frame, frame_end, author, text, resolved}")
    action = param.Dict(default={}, doc="Set by the browser on a click: {op: 'jump'|'resolve'|'reopen', id, frame, n}")

    _esm = """
    export function render({ model, el }) {
      let clicks = 0;
      const box = document.createElement("div");
      box.className = "fr-notes";
      const button = (label, title, onclick) => {
        const b = document.createElement("button");
        b.type = "button"; b.textContent = label; b.title = title; b.className = "fr-note-button";
        b.addEventListener("click", onclick);
        return b;
      };
      const act = (op, n) => { model.action = { op, id: n.id || "", frame: n.frame || 0, n: ++clicks }; };
      const draw = () => {
        box.replaceChildren();
        const notes = model.notes || [];
        if (!notes.length) {
          const p = document.createElement("p"); p.className = "fr-muted"; p.textContent = "no notes yet";
          box.appendChild(p);
        }
        for (const n of notes) {
          const row = document.createElement("div"); row.className = "fr-note";
          const where = "frame " + n.frame + (n.frame_end ? "–" + n.frame_end : "");
          const text = document.createElement("span"); text.className = "fr-note-text";
          const who = document.createElement("b"); who.textContent = n.author || "?";
          text.append(who, " · " + where + ": " + (n.text || ""));
          if (n.resolved) text.style.textDecoration = "line-through";
          row.append(text, button("↦", "jump to " + where, () => act("jump", n)),
                     button(n.resolved ? "reopen" : "resolve", "", () => act(n.resolved ? "reopen" : "resolve", n)));
          box.appendChild(row);
        }
      };
      model.on("notes", draw);
      draw();
      el.appendChild(box);
    }
    """
    _stylesheets = ["""
    .fr-note { display: flex; align-items: center; gap: 4px; margin: 2px 0; font-size: 0.9em; }
    .fr-note-text { flex: 1; overflow-wrap: anywhere; }
    .fr-note-button { border: 1px solid #ccc; background: #f8f9fa; border-radius: 4px; padding: 2px 8px; cursor: pointer; }
    .fr-note-button:hover { background: #e9ecef; }
    .fr-muted { color: #777; font-style: italic; margin: 2px 0; }
    """]


def people_text(names, presenter: str = "") -> str:
    """The participants line: each name once, with how many pages carry it when more than one
    (two unnamed reviewers are "someone ×2", not one "someone"), and the presenter."""
    counts = Counter(names)
    listed = ", ".join(n if k == 1 else f"{n} ×{k}" for n, k in sorted(counts.items()))
    return (f"Here now: {html.escape(listed) or 'just you'}"
            + (f" · presenting: **{html.escape(presenter)}**" if presenter else ""))


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
        self.w_notes = NotesList(sizing_mode="stretch_width", margin=(5, 10))
        self.w_notes.param.watch(self._on_note_action, "action")
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
        self.w_people.object = people_text(self.hub.participants.values(), self.hub.presenter)

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

    def draw_notes(self):
        notes = self.notes()
        key = (repr(notes), self.w_show_resolved.value)
        if key == self._drawn:
            return  # unchanged: nothing to send
        self._drawn = key
        self.w_notes.notes = [
            {"id": n.get("id") or "", "frame": int(n.get("frame", 0)), "frame_end": n.get("frame_end"),
             "author": n.get("author", "") or "", "text": n.get("text", "") or "", "resolved": bool(n.get("resolved"))}
            for n in sorted(notes, key=lambda n: n.get("frame", 0))
            if self.w_show_resolved.value or not n.get("resolved")]
        if self.on_notes is not None:
            self.on_notes([n for n in notes if not n.get("resolved")])

    def _on_note_action(self, event) -> None:
        a = event.new or {}
        if a.get("op") == "jump":
            self.w_frame.value = int(min(max(int(a.get("frame", 0)), self.w_frame.start), self.w_frame.end))
        elif a.get("op") in ("resolve", "reopen") and a.get("id"):
            if self.mirror.set_note(str(a["id"]), a["op"] == "resolve"):
                self.draw_notes()

    def _export_bytes(self):
        import io

        buf = io.BytesIO()
        self.hub.store.export(self.hub.shot_id, buf)
        buf.seek(0)
        return buf

    def close(self):
        for w in self._hub_watchers:
            self.hub.param.unwatch(w)


def when_text(t, now: Optional[float] = None) -> str:
    """A store time (seconds since the epoch) as people read it, in the server's local time:
    "today 14:03", "yesterday 09:12", or "3 Dec 2026 14:03" (the recent shots showed the raw
    number). "" for a missing time."""
    if t is None or t == "":
        return ""
    lt = time.localtime(float(t))
    today = time.localtime(time.time() if now is None else now)
    clock = time.strftime("%H:%M", lt)
    days = (time.mktime(today[:3] + (12, 0, 0, 0, 0, -1)) - time.mktime(lt[:3] + (12, 0, 0, 0, 0, -1))) / 86400
    if round(days) == 0:
        return f"today {clock}"
    if round(days) == 1:
        return f"yesterday {clock}"
    return f"{lt.tm_mday} {time.strftime('%b %Y', lt)} {clock}"


def _start(server, make_shot: Callable, label: str, recent_n: int = 20, on_open: Optional[Callable] = None,
           import_box: bool = True) -> list:
    """The widgets that start a shared shot (from ``make_shot()``), import a review .zip (unless
    ``import_box`` is False: the page's own upload box takes it), or open a recent shot. A new or
    imported shot is ``on_open(shot_id)`` (the page joins it in place), else its page is opened in
    this tab."""
    from urllib.parse import quote

    status = pn.pane.Markdown("", sizing_mode="stretch_width")
    w_title = pn.widgets.TextInput(name="Title of the new shot", value="review", sizing_mode="stretch_width")
    w_new = pn.widgets.Button(name=label, button_type="primary", sizing_mode="stretch_width")

    def go(sid: str, said: str) -> None:
        status.object = f"{said}: [open it](?shot={quote(sid)})"
        if on_open is not None:
            on_open(sid)
        elif pn.state.location is not None:
            pn.state.location.search = f"?shot={quote(sid)}"
            pn.state.location.reload = True

    w_new.on_click(lambda event: go(server.create(make_shot(), title=w_title.value or "review", author=""), "Shot created"))
    rows = []
    for r in server.store.recent(recent_n):
        sid = r["id"] if isinstance(r, dict) else r[0]
        t = (r.get("title") if isinstance(r, dict) else "") or sid
        when = when_text(r.get("updated")) if isinstance(r, dict) else ""
        rows.append(f"- [{html.escape(str(t))}](?shot={quote(sid)}) <span class='fr-muted'>{html.escape(when)}</span>")
    recent = pn.pane.Markdown("**Recent shots**\n\n" + ("\n".join(rows) if rows else "*none yet*"), sizing_mode="stretch_width")
    if not import_box:
        return [w_title, w_new, status, recent]
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
    return [w_title, w_new, pn.pane.Markdown("…or open a review someone sent you (the .zip of *Download the review*):",
                                             css_classes=["fr-muted"]), import_box, status, recent]


def landing(server, make_shot: Callable, title: str = "face-retarget") -> pn.viewable.Viewable:
    """A page of its own for starting a shared shot from ``make_shot()``, or opening a recent one."""
    return pn.Column(
        pn.pane.Markdown(f"# {title}", css_classes=["fr-title"]),
        pn.pane.Markdown("Shared review: everyone with the link sees the same shot — settings, edits, the frame "
                         "and notes — and nothing is lost when the server restarts.", css_classes=["fr-muted"]),
        *_start(server, make_shot, "New shared shot (the bundled sample)"), width=520, margin=30)


def review_start(server, make_shot: Callable, on_open: Optional[Callable] = None) -> pn.Card:
    """The sidebar card of a page of its own (no ``?shot=``) on a review server, collapsed until
    used: share what this page shows as a new shot (``on_open(shot_id)``: the page joins it), or
    open a recent one. A review .zip goes into the page's one upload box."""
    return lazy_card(
        build=lambda: [
            pn.pane.Markdown("Share what this page shows: everyone with the link sees the same shot — settings, "
                             "edits, the frame and notes — and it is kept on the server. A review someone sent "
                             "you (.zip): drop it on the page.", css_classes=["fr-muted"]),
            *_start(server, make_shot, "New shared shot from this page", recent_n=8, on_open=on_open,
                    import_box=on_open is None)],
        title="Shared review", collapsed=True, sizing_mode="stretch_width")
