"""The dashboard's normal-map view (Liu 2011 §5) without a browser: what it sends the viewers.

The blended map is checked against core.normalmap called on the full (K+1, H, W, 3) maps
(the view calls the same functions on the covered texels and the active shapes only), the
image convention against the rig's own vertex normals, the regional path against eq. 3 with
masks, and the traffic (only the map changes with the frame).
"""

from __future__ import annotations

import numpy as np
import param
import pytest

from core.normalmap import (angle_deg, blend_normal_maps, frame_blend_weights, mask_maps, shape_normal_maps,
                            texture_coordinates, vertex_normals_seamless)
from core.pipeline import Pipeline, StageCache
from datapaths import PERFORMANCES, RIGS

CACHE = StageCache()


def target_pipeline(rig_file="ict_facekit.glb", **settings):
    return Pipeline(cache=CACHE, target_rig=str(RIGS / rig_file), **settings)


def bake(pipe):
    return pipe.results(["normalmap_bake"])["normalmap_bake"]["bake"]


@pytest.fixture(scope="module")
def track(ict):
    """(6, K) sparse weights in [0, 1]; frame 3 repeats frame 2."""
    rng = np.random.default_rng(3)
    W = rng.uniform(0, 1, (6, ict.n_shapes)) * (rng.random((6, ict.n_shapes)) < 0.3)
    W[3] = W[2]
    W[0] = 0.0
    return W


def snapshot(rig, W, **extra):
    snap = {"target_rig": rig, "weights": W, "fps": 30.0, "times": np.arange(len(W)) / 30.0, "method": "bounded",
            "segment": None, "solve_info": {}, "solver_names": list(rig.names)}
    snap.update(extra)
    return snap


def decode(img):
    n = 2.0 * img.astype(np.float64) / 255.0 - 1.0
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def lookup(img, st):
    """Bilinear read of an (H, W, 3) image at texture coordinates (n, 2) in [0, 1], the
    viewer's convention: column = s W − ½, row = t H − ½ (row 0 = t 0, flipY false)."""
    H, W = img.shape[:2]
    x, y = st[:, 0] * W - 0.5, st[:, 1] * H - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, W - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, H - 2)
    fx, fy = np.clip(x - x0, 0, 1)[:, None], np.clip(y - y0, 0, 1)[:, None]
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


@pytest.fixture(scope="module")
def view(ict, track):
    from dashboard.normalmap_view import NormalMapView

    v = NormalMapView(target_pipeline())
    v.update(snapshot(ict, track), 1)
    return v


def test_update_sends_a_blended_map_per_frame_and_only_the_map(view, ict, track):
    b = bake(view.pipeline)
    H, W = b.shape
    assert (H, W) == (256, 512)  # ICT's UVs span two UDIM tiles
    img = view.mapped_viewer.normal_map
    assert img.dtype == np.uint8 and img.shape == (H, W, 3)
    assert view.full_viewer.normal_map is None and view.plain_viewer.normal_map is None
    lo = view.mapped_viewer
    assert lo.uvs.shape == (len(lo.neutral), 2) and lo.uvs.dtype == np.float32
    assert lo.uvs.min() >= 0 and lo.uvs.max() <= 1
    assert len(lo.faces) < 0.12 * len(ict.faces)  # 10 % of the triangles
    assert all(v.frame == 1 for v in (view.full_viewer, view.mapped_viewer, view.plain_viewer))

    # same numbers as core on the full maps: blend_normal_maps(all K+1 maps, w, ones)
    maps = shape_normal_maps(ict, b.raster)
    ref = blend_normal_maps(maps, track[1][None], np.ones((1, H, W)))
    cov = b.raster.covered
    err = angle_deg(decode(img)[cov], ref[cov])
    assert np.percentile(err, 99) < 1.0 and err.max() < 3.0, (np.percentile(err, 99), err.max())
    # uncovered texels hold their nearest covered texel (no zero normals for bilinear filtering)
    assert np.all(np.abs(img[~cov].astype(int) - 128).sum(axis=1) > 3)

    # another frame: another map; the mesh arrays do not travel again
    ids = {k: id(getattr(lo, k)) for k in ("neutral", "faces", "deltas", "track", "uvs")}
    view.update(view._snap, 2)
    img2 = lo.normal_map
    assert img2.shape == img.shape and np.abs(img2.astype(int) - img.astype(int)).max() > 20
    assert {k: id(getattr(lo, k)) for k in ids} == ids
    assert view.full_viewer.frame == 2
    # frame 3 has frame 2's weights: nothing recomputed, nothing sent
    view.update(view._snap, 3)
    assert lo.normal_map is img2 and lo.frame == 3
    # frame 0 (all weights zero) is the neutral's map
    view.update(view._snap, 0)
    err0 = angle_deg(decode(lo.normal_map)[cov], maps[0][cov].astype(np.float64))
    assert np.percentile(err0, 99) < 1.0


def test_map_convention_reproduces_the_vertex_normals(view, ict):
    """Read at each vertex's texture coordinates with the viewer's convention, the neutral's
    map gives that vertex's normal (a flipped v would not)."""
    view.update(view._snap, 0)
    img = view.mapped_viewer.normal_map
    st = texture_coordinates(ict.uvs, bake(view.pipeline).raster)
    truth = vertex_normals_seamless(ict)
    err = angle_deg(lookup(decode(img), st), truth)
    flipped = angle_deg(lookup(decode(img[::-1]), st), truth)
    assert np.median(err) < 1.0 and np.median(flipped) > 20, (np.median(err), np.median(flipped))


@pytest.mark.slow
def test_toggle_and_resolution(view, ict):
    lo = view.mapped_viewer
    view.update(view._snap, 1)
    view.enabled = False
    assert lo.normal_map is None and "off" in view.status.object
    view.enabled = True
    assert lo.normal_map is not None and lo.normal_map.shape == (256, 512, 3)
    view.pipeline.configure(normalmap_resolution=512)  # the resolution widget's setting (a pipeline stage's)
    assert lo.normal_map.shape == (512, 1024, 3)
    assert view.mapped_viewer is lo  # no rebuild: only the map changed
    view.pipeline.configure(normalmap_resolution=256)
    assert lo.normal_map.shape == (256, 512, 3)


def test_own_frame_slider_draws_and_reports(ict, track):
    from dashboard.normalmap_view import NormalMapView

    seen = []
    v = NormalMapView(target_pipeline(), on_frame=seen.append)
    v.update(snapshot(ict, track), 1)
    assert (v.w_frame.start, v.w_frame.end, v.w_frame.value) == (0, len(track) - 1, 1) and seen == []
    before = v.mapped_viewer.normal_map
    with param.edit_constant(v.w_frame):
        v.w_frame.value_throttled = 4  # what a released slider handle sends
    assert seen == [4] and v.mapped_viewer.frame == 4 and v.full_viewer.frame == 4
    assert v.mapped_viewer.normal_map is not before
    v.update(v._snap, 4)  # the app following back: nothing new, no report
    assert seen == [4]


def test_inactive_view_defers_work(ict, track):
    from dashboard.normalmap_view import NormalMapView

    v = NormalMapView(target_pipeline(), active=False)
    v.update(snapshot(ict, track), 2)
    assert v.mapped_viewer is None and v.body.objects == []
    v.active = True
    assert v.mapped_viewer is not None and v.mapped_viewer.frame == 2 and v.mapped_viewer.normal_map is not None


@pytest.mark.slow
def test_local_method_blends_with_region_masks(ict):
    """Local results (a real session: the Live Link take on ICT, 3 regions): eq. 3 with the
    regional weights and the masks of the pipeline's segmentation; after an edit (shown weights
    no longer the mask blend of the regional ones) the global weights are used."""
    from dashboard.normalmap_view import NormalMapView
    from dashboard.session import Session

    s = Session(cache=CACHE)
    s.use_files(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
                target_rig=str(RIGS / "ict_facekit.glb"))
    s.pipeline.configure(method="local", regions=3, last_frame=9, target_shapes="")
    assert s.recompute(), s.error
    snap = s.snapshot
    masks, U = snap["segment"]["masks"], snap["solve_info"]["region_weights"]
    Ur, use_masks, note = frame_blend_weights(snap["weights"], 4, ict.names, U, masks, snap["solver_names"])
    assert use_masks and Ur.shape == (len(masks), ict.n_shapes) and note == f"{len(masks)} regions"
    view = NormalMapView(s.pipeline)
    view.update(snap, 4)
    img = view.mapped_viewer.normal_map
    b = bake(s.pipeline)
    maps = shape_normal_maps(ict, b.raster)
    ref = blend_normal_maps(maps, Ur, mask_maps(b.raster, ict.faces, masks))
    cov = b.raster.covered
    err = angle_deg(decode(img)[cov], ref[cov])
    assert np.percentile(err, 99) < 1.0
    assert "regions" in view.status.object

    edited = np.asarray(snap["weights"]) + 0.1 * (np.arange(ict.n_shapes) == 0)
    Ug, mg, note = frame_blend_weights(edited, 4, ict.names, U, masks, snap["solver_names"])
    assert not mg and Ug.shape == (1, ict.n_shapes) and "edited" in note


def test_rig_without_uvs_shows_the_hint(view, rocketbox, ict, track):
    from dashboard.normalmap_view import HINT, NormalMapView

    assert rocketbox.uvs is None
    v = NormalMapView(target_pipeline("rocketbox_female_adult_02.glb"))
    v.update(snapshot(rocketbox, np.zeros((3, rocketbox.n_shapes))), 0)
    assert v.mapped_viewer is None
    (pane,) = v.body.objects
    assert pane.object == HINT and "ict_facekit.glb" in HINT
    # and back to a rig with UVs
    v.pipeline.configure(target_rig=str(RIGS / "ict_facekit.glb"))
    v.update(snapshot(ict, track), 1)
    assert v.mapped_viewer is not None and v.mapped_viewer.normal_map is not None


def test_viewer_normal_map_params_validate(ict):
    from dashboard.viewer import MeshViewer, encode_normal_map

    n = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    rgb = encode_normal_map(n)
    assert rgb.dtype == np.uint8 and rgb.tolist() == [[128, 128, 255], [0, 128, 128], [128, 128, 128]]
    assert np.allclose(2 * rgb[:2].astype(float) / 255 - 1, n[:2], atol=1.01 / 255)
    with pytest.raises(ValueError, match="normals"):
        encode_normal_map(np.zeros((2, 2)))
    img = np.zeros((4, 8, 3), np.uint8)
    with pytest.raises(ValueError, match="needs uvs"):
        MeshViewer.from_rig(ict, normal_map=img)
    st = np.zeros((ict.n_vertices, 2))
    v = MeshViewer.from_rig(ict, uvs=st, normal_map=img)
    assert v.uvs.dtype == np.float32 and v.payload_bytes()["normal_map"] == img.nbytes
    with pytest.raises(ValueError, match=r"uvs: expected shape \(14629, 2\)"):
        v.set_uvs(st[:10])
    with pytest.raises(ValueError, match="uint8"):
        v.set_normal_map(img.astype(np.float32))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        v.set_normal_map(img[..., :2])
    v.set_normal_map(None)
    assert v.normal_map is None
    w = MeshViewer.from_rig(ict)
    with pytest.raises(ValueError, match="set uvs"):
        w.set_normal_map(img)
