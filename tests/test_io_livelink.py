"""Live Link Face CSV reader/writer: the bundled captures, bad input, round trips."""

import csv
import time
import warnings

import numpy as np
import pytest

from datapaths import PERFORMANCES
from core.io.livelink import (LIVELINK_CHANNELS, ROTATION_COLUMNS, read_livelink, write_livelink)
from core.io.performance import read_performance, write_performance
from core.io.tabular import DataQualityWarning
from core.model import Performance
from core.names import ARKIT_NAMES, canonical

FILES = {  # file -> (rows, first timecode, last timecode) as printed in the file
    "livelinkface_rom.csv": (4030, "13:13:04:31.652", "13:15:18:54.561"),
    "livelinkface_take_s07.csv": (2028, "12:27:47:47.169", "12:28:55:24.614"),
    "livelinkface_take_facial.csv": (1913, "12:24:24:19.960", "12:25:28:05.435"),
}
ROM = PERFORMANCES / "livelinkface_rom.csv"


def _seconds(tc, rate=60):
    h, m, s, f = tc.split(":")
    return int(h) * 3600 + int(m) * 60 + int(s) + float(f) / rate


@pytest.fixture(scope="module")
def real():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the real captures are clean: no warning at all
        return {f: read_livelink(PERFORMANCES / f) for f in FILES}


@pytest.fixture(scope="module")
def rom_lines():
    return ROM.read_text().splitlines()


def _small(tmp_path, rom_lines, edit=None, n=40, name="small.csv"):
    """The first ``n`` rows of the ROM capture (1.3 s, crosses a second boundary), edited by
    ``edit(rows)`` where rows are lists of cells (header at index 0)."""
    rows = [ln.split(",") for ln in rom_lines[: n + 1]]
    if edit:
        edit(rows)
    p = tmp_path / name
    p.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return p


# -- the bundled captures -----------------------------------------------------------------
@pytest.mark.parametrize("fname", sorted(FILES))
def test_real_files(real, fname):
    perf = real[fname]
    rows, first, last = FILES[fname]
    assert perf.kind == "curves" and perf.n_frames == rows
    assert perf.fps == 30.0
    assert perf.extras["timecode_rate"] == 60
    assert perf.extras["timecode_start"] == first and perf.extras["timecode"][-1] == last
    assert sorted(perf.names) == sorted(ARKIT_NAMES) and len(perf.names) == 52
    assert not set(perf.names) & set(ROTATION_COLUMNS)
    # times from the timecodes, computed independently of the reader
    assert perf.times[0] == 0.0
    assert perf.times[-1] == pytest.approx(_seconds(last) - _seconds(first), abs=1e-9)
    assert (np.diff(perf.times) > 0).all()
    assert perf.valid.all()
    # ARKit weights: in [0, ~1], and real motion (a range-of-motion / acting take)
    assert perf.data.min() >= 0.0 and perf.data.max() <= 1.1
    assert perf.data.max() > 0.9
    assert perf.data[:, perf.names.index("jawOpen")].max() > 0.2
    for key in ("head_rotation", "eye_rotation_left", "eye_rotation_right"):
        assert perf.extras[key].shape == (rows, 3)
    # head rotation was not captured in these takes (Live Link Face writes 0); eye angles are
    # radians: |yaw| < 0.7 rad (40 degrees) yet clearly moving
    assert (perf.extras["head_rotation"] == 0).all()
    eye = perf.extras["eye_rotation_left"]
    assert 0.1 < np.abs(eye[:, 0]).max() < 0.7


@pytest.mark.parametrize("fname", sorted(FILES))
def test_real_values_match_csv_module(real, fname):
    """Every cell against Python's csv module, mapped by hand-written Live Link spelling."""
    with open(PERFORMANCES / fname, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    table = np.array([[float(c) for c in r[2:]] for r in body])
    perf = real[fname]
    for j, col in enumerate(header[2:]):
        if col in ROTATION_COLUMNS:
            key = {"Head": "head_rotation", "Left": "eye_rotation_left", "Righ": "eye_rotation_right"}[col[:4]]
            axis = ("Yaw", "Pitch", "Roll").index(col.replace("Head", "").replace("LeftEye", "").replace("RightEye", ""))
            np.testing.assert_array_equal(perf.extras[key][:, axis], table[:, j])
        else:
            name = col[0].lower() + col[1:]  # EyeBlinkLeft -> eyeBlinkLeft
            np.testing.assert_array_equal(perf.data[:, perf.names.index(name)], table[:, j])


def test_rom_reads_fast():
    best = min(_timed(lambda: read_livelink(ROM)) for _ in range(3))
    assert best < 0.5, f"reading the 4,030-row ROM took {best:.3f} s"


def _timed(f):
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


def test_dispatch_reads_livelink(real):
    perf = read_performance(ROM)
    np.testing.assert_array_equal(perf.data, real["livelinkface_rom.csv"].data)


def test_livelink_order_is_the_upstream_header(rom_lines):
    header = rom_lines[0].split(",")
    assert tuple(header[2:54]) == LIVELINK_CHANNELS and tuple(header[54:]) == ROTATION_COLUMNS
    assert sorted(canonical(c) for c in LIVELINK_CHANNELS) == sorted(ARKIT_NAMES)


# -- round trips ----------------------------------------------------------------------------
@pytest.mark.parametrize("fname", sorted(FILES))
def test_real_round_trip_is_byte_identical(real, fname, tmp_path):
    perf = real[fname]
    out = tmp_path / fname
    write_livelink(out, perf, timecode_start=perf.extras["timecode_start"], timecode_rate=60)
    assert out.read_text() == (PERFORMANCES / fname).read_text().replace("\r\n", "\n")


def _random_curves(T=75, fps=30.0, seed=0, masked=True):
    rng = np.random.default_rng(seed)
    names = list(ARKIT_NAMES)[::-1]  # any order in, Live Link order out
    w = rng.uniform(0, 1, (T, 52))
    valid = np.ones((T, 52), bool)
    if masked:
        valid[rng.integers(0, T, 10), rng.integers(0, 52, 10)] = False
        valid[5] = False  # a whole masked row
    extras = {"head_rotation": rng.uniform(-0.3, 0.3, (T, 3)),
              "eye_rotation_left": rng.uniform(-0.5, 0.5, (T, 3)),
              "eye_rotation_right": rng.uniform(-0.5, 0.5, (T, 3))}
    return Performance.curves(w, names, fps, valid=valid, extras=extras, name="rand")


@pytest.mark.parametrize("start,rate,fps", [("00:00:00:00.000", 60, 30.0), ("23:59:59:10.250", 60, 30.0),
                                            ("10:00:00:00.000", 24, 24.0), ("01:02:03:04.500", 60, 60.0)])
def test_synthetic_round_trip(tmp_path, start, rate, fps):
    perf = _random_curves(fps=fps)
    p = tmp_path / "rt.csv"
    write_livelink(p, perf, timecode_start=start, timecode_rate=rate)
    with pytest.warns(DataQualityWarning, match="masked"):
        back = read_livelink(p)
    assert back.extras["timecode_rate"] == rate
    assert back.fps == fps
    np.testing.assert_array_equal(back.valid, perf.select(back.names).valid)
    ref = perf.select(back.names)
    ok = ref.valid
    assert np.abs(back.data[ok] - ref.data[ok]).max() <= 5e-11  # printed to 10 decimals
    assert np.isnan(back.data[~ok]).all()
    assert np.abs(back.times - perf.times).max() <= 1 / (2000 * rate) + 1e-12
    for key in ("head_rotation", "eye_rotation_left", "eye_rotation_right"):
        rot = np.array(perf.extras[key])
        keep = np.ones(perf.n_frames, bool)
        keep[5] = False  # the fully masked row reads back as tracking loss: rotations NaN
        assert np.abs(back.extras[key][keep] - rot[keep]).max() <= 5e-11
        assert np.isnan(back.extras[key][5]).all()
    if start.startswith("23:59:59"):
        assert back.extras["timecode"][-1].startswith("00:00:")  # wrapped past midnight
        assert (np.diff(back.times) > 0).all()


def test_write_performance_dispatch_curves(tmp_path):
    perf = _random_curves(masked=False)
    write_performance(tmp_path / "c.csv", perf)
    back = read_performance(tmp_path / "c.csv")
    np.testing.assert_allclose(back.data, perf.select(back.names).data, atol=5e-11)


def test_writer_without_rotations_writes_zero(tmp_path):
    perf = Performance.curves(np.full((40, 52), 0.25), ARKIT_NAMES, 30.0)
    write_livelink(tmp_path / "z.csv", perf)
    back = read_livelink(tmp_path / "z.csv")
    assert (back.extras["head_rotation"] == 0).all()
    assert back.valid.all() and (back.data == 0.25).all()


def test_writer_errors(tmp_path):
    perf = _random_curves(masked=False)
    with pytest.raises(ValueError, match=r"missing ARKit channels \['TongueOut'\]"):
        write_livelink(tmp_path / "a.csv", perf.select([n for n in perf.names if n != "tongueOut"]))
    extra = Performance.curves(np.zeros((3, 53)), list(ARKIT_NAMES) + ["smileWide"], 30.0)
    with pytest.raises(ValueError, match="smileWide.*not ARKit"):
        write_livelink(tmp_path / "b.csv", extra)
    markers = Performance.markers(np.zeros((3, 2, 3)), ["a", "b"], 30.0)
    with pytest.raises(ValueError, match="curves"):
        write_livelink(tmp_path / "c.csv", markers)
    with pytest.raises(ValueError, match="timecode_start.*HH:MM:SS:FF.sss"):
        write_livelink(tmp_path / "d.csv", perf, timecode_start="12:00:00")
    with pytest.raises(ValueError, match="timecode_start"):
        write_livelink(tmp_path / "e.csv", perf, timecode_start="00:00:00:30.000", timecode_rate=30)


# -- bad input --------------------------------------------------------------------------------
def test_small_file_is_clean(tmp_path, rom_lines):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        perf = read_livelink(_small(tmp_path, rom_lines))
    assert perf.n_frames == 40 and perf.fps == 30.0 and perf.valid.all()


def test_truncated_file(tmp_path, rom_lines):
    p = _small(tmp_path, rom_lines)
    text = p.read_text()
    p.write_text(text[: len(text) - 300])  # cut the last row mid-way
    with pytest.raises(ValueError, match=r"small\.csv: line 41: expected 63 comma-separated cells.*got \d+.*truncated"):
        read_livelink(p)


def test_header_only_and_empty(tmp_path, rom_lines):
    p = tmp_path / "h.csv"
    p.write_text(rom_lines[0] + "\n")
    with pytest.raises(ValueError, match=r"h\.csv: header but no data rows"):
        read_livelink(p)
    p.write_text("")
    with pytest.raises(ValueError, match=r"h\.csv: empty file.*Timecode,BlendShapeCount"):
        read_livelink(p)


def test_missing_channel(tmp_path, rom_lines):
    def drop(rows):
        j = rows[0].index("TongueOut")
        for r in rows:
            del r[j]
            if r is not rows[0]:
                r[1] = "60"
    p = _small(tmp_path, rom_lines, drop)
    with pytest.raises(ValueError, match=r"small\.csv: header: missing column\(s\) \['TongueOut'\].*allow_missing"):
        read_livelink(p)
    perf = read_livelink(p, allow_missing=True)
    assert "tongueOut" not in perf.names and len(perf.names) == 51


def test_missing_rotation_columns(tmp_path, rom_lines):
    def drop(rows):
        for r in rows:
            del r[54:57]
            if r is not rows[0]:
                r[1] = "58"
    p = _small(tmp_path, rom_lines, drop)
    with pytest.raises(ValueError, match=r"missing column\(s\) \['HeadYaw', 'HeadPitch', 'HeadRoll'\]"):
        read_livelink(p)
    perf = read_livelink(p, allow_missing=True)
    assert "head_rotation" not in perf.extras and "eye_rotation_left" in perf.extras


def test_nan_and_empty_cells_are_masked_not_zeroed(tmp_path, rom_lines):
    def edit(rows):
        rows[3][2] = "nan"  # line 4, EyeBlinkLeft
        rows[7][20] = ""  # line 8, MouthClose
        rows[9][58] = ""  # line 10, LeftEyePitch (a rotation)
    with pytest.warns(DataQualityWarning) as rec:
        perf = read_livelink(_small(tmp_path, rom_lines, edit))
    msg = str(rec[0].message)
    assert "small.csv" in msg and "not zeroed" in msg
    assert "1 nan/inf cells at lines 4" in msg and "EyeBlinkLeft" in msg
    assert "2 empty cells at lines 8, 10" in msg and "MouthClose" in msg
    i, j = perf.names.index("eyeBlinkLeft"), perf.names.index("mouthClose")
    assert not perf.valid[2, i] and np.isnan(perf.data[2, i])
    assert not perf.valid[6, j] and np.isnan(perf.data[6, j])
    assert perf.valid.sum() == perf.valid.size - 2
    assert np.isnan(perf.extras["eye_rotation_left"][8, 1])


def test_non_numeric_cell(tmp_path, rom_lines):
    def edit(rows):
        rows[12][30] = "0.1x"
    with pytest.warns(DataQualityWarning, match=r"small\.csv.*1 non-numeric cells at lines 13 in columns \['MouthDimpleRight'\]"):
        perf = read_livelink(_small(tmp_path, rom_lines, edit))
    k = perf.names.index("mouthDimpleRight")
    assert not perf.valid[11, k] and perf.valid[11].sum() == 51


def test_tracking_loss_rows(tmp_path, rom_lines):
    def edit(rows):
        rows[10] = [rows[9][0], "61"] + ["0.0000000000"] * 61  # zeros on a repeated timecode
        rows[20] = [rows[20][0], ""] + [""] * 61  # an empty row
        rows[30] = [rows[30][0], "61"] + ["0.0000000000"] * 61  # zeros, but a new timecode
    with pytest.warns(DataQualityWarning, match=r"small\.csv.*2 tracking-loss rows.*at lines 11, 21"):
        perf = read_livelink(_small(tmp_path, rom_lines, edit))
    assert not perf.valid[9].any() and np.isnan(perf.data[9]).all()
    assert not perf.valid[19].any() and np.isnan(perf.extras["eye_rotation_left"][19]).all()
    assert perf.valid[29].all() and (perf.data[29] == 0).all()  # a real all-zero sample stays
    assert perf.valid.sum() == perf.valid.size - 2 * 52
    assert perf.times[9] == perf.times[8]  # the repeated timecode keeps its time
    assert perf.fps == 30.0


def test_row_length_mismatch(tmp_path, rom_lines):
    def edit(rows):
        rows[5].append("0.5")
    with pytest.raises(ValueError, match=r"small\.csv: line 6: expected 63 comma-separated cells as in the header, got 64"):
        read_livelink(_small(tmp_path, rom_lines, edit))

    def trailing(rows):
        rows[5].append("")  # a trailing comma is tolerated
    assert read_livelink(_small(tmp_path, rom_lines, trailing, name="t.csv")).n_frames == 40


@pytest.mark.parametrize("tc", ["13:13:4x:31.652", "13:61:04:31.652", "13:13:04", "", "25:00:00:00.000"])
def test_bad_timecode(tmp_path, rom_lines, tc):
    def edit(rows):
        rows[4][0] = tc
    with pytest.raises(ValueError, match=r"small\.csv: line 5, column Timecode: .* expected HH:MM:SS:FF\.sss"):
        read_livelink(_small(tmp_path, rom_lines, edit))


@pytest.mark.parametrize("count", ["60", "x"])
def test_blendshape_count_checked(tmp_path, rom_lines, count):
    def edit(rows):
        rows[8][1] = count
    with pytest.raises(ValueError, match=r"small\.csv: line 9, column BlendShapeCount: .*expected 61"):
        read_livelink(_small(tmp_path, rom_lines, edit))


def test_not_livelink_header_and_duplicates(tmp_path, rom_lines):
    p = tmp_path / "x.csv"
    p.write_text("frame,time_s,a_X\n")
    with pytest.raises(ValueError, match=r"x\.csv: line 1: not a Live Link Face CSV header"):
        read_livelink(p)

    def dup(rows):
        rows[0][3] = "EyeBlinkLeft"
    with pytest.raises(ValueError, match=r"duplicate columns \['EyeBlinkLeft'\]"):
        read_livelink(_small(tmp_path, rom_lines, dup))


def test_timecode_rate_inference_and_override(tmp_path):
    # 30 fps samples on a 30 fps timecode: counters 0..29 -> rate 30, fps 30
    perf = Performance.curves(np.full((90, 52), 0.5), ARKIT_NAMES, 30.0)
    write_livelink(tmp_path / "r30.csv", perf, timecode_rate=30)
    back = read_livelink(tmp_path / "r30.csv")
    assert back.extras["timecode_rate"] == 30 and back.fps == 30.0
    assert back.times[-1] == pytest.approx(89 / 30, abs=1e-9)
    # a clip shorter than a second cannot prove its rate: warned, and the override fixes it
    short = perf.frames(0, 12)
    write_livelink(tmp_path / "short.csv", short, timecode_rate=60)
    with pytest.warns(DataQualityWarning, match=r"never crosses a second boundary.*timecode_rate="):
        guess = read_livelink(tmp_path / "short.csv")
    assert guess.extras["timecode_rate"] == 24  # counters 0..22 -> smallest rate above is 24
    fixed = read_livelink(tmp_path / "short.csv", timecode_rate=60)
    assert fixed.fps == 30.0 and fixed.times[-1] == pytest.approx(11 / 30, abs=1e-9)
    with pytest.raises(ValueError, match=r"frame counter 22 is not below timecode_rate=20"):
        read_livelink(tmp_path / "short.csv", timecode_rate=20)


def test_gappy_capture_fps_not_assumed(tmp_path):
    """Dropped samples (longer steps) keep their times; fps comes from the median step."""
    t = np.delete(np.arange(200) / 60.0, [10, 11, 50, 120])
    perf = Performance.curves(np.full((len(t), 52), 0.1), ARKIT_NAMES, 60.0, times=t)
    write_livelink(tmp_path / "g.csv", perf)
    back = read_livelink(tmp_path / "g.csv")
    assert back.fps == 60.0
    assert np.abs(back.times - t).max() <= 1 / (2000 * 60)
