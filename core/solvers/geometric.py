"""Per-frame retargeting with the geometric prior and ℓ1 sparsity (Ribera et al. 2017, §5).

For every frame f, with the actor's (personalised) sparse blendshapes Δp_k as the columns of
P (3M × K) and the frame's marker displacements Δa_f (3M):

    E(w) = 1/M ‖Δa_f − P w‖²  +  μ/N ‖L ΔV w‖²  +  λ/K ‖w‖₁                  (eq. 2, 15, 16)

L is the (3N × 3N) cotangent Laplacian of the rig's neutral mesh (one (N × N) block per
coordinate, :func:`core.geometry.cotangent_laplacian`) and ΔV the rig's (3N × K) dense
deltas, so the prior only needs the (K × K) Gram matrix Q = (LΔV)ᵀ(LΔV)/N, computed once per
rig (§5: "we pre-compute the matrix product LΔV"). The paper's μ = 0.3, λ = 0.6 hold for
markers in centimetres.

The paper leaves the weights **unbounded**: it pairs ℓ1 with its prior precisely because valid
expressions can need negative weights (§6.2: "less restrictive than non-negativity
constraints"). That is ``lower = upper = None`` here; with per-shape bounds ``lower ≤ w ≤
upper`` (the pipeline's default, from the per-shape controls) the same energy is minimised
exactly inside them (*Bounds* below). The three priors of Fig. 14 are selectable: ``"geometric"`` (the above),
``"pca"`` (any quadratic wᵀPw + 2qᵀw, e.g. ``core.prior.PCAPrior``'s ``P_``, ``q_``) and
``"l2"`` (‖w‖², the elastic net); ``"none"`` keeps only ℓ1.

Units
-----
Everything inside is in metres. With s the metres per unit the weights are quoted for (s =
0.01 for the paper's cm), lengths scale as x_m = s x_cm, so E_Fit and the geometric prior
(the cotangent Laplacian is dimensionless, L ΔV w is a length) scale by s² while ‖w‖₁ does
not. Minimisers agree when

    λ_m = s² λ_cm,   μ_m = μ_cm                (geometric prior)
    μ_m = s² μ_cm                               (PCA and L2 priors: they are on weights)

which :func:`effective_weights` applies: λ = 0.6 for cm becomes 6e-5 for metres. (The prior
is normalised by the vertex count N as in eq. 15; ‖L x‖² per vertex still depends on the
mesh resolution, so μ transfers between rigs of similar density only.)

ℓ1 by IRLS (unbounded)
----------------------
|w_k| ≤ w_k²/(2|w_k⁰|) + |w_k⁰|/2 turns each step into a (K × K) linear solve. Written with
H = PᵀP/M + μQ, b = PᵀΔa/M − μq, c = λ/(2K) and D = diag(|w⁰|), w = D^½ z,

    (D^½ H D^½ + c I) z = D^½ b,

which stays well conditioned when weights go to 0. All frames iterate in lock-step as
batched numpy.linalg.solve calls on (T, k, k); a weight below ``drop`` × the frame's largest
is frozen at 0 and leaves the frame's system, so k shrinks to the support size. IRLS only
has to find the support: a *polish* then solves the exact optimality conditions on the
support S with signs σ, H_SS w_S = b_S − c σ_S, checks the KKT conditions
(sign(w_S) = σ_S, |(b − Hw)_k| ≤ c off S) and repairs the active set where they fail (a
few rounds, all frames at once). Polished frames (``Solution.polished``) hold the exact ℓ1
optimum, not an ε-smoothed one; the tests compare it with L-BFGS-B on the split
w = w⁺ − w⁻.

Bounds
------
With ``lower ≤ w ≤ upper`` (per shape) eq. 16 is minimised over the box: a convex QP per frame.
Halved and with H, b, c as above, the energy is ½wᵀHw − bᵀw + c‖w‖₁ + const.
Every shape is written as
``w_k = base_k + Σ_j a_j z_j`` with ``z ∈ [0, 1]``, columns pointing away from 0 so that
``|w_k| = |base_k| + Σ_j |a_j| z_j`` on the feasible set:

* ``lower ≥ 0``: ``base = lower``, one column ``a = upper − lower`` (ℓ1 is linear, +c);
* ``upper ≤ 0``: ``base = upper``, one column ``a = lower − upper`` (ℓ1 is linear, −c);
* ``lower < 0 < upper`` and c > 0 (the kink inside the box): the split ``w = p − n``,
  ``base = 0`` and two columns ``a = upper`` (p ∈ [0, upper]) and ``a = lower`` (n ∈ [0, −lower]).
  ``p + n ≥ |p − n|``, so the split problem has the same minimum; it is exact, not a bound;
* ``lower == upper``: fixed, no column.

Each frame is then the unit-box QP ``min ½zᵀ(AᵀHA)z + (Aᵀ(H base − b) + c|a|)ᵀz`` (A: the
columns), solved for all frames by the compiled parametric active-set method of
:func:`core.solvers.boxqp.solve_box_sequence` (the one behind ``range_pf`` and the local
method's box), each frame warm-started from the previous one, every frame's KKT conditions
checked. ``AᵀHA`` is singular when a split shape has both columns, but never on a free set:
the scaled multipliers of a split pair sum to ``2c > 0`` along the whole homotopy (also from a
cold or warm start), so p and n are never free together and every factorised block is a
principal submatrix of H (the solver factorises free blocks only). A singular H (shapes no marker and no prior
sees) gets the spacetime solver's relative ridge ``AUTO_RIDGE · λ_max(H)`` (``ridge_``) for the
bounded solve, as ``range_pf`` does: the minimiser is then the ridged energy's (unique). The result is checked once more against the optimality conditions
of eq. 16 in w (:func:`core.solvers.bounded_spacetime.kkt_violation`, including the kink at 0);
``Solution.polished`` marks frames whose violation is at most ``KKT_RTOL`` relative to
``‖H‖₂ max(1, max|w|) + max|b| + c``, and ``extras["kkt"]`` holds the largest.

Production controls (:mod:`core.controls`), off by default
----------------------------------------------------------
``quadratic`` C (K × K, PSD, e.g. the symmetry term of :func:`core.controls.symmetry_matrix`)
adds ``s_P wᵀCw`` with ``s_P = σ_max(P)²/M`` (relative to the data term, as the other solvers'
relative weights): it joins H, so IRLS and the polish are unchanged. ``zero`` in
:meth:`GeometricSolver.solve` holds weights at 0: they never enter a frame's support (the
first iterate, IRLS and the polish's active set all skip them), which is the exact optimum of
eq. 16 with those weights fixed. With bounds a held weight sits at ``clip(0, lower, upper)``
(as in ``range_pf``): its columns become identity rows of the unit-box Hessian, one Hessian
per pattern of held weights.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import numpy as np

from core.geometry import cotangent_laplacian
from core.model import unit_scale
from core.solvers.bounded_spacetime import KKT_RTOL, kkt_violation_per_entry
from core.solvers.boxqp import solve_box_sequence
from core.solvers.inputs import as_bounds, as_coupling
from core.solvers.spacetime import AUTO_RIDGE

#: Ribera 2017 §5 recommendations, for markers in centimetres
MU = 0.3
LAMBDA = 0.6
PRIORS = ("geometric", "pca", "l2", "none")


def laplacian_deltas(rig, laplacian=None):
    """L ΔV of eq. 15 as (K, N, 3): the cotangent Laplacian of the neutral applied to every delta.

    Parameters
    ----------
    rig : core.model.Rig
    laplacian : (N, N) sparse, optional
        Default :func:`core.geometry.cotangent_laplacian` of ``rig.neutral`` (positive
        semi-definite convention; the sign does not matter here, only ‖L ΔV w‖²).

    Returns
    -------
    (K, N, 3) float64
    """
    N = rig.n_vertices
    L = cotangent_laplacian(rig.neutral, rig.faces) if laplacian is None else laplacian
    if L.shape != (N, N):
        raise ValueError(f"laplacian: expected shape ({N}, {N}) for rig {rig.name!r}, got {L.shape}")
    K = rig.n_shapes
    LD = L @ rig.deltas.transpose(1, 0, 2).reshape(N, 3 * K)
    return np.ascontiguousarray(np.asarray(LD).reshape(N, K, 3).transpose(1, 0, 2))


def geometric_gram(rig, laplacian=None):
    """Q = (L ΔV)ᵀ (L ΔV) / N, the (K, K) matrix of the geometric prior (Ribera 2017 eq. 15).

    E_Prior(w) = wᵀ Q w = ‖L ΔV w‖² / N, in (rig units)²: metres² for our rigs.

    Parameters
    ----------
    rig : core.model.Rig
    laplacian : (N, N) sparse, optional

    Returns
    -------
    (K, K) float64, symmetric positive semi-definite.
    """
    LD = laplacian_deltas(rig, laplacian).reshape(rig.n_shapes, -1)
    Q = LD @ LD.T / rig.n_vertices
    return 0.5 * (Q + Q.T)


def effective_weights(mu=MU, lam=LAMBDA, units="cm", prior="geometric"):
    """(μ, λ) for data in metres from values quoted for data in ``units`` (see module docstring).

    ``λ_m = s² λ``; ``μ_m = μ`` for the geometric prior, ``s² μ`` for PCA/L2 priors, with
    ``s = unit_scale(units)`` metres per unit.

    Raises
    ------
    ValueError
        Unknown units or prior.
    """
    if prior not in PRIORS:
        raise ValueError(f"prior: expected one of {PRIORS}, got {prior!r}")
    s2 = unit_scale(units) ** 2
    return (float(mu) if prior == "geometric" else float(mu) * s2), float(lam) * s2


@dataclass(frozen=True, eq=False)
class Solution:
    """Weights and diagnostics of :meth:`GeometricSolver.solve`.

    Attributes
    ----------
    weights : (T, K)
    energy : (T,) E(w) of eq. 16 (in metres², with the effective μ, λ)
    iterations : int, IRLS iterations run
    polished : (T,) bool, frames whose weights satisfy the exact ℓ1 optimality conditions
    """

    weights: np.ndarray
    energy: np.ndarray
    iterations: int
    polished: np.ndarray
    extras: dict = field(default_factory=dict)


class GeometricSolver:
    """Retarget marker frames onto blendshape weights by eq. 16 (Ribera et al. 2017 §5).

    State that is reused across frames lives here: H = PᵀP/M + μ Q and the prior.

    Parameters
    ----------
    blendshapes : (K, M, 3) float
        The actor's sparse delta blendshapes Δp_k (metres), e.g. from
        :func:`core.personalize.personalize`.
    prior : {"geometric", "pca", "l2", "none"}
    rig : core.model.Rig, optional
        Needed for ``"geometric"`` unless ``gram`` is given.
    gram : (K, K) float, optional
        Precomputed :func:`geometric_gram` (or, for ``"pca"``, the prior's P).
    linear : (K,) float, optional
        q of the ``"pca"`` quadratic wᵀPw + 2qᵀw (default 0).
    mu, lam : float
        Prior and sparsity weights as quoted for ``units`` (paper: 0.3, 0.6 for cm).
    units : str
        Units ``mu`` and ``lam`` are quoted for; scaled to metres by :func:`effective_weights`.
    drop : float
        A weight below ``drop`` × the frame's largest |w| is frozen at 0 during IRLS (its
        1/|w| weight would otherwise only push it towards 0 geometrically, one iteration at a
        time); the polish re-admits it if the optimality conditions ask for it.
    max_iter : int
        IRLS iterations at most; IRLS only has to find the support, the polish does the rest.
    tol : float
        IRLS stops for a frame when no weight changes by more than ``tol`` × max(1, max|w|).
    polish : bool
        Finish with the exact support/sign solve (module docstring).
    quadratic : (K, K) float, optional
        Relative symmetric PSD coupling C: ``σ_max(P)²/M · wᵀCw`` joins the energy (module
        docstring); the absolute matrix is ``coupling_``.
    lower, upper : float or (K,) float, optional
        Per-shape bounds ``lower ≤ w ≤ upper`` (finite, ``lower ≤ upper``; equal = fixed),
        solved exactly (module docstring, *Bounds*). Both None (default): the paper's
        unbounded eq. 16 by IRLS + polish.

    Attributes
    ----------
    columns_ : tuple (shape (n,) int, coefficient (n,) float, base (K,) float) or None
        The bounded solve's change of variables w = base + A z (module docstring).
    ridge_ : float
        ``AUTO_RIDGE · λ_max(H)`` added to H by the bounded solve when H is singular, else 0.

    Raises
    ------
    ValueError
        Bad shapes, unknown prior, a geometric prior without rig/gram, a rig whose shape count
        differs from K, negative weights μ/λ, only one of lower/upper, bounds that are not
        finite, of the wrong shape or with lower > upper.
    """

    def __init__(self, blendshapes, prior="geometric", rig=None, gram=None, linear=None,
                 mu=MU, lam=LAMBDA, units="cm", drop=0.05, max_iter=5, tol=1e-6, polish=True, greedy_rounds=3,
                 quadratic=None, lower=None, upper=None):
        P = np.asarray(blendshapes, dtype=np.float64)
        if P.ndim != 3 or P.shape[2] != 3:
            raise ValueError(f"blendshapes: expected (K, M, 3), got {P.shape}")
        if not np.isfinite(P).all():
            raise ValueError("blendshapes: contain NaN/inf")
        if prior not in PRIORS:
            raise ValueError(f"prior: expected one of {PRIORS}, got {prior!r}")
        if mu < 0 or lam < 0:
            raise ValueError(f"mu and lam must be >= 0, got mu={mu}, lam={lam}")
        K, M, _ = P.shape
        self.K, self.M = K, M
        self.prior = prior
        self.mu, self.lam = effective_weights(mu, lam, units, prior)
        self.drop, self.max_iter, self.tol, self.polish = float(drop), int(max_iter), float(tol), bool(polish)
        self.greedy_rounds = int(greedy_rounds)
        self.P = P.reshape(K, -1).T.copy()  # (3M, K): the paper's P, x0 y0 z0 x1 ...
        q = np.zeros(K)
        if prior == "geometric":
            if gram is None:
                if rig is None:
                    raise ValueError("prior='geometric' needs rig= (or a precomputed gram=)")
                if rig.n_shapes != K:
                    raise ValueError(f"rig {rig.name!r} has {rig.n_shapes} shapes but blendshapes has K={K}")
                gram = geometric_gram(rig)
            Q = np.asarray(gram, dtype=np.float64)
        elif prior == "pca":
            if gram is None:
                raise ValueError("prior='pca' needs gram= (the prior's (K, K) quadratic P_)")
            Q = np.asarray(gram, dtype=np.float64)
            if linear is not None:
                q = np.asarray(linear, dtype=np.float64)
        elif prior == "l2":
            Q = np.eye(K)
        else:
            Q = np.zeros((K, K))
        if Q.shape != (K, K) or q.shape != (K,):
            raise ValueError(f"gram/linear: expected ({K}, {K}) and ({K},), got {Q.shape} and {q.shape}")
        self.Q = 0.5 * (Q + Q.T)
        self.q = q
        self.coupling_ = None
        if quadratic is not None:
            scale = float(np.linalg.norm(self.P, 2) ** 2) / M if self.P.size else 0.0
            self.coupling_ = as_coupling(quadratic, K, scale, "GeometricSolver")
        self.H = self.P.T @ self.P / M + self.mu * self.Q
        if self.coupling_ is not None:
            self.H = self.H + self.coupling_
        self.c = self.lam / (2.0 * K)  # the ℓ1 weight in the halved gradient
        self.lower = self.upper = self.columns_ = None
        if (lower is None) != (upper is None):
            raise ValueError("GeometricSolver: give both lower and upper (bounded) or neither (the paper's unbounded "
                             f"eq. 16), got lower={lower}, upper={upper}")
        self.ridge_ = 0.0
        if lower is not None:
            self.lower, self.upper = as_bounds(lower, upper, K, "GeometricSolver", finite=True)
            self.columns_ = _columns(self.lower, self.upper, self.c)
            try:
                np.linalg.cholesky(self.H)
            except np.linalg.LinAlgError:  # shapes nothing sees: the spacetime solver's relative ridge
                self.ridge_ = AUTO_RIDGE * max(float(np.linalg.eigvalsh(self.H)[-1]), 1e-300)

    # -- pieces ---------------------------------------------------------------------------
    def rhs(self, frames):
        """b = PᵀΔa/M − μ q for frames (T, M, 3) -> (T, K)."""
        A = self._frames(frames)
        return A @ self.P / self.M - self.mu * self.q

    def _frames(self, frames):
        A = np.asarray(frames, dtype=np.float64)
        if A.ndim == 2 and A.shape == (self.M, 3):
            A = A[None]
        if A.ndim != 3 or A.shape[1:] != (self.M, 3):
            raise ValueError(f"frames: expected marker displacements (T, {self.M}, 3), got {A.shape}")
        if not np.isfinite(A).all():
            bad = np.flatnonzero(~np.isfinite(A).all(axis=(1, 2)))
            raise ValueError(f"frames: frames {bad[:8].tolist()}{'...' if len(bad) > 8 else ''} contain NaN; "
                             "fill or drop missing markers before solving")
        return A.reshape(len(A), -1)

    def energy(self, frames, weights):
        """E(w) of eq. 16 per frame (effective μ, λ): 1/M‖Δa − Pw‖² + μ(wᵀQw + 2qᵀw) + λ/K‖w‖₁."""
        A = self._frames(frames)
        W = np.asarray(weights, dtype=np.float64).reshape(len(A), self.K)
        r = A - W @ self.P.T
        e = (np.einsum("ij,ij->i", r, r) / self.M
             + self.mu * (np.einsum("ij,jk,ik->i", W, self.Q, W) + 2 * W @ self.q)
             + self.lam / self.K * np.abs(W).sum(axis=1))
        if self.coupling_ is not None:
            e = e + np.einsum("ij,jk,ik->i", W, self.coupling_, W)
        return e

    # -- solve ----------------------------------------------------------------------------
    def solve(self, frames, zero=None) -> Solution:
        """Weights (T, K) minimising eq. 16 for every frame, all frames at once.

        IRLS (module docstring) on all frames in lock-step; a coordinate whose weight has
        fallen below ``drop`` × the frame's largest weight is frozen at 0 and dropped from the
        frame's system, so later iterations solve small padded (T, k, k) systems with k the
        largest support. The polish then makes the result exact (KKT-checked). With bounds
        (``lower``/``upper`` given) the frames are instead solved within them by the warm-started
        batched box QP (module docstring, *Bounds*); ``iterations`` is then 0, ``extras`` holds
        ``kkt`` (largest relative violation) and ``boxqp`` (the box solver's counters).

        Parameters
        ----------
        frames : (T, M, 3) or (M, 3) float
            Marker displacements from the neutral (metres), markers in the blendshapes' order.
        zero : (K,) or (T, K) bool, optional
            Weights held at 0 (at ``clip(0, lower, upper)`` when bounded; module docstring): an
            active set's off shapes, a cancel pair's weaker shape.

        Returns
        -------
        Solution

        Raises
        ------
        ValueError
            Wrong shape or NaN in ``frames``.
        """
        b = self.rhs(frames)
        T, K = b.shape
        H, c = self.H, self.c
        free = None
        if zero is not None:
            z = np.asarray(zero)
            if z.dtype != bool or z.shape not in ((K,), (T, K)):
                raise ValueError(f"zero: expected a ({K},) or ({T}, {K}) bool mask, got {z.dtype} {z.shape}")
            free = ~np.broadcast_to(z, (T, K))
            if free.all():
                free = None
        if self.columns_ is not None:
            return self._solve_bounded(frames, b, free)
        if c == 0.0 or T == 0:  # no ℓ1: one linear solve
            if free is not None:
                W = _reduced_solve(H, free, np.ones((T, K)), 0.0, b)
            else:
                W = np.linalg.solve(H, b.T).T if T else np.zeros((0, K))
            return Solution(W, self.energy(frames, W), 0, np.ones(T, bool))
        W, it, unconverged = self._irls(b, self.drop, self.max_iter, free)
        polished = np.zeros(T, bool)
        if self.polish:
            W, polished = self._polish(W, b, free=free)
            if not polished.all():  # rare: retry those frames with plain, long IRLS
                rows = np.flatnonzero(~polished)
                fr = None if free is None else free[rows]
                W2, _, _ = self._irls(b[rows], 1e-12, 50 * self.max_iter, fr)
                W2, ok2 = self._polish(W2, b[rows], free=fr)
                W[rows] = W2
                polished[rows] = ok2
        return Solution(W, self.energy(frames, W), it, polished, {"unconverged": unconverged})

    def _solve_bounded(self, frames, b, free):
        """Eq. 16 within ``lower ≤ w ≤ upper`` (module docstring, *Bounds*) for all frames."""
        T, K = b.shape
        lo, hi, c = self.lower, self.upper, self.c
        kcol, a, base = self.columns_
        held = np.broadcast_to(np.clip(0.0, lo, hi), (T, K))
        W = np.broadcast_to(base, (T, K)).copy()
        info = {}
        if len(kcol) and T:
            H = self.H + self.ridge_ * np.eye(K)
            # one unit-box Hessian per pattern of held weights; a held column is an identity row with
            # f = c|a| (> 0, so z = 0 with a positive multiplier: a split pair's multipliers keep
            # their sum when a frame of another pattern starts from this one)
            if free is None:
                pats, pidx = np.zeros((1, K), bool), np.zeros(T, np.int64)
            else:
                pats, pidx = np.unique(~free, axis=0, return_inverse=True)
                pidx = np.asarray(pidx).ravel()
            Hz = H[np.ix_(kcol, kcol)] * a[:, None] * a[None, :]
            Htab, lin, bases = [], [], []
            for pat in pats:
                bp = np.where(pat, held[0], base)
                hc = pat[kcol]
                Hp = np.where(hc[:, None] | hc[None, :], 0.0, Hz)
                Hp[hc, hc] = 1.0
                Htab.append(Hp)
                lin.append(np.where(hc, 0.0, a * (H @ bp)[kcol]) + c * np.abs(a))
                bases.append(bp)
            hcol = np.asarray(pats)[pidx][:, kcol]
            f = np.asarray(lin)[pidx] - np.where(hcol, 0.0, b[:, kcol] * a)
            Z, info = solve_box_sequence(np.asarray(Htab), f, pidx, return_info=True)
            W = np.asarray(bases)[pidx]
            np.add.at(W.T, kcol, (Z * a).T)  # the two columns of a split shape add up
            # a column at its far end puts the weight exactly on the bound (base + a rounds)
            single = np.bincount(kcol, minlength=K)[kcol] == 1
            far = np.where(a > 0, hi[kcol], lo[kcol])
            top = (Z == 1.0) & single & ~hcol
            W[:, kcol] = np.where(top, far, W[:, kcol])
            W = np.clip(W, lo, hi)
        if free is not None:
            W = np.where(free, W, held)
        kkt = self._kkt(b, W, free)
        return Solution(W, self.energy(frames, W), 0, kkt <= KKT_RTOL,
                        {"kkt": float(kkt.max(initial=0.0)), "boxqp": info})

    def _kkt(self, b, W, free=None):
        """(T,) relative violation of eq. 16's optimality conditions within the bounds (module docstring)."""
        T, K = W.shape
        lo = np.full(K, -np.inf) if self.lower is None else self.lower
        hi = np.full(K, np.inf) if self.upper is None else self.upper
        H = self.H + self.ridge_ * np.eye(K)
        g = 2.0 * (W @ H - b)  # dE/dw of the smooth terms (H symmetric)
        v = kkt_violation_per_entry(W, g, lo, hi, np.full(K, 2.0 * self.c), 2.0 * np.linalg.norm(H, 2))
        v = np.where((hi > lo) if free is None else free & (hi > lo), v, 0.0)  # held and fixed weights are constraints
        scale = 2.0 * (np.linalg.norm(H, 2) * np.maximum(1.0, np.abs(W).max(axis=1, initial=0.0))
                       + np.abs(b).max(axis=1, initial=0.0) + self.c)
        return v.max(axis=1, initial=0.0) / scale

    def _irls(self, b, drop, max_iter, free=None):
        T, K = b.shape
        H, c = self.H, self.c
        # first iterate (|w0| = 1 for all k): one matrix, T right-hand sides (held weights left out;
        # IRLS keeps a zero weight at zero, so they stay held)
        if free is None:
            W = np.linalg.solve(H + c * np.eye(K), b.T).T
        else:
            W = _reduced_solve(H, free, np.ones((T, K)), c, b)
        active = np.arange(T)
        it = 0
        for it in range(1, max_iter + 1):
            if not len(active):
                break
            Wa = W[active]
            scale = np.maximum(np.abs(Wa).max(axis=1, keepdims=True), 1e-300)
            on = np.abs(Wa) > drop * scale
            d = np.sqrt(np.abs(Wa))
            # (D^1/2 H D^1/2 + c I) z = D^1/2 b on each frame's support only
            new = _reduced_solve(H, on, d, c, d * b[active])
            new *= d
            change = np.abs(new - Wa).max(axis=1)
            W[active] = new
            active = active[change > self.tol * np.maximum(scale[:, 0], 1.0)]
        return W, it, int(len(active))

    def _polish(self, W, b, rounds=30, free=None):
        """Exact ℓ1 optimum from the IRLS support and signs, by active-set rounds.

        Each round solves H_SS w_S = b_S − c σ_S (c = λ/2K) for every frame at once, then
        checks the KKT conditions of eq. 16: sign(w_S) = σ_S and |(b − Hw)_k| ≤ c off S.
        Frames that fail drop the coordinates whose sign flipped, take in the violators off S
        (all of them in the first round, the worst one afterwards) with the sign of their
        gradient, and try again. Frames still failing after ``rounds`` keep their IRLS weights
        (``Solution.polished`` is False there).
        """
        T, K = W.shape
        H, c = self.H, self.c
        scale = np.maximum(np.abs(W).max(axis=1, keepdims=True), 1e-300)
        on = np.abs(W) > self.drop * scale
        sign = np.sign(W) * on
        out = W.copy()
        done = np.zeros(T, bool)
        todo = np.arange(T)
        tol = 1e-9 * (np.abs(b).max(axis=1) + c)
        for rnd in range(rounds):
            if not len(todo):
                break
            o, sg, bb = on[todo], sign[todo], b[todo]
            Wp = _reduced_solve(H, o, np.ones_like(bb), 0.0, bb - c * sg)
            g = bb - Wp @ H  # H symmetric
            flipped = o & (np.sign(Wp) != sg)
            viol = ~o & (np.abs(g) > c + tol[todo, None])
            if free is not None:
                viol &= free[todo]
            ok = ~flipped.any(axis=1) & ~viol.any(axis=1)
            out[todo[ok]] = Wp[ok]
            done[todo[ok]] = True
            bad = ~ok
            o2 = o[bad] & ~flipped[bad]
            gb = g[bad]
            if rnd < self.greedy_rounds:
                add = viol[bad]
            else:
                excess = np.where(viol[bad], np.abs(gb) - c, -np.inf)
                add = np.zeros_like(o2)
                rows = np.flatnonzero(np.isfinite(excess.max(axis=1)))
                add[rows, excess[rows].argmax(axis=1)] = True
            sg2 = np.where(add, np.sign(gb), sg[bad] * o2)
            on[todo[bad]] = o2 | add
            sign[todo[bad]] = sg2
            todo = todo[bad]
        return out, done


def _columns(lower, upper, c):
    """``w = base + A z``, z ∈ [0, 1] (module docstring, *Bounds*): (shape of each column (n,),
    coefficient (n,), base (K,)); columns point away from 0, so ``|w| = |base| + Σ |a_j| z_j``."""
    move = upper > lower
    split = move & (c > 0) & (lower < 0) & (upper > 0)
    neg = move & ~split & (upper <= 0)
    base = np.where(split, 0.0, np.where(neg, upper, lower))
    one = np.flatnonzero(move)
    a = np.where(split, upper, np.where(neg, lower - upper, upper - lower))[one]
    two = np.flatnonzero(split)
    return np.concatenate([one, two]), np.concatenate([a, lower[two]]), base


def _reduced_solve(H, on, d, c, rhs):
    """Solve (d_S d_Sᵀ ∘ H_SS + c I) x_S = rhs_S per frame, x = 0 off S.

    ``on`` (T, K) bool selects each frame's S. Frames are bucketed by |S| (rounded up to a
    multiple of 8) and each bucket's systems gathered into a padded (n, k, k) batch for
    numpy.linalg.solve (padding rows are identity). Hand-written: numpy/scipy have no batched
    solve over per-item index subsets.
    """
    T, K = on.shape
    out = np.zeros((T, K))
    if T == 0:
        return out
    size = on.sum(axis=1)
    bucket = np.minimum(-(-size // 8) * 8, K)
    for k in np.unique(bucket):
        k = int(k)
        rows = np.flatnonzero(bucket == k)
        if k == 0:
            continue
        o = on[rows]
        order = np.argsort(~o, axis=1, kind="stable")[:, :k]  # support indices first
        valid = np.take_along_axis(o, order, axis=1)
        ds = np.take_along_axis(d[rows], order, axis=1) * valid
        Hs = H[order[:, :, None], order[:, None, :]] * (ds[:, :, None] * ds[:, None, :])
        idx = np.arange(k)
        Hs[:, idx, idx] += c + ~valid  # c I, and identity on padding
        r = np.take_along_axis(rhs[rows], order, axis=1) * valid
        x = np.linalg.solve(Hs, r[..., None])[..., 0] * valid
        sub = np.zeros((len(rows), K))
        np.put_along_axis(sub, order, x, axis=1)
        out[rows] = sub
    return out


def solve_geometric(blendshapes, frames, prior="geometric", **kw) -> Solution:
    """One-line form of :class:`GeometricSolver`: ``GeometricSolver(blendshapes, prior, **kw).solve(frames)``."""
    return GeometricSolver(blendshapes, prior, **kw).solve(frames)
