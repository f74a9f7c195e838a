"""Headless participants of a shared review: the Bokeh websocket protocol spoken from Python,
many pages on one asyncio loop, for the load test (tests/test_review_load.py) and the review
benchmark (benchmarks/bench_review.py).

A :class:`Page` does what a browser does with a Panel page: ``GET /?shot=<id>`` (the server
builds the session's document then), the websocket with the session's token, ``PULL-DOC`` (the
document's models arrive), the GET of the viewers' meshes (dashboard.payloads), ``DocumentReady``; afterwards it applies every ``PATCH-DOC`` the server
sends and sends its own model changes as patches. Bokeh's ``ClientSession`` does the same but
reads messages only inside its own blocking loop, one session at a time; twenty pages at once
need one reader coroutine each, so the protocol steps are spelled out here (on Bokeh's own
message classes).

Localhost only; everything is bounded by timeouts.
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
import re
import time
from typing import Callable, Optional

from bokeh.client.websocket import WebSocketClientConnectionWrapper
from bokeh.document import Document
from bokeh.document.events import MessageSentEvent
from bokeh.events import ButtonClick, DocumentReady
from bokeh.protocol import Protocol
from bokeh.protocol.receiver import Receiver
from tornado.httpclient import AsyncHTTPClient, HTTPRequest
from tornado.websocket import websocket_connect

# twenty pages at once are twenty browsers: Tornado's client would queue all but 10 requests
AsyncHTTPClient.configure(None, max_clients=100)

#: the address of a viewer's mesh in a pulled document (dashboard.payloads.ROUTE)
MESH_URL = re.compile(r"face-retarget/payload/[0-9a-f]{32}")


def run(coro):
    """``asyncio.run(coro)`` in a thread of its own: the caller's thread may already run an event
    loop (a test before this one can leave one running), and asyncio.run refuses to nest."""
    import threading

    out: dict = {}

    def target():
        try:
            out["value"] = asyncio.run(coro)
        except BaseException as e:  # re-raised in the caller
            out["error"] = e

    t = threading.Thread(target=target, name="review-client", daemon=True)
    t.start()
    t.join()
    if "error" in out:
        raise out["error"]
    return out.get("value")


def sample_shot(data_dir, title: str, last_frame: int = 299, **settings) -> str:
    """A new shot of the bundled sample (its first ``last_frame + 1`` frames; -1: all; other
    ``settings`` as the pipeline takes them) in the review store at ``data_dir``, made from outside
    the server as another process would; returns its id."""
    from core.store import Store
    from dashboard.session import Session

    s = Session()
    s.pipeline.configure(last_frame=last_frame, **settings)
    store = Store(data_dir)
    try:
        return store.create_shot(s.shot(), title=title, author="lead")
    finally:
        store.close()


def register_models() -> None:
    """Import every model class a dashboard page may hold, so the client can deserialise them."""
    import importlib
    import pkgutil

    import panel.models
    from bokeh.model import Model

    for m in pkgutil.iter_modules(panel.models.__path__):
        if m.name in CDN_MODULE_MODELS:
            continue
        try:
            importlib.import_module(f"panel.models.{m.name}")
        except Exception:  # an optional model whose dependency is missing: no page of ours uses it
            pass
    import dashboard.connection_view  # noqa: F401  (ConnectionWatch)
    import dashboard.contact_sheet_view  # noqa: F401  (FrameLinks)
    import dashboard.review_view  # noqa: F401  (NameBox)
    import dashboard.upload_guard  # noqa: F401  (UploadGuard)
    import dashboard.viewer  # noqa: F401  (MeshViewer)

    external = sorted({f"{c.__module__}.{c.__name__}" for c in Model.model_class_reverse_map.values()
                       if any("://" in str(u) for u in (getattr(c, "__javascript_modules__", None) or []))})
    if external:
        raise RuntimeError(f"model classes whose ES modules come from a CDN were imported: {external}; "
                           "every page an in-process server makes would ask for them (add their "
                           "modules to CDN_MODULE_MODELS)")


#: panel.models modules whose JavaScript is an ES module Panel does not bundle (a CDN URL). Panel
#: puts the modules of every *imported* model class into every page it serves, so importing these
#: here made the in-process test servers' pages (tests/browser/test_viewer.py) ask the CDN, when
#: run after a test using this client; no dashboard page holds them.
CDN_MODULE_MODELS = {"vizzu"}


def _token(html: str) -> str:
    m = re.search(r'"token"\s*:\s*"([^"]+)"', html) or re.search(r'token\s*[:=]\s*["\']([^"\']+)', html)
    if not m:
        raise RuntimeError("no session token in the page")
    return m.group(1)


def _session_id(token: str) -> str:
    payload = token.split(".")[0]
    payload += "=" * (-len(payload) % 4)
    return json.loads(base64.urlsafe_b64decode(payload))["session_id"]


class Page:
    """One participant's page (see the module docstring).

    ``on_patch(page, changes, t)`` is called for every patch from the server with its property
    changes ``[(model id, property, new value)]`` and the arrival time (``time.monotonic()``).
    A viewer's new ``track_url`` is fetched at once, as the browser does (dashboard.payloads);
    ``on_track(page, model id, t)`` is called when it has arrived (or, for a track sent inside the
    patch, when the patch has).
    """

    def __init__(self, base: str, app: str = "/", args: Optional[dict] = None,
                 on_patch: Optional[Callable] = None, timeout: float = 120.0):
        self.base, self.app, self.args = base.rstrip("/"), app, dict(args or {})
        self.on_patch = on_patch
        self.on_track: Optional[Callable] = None
        self.timeout = timeout
        self.protocol = Protocol()
        self.receiver = Receiver(self.protocol)
        self.doc: Optional[Document] = None
        self.socket = None
        self.get_s = self.pull_s = None
        self.patches = 0
        self.values: dict = {}
        self.errors: list = []
        self._reader: Optional[asyncio.Task] = None

    # -- connecting ----------------------------------------------------------------------------
    async def open(self, defer: bool = False) -> "Page":
        """GET the page, connect, pull the document; ``get_s``/``pull_s``: how long each took.
        ``defer``: stop once the document has arrived and build it in :meth:`load` (a browser
        builds it in its own process; this client would otherwise spend its time building one
        page's models while the next pages' replies wait unread)."""
        from urllib.parse import urlencode

        query = ("?" + urlencode(self.args)) if self.args else ""
        t0 = time.monotonic()
        resp = await AsyncHTTPClient().fetch(HTTPRequest(self.base + self.app + query, request_timeout=self.timeout))
        token = _token(resp.body.decode())
        self.get_s = time.monotonic() - t0
        self.session_id = _session_id(token)
        t0 = time.monotonic()
        ws = self.base.replace("http://", "ws://") + self.app.rstrip("/") + "/ws"
        # the handshake waits while the server builds the other pages' documents, one after another:
        # Tornado's default 20 s request timeout failed the 20th cold page on a slow run
        self.socket = await asyncio.wait_for(websocket_connect(HTTPRequest(ws, connect_timeout=self.timeout,
                                                                           request_timeout=self.timeout),
                                                               subprotocols=["bokeh", token],
                                                               max_message_size=2**30), self.timeout)
        self.conn = WebSocketClientConnectionWrapper(self.socket)
        ack = await self._read()
        if ack is None or ack.msgtype != "ACK":
            raise RuntimeError(f"expected ACK, got {ack and ack.msgtype}")
        req = self.protocol.create("PULL-DOC-REQ")
        await self._send(req)
        while True:
            reply = await asyncio.wait_for(self._read(), self.timeout)
            if reply is None:
                raise RuntimeError("the server closed the connection")
            if reply.msgtype == "PULL-DOC-REPLY":
                break
        self.pull_s = time.monotonic() - t0
        self._reply = reply
        self.doc_bytes = len(reply._content_json or "") + sum(memoryview(b.data).nbytes for b in reply.buffers)
        await self._fetch_meshes(reply._content_json or "")
        return self if defer else await self.load()

    async def get(self, path: str) -> bytes:
        """GET ``path`` (from the server root) as the page's browser would, e.g. a viewer's track."""
        reply = await AsyncHTTPClient().fetch(HTTPRequest(f"{self.base}/{path.lstrip('/')}", request_timeout=self.timeout))
        return reply.body

    async def _fetch_meshes(self, content_json: str) -> None:
        """GET the viewers' meshes as a browser does after the document (dashboard.payloads):
        a page is not usable before them. ``mesh_s``/``mesh_bytes``: how long, how much came over
        the wire (gzip-compressed, as to a browser; the browser inflates them in its own process,
        so this client, which stands for twenty browsers in one, leaves them compressed)."""
        t0 = time.monotonic()
        urls = sorted(set(MESH_URL.findall(content_json)))
        replies = await asyncio.gather(*(AsyncHTTPClient().fetch(HTTPRequest(
            f"{self.base}/{u}", request_timeout=self.timeout, headers={"Accept-Encoding": "gzip"},
            decompress_response=False)) for u in urls))
        self.mesh_bytes = sum(len(r.body) for r in replies)
        self.mesh_s = time.monotonic() - t0

    async def load(self) -> "Page":
        """Build the pulled document and start listening (:meth:`open` does it unless deferred)."""
        reply, self._reply = self._reply, None
        self.doc = Document()
        reply.push_to_document(self.doc)
        self.doc.callbacks.on_change_dispatch_to(self)
        self._reader = asyncio.ensure_future(self._read_loop())
        self.doc.callbacks.trigger_on_change(MessageSentEvent(self.doc, "bokeh_event", DocumentReady()))
        return self

    async def close(self) -> None:
        if self.socket is not None:
            self.socket.close()
        if self._reader is not None:
            try:
                await asyncio.wait_for(self._reader, 5)
            except (asyncio.TimeoutError, Exception):
                self._reader.cancel()

    # -- messages ------------------------------------------------------------------------------
    async def _read(self):
        while True:
            fragment = await self.socket.read_message()
            if fragment is None:
                return None
            msg = await self.receiver.consume(fragment)
            if msg is not None:
                return msg

    async def _read_loop(self) -> None:
        while True:
            msg = await self._read()
            if msg is None:
                return
            if msg.msgtype == "PATCH-DOC":
                # the patch is read, not applied: deserialising every patch (viewer tracks are
                # megabytes) into twenty documents made this process, not the server, the
                # bottleneck of the load test. ``values`` keeps the last value the server sent
                # for each (model id, property).
                t = time.monotonic()
                changes = []
                for e in msg.content.get("events", []):
                    if e.get("kind") == "ModelChanged":
                        key = (e["model"]["id"], e["attr"])
                        self.values[key] = e.get("new")
                        changes.append((key[0], key[1], e.get("new")))
                        if key[1] == "track_url" and e.get("new"):
                            asyncio.ensure_future(self._fetch_track(key[0], e["new"]))
                self.patches += 1
                if self.on_patch is not None:
                    self.on_patch(self, changes, t)
                if self.on_track is not None:  # a track inside the patch: the page has it now
                    for mid, attr, _ in changes:
                        if attr == "track":
                            self.on_track(self, mid, t)
            elif msg.msgtype == "ERROR":
                self.errors.append(msg.content.get("text", "error"))

    async def _fetch_track(self, model_id: str, url: str) -> None:
        try:
            await self.get(url)
        except Exception as e:  # noqa: BLE001 - reported like a server error
            self.errors.append(f"track {url}: {e}")
            return
        if self.on_track is not None:
            self.on_track(self, model_id, time.monotonic())

    def value(self, model, attr: str):
        """``model.attr`` as the server last sent it (or as pulled, when it never changed)."""
        return self.values.get((model.id, attr), getattr(model, attr))

    def _document_patched(self, event) -> None:
        """Bokeh's dispatch of a change of the local document: ours go to the server."""
        msg = self.protocol.create("PATCH-DOC", [event])
        asyncio.ensure_future(self._send(msg))

    async def _send(self, msg) -> None:
        await msg.send(self.conn)  # the wrapper's write lock keeps a message's parts together

    # -- what a person does ---------------------------------------------------------------------
    def find(self, type_name: str, **match):
        """The page's models of bokeh type ``type_name`` whose properties match (a value, or a
        compiled regular expression searched in a string property)."""
        out = []
        for m in self.doc.models:
            if type(m).__name__ != type_name:
                continue
            ok = True
            for k, v in match.items():
                have = getattr(m, k, None)
                ok = ok and (bool(v.search(str(have))) if isinstance(v, re.Pattern) else have == v)
            if ok:
                out.append(m)
        return out

    def one(self, type_name: str, **match):
        found = self.find(type_name, **match)
        if len(found) != 1:
            raise LookupError(f"{len(found)} {type_name} models match {match}")
        return found[0]

    def set(self, model, **props) -> None:
        """Change properties of ``model`` as the browser would (sent as one patch each)."""
        for k, v in props.items():
            model.set_from_json(k, v)  # as from the browser: read-only ones (value_throttled) too
            self.values[(model.id, k)] = v

    def click(self, button) -> None:
        self.doc.callbacks.trigger_on_change(MessageSentEvent(self.doc, "bokeh_event", ButtonClick(button)))

    def send_msg(self, model, data: dict) -> None:
        """What a custom component's script sends its server side (``model.send_msg(data)`` in its
        ESM: a ``data_event``), e.g. dashboard.upload_guard announcing the file it lets through."""
        from panel.models.esm import DataEvent

        self.doc.callbacks.trigger_on_change(MessageSentEvent(self.doc, "bokeh_event", DataEvent(model, data=data)))


def pctl(xs, q: float) -> float:
    xs = sorted(xs)
    return float(xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]) if xs else float("nan")


class Server:
    """``face-retarget serve`` on 127.0.0.1 in a process of its own (``with Server(...) as srv``);
    ``srv.base`` is its URL, ``srv.rss_mb()`` its resident memory. Killed on exit."""

    def __init__(self, *args: str, log=None, timeout: float = 120.0):
        import os
        import socket
        import subprocess
        import sys
        from pathlib import Path

        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        root = Path(__file__).resolve().parents[1]
        self.log = Path(log) if log else Path(os.devnull)
        self._fh = open(self.log, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "core.cli", "serve", "--address", "127.0.0.1", "--port", str(self.port), *args],
            cwd=root, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=self._fh, stderr=subprocess.STDOUT,
            start_new_session=True)
        self.base = f"http://127.0.0.1:{self.port}"
        self._wait(timeout)

    def _wait(self, timeout: float) -> None:
        import urllib.request

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the server exited ({self.proc.returncode}); log {self.log}")
            try:
                with urllib.request.urlopen(self.base + "/liveness", timeout=2) as r:
                    if r.status == 200:
                        return
            except Exception:  # noqa: BLE001 - not up yet
                pass
            time.sleep(0.3)
        self.stop()
        raise RuntimeError(f"the server did not answer within {timeout} s")

    def rss_mb(self) -> float:
        for line in open(f"/proc/{self.proc.pid}/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


# -- the load scenario ------------------------------------------------------------------------------
ALPHA = re.compile(r"Seol α")
BETA = re.compile(r"Seol β")


async def open_pages(base: str, shot_id: Optional[str], n: int, on_patch=None, app: str = "/",
                     defer: bool = False) -> tuple:
    """Open ``n`` pages at once; returns ``(pages, served)`` with ``served[i]`` the time from the
    start to page ``i`` being complete (document pulled), in completion order. ``defer``: the
    times are to each document's arrival, the documents are built after the last (Page.open)."""
    t0 = time.monotonic()
    done = []

    async def one(i):
        p = Page(base, app=app, args={"shot": shot_id} if shot_id else None, on_patch=on_patch)
        p.index = i
        await p.open(defer=defer)
        done.append(time.monotonic() - t0)
        return p

    pages = await asyncio.gather(*(one(i) for i in range(n)))
    if defer:
        for p in pages:
            await p.load()
    return list(pages), sorted(done)


async def review_load(base: str, shot_id: str, n: int, seconds: float, seed: int = 0, present_every=(0.25, 0.75),
                      scrub_every=(2.0, 6.0), setting_every=(20.0, 60.0), note_every=(30.0, 90.0)) -> dict:
    """``n`` pages of one shot for ``seconds``: each scrubs, changes a setting (even pages the
    spacetime α, odd ones β, so changes of one setting race and changes of two rebase) and adds
    notes at random intervals (``*_every``: the range of seconds between two, per page); page 0
    presents (the others follow its frame) and scrubs every ``present_every`` seconds, as a drag
    of the frame slider sends its values.

    Returns what was measured: ``served`` (page completion times), ``response`` (a scrub -> the
    page's own viewer at that frame), ``setting`` / ``seek`` propagation (a change on one page ->
    seen on each other page), ``sent`` (per page: α/β values and note texts), ``refused`` (per
    page: the refusal messages it was shown), ``errors``, ``final`` (each page's α and β).
    """
    import random

    rng = random.Random(seed)
    sent_at: dict = {}          # ("alpha"|"beta"|"frame", value) -> (page index, time sent)
    response, setting_prop, seek_prop = [], [], []
    refused = [[] for _ in range(n)]
    trail = [[] for _ in range(n)]  # per page: (time, setting, value) of every α/β value the server sent it
    pending_scrub: dict = {}    # page index -> (frame, time sent)
    models: dict = {}

    last_patch = [time.monotonic()]

    def on_patch(page, changes, t):
        last_patch[0] = t
        m = models.get(page.index)
        if m is None:
            return
        for mid, attr, new in changes:
            if attr == "value" and mid in (m["alpha"].id, m["beta"].id):
                trail[page.index].append((round(t, 3), "alpha" if mid == m["alpha"].id else "beta", new))
            if attr == "frame" and mid in m["viewers"]:
                ps = pending_scrub.get(page.index)
                if ps and ps[0] == new:
                    response.append(t - ps[1])
                    pending_scrub.pop(page.index, None)
            elif attr == "value" and mid == m["alpha"].id and ("alpha", new) in sent_at:
                i, ts = sent_at[("alpha", new)]
                if i != page.index:
                    setting_prop.append(t - ts)
            elif attr == "value" and mid == m["beta"].id and ("beta", new) in sent_at:
                i, ts = sent_at[("beta", new)]
                if i != page.index:
                    setting_prop.append(t - ts)
            elif attr == "value" and mid == m["frame"].id and page.index != 0 and ("frame", new) in sent_at:
                seek_prop.append(t - sent_at[("frame", new)][1])
            elif attr == "text" and isinstance(new, str) and "refused" in new:
                refused[page.index].append(new)

    pages, served = await open_pages(base, shot_id, n, on_patch=on_patch)
    for p in pages:
        models[p.index] = dict(alpha=p.one("Slider", title=ALPHA), beta=p.one("Slider", title=BETA),
                               frame=p.one("Slider", title="Frame"),
                               viewers={m.id for m in p.doc.models if type(m).__name__.startswith("MeshViewer")})
        for nb in p.find("NameBox1") or [m for m in p.doc.models if type(m).__name__.startswith("NameBox")]:
            p.set(nb, value=f"page{p.index}")
    present = pages[0].find("Toggle", label=re.compile("^Present"))
    if present:
        pages[0].set(present[0], active=True)
    await asyncio.sleep(1.0)
    last_frame = int(pages[0].value(models[0]["frame"], "end"))
    sent = [{"alpha": [], "beta": [], "notes": []} for _ in range(n)]
    counter = iter(range(1, 10**6))

    async def actor(p):
        i = p.index
        m = models[i]
        end = time.monotonic() + seconds
        every = present_every if i == 0 else scrub_every
        next_scrub = time.monotonic() + rng.uniform(*every)
        next_setting = time.monotonic() + rng.uniform(*setting_every)
        next_note = time.monotonic() + rng.uniform(*note_every)
        note_box = p.one("TextAreaInput", placeholder=re.compile("a note at this frame"))
        note_button = p.one("Button", label=re.compile("^Add note"))
        while True:
            now = time.monotonic()
            if now >= end:
                return
            if now >= next_scrub:
                f = rng.randrange(0, last_frame + 1)
                while ("frame", f) in sent_at and i == 0:
                    f = rng.randrange(0, last_frame + 1)
                pending_scrub[i] = (f, time.monotonic())
                if i == 0:
                    sent_at[("frame", f)] = (0, time.monotonic())
                p.set(m["frame"], value=f, value_throttled=f)
                next_scrub = now + rng.uniform(*every)
            if now >= next_setting:
                key = "alpha" if i % 2 == 0 else "beta"
                v = round(0.001 + 1e-5 * next(counter), 6)  # unique: whose change it was is known by value
                # the α slider is over log10 α (dashboard.widgets.LogSlider): it is moved to log10 α, the
                # setting (what the store keeps) is α, rounded by the page to three digits as v is
                pos = math.log10(v) if key == "alpha" else v
                sent_at[(key, pos)] = (i, time.monotonic())
                trail[i].append((round(time.monotonic(), 3), key, v, "sent"))
                sent[i][key].append(v)
                p.set(m[key], value=pos, value_throttled=pos)
                next_setting = now + rng.uniform(*setting_every)
            if now >= next_note:
                text = f"note {i}-{len(sent[i]['notes'])} from page{i}"
                sent[i]["notes"].append(text)
                p.set(note_box, value=text)
                await asyncio.sleep(0.05)  # the text reaches the server before the click, as in a browser
                p.click(note_button)
                next_note = now + rng.uniform(*note_every)
            await asyncio.sleep(0.02)

    await asyncio.gather(*(actor(p) for p in pages))
    # let the last recomputes and their patches arrive: until no page has heard anything for 3 s
    # (a loaded server may still be working through the last changes; at most 60 s)
    quiet_from = time.monotonic()
    while time.monotonic() - last_patch[0] < 3.0 and time.monotonic() - quiet_from < 60.0:
        await asyncio.sleep(0.5)
    final = [dict(alpha=float(f"{10 ** p.value(models[p.index]['alpha'], 'value'):.3g}"),  # the slider's log10 α
                  beta=p.value(models[p.index]["beta"], "value")) for p in pages]
    errors = [e for p in pages for e in p.errors]
    for p in pages:
        await p.close()
    return dict(served=served, get_s=[p.get_s for p in pages], pull_s=[p.pull_s for p in pages],
                response=response, setting=setting_prop, seek=seek_prop, sent=sent, refused=refused, trail=trail,
                errors=errors, final=final, pages=n, seconds=seconds)
