"""A viewer's mesh (neutral, faces, shape deltas) and weight track served once over HTTP, by
content, to every page.

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
  registry keeps weak references) or for :data:`KEEP_S` after it was last registered (the
  newest :data:`KEEP_BYTES` of them): a page is sent a document naming a blob, and may be
  changed (a new track) before its browser has fetched the old one; a key cannot be used to
  read anything else;
* the route (:func:`routes`, added by ``dashboard.assets.serve``) asks for the same login as
  the pages (Bokeh's auth provider: ``--password``, OAuth);
* :func:`enable` is called by that server: until then (a notebook, ``panel serve`` without our
  routes) viewers send the blob inside the document, as before.

A mesh blob is also kept gzip-compressed (:attr:`Payload.gz`, made once when it is registered:
0.13 s for the sample's two rigs) and sent so to a browser that accepts it (``Content-Encoding:
gzip``; the browser inflates it natively before ``viewer.js`` reads it): shape deltas are mostly
zeros (a shape moves a part of the face), so 15 MB become 4.4 MB per page (ICT 9.8 → 3.9 MB,
Rocketbox 5.2 → 0.5 MB) — what a reviewer on another machine downloads to open a shot.

The weight track (T, K) goes the same way (:func:`register_track`): a shared shot's change
gives every page a new track (1.4 MB on the sample), which Bokeh serialised and wrote into each
page's websocket; now the server packs it once and every page gets its URL.

Blob layouts (little-endian), what ``static/viewer.js`` reads:

* mesh (``decodeGeometry``): ``b"FRG1"``, then V, F, K as uint32, then neutral (V, 3) float32,
  faces (F, 3) uint32 and deltas (K, V, 3) float32;
* track (``decodeTrack``): ``b"FRT1"``, then T, K and 0 as uint32, then the (T, K) float32 rows.
"""

from __future__ import annotations

import gzip
import hashlib
import threading
import time
import weakref
from collections import OrderedDict

import numpy as np

#: URL path (relative to the server root) of the blobs: ``/<ROUTE>/<key>``
ROUTE = "face-retarget/payload"

MAGIC = b"FRG1"
TRACK_MAGIC = b"FRT1"

#: bytes written to a connection before waiting for them to leave
CHUNK = 1 << 20
#: seconds a blob stays served after it was last registered, though no viewer holds it any more
KEEP_S = 120.0
#: ... and at most this many bytes of such blobs (the newest kept)
KEEP_BYTES = 64 << 20

_enabled = False
_lock = threading.Lock()
# key -> Payload, only while some viewer holds it
_BY_KEY: "weakref.WeakValueDictionary[str, Payload]" = weakref.WeakValueDictionary()
# (kind, id of each array) -> (weak refs of the arrays, weak ref of the Payload): read-only
# arrays are the pipeline's frozen results shared by every page, so packing and hashing them
# once serves every page of the shot
_BY_SOURCE: dict = {}
# key -> (Payload, time last registered): strong references for KEEP_S (see the module doc)
_RECENT: "OrderedDict[str, tuple]" = OrderedDict()


#: zlib level of :attr:`Payload.gz` (1: 3× smaller on the sample meshes at a third of level 6's
#: time; level 6 gains 5% more)
GZIP_LEVEL = 1


class Payload:
    """One packed blob: :attr:`key` (hex blake2b-128 of :attr:`data`), :attr:`data` (bytes),
    :attr:`gz` (the same gzip-compressed, or None when it is not kept compressed)."""

    __slots__ = ("key", "data", "gz", "__weakref__")

    def __init__(self, key: str, data: bytes, gz: bytes | None = None):
        self.key = key
        self.data = data
        self.gz = gz

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


def pack_track(track: np.ndarray) -> bytes:
    """The blob of a (T, K) weight track (see the module doc)."""
    t = np.ascontiguousarray(track, dtype="<f4")
    if t.ndim != 2:
        raise ValueError(f"track: expected (T, K), got shape {t.shape}")
    return TRACK_MAGIC + np.array([t.shape[0], t.shape[1], 0], dtype="<u4").tobytes() + t.tobytes()


def unpack_track(data: bytes) -> np.ndarray:
    """Inverse of :func:`pack_track`."""
    if data[:4] != TRACK_MAGIC:
        raise ValueError("not a face-retarget track payload (bad magic)")
    T, K = (int(x) for x in np.frombuffer(data, dtype="<u4", count=2, offset=4))
    if len(data) != 16 + 4 * T * K:
        raise ValueError(f"track payload: {len(data)} bytes, expected {16 + 4 * T * K}")
    return np.frombuffer(data, dtype="<f4", count=T * K, offset=16).reshape(T, K)


def register(neutral: np.ndarray, faces: np.ndarray, deltas: np.ndarray) -> Payload:
    """The :class:`Payload` of this mesh, shared with every other holder of the same mesh.
    Keep the returned object as long as a page may fetch it (the registry only refers to it)."""
    return _register((neutral, faces, deltas), pack, compress=True)


def register_track(track: np.ndarray) -> Payload:
    """The :class:`Payload` of a (T, K) weight track, shared like a mesh (see :func:`register`)."""
    return _register((track,), pack_track)


def _register(arrays: tuple, packer, compress: bool = False) -> Payload:
    frozen = all(isinstance(a, np.ndarray) and not a.flags.writeable for a in arrays)
    sid = (packer.__name__,) + tuple(id(a) for a in arrays)
    with _lock:
        if frozen:
            hit = _BY_SOURCE.get(sid)
            if hit is not None and all(r() is a for r, a in zip(hit[0], arrays)):
                p = hit[1]()
                if p is not None:
                    _keep(p)
                    return p
    data = packer(*arrays)
    key = hashlib.blake2b(data, digest_size=16).hexdigest()
    with _lock:
        p = _BY_KEY.get(key)
    if p is None:
        # outside the lock: compressing a rig takes ~0.1 s; two threads racing make the same bytes
        p = Payload(key, data, gzip.compress(data, GZIP_LEVEL, mtime=0) if compress else None)
    with _lock:
        p = _BY_KEY.setdefault(key, p)
        _keep(p)
        if frozen:
            try:
                refs = tuple(weakref.ref(a, lambda r, sid=sid: _BY_SOURCE.pop(sid, None)) for a in arrays)
            except TypeError:  # an array view that takes no weak reference: not cached by identity
                return p
            _BY_SOURCE[sid] = (refs, weakref.ref(p))
    return p


def _keep(p: Payload) -> None:
    """Hold ``p`` for :data:`KEEP_S` from now, dropping the oldest held beyond :data:`KEEP_BYTES`
    (call with the lock held)."""
    now = time.monotonic()
    _RECENT[p.key] = (p, now)
    _RECENT.move_to_end(p.key)
    held = sum(len(q.data) for q, _ in _RECENT.values())
    while _RECENT:
        q, t = next(iter(_RECENT.values()))
        if now - t <= KEEP_S and held <= KEEP_BYTES:
            break
        _RECENT.popitem(last=False)
        held -= len(q.data)


def lookup(key: str) -> Payload | None:
    with _lock:
        return _BY_KEY.get(key)


def accepts_gzip(accept_encoding: str) -> bool:
    """Whether an ``Accept-Encoding`` header value takes gzip (``gzip`` or ``*``, not at ``q=0``)."""
    for item in accept_encoding.split(","):
        coding, _, params = item.strip().partition(";")
        if coding.strip().lower() not in ("gzip", "x-gzip", "*"):
            continue
        q = params.strip().lower()
        if q.startswith("q="):
            try:
                return float(q[2:]) > 0
            except ValueError:
                return False
        return True
    return False


def _handler():
    from bokeh.server.views.auth_request_handler import AuthRequestHandler
    from tornado.web import HTTPError, authenticated

    class PayloadHandler(AuthRequestHandler):
        """``GET /face-retarget/payload/<key>``: a registered blob (mesh or track), behind the pages' login."""

        @authenticated
        async def get(self, key: str):
            p = lookup(key) if len(key) == 32 and all(c in "0123456789abcdef" for c in key) else None
            if p is None:
                raise HTTPError(404, reason="no such mesh or track (it is no longer shown by any page)")
            gz = p.gz is not None and accepts_gzip(self.request.headers.get("Accept-Encoding", ""))
            body = p.gz if gz else p.data
            etag = f'"{p.key}-gz"' if gz else f'"{p.key}"'  # one tag per representation (RFC 9110 8.8.3)
            self.set_header("Content-Type", "application/octet-stream")
            # the key is the content's hash: the reply never changes; private: behind a login
            self.set_header("Cache-Control", "private, max-age=31536000, immutable")
            self.set_header("ETag", etag)
            if p.gz is not None:
                self.set_header("Vary", "Accept-Encoding")
            if self.request.headers.get("If-None-Match") == etag:
                self.set_status(304)
                return
            if gz:
                self.set_header("Content-Encoding", "gzip")
            self.set_header("Content-Length", str(len(body)))
            # in pieces, each written out before the next: twenty pages fetching 15 MB at once
            # would otherwise hold 300 MB of copies in Tornado's output buffers
            for i in range(0, len(body), CHUNK):
                self.write(body[i:i + CHUNK])
                await self.flush()

        def compute_etag(self):  # ours is the key; Tornado's would hash the 10 MB reply again
            return None

    return PayloadHandler


def routes() -> list:
    """The Tornado route of the blobs (``dashboard.assets.serve`` adds it and calls :func:`enable`)."""
    return [(rf"/{ROUTE}/([^/]+)", _handler(), {})]
