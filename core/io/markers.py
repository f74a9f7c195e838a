"""Optical marker trajectories: marker CSV, TRC and C3D.

All readers return ``Performance.markers``: ``data`` (T, M, 3) in metres, ``valid`` (T, M) False
for a marker-frame with any empty / NaN / non-numeric coordinate (its data is NaN, never 0),
``times`` (T,) seconds from the first sample, ``units`` the unit the file was in, and
``extras["frame"]`` (T,) the file's frame numbers (plus ``extras["start_time"]``, the file's first
time stamp, where the format has a time column).

Marker CSV
    ``frame,time_s,<name>_X,<name>_Y,<name>_Z,...``, comma separated. Units rule: a
    ``# units: <u>`` comment line before the header declares them; without one the caller must
    pass ``units=`` (``read_performance`` passes ``"cm"`` for ``animface_*.csv``, the bundled
    AnimFace captures that ``data/SOURCES.md`` documents as centimetres). Units are never guessed
    from the numbers. ``fps`` comes from ``time_s`` (:func:`core.io.tabular.estimate_fps`).
TRC
    The OpenSim/Vicon text format: ``PathFileType 4 (X/Y/Z) <file>``; a line of keys
    (``DataRate CameraRate NumFrames NumMarkers Units OrigDataRate OrigDataStartFrame
    OrigNumFrames``) and a line of their values; ``Frame# Time <name> <tab> <tab> <name> ...``;
    ``<tab> <tab> X1 Y1 Z1 X2 ...``; then tab-separated rows, a missing marker as empty cells.
    ``fps`` = ``DataRate``.
C3D
    Via the optional ``ezc3d`` package (``pip install face-retarget[c3d]``): ``POINT:LABELS``
    (+ ``LABELS2`` ...), ``POINT:RATE``, ``POINT:UNITS``; residual < 0 marks an invalid sample.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from core.io.tabular import DataQualityWarning, checked_rows, estimate_fps, parse_cells, summarize_rows
from core.model import Performance, unit_scale

_UNITS = re.compile(r"^#\s*units\s*[:=]\s*(\S+)\s*$", re.IGNORECASE)
_AXES = ("X", "Y", "Z")


# -- shared ----------------------------------------------------------------------------------
def _resolve_units(path: Path, declared, units, field: str) -> str:
    """The units to read ``path`` in: the caller's ``units`` or what the file declares; both
    given and different is an error, neither is an error."""
    if units is not None and declared is not None and unit_scale(units) != unit_scale(declared):
        raise ValueError(f"{path}: {field} declares units {declared!r} but units={units!r} was passed; "
                         f"drop the argument or fix the file")
    u = units if units is not None else declared
    if u is None:
        raise ValueError(f"{path}: {field}: no units declared; add a '# units: cm' line before the header "
                         f"or pass units= (one of 'm', 'cm', 'mm', ...)")
    try:
        unit_scale(u)
    except ValueError as e:
        raise ValueError(f"{path}: {field}: {e}") from None
    return u


def _warn_masked(path, valid_file: np.ndarray, lines, names, what: str) -> None:
    """One DataQualityWarning naming how many marker-frames were masked, where."""
    bad = ~valid_file
    if bad.any():
        r, c = np.nonzero(bad)
        markers = sorted({names[j] for j in c}, key=list(names).index)
        warnings.warn(
            f"{path}: masked as invalid (not zeroed): {int(bad.sum())} marker-frames with {what} at "
            f"lines {summarize_rows(np.unique(np.asarray(lines)[r]))}, markers {markers[:6]}"
            f"{' ...' if len(markers) > 6 else ''}",
            DataQualityWarning, stacklevel=3,
        )


def _frames_column(path, col: np.ndarray, bad: dict, j: int, lines, name: str) -> np.ndarray:
    """A column that must hold a number on every row (frame numbers, time stamps)."""
    for kind in ("empty", "non-numeric", "nan/inf"):
        rows = np.flatnonzero(bad[kind][:, j])
        if len(rows):
            raise ValueError(f"{path}: line {lines[rows[0]]}, column {name}: {kind} cell; expected a number on every row")
    return col


def _frame_numbers(perf: Performance, start: int) -> np.ndarray:
    f = perf.extras.get("frame")
    if f is not None and np.shape(f) == (perf.n_frames,):
        return np.asarray(f, dtype=np.int64)
    return np.arange(perf.n_frames, dtype=np.int64) + start


def _check_markers(perf, what: str) -> None:
    if not isinstance(perf, Performance) or perf.kind != "markers":
        raise ValueError(f"perf: {what} holds marker trajectories; got {getattr(perf, 'kind', type(perf).__name__)!r}")


def _text_lines(path: Path):
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    return path.read_text(encoding="utf-8-sig").splitlines()


# -- marker CSV --------------------------------------------------------------------------------
def declared_units(path) -> str | None:
    """Units from a ``# units: <u>`` comment line before the header of a marker CSV, else None."""
    with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
        for line in f:
            s = line.strip()
            if not s:
                continue
            if not s.startswith("#"):
                return None
            m = _UNITS.match(s)
            if m:
                return m.group(1)
    return None


def read_marker_csv(path, units=None) -> Performance:
    """Read a marker CSV ``frame,time_s,<name>_X,<name>_Y,<name>_Z,...``.

    ``positions[t, m] = scale(units) * (X, Y, Z)`` in metres; ``times = time_s - time_s[0]``;
    ``fps`` from ``time_s`` (median step over the span, snapped to a standard rate).

    Parameters
    ----------
    path : str or Path
    units : str, optional
        Units of the coordinates. Required when the file has no ``# units:`` comment line; when
        both are present they must agree.

    Returns
    -------
    Performance
        ``kind="markers"``, (T, M, 3) metres, ``valid`` (T, M), ``extras["frame"]`` (T,) int,
        ``extras["start_time"]`` float seconds.

    Raises
    ------
    ValueError
        Naming the file, line/column and what was expected: a header not starting
        ``frame,time_s``, coordinate columns not in ``_X,_Y,_Z`` triplets of one name, duplicate
        marker names, no or conflicting units, a row with a different cell count (truncated
        file), a missing or non-numeric ``frame``/``time_s`` cell, a non-integer frame number.

    Warns
    -----
    DataQualityWarning
        How many marker-frames were masked (empty / NaN / non-numeric), at which lines.
    """
    path = Path(path)
    text = _text_lines(path)
    numbered = [(i + 1, ln) for i, ln in enumerate(text) if ln.strip() and not ln.lstrip().startswith("#")]
    if not numbered:
        raise ValueError(f"{path}: empty file; expected a header 'frame,time_s,<name>_X,<name>_Y,<name>_Z,...'")
    hline, hl = numbered[0]
    header = [c.strip() for c in hl.split(",")]
    if [c.lower() for c in header[:2]] != ["frame", "time_s"]:
        raise ValueError(f"{path}: line {hline}: header must start 'frame,time_s', got {','.join(header[:2])!r}")
    coords = header[2:]
    if len(coords) % 3:
        raise ValueError(f"{path}: line {hline}: {len(coords)} coordinate columns after frame,time_s; "
                         f"expected <name>_X,<name>_Y,<name>_Z triplets (a multiple of 3)")
    names = []
    for m in range(len(coords) // 3):
        first = coords[3 * m]
        if not first.upper().endswith("_X") or len(first) < 3:
            raise ValueError(f"{path}: line {hline}, header column {3 * m + 3} {first!r}: expected '<name>_X'")
        name = first[:-2]
        for a in (1, 2):
            want = f"{name}_{_AXES[a]}"
            if coords[3 * m + a].upper() != want.upper():
                raise ValueError(f"{path}: line {hline}, header column {3 * m + a + 3} "
                                 f"{coords[3 * m + a]!r}: expected {want!r}")
        names.append(name)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{path}: line {hline}: duplicate marker names {dup}")
    u = _resolve_units(path, declared_units(path), units, "'# units:' comment")
    lines = np.array([n for n, _ in numbered[1:]], dtype=np.int64)
    if not len(lines):
        raise ValueError(f"{path}: header but no data rows (truncated file?)")
    rows = checked_rows(path, [ln for _, ln in numbered[1:]], lines, len(header))
    values, bad = parse_cells(rows, len(header))
    frame = _frames_column(path, values[:, 0], bad, 0, lines, header[0])
    time_s = _frames_column(path, values[:, 1], bad, 1, lines, header[1])
    nonint = np.flatnonzero(frame != np.round(frame))
    if len(nonint):
        raise ValueError(f"{path}: line {lines[nonint[0]]}, column frame: {float(frame[nonint[0]]):g}; expected an integer frame number")
    T, M = len(rows), len(names)
    xyz = values[:, 2:].reshape(T, M, 3)
    ok = np.isfinite(xyz).all(axis=2)
    _warn_masked(path, ok, lines, names, "empty/NaN/non-numeric coordinates")
    fps = estimate_fps(time_s, f"{path}: column time_s")
    extras = {"frame": frame.astype(np.int64), "start_time": float(time_s[0])}
    return Performance.markers(xyz * unit_scale(u), names, fps, valid=ok, times=time_s - time_s[0],
                               units=u, name=path.stem, extras=extras)


def write_marker_csv(path, perf: Performance, units: str = "cm", decimals: int = 6) -> None:
    """Write markers as ``# units: <u>`` then ``frame,time_s,<name>_X,<name>_Y,<name>_Z,...``.

    Coordinates are ``data / scale(units)`` printed with ``decimals`` decimals (round trip to
    ``0.5 * 10**-decimals`` units); ``time_s = extras["start_time"] + times`` (``%.6f``), ``frame``
    from ``extras["frame"]`` else 0..T-1. An invalid marker-frame is written as three empty cells.

    Raises
    ------
    ValueError
        Not a marker performance; unknown units.
    """
    path = Path(path)
    _check_markers(perf, "a marker CSV")
    scale = unit_scale(units)
    T, M = perf.n_frames, len(perf.names)
    header = ["frame", "time_s"] + [f"{n}_{a}" for n in perf.names for a in _AXES]
    xyz = np.where(perf.valid[..., None], perf.data, np.nan) / scale
    cells = np.char.mod(f"%.{int(decimals)}f", xyz.reshape(T, 3 * M))
    cells[~np.isfinite(xyz.reshape(T, 3 * M))] = ""
    frames = _frame_numbers(perf, 0)
    t = float(perf.extras.get("start_time", 0.0)) + perf.times
    out = [f"# units: {units}", ",".join(header)]
    out += [f"{f},{ts:.6f}," + ",".join(r) for f, ts, r in zip(frames.tolist(), t.tolist(), cells.tolist())]
    path.write_text("\n".join(out) + "\n")


# -- TRC ----------------------------------------------------------------------------------------
_TRC_KEYS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
             "OrigDataStartFrame", "OrigNumFrames")


def read_trc(path) -> Performance:
    """Read a TRC file (OpenSim/Vicon marker trajectories, tab separated).

    ``positions = scale(Units) * (X, Y, Z)`` in metres; ``fps = DataRate``;
    ``times = Time - Time[0]``.

    Returns
    -------
    Performance
        ``kind="markers"``; ``extras["frame"]`` the ``Frame#`` column, ``extras["start_time"]``
        the first ``Time``, ``extras["camera_rate"]`` when given.

    Raises
    ------
    ValueError
        Naming the file, line and field: a first line not ``PathFileType``; a missing or
        non-numeric ``DataRate``/``NumFrames``/``NumMarkers``; unknown ``Units``; marker names
        that do not match ``NumMarkers``; a row with a different cell count; a data row count
        that does not match ``NumFrames`` (truncated file); a missing ``Frame#``/``Time`` cell.

    Warns
    -----
    DataQualityWarning
        Masked marker-frames (empty / NaN / non-numeric cells); a ``Time`` column whose rate
        disagrees with ``DataRate`` by more than 1 %.
    """
    path = Path(path)
    text = [ln.rstrip("\r\n") for ln in _text_lines(path)]
    if len(text) < 5 or not text[0].startswith("PathFileType"):
        raise ValueError(f"{path}: line 1: expected a TRC header starting 'PathFileType' followed by "
                         f"4 header lines, got {text[0][:40] if text else ''!r}")
    keys = [k.strip() for k in text[1].split("\t")]
    vals = [v.strip() for v in text[2].split("\t")]
    head = dict(zip(keys, vals))

    def number(key, kind=float):
        try:
            v = float(head[key])
        except KeyError:
            raise ValueError(f"{path}: line 2: field {key} missing; expected the keys {list(_TRC_KEYS)}") from None
        except ValueError:
            raise ValueError(f"{path}: line 3, field {key}: {head[key]!r}; expected a number") from None
        if kind is int and v != int(v):
            raise ValueError(f"{path}: line 3, field {key}: {head[key]!r}; expected an integer")
        return kind(v)

    rate, nframes, nmarkers = number("DataRate"), number("NumFrames", int), number("NumMarkers", int)
    if "Units" not in head:
        raise ValueError(f"{path}: line 2: field Units missing; expected the keys {list(_TRC_KEYS)}")
    u = _resolve_units(path, head["Units"], None, "line 3, field Units")
    names = [c.strip() for c in text[3].split("\t")[2:] if c.strip()]
    if len(names) != nmarkers:
        raise ValueError(f"{path}: line 4: {len(names)} marker names but NumMarkers is {nmarkers}")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{path}: line 4: duplicate marker names {dup}")
    numbered = [(i + 1, ln) for i, ln in enumerate(text[5:], start=5) if ln.strip()]
    lines = np.array([n for n, _ in numbered], dtype=np.int64)
    if len(lines) != nframes:
        raise ValueError(f"{path}: field NumFrames is {nframes} but the file has {len(lines)} data rows "
                         f"(truncated file?)")
    if not nframes:
        raise ValueError(f"{path}: no data rows")
    ncol = 2 + 3 * nmarkers
    rows = checked_rows(path, [ln for _, ln in numbered], lines, ncol, "\t")
    values, bad = parse_cells(rows, ncol, "\t")
    frame = _frames_column(path, values[:, 0], bad, 0, lines, "Frame#")
    time = _frames_column(path, values[:, 1], bad, 1, lines, "Time")
    T = len(rows)
    xyz = values[:, 2:].reshape(T, nmarkers, 3)
    ok = np.isfinite(xyz).all(axis=2)
    _warn_masked(path, ok, lines, names, "empty/NaN/non-numeric coordinates")
    if T >= 2 and np.ptp(time) > 0:
        measured = estimate_fps(time, f"{path}: column Time")
        if abs(measured - rate) > 0.01 * rate:
            warnings.warn(f"{path}: field DataRate is {rate} but column Time steps at {measured:.4g} Hz; "
                          f"using DataRate", DataQualityWarning, stacklevel=2)
    extras = {"frame": frame.astype(np.int64), "start_time": float(time[0])}
    if "CameraRate" in head:
        try:
            extras["camera_rate"] = float(head["CameraRate"])
        except ValueError:
            pass
    return Performance.markers(xyz * unit_scale(u), names, rate, valid=ok, times=time - time[0],
                               units=u, name=path.stem, extras=extras)


def write_trc(path, perf: Performance, units: str = "mm", decimals: int = 5) -> None:
    """Write markers as a TRC file (PathFileType 4) that :func:`read_trc` and OpenSim read.

    ``DataRate = CameraRate = OrigDataRate = fps``; ``Frame#`` from ``extras["frame"]`` else
    1..T; ``Time = extras["start_time"] + times``; coordinates ``data / scale(units)`` with
    ``decimals`` decimals; an invalid marker-frame as three empty cells.

    Raises
    ------
    ValueError
        Not a marker performance; unknown units; a marker name containing a tab.
    """
    path = Path(path)
    _check_markers(perf, "a TRC file")
    scale = unit_scale(units)
    bad = [n for n in perf.names if "\t" in n]
    if bad:
        raise ValueError(f"perf {perf.name!r}: marker names {bad} contain a tab, which TRC cannot hold")
    T, M = perf.n_frames, len(perf.names)
    frames = _frame_numbers(perf, 1)
    t = float(perf.extras.get("start_time", 0.0)) + perf.times
    xyz = (np.where(perf.valid[..., None], perf.data, np.nan) / scale).reshape(T, 3 * M)
    cells = np.char.mod(f"%.{int(decimals)}f", xyz)
    cells[~np.isfinite(xyz)] = ""
    fps = f"{perf.fps:.10g}"
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(_TRC_KEYS),
        "\t".join([fps, fps, str(T), str(M), units, fps, str(int(frames[0]) if T else 1), str(T)]),
        "\t".join(["Frame#", "Time"] + [f"{n}\t\t" for n in perf.names]).rstrip("\t"),
        "\t".join(["", ""] + [f"{a}{m + 1}" for m in range(M) for a in _AXES]),
        "",
    ]
    out += [f"{f}\t{ts:.6f}\t" + "\t".join(r) for f, ts, r in zip(frames.tolist(), t.tolist(), cells.tolist())]
    path.write_text("\n".join(out) + "\n")


# -- C3D ----------------------------------------------------------------------------------------
def _ezc3d():
    try:
        import ezc3d
    except ImportError:
        raise ImportError("C3D support needs the ezc3d package: pip install face-retarget[c3d]") from None
    return ezc3d


def read_c3d(path, units=None) -> Performance:
    """Read marker trajectories from a C3D file with ezc3d.

    ``positions = scale(POINT:UNITS) * points[:3]`` in metres; ``fps = POINT:RATE``;
    ``times = arange(T) / fps``; a sample is invalid where its residual is < 0 (C3D's flag for
    an unreconstructed point) or its coordinates are not finite.

    Parameters
    ----------
    path : str or Path
    units : str, optional
        Needed only when ``POINT:UNITS`` is empty; must agree with it otherwise.

    Returns
    -------
    Performance
        ``kind="markers"``; ``extras["frame"]`` the C3D frame numbers (first frame from the header).

    Raises
    ------
    ImportError
        ezc3d is not installed (``pip install face-retarget[c3d]``).
    ValueError
        Naming the file and parameter: no points, unreadable file, missing/unknown units, labels
        that do not match the point count, duplicate labels.

    Warns
    -----
    DataQualityWarning
        How many marker-frames were masked.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    ezc3d = _ezc3d()
    try:
        c = ezc3d.c3d(str(path), extract_forceplat_data=False)
    except Exception as e:  # ezc3d raises plain RuntimeError/IOError on bad files
        raise ValueError(f"{path}: not a readable C3D file ({e})") from None
    point = c["parameters"]["POINT"]
    pts = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, M, T)
    M, T = pts.shape[1], pts.shape[2]
    if not T or not M:
        raise ValueError(f"{path}: no point data (POINT:USED = {M}, {T} frames)")
    labels = [str(s).strip() for s in point["LABELS"]["value"]]
    k = 2
    while len(labels) < M and f"LABELS{k}" in point:
        labels += [str(s).strip() for s in point[f"LABELS{k}"]["value"]]
        k += 1
    if len(labels) < M:
        raise ValueError(f"{path}: parameter POINT:LABELS has {len(labels)} labels for {M} points")
    labels = labels[:M]
    dup = sorted({n for n in labels if labels.count(n) > 1})
    if dup:
        raise ValueError(f"{path}: parameter POINT:LABELS: duplicate labels {dup}")
    declared = [str(s).strip() for s in point.get("UNITS", {}).get("value", [])]
    u = _resolve_units(path, declared[0] if declared and declared[0] else None, units, "parameter POINT:UNITS")
    rate = float(np.ravel(point["RATE"]["value"])[0])
    if not rate > 0:
        raise ValueError(f"{path}: parameter POINT:RATE is {rate}; expected a positive frame rate")
    xyz = pts[:3].transpose(2, 1, 0)  # (T, M, 3)
    ok = np.isfinite(xyz).all(axis=2)
    meta = c["data"].get("meta_points", {})
    if "residuals" in meta:
        ok &= np.asarray(meta["residuals"])[0].T >= 0
    first = int(c["header"]["points"]["first_frame"])
    frames = first + np.arange(T)
    _warn_masked(path, ok, frames, labels, "residual < 0 or non-finite coordinates (frames, not lines)")
    return Performance.markers(xyz * unit_scale(u), labels, rate, valid=ok, units=u, name=path.stem,
                               extras={"frame": frames})


def write_c3d(path, perf: Performance, units: str = "mm") -> None:
    """Write markers to a C3D file with ezc3d (float storage).

    ``points[:3] = data / scale(units)``; ``POINT:RATE = fps``; ``POINT:LABELS = names``;
    ``POINT:UNITS = units``; an invalid marker-frame gets residual -1 (its coordinates are
    stored as 0 with the invalid flag); the header's first frame = ``extras["frame"][0]`` (else
    0). Times are not stored: C3D frames are uniform at ``fps``.

    Raises
    ------
    ImportError
        ezc3d is not installed.
    ValueError
        Not a marker performance; unknown units.
    """
    path = Path(path)
    _check_markers(perf, "a C3D file")
    scale = unit_scale(units)
    ezc3d = _ezc3d()
    T, M = perf.n_frames, len(perf.names)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([perf.fps])
    c["parameters"]["POINT"]["LABELS"]["value"] = list(perf.names)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    pts = np.ones((4, M, T))
    pts[:3] = np.where(perf.valid[..., None], perf.data / scale, 0.0).transpose(2, 1, 0)
    res = np.where(perf.valid.T, 0.0, -1.0)[None]
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": np.zeros((7, M, T), dtype=bool)}
    if T:
        c["header"]["points"]["first_frame"] = int(_frame_numbers(perf, 0)[0])
    c.write(str(path))
