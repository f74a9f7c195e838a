"""Dense correspondence (core/correspondence.py and the correspond stages): many face points
instead of 41 markers, placed by the rig pair's registration or, for a capture, by the RBF of
its layout."""

import numpy as np
import pytest

from core.correspondence import capture_correspondence, rig_correspondence, skin
from core.geometry import face_vertices
from core.pipeline import Pipeline, StageCache
from datapaths import LAYOUTS, PERFORMANCES, RIGS

CURVES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"))


def test_same_topology_is_the_identity_and_points_are_on_the_skin(ict):
    from core.io.layout import read_layout
    from core.transfer import weld_source

    layout = read_layout(LAYOUTS / "ict_facekit.json", rig=ict)
    src, tgt, w = rig_correspondence(ict, layout, weld_source(ict.neutral, ict.faces), None, ict, 300)
    assert src.n_markers == tgt.n_markers == 300 and src.names[:2] == ("d0000", "d0001")
    np.testing.assert_allclose(tgt.points(ict.neutral), src.points(ict.neutral), atol=1e-12)
    np.testing.assert_array_equal(w, 1.0)
    ids = src.vertices[:, 0]
    on = face_vertices(ict.deltas) & skin(ict.faces, ict.n_vertices, layout.vertices.ravel())
    assert on[ids].all()
    # farthest-point: well spread (no two points closer than a fraction of the face's size)
    P = ict.neutral[ids]
    d = np.linalg.norm(P[:, None] - P[None], axis=2) + np.eye(len(P))
    assert d.min() > 1e-3 * ict.size


@pytest.mark.slow
def test_dense_pipeline_on_the_tiger_uses_the_registration_once():
    pipe = Pipeline(cache=StageCache(disk=None), target_rig=str(RIGS / "jeeliz_tiger.glb"), method="bounded",
                    last_frame=59, **CURVES)  # no disk: the registration is computed here, once
    pipe.run()
    assert pipe.runs["register"] == 0 and pipe.runs["dense_correspondence"] == 0  # markers: no registration
    markers_error = np.nanmean(pipe.results(["evaluate"])["evaluate"]["marker_error_mm"])
    pipe.configure(correspondence="dense", dense_points=400)
    res = pipe.results(["shapes", "synthesize", "evaluate"])
    sh = res["shapes"]
    assert len(sh["names"]) == 400 and sh["weights"].shape == (400,)
    assert 0 < sh["weights"].min() and sh["weights"].max() <= 1
    W = res["synthesize"]["weights"]
    assert W.shape == (60, 11) and np.isfinite(W).all() and W.min() >= -1e-9 and W.max() <= 1 + 1e-9
    assert pipe.runs["register"] == 1
    # more points: the first ones are the same (a prefix of one farthest-point order), no new registration
    pipe.configure(dense_points=800)
    sh2 = pipe.results(["shapes"])["shapes"]
    assert sh2["names"][:400] == sh["names"] and pipe.runs["register"] == 1 and pipe.runs["dense_correspondence"] == 1
    assert np.isfinite(markers_error)


def test_capture_points_follow_an_affine_motion_exactly(tiger):
    """The RBF of the layout reproduces affine maps: a capture that only moves rigidly and scales
    moves every dense point by the same map."""
    from core.io.layout import read_layout
    from core.model import Performance

    layout = read_layout(LAYOUTS / "jeeliz_tiger.json", rig=tiger)
    X0 = layout.points(tiger.neutral) * 1.3 + [0.01, 0.02, -0.03]  # an actor of other proportions
    T = 5
    ang = np.linspace(0, 0.3, T)
    frames = []
    for a in ang:
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        frames.append((X0 @ R.T) * (1 + a / 3) + [0, a / 50, 0])
    cap = Performance.markers(np.stack(frames), layout.names, 60.0, name="affine")
    perf, tgt = capture_correspondence(cap, tiger, layout, 200)
    assert perf.data.shape == (T, 200, 3) and tgt.n_markers == 200
    rest = perf.data[0]
    for t, a in enumerate(ang):
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        np.testing.assert_allclose(perf.data[t], (rest @ R.T) * (1 + a / 3) + [0, a / 50, 0], atol=1e-9)


def test_dense_correspondence_of_a_marker_capture_through_the_cli(tmp_path, capsys):
    from core.cli import main

    out = tmp_path / "w.csv"
    assert main(["retarget", "--source", str(PERFORMANCES / "animface_markers_jaw_60hz.csv"), "--target-rig",
                 str(RIGS / "jeeliz_tiger.glb"), "--method", "spacetime", "--correspondence", "dense", "--dense-points",
                 "300", "--last-frame", "59", "--weights-csv", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "300 markers" in text and out.exists()


def test_rom_motion_scale_maps_the_actors_range_onto_the_characters():
    """motion_scale = rom: each point's motion is scaled by the target's range over the source's,
    so the fitted motion's range per point equals the target shapes' range."""
    pipe = Pipeline(cache=StageCache(), target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), method="bounded",
                    last_frame=119, target_shapes="arkit", **CURVES)
    raw = pipe.results(["calibrate"])["calibrate"]
    assert raw["source_scale"] is None
    pipe.configure(motion_scale="rom")
    cal = pipe.results(["calibrate"])["calibrate"]
    s = cal["source_scale"]
    st = pipe.results(["stabilize"])["stabilize"]["source"]
    np.testing.assert_allclose(cal["source"].deltas, st.deltas * s[None, :, None])
    rom_t = np.linalg.norm(cal["deltas"], axis=2).max(0)
    load = pipe.results(["load", "correspond"])
    rom_s = np.linalg.norm(load["correspond"]["source_layout"].select(st.names).points(load["load"]["source_rig"].deltas),
                           axis=2).max(0)
    np.testing.assert_allclose(s, np.clip(rom_t / rom_s, 0.1, 10))
    assert np.median(s) < 0.8  # Rocketbox's ARKit shapes move less than ICT's
