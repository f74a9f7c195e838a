"""Model-specific PCA prior on blendshape weights (Seol et al. 2012, §5).

The prior is a Gaussian over the target face's marker positions, learned by PCA from an
"animation" whose j-th frame is the j-th blendshape (the default), from an example animation
of the target, or from a chosen subset of its shapes (Seol 2012, Fig. 13)::

    f_tgt = E v + t_bar                                  (Seol 2012, eq. 3)
    E_prior(w) = v^T Lambda^-1 v,   v = E^T (B w + n_tgt - t_bar)

Everything here lives in *delta space* (positions minus the target neutral ``n_tgt``), so
``B w + n_tgt - t_bar = B w - mean_`` with ``mean_ = t_bar - n_tgt``. As a function of the
weights the prior is the quadratic::

    E_prior(w) = w^T P w - 2 q^T w + c
    P = B^T E Lambda^-1 E^T B,  q = B^T E Lambda^-1 E^T mean_,  c = mean_^T E Lambda^-1 E^T mean_

Units and the meaning of alpha
------------------------------
``E_match`` (Seol eq. 2) and the Sobolev term are squared lengths; ``E_prior`` is scale-free
(``v`` scales with length and ``Lambda`` with length squared). Measuring lengths in a unit of
``s`` metres multiplies ``E_match`` by ``1/s**2`` and leaves ``E_prior`` unchanged, so the
minimiser of ``E_match + alpha E_prior`` for data in that unit is the minimiser of
``E_match[m^2] + alpha * s**2 * E_prior`` for the same data in metres::

    alpha_internal = alpha * s**2         (s = metres per unit; cm -> 1e-4, mm -> 1e-6)

The paper does not state its length unit ("the value of alpha is empirically decided depending
on the size of the faces"). We read its alpha = 0.01 (spacetime) and 0.5 (per frame) as values
for faces measured in **centimetres**, the scale at which both terms are of the same order for a
human-sized face; the solvers therefore take ``alpha`` together with ``alpha_units="cm"`` and
convert with :func:`alpha_for_units`. ``alpha_units="m"`` passes alpha through unchanged.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from core.model import flatten, unit_scale

__all__ = ["PCAPrior", "alpha_for_units", "prior_quadratic"]


def alpha_for_units(alpha: float, units: str = "cm") -> float:
    """Prior weight for metre data equivalent to ``alpha`` chosen for lengths in ``units``.

    ``alpha_internal = alpha * s**2`` with ``s`` metres per unit (see the module docstring:
    ``E_match`` scales with length squared, ``E_prior`` is scale-free).

    Parameters
    ----------
    alpha : float >= 0
        Prior weight as the paper uses it (Seol 2012, eq. 4), for data in ``units``.
    units : str
        One of :data:`core.model.UNIT_SCALE` ("m", "cm", "mm", ...). Default "cm", our
        reading of the paper's scale.

    Raises
    ------
    ValueError
        ``alpha`` negative or not finite, or unknown ``units``.
    """
    alpha = float(alpha)
    if not np.isfinite(alpha) or alpha < 0:
        raise ValueError(f"alpha must be a finite number >= 0, got {alpha}")
    return alpha * unit_scale(units) ** 2


def _points(X, name: str) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"{name}: expected shape (N, M, 3), got {X.shape}")
    if not np.isfinite(X).all():
        raise ValueError(f"{name}: contains NaN/inf; mask or drop those samples before fitting")
    return X


class PCAPrior:
    """Gaussian PCA prior of a target face's marker positions (Seol et al. 2012, §5, eq. 3).

    Parameters
    ----------
    rtol : float, optional
        Principal directions whose singular value is at most ``rtol * sigma_max`` have a zero
        eigenvalue and are dropped (``h`` = number of non-zero eigenvalues, as in eq. 3).
        Default ``max(N, 3M) * eps``, numpy's ``matrix_rank`` rule.

    Attributes
    ----------
    mean_ : (M, 3) float
        ``t_bar - n_tgt``: mean of the training shapes in delta space (metres).
    components_ : (h, 3M) float
        ``E^T``: orthonormal principal directions in the x0 y0 z0 x1 ... order of
        :func:`core.model.flatten`; each sign fixed so its largest-magnitude entry is positive.
    eigenvalues_ : (h,) float
        ``Lambda``: variances along ``components_`` (``sigma**2 / (N - 1)``), descending.
    n_components_ : int
        ``h``.
    n_samples_ : int
        ``N``, training shapes used.
    basis_ : (K, M, 3) float or None
        Marker deltas ``B`` that the weights multiply (the blendshapes), when known.
    P_ : (K, K) float, q_ : (K,) float, c_ : float
        ``E_prior(w) = w^T P w - 2 q^T w + c`` for ``basis_`` (set when ``basis_`` is known).
    """

    def __init__(self, rtol: Optional[float] = None):
        self.rtol = rtol

    def fit(self, X, neutral_markers=None, basis=None, subset=None) -> "PCAPrior":
        """Learn the PCA model (Seol 2012, eq. 3).

        Parameters
        ----------
        X : (N, M, 3) float
            Training shapes. Without ``basis``: the target's marker blendshape deltas
            (K, M, 3), i.e. the "animation whose j-th frame is the j-th blendshape"; these are
            then also the ``basis_`` the weights multiply. With ``basis``: frames of an example
            animation of the target, as deltas from the neutral, or as positions when
            ``neutral_markers`` is given.
        neutral_markers : (M, 3) float, optional
            Target neutral marker positions ``n_tgt``; when given, ``X`` holds positions and
            ``X - neutral_markers`` is used.
        basis : (K, M, 3) float, optional
            The target's marker blendshape deltas ``B`` (needed for ``P_``, ``q_`` when ``X``
            is an example animation).
        subset : sequence of int or (N,) bool, optional
            Train only on these rows of ``X`` (e.g. the mouth shapes, Seol 2012 Fig. 13);
            ``basis_`` stays all of ``X`` when ``basis`` is None.

        Returns
        -------
        self

        Raises
        ------
        ValueError
            Wrong shapes, NaN, fewer than two training shapes, or no variation at all.
        """
        self.P_ = None  # (quadratic() computes the new basis's below, see _own_basis)
        X = _points(X, "PCAPrior.fit X")
        if basis is None:
            if neutral_markers is not None:
                raise ValueError("PCAPrior.fit: X given as positions (neutral_markers set) needs basis=(K, M, 3) blendshape deltas")
            basis_ = X.copy()
        else:
            basis_ = _points(basis, "PCAPrior.fit basis")
            if basis_.shape[1] != X.shape[1]:
                raise ValueError(f"PCAPrior.fit: basis has {basis_.shape[1]} markers, X has {X.shape[1]}")
        if neutral_markers is not None:
            n = np.asarray(neutral_markers, dtype=np.float64)
            if n.shape != X.shape[1:]:
                raise ValueError(f"PCAPrior.fit neutral_markers: expected shape {X.shape[1:]}, got {n.shape}")
            X = X - n
        if subset is not None:
            idx = np.asarray(subset)
            if idx.dtype == bool:
                if idx.shape != (len(X),):
                    raise ValueError(f"PCAPrior.fit subset: boolean mask must have shape ({len(X)},), got {idx.shape}")
                idx = np.flatnonzero(idx)
            idx = idx.astype(np.int64).ravel()
            if idx.size and (idx.min() < -len(X) or idx.max() >= len(X)):
                raise ValueError(f"PCAPrior.fit subset: indices must lie in [0, {len(X)}), got {idx.min()}..{idx.max()}")
            X = X[idx]
        N = len(X)
        if N < 2:
            raise ValueError(f"PCAPrior.fit: need at least 2 training shapes, got {N}")
        flat = flatten(X)
        mean = flat.mean(0)
        _, sig, Vt = np.linalg.svd(flat - mean, full_matrices=False)
        rtol = self.rtol if self.rtol is not None else max(flat.shape) * np.finfo(np.float64).eps
        # no variation at all when even the largest singular value is rounding noise of the data
        scale = np.linalg.norm(flat)
        h = int(np.count_nonzero(sig > rtol * sig[0])) if sig.size and sig[0] > rtol * scale else 0
        if h == 0:
            raise ValueError("PCAPrior.fit: the training shapes do not vary (all eigenvalues are zero)")
        comps = Vt[:h].copy()
        # svd_flip: the largest-magnitude entry of each direction is made positive so that
        # repeated fits give the same components (scikit-learn convention).
        big = np.abs(comps).argmax(1)
        comps *= np.sign(comps[np.arange(h), big])[:, None]
        self.mean_ = mean.reshape(-1, 3)
        self.components_ = comps
        self.eigenvalues_ = sig[:h] ** 2 / (N - 1)
        self.n_components_ = h
        self.n_samples_ = N
        self.basis_ = basis_
        self.P_, self.q_, self.c_ = self.quadratic(basis_)
        return self

    def _check_fitted(self):
        if not hasattr(self, "components_"):
            raise RuntimeError("PCAPrior is not fitted; call fit() first")

    def _factor(self, basis):
        """R = Lambda^-1/2 E^T B (h, K) and m = Lambda^-1/2 E^T mean (h,): E_prior = ||R w - m||^2."""
        self._check_fitted()
        B = np.asarray(basis, dtype=np.float64)
        if B.ndim == 3:
            if B.shape[1:] != self.mean_.shape:
                raise ValueError(f"basis: expected (K, {len(self.mean_)}, 3) marker deltas, got {B.shape}")
            B = flatten(B).T
        elif B.ndim != 2 or B.shape[0] != self.mean_.size:
            raise ValueError(f"basis: expected (K, M, 3) deltas or a ({self.mean_.size}, K) matrix, got {B.shape}")
        s = 1.0 / np.sqrt(self.eigenvalues_)
        R = (self.components_ @ B) * s[:, None]
        m = (self.components_ @ self.mean_.ravel()) * s
        return R, m

    def quadratic(self, basis):
        """The prior as a quadratic in the weights of ``basis`` (Seol 2012, §5).

        ``E_prior(w) = w^T P w - 2 q^T w + c``, with ``P = R^T R``, ``q = R^T m``, ``c = m^T m``,
        ``R = Lambda^-1/2 E^T B``, ``m = Lambda^-1/2 E^T mean_``.

        Parameters
        ----------
        basis : (K, M, 3) marker deltas or (3M, K) matrix ``B``

        Returns
        -------
        P : (K, K) float, symmetric positive semi-definite
        q : (K,) float
        c : float
        """
        if self._own_basis(basis):  # the fitted quadratic (fit computed it for this basis)
            return self.P_.copy(), self.q_.copy(), self.c_
        R, m = self._factor(basis)
        return R.T @ R, R.T @ m, float(m @ m)

    def _own_basis(self, basis) -> bool:
        """Whether ``basis`` ((K, M, 3) or (3M, K)) holds the same numbers as ``basis_``: the
        solvers ask for the quadratic of the prior's own shapes at every solve (a setting change
        of a dense take: a (h, 3M) x (3M, K) product each time)."""
        own = getattr(self, "basis_", None)
        if own is None or getattr(self, "P_", None) is None:
            return False
        B = np.asarray(basis)
        if B.shape == own.shape:
            return B is own or np.array_equal(B, own)
        return B.shape == (own[0].size, len(own)) and np.array_equal(B, flatten(own).T)

    def coefficients(self, W, basis=None) -> np.ndarray:
        """PCA coefficients ``v = E^T (B w - mean_)`` for weights (K,) or (T, K) -> (h,) or (T, h)."""
        self._check_fitted()
        B = self.basis_ if basis is None else basis
        if B is None:
            raise ValueError("coefficients: give basis, the (K, M, 3) marker deltas the weights multiply")
        R, m = self._factor(B)
        W = np.asarray(W, dtype=np.float64)
        if W.shape[-1] != R.shape[1]:
            raise ValueError(f"W: last axis must be K={R.shape[1]}, got {W.shape}")
        return (W @ R.T - m) * np.sqrt(self.eigenvalues_)

    def energy(self, W, basis=None) -> np.ndarray:
        """``E_prior = v^T Lambda^-1 v`` per frame (Seol 2012, §5): (K,) -> float, (T, K) -> (T,)."""
        v = self.coefficients(W, basis)
        e = (v**2 / self.eigenvalues_).sum(-1)
        return float(e) if np.ndim(e) == 0 else e


def prior_quadratic(prior, B: np.ndarray, K: int):
    """The prior as ``(P, q, c)`` for the weights of ``B``: ``E_prior(w) = w^T P w - 2 q^T w + c``.

    Parameters
    ----------
    prior : PCAPrior, (P, q) or (P, q, c) tuple, or None
        A fitted :class:`PCAPrior` (its :meth:`PCAPrior.quadratic` for ``B``), an explicit
        quadratic, or None: the paper's default, a PCA of ``B``'s own shapes (Seol 2012, §5).
    B : (3M, K) float
        Marker blendshape matrix the weights multiply.
    K : int
        Number of shapes (checked against an explicit ``P``, ``q``).

    Raises
    ------
    ValueError
        An explicit ``P`` that is not (K, K) and symmetric or ``q`` not (K,), or another type.
    """
    if prior is None:
        prior = PCAPrior().fit(B.T.reshape(K, -1, 3))
    if isinstance(prior, PCAPrior):
        return prior.quadratic(B)
    if isinstance(prior, (tuple, list)) and len(prior) in (2, 3):
        P = np.asarray(prior[0], dtype=np.float64)
        q = np.asarray(prior[1], dtype=np.float64)
        c = float(prior[2]) if len(prior) == 3 else 0.0
        if P.shape != (K, K) or q.shape != (K,):
            raise ValueError(f"prior: expected (P (K, K), q (K,)) with K={K}, got {P.shape}, {q.shape}")
        if not np.allclose(P, P.T, rtol=1e-10, atol=1e-12 * max(np.abs(P).max(), 1e-300)):
            raise ValueError("prior: P must be symmetric")
        return 0.5 * (P + P.T), q, c
    raise ValueError(f"prior: expected a fitted PCAPrior, a (P, q) tuple or None, got {type(prior).__name__}")
