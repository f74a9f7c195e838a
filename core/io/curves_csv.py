"""Weight curves as a plain CSV: ``time_s,frame,valid`` then one column per shape, in rig order.

The format every spreadsheet, DCC script and pandas reads. ``valid`` is 1 where the frame had
data and 0 for a gap (tracking loss): a gap's weights are the filled values that are played
(see :mod:`core.gaps`), so the curves stay continuous and the flag says which frames are real.
A NaN weight is written as an empty cell and read back as a masked sample.

:func:`read_curves_csv` also reads the older ``time_s,<shape>...`` layout.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..model import Performance
from .tabular import estimate_fps

#: the columns before the shapes
LEAD = ("time_s", "frame", "valid")


def _formatter(precision: Union[int, str, None]):
    if precision in (None, "full"):  # shortest text that reads back to the same float64
        return repr
    fmt = f"{{:.{int(precision)}f}}"
    return fmt.format


def write_curves_csv(path, times, weights, names, precision: Union[int, str, None] = 6, valid=None,
                     frames=None) -> None:
    """Write (T,) times and (T, K) weights with header ``time_s,frame,valid,<name>...``.

    Parameters
    ----------
    precision : decimals of the weights, or ``"full"`` (round-trip exact float64 text)
    valid : (T,) bool, optional — frames with data (default: frames whose weights are finite)
    frames : (T,) int, optional — the take's frame numbers (default: 0 .. T-1)
    """
    times = np.asarray(times, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2 or W.shape != (len(times), len(names)):
        raise ValueError(f"weights must be (T, K) = ({len(times)}, {len(names)}), got {W.shape}")
    valid = np.isfinite(W).all(1) if valid is None else np.asarray(valid, dtype=bool)
    frames = np.arange(len(times)) if frames is None else np.asarray(frames, dtype=np.int64)
    if valid.shape != (len(times),) or frames.shape != (len(times),):
        raise ValueError(f"valid, frames: expected ({len(times)},), got {valid.shape}, {frames.shape}")
    fmt = _formatter(precision)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([*LEAD, *names])
        for t, n, ok, row in zip(times, frames, valid, W):
            w.writerow([f"{t:.6f}", int(n), int(bool(ok))] + ["" if not np.isfinite(v) else fmt(float(v)) for v in row])


def read_curves_csv(path, name: Optional[str] = None) -> Performance:
    """Read a file written by :func:`write_curves_csv` (fps from the times,
    :func:`core.io.tabular.estimate_fps`; 30 for a single row); a ``valid`` 0 row reads as a
    frame whose samples are all missing."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    if not rows or not rows[0] or rows[0][0] != "time_s":
        raise ValueError(f"{path}: first column must be 'time_s' (a weight-curve CSV), got {rows[0][:1] if rows else 'an empty file'}")
    lead = 3 if tuple(rows[0][:3]) == LEAD else 1
    names = rows[0][lead:]
    body = rows[1:]
    bad = [i + 2 for i, r in enumerate(body) if len(r) != len(names) + lead]
    if bad:
        raise ValueError(f"{path}: rows {bad[:5]} have the wrong number of cells (expected {len(names) + lead})")
    try:
        data = np.array([[float(c) if c.strip() else np.nan for c in r] for r in body]).reshape(len(body), len(names) + lead)
    except ValueError as e:
        raise ValueError(f"{path}: non-numeric cell ({e})") from None
    times = data[:, 0]
    W = data[:, lead:]
    valid = np.isfinite(W)
    if lead == 3:
        valid &= (data[:, 2] != 0)[:, None]
    fps = estimate_fps(times, f"{path}: column time_s") if len(times) > 1 else 30.0
    return Performance.curves(np.where(valid, W, np.nan), names, fps, valid=valid, times=times - times[0], name=name or path.stem)
