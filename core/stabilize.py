"""Rigid head-motion removal (Seol et al. 2012, §3.1).

For every frame t the rotation R_t and translation t_t that best map the neutral markers Y
onto the captured markers X_t are found by Procrustes analysis (Kabsch):

    min_{R in SO(3), t}  sum_i  v_ti * || R y_i + t - x_ti ||^2

with v_ti = 1 for valid samples of the *rigid* markers (forehead, nose bridge ... when they
can be named, else all markers) and 0 otherwise. The stabilised frame is
R_t^T (X_t - t_t); (R_t, t_t) are kept so the head motion can be re-applied to the target.

The paper writes the SVD as Y^T X_l = U D V^T, R = V U^T; we use the centred, reflection-
corrected form of the same solution (Kabsch 1976), batched over all frames with one
``numpy.linalg.svd`` call (:func:`core.geometry.procrustes`).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass

import numpy as np

from .geometry import procrustes
from .model import Performance

#: Name patterns of markers that move with the skull, not with expressions.
RIGID_PATTERN = re.compile(r"(forehead|nosetop|nose_?bridge|temple|ear|head_?top|skull|glabella)", re.IGNORECASE)


def rigid_marker_names(names) -> list:
    """Markers whose names say they sit on the skull (forehead, nose bridge, temples, ears)."""
    return [n for n in names if RIGID_PATTERN.search(n)]


@dataclass(frozen=True)
class Stabilized:
    """Result of :func:`stabilize`.

    Attributes
    ----------
    markers : Performance
        Stabilised marker performance (NaN kept where samples are missing).
    rotations : (T, 3, 3)  with  X_t ≈ R_t Y + t_t
    translations : (T, 3)
    neutral : (M, 3) the neutral markers the frames were aligned to
    residual : (T,) RMS distance (metres) of the rigid markers after alignment
    held : (T,) bool, frames with fewer than 3 valid rigid markers whose motion was
        interpolated from neighbouring frames
    rigid : tuple of marker names used for the fit
    """

    markers: Performance
    rotations: np.ndarray
    translations: np.ndarray
    neutral: np.ndarray
    residual: np.ndarray
    held: np.ndarray
    rigid: tuple


def kabsch(Y: np.ndarray, X: np.ndarray, weights: np.ndarray):
    """Batched weighted Kabsch: R_t, t_t minimising sum_i w_ti ||R_t y_i + t_t - x_ti||^2
    (:func:`core.geometry.procrustes`, rigid, one SVD call for all frames).

    Parameters
    ----------
    Y : (M, 3) reference points.
    X : (T, M, 3) targets (NaN allowed where weight is 0).
    weights : (T, M) non-negative.

    Returns
    -------
    R : (T, 3, 3) proper rotations (det = +1), t : (T, 3)
    """
    _, R, t = procrustes(Y, X, weights)
    return R, t


def stabilize(perf: Performance, neutral=None, neutral_frame: int = 0, rigid=None, robust_iters: int = 2) -> Stabilized:
    """Remove rigid head motion from a marker performance (Seol 2012 §3.1).

    Parameters
    ----------
    perf : Performance of kind "markers".
    neutral : (M, 3), optional
        Neutral marker positions; default: frame ``neutral_frame`` of ``perf`` (every
        marker must be valid there).
    rigid : sequence of names, optional
        Markers used for the rigid fit; default :func:`rigid_marker_names` when at least 3
        are present, else all markers.
    robust_iters : int
        Re-weighting passes that down-weight markers whose residual is far above the median
        (Tukey-style), so a mislabelled or swapping marker does not tilt the head.

    Raises
    ------
    ValueError when ``perf`` is not markers, the neutral frame has missing markers, or
    fewer than 3 rigid markers exist.
    """
    if perf.kind != "markers":
        raise ValueError(f"stabilize: needs a marker performance, got kind {perf.kind!r}")
    X = perf.data
    T, M, _ = X.shape
    if neutral is None:
        if not 0 <= neutral_frame < T:
            raise ValueError(f"stabilize: neutral_frame {neutral_frame} outside 0..{T - 1}")
        if not perf.valid[neutral_frame].all():
            missing = [perf.names[i] for i in np.flatnonzero(~perf.valid[neutral_frame])]
            raise ValueError(
                f"stabilize: neutral frame {neutral_frame} of {perf.name!r} misses markers {missing}; "
                "choose a neutral_frame where every marker is tracked"
            )
        neutral = X[neutral_frame]
    neutral = np.asarray(neutral, dtype=np.float64)
    if neutral.shape != (M, 3):
        raise ValueError(f"stabilize: neutral must be ({M}, 3), got {neutral.shape}")
    if rigid is None:
        rigid = rigid_marker_names(perf.names)
        if len(rigid) < 3:
            rigid = list(perf.names)
    missing = [n for n in rigid if n not in perf.names]
    if missing:
        raise ValueError(f"stabilize: rigid markers {missing} are not in {perf.name!r}")
    if len(rigid) < 3:
        raise ValueError(f"stabilize: need at least 3 rigid markers, got {list(rigid)}")
    sel = np.array([perf.names.index(n) for n in rigid])
    w = perf.valid[:, sel].astype(np.float64)
    Y = neutral[sel]
    Xs = X[:, sel]
    ok = (w > 0).sum(1) >= 3
    for it in range(robust_iters + 1):
        R, t = kabsch(Y, np.where(w[..., None] > 0, Xs, 0.0), np.where(ok[:, None], w, 1.0))
        res = np.linalg.norm(np.einsum("tij,mj->tmi", R, Y) + t[:, None] - Xs, axis=2)
        if it == robust_iters:
            break
        valid_res = np.where(w > 0, res, np.nan)
        med = np.nanmedian(valid_res, axis=1, keepdims=True)
        scale = np.maximum(4.5 * np.nan_to_num(med), 1e-9)
        # Tukey biweight on residuals well above the frame's median
        u = np.nan_to_num(res / scale, nan=2.0)
        w = perf.valid[:, sel] * np.clip(1 - u**2, 0, None) ** 2
        ok = (w > 0).sum(1) >= 3
    held = ~ok
    if held.all():
        raise ValueError(f"stabilize: no frame of {perf.name!r} has 3 valid rigid markers")
    if held.any():
        # too few rigid markers: take the motion of the nearest frame that had enough
        good = np.flatnonzero(ok)
        nearest = good[np.clip(np.searchsorted(good, np.arange(T)), 0, len(good) - 1)]
        prev = good[np.clip(np.searchsorted(good, np.arange(T)) - 1, 0, len(good) - 1)]
        pick = np.where(np.abs(prev - np.arange(T)) <= np.abs(nearest - np.arange(T)), prev, nearest)
        R[held] = R[pick[held]]
        t[held] = t[pick[held]]
        warnings.warn(f"stabilize: {held.sum()} frames of {perf.name!r} had < 3 valid rigid markers; head motion held from the nearest good frame")
    wr = perf.valid[:, sel]
    rms = np.sqrt(np.nansum(np.where(wr, res, 0) ** 2, 1) / np.maximum(wr.sum(1), 1))
    stab = np.einsum("tji,tmj->tmi", R, X - t[:, None])  # R^T (X - t)
    out = Performance.markers(stab, perf.names, perf.fps, valid=perf.valid, times=perf.times, units=perf.units, name=perf.name, extras=dict(perf.extras))
    return Stabilized(out, R, t, neutral, rms, held, tuple(rigid))


def restore(positions: np.ndarray, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Re-apply head motion: (T, N, 3) -> R_t p + t_t, for re-synthesis on the target."""
    return np.einsum("tij,tnj->tni", rotations, positions) + translations[:, None]
