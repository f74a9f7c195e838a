"""Read and write a captured performance in whichever file format it comes in.

:func:`read_performance` dispatches on the suffix and, for ``.csv``, on the header line:

=================  ===========================================  ====================================
format             recognised by                                reader
=================  ===========================================  ====================================
Live Link Face     ``.csv`` whose header starts                 :func:`core.io.livelink.read_livelink`
                   ``Timecode,BlendShapeCount``
marker CSV         ``.csv`` whose header starts ``frame,time_s``  :func:`core.io.markers.read_marker_csv`
TRC                ``.trc``                                     :func:`core.io.markers.read_trc`
C3D                ``.c3d`` (needs ``ezc3d``)                   :func:`core.io.markers.read_c3d`
glTF animation     ``.glb`` / ``.gltf``                         ``core.io.gltf.read_animation``
=================  ===========================================  ====================================

Units rule for marker CSV files: a file that declares its units in a ``# units: <u>`` comment
line is read in those units; a file without one needs ``units=`` from the caller, except that
files named ``animface_*.csv`` (the bundled AnimFace captures, documented as centimetres in
``data/SOURCES.md``) default to ``"cm"``.

This module also holds the two helpers the readers share: :func:`estimate_fps` and
:class:`DataQualityWarning`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.model import Performance

#: Frame rates a derived rate is snapped to when it is within :data:`FPS_SNAP_RTOL` of one.
STANDARD_FPS = (24000 / 1001, 24.0, 25.0, 30000 / 1001, 30.0, 48.0, 50.0, 60000 / 1001, 60.0,
                72.0, 90.0, 96.0, 100.0, 120000 / 1001, 120.0, 144.0, 200.0, 240.0, 250.0, 360.0, 480.0)
#: Relative tolerance for snapping: 2e-4 keeps 29.97 (1e-3 below 30) apart from 30.
FPS_SNAP_RTOL = 2e-4

READ_FORMATS = {
    ".csv": "Live Link Face CSV (header 'Timecode,BlendShapeCount,...') or marker CSV (header 'frame,time_s,...')",
    ".trc": "TRC marker trajectories",
    ".c3d": "C3D marker trajectories (pip install face-retarget[c3d])",
    ".glb": "glTF 2.0 binary morph-weight animation",
    ".gltf": "glTF 2.0 morph-weight animation",
}
WRITE_FORMATS = {
    ".csv": "Live Link Face CSV for curves, marker CSV for markers",
    ".trc": "TRC for markers",
    ".c3d": "C3D for markers (pip install face-retarget[c3d])",
}


class DataQualityWarning(UserWarning):
    """A file was read, but some samples were masked (NaN, empty, tracking loss ...)."""


def estimate_fps(times, what: str = "times") -> float:
    """Sample rate of a (possibly gappy) time column.

    ``dt = median(positive steps)``; ``n = round((t[-1] - t[0]) / dt)`` nominal steps over the
    whole span; ``fps = n / (t[-1] - t[0])``. Counting nominal steps over the span is exact for
    time stamps rounded to a few decimals (the median step alone is off by the rounding) and is
    not thrown off by dropped samples (a gap of two steps counts as two). The result is snapped
    to the nearest rate in :data:`STANDARD_FPS` when within a relative :data:`FPS_SNAP_RTOL`.

    Parameters
    ----------
    times : (T,) float seconds
    what : str
        Names the source (file and column) in error messages.

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Fewer than two distinct time stamps, or non-finite times.
    """
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or len(t) < 2:
        raise ValueError(f"{what}: need at least 2 samples to derive a frame rate, got {t.size}")
    if not np.isfinite(t).all():
        raise ValueError(f"{what}: time stamps must be finite")
    steps = np.diff(t)
    pos = steps[steps > 0]
    if not len(pos):
        raise ValueError(f"{what}: time stamps never increase; cannot derive a frame rate")
    dt = float(np.median(pos))
    span = float(t.max() - t.min())
    n = max(int(round(span / dt)), 1)
    fps = n / span
    for r in STANDARD_FPS:
        if abs(fps - r) <= FPS_SNAP_RTOL * r:
            return float(r)
    return float(fps)


def summarize_rows(rows, limit: int = 8) -> str:
    """'3, 7, 12' or '3, 7, ... (and 40 more)' for a list of (line) numbers."""
    rows = list(rows)
    head = ", ".join(str(r) for r in rows[:limit])
    return head + (f", ... (and {len(rows) - limit} more)" if len(rows) > limit else "")


def parse_cells(rows: list, ncols: int, delimiter: str = ",") -> tuple[np.ndarray, dict]:
    """Numbers from text rows whose cells are all meant to be numeric.

    Parameters
    ----------
    rows : list of str
        Lines holding exactly ``ncols`` cells each (already checked by the caller).
    ncols : int
    delimiter : str

    Returns
    -------
    values : (T, ncols) float64, NaN where a cell is empty, non-numeric or NaN/inf
    bad : dict of (T, ncols) bool masks ``{"empty", "non-numeric", "nan/inf"}``
    """
    T = len(rows)
    try:
        # Fast path, C parser: every cell is a number (the usual case).
        values = np.loadtxt(rows, delimiter=delimiter, dtype=np.float64, ndmin=2, comments=None)
        if values.shape != (T, ncols):
            raise ValueError("shape")
        none = np.zeros((T, ncols), dtype=bool)
        return values, {"empty": none, "non-numeric": none.copy(), "nan/inf": ~np.isfinite(values)}
    except ValueError:
        pass
    # Slow path: find which cells are empty or not numbers, one by one.
    values = np.full((T, ncols), np.nan)
    empty = np.zeros((T, ncols), dtype=bool)
    nonnum = np.zeros((T, ncols), dtype=bool)
    for i, row in enumerate(rows):
        for j, c in enumerate(row.split(delimiter)[:ncols]):
            c = c.strip()
            if not c:
                empty[i, j] = True
                continue
            try:
                values[i, j] = float(c)
            except ValueError:
                nonnum[i, j] = True
    nonfinite = ~np.isfinite(values) & ~empty & ~nonnum
    return values, {"empty": empty, "non-numeric": nonnum, "nan/inf": nonfinite}


def checked_rows(path, rows: list, lines, ncols: int, delimiter: str = ",") -> list:
    """``rows`` with exactly ``ncols`` cells each; empty cells past ``ncols`` (trailing
    delimiters) are dropped.

    Raises
    ------
    ValueError
        Naming ``path``, the line number (from ``lines``) and the expected cell count, for a row
        with fewer cells or with non-empty cells past ``ncols`` (e.g. a truncated last row).
    """
    out = list(rows)
    sep = {",": "comma", "\t": "tab"}.get(delimiter, repr(delimiter))
    for k, ln in enumerate(out):
        n = ln.count(delimiter) + 1
        if n > ncols:
            cells = ln.split(delimiter)
            if not "".join(cells[ncols:]).strip():
                out[k] = ln = delimiter.join(cells[:ncols])
                n = ncols
        if n != ncols:
            last = " (the last row: is the file truncated?)" if k == len(out) - 1 else ""
            raise ValueError(
                f"{path}: line {lines[k]}: expected {ncols} {sep}-separated cells as in the header, "
                f"got {n}{last}"
            )
    return out


def _first_header(path: Path) -> str:
    """First line that is not blank and not a ``#`` comment (BOM stripped)."""
    with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
        for line in f:
            s = line.strip()
            if s and not s.startswith("#"):
                return s
    return ""


def _unsupported(path: Path, table: dict, verb: str) -> ValueError:
    lines = "\n".join(f"  {k}: {v}" for k, v in table.items())
    return ValueError(f"{path}: cannot {verb} suffix {path.suffix or '(none)'!r}; supported formats:\n{lines}")


def read_performance(path, **kw) -> Performance:
    """Read a performance from any supported file (see the module table).

    Parameters
    ----------
    path : str or Path
    **kw
        Passed to the format's reader (``allow_missing=`` for Live Link Face, ``units=`` for
        marker CSV/TRC, ...).

    Returns
    -------
    Performance

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Unknown suffix or CSV header (the message lists the supported formats), or the reader's
        own errors.
    ImportError
        ``.glb``/``.gltf`` while ``core.io.gltf.read_animation`` is not available, or ``.c3d``
        without ezc3d.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        header = _first_header(path)
        cells = [c.strip() for c in header.split(",")]
        if cells[:2] == ["Timecode", "BlendShapeCount"]:
            from core.io.livelink import read_livelink

            return read_livelink(path, **kw)
        if [c.lower() for c in cells[:2]] == ["frame", "time_s"]:
            from core.io.markers import declared_units, read_marker_csv

            if kw.get("units") is None and declared_units(path) is None and path.name.lower().startswith("animface_"):
                kw["units"] = "cm"  # bundled AnimFace captures: centimetres per data/SOURCES.md
            return read_marker_csv(path, **kw)
        raise ValueError(
            f"{path}: unrecognised CSV header {header[:80]!r}; expected a Live Link Face CSV "
            f"(header 'Timecode,BlendShapeCount,...') or a marker CSV (header 'frame,time_s,<name>_X,...'). "
            f"Supported formats: {', '.join(READ_FORMATS)}"
        )
    if suffix == ".trc":
        from core.io.markers import read_trc

        return read_trc(path, **kw)
    if suffix == ".c3d":
        from core.io.markers import read_c3d

        return read_c3d(path, **kw)
    if suffix in (".glb", ".gltf"):
        try:
            from core.io.gltf import read_animation
        except ImportError as e:  # another module provides it; say so rather than fail obscurely
            raise ImportError(
                f"{path}: reading a glTF animation needs core.io.gltf.read_animation, which is not "
                f"available in this build ({e})"
            ) from None
        return read_animation(path, **kw)
    raise _unsupported(path, READ_FORMATS, "read")


def write_performance(path, perf: Performance, **kw) -> None:
    """Write ``perf`` in the format named by the suffix of ``path``.

    ``.csv``: curves as Live Link Face CSV (:func:`core.io.livelink.write_livelink`), markers as
    marker CSV (:func:`core.io.markers.write_marker_csv`); ``.trc`` / ``.c3d``: markers. glTF
    animations need a rig to write against: use ``core.io.gltf`` directly.

    Raises
    ------
    TypeError
        ``perf`` is not a Performance.
    ValueError
        Unknown suffix (the message lists the supported ones), or a kind the format cannot hold.
    """
    path = Path(path)
    if not isinstance(perf, Performance):
        raise TypeError(f"perf: expected a core.model.Performance, got {type(perf).__name__}")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        if perf.kind == "curves":
            from core.io.livelink import write_livelink

            return write_livelink(path, perf, **kw)
        if perf.kind == "markers":
            from core.io.markers import write_marker_csv

            return write_marker_csv(path, perf, **kw)
        raise ValueError(f"{path}: a {perf.kind!r} performance cannot be written as CSV; expected curves or markers")
    if suffix in (".trc", ".c3d"):
        if perf.kind != "markers":
            raise ValueError(f"{path}: {suffix} holds marker trajectories; got a {perf.kind!r} performance")
        from core.io import markers

        return (markers.write_trc if suffix == ".trc" else markers.write_c3d)(path, perf, **kw)
    if suffix in (".glb", ".gltf"):
        raise ValueError(
            f"{path}: writing a glTF animation needs the target rig; use core.io.gltf's writer. "
            f"write_performance supports: {', '.join(WRITE_FORMATS)}"
        )
    raise _unsupported(path, WRITE_FORMATS, "write")
