"""Aligning the actor's motion space to the character's, point by point, without names.

The range-of-motion match (``motion_scale = "rom"``, :func:`core.stages.retarget.rom_scale`)
scales each point's motion by one number. Two faces also move a point in *different directions*
for the same expression: ICT's jaw drop moves the chin back as much as down (z/|y| ≈ −0.97),
Rocketbox's almost straight down (−0.11); a scalar keeps the actor's direction, and a geometric
fit then builds the chin's backward motion out of jaw-in, visemes and cheek puffs instead of jaw
open. This module maps each point's motion by a 3×3 matrix instead, learned from what both sides
have without any names: the displacements the two rigs' shapes give the point.

**Covariance alignment** (whitening–colouring as in CORAL, Sun et al. 2016, per point, with the
principal axes paired as in a Procrustes fit; in the spirit of Ribera et al. 2017's range-of-motion
alignment, §4 eq. 4, which moves the rig towards the actor instead): the second moments of the
point's displacements over each rig's shapes,

    C_s(p) = 1/K_s Σ_k d_k^s(p) d_k^s(p)ᵀ,    C_t(p) = 1/K_t Σ_k d_k^t(p) d_k^t(p)ᵀ    (3×3),

regularised towards isotropy, C ← C + ε tr(C)/3 · I, have eigen-decompositions U Λ Uᵀ
(ascending). The map whitens the source's axes and colours them with the target's, axis i onto
axis i:

    A(p) = U_t S Λ_t^{1/2} Λ_s^{−1/2} U_sᵀ,   so that   A C_s Aᵀ = C_t,

with S = diag(±1) the sign fix: each pair of axes points the same way (u_t,i · u_s,i ≥ 0), and if
that makes A a reflection the least certain pair (smallest |u_t,i · u_s,i|) is flipped. A motion
space rotated by R (source displacements R d of the target's) is rotated back exactly (A = Rᵀ; when
the eigenvalues are distinct and no axis turns by 90° or more), which the symmetric choice C_t^{1/2} C_s^{−1/2} does not do (it shrinks a rotated axis by the
cosine of the angle). ``ε → ∞`` leaves the scalar ``sqrt(tr C_t / tr C_s)``: an RMS
range-of-motion scale, today's ``rom`` with the mean square in place of the maximum.

The actor's motion s_t(p) is then solved as A(p) s_t(p).

Measured on the sample (S07, ICT → Rocketbox, per-frame bounded solve, ridge 1e-2; see
docs/evaluation.md): case B 0.556 → 0.522 mm, case C 0.530 → 0.472 mm (the
symmetric map: 0.522 and 0.482).

**Matched alignment** (:func:`matched_alignment`, what ``auto`` uses when the take is a source
rig's curves): one step of an ICP on the two rigs' shape sets, weighted by the take. Under the
covariance map A₀, each source shape is paired with the target shape nearest to it,

    k(j) = argmin_k ‖A₀ s_j − t_k‖² / ‖A₀ s_j‖²                                  (M·3 norms),

the full source shape asking for the full target shape (weight 1 is each rig's extreme of the
expression, so no gain); then each point's map is refitted so that the *take* built from the
source shapes lands on the take built from their partners,

    A(p) = argmin_A Σ_t ‖A Σ_j w_tj s_j(p) − Σ_j w_tj t_k(j)(p)‖² + λ τ(p) ‖A − A₀(p)‖²_F
         = (Y Q Xᵀ + λ τ A₀)(X Q Xᵀ + λ τ I)⁻¹,

X, Y (3, J) the shapes s_j(p), t_k(j)(p); Q = WᵀW / T (J, J) the take's second moments of its
weight curves W (T, J), so the pairs the take uses most decide the map; τ(p) = tr(X Q Xᵀ)/3, λ
the pull towards the covariance map. Weighting by the take is what matters: with the *true* pairs
(names known) the same fit gives 0.35 mm on case C, unweighted (Q = I) 0.48, worse than A₀.
Each singular value of A(p) is then capped at κ σ_max(A₀(p)) (κ = 1.5): the refit may turn and
reshape the map, not make it stronger than 1.5× the covariance map in any direction. Measured
(every 4th frame): B 0.522 → 0.472 mm, C 0.472 → 0.415 mm; iterating the pairing and the refit
measured worse (C 0.45 after 3 steps), so it is one step.
"""

from __future__ import annotations

import numpy as np

#: isotropic regularisation of the second moments, relative to their trace (ε above); 0.1 was the
#: best of 0.01, 0.1, 0.3 and 1 on the sample (measured with the symmetric map; 0.3 within 0.002 mm)
COVARIANCE_EPS = 0.1
#: pull of :func:`matched_alignment`'s refit towards the covariance map (λ above, relative to each
#: point's take-weighted moment); 0.03-0.3 within 0.01 mm on the sample, 1 lost 0.02 in case C
MATCH_PRIOR = 0.1
#: the refitted map's singular values are capped at this times the covariance map's largest (κ): at
#: a point the take barely moves, partners that move it a lot would blow the map up (the jeeliz
#: triceratops: σ_max 164 where the covariance map has 9); 1.5 and 2 cost nothing on the sample
#: (B 0.472 / 0.474, C 0.415 / 0.418 mm), 1 costs 0.004
MATCH_CAP = 1.5


def second_moments(deltas, eps: float = COVARIANCE_EPS) -> np.ndarray:
    """(M, 3, 3) ``1/K Σ_k d_k(p) d_k(p)ᵀ + ε tr/3 · I`` of (K, M, 3) displacements.

    Raises ValueError for a shape other than (K, M, 3) with K ≥ 1.
    """
    d = np.asarray(deltas, dtype=np.float64)
    if d.ndim != 3 or d.shape[2] != 3 or len(d) == 0:
        raise ValueError(f"second_moments: deltas must be (K, M, 3) with K >= 1, got {d.shape}")
    C = np.einsum("kmi,kmj->mij", d, d) / len(d)
    tr = np.trace(C, axis1=1, axis2=2)
    return C + (eps * tr / 3.0)[:, None, None] * np.eye(3)


def covariance_alignment(source_deltas, target_deltas, eps: float = COVARIANCE_EPS) -> np.ndarray:
    """(M, 3, 3) per-point maps ``A(p) = U_t Λ_t^{1/2} Λ_s^{−1/2} U_sᵀ`` (see the module docstring).

    Parameters
    ----------
    source_deltas : (K_s, M, 3) the source rig's shapes' displacements at the M points.
    target_deltas : (K_t, M, 3) the target's (calibrated) shapes' displacements at the same points.
    eps : float >= 0, isotropic regularisation relative to each point's trace.

    A point either rig leaves still gets the identity. Raises ValueError on shapes that do not match.
    """
    s, t = np.asarray(source_deltas, dtype=np.float64), np.asarray(target_deltas, dtype=np.float64)
    if s.ndim != 3 or t.ndim != 3 or s.shape[1:] != t.shape[1:] or s.shape[2] != 3:
        raise ValueError(f"covariance_alignment: source and target deltas must be (K_s, M, 3) and (K_t, M, 3) "
                         f"over the same M points, got {s.shape} and {t.shape}")
    if eps < 0:
        raise ValueError(f"covariance_alignment: eps must be >= 0, got {eps}")
    Cs, Ct = second_moments(s, eps), second_moments(t, eps)
    ls, Us = np.linalg.eigh(Cs)  # ascending: axis i of one rig is paired with axis i of the other
    lt, Ut = np.linalg.eigh(Ct)
    dots = np.einsum("mji,mji->mi", Us, Ut)
    sign = np.where(dots < 0, -1.0, 1.0)
    # a proper map: if the signs make U_t S U_sᵀ a reflection, flip the least certain pair
    det = np.linalg.det(Us) * np.linalg.det(Ut) * sign.prod(1)
    weak = np.abs(dots).argmin(1)
    rows = np.flatnonzero(det < 0)
    sign[rows, weak[rows]] *= -1
    still = (ls[:, -1] <= 0) | (lt[:, -1] <= 0)
    ratio = np.sqrt(np.maximum(lt, 0) / np.where(ls > 0, ls, 1.0))
    A = np.einsum("mij,mj,mkj->mik", Ut * sign[:, None, :], ratio, Us)
    A[still] = np.eye(3)
    return A


def apply_alignment(A, deltas) -> np.ndarray:
    """(..., M, 3) ``A(p) d(p)`` for (M, 3, 3) maps and (..., M, 3) displacements (a new array)."""
    return np.einsum("mij,...mj->...mi", np.asarray(A, dtype=np.float64), np.asarray(deltas, dtype=np.float64))


def nearest_shapes(source_deltas, target_deltas) -> np.ndarray:
    """(J,) int: for each source shape the target shape nearest to it relative to its own size,
    ``k(j) = argmin_k ‖s_j − t_k‖² / ‖s_j‖²`` over all points (a shape that moves nothing: 0)."""
    s = np.asarray(source_deltas, dtype=np.float64).reshape(len(source_deltas), -1)
    t = np.asarray(target_deltas, dtype=np.float64).reshape(len(target_deltas), -1)
    d = (s ** 2).sum(1)[:, None] - 2.0 * s @ t.T + (t ** 2).sum(1)[None]
    return d.argmin(1)


def matched_alignment(source_deltas, target_deltas, source_weights, eps: float = COVARIANCE_EPS,
                      prior: float = MATCH_PRIOR, cap: float = MATCH_CAP, initial=None) -> np.ndarray:
    """(M, 3, 3) per-point maps refitted on the take from matched shapes (module docstring):
    ``A(p) = (Y Q Xᵀ + λ τ A₀)(X Q Xᵀ + λ τ I)⁻¹``, ``A₀`` :func:`covariance_alignment`, each
    source shape paired with its :func:`nearest_shapes` under ``A₀``, ``Q = WᵀW / T``; then each
    singular value of ``A(p)`` capped at ``κ σ_max(A₀(p))``.

    Parameters
    ----------
    source_deltas : (J, M, 3) the source rig's shapes' displacements at the M points.
    target_deltas : (K, M, 3) the target's (calibrated) shapes' displacements at the same points.
    source_weights : (T, J) the take's weight curves over the source shapes (NaN: no data, as 0).
    eps : float >= 0, the covariance map's regularisation (:func:`covariance_alignment`).
    prior : float >= 0, λ, the pull towards ``A₀``; a point the take does not move keeps ``A₀``.
    cap : float > 0, κ (``np.inf``: no cap).
    initial : (M, 3, 3), optional, ``A₀`` when already computed (``covariance_alignment(source, target, eps)``).

    Raises ValueError on shapes that do not match or a negative ``prior``.
    """
    s, t = np.asarray(source_deltas, dtype=np.float64), np.asarray(target_deltas, dtype=np.float64)
    W = np.nan_to_num(np.asarray(source_weights, dtype=np.float64))
    if W.ndim != 2 or W.shape[1] != len(s) or len(W) == 0:
        raise ValueError(f"matched_alignment: source_weights must be (T, {len(s)}) curves over the source shapes "
                         f"with T >= 1, got {W.shape}")
    if prior < 0:
        raise ValueError(f"matched_alignment: prior must be >= 0, got {prior}")
    if not cap > 0:
        raise ValueError(f"matched_alignment: cap must be > 0, got {cap}")
    A0 = covariance_alignment(s, t, eps) if initial is None else np.asarray(initial, dtype=np.float64)
    Y = t[nearest_shapes(apply_alignment(A0, s), t)]  # (J, M, 3) each source shape's partner
    Q = W.T @ W / len(W)
    G = np.einsum("jmi,jk,kmn->min", s, Q, s)
    R = np.einsum("jmi,jk,kmn->min", Y, Q, s)
    tau = prior * np.trace(G, axis1=1, axis2=2) / 3.0
    G = G + tau[:, None, None] * np.eye(3)
    R = R + tau[:, None, None] * A0
    still = np.trace(G, axis1=1, axis2=2) <= 0
    A = np.einsum("mij,mjk->mik", R, np.linalg.pinv(G, hermitian=True))
    A[still] = A0[still]
    if np.isfinite(cap):
        U, sv, Vt = np.linalg.svd(A)
        limit = cap * np.linalg.norm(A0, ord=2, axis=(1, 2))
        A = np.einsum("mij,mj,mjk->mik", U, np.minimum(sv, limit[:, None]), Vt)
    return A
