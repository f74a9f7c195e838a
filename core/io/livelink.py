"""Live Link Face CSV: ARKit blendshape curves recorded by Epic's iPhone app.

Layout (one header line, one row per sample, comma separated, no quoting)::

    Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,
    LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll
    16:48:52:27.134,61,0.1588692218,...
    16:48:52:29.134,0
    16:48:52:31.134,0

What the app writes (real takes read for this reader: the bundled three and two more from the
same upstream repository, ``anim/S88-001.csv`` and ``csv/apfel.csv`` of
alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder; Epic's own importer,
``LiveLinkFaceImporterFactory.cpp`` of the Unreal plugin LiveLinkFaceImporter; and the readers
in nmfisher/blender_livelinkface, Diffeomorphic/import_daz ``facecap.py``,
aronamao/Maya-Live-Link-CSV-Import):

* ``Timecode`` is ``HH:MM:SS:FF.sss``: FF a timecode frame counter, ``.sss`` the fraction of a
  timecode frame (subframe). The timecode rate is not written in the file. Epic's importer
  infers 30 or 60 (60 when a counter exceeds 30); we take the smallest standard rate (24, 25,
  30, 48, 50, 60, 120) greater than the largest counter seen, which agrees on every app file
  and also covers an external timecode source at 24 or 25. In the real captures the counter
  runs to 59 in steps of ~2, i.e. a 60 fps timecode sampled at 30 Hz; a 60 fps take steps by
  1. A file that never crosses a second boundary cannot prove its rate: the reader warns and
  ``timecode_rate=`` overrides. No app file and no reader seen uses a drop-frame ``;``
  separator (Epic's importer splits on ``:`` only and would reject it); if one appears it is
  read as SMPTE drop-frame at 29.97 or 59.94 (nominal 30 or 60).
* ``BlendShapeCount`` is the number of value columns after it: 61 (52 ARKit channels + 9
  rotations) in every real row, except **tracking loss**: when the app lost the face it writes
  ``Timecode,0`` and nothing else (277 such rows in S88-001, at lines 384-512, 1713-1835 and
  1841-1865; 35 in apfel), with the timecode still advancing. Epic's importer stops the import
  at the first such row; pandas-based readers turn it into NaN and then 0. Here the row keeps
  its place in the timeline with every channel invalid.
* The 52 ARKit channels in Live Link spelling (``EyeBlinkLeft``). Every real header has them
  in the order of :data:`LIVELINK_CHANNELS` (``JawRight`` before ``JawLeft``, ``MouthRight``
  before ``MouthLeft``, unlike ARKit's and Unreal's own enum order), but columns are matched by
  header name, in any order and case (``eyeBlinkLeft``), never by position. (A Blender reader
  offers to swap MouthLeft/MouthRight "to compensate for a LiveLinkFace bug"; that is about
  what the values mean, which a file cannot tell, so it is not done here.)
* Nine rotations, matched by name (any case). Live Link Face writes 0 in the head columns when
  head rotation was not captured (true of all five real takes). Units are not stated by the
  format; the values are kept as written. In the captures the eye angles are radians: eye yaw
  spans about +/-0.61 and tracks ``eyeLookOut - eyeLookIn`` with correlation 0.999, i.e.
  +/-35 degrees (Unreal's older ARKit plugin normalised degrees/180, which would mean an
  impossible +/-110); Diffeomorphic's importer also uses them as radians.
* The first two header names are matched in any case: a real take from another app version
  (``MySlate_1_iPhone.csv`` of dwskillman/BlendFiles, 679 rows, 11:54:29:19.804 on) spells the
  second ``BlendshapeCount``, as do several third-party writers.
* UTF-8 (a byte-order mark is skipped), LF or CRLF line ends, trailing empty cells (a trailing
  comma) ignored.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from core.io.tabular import (DataQualityWarning, checked_rows, estimate_fps, line_runs, parse_cells, summarize_rows,
                             summarize_runs)
from core.model import Performance
from core.names import ARKIT_NAMES, NameMap, canonical

#: The 52 ARKit channels as Live Link Face spells and orders them in its CSV header.
LIVELINK_CHANNELS = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft",
    "EyeSquintLeft", "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight",
    "EyeLookOutRight", "EyeLookUpRight", "EyeSquintRight", "EyeWideRight", "JawForward",
    "JawRight", "JawLeft", "JawOpen", "MouthClose", "MouthFunnel", "MouthPucker", "MouthRight",
    "MouthLeft", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft", "MouthFrownRight",
    "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft",
    "MouthPressRight", "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft",
    "MouthUpperUpRight", "BrowDownLeft", "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft",
    "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft", "CheekSquintRight", "NoseSneerLeft",
    "NoseSneerRight", "TongueOut",
)
#: The rotation columns, grouped into the ``extras`` entries they become, each (T, 3) as
#: (yaw, pitch, roll).
ROTATIONS = {
    "head_rotation": ("HeadYaw", "HeadPitch", "HeadRoll"),
    "eye_rotation_left": ("LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll"),
    "eye_rotation_right": ("RightEyeYaw", "RightEyePitch", "RightEyeRoll"),
}
ROTATION_COLUMNS = tuple(c for cols in ROTATIONS.values() for c in cols)
#: Timecode rates the counter is matched against (smallest one above the largest counter).
#: Timecode rates the counter is matched against (smallest one above the largest counter).
TIMECODE_RATES = (24, 25, 30, 48, 50, 60, 120)
#: Nominal rates of SMPTE drop-frame timecode (29.97 and 59.94 fps), with the frame numbers
#: dropped at the start of every minute that is not a multiple of ten.
DROP_FRAME_RATES = {30: 2, 60: 4}
TIMECODE_FORMAT = "HH:MM:SS:FF.sss"
HEADER_START = ("Timecode", "BlendShapeCount")
#: ``BlendShapeCount`` of a row the app wrote when it lost the face (no values follow).
TRACKING_LOST_COUNT = "0"


def is_livelink_header(cells) -> bool:
    """Whether header ``cells`` start ``Timecode,BlendShapeCount`` (any case, cells stripped).

    The one test of "this CSV is Live Link Face", used by the reader and by the format sniffer
    (:mod:`core.io.performance`).
    """
    return [str(c).strip().lower() for c in list(cells)[:2]] == [h.lower() for h in HEADER_START]

_LIVE_SPELLING = {canonical(c): c for c in LIVELINK_CHANNELS}
_ROTATION_BY_KEY = {c.lower(): c for c in ROTATION_COLUMNS}
_TC = re.compile(r"^\s*(\d{1,2}):(\d{2}):(\d{2})([:;])(\d{1,3})(?:\.(\d+))?\s*$")


def _parse_timecode(tc: str):
    """(hours, minutes, seconds, counter, subframe fraction, drop frame) or None when malformed."""
    m = _TC.match(tc)
    if not m:
        return None
    h, mi, s, sep, ff, frac = m.groups()
    h, mi, s = int(h), int(mi), int(s)
    if h >= 24 or mi >= 60 or s >= 60:
        return None
    return h, mi, s, int(ff), float("0." + frac) if frac else 0.0, sep == ";"


def _timecode_seconds(parts: np.ndarray, rate: int, drop: bool) -> np.ndarray:
    """Seconds since midnight of (T, 5) ``(h, m, s, counter, subframe)`` at ``rate``.

    Non-drop: ``3600 h + 60 m + s + (counter + subframe) / rate``. Drop frame (SMPTE 12M):
    frame number ``F = (3600 h + 60 m + s) rate + counter - d (M - floor(M / 10))`` with
    ``M = 60 h + m`` and ``d`` = 2 at 30, 4 at 60; seconds ``(F + subframe) 1001 / (1000 rate)``.
    """
    h, m, s, ff, sub = parts.T
    if not drop:
        return h * 3600 + m * 60 + s + (ff + sub) / rate
    minutes = h * 60 + m
    frames = (h * 3600 + m * 60 + s) * rate + ff - DROP_FRAME_RATES[rate] * (minutes - minutes // 10)
    return (frames + sub) * 1001 / (1000 * rate)


def _rate(path, parts, lines, drop: bool, timecode_rate) -> int:
    """The timecode rate: ``timecode_rate`` checked against the counters, or inferred."""
    max_counter = int(parts[:, 3].max())
    if timecode_rate is None:
        ladder = tuple(DROP_FRAME_RATES) if drop else TIMECODE_RATES
        above = [r for r in ladder if r > max_counter]
        if not above:
            raise ValueError(
                f"{path}: column Timecode: frame counter reaches {max_counter}, above every "
                f"{'drop-frame' if drop else 'standard'} rate {ladder}; pass timecode_rate="
            )
        return above[0]
    rate = int(timecode_rate)
    if rate <= max_counter:
        k = int(np.argmax(parts[:, 3]))
        raise ValueError(
            f"{path}: line {lines[k]}, column Timecode: frame counter {max_counter} is not "
            f"below timecode_rate={rate}"
        )
    if drop and rate not in DROP_FRAME_RATES:
        raise ValueError(f"{path}: column Timecode: drop-frame timecode (';') at timecode_rate={rate}; "
                         f"drop frame exists at {tuple(DROP_FRAME_RATES)} only")
    return rate


def read_livelink(path, allow_missing: bool = False, timecode_rate=None) -> Performance:
    """Read a Live Link Face CSV as ARKit weight curves.

    Each row ``i`` gives ``w_i`` (K,) and a timecode ``HH:MM:SS:FF.sss``;
    ``t_i = 3600 HH + 60 MM + SS + (FF + .sss) / rate - t_0`` (plus a day after a midnight
    wrap; drop-frame timecodes ``HH:MM:SS;FF`` are counted as SMPTE drop frame). ``fps`` is
    derived from the times (:func:`core.io.tabular.estimate_fps`), never assumed. Rows are not
    resampled: dropped samples show as longer steps in ``times``.

    Parameters
    ----------
    path : str or Path
    allow_missing : bool
        When False (default) a missing ARKit channel or rotation column is an error; when True
        the channel is simply absent from the result.
    timecode_rate : int, optional
        Timecode frames per second; default: the smallest of :data:`TIMECODE_RATES` above the
        largest frame counter in the file (of 30, 60 for drop-frame timecode).

    Returns
    -------
    Performance
        ``kind="curves"``, ``data`` (T, K) with canonical ARKit names (``eyeBlinkLeft``) in file
        order, ``valid`` (T, K) False for NaN/empty/non-numeric cells and for tracking-loss rows
        (their data is NaN, never 0): rows the app wrote as ``Timecode,0``, rows with every
        channel empty, and rows all zero on a repeated timecode. Tracking-loss rows keep their
        place and time in the timeline.
        ``extras``: ``head_rotation``, ``eye_rotation_left``, ``eye_rotation_right`` (T, 3)
        yaw/pitch/roll as written (NaN where masked), ``timecode`` (T,) str,
        ``timecode_start`` str, ``timecode_rate`` int, ``timecode_drop_frame`` bool,
        ``tracking_loss`` (T,) bool, ``tracking_loss_lines`` ``((first line, last line), ...)``
        of each run of tracking-loss rows in the file.

    Raises
    ------
    ValueError
        Naming the file, the line and column, and what was expected: a header that is not
        ``Timecode,BlendShapeCount,...``; an empty or duplicate column name; a missing channel
        (unless ``allow_missing``); a row with a different cell count (e.g. a truncated file);
        a bad timecode; a ``BlendShapeCount`` that does not match the number of value columns
        (0 with values after it included).
    FileNotFoundError

    Warns
    -----
    DataQualityWarning
        One warning naming the file: how many rows were tracking loss and at which line ranges,
        how many cells were masked and where; a non-increasing timecode; a timecode rate that
        the file cannot confirm.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    text = path.read_text(encoding="utf-8-sig")
    numbered = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip()]
    if not numbered:
        raise ValueError(f"{path}: empty file; expected a header line starting 'Timecode,BlendShapeCount'")
    hline = numbered[0][0]
    header = [c.strip() for c in numbered[0][1].split(",")]
    while len(header) > 2 and not header[-1]:
        header.pop()  # trailing commas
    if not is_livelink_header(header):
        raise ValueError(
            f"{path}: line {hline}: not a Live Link Face CSV header; expected it to start "
            f"'Timecode,BlendShapeCount', got {','.join(header[:3])!r}"
        )
    value_cols = header[2:]
    if "" in value_cols:
        raise ValueError(f"{path}: line {hline}: header column {value_cols.index('') + 3} has no name")
    dup = sorted({c for c in value_cols if value_cols.count(c) > 1})
    if dup:
        raise ValueError(f"{path}: line {hline}: duplicate columns {dup}")
    body = numbered[1:]
    lines = np.array([n for n, _ in body], dtype=np.int64)
    if not len(lines):
        raise ValueError(f"{path}: header but no data rows (truncated file?)")
    ncol, nval, T = len(header), len(value_cols), len(body)

    # -- rows: Timecode, BlendShapeCount, values; 'Timecode,0' is tracking loss ----------------
    tcs = [""] * T
    lost0 = np.zeros(T, dtype=bool)  # what the app writes
    lost = np.zeros(T, dtype=bool)  # ... or a row with every cell empty
    for k, (_, ln) in enumerate(body):
        head = ln.rstrip(", \t")  # 'Timecode,Count' once the empty cells after it are gone
        if "," in ln and head.count(",") <= 1:
            tc, _, count = head.partition(",")
            count = count.strip()
            lost0[k] = count == TRACKING_LOST_COUNT
            # an empty count is loss only in a row of full width ('tc,' alone is a cut-off row)
            lost[k] = lost0[k] or (not count and ln.count(",") >= ncol - 1)
            tcs[k] = tc.strip()
    keep = np.flatnonzero(~lost)
    rows = checked_rows(path, [body[k][1] for k in keep], lines[keep], ncol)
    values = np.full((T, nval), np.nan)
    bad = {kind: np.zeros((T, nval), dtype=bool) for kind in ("empty", "non-numeric", "nan/inf")}
    bad["empty"][lost] = True
    if len(keep):
        cells = [ln.split(",", 2) for ln in rows]
        for k, c in zip(keep.tolist(), cells):
            tcs[k] = c[0].strip()
        vals, bad_kept = parse_cells([c[2] for c in cells], nval)
        values[keep] = vals
        for kind, mask in bad_kept.items():
            bad[kind][keep] = mask
        counts = np.array([c[1].strip() for c in cells])
        for cval in np.unique(counts):
            where = keep[counts == cval]
            if cval == str(nval):
                continue
            if cval == "":
                what = "empty"
            elif cval == TRACKING_LOST_COUNT:
                what = "0 (tracking lost) but the row has values"
            else:
                what = repr(cval)
            raise ValueError(
                f"{path}: line {lines[where[0]]}, column BlendShapeCount: {what}; expected {nval}, "
                f"the number of value columns in the header"
            )

    # -- timecodes ------------------------------------------------------------------------
    tcs = np.array(tcs)
    parts = []
    for k, tc in enumerate(tcs):
        p = _parse_timecode(tc)
        if p is None:
            raise ValueError(
                f"{path}: line {lines[k]}, column Timecode: {tc!r} is not a timecode; expected "
                f"{TIMECODE_FORMAT} (hours < 24, minutes and seconds < 60, frame counter, subframe)"
            )
        parts.append(p)
    drops = np.array([p[5] for p in parts])
    drop = bool(drops[0])
    if (drops != drop).any():
        k = int(np.argmax(drops != drop))
        raise ValueError(f"{path}: line {lines[k]}, column Timecode: {str(tcs[k])!r} mixes drop-frame (';') and "
                         f"non-drop (':') timecode with line {lines[0]} ({str(tcs[0])!r})")
    parts = np.array([p[:5] for p in parts], dtype=np.float64)
    rate = _rate(path, parts, lines, drop, timecode_rate)
    if drop:
        d = DROP_FRAME_RATES[rate]
        skipped = np.flatnonzero((parts[:, 2] == 0) & (parts[:, 1] % 10 != 0) & (parts[:, 3] < d))
        if len(skipped):
            raise ValueError(f"{path}: line {lines[skipped[0]]}, column Timecode: {str(tcs[skipped[0]])!r} does not "
                             f"exist in drop-frame timecode at {rate * 1000 / 1001:.2f} fps (frames 0-{d - 1} "
                             f"are dropped at the start of each minute not divisible by 10)")
    secs = _timecode_seconds(parts, rate, drop)
    day = float(_timecode_seconds(np.array([[24.0, 0, 0, 0, 0]]), rate, drop)[0])
    secs = secs + day * np.concatenate([[0], np.cumsum(np.diff(secs) < -day / 2)])  # midnight wrap
    steps = np.diff(secs)
    if timecode_rate is None and not (np.diff(parts[:, 2]) != 0).any():
        warnings.warn(
            f"{path}: column Timecode never crosses a second boundary, so the timecode rate "
            f"{rate} (inferred from frame counters up to {int(parts[:, 3].max())}) is a guess; pass "
            f"timecode_rate= if it is wrong",
            DataQualityWarning, stacklevel=2,
        )
    back = np.flatnonzero(steps < 0)
    if len(back):
        warnings.warn(
            f"{path}: column Timecode goes backwards at lines {summarize_rows(lines[back + 1])}; "
            f"times kept as written",
            DataQualityWarning, stacklevel=2,
        )
    times = secs - secs[0]

    # -- columns --------------------------------------------------------------------------
    # by header name, in any order and case: channels by canonical ARKit name, rotations by name
    canon = [_ROTATION_BY_KEY.get(c.lower()) or canonical(c) for c in value_cols]
    dup = sorted({c for c in canon if canon.count(c) > 1})
    if dup:
        raise ValueError(f"{path}: header: several columns map to the same channel {dup}")
    rot_of = {j: c for j, c in enumerate(canon) if c in ROTATION_COLUMNS}
    chan = [j for j in range(nval) if j not in rot_of]
    missing = [n for n in ARKIT_NAMES if n not in canon]
    missing_rot = [c for c in ROTATION_COLUMNS if c not in canon]
    if (missing or missing_rot) and not allow_missing:
        what = [_LIVE_SPELLING.get(m, m) for m in missing] + missing_rot
        raise ValueError(
            f"{path}: header: missing column(s) {what}; a Live Link Face CSV has the 52 ARKit "
            f"channels and 9 rotations (pass allow_missing=True to read the file without them)"
        )
    if not chan:
        raise ValueError(f"{path}: header: no blendshape channel columns after Timecode,BlendShapeCount")
    arkit_cols = [j for j in chan if canon[j] in ARKIT_NAMES] or chan
    data = values[:, chan]

    # -- masks ----------------------------------------------------------------------------
    empty_rows = bad["empty"][:, arkit_cols].all(axis=1) & ~lost0
    repeated = np.concatenate([[False], tcs[1:] == tcs[:-1]])
    zero_rep = repeated & (values[:, arkit_cols] == 0).all(axis=1)
    loss = lost | empty_rows | zero_rep
    badcell = bad["empty"] | bad["non-numeric"] | bad["nan/inf"]
    valid = ~badcell[:, chan] & ~loss[:, None]
    data = np.where(valid, data, np.nan)

    notes = []
    loss_lines = line_runs(loss, lines)
    if loss.any():
        kinds = [f"{int(m.sum())} {what}" for m, what in (
            (lost0, "written as 'Timecode,0', i.e. the app lost the face"),
            (empty_rows, "with every channel empty"),
            (zero_rep & ~lost0 & ~empty_rows, "all zero on a repeated timecode")) if m.any()]
        notes.append(f"{int(loss.sum())} tracking-loss rows at lines {summarize_runs(loss_lines)} "
                     f"({'; '.join(kinds)}); kept in the timeline, every channel invalid")
    for kind, mask in bad.items():
        m = mask & ~loss[:, None]
        if m.any():
            r, c = np.nonzero(m)
            cols = sorted({value_cols[j] for j in c}, key=value_cols.index)
            notes.append(f"{int(m.sum())} {kind} cells at lines {summarize_runs(line_runs(m.any(axis=1), lines))} "
                         f"in columns {cols[:6]}{' ...' if len(cols) > 6 else ''}")
    if notes:
        warnings.warn(f"{path}: masked as invalid (not zeroed): " + "; ".join(notes),
                      DataQualityWarning, stacklevel=2)

    tcs.setflags(write=False)
    loss_flag = loss.copy()
    loss_flag.setflags(write=False)
    extras = {"timecode": tcs, "timecode_start": str(tcs[0]), "timecode_rate": rate,
              "timecode_drop_frame": drop, "tracking_loss": loss_flag, "tracking_loss_lines": loss_lines}
    by_name = {c: j for j, c in rot_of.items()}
    for key, cols in ROTATIONS.items():
        if all(c in by_name for c in cols):
            rot = values[:, [by_name[c] for c in cols]].copy()
            rot[loss] = np.nan
            rot.setflags(write=False)
            extras[key] = rot

    fps = estimate_fps(times, f"{path}: column Timecode")
    return Performance.curves(data, [canon[j] for j in chan], fps, valid=valid, times=times,
                              name=path.stem, extras=extras)


def _format_timecodes(start: str, rate: int, rel_times: np.ndarray) -> list:
    """``start + rel_times`` as ``HH:MM:SS:FF.sss`` strings at ``rate`` (hours wrap at 24)."""
    p = _parse_timecode(start)
    if p is None or p[3] >= rate:
        raise ValueError(f"timecode_start: {start!r} is not a timecode below rate {rate}; expected {TIMECODE_FORMAT}")
    h, m, s, ff, sub, drop = p
    if drop:
        raise ValueError(f"timecode_start: {start!r} is drop-frame (';'); the writer writes non-drop "
                         f"timecode only, as Live Link Face does ({TIMECODE_FORMAT})")
    x = ((h * 3600 + m * 60 + s) * rate + ff + sub) + np.asarray(rel_times, dtype=np.float64) * rate
    milli = np.rint(x * 1000).astype(np.int64)  # timecode frames in thousandths, as printed
    frames, subs = np.divmod(milli, 1000)
    secs, ffs = np.divmod(frames, rate)
    width = len(str(rate - 1))
    return [f"{(q // 3600) % 24:02d}:{(q // 60) % 60:02d}:{q % 60:02d}:{f:0{width}d}.{u:03d}"
            for q, f, u in zip(secs.tolist(), ffs.tolist(), subs.tolist())]


def write_livelink(path, perf: Performance, timecode_start: str = "00:00:00:00.000",
                   timecode_rate: int = 60) -> None:
    """Write weight curves as a Live Link Face CSV that :func:`read_livelink` reads back.

    Row ``i`` gets timecode ``timecode_start + (times[i] - times[0])`` at ``timecode_rate``
    (subframe printed to 3 decimals, so times round-trip to ``1 / (2000 * rate)`` s), then
    ``BlendShapeCount`` = 61, the 52 channels in Live Link order and spelling printed ``%.10f``
    as upstream, then the 9 rotations from ``perf.extras`` (``head_rotation``, ...); a rotation
    group the performance does not carry is written as 0, which is what Live Link Face writes
    when it did not capture it. Invalid samples are written as empty cells, so a masked sample
    reads back masked; a row with nothing to write (every channel invalid and no finite
    rotation, e.g. a tracking-loss row read back) is written ``Timecode,0`` as the app writes
    tracking loss, so a real take round-trips byte for byte.

    Parameters
    ----------
    path : str or Path
    perf : Performance
        ``kind="curves"`` holding the 52 ARKit channels (any spelling :func:`canonical` maps).
    timecode_start : str
        ``HH:MM:SS:FF.sss`` of the first row (non-drop).
    timecode_rate : int
        Timecode frames per second (the file does not record it; a file shorter than a second
        needs it passed to :func:`read_livelink` again).

    Raises
    ------
    ValueError
        Not curves, a missing ARKit channel, a channel Live Link Face cannot hold (select the
        ARKit channels first), a bad ``timecode_start``/``timecode_rate``, or a rotation extra
        that is not (T, 3).
    """
    path = Path(path)
    if not isinstance(perf, Performance) or perf.kind != "curves":
        raise ValueError(f"perf: expected a curves Performance, got {getattr(perf, 'kind', type(perf).__name__)!r}")
    if int(timecode_rate) != timecode_rate or timecode_rate <= 0:
        raise ValueError(f"timecode_rate: expected a positive integer, got {timecode_rate!r}")
    rate = int(timecode_rate)
    canon = {canonical(n): j for j, n in enumerate(perf.names)}
    missing = [LIVELINK_CHANNELS[i] for i, n in enumerate(map(canonical, LIVELINK_CHANNELS)) if n not in canon]
    if missing:
        raise ValueError(f"perf {perf.name!r}: missing ARKit channels {missing}; Live Link Face CSV needs all 52")
    extra = [n for n in perf.names if canonical(n) not in ARKIT_NAMES]
    if extra:
        raise ValueError(
            f"perf {perf.name!r}: channels {extra[:8]} are not ARKit channels and have no Live Link "
            f"Face column; write perf.select(<the ARKit channels>) instead"
        )
    T = perf.n_frames
    order = [canon[canonical(n)] for n in LIVELINK_CHANNELS]
    vals = np.where(perf.valid[:, order], perf.data[:, order], np.nan)
    rots = []
    for key in ROTATIONS:
        r = perf.extras.get(key)
        if r is None:
            r = np.zeros((T, 3))
        r = np.asarray(r, dtype=np.float64)
        if r.shape != (T, 3):
            raise ValueError(f"perf {perf.name!r}: extras[{key!r}] must be (T, 3) = ({T}, 3), got {r.shape}")
        rots.append(r)
    table = np.concatenate([vals] + rots, axis=1)
    rel = perf.times - perf.times[0] if T else perf.times
    tcs = _format_timecodes(timecode_start, rate, rel)
    count = str(len(LIVELINK_CHANNELS) + len(ROTATION_COLUMNS))
    strs = np.char.mod("%.10f", table)
    finite = np.isfinite(table)
    strs[~finite] = ""
    lost = ~finite.any(axis=1)
    out = [",".join(HEADER_START + LIVELINK_CHANNELS + ROTATION_COLUMNS)]
    out += [tc + "," + TRACKING_LOST_COUNT if gone else tc + "," + count + "," + ",".join(row)
            for tc, row, gone in zip(tcs, strs.tolist(), lost.tolist())]
    path.write_text("\n".join(out) + "\n")


def arkit_curves(weights, names, fps: float, times=None, name: str = "arkit") -> tuple:
    """The 52 ARKit channels of weights on a rig's shapes, for :func:`write_livelink`.

    ``arkit = W @ G.T`` with ``G`` the automatic name map from the rig's shapes to the ARKit names
    (:meth:`core.names.NameMap.automatic`: same canonical name, ``AK_09_EyeBlinkLeft`` or
    ``eyeBlink_L`` -> ``eyeBlinkLeft``; a sideless ARKit channel such as ``browInnerUp`` is the
    mean of a rig's split pair ``browInnerUp_L`` / ``_R``). An ARKit channel no shape maps to is 0
    (the rig has no such shape, so a Live Link consumer must not move it) and is listed.

    Parameters
    ----------
    weights : (T, K) float, finite
    names : K shape names of the rig
    fps : float; times : (T,) seconds, optional (default ``arange(T) / fps``)

    Returns
    -------
    (Performance of kind "curves" with the 52 ARKit channels, list of the ARKit channels no
    shape drives)

    Raises
    ------
    ValueError
        ``weights`` not (T, K) or not finite, or no shape has an ARKit name.
    """
    W = np.asarray(weights, dtype=np.float64)
    names = [str(n) for n in names]
    if W.ndim != 2 or W.shape[1] != len(names):
        raise ValueError(f"weights: expected (T, {len(names)}) for the {len(names)} shapes, got {W.shape}")
    if not np.isfinite(W).all():
        raise ValueError("weights: NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
    nm = NameMap.automatic(names, ARKIT_NAMES)
    if not nm.entries:
        raise ValueError(f"none of the {len(names)} shapes has an ARKit name (e.g. {names[:3]}); "
                         "a Live Link Face CSV holds the 52 ARKit channels")
    G = nm.matrix(names, ARKIT_NAMES)
    perf = Performance.curves(W @ G.T, ARKIT_NAMES, fps, times=times, name=name)
    return perf, nm.unmapped(ARKIT_NAMES)
