"""Shared review: one shot, many pages, nothing lost.

A review session is a shot in the review store (:mod:`core.store`, SQLite under ``--data-dir``)
with an unguessable id; ``/?shot=<id>`` joins it. The server keeps one :class:`Hub` per open
shot — the shot as last committed, its version, who is looking, the presenter's frame and
playback — and each page one :class:`Mirror`: the page's own pipeline (its settings objects are
the page's widgets) kept equal to the hub's shot.

* A page's change (a setting, an edit, undo/redo, a note, a seek while presenting) becomes a
  change dict sent to :meth:`Hub.apply`, which writes it to SQLite *before* anyone hears of it
  (:meth:`core.store.Store.apply`: serialised by the version the page saw; a stale change is
  rebased or refused with a message, never dropped). Then every other page of the shot is told.
* A page told of a new version pulls the shot and applies what differs to its own pipeline on
  its own document's event loop (Bokeh models belong to one document), then redraws — the
  stages are cache hits: the page that made the change computed them, and the cache is shared.
* Widgets are never bound to the hub itself (PANEL_NOTES: that leaks a watcher per closed
  session); each mirror has one watcher on its hub, removed when its session is destroyed.

Nothing numeric here: choosing what to send and applying what came back.
"""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
import time
from typing import Optional

import param

log = logging.getLogger("face_retarget.review")


class Hub(param.Parameterized):
    """The server's one copy of an open shot (see the module docstring)."""

    version = param.Integer(default=0, doc="The version last committed (bumped on every change)")
    frame = param.Integer(default=0, doc="The presenter's frame")
    playing = param.Boolean(default=False, doc="The presenter's playback")
    presenter = param.String(default="", doc="Who presents (the pages that follow follow them)")
    participants = param.Dict(default={}, doc="session id -> name of the pages looking at the shot")
    last_change = param.Dict(default={}, doc="The last change applied: {version, author, kind, at}")

    def __init__(self, store, shot_id: str, **params):
        super().__init__(**params)
        self.store, self.shot_id = store, shot_id
        self.shot, self.version = store.get(shot_id)
        self.frame = int(self.shot.frame)
        self._lock = threading.RLock()

    def apply(self, change: dict, base_version: int, author: str):
        """Commit ``change`` (made against ``base_version``) and tell every page; returns the
        :class:`core.store.Applied`. Raises :class:`core.store.Conflict` for a refused change."""
        with self._lock:
            a = self.store.apply(self.shot_id, change, base_version, author)
            if a.change is not None:
                self.shot = a.shot
                self.last_change = {"version": a.version, "author": author, "kind": change.get("kind"), "at": time.time(),
                                    "rebased": bool(a.rebased)}
                self.version = a.version  # watchers (the mirrors) run here
            return a

    def seek(self, frame: int, playing: bool, author: str) -> None:
        """The presenter's cursor: shared at once in memory, and written to the store while not
        playing (a frame during playback is a moving cursor; the frame it stops on is kept)."""
        self.param.update(frame=int(frame), playing=bool(playing))
        if not playing:
            try:
                self.apply({"kind": "frame", "frame": int(frame)}, self.version, author)
            except ValueError:  # a cursor never conflicts (last writer wins); a failure is not the user's
                log.warning("could not store the review frame", exc_info=True)

    def join(self, session_id: str, name: str) -> None:
        with self._lock:
            self.participants = {**self.participants, session_id: name or "someone"}
            try:
                self.store.touch(self.shot_id, name or "someone")
            except ValueError:
                pass

    def leave(self, session_id: str) -> None:
        with self._lock:
            p = dict(self.participants)
            p.pop(session_id, None)
            self.participants = p


class ReviewServer:
    """The store and the hubs of one server process (``face-retarget serve --data-dir``)."""

    def __init__(self, data_dir=None, max_upload_mb: float = 200.0):
        from core.store import Store, data_dir as default_dir

        self.data_dir = default_dir(data_dir)
        self.store = Store(self.data_dir, max_upload=int(max_upload_mb * 2**20))
        self.hubs: dict = {}
        self._lock = threading.Lock()

    def hub(self, shot_id: str) -> Hub:
        """The hub of ``shot_id`` (opened from the store on first use). Raises KeyError-like
        :class:`core.store.UnknownShot` for an id the store does not have."""
        with self._lock:
            if shot_id not in self.hubs:
                self.hubs[shot_id] = Hub(self.store, shot_id, name=f"hub-{shot_id[:6]}")
            return self.hubs[shot_id]

    def create(self, shot, title: str, author: str) -> str:
        return self.store.create_shot(shot, title=title, author=author)


#: the process's review server, when ``serve`` was started with a data directory (else None:
#: every page is on its own, as before)
SERVER: Optional[ReviewServer] = None


def configure(data_dir=None, max_upload_mb: float = 200.0) -> ReviewServer:
    global SERVER
    SERVER = ReviewServer(data_dir, max_upload_mb)
    return SERVER


class Mirror:
    """One page's side of a shared shot: keeps the page's pipeline equal to the hub's shot, and
    sends the page's own changes to the hub.

    Parameters
    ----------
    hub : Hub
    session : dashboard.session.Session (its pipeline is the page's)
    name : who this page is (the participants list, the authors of changes)
    on_change : called (on the page's event loop) after a remote change was applied
    notify : ``(kind, message)`` for refusals
    on_own : called with the setting names of the page's own change once the hub took it
    """

    def __init__(self, hub: Hub, session, name: str, on_change=None, notify=None, doc=None, on_own=None,
                 dormant: bool = False):
        self.hub, self.session, self.name = hub, session, name
        #: a page built ahead (dashboard.warm): it hears of no change until it is handed out, then
        #: pulls them all at once
        self.dormant = dormant
        self.on_change, self.notify = on_change, notify
        self.on_own = on_own
        self.doc = doc
        self.version = 0
        self._applying = False
        self.follow = True
        self._watchers = []
        pipe = session.pipeline
        # the page's edits go to the hub (the pipeline calls back for each edit operation)
        pipe.listeners.append(self._on_edit)
        for st in pipe.stages.values():
            names = [n for n in st.setting_names() if n not in _EDIT_SETTINGS]
            if names:
                self._watchers.append((st, st.param.watch(self._on_setting, names)))
        self._hub_watch = hub.param.watch(self._on_hub, ["version"])
        self._pull(initial=True)

    # -- pulling the hub's shot into the page -------------------------------------------------
    def _on_hub(self, event):
        if event.new == self.version or self.dormant:
            return
        if self.hub.last_change.get("kind") == "frame" and event.new == self.version + 1:
            # the presenter's cursor only (the follow toggle moves this page's): nothing to pull
            self.version = event.new
            return
        self._schedule_pull()

    def _schedule_pull(self) -> None:
        if self.doc is not None:
            self.doc.add_next_tick_callback(self._pull_after_own)
        else:
            self._pull()

    async def _pull_after_own(self) -> None:
        """The page's own changes still waiting in Panel (a widget's change is debounced 50 ms)
        go first, each sent on the version it was made on (so it is rebased or refused with a
        message); then the hub's shot. Otherwise Panel lets the remote value win and drops the
        user's pending one without a word (``Syncable._update_model``: "the Python update wins";
        found by the review load test). The same flush Panel's ``_event_coroutine`` does."""
        try:
            from panel.io.state import state

            pending = list(getattr(state, "_change_callbacks", {}).get(self.doc, {}).values())
        except Exception:  # another Panel: nothing to flush
            pending = []
        for cb in pending:
            await cb()
        self._pull()

    def _pull(self, initial: bool = False) -> None:
        """Apply the hub's shot to the page's pipeline (what differs only), then redraw."""
        shot, version = self.hub.shot, self.hub.version
        if version == self.version and not initial:
            return
        pipe = self.session.pipeline
        self._applying = True
        try:
            with on_page(self.doc):  # the page gets the whole change in one message
                self._apply_shot(shot, version, initial)
        finally:
            self._applying = False

    def _apply_shot(self, shot, version: int, initial: bool) -> None:
        pipe = self.session.pipeline
        mine = pipe.shot()
        changed = {}
        for stage, vals in shot.settings.items():
            for k, v in vals.items():
                if mine.settings.get(stage, {}).get(k, object()) != v:
                    changed[k] = v
        files = False
        for role, ref in shot.files.items():
            if role not in mine.files or mine.files[role].sha != ref.sha:
                changed[role] = self.hub.store.locate(role, ref)
                files = True
        if changed:
            pipe.configure(**changed)
        from core.shot import EDITORS

        for editor in EDITORS:
            theirs = shot.edits[editor]
            if pipe.edits(editor) != theirs:
                pipe._set_edits(editor, theirs)
        pipe.notes = list(shot.notes)
        if files or initial:  # the file lists (paths resolved, contents hashed) only when a file changed
            self.session.sync_selection()
        self.version = version
        if self.on_change is not None and not initial:
            self.on_change(self.hub.last_change)

    # -- pushing the page's changes ----------------------------------------------------------------
    def _send(self, change: dict) -> bool:
        if self._applying:
            return True
        from core.store import Conflict

        try:
            base = self.version
            a = self.hub.apply(change, base, self.name)
            if a.version == base + 1:
                self.version = a.version  # nothing came between: the page is the shot
                if change.get("kind") == "note":  # the store gave the note its id and author
                    self.session.pipeline.notes = list(a.shot.notes)
            else:
                # rebased over changes this page has not pulled yet: not marked as seen (the pull
                # they scheduled brings them; taking this version would skip them — found by the
                # review load test: a note rebased over a setting hid that setting from the page)
                self._schedule_pull()
            return True
        except Conflict as e:
            if self.notify:
                self.notify("error", str(e))
            self._pull(initial=True)  # back to the shot as it is
            return False
        except ValueError as e:
            if self.notify:
                self.notify("error", f"not saved: {e}")
            return False

    def _on_setting(self, *events):
        if self._applying:
            return
        pipe = self.session.pipeline
        files = {}
        values = {}
        for e in events:
            stage = pipe._owners[e.name]
            if e.name in stage.files:
                files[e.name] = e.new
            else:
                values.setdefault(stage.stage_name, {})[e.name] = e.new
        if values and self._send({"kind": "settings", "values": values}) and self.on_own is not None:
            self.on_own([n for vals in values.values() for n in vals])
        if files:
            store = self.hub.store
            shas = {}
            for role, path in files.items():
                shas[role] = store.put_path(path) if path else None
            self._send({"kind": "files", "values": shas})

    def _on_edit(self, editor: str, op: str, arg) -> None:
        change = {"kind": "edit", "editor": editor, "op": op}
        if op == "add":
            change["edit"] = arg
        elif op == "remove":
            change["index"] = int(arg)
        self._send(change)

    def add_note(self, frame: int, text: str, frame_end: Optional[int] = None) -> bool:
        return self._send({"kind": "note", "op": "add", "frame": int(frame), "text": str(text),
                           **({"frame_end": int(frame_end)} if frame_end is not None else {})})

    def set_note(self, note_id: str, resolved: bool) -> bool:
        return self._send({"kind": "note", "op": "resolve" if resolved else "reopen", "note_id": note_id})

    def close(self) -> None:
        """Remove every watcher (the session is gone)."""
        self.hub.param.unwatch(self._hub_watch)
        for st, w in self._watchers:
            st.param.unwatch(w)
        pipe = self.session.pipeline
        if self._on_edit in pipe.listeners:
            pipe.listeners.remove(self._on_edit)


_EDIT_SETTINGS = ("edits", "transfer_edits", "detail_edits")


@contextmanager
def on_page(doc):
    """Run a change of ``doc``'s page as if from its own event: the page's document is Panel's
    current one (so widget changes apply at once instead of one scheduled callback each) and its
    events are held and sent to the browser as one message (each one sent alone re-lays the page
    out: ~0.3 s each in Chromium here). Nothing to do without a server page (``doc`` None)."""
    if doc is None:
        yield
        return
    import panel as pn
    from panel.io.state import set_curdoc

    with set_curdoc(doc), pn.io.hold(doc):
        yield
