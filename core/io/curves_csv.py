"""Weight curves as a plain CSV: ``time_s`` then one column per shape, in rig order.

The format every spreadsheet, DCC script and pandas reads; NaN (a frame with no data) is
written as an empty cell and read back as a masked sample.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..model import Performance
from .tabular import estimate_fps


def write_curves_csv(path, times, weights, names, precision: int = 6) -> None:
    """Write (T,) times and (T, K) weights with header ``time_s,<name>...``."""
    times = np.asarray(times, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2 or W.shape != (len(times), len(names)):
        raise ValueError(f"weights must be (T, K) = ({len(times)}, {len(names)}), got {W.shape}")
    fmt = f"{{:.{precision}f}}"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", *names])
        for t, row in zip(times, W):
            w.writerow([f"{t:.6f}"] + ["" if not np.isfinite(v) else fmt.format(v) for v in row])


def read_curves_csv(path, name: str | None = None) -> Performance:
    """Read a file written by :func:`write_curves_csv` (fps from the times,
    :func:`core.io.tabular.estimate_fps`; 30 for a single row)."""
    path = Path(path)
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows or not rows[0] or rows[0][0] != "time_s":
        raise ValueError(f"{path}: first column must be 'time_s' (a weight-curve CSV), got {rows[0][:1] if rows else 'an empty file'}")
    names = rows[0][1:]
    body = rows[1:]
    bad = [i + 2 for i, r in enumerate(body) if len(r) != len(names) + 1]
    if bad:
        raise ValueError(f"{path}: rows {bad[:5]} have the wrong number of cells (expected {len(names) + 1})")
    try:
        data = np.array([[float(c) if c.strip() else np.nan for c in r] for r in body]).reshape(len(body), len(names) + 1)
    except ValueError as e:
        raise ValueError(f"{path}: non-numeric cell ({e})") from None
    times = data[:, 0]
    fps = estimate_fps(times, f"{path}: column time_s") if len(times) > 1 else 30.0
    return Performance.curves(data[:, 1:], names, fps, times=times - times[0], name=name or path.stem)
