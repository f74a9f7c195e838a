"""Scale–proportion matching by an RBF warp (Seol et al. 2012, §3.2).

    d(x) = sum_i w_i ||x - c_i|| + A x + a0

The centres c_i are the markers on the neutral target face, trained so that d(c_i) equals
the corresponding marker on the neutral source face. With the kernel ||x - c|| (the
biharmonic spline in 3D, which minimises bending energy) and the linear polynomial term the
warp reproduces affine maps exactly. Every target blendshape's markers b_ij are then moved
to b*_ij = d(b_ij): the target's expressions in the actor's proportions.

Written by hand because scipy's ``RBFInterpolator`` (kernel="linear" is -r, degree=1) gives
the same interpolant but not the polynomial/affine part separately; we use it as the
reference in the tests.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist


#: distances evaluated at once by :meth:`RBFWarp.__call__` (points x centres; 32 MB of float64)
RBF_BLOCK = 2**22


class RBFWarp:
    """Interpolating RBF warp with kernel ||x - c|| and a linear polynomial.

    Parameters
    ----------
    smoothing : float
        Ridge added to the kernel diagonal, relative to the mean centre distance; 0 (the
        default) interpolates exactly as the paper does.

    Attributes
    ----------
    centers_ : (M, 3)
    weights_ : (M, 3)
    affine_ : (4, 3) rows: constant, x, y, z
    """

    def __init__(self, smoothing: float = 0.0):
        self.smoothing = smoothing

    def fit(self, centers, values) -> "RBFWarp":
        """Solve [[Phi, P], [P^T, 0]] [w; a] = [values; 0] for (M, 3) centres and (M, C) values
        (C = 3 for a warp; any C interpolates C fields at once with one factorisation).

        Raises ValueError on shape mismatch, fewer than 4 centres, or coplanar centres
        (the affine part is then undetermined).
        """
        c = np.asarray(centers, dtype=np.float64)
        v = np.asarray(values, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or v.ndim != 2 or len(v) != len(c):
            raise ValueError(f"RBFWarp.fit: centers must be (M, 3) and values (M, C), got {c.shape} and {v.shape}")
        M = len(c)
        if M < 4:
            raise ValueError(f"RBFWarp.fit: need at least 4 corresponding markers, got {M}")
        if not (np.isfinite(c).all() and np.isfinite(v).all()):
            raise ValueError("RBFWarp.fit: centers/values contain NaN")
        P = np.hstack([np.ones((M, 1)), c])
        sv = np.linalg.svd(P - P.mean(0) * [0, 1, 1, 1], compute_uv=False)
        if sv[-1] < 1e-9 * sv[0]:
            raise ValueError("RBFWarp.fit: the corresponding markers are (nearly) coplanar; the affine part is undetermined")
        Phi = cdist(c, c)
        if self.smoothing:
            Phi = Phi + self.smoothing * Phi.mean() * np.eye(M)
        A = np.zeros((M + 4, M + 4))
        A[:M, :M] = Phi
        A[:M, M:] = P
        A[M:, :M] = P.T
        rhs = np.vstack([v, np.zeros((4, v.shape[1]))])
        sol = np.linalg.solve(A, rhs)
        self.centers_ = c
        self.weights_ = sol[:M]
        self.affine_ = sol[M:]
        return self

    def __call__(self, x) -> np.ndarray:
        """Warp points (..., 3) -> (..., C)."""
        x = np.asarray(x, dtype=np.float64)
        flat = x.reshape(-1, 3)
        out = flat @ self.affine_[1:] + self.affine_[0]
        # in blocks of points: the (points, centres) distance matrix of every shape of a dense
        # correspondence at once (175 shapes x 1,000 points, 1,000 centres) took 10 GB, and 24 GB
        # was not enough for 2,000 points
        step = max(1, RBF_BLOCK // max(len(self.centers_), 1))
        for i in range(0, len(flat), step):
            out[i:i + step] += cdist(flat[i:i + step], self.centers_) @ self.weights_
        return out.reshape(x.shape[:-1] + (self.weights_.shape[1],))


def calibrate_deltas(target_neutral, target_deltas, source_neutral, smoothing: float = 0.0):
    """Target marker blendshapes in the source's proportions (Seol 2012 §3.2).

    Parameters
    ----------
    target_neutral : (M, 3) markers on the neutral target.
    target_deltas : (K, M, 3) marker deltas of the target's blendshapes.
    source_neutral : (M, 3) the same markers on the neutral source (actor).

    Returns
    -------
    deltas : (K, M, 3)  d(n + delta_k) - d(n), with d(n) = source_neutral up to smoothing.
    warp : the fitted :class:`RBFWarp`.
    """
    warp = RBFWarp(smoothing).fit(target_neutral, source_neutral)
    base = warp(target_neutral)
    moved = warp(np.asarray(target_neutral)[None] + np.asarray(target_deltas))
    return moved - base[None], warp
