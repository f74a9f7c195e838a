"""``face-retarget serve``: the dashboard on a Panel/Bokeh server, three.js from our own route."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import uuid
from typing import Optional

from core.solvers import boxqp, spacetime


def serve(port: int = 5006, address: str = "localhost", show: bool = False, allow_websocket_origin=None,
          data_dir=None, review: bool = True, password: Optional[str] = None, max_upload_mb: float = 200.0,
          oauth: Optional[dict] = None, warm_pages: int = 4, warm_wait: float = 30.0) -> int:
    """Serve the dashboard until interrupted. No browser opens unless ``show``.

    Parameters
    ----------
    address : where to listen; ``localhost`` (the default) serves this machine only — give an
        address (e.g. ``0.0.0.0``) to share with others, together with ``password`` or ``oauth``
    data_dir : the review store's folder (shots, files by hash, notes; SQLite); default the per-user
        data folder (``core.store.data_dir``). ``review=False`` serves pages of their own (nothing kept)
    password : Panel's basic auth: one password for every reviewer (their name is asked in the page)
    max_upload_mb : the largest file a page may upload (the websocket refuses larger messages)
    oauth : ``{"provider": "github", "key": ..., "secret": ..., "redirect_uri": ..., "encryption_key": ...}``
        for Panel's OAuth (see docs/review.md)
    warm_pages : pages of every opened shot built ahead while the server is idle, so that this many
        reviewers opening it at once are served without waiting for Bokeh to build their pages
        (:mod:`dashboard.warm`; 0: none; each costs ~4.5 MB while it waits); a shot that has had
        more people on it at once keeps that many (up to 24)
    warm_wait : seconds of quiet (no change, no page asked for) before a warm page is built while
        someone is on the shot (a change made during a build waits for it); 3 s when nobody is
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    return_large_buffers()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from dashboard import assets, review as rv, warm
    from dashboard.app import create_app

    assets.three_dir()  # fail early with the `npm ci` hint when three.js is missing
    from dashboard import session as sessions

    sessions.MAX_UPLOAD = int(max_upload_mb * 2**20)
    swept = sessions.sweep_orphan_uploads()  # what killed servers left behind
    if swept:
        print(f"removed {swept} upload folder(s) of servers that are gone", flush=True)
    if review:
        server = rv.configure(data_dir, max_upload_mb)
        print(f"review store: {server.data_dir}", flush=True)
        warm.configure(warm_pages, busy_idle_s=warm_wait)
    if not (boxqp.kernel_cached() and spacetime.kernels_cached()):
        # the per-frame box QP kernel and the spacetime solver's are compiled once after an install
        # (~6 s and a few s of CPU, numba's cache): in a process of their own, so that neither this
        # server's GIL nor a request waits for them
        subprocess.Popen([sys.executable, "-c", "from core.solvers.boxqp import warm; warm(); "
                          "from core.solvers.spacetime import warm_kernels; warm_kernels()"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    origins = [f"{address}:{port}", f"localhost:{port}", f"127.0.0.1:{port}"] + list(allow_websocket_origin or [])
    # the server's loop runs here, on the main thread, until interrupted: with pn.serve(threaded=True)
    # this function returned, the main thread ended and Python began its shutdown while the
    # server thread went on, so every later import of concurrent.futures (Dask, in the Batch tab)
    # failed with "can't register atexit after shutdown" and thread pools refused new work
    kwargs = dict(websocket_origin=origins, liveness=True, threaded=False,
                  # base64 of the largest file a page may send; beyond that Tornado closes the connection
                  websocket_max_message_size=int(sessions.largest_message_file() * 1.37) + 2**20,
                  # a page whose websocket has not connected yet is kept this long: Bokeh's 15 s
                  # dropped the first of 20 pages requested at once while the server built the
                  # others (one after another), and built it a second time when its socket came
                  unused_session_lifetime_milliseconds=UNUSED_SESSION_S * 1000)
    if password:
        import secrets

        kwargs.update(basic_auth=password, cookie_secret=secrets.token_hex(32))
    if oauth:
        kwargs.update(oauth_provider=oauth["provider"], oauth_key=oauth["key"], oauth_secret=oauth["secret"],
                      oauth_redirect_uri=oauth.get("redirect_uri"), oauth_encryption_key=oauth.get("encryption_key"),
                      cookie_secret=oauth.get("cookie_secret") or __import__("secrets").token_hex(32))
    print(f"face-retarget dashboard: http://{address}:{port}/  (Ctrl-C to stop)", flush=True)
    if review and warm.POOL is not None and not os.environ.get(COLD_FIRST_PAGE):
        # the first page (/) is built ahead once the server is idle: it answers from the stage
        # cache with its document made (dashboard.warm, issue 30); the server runs on this loop
        import panel as pn
        from tornado.ioloop import IOLoop

        kwargs["loop"], kwargs["server_id"] = IOLoop(make_current=False), uuid.uuid4().hex
        kwargs["loop"].add_callback(lambda sid=kwargs["server_id"]: warm.POOL.start(pn.state._servers[sid][0]))
    try:
        assets.serve({"/": create_app}, port=port, address=address, show=show, title="face-retarget", **kwargs)
    except KeyboardInterrupt:
        print("stopped", flush=True)
    return 0


#: set (to anything) to build the first page only when asked for, as before issue 30; kept for
#: benchmarks/bench_first_page.py's reference
COLD_FIRST_PAGE = "FACE_RETARGET_COLD_FIRST_PAGE"


#: seconds a page's session waits for its websocket before Bokeh discards it
UNUSED_SESSION_S = 120

#: allocations at least this large get their own memory mapping (see return_large_buffers)
MMAP_THRESHOLD = 256 * 1024


def return_large_buffers() -> bool:
    """Have glibc give every freed buffer of :data:`MMAP_THRESHOLD` or more straight back to the
    system. Each page served makes buffers of megabytes that live a moment (its document as JSON,
    the websocket frames, the mesh blobs' writes); glibc's own threshold rises after the first
    such buffer is freed, the later ones are then carved from the heap, which they fragment, and
    the server's resident memory grew by ~1 MB a page that was never returned (measured with 30
    pages of a shot: 5.5 → 4.5 MB a page, and 47 MB less after the first). No library sets
    ``mallopt``; ctypes does. A no-op (False) off glibc."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    M_MMAP_THRESHOLD = -3  # malloc.h
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD))
