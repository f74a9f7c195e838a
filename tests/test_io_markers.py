"""Marker CSV / TRC / C3D readers and writers, and the read/write_performance dispatch."""

import csv
import sys
import warnings

import numpy as np
import pytest

import core.io.gltf
from datapaths import PERFORMANCES
from core.io.markers import (declared_units, read_c3d, read_marker_csv, read_trc, write_c3d,
                             write_marker_csv, write_trc)
from core.io.performance import read_performance, write_performance
from core.io.tabular import DataQualityWarning, estimate_fps
from core.model import Performance

ANIMFACE = {"animface_markers_jaw_60hz.csv": 1590, "animface_markers_eyebrows_60hz.csv": 902}
JAW = PERFORMANCES / "animface_markers_jaw_60hz.csv"


@pytest.fixture(scope="module")
def real():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return {f: read_performance(PERFORMANCES / f) for f in ANIMFACE}


def _random_markers(T=50, M=5, fps=100.0, seed=1, masked=True):
    rng = np.random.default_rng(seed)
    pos = rng.normal(0, 0.05, (T, M, 3)) + np.array([0, 1.6, 0.1])
    valid = np.ones((T, M), bool)
    if masked:
        valid[rng.integers(0, T, 6), rng.integers(0, M, 6)] = False
    names = [f"mk{m}" for m in range(M - 1)] + ["Chin L2"]  # a space in a name survives
    return Performance.markers(pos, names, fps, valid=valid, name="rand")


def _assert_same(back, perf, atol):
    assert back.names == perf.names and back.n_frames == perf.n_frames
    np.testing.assert_array_equal(back.valid, perf.valid)
    ok = perf.valid
    assert np.abs(back.data[ok] - perf.data[ok]).max() <= atol
    assert np.isnan(back.data[~ok]).all()


# -- the bundled AnimFace captures -------------------------------------------------------------
@pytest.mark.parametrize("fname", sorted(ANIMFACE))
def test_real_files(real, fname):
    perf = real[fname]
    assert perf.kind == "markers" and perf.n_frames == ANIMFACE[fname]
    assert perf.fps == 60.0 and perf.units == "cm"
    assert len(perf.names) == 41 and perf.names[0] == "ForeHead_M" and perf.names[-1] == "Chin_L2"
    assert "Leyebrow_Inside" in perf.names
    assert perf.valid.all()
    assert perf.duration == pytest.approx((ANIMFACE[fname] - 1) / 60, abs=1e-4)
    # a human face in metres: markers span 10-30 cm, sit ~0.8 m up (the capture's origin)
    extent = np.ptp(perf.data[0], axis=0)
    assert 0.08 < extent.max() < 0.3
    assert 0.6 < perf.data[..., 1].mean() < 1.0
    np.testing.assert_array_equal(perf.extras["frame"], np.arange(perf.n_frames))


@pytest.mark.parametrize("fname", sorted(ANIMFACE))
def test_real_values_match_csv_module(real, fname):
    with open(PERFORMANCES / fname, newline="") as f:
        rows = list(csv.reader(f))
    table = np.array([[float(c) for c in r] for r in rows[1:]])
    perf = real[fname]
    np.testing.assert_allclose(perf.data.reshape(perf.n_frames, -1), table[:, 2:] * 0.01, rtol=1e-15, atol=0)
    np.testing.assert_allclose(perf.times, table[:, 1] - table[0, 1], atol=1e-12)
    assert rows[0][2:5] == [f"{perf.names[0]}_{a}" for a in "XYZ"]


def test_units_rule(tmp_path):
    # the AnimFace file has no units comment: the reader refuses to guess ...
    with pytest.raises(ValueError, match=r"animface_markers_jaw_60hz\.csv.*no units declared.*units="):
        read_marker_csv(JAW)
    assert declared_units(JAW) is None
    # ... the caller may say so, and a '# units:' line declares them
    mm = read_marker_csv(JAW, units="mm")
    cm = read_marker_csv(JAW, units="cm")
    np.testing.assert_allclose(cm.data, 10 * mm.data)
    p = tmp_path / "decl.csv"
    p.write_text("# units: mm\n" + JAW.read_text())
    assert declared_units(p) == "mm"
    np.testing.assert_array_equal(read_performance(p).data, mm.data)  # the comment wins over the animface default
    with pytest.raises(ValueError, match=r"decl\.csv.*declares units 'mm' but units='cm'"):
        read_marker_csv(p, units="cm")
    p.write_text("# units: furlong\n" + JAW.read_text())
    with pytest.raises(ValueError, match=r"unknown units 'furlong'"):
        read_marker_csv(p)


# -- round trips ----------------------------------------------------------------------------------
@pytest.mark.parametrize("units", ["cm", "mm", "m"])
def test_marker_csv_round_trip(tmp_path, units):
    perf = _random_markers()
    p = tmp_path / "m.csv"
    write_marker_csv(p, perf, units=units)
    assert p.read_text().startswith(f"# units: {units}\nframe,time_s,mk0_X,mk0_Y,mk0_Z")
    with pytest.warns(DataQualityWarning, match=r"m\.csv: masked as invalid"):
        back = read_performance(p)
    _assert_same(back, perf, atol=0.5e-6 * {"cm": 0.01, "mm": 0.001, "m": 1}[units] + 1e-15)
    assert back.fps == 100.0 and back.units == units
    assert np.abs(back.times - perf.times).max() <= 5e-7


@pytest.mark.parametrize("fname", sorted(ANIMFACE))
def test_real_round_trips_all_formats(real, fname, tmp_path):
    perf = real[fname]
    for suffix, tol in ((".csv", 1e-12), (".trc", 1e-12), (".c3d", 1e-7)):
        p = tmp_path / ("out" + suffix)
        write_performance(p, perf)
        back = read_performance(p)
        _assert_same(back, perf, atol=tol)  # csv: cm 6 decimals >= file's 5; c3d: float32
        assert back.fps == 60.0
        np.testing.assert_array_equal(back.extras["frame"], perf.extras["frame"])
    assert JAW.stat().st_size > 0  # the bundled data is read-only and untouched


def test_trc_round_trip(tmp_path):
    perf = _random_markers(fps=120.0)
    p = tmp_path / "m.trc"
    write_trc(p, perf, units="mm")
    with pytest.warns(DataQualityWarning, match=r"m\.trc: masked"):
        back = read_trc(p)
    _assert_same(back, perf, atol=0.5e-5 * 1e-3 + 1e-15)
    assert back.fps == 120.0 and back.units == "mm" and back.extras["camera_rate"] == 120.0
    np.testing.assert_array_equal(back.extras["frame"], np.arange(1, 51))
    lines = p.read_text().splitlines()
    assert lines[0].split("\t")[:2] == ["PathFileType", "4"]
    assert lines[1].split("\t")[:5] == ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units"]
    assert lines[2].split("\t")[:5] == ["120", "120", "50", "5", "mm"]
    assert lines[3].split("\t")[:6] == ["Frame#", "Time", "mk0", "", "", "mk1"]
    assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"]


def test_c3d_round_trip(tmp_path):
    perf = _random_markers(fps=250.0)
    p = tmp_path / "m.c3d"
    write_c3d(p, perf, units="mm")
    with pytest.warns(DataQualityWarning, match=r"m\.c3d: masked"):
        back = read_c3d(p)
    _assert_same(back, perf, atol=2e-7)  # float32 storage of ~1600 mm values
    assert back.fps == 250.0 and back.units == "mm"


# -- TRC written by hand (independent of our writer) ----------------------------------------------
TRC = (
    "PathFileType\t4\t(X/Y/Z)\thand.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "50.00\t50.00\t3\t2\tmm\t50.00\t7\t3\n"
    "Frame#\tTime\tNose\t\t\tChin\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
    "7\t0.140\t1.0\t2.0\t3.0\t4.0\t5.0\t6.0\n"
    "8\t0.160\t1.5\t2.5\t3.5\t\t\t\n"
    "9\t0.180\t2.0\t3.0\t4.0\t7.0\t8.0\t9.0\n"
)


def test_trc_by_hand(tmp_path):
    p = tmp_path / "hand.trc"
    p.write_text(TRC)
    with pytest.warns(DataQualityWarning, match=r"hand\.trc: masked as invalid \(not zeroed\): 1 marker-frames .* lines 8, markers \['Chin'\]"):
        perf = read_trc(p)
    assert perf.names == ("Nose", "Chin") and perf.fps == 50.0 and perf.units == "mm"
    np.testing.assert_allclose(perf.data[0], [[0.001, 0.002, 0.003], [0.004, 0.005, 0.006]])
    np.testing.assert_array_equal(perf.valid, [[True, True], [True, False], [True, True]])
    np.testing.assert_allclose(perf.times, [0, 0.02, 0.04])
    np.testing.assert_array_equal(perf.extras["frame"], [7, 8, 9])
    assert perf.extras["start_time"] == pytest.approx(0.14)


@pytest.mark.parametrize("edit,match", [
    (lambda s: s.rsplit("9\t0.180", 1)[0], r"hand\.trc: field NumFrames is 3 but the file has 2 data rows \(truncated"),
    (lambda s: s.replace("\t2\tmm", "\t3\tmm"), r"hand\.trc: line 4: 2 marker names but NumMarkers is 3"),
    (lambda s: s.replace("\tmm\t", "\tparsec\t"), r"hand\.trc: line 3, field Units: unknown units 'parsec'"),
    (lambda s: s.replace("50.00\t50.00\t3", "fast\t50.00\t3"), r"hand\.trc: line 3, field DataRate: 'fast'; expected a number"),
    (lambda s: s.replace("7\t0.140\t1.0", "7\t0.140\t1.0\t1.0"), r"hand\.trc: line 7: expected 8 tab-separated cells"),
    (lambda s: s.replace("8\t0.160", "8\t"), r"hand\.trc: line 8, column Time: empty cell"),
    (lambda s: s.replace("PathFileType", "Path"), r"hand\.trc: line 1: expected a TRC header"),
])
def test_trc_bad_input(tmp_path, edit, match):
    p = tmp_path / "hand.trc"
    p.write_text(edit(TRC))
    with pytest.raises(ValueError, match=match):
        read_trc(p)


def test_trc_rate_disagreement_warns(tmp_path):
    p = tmp_path / "hand.trc"
    p.write_text(TRC.replace("50.00\t50.00", "100.00\t100.00"))
    with pytest.warns(DataQualityWarning) as rec:
        perf = read_trc(p)
    msgs = " | ".join(str(w.message) for w in rec)
    assert "field DataRate is 100.0 but column Time steps at 50 Hz" in msgs and "1 marker-frames" in msgs
    assert perf.fps == 100.0


# -- C3D written directly with ezc3d (independent of our writer) ---------------------------------
def test_c3d_written_with_ezc3d(tmp_path):
    import ezc3d  # a declared test dependency (pyproject [test])
    T, M = 30, 3
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-200, 200, (T, M, 3))  # millimetres
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([100.0])
    c["parameters"]["POINT"]["LABELS"]["value"] = ["LBrow", "RBrow", "Jaw"]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    pts = np.ones((4, M, T))
    pts[:3] = xyz.transpose(2, 1, 0)
    res = np.zeros((1, M, T))
    res[0, 2, [4, 5]] = -1  # Jaw not reconstructed on frames 4, 5
    res[0, 0, 9] = -1
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": np.zeros((7, M, T), dtype=bool)}
    p = tmp_path / "direct.c3d"
    c.write(str(p))
    with pytest.warns(DataQualityWarning, match=r"direct\.c3d: masked as invalid.*3 marker-frames"):
        perf = read_performance(p)
    assert perf.names == ("LBrow", "RBrow", "Jaw") and perf.fps == 100.0 and perf.units == "mm"
    expect = np.ones((T, M), bool)
    expect[[4, 5], 2] = False
    expect[9, 0] = False
    np.testing.assert_array_equal(perf.valid, expect)
    np.testing.assert_allclose(perf.data[expect], xyz[expect] / 1000, atol=1e-7)
    assert np.isnan(perf.data[~expect]).all()
    np.testing.assert_allclose(perf.times, np.arange(T) / 100)


def test_c3d_needs_ezc3d(tmp_path, monkeypatch):
    p = tmp_path / "x.c3d"
    write_c3d(p, _random_markers(masked=False))
    monkeypatch.setitem(sys.modules, "ezc3d", None)
    with pytest.raises(ImportError, match=r"pip install face-retarget\[c3d\]"):
        read_c3d(p)
    with pytest.raises(ImportError, match=r"pip install face-retarget\[c3d\]"):
        write_c3d(tmp_path / "y.c3d", _random_markers())


def test_c3d_bad_file(tmp_path):
    p = tmp_path / "bad.c3d"
    p.write_bytes(b"not a c3d file at all" * 10)
    with pytest.raises(ValueError, match=r"bad\.c3d: not a readable C3D file"):
        read_c3d(p)


# -- marker CSV bad input -------------------------------------------------------------------------
def _small(tmp_path, edit=None, n=30, name="small.csv"):
    rows = [ln.split(",") for ln in JAW.read_text().splitlines()[: n + 1]]
    if edit:
        edit(rows)
    p = tmp_path / name
    p.write_text("# units: cm\n" + "\n".join(",".join(r) for r in rows) + "\n")
    return p  # line numbers: comment 1, header 2, data row i at line i + 2


def test_small_marker_csv_clean(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        perf = read_marker_csv(_small(tmp_path))
    assert perf.n_frames == 30 and perf.fps == 60.0 and perf.valid.all()


def test_marker_csv_nan_empty_non_numeric_masked_per_marker_frame(tmp_path):
    def edit(rows):
        rows[3][2] = ""  # ForeHead_M X on data row 3
        rows[5][7] = "nan"  # ForeHead_L Z on data row 5
        rows[5][9] = "??"  # ForeHead_R Y (not a number)
    with pytest.warns(DataQualityWarning) as rec:
        perf = read_marker_csv(_small(tmp_path, edit))
    msg = str(rec[0].message)
    assert "small.csv" in msg and "3 marker-frames" in msg and "lines 5, 7" in msg
    assert "['ForeHead_M', 'ForeHead_L', 'ForeHead_R']" in msg
    bad = {(2, 0), (4, 1), (4, 2)}
    for t, m in bad:
        assert not perf.valid[t, m] and np.isnan(perf.data[t, m]).all()
    assert perf.valid.sum() == perf.valid.size - len(bad)
    assert perf.valid[2, 1] and np.isfinite(perf.data[2, 1]).all()  # the rest of that frame stays


@pytest.mark.parametrize("edit,match", [
    (lambda r: r[7].pop(), r"small\.csv: line 9: expected 125 comma-separated cells as in the header, got 124"),
    (lambda r: r[0].__setitem__(3, "ForeHead_M_Q"), r"small\.csv: line 2, header column 4 'ForeHead_M_Q': expected 'ForeHead_M_Y'"),
    (lambda r: r[0].__setitem__(1, "t"), r"small\.csv: line 2: header must start 'frame,time_s'"),
    (lambda r: r[4].__setitem__(1, ""), r"small\.csv: line 6, column time_s: empty cell; expected a number"),
    (lambda r: r[4].__setitem__(0, "x"), r"small\.csv: line 6, column frame: non-numeric cell"),
    (lambda r: r[4].__setitem__(0, "3.5"), r"small\.csv: line 6, column frame: 3\.5; expected an integer"),
    (lambda r: [row.extend(row[2:5]) for row in r], r"small\.csv: line 2: duplicate marker names \['ForeHead_M'\]"),
])
def test_marker_csv_bad_input(tmp_path, edit, match):
    with pytest.raises(ValueError, match=match):
        read_marker_csv(_small(tmp_path, edit))


def test_marker_csv_truncated(tmp_path):
    p = _small(tmp_path)
    text = p.read_text()
    p.write_text(text[: len(text) - 200])
    with pytest.raises(ValueError, match=r"small\.csv: line 32: expected 125 comma-separated cells.*truncated"):
        read_marker_csv(p)


# -- dispatch -----------------------------------------------------------------------------------------
def test_dispatch_unknown(tmp_path):
    p = tmp_path / "x.bvh"
    p.write_text("HIERARCHY\n")
    with pytest.raises(ValueError, match=r"x\.bvh: cannot read suffix '\.bvh'; supported formats:(.|\n)*\.trc(.|\n)*\.c3d"):
        read_performance(p)
    q = tmp_path / "x.csv"
    q.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(ValueError, match=r"x\.csv: unrecognised CSV header 'a,b,c'.*Timecode,BlendShapeCount.*frame,time_s"):
        read_performance(q)
    with pytest.raises(FileNotFoundError, match="nope.csv"):
        read_performance(tmp_path / "nope.csv")
    perf = _random_markers()
    with pytest.raises(ValueError, match=r"cannot write suffix '\.bvh'; supported formats:(.|\n)*\.trc"):
        write_performance(p, perf)
    with pytest.raises(ValueError, match=r"\.trc holds marker trajectories; got a 'curves'"):
        write_performance(tmp_path / "c.trc", Performance.curves(np.zeros((3, 2)), ["a", "b"], 30.0))
    with pytest.raises(ValueError, match=r"glTF animation needs the target rig"):
        write_performance(tmp_path / "c.glb", perf)


def test_dispatch_gltf_guarded(tmp_path, monkeypatch):
    p = tmp_path / "anim.glb"
    p.write_bytes(b"glTF")
    monkeypatch.delattr(core.io.gltf, "read_animation", raising=False)
    with pytest.raises(ImportError, match=r"anim\.glb: reading a glTF animation needs core\.io\.gltf\.read_animation"):
        read_performance(p)
    seen = {}

    def fake(path, **kw):
        seen.update(path=path, kw=kw)
        return _random_markers()

    monkeypatch.setattr(core.io.gltf, "read_animation", fake, raising=False)
    assert read_performance(p, rig="r").kind == "markers"
    assert seen == {"path": p, "kw": {"rig": "r"}}


# -- estimate_fps -------------------------------------------------------------------------------------
def test_estimate_fps():
    t = np.arange(1000) / 60.0
    assert estimate_fps(t) == 60.0
    assert estimate_fps(np.round(t, 5)) == 60.0  # rounded time stamps (AnimFace prints 5 decimals)
    assert estimate_fps(np.delete(t, [3, 4, 5, 400])) == 60.0  # dropped samples
    ntsc = np.arange(500) * 1001 / 30000
    assert estimate_fps(ntsc) == pytest.approx(30000 / 1001, rel=1e-12)  # 29.97 is not 30
    odd = np.arange(100) / 37.3
    assert estimate_fps(odd) == pytest.approx(37.3, rel=1e-9)  # no standard rate near: kept
    with pytest.raises(ValueError, match="need at least 2 samples"):
        estimate_fps([0.0], "f.csv: column time_s")
    with pytest.raises(ValueError, match="f.csv: column time_s: time stamps never increase"):
        estimate_fps([1.0, 1.0, 1.0], "f.csv: column time_s")
