"""Marker layout JSON (core.io.layout) and the bundled layouts in data/layouts/."""

import csv
import json
import warnings

import numpy as np
import pytest

from datapaths import LAYOUTS, PERFORMANCES, RIGS
from core.io.layout import LayoutError, LayoutRigMismatch, default_layout_path, read_layout, write_layout
from core.model import MarkerLayout
from core.names import canonical

STEMS = ("ict_facekit", "rocketbox_female_adult_02", "jeeliz_tiger", "jeeliz_triceratops")
HUMANS = ("ict_facekit", "rocketbox_female_adult_02")


def animface_names():
    with open(PERFORMANCES / "animface_markers_jaw_60hz.csv") as f:
        header = next(csv.reader(f))
    return [c[:-2] for c in header[2::3]]


def doc(markers, rig="ict_facekit.glb", **extra):
    d = {"format": "face-retarget marker layout", "version": 1, "rig": rig, "markers": markers, "notes": ""}
    d.update(extra)
    return d


def dump(tmp_path, obj, name="x.json"):
    p = tmp_path / name
    p.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return p


# -- format --------------------------------------------------------------------------------------
def test_roundtrip_vertex_and_face_markers(tmp_path, ict):
    f = 1000
    tri = ict.faces[f]
    layout = MarkerLayout(["A", "B"], [[5, 5, 5], tri], [[1, 0, 0], [0.2, 0.3, 0.5]], "ict_facekit.glb",
                          {"faces": np.array([-1, f]), "notes": "n"})
    p = write_layout(tmp_path / "l.json", layout)
    raw = json.loads(p.read_text())
    assert raw["markers"]["A"] == {"vertex": 5}
    assert raw["markers"]["B"]["face"] == f and raw["markers"]["B"]["vertices"] == tri.tolist()
    back = read_layout(p, ict)
    assert back.names == ("A", "B") and back.rig == "ict_facekit.glb" and back.extras["notes"] == "n"
    np.testing.assert_array_equal(back.vertices, layout.vertices)
    np.testing.assert_allclose(back.weights, layout.weights, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.points(ict.neutral), layout.points(ict.neutral), rtol=0, atol=1e-9 * ict.size)
    # without the rig the file is self-contained: same points
    np.testing.assert_array_equal(read_layout(p).vertices, layout.vertices)


def test_barycentric_marker_without_known_face_roundtrips(tmp_path, ict):
    layout = MarkerLayout(["A"], [ict.faces[3]], [[0.1, 0.6, 0.3]], "ict_facekit.glb")  # no extras["faces"]
    p = write_layout(tmp_path / "l.json", layout)
    assert "face" not in json.loads(p.read_text())["markers"]["A"]
    back = read_layout(p, ict)
    np.testing.assert_array_equal(back.vertices, layout.vertices)
    np.testing.assert_allclose(back.weights, layout.weights, atol=1e-12)


def test_face_marker_without_vertices_is_resolved_from_the_rig(tmp_path, ict):
    p = dump(tmp_path, doc({"M": {"face": 7, "barycentric": [0.5, 0.25, 0.25]}}))
    lay = read_layout(p, ict)
    np.testing.assert_array_equal(lay.vertices[0], ict.faces[7])
    with pytest.raises(LayoutError, match="needs the rig"):
        read_layout(p)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", r"x\.json: not valid JSON"),
        (json.dumps([1, 2]), "top level"),
        (json.dumps(doc({"A": {"vertex": 1}}, format="something else")), "field 'format'"),
        (json.dumps(doc({"A": {"vertex": 1}}, version=2)), "field 'version' must be 1"),
        (json.dumps({"format": "face-retarget marker layout", "version": 1, "markers": {"A": {"vertex": 1}}}), "missing field 'rig'"),
        (json.dumps({"format": "face-retarget marker layout", "version": 1, "rig": "ict_facekit.glb"}), "missing field 'markers'"),
        (json.dumps(doc({})), "non-empty"),
        (json.dumps(doc({"A": {"vertex": -3}})), r"marker 'A': 'vertex' must be >= 0"),
        (json.dumps(doc({"A": {"vertex": 1.5}})), "integer index"),
        (json.dumps(doc({"A": {"vert": 1}})), "needs 'vertex' or 'face'"),
        (json.dumps(doc({"A": {"face": 3}})), "needs 'barycentric'"),
        (json.dumps(doc({"A": {"face": 3, "vertices": [1, 2, 3], "barycentric": [0.5, 0.5, 0.5]}})), "sum to 1"),
        (json.dumps(doc({"A": {"face": 3, "vertices": [1, 2, 3], "barycentric": [1.5, -0.5, 0.0]}})), ">= 0"),
        (json.dumps(doc({"A": {"face": 3, "vertices": [1, 2], "barycentric": [1, 0, 0]}})), "3 vertex indices"),
        ('{"format": "face-retarget marker layout", "version": 1, "rig": "r.glb", "markers": {"A": {"vertex": 1}, "A": {"vertex": 2}}}',
         "duplicate key 'A'"),
    ],
)
def test_bad_files_name_the_file_and_the_problem(tmp_path, content, message):
    p = dump(tmp_path, content)
    with pytest.raises(LayoutError, match=message) as e:
        read_layout(p)
    assert "x.json" in str(e.value)


def test_index_out_of_range_for_the_rig(tmp_path, ict):
    p = dump(tmp_path, doc({"ForeHead_M": {"vertex": 3}, "Chin_L2": {"vertex": 20000}}))
    with pytest.raises(LayoutError, match=r"layout x\.json marker 'Chin_L2': vertex 20000 out of range for rig ict_facekit \(14629 vertices\)"):
        read_layout(p, ict)
    read_layout(p)  # without a rig only the form is checked
    p = dump(tmp_path, doc({"A": {"face": 10 ** 6, "barycentric": [1, 0, 0]}}))
    with pytest.raises(LayoutError, match="face 1000000 out of range for rig ict_facekit"):
        read_layout(p, ict)
    p = dump(tmp_path, doc({"A": {"face": 0, "vertices": [1, 2, 3], "barycentric": [1, 0, 0]}}))
    with pytest.raises(LayoutError, match="are not face 0 of rig ict_facekit"):
        read_layout(p, ict)


def test_layout_for_another_rig_warns_or_raises(tmp_path, rocketbox):
    p = dump(tmp_path, doc({"A": {"vertex": 3}}, rig="ict_facekit.glb"))
    with pytest.warns(LayoutRigMismatch, match="made for rig 'ict_facekit.glb', not 'rocketbox_female_adult_02'"):
        read_layout(p, rocketbox)
    with pytest.raises(LayoutError, match="made for rig"):
        read_layout(p, rocketbox, strict_rig=True)
    # and the bundled ICT layout used on Rocketbox: indices beyond its 2,458 vertices are refused
    with pytest.warns(LayoutRigMismatch), pytest.raises(LayoutError, match="out of range for rig rocketbox_female_adult_02"):
        read_layout(LAYOUTS / "ict_facekit.json", rocketbox)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        read_layout(tmp_path / "nope.json")


def test_default_layout_path(tmp_path):
    for stem in STEMS:
        assert default_layout_path(RIGS / f"{stem}.glb") == LAYOUTS / f"{stem}.json"
        assert default_layout_path(f"/somewhere/else/{stem}.glb") == LAYOUTS / f"{stem}.json"
    assert default_layout_path(tmp_path / "my_own_rig.glb") is None


# -- the bundled layouts ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def layouts(rigs):
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # each file names its own rig: no mismatch warning
        for stem in STEMS:
            out[stem] = read_layout(LAYOUTS / f"{stem}.json", rigs[stem])
    return out


def test_bundled_layouts_have_all_animface_markers(layouts):
    names = animface_names()
    assert len(names) == 41
    for stem, lay in layouts.items():
        assert lay.names == tuple(names), stem
        assert lay.rig == f"{stem}.glb"
        assert lay.extras["notes"]


def pos(lay, rig):
    return dict(zip(lay.names, lay.points(rig.neutral)))


@pytest.mark.parametrize("stem", STEMS)
def test_left_is_plus_x_and_midline_is_centred(layouts, rigs, stem):
    rig, p = rigs[stem], pos(layouts[stem], rigs[stem])
    x0 = p["NoseHead"][0]
    pairs = [(n, n.replace("L", "R", 1)) for n in p if n.startswith("L") and n.replace("L", "R", 1) in p]
    pairs += [(n, n[:-1] + "R") for n in p if n.endswith("_L") and n[:-1] + "R" in p]
    pairs += [("Mouth_Lend", "Mouth_Rend"), ("Mouth_UpL1", "Mouth_UpR1"), ("Mouth_DownL", "Mouth_DownR"),
              ("Chin_L1", "Chin_R1"), ("Chin_L2", "Chin_R2"), ("NoseHead_L", "NoseHead_R")]
    assert len(pairs) >= 18
    for left, right in pairs:
        assert p[left][0] > x0 > p[right][0], (stem, left, right)
    for n in ("ForeHead_M", "Eyebrow_Center", "NoseTop", "Mouth_Up", "Mouth_Down", "Chin"):
        assert abs(p[n][0] - x0) < 0.01 * rig.size, (stem, n)


@pytest.mark.parametrize("stem", STEMS)
def test_vertical_order(layouts, rigs, stem):
    p = pos(layouts[stem], rigs[stem])
    y = {n: v[1] for n, v in p.items()}
    chain = ["ForeHead_M", "Eyebrow_Center", "NoseHead", "Mouth_Up", "Mouth_Down", "Chin"]
    assert all(y[a] > y[b] for a, b in zip(chain, chain[1:])), {n: y[n] for n in chain}
    for s in "LR":
        assert y[f"{s}eyebrow_M"] > y[f"{s}eye_Up"] > y[f"{s}eye_Down"]
        assert y[f"{s}eye_Up"] > y[f"{s}eye_Inside"] > y[f"{s}eye_Down"]
    if stem != "jeeliz_triceratops":  # a beak's slit rises towards its corners, far back
        assert y["Mouth_Up"] > y["Mouth_Lend"] > y["Mouth_Down"]
    assert y["Mouth_Up"] > y["Mouth_Down"] and y["Mouth_Lend"] > y["Chin"]


def shape_motion(lay, rig, shape):
    d = np.linalg.norm(lay.points(rig.deltas[rig.index(shape)]), axis=1)
    return dict(zip(lay.names, d)), np.linalg.norm(rig.deltas[rig.index(shape)], axis=1).max()


SHAPES = {
    "ict_facekit": dict(blink=("eyeBlink_L", "eyeBlink_R"), jaw="jawOpen"),
    "rocketbox_female_adult_02": dict(blink=("AK_09_EyeBlinkLeft", "AK_10_EyeBlinkRight"), jaw="AK_25_JawOpen"),
    "jeeliz_tiger": dict(blink=("eyeLeftClose", "eyeRightClose"), jaw="mouthOpen"),
    "jeeliz_triceratops": dict(blink=("eyeLeftClose", "eyeRightClose"), jaw="mouthOpen"),
}


@pytest.mark.parametrize("stem", STEMS)
def test_lid_markers_ride_the_blink(layouts, rigs, stem):
    lay, rig = layouts[stem], rigs[stem]
    for side, shape in zip("LR", SHAPES[stem]["blink"]):
        other = "R" if side == "L" else "L"
        m, dmax = shape_motion(lay, rig, shape)
        assert m[f"{side}eye_Up"] > 0.5 * dmax, (shape, m[f"{side}eye_Up"], dmax)
        assert m[f"{side}eye_Up"] > 2 * m[f"{side}eye_Down"]
        assert m[f"{other}eye_Up"] < 0.05 * dmax  # the other eye stays open
        assert m["Mouth_Down"] < 0.05 * dmax


@pytest.mark.parametrize("stem", STEMS)
def test_lower_lip_and_chin_ride_the_jaw(layouts, rigs, stem):
    lay, rig = layouts[stem], rigs[stem]
    m, _ = shape_motion(lay, rig, SHAPES[stem]["jaw"])
    dmax = max(m.values())  # relative to the marker the jaw moves most (the shape's global
    # maximum can be inside the mouth)
    assert dmax > 0.5 * _ and max(m, key=m.get) in ("Mouth_Down", "Chin", "Mouth_DownL", "Mouth_DownR")
    for n in ("Mouth_Down", "Mouth_DownL", "Mouth_DownR", "Chin"):
        assert m[n] > 0.4 * dmax, (n, m[n], dmax)
    for n in ("Chin_L1", "Chin_R1"):
        assert m[n] > 0.3 * dmax, (n, m[n], dmax)
    for n in ("Chin_L2", "Chin_R2"):
        assert m[n] > 0.15 * dmax, (n, m[n], dmax)
    for n in ("Mouth_Up", "Mouth_UpL1", "Mouth_UpR1", "NoseHead", "Leye_Up", "ForeHead_M"):
        assert m[n] < 0.35 * dmax, (n, m[n], dmax)
    assert m["Mouth_Down"] > 2 * m["Mouth_Up"]


@pytest.mark.parametrize("stem", HUMANS)
def test_human_shapes_move_their_markers_most(layouts, rigs, stem):
    """Per ARKit shape, the marker it moves most is one an artist would expect."""
    lay, rig = layouts[stem], rigs[stem]
    expect = {
        "mouthSmileLeft": {"Mouth_Lend", "Mouth_UpL1", "Mouth_DownL"},
        "mouthSmileRight": {"Mouth_Rend", "Mouth_UpR1", "Mouth_DownR"},
        "browOuterUpLeft": {"Leyebrow_Outside", "Leyebrow_M"},
        "browOuterUpRight": {"Reyebrow_Outside", "Reyebrow_M"},
        "eyeBlinkLeft": {"Leye_Up"},
        "jawOpen": {"Mouth_Down", "Chin"},
    }
    by_canon = {canonical(n): n for n in rig.names}
    for shape, allowed in expect.items():
        m, _ = shape_motion(lay, rig, by_canon[shape])
        assert max(m, key=m.get) in allowed, (shape, max(m, key=m.get))


@pytest.mark.parametrize("stem", STEMS)
def test_markers_are_on_the_skin(layouts, rigs, stem):
    from core.geometry import largest_component

    rig, lay = rigs[stem], layouts[stem]
    on_skin = np.zeros(rig.n_vertices, bool)
    on_skin[rig.faces[largest_component(rig.neutral, rig.faces)].ravel()] = True
    assert on_skin[lay.vertices].all()
    # distinct spots: no two markers closer than 1 mm
    p = lay.points(rig.neutral)
    d = np.linalg.norm(p[:, None] - p[None], axis=2) + np.eye(len(p))
    assert d.min() > 1e-3, stem


def test_rocketbox_layout_is_reproduced_by_the_script(rocketbox, layouts):
    """scripts/make_layouts.py regenerates the bundled file exactly (same rules, same data)."""
    import sys

    from datapaths import ROOT

    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import make_layouts
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    names, actor = make_layouts.animface_rest()
    stem = "rocketbox_female_adult_02"
    lay, aligned, info = make_layouts.place(rocketbox, make_layouts.CONFIG[stem], names, actor, log=lambda *a: None)
    np.testing.assert_array_equal(lay.vertices, layouts[stem].vertices)
    # the similarity + ICP put the actor on the rig's face: the aligned actor markers are a few mm
    # from their final vertices (measured median 7.5 mm: 2.5k-vertex mesh, lip/lid rules); a broken
    # alignment (e.g. mouth corners found at the nostrils, as in an early version) gave > 30 mm
    assert np.median(info["snap_mm"]) < 10.0
