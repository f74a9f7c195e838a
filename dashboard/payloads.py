"""A viewer's mesh (neutral, faces, shape deltas) served once over HTTP, by content, to every page.

Inside a Bokeh document the mesh travels in every page's websocket: on the sample the two
viewers of a page carry 17 MB, which the server serialises again for every page that opens
(``docs/review.md``). Served from here instead, a page's document holds only the mesh's key,
the server writes the same bytes to every page (no serialisation, no per-page copy), and the
browser's HTTP cache keeps them across reloads: the key is the hash of the bytes, so the reply
never changes (``Cache-Control: immutable``).

* :func:`register` packs ``(neutral, faces, deltas)`` into one blob (:func:`pack`) and returns
  a :class:`Payload` holding it; the same arrays (by identity, for read-only arrays) or the
  same bytes give the same object, so every page of a shot shares one blob;
* only registered blobs are served, and only while a viewer holds its :class:`Payload` (the
  registry keeps weak references): a key cannot be used to read anything else;
* the route (:func:`routes`, added by ``dashboard.assets.serve``) asks for the same login as
  the pages (Bokeh's auth provider: ``--password``, OAuth);
* :func:`enable` is called by that server: until then (a notebook, ``panel serve`` without our
  routes) viewers send the blob inside the document, as before.

Blob layout (little-endian): ``b"FRG1"``, then V, F, K as uint32, then neutral (V, 3) float32,
faces (F, 3) uint32 and deltas (K, V, 3) float32 — what ``static/viewer.js`` reads
(``decodeGeometry``).
"""

from __future__ import annotations

import hashlib
import threading
import weakref

import numpy as np

#: URL path (relative to the server root) of the blobs: ``/<ROUTE>/<key>``
ROUTE = "face-retarget/payload"

MAGIC = b"FRG1"

#: bytes written to a connection before waiting for them to leave
CHUNK = 1 << 20

_enabled = False
_lock = threading.Lock()
# key -> Payload, only while some viewer holds it
_BY_KEY: "weakref.WeakValueDictionary[str, Payload]" = weakref.WeakValueDictionary()
# (id(neutral), id(faces), id(deltas)) -> (weak refs of the three arrays, weak ref of the Payload):
# read-only arrays are the pipeline's frozen results shared by every page, so packing and
# hashing them once serves every page of the shot
_BY_SOURCE: dict = {}


class Payload:
    """One packed mesh: :attr:`key` (hex blake2b-128 of :attr:`data`), :attr:`data` (bytes)."""

    __slots__ = ("key", "data", "__weakref__")

    def __init__(self, key: str, data: bytes):
        self.key = key
        self.data = data

    @property
    def url(self) -> str:
        """Path relative to the server root (the page resolves it against its own address)."""
        return f"{ROUTE}/{self.key}"


def enable(on: bool = True) -> None:
    """Declare that this process's server answers :data:`ROUTE` (``dashboard.assets.serve``)."""
    global _enabled
    _enabled = bool(on)


def enabled() -> bool:
    return _enabled


def pack(neutral: np.ndarray, faces: np.ndarray, deltas: np.ndarray) -> bytes:
    """The blob of a (V, 3) neutral, (F, 3) faces and (K, V, 3) deltas (see the module doc)."""
    n = np.ascontiguousarray(neutral, dtype="<f4").reshape(-1, 3)
    f = np.ascontiguousarray(faces, dtype="<u4").reshape(-1, 3)
    d = np.ascontiguousarray(deltas, dtype="<f4").reshape(-1, len(n), 3)
    head = MAGIC + np.array([len(n), len(f), len(d)], dtype="<u4").tobytes()
    return b"".join((head, n.tobytes(), f.tobytes(), d.tobytes()))


def unpack(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`pack` (tests, and a check of what the browser reads)."""
    if data[:4] != MAGIC:
        raise ValueError("not a face-retarget mesh payload (bad magic)")
    V, F, K = (int(x) for x in np.frombuffer(data, dtype="<u4", count=3, offset=4))
    if len(data) != 16 + 12 * (V + F + K * V):
        raise ValueError(f"mesh payload: {len(data)} bytes, expected {16 + 12 * (V + F + K * V)}")
    o = 16
    n = np.frombuffer(data, dtype="<f4", count=3 * V, offset=o).reshape(V, 3)
    o += 12 * V
    f = np.frombuffer(data, dtype="<u4", count=3 * F, offset=o).reshape(F, 3)
    o += 12 * F
    d = np.frombuffer(data, dtype="<f4", count=3 * V * K, offset=o).reshape(K, V, 3)
    return n, f, d


def register(neutral: np.ndarray, faces: np.ndarray, deltas: np.ndarray) -> Payload:
    """The :class:`Payload` of these arrays, shared with every other holder of the same mesh.
    Keep the returned object as long as a page may fetch it (the registry only refers to it)."""
    arrays = (neutral, faces, deltas)
    frozen = all(isinstance(a, np.ndarray) and not a.flags.writeable for a in arrays)
    sid = tuple(id(a) for a in arrays)
    with _lock:
        if frozen:
            hit = _BY_SOURCE.get(sid)
            if hit is not None and all(r() is a for r, a in zip(hit[0], arrays)):
                p = hit[1]()
                if p is not None:
                    return p
    data = pack(*arrays)
    key = hashlib.blake2b(data, digest_size=16).hexdigest()
    with _lock:
        p = _BY_KEY.get(key)
        if p is None:
            p = Payload(key, data)
            _BY_KEY[key] = p
        if frozen:
            try:
                refs = tuple(weakref.ref(a, lambda r, sid=sid: _BY_SOURCE.pop(sid, None)) for a in arrays)
            except TypeError:  # an array view that takes no weak reference: not cached by identity
                return p
            _BY_SOURCE[sid] = (refs, weakref.ref(p))
    return p


def lookup(key: str) -> Payload | None:
    with _lock:
        return _BY_KEY.get(key)


def _handler():
    from bokeh.server.views.auth_request_handler import AuthRequestHandler
    from tornado.web import HTTPError, authenticated

    class PayloadHandler(AuthRequestHandler):
        """``GET /face-retarget/payload/<key>``: a registered mesh blob, behind the pages' login."""

        @authenticated
        async def get(self, key: str):
            p = lookup(key) if len(key) == 32 and all(c in "0123456789abcdef" for c in key) else None
            if p is None:
                raise HTTPError(404, reason="no such mesh (it is no longer shown by any page)")
            etag = f'"{p.key}"'
            self.set_header("Content-Type", "application/octet-stream")
            # the key is the content's hash: the reply never changes; private: behind a login
            self.set_header("Cache-Control", "private, max-age=31536000, immutable")
            self.set_header("ETag", etag)
            if self.request.headers.get("If-None-Match") == etag:
                self.set_status(304)
                return
            self.set_header("Content-Length", str(len(p.data)))
            # in pieces, each written out before the next: twenty pages fetching 15 MB at once
            # would otherwise hold 300 MB of copies in Tornado's output buffers
            for i in range(0, len(p.data), CHUNK):
                self.write(p.data[i:i + CHUNK])
                await self.flush()

        def compute_etag(self):  # ours is the key; Tornado's would hash the 10 MB reply again
            return None

    return PayloadHandler


def routes() -> list:
    """The Tornado route of the blobs (``dashboard.assets.serve`` adds it and calls :func:`enable`)."""
    return [(rf"/{ROUTE}/([^/]+)", _handler(), {})]
