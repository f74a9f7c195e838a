"""The one policy for missing samples: fill what is played and written, flag it, never score it.

A frame without data (tracking loss in a Live Link take, a frame where every marker is
occluded, a frame a solver could not determine) is a **gap**. Everywhere in the program:

* what is **played and written** (viewer tracks, GLB animations, CSV curves, dense source
  sequences) is filled by :func:`fill_gaps`: linear interpolation between the last valid frame
  before the gap and the first after it, the nearest valid frame held before the first and
  after the last valid frame (no zeros: a neutral face in the middle of a smile is a pop);
* the gap is **flagged** per frame: ``valid`` (T,) in the pipeline's results, a ``valid``
  column (1/0) in the weights CSV, and shaded bands in the dashboard's curve plot;
* gaps are **excluded** from every error statistic (:func:`core.evaluate.evaluate`).

A take with no valid frame at all cannot be filled from anything: :func:`fill_gaps` returns
zeros then (and every frame stays flagged).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fill_gaps", "gap_ranges"]


def fill_gaps(X, valid) -> np.ndarray:
    """``X`` (T, ...) with the rows where ``valid`` (T,) is False filled from the valid ones.

    Linear in time across interior gaps (``x_t = x_a + (t - a)/(b - a) (x_b - x_a)`` between
    valid frames ``a < t < b``), the nearest valid row held at both ends. Non-finite entries
    of valid rows are filled the same way, per column. Returns a new float64 array.

    Raises
    ------
    ValueError
        ``valid`` is not (T,) for T = len(X).
    """
    X = np.array(X, dtype=np.float64)  # a copy: inputs are never modified
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != (len(X),):
        raise ValueError(f"valid: expected ({len(X)},) frame flags, got {valid.shape}")
    T = len(X)
    if T == 0:
        return X
    flat = X.reshape(T, -1)
    ok = valid[:, None] & np.isfinite(flat)
    if ok.all():
        return X
    t = np.arange(T, dtype=np.float64)
    cols = np.flatnonzero(~ok.all(0))
    # columns sharing a validity pattern (the usual case: whole frames missing) share one interpolation
    patterns: dict = {}
    for c in cols:
        patterns.setdefault(ok[:, c].tobytes(), []).append(c)
    for key, cs in patterns.items():
        good = ok[:, cs[0]]
        if not good.any():
            flat[:, cs] = 0.0
            continue
        tg = t[good]
        for c in cs:
            flat[:, c] = np.interp(t, tg, flat[good, c])  # np.interp holds the end values
    return flat.reshape(X.shape)


def gap_ranges(valid) -> list:
    """The gaps of a (T,) validity flag as inclusive ``(first, last)`` frame ranges."""
    v = np.asarray(valid, dtype=bool)
    if v.all():
        return []
    d = np.diff(np.r_[0, (~v).astype(np.int8), 0])
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, stops)]
