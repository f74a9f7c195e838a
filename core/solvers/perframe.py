"""Per-frame least-squares retargeting: the baseline every other method is compared with.

For every frame t independently:

    lsq:      min_w || B w - s_t ||^2                       (Seol 2012 §7 "No Const")
    bounded:  min_w || B w - s_t ||^2,  lo <= w <= hi       (Bregler et al. 2002; "Range PF")

B is the (3M x K) matrix of marker deltas (``flatten(deltas).T``), s_t the (3M,) source
marker deltas. Missing samples remove the marker's three rows for that frame. Frames are
batched: frames that share a validity pattern share one pseudo-inverse (lsq); the bounded
solve calls SciPy's ``lsq_linear`` (BVLS) per frame, warm-free but exact.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..model import flatten
from ..progress import ProgressFn, report


def _check(deltas, S, valid):
    deltas = np.asarray(deltas, dtype=np.float64)
    S = np.asarray(S, dtype=np.float64)
    if deltas.ndim != 3 or deltas.shape[2] != 3:
        raise ValueError(f"deltas must be (K, M, 3), got {deltas.shape}")
    K, M, _ = deltas.shape
    if S.ndim != 3 or S.shape[1:] != (M, 3):
        raise ValueError(f"source deltas must be (T, {M}, 3) to match {M} markers, got {S.shape}")
    if valid is None:
        valid = np.isfinite(S).all(axis=2)
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != S.shape[:2]:
        raise ValueError(f"valid must be {S.shape[:2]}, got {valid.shape}")
    return deltas, S, valid


def _patterns(valid: np.ndarray):
    """Group frames by validity pattern: yields (row mask (3M,), frame indices)."""
    pats, inverse = np.unique(valid, axis=0, return_inverse=True)
    for p, pat in enumerate(pats):
        yield np.repeat(pat, 3), np.flatnonzero(inverse.ravel() == p)


def solve_lsq(deltas, S, valid=None, rcond: float = 1e-10) -> np.ndarray:
    """Unconstrained per-frame least squares, all frames at once.

    Parameters
    ----------
    deltas : (K, M, 3) target marker deltas (after calibration).
    S : (T, M, 3) source marker deltas (NaN where missing).
    valid : (T, M) bool, optional (default: finite samples).
    rcond : singular values below ``rcond * s_max`` are dropped (minimum-norm solution for
        shapes the markers cannot see, e.g. eye-look shapes).

    Returns
    -------
    W : (T, K); frames with no valid marker get NaN.
    """
    deltas, S, valid = _check(deltas, S, valid)
    B = flatten(deltas).T  # (3M, K)
    s = flatten(np.nan_to_num(S))  # (T, 3M)
    W = np.full((len(S), len(deltas)), np.nan)
    for rows, frames in _patterns(valid):
        if not rows.any():
            continue
        pinv = np.linalg.pinv(B[rows], rcond=rcond)  # (K, r)
        W[frames] = s[frames][:, rows] @ pinv.T
    return W


def solve_bounded(deltas, S, valid=None, lower: float = 0.0, upper: float = 1.0,
                  progress: Optional[ProgressFn] = None, tol: float = 1e-10) -> np.ndarray:
    """Per-frame bounded least squares ``lower <= w <= upper`` with SciPy's BVLS.

    Same arguments as :func:`solve_lsq`; ``progress(fraction, message)`` is called as frames
    finish. Returns W (T, K).
    """
    from scipy.optimize import lsq_linear

    deltas, S, valid = _check(deltas, S, valid)
    if not lower < upper:
        raise ValueError(f"bounds must satisfy lower < upper, got {lower}, {upper}")
    B = flatten(deltas).T
    s = flatten(np.nan_to_num(S))
    T = len(S)
    W = np.full((T, len(deltas)), np.nan)
    done = 0
    for rows, frames in _patterns(valid):
        if not rows.any():
            done += len(frames)
            continue
        Br = B[rows]
        for t in frames:
            W[t] = lsq_linear(Br, s[t, rows], bounds=(lower, upper), method="bvls", tol=tol).x
            done += 1
            if done % 50 == 0:
                report(progress, done / T, f"frame {done}/{T}")
    report(progress, 1.0, f"{T} frames")
    return W
