"""Retargeting diagnostics: velocity error (Seol et al. 2012, Fig. 11), marker error, weight range,
and the vertex error of a result against a known truth on the same rig.

Inputs follow the solvers: ``B`` (K, M, 3) target marker deltas or the paper's (3M, K) matrix,
``W`` (T, K) weights, ``S`` (T, M, 3) source marker deltas, all lengths in metres; a (T, M)
validity mask drops missing samples (default: where ``S`` is finite). Errors are reported in
millimetres (squared millimetres for the velocity error).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from core.solvers.inputs import as_basis, as_sequence, as_valid, zero_filled

__all__ = ["velocity_error", "marker_error_mm", "marker_and_velocity_error", "vertex_errors", "weight_range", "VelocityError",
           "MarkerError", "WeightRange", "ErrorProducts", "error_products", "squared_errors"]

_MM = 1e3


class VelocityError(NamedTuple):
    """``||D(BW)^T - DS^T||_F^2`` in mm^2: ``total`` and ``per_frame`` (T,), ``per_frame[0] = 0``."""

    total: float
    per_frame: np.ndarray


class MarkerError(NamedTuple):
    """Marker position error in mm.

    distances : (T, M) Euclidean distance ``||B_m w_t - s_tm||`` (NaN where missing)
    per_frame : (T,) RMS over the frame's valid markers (NaN when it has none)
    per_marker : (M,) RMS over the marker's valid frames (NaN when it has none)
    rms : float, RMS over all valid samples
    max : float, largest valid distance
    """

    distances: np.ndarray
    per_frame: np.ndarray
    per_marker: np.ndarray
    rms: float
    max: float


class WeightRange(NamedTuple):
    """Per-shape ``min`` and ``max`` (K,), overall ``low``/``high``, and ``outside``: the
    fraction of weights outside [0, 1] (the range artists build shapes for, Seol 2012 §5)."""

    min: np.ndarray
    max: np.ndarray
    low: float
    high: float
    outside: float


def _inputs(B, W, S, valid):
    Bm = as_basis(B)
    K = Bm.shape[1]
    M = Bm.shape[0] // 3
    S3 = as_sequence(S, M)
    W = np.asarray(W, dtype=np.float64)
    if W.shape != (len(S3), K):
        raise ValueError(f"W: expected ({len(S3)}, {K}) weights for {len(S3)} frames and {K} shapes, got {W.shape}")
    valid = as_valid(valid, S3)
    return Bm, W, zero_filled(S3, valid), valid


def _residual(B, W, S, valid, predicted):
    """(T, 3M) residual of the prediction (``B w_t``, or ``predicted`` (T, M, 3) when a method
    does not synthesise by one global weight vector, e.g. Liu 2011's mask blending)."""
    Bm, W, Sz, valid = _inputs(B, W, S, valid)
    if predicted is not None:
        return np.asarray(predicted, dtype=np.float64).reshape(Sz.shape) - Sz, valid
    P = W @ Bm.T
    P -= Sz  # in place: the product is ours (one (T, 3M) array less for a dense take)
    return P, valid


def velocity_error(B, W, S, valid=None, predicted=None) -> VelocityError:
    """Velocity (movement) error of Seol et al. 2012, eq. 2 and Fig. 11, in mm^2.

    ``e_t = sum_m ||B_m (w_t - w_{t-1}) - (s_tm - s_{t-1,m})||^2`` over the markers valid at
    both ``t-1`` and ``t``; ``total = sum_t e_t = ||D(BW)^T - DS^T||_F^2``.

    Parameters
    ----------
    B : (K, M, 3) or (3M, K) float
    W : (T, K) float
    S : (T, M, 3) float
    valid : (T, M) bool, optional
    predicted : (T, M, 3) float, optional
        Predicted marker deltas when they are not ``B w_t`` (local methods).

    Returns
    -------
    VelocityError(total, per_frame (T,))
    """
    return _velocity_error(*_residual(B, W, S, valid, predicted))


def _velocity_error(X, valid) -> VelocityError:
    per = np.zeros(len(X))
    if len(X) > 1:
        dX = X[1:] - X[:-1]
        both = valid[:-1] & valid[1:]
        if not both.all():  # (times a mask of ones is the identity: skipped)
            dX *= np.repeat(both, 3, axis=1)
        np.multiply(dX, dX, out=dX)
        per[1:] = dX.sum(1) * _MM**2
    return VelocityError(float(per.sum()), per)


def marker_error_mm(B, W, S, valid=None, predicted=None) -> MarkerError:
    """Marker position error ``||B_m w_t - s_tm||`` in mm, with RMS per frame and per marker.

    Parameters
    ----------
    B : (K, M, 3) or (3M, K) float
    W : (T, K) float
    S : (T, M, 3) float
    valid : (T, M) bool, optional
    predicted : (T, M, 3) float, optional
        Predicted marker deltas when they are not ``B w_t`` (local methods).

    Returns
    -------
    MarkerError(distances (T, M), per_frame (T,), per_marker (M,), rms, max)
    """
    return _marker_error(*_residual(B, W, S, valid, predicted))


def _marker_error(X, valid) -> MarkerError:
    T, M = valid.shape
    # the norm over x, y, z as np.linalg.norm sums it, (x² + y²) + z² (the same numbers), without
    # its reduction over an axis of length 3 (a third of a dense take's evaluation)
    s = (X * X).reshape(T, M, 3)
    d = s[:, :, 0] + s[:, :, 1]
    d += s[:, :, 2]
    del s
    np.sqrt(d, out=d)
    d *= _MM
    if valid.all():
        d2 = d * d
    else:
        d = np.where(valid, d, np.nan)
        d2 = np.where(valid, d, 0.0) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame = np.sqrt(d2.sum(1) / valid.sum(1))
        per_marker = np.sqrt(d2.sum(0) / valid.sum(0))
    n = int(valid.sum())
    rms = float(np.sqrt(d2.sum() / n)) if n else float("nan")
    mx = float(np.nanmax(d)) if n else float("nan")
    return MarkerError(d, per_frame, per_marker, rms, mx)


def marker_and_velocity_error(B, W, S, valid=None, predicted=None) -> tuple:
    """``(marker_error_mm(...), velocity_error(...))`` of the same arguments from one residual
    ``B w_t - s_t`` (the same numbers; the residual of a long take with dense correspondence,
    (T, 3M) for M = 1,000 points, is most of either's time)."""
    X, valid = _residual(B, W, S, valid, predicted)
    return _marker_error(X, valid), _velocity_error(X, valid)


class ErrorProducts(NamedTuple):
    """What the marker and velocity errors of any weights need of one take and rig, when every
    sample is present (:func:`error_products`; units: metres).

    B : (3M, K) the target marker deltas; S : (T, 3M) the source marker deltas (read, not copied);
    G : (K, K) ``B^T B``; SB : (T, K) ``S B``; s2 : (T,) ``||s_t||^2``; ds2 : (T,)
    ``||s_t - s_(t-1)||^2`` (0 at t = 0); p2 : (3M,) ``sum_t S_tr^2`` over the rows of ``B``;
    low_rank : ``(A (T, r), V (r, 3M))`` with ``S = A V`` to rounding when the take has a low
    numerical rank (:func:`_low_rank`), else None.
    """

    B: np.ndarray
    S: np.ndarray
    G: np.ndarray
    SB: np.ndarray
    s2: np.ndarray
    ds2: np.ndarray
    p2: np.ndarray
    low_rank: tuple = None


#: columns of the random sketches that look for a low-rank take, tried in turn (:func:`_low_rank`)
_SKETCHES = (64, 192)
#: singular values below this fraction of the largest are rounding (dropped from the factors)
_LOW_RANK_DROP = 1e-14
#: the factors are kept when ``||S - A V||_F <= _LOW_RANK_TOL ||S||_F`` (checked on every entry)
_LOW_RANK_TOL = 1e-13
#: takes of fewer entries are not factorised (their ``W^T S`` is well below a millisecond)
_LOW_RANK_MIN_SIZE = 100_000


def _low_rank(S: np.ndarray):
    """``(A (T, r), V (r, n))`` with ``S = A V`` to rounding (``||S - A V||_F <= 1e-13
    ||S||_F``, checked), or None when the take is small (:data:`_LOW_RANK_MIN_SIZE` entries), its
    numerical rank is not below the largest sketch (:data:`_SKETCHES`) or the factors would not
    make ``W^T S`` cheaper (``r (T + 3M) >= T 3M / 2``). A take of the face points of dense
    correspondence is a source rig's shapes driven by the take's curves: its rank is at most the
    source's shape count (51 on the sample's 3,000 coordinates), and ``(W^T A) V`` costs
    ``K r (T + 3M)`` flops instead of ``K T 3M`` (14 -> ~2 ms a change on the sample).

    A randomised range finder (Halko, Martinsson & Tropp 2011, alg. 4.1 and 5.1; seeded, so the
    same take gives the same factors): ``Q = orth(S Omega)``, the SVD of ``Q^T S`` (through the QR
    of its transpose) truncated below ``1e-14 sigma_1``, a larger sketch when the first one is
    full, and the residual checked (~50 ms once per take and rig on the sample, single-threaded;
    ~0.17 s when no sketch finds a low rank)."""
    T, n = S.shape
    if T * n < _LOW_RANK_MIN_SIZE:
        return None
    for k in _SKETCHES:
        k = min(k, T, n)
        Q, _ = np.linalg.qr(S @ np.random.default_rng(0).standard_normal((n, k)))
        Q2, R2 = np.linalg.qr((Q.T @ S).T)  # Q^T S = R2^T Q2^T: its SVD from the k x k R2^T
        U, sv, Vt = np.linalg.svd(R2.T)
        if not sv.size or sv[0] == 0:
            return None
        r = int(np.count_nonzero(sv > _LOW_RANK_DROP * sv[0]))
        if r < k or k == min(T, n):
            break
    if r * (T + n) >= T * n // 2:  # the rank is higher than the sketches, or no gain
        return None
    A, V = Q @ (U[:, :r] * sv[:r]), np.ascontiguousarray((Q2 @ Vt[:r].T).T)
    if np.linalg.norm(S - A @ V) > _LOW_RANK_TOL * np.linalg.norm(S):
        return None
    return A, V


def error_products(B, S, valid=None):
    """:class:`ErrorProducts` of target marker deltas ``B`` (K, M, 3) or (3M, K) and source deltas
    ``S`` (T, M, 3), or None when a sample is missing (``valid`` (T, M), default where ``S`` is
    finite, not all True: the masked errors need every frame's own Gram matrix, and
    :func:`squared_errors` does not apply). They depend on the take and the rig only: the
    pipeline makes them once (the ``error_products`` stage) and every setting change scores its
    weights with :func:`squared_errors` in weight space instead of forming the (T, 3M) residual
    (with 1,000 dense points, 3M = 3,000: ~45-70 ms of every change before)."""
    Bm = as_basis(B)
    S3 = as_sequence(S, Bm.shape[0] // 3)
    if not as_valid(valid, S3).all():
        return None
    Sz = S3.reshape(len(S3), -1)
    dS = np.diff(Sz, axis=0)
    ds2 = np.zeros(len(Sz))
    ds2[1:] = np.einsum("ij,ij->i", dS, dS)
    return ErrorProducts(Bm, Sz, Bm.T @ Bm, Sz @ Bm, np.einsum("ij,ij->i", Sz, Sz), ds2, np.einsum("ij,ij->j", Sz, Sz),
                         _low_rank(Sz))


def squared_errors(P: ErrorProducts, W, used=None) -> tuple:
    """The summed squared marker and velocity errors of weights ``W`` (T, K) from the take's
    :class:`ErrorProducts` (metres², no (T, 3M) residual), over the frames ``used`` (T,) bool
    (default every frame; the weights of the others are never read):

    * ``frame`` (T,): ``||B w_t - s_t||^2 = w_t^T G w_t - 2 w_t^T (S B)_t + ||s_t||^2`` (NaN
      where not used);
    * ``marker`` (M,): ``sum_t ||B_m w_t - s_tm||^2`` over the used frames, per row
      ``b_r^T (W^T W) b_r - 2 b_r^T (W^T S)_r + sum_t S_tr^2``, summed over x, y, z;
    * ``velocity`` (T,): Seol 2012 eq. 2 per frame, ``||B dw_t - ds_t||^2`` with
      ``dw_t = w_t - w_(t-1)`` (0 at t = 0 and where frame t or t - 1 is not used).

    The same numbers as the residual's (:func:`marker_and_velocity_error`) to rounding: the
    expansion cancels ``||s_t||^2`` against the fitted part, so a term loses
    ``eps (||s|| / ||r||)^2`` relative (on the sample, errors ~1 mm against motions ~10 mm:
    ~1e-13; a difference rounded below zero is 0). The one product with the take that
    remains, ``W^T S`` (T x K x 3M flops, the residual's own), is what the per-marker error
    needs (the page's heat map): through the take's factors ``S = A V`` when it has them
    (``low_rank``, exact to rounding: ``||S - A V||_F <= 1e-13 ||S||_F``)."""
    W = np.asarray(W, dtype=np.float64)
    T = len(W)
    used = np.ones(T, dtype=bool) if used is None else np.asarray(used, dtype=bool)
    Wz = np.where(used[:, None], W, 0.0) if not used.all() else W
    WG = Wz @ P.G
    frame = np.einsum("ij,ij->i", WG, Wz) - 2 * np.einsum("ij,ij->i", Wz, P.SB) + P.s2
    np.maximum(frame, 0.0, out=frame)
    frame[~used] = np.nan
    s2 = P.p2 if used.all() else P.p2 - np.einsum("ij,ij->j", P.S[~used], P.S[~used])
    WS = Wz.T @ P.S if P.low_rank is None else (Wz.T @ P.low_rank[0]) @ P.low_rank[1]  # (K, 3M)
    rows = np.einsum("ij,ij->i", P.B @ (Wz.T @ Wz), P.B) - 2 * np.einsum("ij,ji->i", P.B, WS) + s2
    marker = np.maximum(rows.reshape(-1, 3).sum(1), 0.0)
    velocity = np.zeros(T)
    if T > 1:
        dW, dC = np.diff(Wz, axis=0), np.diff(P.SB, axis=0)
        v = np.einsum("ij,ij->i", np.diff(WG, axis=0), dW) - 2 * np.einsum("ij,ij->i", dW, dC) + P.ds2[1:]  # dW G = diff(W G)
        velocity[1:] = np.where(used[1:] & used[:-1], np.maximum(v, 0.0), 0.0)
    return frame, marker, velocity


def weight_range(W) -> WeightRange:
    """Per-shape and overall range of weights (T, K), and the fraction outside [0, 1]."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2 or W.size == 0:
        raise ValueError(f"W: expected non-empty (T, K) weights, got {W.shape}")
    if not np.isfinite(W).all():
        raise ValueError("W: contains NaN/inf")
    return WeightRange(W.min(0), W.max(0), float(W.min()), float(W.max()), float(((W < 0) | (W > 1)).mean()))


def vertex_errors(deltas, W, Wt, face, valid, chunk: int = 128) -> tuple:
    """The mesh of weights ``W`` against the mesh of the true weights ``Wt`` on the same rig, over
    the vertices ``face``: with ``e_tv = || sum_k (W_tk - Wt_tk) deltas_kv ||`` (mm),

    * ``mean`` (T,): ``mean_v e_tv`` per frame (NaN where ``valid`` is False),
    * ``p95``: the 95th percentile of every ``e_tv`` of the valid frames (NaN without any),
    * ``velocity`` (T,): ``mean_v || E_tv - E_(t-1)v ||`` (mm per frame), the mean distance between
      the two meshes' motions from the previous frame (NaN unless both frames are valid; NaN at 0).

    This is how the evaluation suite scores a method where the truth is known (:mod:`core.report`).

    Parameters
    ----------
    deltas : (K, V, 3) float, metres; W, Wt : (T, K) float (NaN read as 0); face : (F,) int vertex
        ids; valid : (T,) bool; chunk : frames per block (memory: chunk x F x 3 floats)

    Returns
    -------
    (mean (T,), p95 float, velocity (T,))
    """
    K = len(deltas)
    D = np.asarray(np.asarray(deltas)[:, face], dtype=np.float64).reshape(K, -1)
    T = len(W)
    mean, vel = np.full(T, np.nan), np.full(T, np.nan)
    samples = []
    for a in range(0, T, chunk):
        lo, b = max(a - 1, 0), min(a + chunk, T)  # one frame of overlap for the velocity
        E = ((np.nan_to_num(W[lo:b]) - np.nan_to_num(Wt[lo:b])) @ D).reshape(b - lo, len(face), 3)
        d = np.linalg.norm(E[a - lo:], axis=2) * _MM
        ok = valid[a:b]
        mean[a:b] = np.where(ok, d.mean(1), np.nan)
        samples.append(d[ok].ravel())
        dv = np.linalg.norm(np.diff(E, axis=0), axis=2).mean(1) * _MM
        vel[lo + 1:b] = np.where(valid[lo + 1:b] & valid[lo:b - 1], dv, np.nan)
    s = np.concatenate(samples) if samples else np.zeros(0)
    return mean, (float(np.percentile(s, 95)) if s.size else float("nan")), vel
