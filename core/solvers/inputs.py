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

The solvers' settings are checked here too, one implementation each: per-shape values
(:func:`as_per_shape`), non-negative marker and frame weights (:func:`as_nonnegative`), weight
bounds (:func:`as_bounds`), a constant coupling of the weights (:func:`as_coupling`) and the mask
of weights held at zero (:func:`as_zero_mask`). ``name`` (a function's name) prefixes the
message of the ``ValueError`` each raises.
"""

from __future__ import annotations

import numpy as np

from core.model import flatten

__all__ = ["as_basis", "as_sequence", "as_valid", "zero_filled", "as_per_shape", "as_nonnegative", "as_bounds",
           "as_coupling", "as_zero_mask"]


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


def _prefix(name) -> str:
    return f"{name}: " if name else ""


def as_per_shape(x, K: int, name: str, allow_inf: bool = False) -> np.ndarray:
    """A scalar or (K,) setting -> (K,) float64 (finite and >= 0 unless ``allow_inf``).

    Raises
    ------
    ValueError
        Not a number or (K,) numbers; NaN; negative or infinite without ``allow_inf``.
    """
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number or ({K},) numbers, got {x!r}") from None
    if a.ndim == 0:
        a = np.full(K, float(a))
    if a.shape != (K,):
        raise ValueError(f"{name}: expected a number or ({K},) per-shape values, got shape {a.shape}")
    if allow_inf and np.isnan(a).any():
        raise ValueError(f"{name}: must not be NaN, got {x!r}")
    if np.isnan(a).any() or (not allow_inf and not np.isfinite(a).all()) or (not allow_inf and (a < 0).any()):
        raise ValueError(f"{name}: must be finite and >= 0, got {x!r}")
    return a.copy()


def as_nonnegative(x, shape: tuple, name: str) -> np.ndarray:
    """Weights of the given shape (e.g. per marker (M,), per frame (T,)) as float64, finite and >= 0.

    Raises
    ------
    ValueError
        Another shape, NaN/inf or a negative entry.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {x.shape}")
    if not np.isfinite(x).all() or (x < 0).any():
        raise ValueError(f"{name}: must be finite and >= 0")
    return x


def as_bounds(lower, upper, K: int, name: str = None, finite: bool = False):
    """(K,) lower and upper weight bounds from scalars, (K,) arrays or None (unbounded).

    ``finite``: refuse infinite (and None) bounds, for solvers that need a box.

    Raises
    ------
    ValueError
        Bounds of the wrong shape, NaN, infinite where ``finite``, ``lower = inf``,
        ``upper = -inf``, or ``lower > upper`` for a shape (naming it).
    """
    p = _prefix(name)
    lo = as_per_shape(-np.inf if lower is None else lower, K, p + "lower", allow_inf=True)
    hi = as_per_shape(np.inf if upper is None else upper, K, p + "upper", allow_inf=True)
    if finite and not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError(f"{p}bounds must be finite (use a large number for 'no bound'), got {lower}, {upper}")
    if (lo == np.inf).any() or (hi == -np.inf).any():
        raise ValueError(f"{p}lower must be < inf and upper > -inf")
    if (lo > hi).any():
        k = int(np.flatnonzero(lo > hi)[0])
        raise ValueError(f"{p}lower must be <= upper for every shape: shape {k} has lower={lo[k]:g} > upper={hi[k]:g}")
    return lo, hi


def as_coupling(Q, K: int, scale: float, name: str = None):
    """``scale * Q`` for a relative (K, K) coupling of the weights, validated; None -> None.

    ``Q`` must be finite, symmetric (to ``1e-12`` relative) and positive semi-definite (to
    ``1e-10`` relative), e.g. :func:`core.controls.symmetry_matrix`; its symmetric part is used.

    Raises
    ------
    ValueError
        Not (K, K), NaN/inf, not symmetric, not positive semi-definite.
    """
    if Q is None:
        return None
    p = _prefix(name)
    Q = np.asarray(Q, dtype=np.float64)
    if Q.shape != (K, K):
        raise ValueError(f"{p}quadratic: expected a ({K}, {K}) matrix (one row and column per shape), got {Q.shape}")
    if not np.isfinite(Q).all():
        raise ValueError(f"{p}quadratic: contains NaN/inf")
    top = max(float(np.abs(Q).max()), 1e-300)
    if np.abs(Q - Q.T).max() > 1e-12 * top:
        raise ValueError(f"{p}quadratic: must be symmetric")
    if np.linalg.eigvalsh(Q)[0] < -1e-10 * top:
        raise ValueError(f"{p}quadratic: must be positive semi-definite (a sum of squares, e.g. "
                         "core.controls.symmetry_matrix)")
    return scale * 0.5 * (Q + Q.T)


def as_zero_mask(zero, T: int, K: int, name: str = None):
    """(T, K) bool of the weights held at 0, from None, (K,) or (T, K); None when nothing is held.

    Raises
    ------
    ValueError
        Not a bool mask, or another shape.
    """
    if zero is None:
        return None
    p = _prefix(name)
    z = np.asarray(zero)
    if z.dtype != bool:
        raise ValueError(f"{p}zero must be a bool mask, got dtype {z.dtype}")
    if z.shape == (K,):
        z = np.broadcast_to(z, (T, K))
    if z.shape != (T, K):
        raise ValueError(f"{p}zero must be a ({K},) or ({T}, {K}) bool mask, got shape {z.shape}")
    return z if z.any() else None
