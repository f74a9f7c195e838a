"""The viewers' meshes and weight tracks served by content (dashboard.payloads): the blobs
round-trip, every page of one mesh or track shares one blob, a blob is served only while a viewer
holds it, a viewer sends its mesh and track by URL on our server and inline elsewhere, and a real
server's page fetches the mesh and track it shows (the document carries none of them). The browser side (decodeGeometry, both paths) runs in
tests/browser/test_viewer.py and every dashboard browser test."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import requests

import review_client as rc
from dashboard import payloads
from dashboard.viewer import MeshViewer


def _mesh(V=50, F=40, K=3, seed=0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(V, 3)).astype(np.float32)
    f = rng.integers(0, V, size=(F, 3)).astype(np.uint32)
    d = rng.normal(size=(K, V, 3)).astype(np.float32)
    return n, f, d


def _rig(n, f, d):
    """A three-shape rig of these arrays, as MeshViewer.from_rig reads one."""
    class Rig:
        name, neutral, faces, deltas = "r", n, f, d
        names = ["a", "b", "c"]
        n_vertices, n_shapes = len(n), len(d)
    return Rig


def _frozen(*arrays):
    for a in arrays:
        a.flags.writeable = False
    return arrays


@pytest.fixture
def served():
    was = payloads.enabled()
    payloads.enable(True)
    yield
    payloads.enable(was)


def test_pack_round_trips_and_rejects_other_bytes():
    n, f, d = _mesh()
    blob = payloads.pack(n, f, d)
    assert len(blob) == 16 + n.nbytes + f.nbytes + d.nbytes
    n2, f2, d2 = payloads.unpack(blob)
    assert np.array_equal(n2, n) and np.array_equal(f2, f) and np.array_equal(d2, d)
    with pytest.raises(ValueError, match="magic"):
        payloads.unpack(b"GLB0" + blob[4:])
    with pytest.raises(ValueError, match="bytes"):
        payloads.unpack(blob[:-4])


def test_one_blob_per_mesh_held_only_while_a_viewer_holds_it():
    n, f, d = _frozen(*_mesh(seed=1))
    a = payloads.register(n, f, d)
    assert payloads.register(n, f, d) is a  # the same arrays: no second pack
    assert payloads.register(n.copy(), f.copy(), d.copy()) is a  # the same bytes: the same blob
    other = payloads.register(*_mesh(seed=2))
    assert other.key != a.key and len(a.key) == 32
    assert payloads.lookup(a.key) is a
    key = a.key
    del a, other
    gc.collect()
    # nobody shows it: still served for a while (a page sent its URL may not have fetched it yet)
    assert payloads.lookup(key) is not None, "a blob was dropped the moment its last viewer let it go"
    _expire_recent()
    assert payloads.lookup(key) is None, "a blob nobody shows is still served after the grace period"


def _expire_recent():
    """The grace period of blobs nobody holds ends (dashboard.payloads.KEEP_S elapsed)."""
    keep = payloads.KEEP_S
    payloads.KEEP_S = -1.0
    try:
        payloads.register(*_mesh(seed=99))  # any registration expires the old ones, then itself
    finally:
        payloads.KEEP_S = keep
    gc.collect()


def test_accept_encoding_is_read_as_http_says():
    assert payloads.accepts_gzip("gzip, deflate, br, zstd")  # Chromium's
    assert payloads.accepts_gzip("deflate, GZIP;q=0.5") and payloads.accepts_gzip("*")
    assert not payloads.accepts_gzip("") and not payloads.accepts_gzip("identity")
    assert not payloads.accepts_gzip("gzip;q=0") and not payloads.accepts_gzip("br, gzip;q=0.0")
    assert not payloads.accepts_gzip("gzip;q=x")


def test_a_mesh_blob_is_kept_compressed_and_a_track_is_not():
    import gzip

    n, f, d = _mesh(K=12, seed=7)
    d[1:] = 0  # shapes that move nothing, as most of a face's vertices in a shape
    p = payloads.register(n, f, d)
    assert p.gz is not None and gzip.decompress(p.gz) == p.data and len(p.gz) < len(p.data) / 2
    assert payloads.register_track(np.zeros((10, 3))).gz is None


def test_recent_blobs_are_kept_within_a_byte_budget():
    keep = payloads.KEEP_BYTES
    payloads.KEEP_BYTES = 3 * len(payloads.pack(*_mesh()))
    try:
        keys = [payloads.register(*_mesh(seed=100 + i)).key for i in range(5)]
        gc.collect()
        assert [payloads.lookup(k) is not None for k in keys] == [False, False, True, True, True]
    finally:
        payloads.KEEP_BYTES = keep


def test_track_blob_round_trips_and_is_shared_like_a_mesh():
    W = np.random.default_rng(4).uniform(-0.5, 1.5, size=(7, 5)).astype(np.float32)
    blob = payloads.pack_track(W)
    assert len(blob) == 16 + W.nbytes and np.array_equal(payloads.unpack_track(blob), W)
    with pytest.raises(ValueError, match="magic"):
        payloads.unpack_track(payloads.pack(*_mesh()))
    with pytest.raises(ValueError, match="bytes"):
        payloads.unpack_track(blob[:-4])
    (frozen,) = _frozen(W.copy())
    a = payloads.register_track(frozen)
    assert payloads.register_track(frozen) is a and payloads.register_track(W.copy()) is a
    # a mesh whose bytes happen to be arranged otherwise is another blob: the kinds do not mix
    assert payloads.register_track(W[:, :4].copy()).key != a.key
    key = a.key
    del a
    _expire_recent()
    assert payloads.lookup(key) is None


def test_viewer_sends_its_track_by_url_and_every_page_of_a_result_shares_it(served):
    n, f, d = _frozen(*_mesh(seed=5))
    Rig = _rig(n, f, d)

    (W,) = _frozen(np.random.default_rng(6).uniform(0, 1, size=(9, 3)))
    pages = [MeshViewer.from_rig(Rig, track=W) for _ in range(3)]
    assert len({v.track_url for v in pages}) == 1 and pages[0].track_url.startswith(payloads.ROUTE + "/")
    blob = payloads.lookup(pages[0].track_url.rsplit("/", 1)[-1]).data
    assert np.array_equal(payloads.unpack_track(blob), W.astype(np.float32))
    # the document holds the URL, not the track; Python keeps the array (n_frames, tests)
    model = pages[0].get_root()
    assert model.data.track is None and model.data.track_url == pages[0].track_url
    assert pages[0].n_frames == 9 and pages[0].track.dtype == np.float32
    # a new track is a new URL, and only the URL changes on the model
    W2 = np.zeros((4, 3))
    pages[0].set_track(W2)
    assert model.data.track_url == pages[0].track_url != pages[1].track_url and model.data.track is None
    assert pages[0].frame <= 3
    # inline (on request, or without our route): the track in the document, no URL
    pages[1].inline_geometry = True
    m1 = pages[1].get_root()
    assert pages[1].track_url == "" and m1.data.track_url == "" and np.array_equal(m1.data.track, W.astype(np.float32))
    payloads.enable(False)
    v = MeshViewer.from_rig(Rig, track=W)
    assert v.track_url == "" and np.array_equal(v.get_root().data.track, W.astype(np.float32))
    with pytest.raises(ValueError, match="NaN"):
        v.set_track(np.full((2, 3), np.nan))


def test_viewer_sends_its_mesh_by_url_on_our_server_and_inline_elsewhere(served):
    n, f, d = _frozen(*_mesh(seed=3))
    Rig = _rig(n, f, d)

    v = MeshViewer.from_rig(Rig, track=np.zeros((4, 3)))
    key = v.geometry_url.rsplit("/", 1)[-1]
    assert v.geometry_url.startswith(payloads.ROUTE + "/") and v.geometry is None
    assert np.array_equal(payloads.unpack(payloads.lookup(key).data)[2], d)
    # the arrays are not synced as such: the document holds the key only
    model = v.get_root()
    assert "neutral" not in model.data.properties() and "deltas" not in model.data.properties()
    assert model.data.geometry_url == v.geometry_url
    # new shapes: a new blob, the track with them
    v.set_shapes(d[:2] * 2, np.zeros((4, 2)), ["x", "y"])
    assert v.geometry_url != payloads.ROUTE + "/" + key and v.n_shapes == 2
    assert np.allclose(payloads.unpack(payloads.lookup(v.geometry_url.rsplit("/", 1)[-1]).data)[2], d[:2] * 2)
    # a direct assignment repacks too
    v.deltas = np.asarray(d[:2] * 3)
    assert np.allclose(payloads.unpack(payloads.lookup(v.geometry_url.rsplit("/", 1)[-1]).data)[2], d[:2] * 3)
    # inline: the blob in the document, no URL
    w = MeshViewer.from_rig(Rig, inline_geometry=True)
    assert w.geometry_url == "" and bytes(w.geometry) == payloads.pack(n, f, d)
    payloads.enable(False)
    assert MeshViewer.from_rig(Rig).geometry_url == ""


@pytest.mark.slow
def test_a_page_fetches_the_mesh_and_track_it_shows(tmp_path):
    rc.register_models()
    sid = rc.sample_shot(tmp_path / "data", "mesh", last_frame=59)
    with rc.Server("--data-dir", str(tmp_path / "data"), "--warm-pages", "0") as srv:
        async def scenario():
            (p,), _ = await rc.open_pages(srv.base, sid, 1)
            viewers = [m for m in p.doc.models if hasattr(m, "data") and hasattr(m.data, "geometry_url")]
            await p.close()
            return [(m.data.geometry_url, m.data.geometry, (m.data.track_url, m.data.track)) for m in viewers]

        found = rc.run(scenario())
        assert len(found) >= 2, found
        tracks = [t for _, _, t in found]
        assert all(u.startswith(payloads.ROUTE + "/") for u, _ in tracks), tracks
        for u, _ in tracks:
            W = payloads.unpack_track(requests.get(f"{srv.base}/{u}", timeout=30).content)
            assert W.shape[0] == 60 and np.isfinite(W).all()
        for url, inline, _ in found:
            assert url.startswith(payloads.ROUTE + "/") and inline is None, (url, inline)
            r = requests.get(f"{srv.base}/{url}", timeout=30)
            assert r.status_code == 200 and r.headers["Content-Type"] == "application/octet-stream"
            assert "immutable" in r.headers["Cache-Control"]
            n, f, d = payloads.unpack(r.content)
            assert len(n) > 100 and len(f) > 100 and len(d) >= 1 and np.isfinite(d).all()
            # sent compressed to a client that takes gzip (requests does, as browsers do): the
            # shapes' zero deltas make a rig 2.5-10x smaller on the wire
            assert r.headers["Content-Encoding"] == "gzip" and "Accept-Encoding" in r.headers["Vary"]
            assert int(r.headers["Content-Length"]) < len(r.content) / 2, (r.headers["Content-Length"], len(r.content))
            plain = requests.get(f"{srv.base}/{url}", headers={"Accept-Encoding": "identity"}, timeout=30)
            assert "Content-Encoding" not in plain.headers and plain.content == r.content
            assert plain.headers["ETag"] != r.headers["ETag"]
            again = requests.get(f"{srv.base}/{url}", headers={"If-None-Match": r.headers["ETag"]}, timeout=30)
            assert again.status_code == 304 and not again.content
        assert requests.get(f"{srv.base}/{payloads.ROUTE}/{'0' * 32}", timeout=30).status_code == 404
        assert requests.get(f"{srv.base}/{payloads.ROUTE}/..%2F..%2Fetc%2Fpasswd", timeout=30).status_code == 404
