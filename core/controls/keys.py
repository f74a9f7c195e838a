"""Keyframe reduction: few keys per weight curve that reproduce it within a tolerance, for export.

:func:`reduce_keys` finds per curve the keys (a subset of the frames, with the dense values)
that reproduce the dense curve within ``tolerance`` at every frame: LINEAR by an *optimal*
dynamic program over segments (Imai and Iri's segment graph [1] with the sliding-wedge validity
test: fewest keys among all subsets of frames), CUBICSPLINE (glTF's cubic Hermite, separate
in- and out-tangents per key) greedily, each segment as long as a least-squares tangent fit (or
the chord) stays within tolerance. Both errors are measured at the frames; for LINEAR the
difference of two piecewise-linear curves with breakpoints at frames is largest at a frame, so
the tolerance holds at every time in between too.

The reduced curves are glTF 2.0 animation samplers (:func:`evaluate_sampler`, glTF 2.0
Appendix C); :meth:`Keys.grid` lays them on the one time grid a glTF sampler shares across all
morph targets. The GLB and CSV writers take :class:`Keys` (:mod:`core.io.gltf`,
:mod:`core.io.curves_csv`).

References
----------
.. [1] H. Imai, M. Iri, "Polygonal approximations of a curve -- formulations and algorithms",
       in Computational Morphology, 1988, pp. 71-86.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .inputs import as_fps, as_names, as_weights

__all__ = ["INTERPOLATIONS", "Keys", "reduce_keys", "evaluate_sampler"]


INTERPOLATIONS = ("LINEAR", "CUBICSPLINE")


def _hermite(s):
    """Cubic Hermite basis (h00, h10, h01, h11) at s in [0, 1]."""
    s2, s3 = s * s, s * s * s
    return 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2


def evaluate_sampler(times, values, t, interpolation: str = "LINEAR", in_tangents=None, out_tangents=None):
    """A glTF 2.0 animation sampler evaluated at times ``t`` (glTF 2.0 Appendix C).

    ``LINEAR``: linear between keys; ``CUBICSPLINE``: on ``[t_k, t_{k+1}]`` with ``d = t_{k+1} -
    t_k`` and ``s = (t - t_k) / d``, ``v = h00(s) v_k + d h10(s) b_k + h01(s) v_{k+1} + d h11(s)
    a_{k+1}`` (``b_k`` the out-tangent of key k, ``a_{k+1}`` the in-tangent of key k+1, per
    second); held at the end values outside the keys.

    Parameters
    ----------
    times : (n,) increasing; values, in_tangents, out_tangents : (n, K); t : (m,)

    Returns
    -------
    (m, K) float64
    """
    times = np.asarray(times, dtype=np.float64)
    V = np.asarray(values, dtype=np.float64)
    V = V[:, None] if V.ndim == 1 else V
    t = np.asarray(t, dtype=np.float64)
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got {interpolation!r}")
    if len(times) == 1:
        return np.repeat(V[:1], len(t), axis=0)
    tc = np.clip(t, times[0], times[-1])
    k = np.clip(np.searchsorted(times, tc, side="right") - 1, 0, len(times) - 2)
    d = times[k + 1] - times[k]
    s = ((tc - times[k]) / d)[:, None]
    if interpolation == "LINEAR":
        return V[k] * (1 - s) + V[k + 1] * s
    a = np.asarray(in_tangents, dtype=np.float64).reshape(V.shape)
    b = np.asarray(out_tangents, dtype=np.float64).reshape(V.shape)
    h00, h10, h01, h11 = _hermite(s)
    return h00 * V[k] + d[:, None] * h10 * b[k] + h01 * V[k + 1] + d[:, None] * h11 * a[k + 1]


@dataclass(frozen=True, eq=False)
class Keys:
    """Reduced keys of K curves (:func:`reduce_keys`).

    Attributes
    ----------
    frames : tuple of K (n_k,) int arrays, increasing, first 0 and last T-1
    values : tuple of K (n_k,) float arrays (the dense curve's values at those frames)
    in_tangents, out_tangents : tuple of K (n_k,) float arrays (weight per second), CUBICSPLINE only
    fps : float
    n_frames : int (T of the dense curves)
    interpolation : "LINEAR" or "CUBICSPLINE"
    tolerance : float, the largest allowed |reduced - dense| at a frame
    names : tuple of K str, optional
    """

    frames: tuple
    values: tuple
    in_tangents: Optional[tuple]
    out_tangents: Optional[tuple]
    fps: float
    n_frames: int
    interpolation: str
    tolerance: float
    names: Optional[tuple] = None

    @property
    def counts(self) -> np.ndarray:
        """(K,) keys per curve."""
        return np.array([len(f) for f in self.frames], dtype=np.int64)

    def evaluate(self, t=None) -> np.ndarray:
        """The reduced curves at times ``t`` seconds (default: every frame), (m, K)."""
        t = np.arange(self.n_frames) / self.fps if t is None else np.asarray(t, dtype=np.float64)
        out = np.empty((len(t), len(self.frames)))
        for c, (f, v) in enumerate(zip(self.frames, self.values)):
            if self.interpolation == "LINEAR":
                out[:, c] = evaluate_sampler(f / self.fps, v, t)[:, 0]
            else:
                out[:, c] = evaluate_sampler(f / self.fps, v, t, "CUBICSPLINE", self.in_tangents[c],
                                             self.out_tangents[c])[:, 0]
        return out

    def grid(self):
        """The curves on the union of their key frames: what one glTF sampler stores.

        glTF animates all morph weights of a node through one sampler (one time grid, one
        interpolation); each curve is therefore written at every key frame of every curve. The
        extra keys lie on the curve's own interpolant: a LINEAR curve gets collinear points, a
        CUBICSPLINE curve is split at the new time with value and derivative of its Hermite
        segment (in-tangent = out-tangent), which reproduces the same cubic pieces exactly.

        Returns
        -------
        frames : (n,) int; times : (n,) float seconds; values : (n, K);
        in_tangents, out_tangents : (n, K) (CUBICSPLINE) or None
        """
        F = np.unique(np.concatenate(self.frames))
        t = F / self.fps
        V = self.evaluate(t)
        if self.interpolation == "LINEAR":
            return F, t, V, None, None
        A = np.empty_like(V)
        Bt = np.empty_like(V)
        for c, (f, v) in enumerate(zip(self.frames, self.values)):
            a, b = self.in_tangents[c], self.out_tangents[c]
            tk = f / self.fps
            k = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
            d = tk[k + 1] - tk[k]
            s = (t - tk[k]) / d
            # derivative of the Hermite segment, per second
            dh00, dh10, dh01, dh11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
            der = (dh00 * v[k] + dh01 * v[k + 1]) / d + dh10 * b[k] + dh11 * a[k + 1]
            A[:, c] = der
            Bt[:, c] = der
            own = np.searchsorted(F, f)
            A[own, c] = a
            Bt[own, c] = b
        return F, t, V, A, Bt


def _linear_dp(Y, tol):
    """Optimal LINEAR keys for every column of Y (T, K): fewest keys (subset of frames, dense
    values) with |chord - y| <= tol at every frame. Imai-Iri segment graph: segment (i, j) is
    valid iff its slope lies in the wedge of slopes through (k, y_k +- tol) for i < k < j; the
    shortest path from frame 0 to T-1 in the graph of valid segments (a DP in frame order).
    Work: the sum over starts of the wedge's length, vectorised over the curves."""
    T, K = Y.shape
    cost = np.full((K, T), np.iinfo(np.int64).max // 2, dtype=np.int64)
    parent = np.zeros((K, T), dtype=np.int64)
    cost[:, 0] = 1
    # curves the chord from the first to the last frame already fits (constant curves: shapes the
    # solve never used) need two keys; leaving them out of the DP saves its O(T^2) worst case
    s = np.arange(T) / max(T - 1, 1)
    whole = (np.abs(Y[0] + (Y[-1] - Y[0]) * s[:, None] - Y) <= tol).all(0)
    cost[whole, -1] = 2
    kk = np.flatnonzero(~whole)
    for i in range(T - 1):
        rows = kk
        j0 = i + 1
        lo_run = np.full(K, -np.inf)
        hi_run = np.full(K, np.inf)
        yi = Y[i]
        ci = cost[:, i] + 1
        chunk = 32
        while len(rows) and j0 < T:
            j1 = min(T, j0 + chunk)
            js = np.arange(j0, j1)
            dt = (js - i).astype(np.float64)
            Yr = Y[j0:j1][:, rows].T  # (n_rows, n)
            base = yi[rows][:, None]
            slope = (Yr - base) / dt
            lo_k = (Yr - tol - base) / dt
            hi_k = (Yr + tol - base) / dt
            # wedge over the interior points i < k < j: running max/min of the previous columns
            lo_prev = np.maximum.accumulate(np.concatenate([lo_run[rows][:, None], lo_k], axis=1), axis=1)[:, :-1]
            hi_prev = np.minimum.accumulate(np.concatenate([hi_run[rows][:, None], hi_k], axis=1), axis=1)[:, :-1]
            ok = (slope >= lo_prev) & (slope <= hi_prev)
            better = ok & (ci[rows][:, None] < cost[rows][:, j0:j1])
            if better.any():
                r, c = np.nonzero(better)
                cost[rows[r], j0 + c] = ci[rows[r]]
                parent[rows[r], j0 + c] = i
            lo_run[rows] = np.maximum(lo_prev[:, -1], lo_k[:, -1])
            hi_run[rows] = np.minimum(hi_prev[:, -1], hi_k[:, -1])
            keep = lo_run[rows] <= hi_run[rows]  # the wedge is still open: longer segments may be valid
            rows = rows[keep]
            j0 = j1
            chunk *= 2
    frames = []
    for c in range(K):
        path = [T - 1]
        while path[-1] > 0:
            path.append(int(parent[c, path[-1]]))
        frames.append(np.asarray(path[::-1], dtype=np.int64))
    return frames


def _linear_dp_shared(Y, tol):
    """Optimal LINEAR keys shared by all columns of Y: a segment is valid when it is valid for
    every curve (the same DP as :func:`_linear_dp` on the intersection of the segment graphs)."""
    T, K = Y.shape
    live = np.flatnonzero(np.ptp(Y, axis=0) > 0)  # constant curves fit every chord exactly
    Y = Y[:, live]
    cost = np.full(T, np.iinfo(np.int64).max // 2, dtype=np.int64)
    parent = np.zeros(T, dtype=np.int64)
    cost[0] = 1
    for i in range(T - 1):
        j0 = i + 1
        lo_run = np.full(len(live), -np.inf)
        hi_run = np.full(len(live), np.inf)
        yi = Y[i][:, None]
        chunk = 32
        while j0 < T:
            j1 = min(T, j0 + chunk)
            dt = np.arange(j0 - i, j1 - i, dtype=np.float64)
            Yr = Y[j0:j1].T
            slope = (Yr - yi) / dt
            lo_k = (Yr - tol - yi) / dt
            hi_k = (Yr + tol - yi) / dt
            lo_prev = np.maximum.accumulate(np.concatenate([lo_run[:, None], lo_k], axis=1), axis=1)[:, :-1]
            hi_prev = np.minimum.accumulate(np.concatenate([hi_run[:, None], hi_k], axis=1), axis=1)[:, :-1]
            ok = ((slope >= lo_prev) & (slope <= hi_prev)).all(0)
            better = ok & (cost[i] + 1 < cost[j0:j1])
            cost[j0:j1][better] = cost[i] + 1
            parent[j0:j1][better] = i
            lo_run = np.maximum(lo_prev[:, -1], lo_k[:, -1])
            hi_run = np.minimum(hi_prev[:, -1], hi_k[:, -1])
            if (lo_run > hi_run).any():
                break  # some curve's wedge closed: no longer segment from i is valid
            j0 = j1
            chunk *= 2
    path = [T - 1]
    while path[-1] > 0:
        path.append(int(parent[path[-1]]))
    return np.asarray(path[::-1], dtype=np.int64)


def _cubic_fit(y, i, j, tol):
    """Best cubic Hermite segment from frame i to j with end values y_i, y_j for curves y (K', T)
    rows: least-squares unit-interval tangents (m0, m1) over the interior frames (biased to
    the chord's by a tiny ridge), accepted when within tol, else the chord if that is.
    Returns ok (K',), m0, m1 (K',)."""
    n = j - i  # (K',) segment lengths
    L = int(n.max()) - 1
    Kc = len(y)
    lin = y[np.arange(Kc), j] - y[np.arange(Kc), i]
    if L <= 0:
        return np.ones(Kc, bool), lin, lin
    off = np.arange(1, L + 1)[None]
    mask = off < n[:, None]
    k = np.minimum(i[:, None] + off, y.shape[1] - 1)
    s = off / n[:, None]
    h00, h10, h01, h11 = _hermite(s)
    yi, yj = y[np.arange(Kc), i][:, None], y[np.arange(Kc), j][:, None]
    yk = y[np.arange(Kc)[:, None], k]
    base = h00 * yi + h01 * yj
    chord = yi + (yj - yi) * s
    r = np.where(mask, yk - base - (h10 + h11) * lin[:, None], 0.0)  # residual after the chord's tangents
    a11 = np.where(mask, h10 * h10, 0).sum(1)
    a12 = np.where(mask, h10 * h11, 0).sum(1)
    a22 = np.where(mask, h11 * h11, 0).sum(1)
    b1 = (np.where(mask, h10, 0) * r).sum(1)
    b2 = (np.where(mask, h11, 0) * r).sum(1)
    eps = 1e-9 * (a11 + a22) + 1e-300
    a11, a22 = a11 + eps, a22 + eps
    det = a11 * a22 - a12 * a12
    d0 = (a22 * b1 - a12 * b2) / det
    d1 = (a11 * b2 - a12 * b1) / det
    m0, m1 = lin + d0, lin + d1
    fit = base + h10 * m0[:, None] + h11 * m1[:, None]
    err_c = np.where(mask, np.abs(fit - yk), 0).max(1)
    err_l = np.where(mask, np.abs(chord - yk), 0).max(1)
    ok_c = err_c <= tol
    ok_l = err_l <= tol
    m0 = np.where(ok_c, m0, lin)
    m1 = np.where(ok_c, m1, lin)
    return ok_c | ok_l, m0, m1


def _cubic_greedy(Y, tol):
    """CUBICSPLINE keys per column of Y (T, K): from each key, the farthest next key whose
    segment fits (galloping 1, 2, 4, ... frames, then bisection), all curves in lock-step.
    Not optimal (validity is not monotone in the length); every accepted segment is checked."""
    T, K = Y.shape
    y = Y.T.copy()
    keys = [[0] for _ in range(K)]
    tin = [[0.0] for _ in range(K)]  # unit-interval tangents, converted at the end
    tout = [[] for _ in range(K)]
    i = np.zeros(K, np.int64)
    good = np.minimum(i + 1, T - 1)
    gm0 = y[np.arange(K), good] - y[np.arange(K), i]
    gm1 = gm0.copy()
    bad = np.full(K, -1)
    step = np.full(K, 2)
    live = np.flatnonzero(i < T - 1)
    while len(live):
        # candidate per live curve: gallop (bad < 0) or bisect
        gallop = bad[live] < 0
        cand = np.where(gallop, np.minimum(i[live] + step[live], T - 1), (good[live] + bad[live]) // 2)
        test = cand > good[live]
        if test.any():
            rows = live[test]
            ok, m0, m1 = _cubic_fit(y[rows], i[rows], cand[test], tol)
            rr, cc = rows[ok], cand[test][ok]
            good[rr], gm0[rr], gm1[rr] = cc, m0[ok], m1[ok]
            fail = rows[~ok]
            bad[fail] = cand[test][~ok]
            step[rr] *= 2
        # a curve is done searching when its gallop reached the end or bisection closed
        done = (good[live] == T - 1) | ((bad[live] >= 0) & (bad[live] - good[live] <= 1))
        for c in live[done]:
            j = int(good[c])
            d = (j - int(i[c])) / 1.0
            tout[c].append(gm0[c] / d)
            tin[c].append(gm1[c] / d)
            keys[c].append(j)
            i[c] = j
            if j < T - 1:
                good[c] = j + 1
                gm0[c] = gm1[c] = y[c, j + 1] - y[c, j]
                bad[c] = -1
                step[c] = 2
        live = np.flatnonzero(i < T - 1)
    frames, ins, outs = [], [], []
    for c in range(K):
        frames.append(np.asarray(keys[c], np.int64))
        ins.append(np.asarray(tin[c], np.float64))  # per frame; the first key's in-tangent is unused
        outs.append(np.asarray(tout[c] + [0.0], np.float64))  # the last key's out-tangent is unused
    return frames, ins, outs


def _cubic_greedy_shared(Y, tol):
    """CUBICSPLINE keys shared by all columns: :func:`_cubic_greedy`'s search, a segment
    accepted when every curve fits it (tangents per curve)."""
    T, K = Y.shape
    y = Y.T.copy()
    ar = np.arange(K)
    keys, tin, tout = [0], [np.zeros(K)], []
    i = 0
    while i < T - 1:
        good = i + 1
        gm0 = gm1 = y[:, good] - y[:, i]
        bad, step = -1, 2
        while True:
            cand = min(i + step, T - 1) if bad < 0 else (good + bad) // 2
            if cand > good:
                ok, m0, m1 = _cubic_fit(y, np.full(K, i), np.full(K, cand), tol)
                if ok.all():
                    good, gm0, gm1 = cand, m0, m1
                    step *= 2
                else:
                    bad = cand
            if good == T - 1 or (bad >= 0 and bad - good <= 1):
                break
        d = float(good - i)
        tout.append(gm0 / d)
        tin.append(gm1 / d)
        keys.append(good)
        i = good
    tout.append(np.zeros(K))
    fr = np.asarray(keys, np.int64)
    A, B = np.asarray(tin), np.asarray(tout)
    return [fr] * K, [A[:, c] for c in ar], [B[:, c] for c in ar]


def reduce_keys(W, fps, tolerance: float = 0.005, interpolation: str = "LINEAR", names=None,
                shared: bool = False) -> Keys:
    """Per curve, few keys that reproduce the dense curve within ``tolerance`` at every frame.

    Keys sit on frames and take the dense values there (an animator's keys lie on the curve);
    the first and last frames are always keys.

    * ``"LINEAR"``: the fewest such keys, exactly (module docstring: Imai-Iri's segment graph
      with the wedge test, a dynamic program in frame order). Linear interpolation between
      frames of both curves means the bound holds at every time, not only at frames.
    * ``"CUBICSPLINE"``: glTF's cubic Hermite with separate in- and out-tangents per key (so
      each segment has two free tangents); segments are grown greedily from each key as long as
      the least-squares tangents (or the chord) keep every frame within tolerance. Not
      provably fewest; never worse per segment than the chord.

    Parameters
    ----------
    W : (T, K) float, finite
    fps : float > 0
    tolerance : float > 0 (weight units; default 0.005)
    interpolation : {"LINEAR", "CUBICSPLINE"}
    names : sequence of K str, optional (kept on the result for the writers)
    shared : bool
        One key set for all curves (a segment must fit every curve): the fewest keys of a glTF
        sampler, which shares its times across all morph targets (LINEAR: optimal, the same DP
        on the intersection of the curves' segment graphs). Default: keys per curve.

    Returns
    -------
    Keys (``counts`` per curve; ``evaluate()`` the reduced curves at every frame; ``grid()`` the
    one-sampler layout for glTF).

    Raises
    ------
    ValueError
        Non-finite weights, tolerance <= 0, unknown interpolation, names of the wrong length.
    """
    W = as_weights(W)
    f = as_fps(fps)
    tol = float(tolerance)
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tolerance: expected a positive weight difference, got {tolerance}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got {interpolation!r}")
    if not np.isfinite(W).all():
        raise ValueError("W: contains NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
    T, K = W.shape
    if T == 0:
        raise ValueError("W: needs at least one frame")
    if names is not None:
        names = as_names(names)
        if len(names) != K:
            raise ValueError(f"names: expected {K} names, got {len(names)}")
    # the acceptance tests compare with <=; shave a hair off so float rounding in the test and in
    # evaluation (a few ulps of the values) cannot push a frame past the tolerance
    t_eff = tol * (1.0 - 1e-9) - 8 * np.finfo(float).eps * max(1.0, float(np.abs(W).max(initial=0.0)))
    if T == 1:
        fr = [np.zeros(1, np.int64) for _ in range(K)]
        vals = tuple(W[0, c:c + 1].copy() for c in range(K))
        tan = tuple(np.zeros(1) for _ in range(K)) if interpolation == "CUBICSPLINE" else None
        return Keys(tuple(fr), vals, tan, tan, f, T, interpolation, tol, names)
    if interpolation == "LINEAR":
        frames = [_linear_dp_shared(W, t_eff)] * K if shared else _linear_dp(W, t_eff)
        return Keys(tuple(frames), tuple(W[fr_, c].copy() for c, fr_ in enumerate(frames)), None, None, f, T,
                    interpolation, tol, names)
    frames, ins, outs = (_cubic_greedy_shared if shared else _cubic_greedy)(W, t_eff)
    # unit-interval tangents -> per second: the segment's tangent m over d frames is m / (d / fps)
    tin, tout = [], []
    for fr_, a, b in zip(frames, ins, outs):
        tin.append(a * f)
        tout.append(b * f)
    return Keys(tuple(frames), tuple(W[fr_, c].copy() for c, fr_ in enumerate(frames)), tuple(tin), tuple(tout), f, T,
                interpolation, tol, names)
