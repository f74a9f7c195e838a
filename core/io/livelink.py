"""Live Link Face CSV: ARKit blendshape curves recorded by Epic's iPhone app.

Layout (one header line, one row per sample, comma separated, no quoting)::

    Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,
    LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll
    13:13:04:31.652,61,0.1236470118,...

* ``Timecode`` is ``HH:MM:SS:FF.sss``: FF a timecode frame counter, ``.sss`` the fraction of a
  timecode frame (subframe). The timecode rate is not written in the file. We take the smallest
  standard rate (24, 25, 30, 48, 50, 60, 120) greater than the largest counter seen; in the
  bundled captures the counter runs to 59 in steps of ~2, i.e. a 60 fps timecode sampled at
  30 Hz. A file that never crosses a second boundary cannot prove its rate: the reader warns and
  ``timecode_rate=`` overrides.
* ``BlendShapeCount`` is the number of value columns after it (61 = 52 ARKit channels + 9
  rotations in every upstream file).
* The 52 ARKit channels in Live Link order (which lists ``JawRight`` before ``JawLeft`` and
  ``MouthRight`` before ``MouthLeft``), Live Link spelling (``EyeBlinkLeft``).
* Nine rotations. Live Link Face writes 0 in the head columns when head rotation was not
  captured (true of all three bundled files). Units are not stated by the format; the values are
  kept as written. In the bundled captures the eye angles are radians: eye yaw spans about
  +/-0.61 and tracks ``eyeLookOut - eyeLookIn`` with correlation 0.999, i.e. +/-35 degrees
  (Unreal's older ARKit plugin normalised degrees/180, which would mean an impossible +/-110).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from core.io.tabular import DataQualityWarning, checked_rows, estimate_fps, parse_cells, summarize_rows
from core.model import Performance
from core.names import ARKIT_NAMES, canonical

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
TIMECODE_RATES = (24, 25, 30, 48, 50, 60, 120)
TIMECODE_FORMAT = "HH:MM:SS:FF.sss"
HEADER_START = ("Timecode", "BlendShapeCount")

_LIVE_SPELLING = {canonical(c): c for c in LIVELINK_CHANNELS}
_TC = re.compile(r"^\s*(\d{1,2}):(\d{2}):(\d{2})[:;](\d{1,3})(?:\.(\d+))?\s*$")
_DAY = 86400.0


def _parse_timecode(tc: str):
    """(hours, minutes, seconds, counter, subframe fraction) or None when malformed."""
    m = _TC.match(tc)
    if not m:
        return None
    h, mi, s, ff = (int(g) for g in m.groups()[:4])
    if h >= 24 or mi >= 60 or s >= 60:
        return None
    sub = float("0." + m.group(5)) if m.group(5) else 0.0
    return h, mi, s, ff, sub


def read_livelink(path, allow_missing: bool = False, timecode_rate=None) -> Performance:
    """Read a Live Link Face CSV as ARKit weight curves.

    Each row ``i`` gives ``w_i`` (K,) and a timecode ``HH:MM:SS:FF.sss``;
    ``t_i = 3600 HH + 60 MM + SS + (FF + .sss) / rate - t_0`` (plus 86400 s after a midnight
    wrap). ``fps`` is derived from the times (:func:`core.io.tabular.estimate_fps`), never
    assumed. Rows are not resampled: dropped samples show as longer steps in ``times``.

    Parameters
    ----------
    path : str or Path
    allow_missing : bool
        When False (default) a missing ARKit channel or rotation column is an error; when True
        the channel is simply absent from the result.
    timecode_rate : int, optional
        Timecode frames per second; default: the smallest of :data:`TIMECODE_RATES` above the
        largest frame counter in the file.

    Returns
    -------
    Performance
        ``kind="curves"``, ``data`` (T, K) with canonical ARKit names (``eyeBlinkLeft``) in file
        order, ``valid`` (T, K) False for NaN/empty/non-numeric cells and for tracking-loss rows
        (all channels empty, or all zero on a repeated timecode; their data is NaN, never 0).
        ``extras``: ``head_rotation``, ``eye_rotation_left``, ``eye_rotation_right`` (T, 3)
        yaw/pitch/roll as written (NaN where masked), ``timecode`` (T,) str,
        ``timecode_start`` str, ``timecode_rate`` int.

    Raises
    ------
    ValueError
        Naming the file, the line and column, and what was expected: a header that is not
        ``Timecode,BlendShapeCount,...``; a duplicate column; a missing channel (unless
        ``allow_missing``); a row with a different cell count (e.g. a truncated file); a bad
        timecode; a ``BlendShapeCount`` that does not match the number of value columns.
    FileNotFoundError

    Warns
    -----
    DataQualityWarning
        How many cells / rows were masked and at which lines; a non-increasing timecode; a
        timecode rate that the file cannot confirm.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    text = path.read_text(encoding="utf-8-sig")
    numbered = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip()]
    if not numbered:
        raise ValueError(f"{path}: empty file; expected a header line starting 'Timecode,BlendShapeCount'")
    header = [c.strip() for c in numbered[0][1].split(",")]
    if tuple(header[:2]) != HEADER_START:
        raise ValueError(
            f"{path}: line {numbered[0][0]}: not a Live Link Face CSV header; expected it to start "
            f"'Timecode,BlendShapeCount', got {','.join(header[:3])!r}"
        )
    value_cols = header[2:]
    dup = sorted({c for c in value_cols if value_cols.count(c) > 1})
    if dup:
        raise ValueError(f"{path}: line {numbered[0][0]}: duplicate columns {dup}")
    lines = np.array([n for n, _ in numbered[1:]], dtype=np.int64)
    if not len(lines):
        raise ValueError(f"{path}: header but no data rows (truncated file?)")
    ncol = len(header)
    rows = checked_rows(path, [ln for _, ln in numbered[1:]], lines, ncol)
    split = [ln.split(",", 2) for ln in rows]
    tcs = np.array([c[0].strip() for c in split])
    counts = np.array([c[1] for c in split])

    # -- timecodes ------------------------------------------------------------------------
    parts = []
    for k, tc in enumerate(tcs):
        p = _parse_timecode(tc)
        if p is None:
            raise ValueError(
                f"{path}: line {lines[k]}, column Timecode: {tc!r} is not a timecode; expected "
                f"{TIMECODE_FORMAT} (hours < 24, minutes and seconds < 60, frame counter, subframe)"
            )
        parts.append(p)
    parts = np.array(parts, dtype=np.float64)
    max_counter = int(parts[:, 3].max())
    if timecode_rate is None:
        above = [r for r in TIMECODE_RATES if r > max_counter]
        if not above:
            raise ValueError(
                f"{path}: column Timecode: frame counter reaches {max_counter}, above every standard "
                f"rate {TIMECODE_RATES}; pass timecode_rate="
            )
        rate = above[0]
    else:
        rate = int(timecode_rate)
        if rate <= max_counter:
            k = int(np.argmax(parts[:, 3]))
            raise ValueError(
                f"{path}: line {lines[k]}, column Timecode: frame counter {max_counter} is not "
                f"below timecode_rate={rate}"
            )
    secs = parts[:, 0] * 3600 + parts[:, 1] * 60 + parts[:, 2] + (parts[:, 3] + parts[:, 4]) / rate
    steps = np.diff(secs)
    secs = secs + _DAY * np.concatenate([[0], np.cumsum(steps < -_DAY / 2)])  # midnight wrap
    steps = np.diff(secs)
    if timecode_rate is None and not (np.diff(parts[:, 2]) != 0).any():
        warnings.warn(
            f"{path}: column Timecode never crosses a second boundary, so the timecode rate "
            f"{rate} (inferred from frame counters up to {max_counter}) is a guess; pass "
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

    # -- values ---------------------------------------------------------------------------
    values, bad = parse_cells([c[2] for c in split], len(value_cols))
    all_empty = bad["empty"].all(axis=1)
    for cval in np.unique(counts):
        where = np.flatnonzero(counts == cval)
        if not cval.strip():
            stray = where[~all_empty[where]]
            if len(stray):
                raise ValueError(
                    f"{path}: line {lines[stray[0]]}, column BlendShapeCount: empty; expected the "
                    f"number of value columns ({len(value_cols)})"
                )
            continue
        try:
            n = int(cval)
        except ValueError:
            n = None
        if n != len(value_cols):
            raise ValueError(
                f"{path}: line {lines[where[0]]}, column BlendShapeCount: {cval.strip()!r}; expected "
                f"{len(value_cols)}, the number of value columns in the header"
            )

    # -- columns --------------------------------------------------------------------------
    canon = [canonical(c) for c in value_cols]
    dup = sorted({c for c in canon if canon.count(c) > 1})
    if dup:
        raise ValueError(f"{path}: header: several columns map to the same ARKit channel {dup}")
    missing = [n for n in ARKIT_NAMES if n not in canon]
    missing_rot = [c for c in ROTATION_COLUMNS if c not in value_cols]
    if (missing or missing_rot) and not allow_missing:
        what = [_LIVE_SPELLING.get(m, m) for m in missing] + missing_rot
        raise ValueError(
            f"{path}: header: missing column(s) {what}; a Live Link Face CSV has the 52 ARKit "
            f"channels and 9 rotations (pass allow_missing=True to read the file without them)"
        )
    chan = [j for j, c in enumerate(value_cols) if c not in ROTATION_COLUMNS]
    if not chan:
        raise ValueError(f"{path}: header: no blendshape channel columns after Timecode,BlendShapeCount")
    arkit_cols = [j for j in chan if canon[j] in ARKIT_NAMES]
    data = values[:, chan]

    # -- masks ----------------------------------------------------------------------------
    ark = values[:, arkit_cols] if arkit_cols else values[:, chan]
    ark_empty = bad["empty"][:, arkit_cols if arkit_cols else chan].all(axis=1)
    repeated = np.concatenate([[False], tcs[1:] == tcs[:-1]])
    zero_rep = repeated & (ark == 0).all(axis=1)
    loss = ark_empty | zero_rep
    badcell = bad["empty"] | bad["non-numeric"] | bad["nan/inf"]
    valid = ~badcell[:, chan] & ~loss[:, None]
    data = np.where(valid, data, np.nan)

    notes = []
    if loss.any():
        notes.append(f"{int(loss.sum())} tracking-loss rows (all channels empty, or zero on a repeated "
                     f"timecode) at lines {summarize_rows(lines[loss])}")
    for kind, mask in bad.items():
        m = mask & ~loss[:, None]
        if m.any():
            r, c = np.nonzero(m)
            cols = sorted({value_cols[j] for j in c}, key=value_cols.index)
            notes.append(f"{int(m.sum())} {kind} cells at lines {summarize_rows(np.unique(lines[r]))} "
                         f"in columns {cols[:6]}{' ...' if len(cols) > 6 else ''}")
    if notes:
        warnings.warn(f"{path}: masked as invalid (not zeroed): " + "; ".join(notes),
                      DataQualityWarning, stacklevel=2)

    tcs.setflags(write=False)
    extras = {"timecode": tcs, "timecode_start": str(tcs[0]), "timecode_rate": rate}
    for key, cols in ROTATIONS.items():
        if all(c in value_cols for c in cols):
            rot = values[:, [value_cols.index(c) for c in cols]].copy()
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
    h, m, s, ff, sub = p
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
    reads back masked.

    Parameters
    ----------
    path : str or Path
    perf : Performance
        ``kind="curves"`` holding the 52 ARKit channels (any spelling :func:`canonical` maps).
    timecode_start : str
        ``HH:MM:SS:FF.sss`` of the first row.
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
    strs[~np.isfinite(table)] = ""
    out = [",".join(HEADER_START + LIVELINK_CHANNELS + ROTATION_COLUMNS)]
    out += [tc + "," + count + "," + ",".join(row) for tc, row in zip(tcs, strs.tolist())]
    path.write_text("\n".join(out) + "\n")
