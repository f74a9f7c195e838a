"""Live Link Face CSV reader/writer: the bundled captures, bad input, round trips."""

import csv
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


# -- real takes: what the app writes beyond the bundled captures ---------------------------------
# Built here from the bundled ROM capture's own rows, edited the way real takes differ (see the
# module docstring of core.io.livelink for the takes and readers this is based on).
def _lost(rows, first, last):
    """Rows ``first..last`` (indices into ``rows``, header at 0) as the app writes tracking loss:
    the timecode, then BlendShapeCount 0 and nothing else."""
    for i in range(first, last + 1):
        rows[i] = [rows[i][0], "0"]


def test_tracking_loss_rows_as_the_app_writes_them(tmp_path, rom_lines):
    def edit(rows):
        _lost(rows, 11, 19)  # file lines 12-20
        _lost(rows, 30, 30)  # line 31
    p = _small(tmp_path, rom_lines, edit, name="take.csv")
    with pytest.warns(DataQualityWarning) as rec:
        perf = read_livelink(p)
    assert len(rec) == 1
    msg = str(rec[0].message)
    assert "take.csv" in msg and "not zeroed" in msg
    assert "10 tracking-loss rows at lines 12-20, 31" in msg and "'Timecode,0'" in msg
    full = read_livelink(_small(tmp_path, rom_lines))
    assert perf.n_frames == 40  # kept in the timeline ...
    np.testing.assert_array_equal(perf.times, full.times)  # ... at their own timecodes
    assert perf.fps == 30.0
    lost = np.zeros(40, bool)
    lost[10:19] = lost[29] = True
    assert not perf.valid[lost].any() and np.isnan(perf.data[lost]).all()  # invalid, never zeros
    assert perf.valid[~lost].all()
    np.testing.assert_array_equal(perf.data[~lost], full.data[~lost])
    np.testing.assert_array_equal(perf.extras["tracking_loss"], lost)
    assert perf.extras["tracking_loss_lines"] == ((12, 20), (31, 31))
    for key in ("head_rotation", "eye_rotation_left", "eye_rotation_right"):
        assert np.isnan(perf.extras[key][lost]).all() and np.isfinite(perf.extras[key][~lost]).all()
    assert list(perf.extras["timecode"]) == [r.split(",")[0] for r in rom_lines[1:41]]
    # the slice of a take carries its own loss flags
    assert perf.frames(10, 20).extras["tracking_loss"].sum() == 9
    # written back, the rows are 'Timecode,0' again: the take round-trips byte for byte
    out = tmp_path / "back.csv"
    write_livelink(out, perf, timecode_start=perf.extras["timecode_start"], timecode_rate=60)
    assert out.read_text() == p.read_text()


@pytest.mark.parametrize("row", ["{tc},0,", "{tc},0" + "," * 61, "{tc},0" + ", " * 300, "{tc}, 0 ", "{tc},," + "," * 60])
def test_tracking_loss_row_variants(tmp_path, rom_lines, row):
    """A trailing comma, the row padded with empty cells, spaces, or an empty count: still loss."""
    def edit(rows):
        rows[5] = [row.format(tc=rows[5][0])]
    with pytest.warns(DataQualityWarning, match=r"1 tracking-loss rows at lines 6 "):
        perf = read_livelink(_small(tmp_path, rom_lines, edit))
    assert perf.n_frames == 40 and not perf.valid[4].any() and perf.valid.sum() == 39 * 52


def test_real_like_take_with_300_tracking_loss_rows(tmp_path, rom_lines):
    """Runs of loss rows like a real take's (S88-001: 129, 123 and 25 rows), 300 in all, read
    through the format dispatch (its time: benchmarks/bench_io.py, livelink_read_1000rows_300loss)."""
    def edit(rows):
        for a, b in ((100, 229), (400, 522), (700, 746)):
            _lost(rows, a, b)
    p = _small(tmp_path, rom_lines, edit, n=1000, name="real_like.csv")
    with pytest.warns(DataQualityWarning, match=r"real_like\.csv.*300 tracking-loss rows at lines "
                                                r"101-230, 401-523, 701-747 "):
        perf = read_performance(p)
    assert perf.n_frames == 1000 and (~perf.valid.any(axis=1)).sum() == 300
    assert perf.fps == 30.0


def test_row_cut_after_the_timecode_is_truncation_not_loss(tmp_path, rom_lines):
    p = _small(tmp_path, rom_lines)
    p.write_text(p.read_text() + rom_lines[41].split(",")[0] + ",\n")
    with pytest.raises(ValueError, match=r"line 42: expected 63 comma-separated cells .* got 2 \(the last row"):
        read_livelink(p)


def test_loss_count_with_values_is_refused(tmp_path, rom_lines):
    def edit(rows):
        rows[7][1] = "0"
    with pytest.raises(ValueError, match=r"small\.csv: line 8, column BlendShapeCount: 0 \(tracking lost\) "
                                         r"but the row has values; expected 61"):
        read_livelink(_small(tmp_path, rom_lines, edit))


def test_sixty_fps_take(tmp_path):
    """A 60 fps take: the counter steps by 1 through 0..59 on a 60 fps timecode."""
    perf = _random_curves(T=150, fps=60.0, masked=False)
    write_livelink(tmp_path / "t60.csv", perf, timecode_start="09:30:00:00.000", timecode_rate=60)
    counters = [int(r.split(",")[0].split(":")[3].split(".")[0]) for r in (tmp_path / "t60.csv").read_text().splitlines()[1:]]
    assert counters[:3] == [0, 1, 2] and max(counters) == 59
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = read_livelink(tmp_path / "t60.csv")
    assert back.fps == 60.0 and back.extras["timecode_rate"] == 60
    assert back.times[-1] == pytest.approx(149 / 60, abs=1e-9)


def test_head_rotation_is_kept_as_written(tmp_path, rom_lines):
    """A take with head rotation captured: the values are not zero and are kept as written."""
    yaw = np.linspace(-0.4, 0.4, 40)

    def edit(rows):
        j = rows[0].index("HeadYaw")
        for i in range(1, 41):
            rows[i][j:j + 3] = [f"{yaw[i - 1]:.10f}", "-0.1250000000", "0.0312500000"]
    perf = read_livelink(_small(tmp_path, rom_lines, edit))
    head = perf.extras["head_rotation"]
    np.testing.assert_array_equal(head[:, 0], np.round(yaw, 10))
    assert (head[:, 1] == -0.125).all() and (head[:, 2] == 0.03125).all()
    assert "headYaw" not in perf.names and len(perf.names) == 52


def test_columns_are_matched_by_name_not_position(tmp_path, rom_lines):
    """Other column orders (JawLeft/JawRight and MouthLeft/MouthRight swapped, the rotations
    first, the sides in Right-first order) and spellings (lower camel case) read the same."""
    ref = read_livelink(_small(tmp_path, rom_lines))
    header = rom_lines[0].split(",")
    swap = {"JawRight": "JawLeft", "JawLeft": "JawRight", "MouthRight": "MouthLeft", "MouthLeft": "MouthRight"}
    names = [swap.get(c, c) for c in header[2:54]]  # the swapped order ...
    names = ([c for c in names if c.endswith("Right")] + [c for c in names if not c.endswith("Right")])
    order = header[54:] + names  # ... rotations first
    cols = {c: j for j, c in enumerate(header)}
    lower = {c: c[0].lower() + c[1:] for c in order}

    def permute(rows):
        for i, r in enumerate(rows):
            rows[i] = r[:2] + ([lower[c] for c in order] if i == 0 else [r[cols[c]] for c in order])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        perf = read_livelink(_small(tmp_path, rom_lines, permute, name="perm.csv"))
    assert perf.names != ref.names and sorted(perf.names) == sorted(ref.names)
    np.testing.assert_array_equal(perf.select(ref.names).data, ref.data)
    for key in ("head_rotation", "eye_rotation_left", "eye_rotation_right"):
        np.testing.assert_array_equal(perf.extras[key], ref.extras[key])


def test_bom_crlf_and_trailing_cells(tmp_path, rom_lines):
    ref = read_livelink(_small(tmp_path, rom_lines))
    text = "\ufeff" + "\r\n".join(ln + "," for ln in rom_lines[:41]) + "\r\n"
    p = tmp_path / "win.csv"
    p.write_bytes(text.encode("utf-8"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        perf = read_performance(p)  # the dispatch sees the header through the BOM too
    np.testing.assert_array_equal(perf.data, ref.data)
    np.testing.assert_array_equal(perf.times, ref.times)
    assert perf.names == ref.names and perf.extras["timecode_start"] == ref.extras["timecode_start"]


def test_subframe_timecodes(tmp_path, rom_lines):
    """t = 3600 HH + 60 MM + SS + (FF + .sss) / rate, by hand for a few rows."""
    tcs = ["10:00:00:00.000", "10:00:00:01.998", "10:00:00:04.250", "10:00:00:58.5", "10:00:01:00.001", "10:00:01:02"]

    def edit(rows):
        del rows[len(tcs) + 1:]
        for i, tc in enumerate(tcs):
            rows[i + 1][0] = tc
    perf = read_livelink(_small(tmp_path, rom_lines, edit))
    want = np.array([0.0, 1.998, 4.25, 58.5, 60.001, 62.0]) / 60
    np.testing.assert_allclose(perf.times, want, rtol=0, atol=1e-10)  # seconds since midnight, float64
    assert perf.extras["timecode_rate"] == 60 and perf.extras["timecode_drop_frame"] is False


def test_drop_frame_timecodes(tmp_path, rom_lines):
    """';' is SMPTE drop frame: frame numbers 0 and 1 do not exist at the start of a minute
    unless it is a multiple of ten. No app file seen uses it; it is read correctly if one does.
    Frame numbers by hand: 00:00:59;29 = 1799, 00:01:00;02 = 1800, 00:09:59;29 = 17981,
    00:10:00;00 = 17982."""
    tcs = ["00:00:59;28", "00:00:59;29", "00:01:00;02", "00:01:00;03",
           "00:09:59;28", "00:09:59;29", "00:10:00;00", "00:10:00;01"]
    frames = np.array([1798, 1799, 1800, 1801, 17980, 17981, 17982, 17983])

    def edit(rows, tcs=tcs):
        del rows[len(tcs) + 1:]
        for i, tc in enumerate(tcs):
            rows[i + 1][0] = tc
    perf = read_livelink(_small(tmp_path, rom_lines, edit), timecode_rate=30)
    assert perf.extras["timecode_drop_frame"] is True and perf.extras["timecode_rate"] == 30
    np.testing.assert_allclose(perf.times, (frames - frames[0]) * 1001 / 30000, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"line 2, column Timecode: '00:01:00;00' does not exist in drop-frame"):
        read_livelink(_small(tmp_path, rom_lines, lambda r: edit(r, ["00:01:00;00", "00:01:00;02"])))
    with pytest.raises(ValueError, match=r"line 3, column Timecode: .* mixes drop-frame"):
        read_livelink(_small(tmp_path, rom_lines, lambda r: edit(r, ["00:00:01;00", "00:00:01:01"])))
    with pytest.raises(ValueError, match=r"drop frame exists at \(30, 60\) only"):
        read_livelink(_small(tmp_path, rom_lines, edit), timecode_rate=50)
    with pytest.raises(ValueError, match=r"timecode_start: .* drop-frame"):
        write_livelink(tmp_path / "df.csv", perf, timecode_start="00:00:00;00.000", timecode_rate=30)


def test_header_trailing_comma_and_empty_name(tmp_path, rom_lines):
    def trailing(rows):
        rows[0].append("")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_livelink(_small(tmp_path, rom_lines, trailing)).n_frames == 40

    def hole(rows):
        rows[0][10] = ""
    with pytest.raises(ValueError, match=r"small\.csv: line 1: header column 11 has no name"):
        read_livelink(_small(tmp_path, rom_lines, hole))


def test_header_blendshapecount_in_another_case(tmp_path, rom_lines):
    """A real take of another app version (``MySlate_1_iPhone.csv`` of dwskillman/BlendFiles, no
    licence, so not copied: this replica keeps its header) spells the count ``BlendshapeCount``.
    The reader and the format sniffer both take it; the data is the same as the canonical spelling."""
    def other_case(rows):
        rows[0][1] = "BlendshapeCount"
    p = _small(tmp_path, rom_lines, other_case, name="MySlate_1_iPhone.csv")
    ref = read_livelink(_small(tmp_path, rom_lines))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for perf in (read_livelink(p), read_performance(p)):
            assert perf.names == ref.names and perf.n_frames == 40
            np.testing.assert_array_equal(perf.data, ref.data)
            np.testing.assert_array_equal(perf.times, ref.times)
    p.write_text(p.read_text().replace("BlendshapeCount", "ShapeCount", 1))
    with pytest.raises(ValueError, match="unrecognised CSV header"):
        read_performance(p)
