r"""Greedy blendshape basis selection with non-negative weights (Xu et al. 2014 §4.1, eq. 6-7).

The smoothed sequence is written as ``S̄_t ≈ S̄_0 + Σ_k w_tk (S̄_{j_k} - S̄_0)``, ``w_t >= 0``:
eq. 6 with the first basis ``b_1 = S̄_0`` held at weight 1 — the delta-blendshape form, so the
result is directly a rig "neutral + K deltas" (K counts the deltas). Bases are frames of the
sequence (eq. 7 restricted to the discrete set of frames, as the paper does), added greedily
until the relative residual energy falls below ``eps`` or ``max_bases`` is reached.

Everything runs on inner products: with the frame displacements ``Y`` (T, 3V) the problem
only needs the Gram matrix ``Γ = Y Y^T`` (T, T), which :func:`gram_from_factored` gets from a
:class:`~core.transfer.decompose.FactoredSequence` in O(T r²).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.optimize import nnls

__all__ = ["nnls_gram", "select_bases", "BasisSelection", "gram_from_factored"]


def nnls_gram(G: np.ndarray, H: np.ndarray, maxiter: int | None = None) -> np.ndarray:
    r"""Non-negative least squares for many right-hand sides given in Gram form.

    For every column ``h = B^T s`` of ``H`` solves

    .. math:: \min_{w \ge 0} \|B w - s\|^2 = w^T G w - 2 w^T h + \text{const},\quad G = B^T B

    (Xu et al. 2014 eq. 7; the NNLS of James & Twigg 2005). With ``G = R^T R`` (Cholesky) this
    is the K x K problem ``min ||R w - R^{-T} h||``, solved by Lawson–Hanson
    (:func:`scipy.optimize.nnls`) per column: O(K³) each, independent of the mesh size.
    Columns whose unconstrained solution ``G^{-1} h`` is non-negative skip the active set.

    Parameters
    ----------
    G : (K, K) symmetric positive definite
    H : (K,) or (K, T)

    Returns
    -------
    W : (K,) or (K, T) float64, non-negative

    Raises
    ------
    ValueError
        Shapes that do not match; ``np.linalg.LinAlgError`` when ``G`` is singular
        (linearly dependent bases).
    """
    G = np.asarray(G, dtype=np.float64)
    H = np.asarray(H, dtype=np.float64)
    K = G.shape[0]
    if G.shape != (K, K) or H.shape[0] != K:
        raise ValueError(f"G, H: expected (K, K) and (K, ...), got {G.shape} and {H.shape}")
    vec = H.ndim == 1
    H2 = H[:, None] if vec else H
    if K == 0:
        return np.zeros_like(H)
    # scale-invariant Cholesky: the Gram of mesh displacements can be ~1e-8
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    Gs = G / np.outer(d, d)
    Rl = np.linalg.cholesky(Gs)  # lower, Gs = Rl Rl^T
    R = Rl.T
    Z = solve_triangular(Rl, H2 / d[:, None], lower=True)
    # where the unconstrained minimiser is already >= 0 it is the NNLS solution (G is SPD):
    # solve all columns at once, send only the others to Lawson-Hanson
    W = solve_triangular(R, Z, lower=False)
    for t in np.flatnonzero((W < 0).any(axis=0)):
        W[:, t] = nnls(R, Z[:, t], maxiter=maxiter)[0]
    W /= d[:, None]
    return W[:, 0] if vec else W


def gram_from_factored(coeffs: np.ndarray, basis_gram: np.ndarray) -> np.ndarray:
    """``Γ = C M C^T`` for displacements ``Y = C Q`` with ``M = Q Q^T``."""
    return coeffs @ basis_gram @ coeffs.T


@dataclass(frozen=True)
class BasisSelection:
    """Result of :func:`select_bases`.

    Attributes
    ----------
    frames : (K,) int     frame index of each selected basis, in selection order
    weights : (T, K)      non-negative weights of every frame
    errors : (K + 1,)     relative residual energy after 0, 1, ..., K bases
    """

    frames: np.ndarray
    weights: np.ndarray
    errors: np.ndarray

    @property
    def n_bases(self) -> int:
        return len(self.frames)


def _fit(Gam: np.ndarray, sel: list) -> tuple[np.ndarray, np.ndarray]:
    """Weights (T, k) and per-frame residual energies (T,) for bases ``sel``."""
    G = Gam[np.ix_(sel, sel)]
    H = Gam[sel, :]
    W = nnls_gram(G, H)
    res = np.diag(Gam) - 2 * np.einsum("kt,kt->t", W, H) + np.einsum("kt,kl,lt->t", W, G, W)
    return W.T, np.maximum(res, 0.0)


def select_bases(gram: np.ndarray, eps: float = 1e-3, max_bases: int = 30, candidates: int = 8,
                 min_bases: int = 0) -> BasisSelection:
    r"""Greedy basis selection from a sequence (Xu et al. 2014 eq. 7, after Huang et al. 2011).

    .. math:: \min_{\{j_k\}, w_t \ge 0} \sum_t \|\textstyle\sum_k w_{tk} y_{j_k} - y_t\|^2,
              \quad y_t = \bar S_t - \bar S_0

    One basis is added per step: of the ``candidates`` frames worst reconstructed so far,
    the one that lowers the total NNLS error most (``candidates >= T`` evaluates every
    frame: the exact greedy step). Stops when ``error / Σ_t ||y_t||² <= eps``.

    Parameters
    ----------
    gram : (T, T) the Gram matrix ``Γ_st = <y_s, y_t>``
    eps : float, relative residual energy to reach
    max_bases : int
    candidates : int
    min_bases : int, select at least this many (when the sequence has that many independent frames)

    Returns
    -------
    BasisSelection

    Raises
    ------
    ValueError
        ``gram`` not square, ``eps < 0``, ``max_bases < 0`` or ``candidates < 1``.
    """
    Gam = np.asarray(gram, dtype=np.float64)
    T = Gam.shape[0]
    if Gam.ndim != 2 or Gam.shape != (T, T):
        raise ValueError(f"gram: expected (T, T), got {Gam.shape}")
    if eps < 0 or max_bases < 0 or candidates < 1:
        raise ValueError(f"eps >= 0, max_bases >= 0, candidates >= 1 expected, got {eps}, {max_bases}, {candidates}")
    total = float(np.trace(Gam))
    sel: list = []
    res = np.diag(Gam).copy()
    W = np.zeros((T, 0))
    errors = [1.0 if total > 0 else 0.0]
    scale = max(total / max(T, 1), 1e-300)
    while len(sel) < min(max_bases, T) and (errors[-1] > eps or len(sel) < min_bases):
        order = np.argsort(-res, kind="stable")
        pool = [int(j) for j in order if j not in sel and res[j] > 1e-12 * scale][:candidates]
        if not pool:
            break
        best = None
        for j in pool:
            try:
                Wj, rj = _fit(Gam, sel + [j])
            except np.linalg.LinAlgError:  # j is a combination of the bases already chosen
                continue
            e = float(rj.sum())
            if best is None or e < best[0]:
                best = (e, j, Wj, rj)
        if best is None:
            break
        e, j, W, res = best
        sel.append(j)
        errors.append(e / total if total > 0 else 0.0)
    return BasisSelection(np.asarray(sel, dtype=np.int64), W, np.asarray(errors))
