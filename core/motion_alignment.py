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
"""

from __future__ import annotations

import numpy as np

#: isotropic regularisation of the second moments, relative to their trace (ε above); 0.1 was the
#: best of 0.01, 0.1, 0.3 and 1 on the sample (measured with the symmetric map; 0.3 within 0.002 mm)
COVARIANCE_EPS = 0.1


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
