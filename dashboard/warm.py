"""Warm pages: pages of a shared shot built ahead of the people who will open them.

Every page costs the server the Bokeh document Panel builds for it in Python, under the GIL:
about 260 models, ~0.9 s of CPU on the 2-core machines (the review issue's "sessions are cheap";
measured: 20 pages of a computed shot requested at once, the 20th served after 17-19 s, one
after another). Sharing the computed results (the stage cache, the viewer payloads) is already done;
what is left is Bokeh's per-document work, which no sharing removes: a bare Bokeh page of 100
``Div`` models served to 20 clients at once takes 3.7 s for the 20th on the same machine.

So the server builds a shot's pages before they are asked for, while it is idle. The pages of
one shot are alike until someone opens them, and a review is opened by a few people at once
(the lead mails the link). ``face-retarget serve --warm-pages N`` keeps up to N pages of every
shot that was opened ready — or as many as have been on the shot at once, when that is more (up
to :data:`MAX_PEAK_PAGES`: a review that met with twelve people finds twelve pages after a break);
``/?shot=<id>`` hands one out and then costs only the HTML, a fresh session token and the
document's serialisation.

A warm page is *dormant* until it is handed out: it is not among the participants, and it does
not follow the hub as changes come (twenty dormant pages recomputing every change would
multiply the work of each change by twenty). Instead a waiting page that missed changes catches
up with them when the server is idle again, one page at a time — the same pull as a remote
change (:class:`dashboard.review.Mirror`). Handed out, it takes the request's token, cookies and
arguments, joins the shot under the reviewer's name and pulls whatever it still missed. Its Bokeh
session is kept from expiring while it waits (Bokeh discards a session nobody connected to after
15 s).

A waiting page's document is also *serialised* ahead (:class:`PulledDocument`): when its
reviewer's browser asks for the document, the reply is already made, unless the document changed
since (then it is made as always). Bokeh would otherwise turn the page's 260-odd models into JSON
when asked (~0.15 s each, one page after another: 3 s for twenty pages at once). That is why a
handed-out page joins its shot (its name in the participants, the changes it missed) right
*after* its document is sent: those changes reach the browser as patches, like any other.
Its HTML page is made ahead too, with a stand-in for the session token that the request's
token replaces: Panel renders the page for each request, and walks every model of the document
to patch stylesheet URLs first (~40 ms a page; 0.8 s for twenty pages at once, measured with
py-spy: half of the server's work in such a burst).

The dashboard's own first page (``/``, a page of its own on the sample) is kept warm the same way
under the key :data:`SAMPLE` (the empty shot id), from the moment the server starts
(:meth:`WarmPool.start`): an idle server answers ``/`` with a page whose results came from the
stage cache and whose document is made, so the browser has only its own work to do (issue 30,
"the first page"). It keeps :data:`SAMPLE_PAGES` such pages (each ~4.5 MB while it waits); they
follow nothing (a page of its own has no shot to change), so they never go stale.

Building waits until the server has been idle for :data:`IDLE_S` (no page asked for, no change
to the shot, and the event loop answering on time), or :data:`BUSY_IDLE_S` while someone is on
the shot: a build holds the event loop for about a second, and a change of a review should not
wait behind one (measured: twenty pages open, a build begun in a pause held the next change of
the shot for a second on every page: the 95th percentile of the 20-page propagation benchmark was
1.5 s, 0.68 s with builds waiting 30 s). Each build is one page; the loop runs the other
sessions' work in between.
"""

from __future__ import annotations

import logging
import time
from typing import Optional

log = logging.getLogger("face_retarget.warm")

#: seconds without a page request or a change before a warm page is built
IDLE_S = 3.0
#: the same while someone is on the shot: reviewers pause for a few seconds between changes, and
#: a change made while a page is being built waits for it; 15 s was not enough for twenty pages
#: whose documents their (Python) client built one after another in 14 s before the first change
BUSY_IDLE_S = 30.0
#: the most shots that keep warm pages (the most recently opened)
MAX_SHOTS = 8
#: the key of the dashboard's own first page (``/`` without ``?shot=``) among the shots' pages
SAMPLE = ""
#: warm pages of the first page (``/``) kept ready: the page opened most, by one person at a time
SAMPLE_PAGES = 2
#: seconds of quiet before the first page is built again once one was handed out: its browser is
#: still loading it (the document, the meshes, the first views), and a build holds the event loop
#: for about a second (measured: a refill 3 s after the hand-out made the page's own load ~2 s slower)
SAMPLE_REFILL_S = 12.0
#: the most warm pages a shot keeps because of how many people it has had at once (above
#: ``--warm-pages``; ~4.5 MB each while they wait)
MAX_PEAK_PAGES = 24


def _named(shot_id: str) -> str:
    """A shot as the log names it: ``shot`` and its id's first characters, or ``first page``."""
    return f"shot {shot_id[:6]}" if shot_id != SAMPLE else "first page"


class WarmPool:
    """Ready (dormant) pages per shot id, and their refilling (see the module docstring)."""

    def __init__(self, size: int, idle_s: float = IDLE_S, max_shots: int = MAX_SHOTS, busy_idle_s: float = BUSY_IDLE_S):
        if size < 0:
            raise ValueError(f"warm pages: expected a count >= 0, got {size}")
        self.size, self.idle_s, self.max_shots = int(size), float(idle_s), int(max_shots)
        self.busy_idle_s = max(float(busy_idle_s), self.idle_s)
        self.ready: dict = {}  # shot id -> [(ServerSession, DashboardApp)], oldest first
        self.building: set = set()  # Bokeh session ids being built as warm pages
        self.apps: dict = {}  # Bokeh session id -> the DashboardApp built for it (create_app puts it)
        self._filling: set = set()  # shot ids whose refill is running
        self._order: list = []  # shot ids, most recently opened last
        self._watched: dict = {}  # shot id -> (hub, watchers) bumping the activity clock on changes
        self.peak: dict = {}  # shot id -> the most pages that have been on it at once
        self.served: set = set()  # shot ids a page was asked for (the first page refills after SAMPLE_REFILL_S)
        self._ctx = None  # (Bokeh application context, application) of the page route, pages are built in
        self._loop = None  # the server's event loop (a shot may change on another thread)
        self.last_activity = time.monotonic()

    def touch(self, *_) -> None:
        """Something happened (a page was asked for, a shot changed): builds wait."""
        self.last_activity = time.monotonic()

    def claim(self, shot_id: str):
        """A ready ``(ServerSession, DashboardApp)`` of ``shot_id``, or None."""
        pages = self.ready.get(shot_id) or []
        self.served.add(shot_id)
        while pages:
            session, app = pages.pop(0)
            if not session.destroyed:
                return session, app
        return None

    def count(self, shot_id: str) -> int:
        return len(self.ready.get(shot_id) or [])

    def target(self, shot_id: str) -> int:
        """How many pages ``shot_id`` keeps ready: ``--warm-pages``, or as many as have been on
        it at once (up to :data:`MAX_PEAK_PAGES`) — a review that met with twelve people, who
        come back after a break or reload, finds twelve pages ready."""
        if self.size <= 0:
            return 0
        if shot_id == SAMPLE:
            return min(self.size, SAMPLE_PAGES)
        return max(self.size, min(self.peak.get(shot_id, 0), MAX_PEAK_PAGES))

    def _people(self, shot_id: str, hub) -> None:
        n = len(hub.participants)
        if n > self.peak.get(shot_id, 0):
            self.peak[shot_id] = n
            if n > self.size:
                self._changed(shot_id)

    def want(self, app_context, application, shot_id: str, hub=None) -> None:
        """Keep ``shot_id``'s pages topped up and current (on the event loop, while idle)."""
        if self.size <= 0:
            return
        from tornado.ioloop import IOLoop

        self._loop = IOLoop.current()
        self._ctx = (app_context, application)
        if shot_id in self._order:
            self._order.remove(shot_id)
        self._order.append(shot_id)
        for old in self._order[:-self.max_shots]:  # shots no one opened for a while: let their pages go
            self._order.remove(old)
            for session, _ in self.ready.pop(old, []):
                session.unblock_expiration()
            self.peak.pop(old, None)
            hub_w = self._watched.pop(old, None)
            if hub_w is not None:
                for w in hub_w[1]:
                    hub_w[0].param.unwatch(w)
        if hub is not None and shot_id not in self._watched:
            self._watched[shot_id] = (hub, (hub.param.watch(lambda e, s=shot_id: self._changed(s), ["version"]),
                                            hub.param.watch(lambda e, s=shot_id, h=hub: self._people(s, h),
                                                            ["participants"])))
            self._people(shot_id, hub)
        self._kick(shot_id)

    def route(self, app_context, application) -> None:
        """The page route's Bokeh application context and Tornado application, as a page asked for
        without a shot saw them: a shot made on such a page (in place) is warmed with them."""
        if self._ctx is None:
            self._ctx = (app_context, application)

    def want_made_here(self, shot_id: str, hub) -> None:
        """:meth:`want` for a shot a page made of itself (no ``?shot=`` request went through the
        page handler); on the event loop. A no-op before any page was served."""
        if self._ctx is not None:
            self.want(*self._ctx, shot_id, hub)

    def start(self, server) -> None:
        """Keep the first page (``/``, :data:`SAMPLE`) warm from the start of ``server`` (a
        :class:`bokeh.server.server.Server` serving the dashboard at ``/``; call on its event loop).
        The first build also fills the stage cache with the sample's results."""
        tornado_app = server._tornado  # Bokeh's application; the handlers' self.application
        ctx = tornado_app._applications.get("/")  # Bokeh has no public lookup of an app's context
        if ctx is not None:
            self.want(ctx, tornado_app, SAMPLE)

    def _changed(self, shot_id: str) -> None:
        """The shot changed (any thread): builds wait, and its waiting pages will catch up."""
        self.touch()
        if self._loop is not None:
            self._loop.add_callback(self._kick, shot_id)

    def _kick(self, shot_id: str) -> None:
        if shot_id in self._filling or shot_id not in self._order:
            return
        self._filling.add(shot_id)
        self._loop.spawn_callback(self._maintain, shot_id)

    def _stale(self, shot_id: str):
        for session, app in self.ready.get(shot_id) or []:
            m = app.mirror
            if not session.destroyed and m is not None and m.version != m.hub.version:
                return app
        return None

    def _unserialised(self, shot_id: str):
        """A waiting, current page of ``shot_id`` whose document reply is not made (or no longer
        valid), as its :class:`PulledDocument`; None when there is none."""
        for session, app in self.ready.get(shot_id) or []:
            m = app.mirror
            pulled = getattr(session, "_face_retarget_pull", None)
            if (not session.destroyed and pulled is not None and not pulled.ready()
                    and (m is None or m.version == m.hub.version)):
                return pulled
        return None

    async def _maintain(self, shot_id: str) -> None:
        """While idle, one step at a time: a waiting page that missed a change catches up (so a
        page handed out is current and costs no recompute then), else one more page is built."""
        import asyncio

        try:
            while shot_id in self._order:
                stale = self._stale(shot_id)
                if stale is None and self._unserialised(shot_id) is None and self.count(shot_id) >= self.target(shot_id):
                    break
                await self._idle(shot_id)
                if shot_id not in self._order:
                    break
                stale = self._stale(shot_id)
                if stale is not None:
                    stale.catch_up()
                elif (pulled := self._unserialised(shot_id)) is not None:
                    if _queued(pulled.session.document):
                        # changes still queued for the document (a pane's update deferred to the
                        # next tick) would drop the reply right after it is made: let them run
                        await asyncio.sleep(0.1)
                        continue
                    await pulled.session.with_document_locked(pulled.prepare, self._ctx[1])
                    if self._unserialised(shot_id) is None and self._stale(shot_id) is None:
                        if shot_id == SAMPLE:
                            log.info("first page: %d built ahead, ready to send", self.count(shot_id))
                        else:
                            log.info("shot %s: %d warm pages current, their documents made", shot_id[:6], self.count(shot_id))
                elif self.count(shot_id) < self.target(shot_id):
                    got = await self._build(*self._ctx, shot_id)
                    if got is None:
                        break
                    self.ready.setdefault(shot_id, []).append(got)
                    n = self.count(shot_id)
                    if n == self.target(shot_id):
                        log.info("%s: %d of %d %s ready", _named(shot_id), n, n,
                                 "warm pages" if shot_id != SAMPLE else "pages built ahead")
                await asyncio.sleep(0.05)  # the other sessions' work between two steps
        finally:
            self._filling.discard(shot_id)

    async def _idle(self, shot_id: str) -> None:
        """Return once the server has been idle for :attr:`idle_s` (:attr:`busy_idle_s` while
        someone is on ``shot_id``)."""
        import asyncio

        def need() -> float:
            hub = self._watched.get(shot_id, (None,))[0]
            if shot_id == SAMPLE and shot_id in self.served:
                return max(self.idle_s, SAMPLE_REFILL_S)
            return self.busy_idle_s if hub is not None and hub.participants else self.idle_s

        while time.monotonic() - self.last_activity < need():
            t = time.monotonic()
            await asyncio.sleep(0.25)
            if time.monotonic() - t > 0.4:  # the loop was busy (pages being built, a recompute): not idle
                self.touch()

    async def _build(self, app_context, application, shot_id: str):
        """One dormant page of ``shot_id``, as Bokeh builds a requested one (the app function runs
        with ``?shot=<id>``; :func:`dashboard.app.create_app` sees it is warm by its session id)."""
        from bokeh.util.token import generate_jwt_token, generate_session_id
        from tornado.httputil import HTTPHeaders, HTTPServerRequest

        sid = generate_session_id(secret_key=application.secret_key, signed=application.sign_sessions)
        token = generate_jwt_token(sid, secret_key=application.secret_key, signed=application.sign_sessions,
                                   expiration=application.session_token_expiration,
                                   extra_payload={"headers": {}, "cookies": {},
                                                  "arguments": {"shot": [shot_id.encode()]} if shot_id else {}})
        request = HTTPServerRequest(method="GET", uri=f"/?shot={shot_id}" if shot_id else "/", headers=HTTPHeaders())
        self.building.add(sid)
        t0 = time.perf_counter()
        try:
            session = await app_context.create_session_if_needed(sid, request, token)
        except Exception:  # noqa: BLE001 - a page that cannot be built is built when asked for, with its error
            log.warning("%s: building a warm page failed", _named(shot_id), exc_info=True)
            return None
        finally:
            self.building.discard(sid)
        app = self.apps.pop(sid, None)
        if app is None:  # the app function served something else (an unknown shot): not a page to keep
            return None
        session.block_expiration()
        PulledDocument.install(session)
        log.debug("%s: warm page built in %.2f s", _named(shot_id), time.perf_counter() - t0)
        return session, app


def _queued(doc) -> bool:
    """Whether ``doc`` has next-tick callbacks waiting: Panel defers a pane's update made outside
    the document's lock to one, and it changes the document when it runs."""
    from bokeh.server.callbacks import NextTickCallback

    return any(isinstance(cb, NextTickCallback) for cb in doc.callbacks.session_callbacks)


#: what a page made ahead holds in place of its session token (a JWT's characters, so that it is
#: written into the page as it is, like the token)
TOKEN_SLOT = "face-retarget-warm-page-token-slot"


def render_page(session, application, token: str) -> str:
    """The HTML page of ``session`` with ``token``, as Panel's page handler renders it."""
    from panel.io.resources import Resources
    from panel.io.server import server_html_page_for_session
    from panel.io.state import set_curdoc

    doc = session.document
    with set_curdoc(doc):
        return server_html_page_for_session(session, resources=Resources.from_bokeh(application.resources()),
                                            title=doc.title, token=token, template=doc.template,
                                            template_variables=doc.template_variables)


class PulledDocument:
    """A warm page's HTML page and ``PULL-DOC-REPLY`` made ahead, and what runs once it has been
    sent.

    :meth:`install` replaces the session's pull handler (Bokeh looks it up on the session, so only
    warm pages are affected). :meth:`prepare` (while the server is idle) renders the page as
    Panel's handler would, with :data:`TOKEN_SLOT` for the token, and serialises the document as
    Bokeh's own reply would (``Document.to_json``, then its JSON text); any change of the document
    afterwards drops both. The pull then sends the prepared reply when it is still valid and the
    document holds no collected changes, else makes one as Bokeh does, and afterwards runs
    :attr:`after_pull` (the page joining its shot) on the event loop: its changes reach the
    browser as patches behind the reply.
    """

    def __init__(self, session):
        self.session = session
        self.page = None  # the HTML page with TOKEN_SLOT for the token, or None
        self.reply = None  # (content, content JSON, buffers), or None
        self.after_pull = None  # callable run once the document has been sent
        session.document.callbacks.on_change(self._changed)

    @classmethod
    def install(cls, session) -> "PulledDocument":
        import types

        from bokeh.server.session import _needs_document_lock

        pulled = cls(session)
        session._face_retarget_pull = pulled
        # the original is this same function wrapped in Bokeh's document lock
        session._handle_pull = types.MethodType(_needs_document_lock(PulledDocument._pull), session)
        return pulled

    def _changed(self, event) -> None:
        from bokeh.document.events import MessageSentEvent, SessionCallbackAdded, SessionCallbackRemoved

        # callbacks added or removed and messages sent change nothing the reply holds
        if not isinstance(event, (SessionCallbackAdded, SessionCallbackRemoved, MessageSentEvent)):
            self.page = self.reply = None

    def ready(self) -> bool:
        return self.reply is not None and self.page is not None

    def prepare(self, application) -> None:
        from bokeh.core.json_encoder import serialize_json

        # first: rendering patches stylesheet URLs (once; Panel keeps the changes out of the
        # document's events, so it cannot drop what is made here)
        page = render_page(self.session, application, TOKEN_SLOT)
        self.page = page if page.count(TOKEN_SLOT) == 1 else None
        serialized = self.session.document.to_json()
        content = {"doc": serialized.content}
        self.reply = (content, serialize_json(content), list(serialized.buffers))

    @staticmethod
    def _pull(session, message, connection):
        from bokeh.protocol.messages.pull_doc_reply import pull_doc_reply

        self = session._face_retarget_pull
        cb = session.document.callbacks
        if self.reply is not None and cb.hold_value is None and not cb._held_events:
            content, text, buffers = self.reply
            msg = pull_doc_reply(pull_doc_reply.create_header(request_id=message.header["msgid"]), {}, content)
            msg._content_json = text  # the JSON made ahead (Message keeps it once made)
            msg.add_buffers(*buffers)
        else:
            msg = connection.protocol.create("PULL-DOC-REPLY", message.header["msgid"], session.document)
        self.reply = None  # a page pulls once; a reconnect gets a fresh reply
        after, self.after_pull = self.after_pull, None
        if after is not None:  # with the document lock, once this reply has been written
            session.document.add_next_tick_callback(after)
        return msg


#: the server's pool, when ``serve`` was started with ``warm_pages > 0`` (else None)
POOL: Optional[WarmPool] = None


def configure(size: int, busy_idle_s: float = BUSY_IDLE_S) -> Optional[WarmPool]:
    """Set up the pool and route page requests through :func:`handler_class` (before the server
    is made: Bokeh reads its URL patterns then)."""
    global POOL
    POOL = WarmPool(size, busy_idle_s=busy_idle_s) if size > 0 else None
    if POOL is not None:
        from bokeh.server import urls

        urls.per_app_patterns[:] = [(p, handler_class() if p == r"/?" else h) for p, h in urls.per_app_patterns]
    return POOL


def is_warming(doc) -> bool:
    """True while ``doc`` is being built as a warm page."""
    ctx = getattr(doc, "session_context", None)
    return POOL is not None and ctx is not None and ctx.id in POOL.building


def handler_class():
    """Panel's page handler, which hands out a warm page of the requested shot when one is ready."""
    from panel.io.server import DocHandler
    from tornado.web import authenticated

    class WarmDocHandler(DocHandler):
        _claimed = None  # the warm page get() took for this request

        def _warm_shot(self):
            """The shot id of a request a warm page may answer (:data:`SAMPLE` for the first
            page, ``/`` without arguments), else None."""
            explicit = self.get_argument("bokeh-token", default=None) or self.get_argument("bokeh-session-id", default=None)
            if POOL is None or explicit:
                return None
            shot_id = (self.get_argument("shot", default="") or "").strip()
            if shot_id:
                return shot_id
            return SAMPLE if not self.request.arguments else None

        @authenticated
        async def get(self, *args, **kwargs):
            """A warm page whose HTML was made ahead is written with this request's token; any
            other request is Panel's (which renders the page, and calls :meth:`get_session`)."""
            from panel.config import config
            from panel.io.server import _set_request_route_context

            shot_id = self._warm_shot()
            if shot_id is not None:
                POOL.touch()
                self._claimed = POOL.claim(shot_id)
                pulled = getattr(self._claimed[0], "_face_retarget_pull", None) if self._claimed else None
                page = pulled.page if pulled is not None else None
                prefix = self.application.prefix
                plain = (not config.authorize_callback and not config.reuse_sessions
                         and not (prefix and self.request.path == prefix and not prefix.endswith("/")))
                if page is not None and plain:  # what Panel's get does for such a request, but rendering
                    self.set_header("Cache-Control", "no-store")
                    _set_request_route_context(self, *args, **kwargs)
                    session = await self.get_session()
                    pulled.page = None  # written once: a reload is a new request, rendered by Panel
                    self.set_header("Content-Type", "text/html")
                    self.write(page.replace(TOKEN_SLOT, session.token))
                    return
            await super().get(*args, **kwargs)

        async def get_session(self):
            pool = POOL
            shot_id = self._warm_shot()
            if not shot_id and pool is not None:  # a page that may make a shot in place (DashboardApp.open_shared)
                pool.route(self.application_context, self.application)
            if shot_id is None:
                return await super().get_session()
            got, self._claimed = self._claimed, None
            if got is None:
                session = await super().get_session()
            else:
                session = self._hand_out(*got)
            from dashboard import review

            hub = review.SERVER.hubs.get(shot_id) if review.SERVER is not None and shot_id != SAMPLE else None
            if hub is not None or shot_id == SAMPLE:  # a shot that exists, or the first page: keep its pages warm
                pool.want(self.application_context, self.application, shot_id, hub)
            return session

        def _hand_out(self, session, app):
            """The warm page becomes this request's: its token (expiry, cookies, headers,
            arguments), its request as Panel reads it, the reviewer, and the shot as it is now."""
            from bokeh.server.contexts import _RequestProxy
            from bokeh.util.token import generate_jwt_token
            from panel.io.state import set_curdoc

            payload = self._generate_token_payload()
            token = generate_jwt_token(session.id, secret_key=self.application.secret_key,
                                       signed=self.application.sign_sessions,
                                       expiration=self.application.session_token_expiration, extra_payload=payload)
            # Bokeh keeps the token and request of the (made-up) request the page was built for;
            # the page is now this request's (private attributes: Bokeh has no API to re-key a session)
            session._token = token
            ctx = self.application_context._session_contexts.get(session.id)
            if ctx is not None:
                ctx._token = token
                ctx._request = _RequestProxy(self.request, arguments=payload.get("arguments"),
                                             cookies=payload.get("cookies"), headers=payload.get("headers"))
            session.unblock_expiration()
            import panel as pn

            with set_curdoc(session.document):
                user = getattr(pn.state, "user", None) or ""  # as create_app reads it

            def wake(doc=session.document):
                with set_curdoc(doc):
                    app.wake(user)

            pulled = getattr(session, "_face_retarget_pull", None)
            if pulled is not None:  # the page joins its shot once its document has been sent
                pulled.after_pull = wake
            else:
                wake()
            log.info("%s: %s handed out%s", *(("shot " + app.mirror.hub.shot_id[:6], "a warm page") if app.mirror
                                                else ("first page", "a page built ahead")),
                     " (its page and document made ahead)" if pulled is not None and pulled.ready() else "")
            return session

    return WarmDocHandler
