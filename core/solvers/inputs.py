"""Input normalisation shared by the marker solvers and the metrics.

Every solver and metric takes the same three inputs, normalised here once:

* ``B``: target marker blendshape deltas, (K, M, 3) or the paper's (3M, K) matrix (Seol 2012,
  eq. 1), returned as the (3M, K) float64 matrix with rows in the x0 y0 z0 x1 ... order of
  :func:`core.model.flatten`;
* ``S``: source marker deltas (T, M, 3) in metres, NaN where a sample is missing;
* ``valid``: a (T, M) mask of the samples that exist (default: where ``S`` is finite).

Missing samples are dropped from every term by the mask, never zeroed silently:
:func:`zero_filled` puts zeros there only so that the masked products can be written as
dense ones.
"""

from __future__ import annotations

import numpy as np

from core.model import flatten

__all__ = ["as_basis", "as_sequence", "as_valid", "zero_filled"]


def as_basis(B, name: str = "B") -> np.ndarray:
    """(K, M, 3) marker deltas or the paper's (3M, K) matrix -> (3M, K) float64.

    Raises
    ------
    ValueError
        Not (K, M, 3) or (3M, K), or NaN/inf entries.
    """
    B = np.asarray(B, dtype=np.float64)
    if B.ndim == 3:
        if B.shape[2] != 3:
            raise ValueError(f"{name}: expected (K, M, 3) marker deltas or a (3M, K) matrix, got {B.shape}")
        B = flatten(B).T
    elif B.ndim != 2 or B.shape[0] % 3:
        raise ValueError(f"{name}: expected (K, M, 3) marker deltas or a (3M, K) matrix, got {B.shape}")
    if not np.isfinite(B).all():
        raise ValueError(f"{name}: contains NaN/inf")
    return np.ascontiguousarray(B)


def as_sequence(S, M: int, name: str = "S") -> np.ndarray:
    """(T, M, 3) source marker deltas -> float64 (T, M, 3) (NaN kept for missing samples).

    Raises
    ------
    ValueError
        Not (T, M, 3) with the given ``M``, or no frame.
    """
    S = np.asarray(S, dtype=np.float64)
    if S.ndim != 3 or S.shape[1:] != (M, 3):
        raise ValueError(f"{name}: expected (T, {M}, 3) source marker deltas, got {S.shape}")
    if len(S) < 1:
        raise ValueError(f"{name}: needs at least one frame")
    return S


def as_valid(valid, S3: np.ndarray, name: str = "valid") -> np.ndarray:
    """(T, M) bool mask: given, or where ``S`` is finite. Valid samples must be finite.

    Raises
    ------
    ValueError
        Wrong shape, or a sample marked valid that is NaN/inf (naming frame and marker).
    """
    with np.errstate(all="ignore"):
        all_finite = bool(np.isfinite(np.add.reduce(S3, axis=None)))  # one pass, no temporaries
    finite = np.ones(S3.shape[:2], bool) if all_finite else np.isfinite(S3).all(-1)
    if valid is None:
        return finite
    v = np.asarray(valid)
    if v.shape != finite.shape:
        raise ValueError(f"{name}: expected shape {finite.shape} (frames, markers), got {v.shape}")
    v = v.astype(bool)
    bad = v & ~finite
    if bad.any():
        t, m = np.argwhere(bad)[0]
        raise ValueError(f"{name}: sample (frame {t}, marker {m}) is marked valid but is NaN/inf")
    return v


def zero_filled(S3: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 3M) with missing samples set to 0 (they are masked out of every term).

    Without missing samples this is a read-only view of ``S3`` (no copy of a long take).
    """
    if valid.all():
        v = S3.reshape(len(S3), -1).view()
        v.flags.writeable = False
        return v
    return np.where(valid[:, :, None], S3, 0.0).reshape(len(S3), -1)
