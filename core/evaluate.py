"""The evaluate stage: every diagnostic of one solution, as plain arrays for views and reports.

Composes :mod:`core.metrics` (marker error, Seol 2012 Fig. 11 velocity error, weight range)
with a jitter measure, so the dashboard and the CLI read the same numbers.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .metrics import _MM, marker_and_velocity_error, squared_errors, weight_range

#: a shape "is used" in a frame above this weight
ACTIVE = 0.05


def jitter(W, step: int = 1) -> np.ndarray:
    """Mean absolute second difference of the weights per frame (T,), a jitter measure:
    ``mean_k |w_{t+s} - 2 w_t + w_{t-s}|`` (0 at the ends)."""
    W = np.nan_to_num(np.asarray(W, dtype=np.float64))
    out = np.zeros(len(W))
    if len(W) > 2 * step:
        out[step:-step] = np.abs(W[2 * step:] - 2 * W[step:-step] + W[:-2 * step]).mean(1)
    return out


def evaluate(B, W, S, valid=None, step: int = 1, predicted=None, frame_valid=None, products=None) -> dict:
    """Diagnostics of weights ``W`` (T, K) for target marker deltas ``B`` (K, M, 3) against
    source marker deltas ``S`` (T, M, 3). ``predicted`` (T, M, 3) replaces ``B w_t`` as the
    prediction for methods that do not synthesise with one weight vector (Liu 2011 eq. 3).
    ``products``: :func:`core.metrics.error_products` of ``B`` and ``S`` (the pipeline's
    ``error_products`` stage, None when a sample is missing): the errors are then summed in
    weight space (:func:`core.metrics.squared_errors`) instead of from the (T, 3M) residual
    (the same numbers to rounding; with 1,000 dense points ~10x faster).

    Frames without data are excluded from every statistic, never scored as a neutral face: a
    frame is used where ``frame_valid`` (T,) is True (default: every frame), its weights are
    finite and it has at least one valid marker sample. Per-frame arrays are NaN there.

    Returns a dict: ``marker_error_mm`` (T,) RMS per frame, ``marker_error_per_marker_mm`` (M,),
    ``marker_rms_mm`` (RMS over every sample), ``velocity_error_mm2`` (T,) (Seol 2012 eq. 2 per
    frame, a sum of squares over the markers, mm²) and its sum ``velocity_error_total_mm2``,
    ``velocity_error_mm_per_frame`` (T,) = sqrt(``velocity_error_mm2`` / M) (an RMS per marker: mm
    per frame) and its mean over the used frames ``velocity_error_mean_mm_per_frame`` (None without any),
    ``weight_min``/``weight_max`` (K,), ``weight_low``/``weight_high``, ``outside_01``, ``jitter`` (T,),
    ``frame_valid`` (T,) and ``n_valid_frames``. (No (T, M) distances: nothing read them, and they
    need the residual; :func:`core.metrics.marker_error_mm` has them.)
    """
    W = np.asarray(W, dtype=np.float64)
    S = np.asarray(S, dtype=np.float64)
    T, M = S.shape[:2]
    mask = np.isfinite(S).all(-1) if valid is None else np.asarray(valid, dtype=bool).copy()
    fv = np.isfinite(W).all(1) & mask.any(1)
    if frame_valid is not None:
        fv &= np.asarray(frame_valid, dtype=bool)
    mask &= fv[:, None]
    Wz = np.where(fv[:, None], W, 0.0)  # excluded frames carry no sample: their value is never read
    if products is not None and predicted is None:
        if products.S.shape != (T, 3 * M) or products.G.shape[0] != W.shape[1]:
            raise ValueError(f"products: made for S {products.S.shape} and {products.G.shape[0]} shapes, given "
                             f"S ({T}, {3 * M}) and W {W.shape}")
        frame, marker, per = squared_errors(products, Wz, fv)
        n = M * int(fv.sum())
        per_frame = np.sqrt(frame / M) * _MM
        per_marker = np.sqrt(marker / fv.sum()) * _MM if n else np.full(M, np.nan)
        rms = float(np.sqrt(np.nansum(frame) / n) * _MM) if n else float("nan")
        per = per * _MM**2
        total = float(per.sum())
    else:
        me, ve = marker_and_velocity_error(B, Wz, S, mask, predicted)
        per_frame, per_marker, rms, per, total = me.per_frame, me.per_marker, me.rms, ve.per_frame, ve.total
    wr = weight_range(W[fv]) if fv.any() else weight_range(np.zeros((1, W.shape[1])))
    jit = jitter(Wz, step)
    jit[~fv] = np.nan
    if len(fv) > 2 * step:  # a difference across an excluded frame is no jitter of the result
        near = np.zeros(T, dtype=bool)
        near[step:-step] = ~fv[2 * step:] | ~fv[:-2 * step]
        jit[near] = np.nan
    vpf = np.where(fv, per, np.nan)
    vrms = np.sqrt(vpf / M)
    return {
        "marker_error_mm": per_frame, "marker_error_per_marker_mm": per_marker, "marker_rms_mm": rms,
        "velocity_error_mm2": vpf, "velocity_error_total_mm2": total, "velocity_error_mm_per_frame": vrms,
        "velocity_error_mean_mm_per_frame": _stats(vrms)[0],
        "weight_min": wr.min, "weight_max": wr.max, "weight_low": wr.low, "weight_high": wr.high, "outside_01": wr.outside,
        "jitter": jit, "frame_valid": fv, "n_valid_frames": int(fv.sum()),
    }


def marker_error_field(rig, layout, per_marker_error, k: int = 3) -> np.ndarray:
    """Per-vertex error (V,) for a heat map: inverse-distance blend of the ``k`` nearest
    markers' errors (M,) on the neutral mesh. NaN marker errors are ignored (a vertex whose
    nearest markers all lack data is NaN, shown as missing, not as zero)."""

    e = np.asarray(per_marker_error, dtype=np.float64)
    pts = layout.points(rig.neutral)
    ok = np.isfinite(e)
    if not ok.any():
        return np.full(rig.n_vertices, np.nan)
    k = min(k, int(ok.sum()))
    d, i = cKDTree(pts[ok]).query(rig.neutral, k=k)
    d, i = d.reshape(len(rig.neutral), k), i.reshape(len(rig.neutral), k)
    w = 1.0 / np.maximum(d, 1e-6 * rig.size) ** 2
    return (w * e[ok][i]).sum(1) / w.sum(1)


def _stats(x) -> tuple:
    """mean / p95 / max of the finite values of ``x`` as plain floats (None when there are none)."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if not x.size:
        return None, None, None
    return float(x.mean()), float(np.percentile(x, 95)), float(x.max())


def summarize(ev, W, valid=None, names=None, active=None) -> dict:
    """One solution's diagnostics as plain numbers (JSON, a row of a batch's summary table).

    The keys :func:`core.report.method_metrics` also reports mean the same there (``face-retarget
    evaluate``); this adds the maxima and needs no mesh, so it costs nothing beside the solve.

    Parameters
    ----------
    ev : dict from :func:`evaluate` (the pipeline's ``evaluate`` stage), or None (dense transfer:
        no markers to score, only the weight statistics)
    W : (T, K) the written weights
    valid : (T,) bool frames with data (default: every frame); the others are left out of every
        statistic, as in :func:`evaluate`
    names : (K,) shape names, for the per-shape weight ranges
    active : a shape is used in a frame where ``|w| > active`` (default :data:`ACTIVE`)

    Returns
    -------
    dict of floats/ints (None where a statistic has no frame to use): ``frames``, ``frames_without_data``,
    ``marker_mean_mm`` / ``marker_p95_mm`` / ``marker_max_mm`` (over frames of the per-frame RMS over
    the markers, mm), ``velocity_error_mm_per_frame`` / ``velocity_error_p95_mm_per_frame`` /
    ``velocity_error_max_mm_per_frame`` (over frames of the per-frame RMS per marker of Seol 2012
    eq. 2, mm per frame), ``velocity_error_total_mm2`` (the eq. 2 sum, mm²), ``jitter``, ``weight_min``,
    ``weight_max``, ``outside_01`` (fraction of weights outside [0, 1]), ``active_per_frame`` /
    ``active_per_frame_max`` (shapes with ``|w| > active``), ``active_threshold`` and
    ``weight_range_per_shape`` ({name: [min, max]}).
    """
    active = ACTIVE if active is None else float(active)
    W = np.asarray(W, dtype=np.float64)
    T, K = W.shape
    fv = np.ones(T, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if ev is not None:
        fv = fv & np.asarray(ev["frame_valid"], dtype=bool)
    fv &= np.isfinite(W).all(1)
    Wv = W[fv]
    out = {"frames": int(T), "frames_without_data": int(T - fv.sum())}
    if ev is not None:
        out["marker_mean_mm"], out["marker_p95_mm"], out["marker_max_mm"] = _stats(ev["marker_error_mm"])
        (out["velocity_error_mm_per_frame"], out["velocity_error_p95_mm_per_frame"],
         out["velocity_error_max_mm_per_frame"]) = _stats(ev["velocity_error_mm_per_frame"])
        total = float(ev["velocity_error_total_mm2"])
        out["velocity_error_total_mm2"] = total if np.isfinite(total) else None
        jit = np.asarray(ev["jitter"], dtype=np.float64)
        out["jitter"] = float(np.nanmean(jit)) if np.isfinite(jit).any() else None
    n_active = (np.abs(Wv) > active).sum(1) if len(Wv) else np.zeros(0)
    out.update({
        "weight_min": float(Wv.min()) if Wv.size else None,
        "weight_max": float(Wv.max()) if Wv.size else None,
        "outside_01": float(((Wv < 0) | (Wv > 1)).mean()) if Wv.size else None,
        "active_per_frame": float(n_active.mean()) if len(n_active) else None,
        "active_per_frame_max": int(n_active.max()) if len(n_active) else None,
        "active_threshold": active,
    })
    names = list(names) if names is not None else [str(k) for k in range(K)]
    out["weight_range_per_shape"] = ({n: [float(a), float(b)] for n, a, b in zip(names, Wv.min(0), Wv.max(0))}
                                     if len(Wv) else {n: [None, None] for n in names})
    return out


def worst_frame(ev) -> int:
    """The frame whose marker error RMS (``ev["marker_error_mm"]`` of :func:`evaluate`) is largest:
    the frame of :func:`summarize`'s ``marker_max_mm``, the page's "max N mm at frame F" and the
    contact sheet's worst frame (frames without data are never it); 0 when no frame has data."""
    per = np.asarray(ev["marker_error_mm"], dtype=np.float64)
    ok = np.isfinite(per)
    return int(np.argmax(np.where(ok, per, -np.inf))) if ok.any() else 0
