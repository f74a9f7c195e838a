"""Helpers shared by the text-table readers (Live Link Face CSV, marker CSV, TRC) and glTF.

Everything here is independent of any one file format, so the format modules import it and
nothing here imports them: ``tabular`` <- ``livelink``, ``markers``, ``gltf`` <- ``performance``.

* :class:`DataQualityWarning`: a file was read, but some samples were masked.
* :func:`estimate_fps`: the sample rate of a (possibly gappy) time column.
* :func:`checked_rows`, :func:`parse_cells`: rows of a delimited table as numbers plus masks of
  the cells that are empty, non-numeric or NaN/inf.
* :func:`summarize_rows`, :func:`line_runs`, :func:`summarize_runs`: line numbers and ranges
  of lines for a message.
"""

from __future__ import annotations

import numpy as np

#: Frame rates a derived rate is snapped to when it is within :data:`FPS_SNAP_RTOL` of one.
STANDARD_FPS = (24000 / 1001, 24.0, 25.0, 30000 / 1001, 30.0, 48.0, 50.0, 60000 / 1001, 60.0,
                72.0, 90.0, 96.0, 100.0, 120000 / 1001, 120.0, 144.0, 200.0, 240.0, 250.0, 360.0, 480.0)
#: Relative tolerance for snapping: 2e-4 keeps 29.97 (1e-3 below 30) apart from 30.
FPS_SNAP_RTOL = 2e-4


class DataQualityWarning(UserWarning):
    """A file was read, but some samples were masked (NaN, empty, tracking loss ...)."""


#: What :func:`estimate_fps` may snap a measured rate to.
FPS_SNAP = ("standard", "whole", "none")


def _snap_fps(fps: float, snap: str) -> float:
    """``fps`` replaced by the rate it is within a relative :data:`FPS_SNAP_RTOL` of, if any."""
    if snap == "standard":
        candidates = STANDARD_FPS
    elif snap == "whole":
        candidates = [c for c in (round(fps), round(fps * 1.001) * 1000 / 1001) if c > 0]
    else:
        candidates = ()
    for r in candidates:
        if abs(fps - r) <= FPS_SNAP_RTOL * r:
            return float(r)
    return float(fps)


def estimate_fps(times, what: str = "times", snap: str = "standard") -> float:
    """Sample rate of a (possibly gappy) time column.

    With ``s_i`` the positive steps and ``dt_0 = median(s_i)``:

    1. each step spans ``n_i = round(s_i / dt_0)`` nominal steps; the steps that are clearly
       whole multiples (``|s_i / dt_0 - n_i| < 1/4``) give the mean step
       ``dt = sum(s_i) / sum(n_i)`` over them;
    2. ``N = round(S / dt)`` nominal steps over the span ``S = sum(s_i)``; ``fps = N / S``.

    The mean step is exact where the median step is off by the rounding of the time stamps
    (a few printed decimals; float32 seconds, whose steps are quantised by 0.4 % after two hours);
    counting over the span is not thrown off by jitter or by dropped samples (a gap of two steps
    counts as two). Repeated time stamps (zero steps) and backward jumps do not count. The result
    is then snapped (``snap``) when within a relative :data:`FPS_SNAP_RTOL`:

    * ``"standard"``: to the nearest rate in :data:`STANDARD_FPS` (capture files: Live Link
      Face, marker CSV, TRC);
    * ``"whole"``: to the nearest whole rate or NTSC rate ``n * 1000 / 1001`` (glTF animations,
      which exporters key at any whole rate: 12 and 15 as often as 24);
    * ``"none"``: not snapped.

    Parameters
    ----------
    times : (T,) float seconds
    what : str
        Names the source (file and column) in error messages.
    snap : {"standard", "whole", "none"}

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Fewer than two distinct time stamps, non-finite times, or an unknown ``snap``.
    """
    if snap not in FPS_SNAP:
        raise ValueError(f"snap: expected one of {FPS_SNAP}, got {snap!r}")
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or len(t) < 2:
        raise ValueError(f"{what}: need at least 2 samples to derive a frame rate, got {t.size}")
    if not np.isfinite(t).all():
        raise ValueError(f"{what}: time stamps must be finite")
    steps = np.diff(t)
    pos = steps[steps > 0]
    if not len(pos):
        raise ValueError(f"{what}: time stamps never increase; cannot derive a frame rate")
    ratio = pos / float(np.median(pos))
    n = np.rint(ratio)
    sure = (np.abs(ratio - n) < 0.25) & (n >= 1)  # the median step itself always is
    dt = float(pos[sure].sum() / n[sure].sum())
    span = float(pos.sum())
    return _snap_fps(max(round(span / dt), 1) / span, snap)


def summarize_rows(rows, limit: int = 8) -> str:
    """'3, 7, 12' or '3, 7, ... (and 40 more)' for a list of (line) numbers."""
    rows = list(rows)
    head = ", ".join(str(r) for r in rows[:limit])
    return head + (f", ... (and {len(rows) - limit} more)" if len(rows) > limit else "")


def runs(mask) -> np.ndarray:
    """The runs of True in a (T,) bool ``mask`` as (n, 2) int rows ``[start, stop)``."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return edges.reshape(-1, 2)


def line_runs(mask, lines) -> tuple:
    """The runs of True in ``mask`` (T,) as ``((first line, last line), ...)`` of the file
    lines ``lines`` (T,) they were read from (blank lines between rows do not split a run)."""
    lines = np.asarray(lines)
    return tuple((int(lines[a]), int(lines[b - 1])) for a, b in runs(mask))


def summarize_runs(pairs, limit: int = 8) -> str:
    """'3, 7-12, 40-41' or '..., (and 5 more)' for ``((first, last), ...)`` line pairs."""
    pairs = list(pairs)
    text = [str(a) if a == b else f"{a}-{b}" for a, b in pairs[:limit]]
    return ", ".join(text) + (f", ... (and {len(pairs) - limit} more)" if len(pairs) > limit else "")


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
