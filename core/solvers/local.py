"""Local (per-region) retargeting: Liu et al. 2011, §3.2.2 (eq. 2) and §4 (eq. 3).

The problem
-----------
For frame t and region k the paper solves (eq. 2)

    min_w ‖M_k (S w − t)‖²   s.t.  0 ≤ w(i) ≤ 1,  Σ_i w(i) = 1

over the n_b *absolute* poses S = [s_1 … s_nb] (marker positions of every pose, the neutral
among them), with M_k = diag(m_k) the region's marker scaling (repeated for x, y, z; see
:func:`core.segment.marker_weights`). With the neutral as pose 0 and delta shapes
``D = [s_1 − s_0, …]`` the same problem in the rig's delta weights u = (w_1 … w_K) is

    "simplex":  min_u ‖M_k (D u − b)‖²   s.t.  u ≥ 0,  1ᵀu ≤ 1,     b = t − s_0

(w_0 = 1 − 1ᵀu ≥ 0 is the neutral's share; u ≤ 1 is implied). The usual delta-rig
formulation drops the sum constraint:

    "box":      min_u ‖M_k (D u − b)‖²   s.t.  0 ≤ u ≤ 1.

Both are strictly convex QPs ½ uᵀH u + fᵀu with H = Dᵀ M_k² D (+ a tiny ridge, see
:class:`LocalProblem`) and f = −Dᵀ M_k² b. H depends on the region (and the frame's set of
valid markers) only, so it is formed once per region; every (frame, region) pair is one QP.

The solver
----------
K ≈ 20–50 and there are T·R problems (24,000 for 2,000 frames and 12 regions), so the work
is in batching, not in any single QP: the batched active-set kernels of :mod:`core.solvers.qp`.
The simplex form goes through :func:`core.solvers.qp.solve_simplex_sequence` (primal–dual
active set on the first frame of every block of frames, the primal active set warm-started
from the previous frame on the others; every QP solved to its KKT conditions, exactly).

The box form goes through :func:`core.solvers.boxqp.solve_box_sequence` instead: a compiled
parametric active-set method along the frames of every region (each frame starts from the
previous frame's solution and active set, one Cholesky update per set change, KKT conditions
verified per frame).

Synthesis (eq. 3) blends the regional results with the masks: ``x = n + Σ_k B_k D̄ u_k``.

Production controls (:mod:`core.controls`), all off by default
---------------------------------------------------------------
* ``quadratic`` Q (K × K, PSD, e.g. the symmetry term of :func:`core.controls.symmetry_matrix`):
  region k's Hessian gains ``λ_max(Dᵀ M_k² D) · Q``, so the term is equally strong relative to
  every region's own data term (per region, as the brief's "local (per region)" asks);
* ``lower``/``upper`` per shape for the box form: ``w = lower + (upper − lower) u`` turns
  ``lower ≤ w ≤ upper`` into the unit box (a pinned shape, ``lower = upper``, gets an identity row);
* ``zero`` in :meth:`LocalProblem.solve`: (T, K) or (T, R, K) weights held at 0 (the same
  identity-row device: one Hessian per region, mask pattern and zero pattern), used by the
  cancel pairs' second pass of :func:`core.controls.cancel_pairs`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d

from core.model import MarkerLayout, Rig, flatten
from core.solvers.boxqp import solve_box_sequence
from core.solvers.inputs import as_coupling
from core.solvers.qp import CONSTRAINTS, hessian_products, max_kkt_violation, solve_simplex_sequence
from core.solvers.spacetime import SpacetimeSolver


# ----------------------------------------------------------------------------------------
# the regional problem
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LocalProblem:
    """Precomputed regional normal equations for eq. 2 (Liu et al. 2011).

    ``H_k = Dᵀ M_k² D + ε_k I`` and the map ``b ↦ f = −Dᵀ M_k² b`` for every region k.
    ε_k = ``ridge`` · mean(diag Dᵀ M_k² D) keeps H_k invertible where a region's markers
    cannot see some shapes at all (their weights are then pulled to 0 instead of being
    arbitrary); at the default 1e-9 it changes no well-determined weight measurably.

    Build with :func:`local_precompute`; call :meth:`solve`.

    Attributes
    ----------
    neutral : (M, 3)
    deltas : (K, M, 3)
    marker_weights : (R, M) — the diagonals m_k of M_k (per marker, repeated over x, y, z)
    constraint : {"simplex", "box"}
    ridge : float
    H : (R, K, K) Hessians for frames where every marker is valid
    """

    neutral: np.ndarray
    deltas: np.ndarray
    marker_weights: np.ndarray
    constraint: str
    ridge: float
    H: np.ndarray
    info: dict = field(default_factory=dict)
    #: (R, K, K) absolute coupling per region (``quadratic`` times the region's scale), or None
    coupling: Optional[np.ndarray] = None
    #: (K,) box bounds of the weights (None: the unit box)
    lower: Optional[np.ndarray] = None
    upper: Optional[np.ndarray] = None

    @property
    def n_regions(self) -> int:
        return len(self.marker_weights)

    @property
    def n_shapes(self) -> int:
        return len(self.deltas)

    def hessians(self, valid: Optional[np.ndarray] = None) -> np.ndarray:
        """(R, K, K) Hessians for one validity pattern (M,) of markers (default all valid)."""
        B = flatten(self.deltas).T  # (3M, K)
        w = self.marker_weights**2
        if valid is not None:
            w = w * np.asarray(valid, dtype=np.float64)[None, :]
        w3 = np.repeat(w, 3, axis=1)  # (R, 3M)
        H = np.einsum("ak,ra,al->rkl", B, w3, B)
        tr = np.einsum("rkk->r", H) / self.n_shapes
        floor = 1e-300 + 1e-12 * max(tr.max(initial=0.0), 0.0)
        eps = self.ridge * np.maximum(tr, floor)
        H = H + eps[:, None, None] * np.eye(self.n_shapes)[None]
        return H if self.coupling is None else H + self.coupling

    def linear_terms(self, targets: np.ndarray, valid: Optional[np.ndarray] = None) -> np.ndarray:
        """f (T, R, K) = −Dᵀ M_k² (t − s_0) for targets (T, M, 3) (missing markers weigh 0)."""
        b = np.asarray(targets, dtype=np.float64) - self.neutral[None]
        w = np.broadcast_to(self.marker_weights[None] ** 2, (len(b),) + self.marker_weights.shape)
        if valid is not None:
            w = w * valid[:, None, :]
            b = np.where(valid[..., None], b, 0.0)
        T, M, R, K = len(b), len(self.neutral), self.n_regions, self.n_shapes
        if valid is None:
            # one GEMM: (T, 3M) @ (3M, R K) with the weighted bases Dᵀ M_k², (T, R, K) contiguous
            DW = self.deltas.reshape(1, K, 3 * M) * np.repeat(self.marker_weights**2, 3, axis=1)[:, None]  # (R, K, 3M)
            return -(b.reshape(T, 3 * M) @ DW.reshape(R * K, 3 * M).T).reshape(T, R, K)
        X = np.einsum("kmc,tmc->tkm", self.deltas, b, optimize=True)  # (T, K, M)
        return -np.einsum("tkm,trm->trk", X, w, optimize=True)

    def solve(self, targets, valid=None, max_iter: int = 10, return_info: bool = False, block: Optional[int] = None,
              warm_iter: int = 3, zero=None):
        """Regional weights for every frame: eq. 2 for all (frame, region) pairs.

        Parameters
        ----------
        targets : (T, M, 3) float
            Marker positions (same frame and units as ``neutral``); NaN where missing.
        valid : (T, M) bool, optional
            Default: finite targets. A missing marker gets weight 0 in that frame.
        max_iter : int
            ``"simplex"``: PDAS iterations before the primal active-set fallback.
        return_info : bool
        block : int, optional
            ``"simplex"``: frames per warm-start block: the first frame of each block is solved
            cold, the others warm-started from their predecessor; all blocks run as one batch
            (default 16). The result does not depend on it (every QP is solved to its KKT
            conditions). ``"box"`` walks every region's frames in one chain and ignores it.
        warm_iter : int
            ``"simplex"``: active-set iterations a warm-started QP gets within its step; the few
            that need more are resumed from their (feasible) iterate in one batch at the end.
        zero : (T, K) or (T, R, K) bool, optional
            Weights held at 0 (at ``lower`` when 0 is below it): per (frame, region) problem a held
            weight gets an identity row of the Hessian (module docstring). (T, K) holds them in
            every region.

        ``"box"`` is solved by the compiled parametric active-set method of
        :func:`core.solvers.boxqp.solve_box_sequence` (every region a chain of frames, each
        frame warm-started from the previous one's active set and verified by its KKT
        conditions); ``"simplex"`` by the block-warm-started PDAS / primal active set of
        :func:`core.solvers.qp.solve_simplex_sequence`.

        Returns
        -------
        U : (T, R, K) float64 delta weights per region (the neutral's share is 1 − ΣU for
            ``"simplex"``)
        info : dict (when ``return_info``): the solver's counters (``"simplex"``: PDAS
            iterations, fallbacks; ``"box"``: see ``solve_box_sequence``), ``kkt_violation``,
            ``objective`` (T, R) = ‖M_k (D u − b)‖² in m².

        Raises
        ------
        ValueError
            Targets of the wrong shape; a frame without any valid marker.
        """
        targets = np.asarray(targets, dtype=np.float64)
        M = len(self.neutral)
        if targets.ndim != 3 or targets.shape[1:] != (M, 3):
            raise ValueError(f"targets: expected (T, {M}, 3) marker positions, got {targets.shape}")
        finite = np.isfinite(targets).all(2)
        valid = finite if valid is None else np.asarray(valid, dtype=bool)
        if valid.shape != targets.shape[:2]:
            raise ValueError(f"valid: expected {targets.shape[:2]}, got {valid.shape}")
        if (valid & ~finite).any():
            raise ValueError("targets: samples marked valid contain NaN/inf")
        empty = ~valid.any(1)
        if empty.any():
            raise ValueError(f"targets: frames {np.flatnonzero(empty)[:10].tolist()} have no valid marker; drop or interpolate them first")
        T, R, K = len(targets), self.n_regions, self.n_shapes
        if valid.all():
            Htab = self.H
            hidx = np.tile(np.arange(R), T)
            f = self.linear_terms(targets)
        else:
            pats, inv = np.unique(valid, axis=0, return_inverse=True)
            inv = inv.ravel()
            Htab = np.concatenate([self.hessians(p) for p in pats])
            hidx = (inv[:, None] * R + np.arange(R)[None]).ravel()
            f = self.linear_terms(targets, valid)
        f = f.reshape(T, R, K)
        hidx = hidx.reshape(T, R)
        unit = self._unit(Htab, f, hidx, zero)
        if unit is not None:  # bounds or held weights: the problems in unit-box coordinates
            Htab, f, hidx, start, dz = unit
            if self.constraint == "box":
                u, stats = solve_box_sequence(Htab, f, hidx, return_info=True)
            else:
                u, stats = solve_simplex_sequence(Htab, f, hidx, block, max_iter, warm_iter)
            U = start + u * dz
            if self.lower is not None:
                U = np.clip(U, self.lower, self.upper)
            if not return_info:
                return U
            _, inf = self._finish(u, Htab, f, hidx, targets, valid, stats)  # KKT of the unit problems
            return U, dict(inf, objective=self._objective(U, targets, valid))
        if self.constraint == "box":
            U, stats = solve_box_sequence(Htab, f, hidx, return_info=True)
            return self._finish(U, Htab, f, hidx, targets, valid, stats) if return_info else U
        U, stats = solve_simplex_sequence(Htab, f, hidx, block, max_iter, warm_iter)
        if not return_info:
            return U
        return self._finish(U, Htab, f, hidx, targets, valid, stats)

    def _finish(self, U, Htab, f, hidx, targets, valid, info):
        """``(U, info)`` with the KKT violation and the objective ‖M_k (D u − b)‖² per (frame, region)."""
        K = self.n_shapes
        kkt = max_kkt_violation(Htab, f.reshape(-1, K), hidx.ravel(), U.reshape(-1, K), self.constraint)
        return U, dict(info, kkt_violation=kkt, objective=self._objective(U, targets, valid))

    def _objective(self, U, targets, valid):
        """‖M_k (D u − b)‖² per (frame, region), (T, R)."""
        res = np.einsum("trk,kmc->trmc", U, self.deltas) - (targets - self.neutral[None])[:, None]
        res = np.where(valid[:, None, :, None], res, 0.0)
        return np.einsum("trmc,rm->tr", res**2, self.marker_weights**2)

    def _unit(self, Htab, f, hidx, zero):
        """The problems in unit-box coordinates when there are bounds or held weights, else None.

        With ``w = start + d∘u`` (``start`` = lower, or the held value; ``d`` = upper − lower, 0
        for pinned and held weights) the QP ``½wᵀHw + fᵀw`` becomes ``½uᵀ(dHd)u + (d∘(H start +
        f))ᵀu``; rows and columns with ``d = 0`` get the identity (``u = 0``). One unit Hessian per
        (Hessian, held pattern). Returns ``(Htab, f, hidx, start (T, R, K), d (T, R, K))``.
        """
        T, R, K = f.shape
        z = None
        if zero is not None:
            z = np.asarray(zero)
            if z.dtype != bool:
                raise ValueError(f"zero: expected a bool mask, got dtype {z.dtype}")
            if z.shape == (T, K):
                z = np.broadcast_to(z[:, None, :], (T, R, K))
            if z.shape != (T, R, K):
                raise ValueError(f"zero: expected ({T}, {K}) or ({T}, {R}, {K}) bool, got {z.shape}")
            if not z.any():
                z = None
        if z is None and self.lower is None:
            return None
        lo = np.zeros(K) if self.lower is None else self.lower
        hi = np.ones(K) if self.upper is None else self.upper
        d0 = hi - lo
        held = np.clip(0.0, lo, hi)
        zz = np.zeros((T, R, K), bool) if z is None else z
        zz = zz | (d0 <= 0)[None, None]
        pats, zinv = np.unique(zz.reshape(-1, K), axis=0, return_inverse=True)
        zinv = np.asarray(zinv).ravel()
        combo, cinv = np.unique(np.column_stack([hidx.ravel(), zinv]), axis=0, return_inverse=True)
        cinv = np.asarray(cinv).ravel()
        Hu = np.empty((len(combo), K, K))
        starts = np.empty((len(combo), K))
        ds = np.empty((len(combo), K))
        for c, (h, p) in enumerate(combo):
            zr = pats[p]
            dz = np.where(zr, 0.0, d0)
            Hu[c] = Htab[h] * dz[:, None] * dz[None, :]
            Hu[c][zr, zr] = 1.0
            starts[c] = np.where(zr, np.where(d0 <= 0, lo, held), lo)
            ds[c] = dz
        st, dz = starts[cinv], ds[cinv]
        fl = f.reshape(-1, K)
        fu = dz * (hessian_products(Htab, hidx.ravel(), st) + fl)
        return Hu, fu.reshape(T, R, K), cinv.reshape(T, R), st.reshape(T, R, K), dz.reshape(T, R, K)


def local_precompute(neutral_markers, marker_deltas, marker_weights=None, constraint: str = "simplex",
                     ridge: float = 1e-9, quadratic=None, lower=None, upper=None) -> LocalProblem:
    """Precompute eq. 2's regional Hessians (Liu et al. 2011, §3.2.2).

    Parameters
    ----------
    neutral_markers : (M, 3) float
        s_0: marker positions on the neutral (metres).
    marker_deltas : (K, M, 3) float
        s_i − s_0 for every shape (``MarkerLayout.on_rig(rig)``).
    marker_weights : (R, M) float, optional
        Diagonals of M_k (:func:`core.segment.marker_weights`); default one region with all
        markers weighted 1 — the global problem, eq. 1.
    constraint : {"simplex", "box"}
        ``"simplex"`` is the paper (u ≥ 0, 1ᵀu ≤ 1); ``"box"`` is 0 ≤ u ≤ 1.
    ridge : float >= 0
        Relative Tikhonov term (see :class:`LocalProblem`).
    quadratic : (K, K) float, optional
        Relative symmetric PSD coupling Q (e.g. :func:`core.controls.symmetry_matrix`): region
        k's Hessian gains ``λ_max(Dᵀ M_k² D) Q`` (module docstring).
    lower, upper : float or (K,) float, optional
        Per-shape weight bounds of the ``"box"`` form (default the unit box [0, 1]); the
        ``"simplex"`` form has no per-shape bounds and refuses them.

    Returns
    -------
    LocalProblem

    Raises
    ------
    ValueError
        Shapes that disagree, negative weights or ridge, unknown constraint.
    """
    n = np.asarray(neutral_markers, dtype=np.float64)
    D = np.asarray(marker_deltas, dtype=np.float64)
    if n.ndim != 2 or n.shape[1] != 3:
        raise ValueError(f"neutral_markers: expected (M, 3), got {n.shape}")
    M = len(n)
    if D.ndim != 3 or D.shape[1:] != (M, 3):
        raise ValueError(f"marker_deltas: expected (K, {M}, 3), got {D.shape}")
    if len(D) == 0:
        raise ValueError("marker_deltas: need at least one shape")
    mw = np.ones((1, M)) if marker_weights is None else np.asarray(marker_weights, dtype=np.float64)
    if mw.ndim != 2 or mw.shape[1] != M:
        raise ValueError(f"marker_weights: expected (R, {M}), got {mw.shape}")
    if (mw < 0).any() or not np.isfinite(mw).all():
        raise ValueError("marker_weights: expected finite non-negative values")
    if constraint not in CONSTRAINTS:
        raise ValueError(f"constraint: expected one of {CONSTRAINTS}, got {constraint!r}")
    if not ridge >= 0:
        raise ValueError(f"ridge: expected >= 0, got {ridge}")
    K = len(D)
    lo = hi = None
    if lower is not None or upper is not None:
        if constraint != "box":
            raise ValueError("lower/upper: per-shape bounds need constraint='box' (the simplex form is u >= 0, "
                             "sum u <= 1)")
        lo = np.broadcast_to(np.asarray(0.0 if lower is None else lower, dtype=np.float64), (K,)).copy()
        hi = np.broadcast_to(np.asarray(1.0 if upper is None else upper, dtype=np.float64), (K,)).copy()
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (lo > hi).any():
            raise ValueError(f"lower/upper: expected finite per-shape bounds with lower <= upper, got {lower}, {upper}")
    for a in (n, D, mw):
        a.setflags(write=False)
    prob = LocalProblem(n, D, mw, constraint, float(ridge), np.empty((0, 0, 0)), lower=lo, upper=hi)
    if quadratic is not None:
        Q = as_coupling(quadratic, K, 1.0, "local_precompute")
        H0 = prob.hessians()
        scale = np.linalg.eigvalsh(H0)[:, -1]  # λ_max of every region's data term
        object.__setattr__(prob, "coupling", scale[:, None, None] * Q[None])
    H = prob.hessians()
    H.setflags(write=False)
    object.__setattr__(prob, "H", H)
    return prob


def solve_local(neutral_markers, marker_deltas, targets, marker_weights=None, constraint: str = "simplex",
                valid=None, ridge: float = 1e-9, **options) -> np.ndarray:
    """One-line form: ``local_precompute(...).solve(targets, valid)`` → (T, R, K); ``options``:
    :func:`local_precompute`'s ``quadratic``, ``lower``, ``upper``."""
    return local_precompute(neutral_markers, marker_deltas, marker_weights, constraint, ridge, **options).solve(targets, valid)


# ----------------------------------------------------------------------------------------
# synthesis and views of the regional weights
# ----------------------------------------------------------------------------------------
def _check_rw(region_weights, masks, K=None, V=None):
    U = np.asarray(region_weights, dtype=np.float64)
    B = np.asarray(masks, dtype=np.float64)
    if U.ndim != 3:
        raise ValueError(f"region_weights: expected (T, R, K), got {U.shape}")
    if B.ndim != 2 or len(B) != U.shape[1]:
        raise ValueError(f"masks: expected (R, V) with R={U.shape[1]} to match region_weights, got {B.shape}")
    if K is not None and U.shape[2] != K:
        raise ValueError(f"region_weights: last axis must be K={K}, got {U.shape[2]}")
    if V is not None and B.shape[1] != V:
        raise ValueError(f"masks: expected {V} columns (the rig's vertices), got {B.shape[1]}")
    return U, B


def synthesize(rig: Rig, region_weights, masks) -> np.ndarray:
    """Meshes from regional weights by mask blending (Liu et al. 2011, eq. 3).

    ``x_t = Σ_k B_k S̄ w_{t,k} = n + Σ_k B_k (D̄ u_{t,k})`` (the masks sum to 1 per vertex).

    Parameters
    ----------
    rig : Rig with K shapes and V vertices
    region_weights : (T, R, K) delta weights per region
    masks : (R, V) soft masks

    Returns
    -------
    (T, V, 3) float64 — T·V·3·8 bytes: call on frame ranges for long takes.
    """
    U, B = _check_rw(region_weights, masks, rig.n_shapes, rig.n_vertices)
    T, R, K = U.shape
    V = rig.n_vertices
    out = np.broadcast_to(rig.neutral, (T, V, 3)).copy()
    flat = rig.deltas.reshape(K, V, 3)
    for k in range(R):
        sup = np.flatnonzero(B[k] > 0)  # masks are mostly zero away from their region
        if len(sup) == 0:
            continue
        disp = (U[:, k] @ flat[:, sup].reshape(K, -1)).reshape(T, len(sup), 3)
        out[:, sup] += B[k, sup][None, :, None] * disp
    return out


def masks_at(layout: MarkerLayout, masks) -> np.ndarray:
    """Mask values at the markers (barycentric interpolation): (R, V) → (R, M)."""
    B = np.asarray(masks, dtype=np.float64)
    return np.einsum("rmj,mj->rm", B[:, layout.vertices], layout.weights)


def reconstruct_markers(neutral_markers, marker_deltas, region_weights, marker_masks) -> np.ndarray:
    """Eq. 3 evaluated at the markers: ``p_q = s_0q + Σ_k B_k(q) Σ_i u_{k,i} d_iq``.

    Parameters
    ----------
    neutral_markers : (M, 3); marker_deltas : (K, M, 3); region_weights : (T, R, K);
    marker_masks : (R, M) — :func:`masks_at`.

    Returns
    -------
    (T, M, 3)
    """
    U = np.asarray(region_weights, dtype=np.float64)
    Bm = np.asarray(marker_masks, dtype=np.float64)
    D = np.asarray(marker_deltas, dtype=np.float64)
    if Bm.shape != (U.shape[1], D.shape[1]):
        raise ValueError(f"marker_masks: expected (R, M) = {(U.shape[1], D.shape[1])}, got {Bm.shape}")
    return np.asarray(neutral_markers)[None] + np.einsum("trk,rm,kmc->tmc", U, Bm, D, optimize=True)


def blend_weights(region_weights, masks, areas=None) -> np.ndarray:
    """One global weight curve per shape: the mask-area-weighted mean of the regions.

    ``w̄_t = Σ_k a_k u_{t,k} / Σ_k a_k`` with ``a_k = Σ_v A_v B_k(v)`` (A_v the vertex area
    if ``areas`` is given, else 1). A summary for curve views and export to tools without
    regions; it does *not* reproduce the local result when applied globally.

    Parameters
    ----------
    region_weights : (T, R, K); masks : (R, V); areas : (V,), optional

    Returns
    -------
    (T, K)
    """
    U, B = _check_rw(region_weights, masks)
    a = B @ (np.ones(B.shape[1]) if areas is None else np.asarray(areas, dtype=np.float64))
    a = a / max(a.sum(), 1e-300)
    return np.einsum("trk,r->tk", U, a)


def smooth_weights(region_weights, sigma: float) -> np.ndarray:
    """Temporal Gaussian filter of the weights (Liu et al. 2011, §7), frames on axis 0.

    ``scipy.ndimage.gaussian_filter1d(U, sigma, axis=0, mode="nearest")``. The kernel is
    non-negative and sums to 1, so every output frame is a convex combination of input
    frames and stays inside the (convex) feasible set: bounds and 1ᵀu ≤ 1 are preserved.

    Parameters
    ----------
    region_weights : (T, ...) float
    sigma : float >= 0, in frames (0 returns a copy)
    """
    U = np.asarray(region_weights, dtype=np.float64)
    if not sigma >= 0:
        raise ValueError(f"sigma: expected >= 0 frames, got {sigma}")
    if sigma == 0 or len(U) < 2:
        return U.copy()
    out = gaussian_filter1d(U, float(sigma), axis=0, mode="nearest")
    # the kernel sums to 1 only up to rounding: a weight at its bound came out 1 ulp past it
    # (1.0000000000000002 with scipy 1.17); a convex combination lies within its inputs' range
    return np.clip(out, U.min(axis=0), U.max(axis=0), out=out)


def region_curves(region_weights, shape_names: Sequence[str], region_names: Optional[Sequence[str]] = None) -> dict:
    """Per-region weight curves for export: ``{"<shape>@<region>": (T,) array}``.

    Region names default to ``r0, r1, …``.
    """
    U = np.asarray(region_weights, dtype=np.float64)
    T, R, K = U.shape
    if len(shape_names) != K:
        raise ValueError(f"shape_names: expected {K} names, got {len(shape_names)}")
    region_names = list(region_names) if region_names is not None else [f"r{k}" for k in range(R)]
    if len(region_names) != R:
        raise ValueError(f"region_names: expected {R} names, got {len(region_names)}")
    return {f"{s}@{r}": U[:, k, i].copy() for k, r in enumerate(region_names) for i, s in enumerate(shape_names)}


def local_spacetime(marker_deltas, source_deltas, marker_weights, per_frame, alpha: float = 0.01, beta: float = 0.0,
                    valid=None, quadratic=None) -> np.ndarray:
    """Local spacetime retargeting: Seol et al. 2012 movement matching inside each region.

    For region k the spacetime energy is evaluated on markers weighted by ``m_k`` (the
    diagonal of M_k, Liu 2011 §3.2.2): ``B_k = M_k B``, ``S_k = M_k S``, so region k follows
    the movement of its own markers; the PCA prior is the one of ``B_k``'s shapes. The first
    and last frames are fixed to the per-frame regional solution, and the result is
    unconstrained in between (movement matching has no bounds). A region whose markers all
    have (numerically) zero weight, or whose weighted shapes do not move, keeps the
    per-frame solution.

    Parameters
    ----------
    marker_deltas : (K, M, 3); source_deltas : (T, M, 3); marker_weights : (R, M)
    per_frame : (T, R, K) the per-frame regional solution (eq. 2): end frames and fallback
    alpha, beta : spacetime prior and Sobolev weights (see :class:`SpacetimeSolver`)
    valid : (T, M) bool, optional
    quadratic : (K, K), optional — relative coupling (symmetry) of each region's solve, as
        :class:`SpacetimeSolver`'s ``quadratic`` (relative to that region's weighted markers)

    Returns
    -------
    (T, R, K) regional weights
    """
    D = np.asarray(marker_deltas, dtype=np.float64)
    S = np.asarray(source_deltas, dtype=np.float64)
    mw = np.asarray(marker_weights, dtype=np.float64)
    T, R = len(S), len(mw)
    U = np.asarray(per_frame, dtype=np.float64)
    out = U.copy()
    for r in range(R):
        if mw[r].max() <= 1e-9 * max(mw.max(), 1e-300):
            continue
        g = np.sqrt(mw[r])[:, None]
        try:
            solver = SpacetimeSolver(D * g[None], S * g[None], alpha=alpha, beta=beta, valid=valid,
                                     known={0: U[0, r], T - 1: U[-1, r]}, quadratic=quadratic)
        except ValueError:  # the region's weighted shapes do not move: nothing to match
            continue
        out[:, r] = solver.solve()
    return out
