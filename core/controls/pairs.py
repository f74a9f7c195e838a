"""Symmetry pairs and cancel pairs: two shapes tied together, or kept apart, in the solve.

Symmetry (soft)
---------------
For pairs ``(L, R)`` the energy gains ``mu_s sum_pairs (w_L - w_R)^2 = mu_s w^T Q w`` per frame
with ``Q = sum (e_L - e_R)(e_L - e_R)^T`` (the graph Laplacian of the pairs, PSD). The solvers
take ``Q`` relative to ``sigma_max(B)^2`` (like their ridge): ``mu_s = 1`` makes a unit L/R
difference cost as much as a unit move along the most visible shape combination. It is the
"symmetry pairs" term of NVIDIA's Audio2Face-3D blendshape solver [1] (there an absolute
``A += symmetry * scale * S^T S`` with ``S`` rows ``e_a - e_b``). Because ``Q`` is the same
matrix in every frame it joins the per-frame Gram matrix (per-frame solvers) or the spacetime
solver's ``C`` (exact, fast path kept). The default pairs come from the names
(:func:`symmetry_pairs`: the left/right mirrors of :mod:`core.controls.sides` that are not
directions).

Cancel pairs (hard)
-------------------
``w_a w_b = 0`` (two shapes that must not fire together: blink vs wide, jawOpen vs
mouthClose) is a complementarity constraint: the feasible set is not convex. We use the
Audio2Face-style *second pass* [1]: solve; in every frame (and region) where both weights of a
pair exceed ``threshold`` hold the weaker one at 0 and re-solve the others with it held; repeat
while a re-solve makes another pair fire (each pass only adds held entries, so it ends). The
result is the optimum of the convex problem with those entries fixed, not the optimum of the
non-convex one (which would need a branch per pair and frame). Its marker-error cost is
measured in ``docs/controls.md``.

References
----------
.. [1] NVIDIA, Audio2Face-3D blendshape solver (MIT, 2025): ``FacsSolver`` with active poses,
       cancel pairs, symmetry pairs, L1/L2 and temporal terms.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..names import canonical
from .inputs import as_names, as_weights, shape_index
from .sides import is_directional, mirror_pairs

__all__ = ["symmetry_pairs", "suggested_cancel_pairs", "pair_indices", "symmetry_matrix", "cancel_conflicts",
           "cancel_pairs", "cancel_clamp"]


def symmetry_pairs(names: Sequence[str]) -> list:
    """The default symmetry pairs: :func:`mirror_pairs` minus directional shapes.

    A symmetry pair ties the two sides of one expression (``eyeBlinkLeft``/``eyeBlinkRight``,
    ``AU_12_L_LipCornerPuller``/``AU_12_R_...``). Left out: pairs whose side token is a
    direction, whose mirror is the opposite motion (``jawLeft``/``jawRight``,
    ``mouthLeft``/``mouthRight``, ``SR_20_Jaw_Left``, ``HB_10_L_Tongue``, ``SR_27_Mouth_Lower_Left``,
    ``AU_61_EyesTurnLeft``), names with two side tokens (``SR_07_Eye_Left_Left``: gaze), and ARKit's
    horizontal gaze (``eyeLookIn*``/``eyeLookOut*``: the eyes turn together, in-left with
    out-right). Vertical gaze (``eyeLookUp*``) stays tied. Edit the table's ``symmetry`` list to
    change it.
    """
    return [(a, b) for a, b in mirror_pairs(names) if not is_directional(a, b)]


#: suggested cancel pairs, by canonical ARKit name (blink vs wide per eye; jaw open vs mouth
#: close is a candidate for rigs whose mouthClose is a standalone lip press)
_SUGGESTED_CANCEL = (("eyeBlinkLeft", "eyeWideLeft"), ("eyeBlinkRight", "eyeWideRight"), ("jawOpen", "mouthClose"))


def suggested_cancel_pairs(names: Sequence[str]) -> list:
    """Cancel pairs worth trying on a rig with ARKit shapes: blink vs wide per eye and jaw
    open vs mouth close, as ``[(a, b), ...]`` in the rig's spelling (pairs whose shapes the rig
    lacks are left out). Not a default: a cancel pair costs marker error (docs/controls.md), and
    ARKit's own mouthClose is meant to be used *with* jawOpen."""
    names = as_names(names)
    by = {}
    for n in names:
        by.setdefault(canonical(n), []).append(n)
    return [(by[a][0], by[b][0]) for a, b in _SUGGESTED_CANCEL if a in by and b in by]


def pair_indices(pairs, names: Sequence[str], where: str = "pairs") -> np.ndarray:
    """``[(a, b), ...]`` of names (exact or canonical ARKit names) or indices -> (P, 2) int."""
    names = as_names(names)
    out = []
    for i, p in enumerate(pairs):
        if len(p) != 2:
            raise ValueError(f"{where}[{i}]: expected a pair, got {p!r}")
        row = [x if isinstance(x, (int, np.integer)) else shape_index(str(x), names, f"{where}[{i}]") for x in p]
        for x in row:
            if not 0 <= int(x) < len(names):
                raise ValueError(f"{where}[{i}]: index {x} is outside [0, {len(names)})")
        if row[0] == row[1]:
            raise ValueError(f"{where}[{i}]: a pair needs two different shapes")
        out.append([int(row[0]), int(row[1])])
    return np.asarray(out, np.int64).reshape(-1, 2)


def _index_pairs(pairs, K: int, name: str) -> np.ndarray:
    P = np.asarray(pairs if len(pairs) else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    if P.size and (P.min() < 0 or P.max() >= K):
        raise ValueError(f"{name}: indices must be in [0, {K}), got {P.min()}..{P.max()}")
    if (P[:, 0] == P[:, 1]).any():
        raise ValueError(f"{name}: a pair needs two different shapes")
    return P


def symmetry_matrix(pairs, K: int, weight: float = 1.0) -> np.ndarray:
    """``Q`` with ``w^T Q w = weight * sum_pairs (w_a - w_b)^2`` (the pairs' graph Laplacian).

    Pass it as the ``quadratic`` option of :func:`core.solvers.baselines.range_pf`,
    :func:`~core.solvers.baselines.prior_pf`, :class:`~core.solvers.spacetime.SpacetimeSolver`,
    :func:`~core.solvers.local.local_precompute` and
    :class:`~core.solvers.geometric.GeometricSolver`, which scale it by their data term's
    ``sigma_max^2`` (module docstring).

    Parameters
    ----------
    pairs : (P, 2) int (see :func:`pair_indices` for names)
    K : int
    weight : float >= 0, the relative ``mu_s``

    Returns
    -------
    (K, K) float, symmetric positive semi-definite.
    """
    w = float(weight)
    if not (np.isfinite(w) and w >= 0):
        raise ValueError(f"weight: expected a finite number >= 0, got {weight}")
    P = _index_pairs(pairs, K, "pairs")
    Q = np.zeros((K, K))
    np.add.at(Q, (P[:, 0], P[:, 0]), w)
    np.add.at(Q, (P[:, 1], P[:, 1]), w)
    np.add.at(Q, (P[:, 0], P[:, 1]), -w)
    np.add.at(Q, (P[:, 1], P[:, 0]), -w)
    return Q


def cancel_conflicts(W, pairs, threshold: float = 0.0) -> np.ndarray:
    """(N, P) bool: rows where both weights of a cancel pair exceed ``threshold``."""
    W = as_weights(W)
    P = _index_pairs(pairs, W.shape[1], "pairs")
    with np.errstate(invalid="ignore"):
        return (W[:, P[:, 0]] > threshold) & (W[:, P[:, 1]] > threshold)


def _weaker(W, P, conflict):
    """(rows, shapes) of the weaker weight of each conflicting pair (ties: the second)."""
    r, p = np.nonzero(conflict)
    a, b = P[p, 0], P[p, 1]
    k = np.where(W[r, a] >= W[r, b], b, a)
    return r, k


def cancel_clamp(W, pairs, threshold: float = 0.0) -> np.ndarray:
    """The cheap alternative to :func:`cancel_pairs`: the weaker weight of every firing pair
    set to 0 without re-solving (the marker error it costs is larger, docs/controls.md)."""
    W = as_weights(W).copy()
    P = _index_pairs(pairs, W.shape[1], "pairs")
    for _ in range(len(P) + 1):
        c = cancel_conflicts(W, P, threshold)
        if not c.any():
            break
        r, k = _weaker(W, P, c)
        W[r, k] = 0.0
    return W


def cancel_pairs(solve: Callable, W, pairs, threshold: float = 0.0, max_passes: int = 8):
    """Cancel pairs by re-solving with the weaker shape held at 0 (Audio2Face's second pass [1]).

    ``w_a w_b = 0`` is not convex. Pass ``n``: find the rows (frames, or frame-region problems)
    where both weights of a pair exceed ``threshold``; hold the weaker at 0 there (for good:
    the held set only grows); re-solve everything with ``solve(zero)``. Stop when no pair fires.
    A re-solve can make another pair fire (the freed marker residual goes somewhere), hence the
    passes; each adds held entries, so the loop ends. After ``max_passes`` the remaining firing
    pairs are clamped (``info["clamped"]``, 0 in every case measured).

    Parameters
    ----------
    solve : callable ``zero (N, K) bool -> (N, K) weights``
        The method's solve with those weights held at 0, e.g.
        ``lambda z: range_pf(B, S, lo, hi, valid, ridge, zero=z)``,
        ``lambda z: SpacetimeSolver(...).solve(zero=z)``,
        ``lambda z: problem.solve(S, valid, zero=z.reshape(T, R, K)).reshape(T * R, K)`` (local,
        per region), ``lambda z: GeometricSolver(...).solve(frames, zero=z).weights``.
    W : (N, K) float
        The first pass (the method's result without cancel pairs).
    pairs : (P, 2) int
    threshold : float >= 0
        "Fires": above this weight (0: any positive weight, the complementarity ``w_a w_b = 0``).
    max_passes : int

    Returns
    -------
    W : (N, K) float, no pair with both weights above ``threshold``
    info : dict ``passes``, ``held`` (N, K) bool, ``rows`` (rows that changed), ``clamped``

    Raises
    ------
    ValueError
        ``threshold < 0``; a held weight the solve did not bring to ``<= threshold`` (its lower
        bound is above the threshold: the pair cannot be cancelled).
    """
    W = as_weights(W).copy()
    N, K = W.shape
    P = _index_pairs(pairs, K, "pairs")
    thr = float(threshold)
    if not (np.isfinite(thr) and thr >= 0):
        raise ValueError(f"threshold: expected a finite number >= 0, got {threshold}")
    held = np.zeros((N, K), bool)
    info = {"passes": 0, "held": held, "rows": 0, "clamped": 0}
    if not len(P):
        return W, info
    touched = np.zeros(N, bool)
    for _ in range(int(max_passes)):
        c = cancel_conflicts(W, P, thr)
        if not c.any():
            break
        r, k = _weaker(W, P, c)
        if held[r, k].any():
            i = int(np.flatnonzero(held[r, k])[0])
            raise ValueError(f"cancel pairs: shape {int(k[i])} is held at 0 in row {int(r[i])} but the solve gave "
                             f"{W[r[i], k[i]]:g} > threshold {thr:g} (its lower bound?); a cancel pair needs shapes "
                             "that can reach 0")
        held[r, k] = True
        touched[r] = True
        W = as_weights(solve(held.copy()), "solve(zero)").copy()
        if W.shape != (N, K):
            raise ValueError(f"solve(zero) returned {W.shape}, expected ({N}, {K})")
        info["passes"] += 1
    c = cancel_conflicts(W, P, thr)
    if c.any():
        r, k = _weaker(W, P, c)
        W[r, k] = 0.0
        info["clamped"] = int(len(r))
    info["rows"] = int(touched.sum())
    return W, info
