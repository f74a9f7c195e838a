"""Spacetime expression cloning: whole-sequence movement matching (Seol et al. 2012, §4–7).

Minimise over the weights ``W`` (T, K), given target marker blendshapes ``B`` and source marker
deltas ``S`` (T, M, 3)::

    E(W) = sum_t ||B (w_t - w_{t-1}) - (s_t - s_{t-1})||^2          velocity / movement matching (eq. 2, 5)
         + alpha * sum_t E_prior(w_t)                                  PCA prior (§5, eq. 4)
         + sum_t beta * f_t * ||Gamma^1/2 (B w_t - s_t)||^2            Sobolev position term (§7.1)
         + rho * sum_t ||w_t||^2                                       ridge, only when B is rank deficient

subject to known entries of ``W`` (boundary frames, user poses, partial poses; §4, §6).
``f_t`` are per-frame and ``Gamma = diag(gamma_m)`` per-marker Sobolev weights. Missing samples
(a ``(T, M)`` validity mask) drop out: marker ``m`` enters the velocity term of the difference
``(t-1, t)`` only when it is valid at both frames, and the position term at ``t`` only when
valid at ``t``.

Normal equations
----------------
With ``A = B^T B``, ``P`` the prior quadratic (:class:`core.prior.PCAPrior`),
``G = B^T Gamma B``, the path-graph Laplacian ``L = D^T D`` (tridiagonal; Seol's appendix) and
``vec`` stacking the frames' weight vectors (= the paper's ``vec(W)`` of its K x T ``W``)::

    (L (x) A + I (x) alpha P + diag(beta f) (x) G + rho I) vec(W) = r                      (*)

Known frames delete rows/columns of ``L`` (the unknown frames' ``L_uu`` stays tridiagonal and
falls apart into independent segments between known frames); their values move to ``r``.

Fast path (simultaneous diagonalisation), used when there is no missing sample and either the
marker weights are uniform (``G = c A``) or the frame weights are (``f = const``). Then (*) is
``L' (x) A + I (x) C`` with ``L' = L_uu + diag(beta f c)`` and ``C = alpha P + rho I`` (or
``L' = L_uu`` and ``C = alpha P + beta f G + rho I``). The generalised symmetric eigenproblem of
the pencil ``(A, A + C)``, ``A U = (A + C) U diag(mu)``, ``U^T (A + C) U = I``, gives
``U^T A U = diag(mu)``, ``U^T C U = diag(1 - mu)`` with ``0 <= mu <= 1``; it needs only
``A + C`` positive definite (not ``A``), so rank-deficient ``B`` with a prior, or shapes the
markers barely see, are handled without inverting ``B^T B``. With ``W = Z U^T``, (*) becomes K
independent SPD tridiagonal systems ``(mu_j L' + (1 - mu_j) I) z_j = (R U)_j`` of size T, solved
by LAPACK ``pttrf/pttrs``. Cost ``O(K^3)`` once per solver, ``O(T M K + T K^2)`` per solve.

Partial known weights (some shapes of a frame fixed) are exact constraints ``E^T x = c`` on the
fast system ``H0`` where those frames are free: ``x = H0^-1 (r - E lam)`` with the capacitance
system ``(E^T H0^-1 E) lam = E^T H0^-1 r - c``. ``E^T H0^-1 E`` is assembled from the columns of
the K tridiagonal inverses at the constrained frames: cost ``O(T K F + p^2 K + p^3)`` for ``p``
constrained entries on ``F`` frames.

General path (block tridiagonal), used with missing samples or per-frame *and* per-marker
weights: (*) is block tridiagonal with K x K blocks (each difference's and frame's own mask),
known entries are eliminated symmetrically, and a block Cholesky-Thomas sweep solves it in
``O(T K^3)`` time and ``O(T K^2)`` memory. Exact, not iterative.

Units: ``B`` and ``S`` in metres (the library convention). ``alpha`` is given for lengths in
``alpha_units`` (default cm, see :func:`core.prior.alpha_for_units`) and used internally as
``alpha * s**2``. ``beta`` is scale-free (both terms are squared lengths).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.linalg.lapack import dpotrf, dpotrs, dptsv, dpttrf, dpttrs

from core.prior import PCAPrior, alpha_for_units, prior_quadratic
from core.solvers.inputs import as_basis, as_sequence, as_valid, zero_filled

__all__ = [
    "SpacetimeSolver", "solve_spacetime", "spacetime_reference", "Edit", "SpacetimeEnergy",
    "known_matrix", "known_rows",
]

#: Deprecated alias kept only while core/stages.py (being redesigned) imports it from here;
#: use :func:`core.prior.prior_quadratic`.
_prior_quadratic = prior_quadratic

#: relative ridge used by ``ridge="auto"`` when ``B`` is rank deficient (times sigma_max(B)^2)
AUTO_RIDGE = 1e-9


def _nonneg(x, shape, name) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {x.shape}")
    if not np.isfinite(x).all() or (x < 0).any():
        raise ValueError(f"{name}: must be finite and >= 0")
    return x


def known_rows(known, T: int, K: int, boundary="neutral", name: str = "known") -> dict:
    """Known weights as ``{frame: (K,) row}`` (NaN = free), frames in ``[0, T)``, sorted.

    Parameters
    ----------
    known : None, mapping {frame: (K,) weights}, or (T, K) array
        NaN entries are free; so a frame with some finite entries is a partial pose
        constraint. Negative frames count from the end.
    boundary : {"neutral", "none", None}
        "neutral": frames 0 and T-1 are fixed to zero weights (the neutral pose, Seol 2012
        §3.1) unless ``known`` says something about that frame.

    Raises
    ------
    ValueError
        Unknown ``boundary``, a frame out of range, a weight vector that is not (K,), inf.
    """
    rows = {}
    if boundary == "neutral":
        rows[0] = np.zeros(K)
        rows[T - 1] = np.zeros(K)
    elif boundary not in (None, "none"):
        raise ValueError(f"boundary must be 'neutral' or 'none', got {boundary!r}")
    if known is None:
        pass
    elif isinstance(known, Mapping):
        for t, w in known.items():
            t = int(t)
            if not -T <= t < T:
                raise ValueError(f"{name}: frame {t} is outside [0, {T})")
            w = np.array(w, dtype=np.float64)
            if w.shape != (K,):
                raise ValueError(f"{name}[{t}]: expected ({K},) weights (NaN = free), got {w.shape}")
            if np.isinf(w).any():
                raise ValueError(f"{name}[{t}]: known weights must be finite (NaN marks a free weight)")
            rows[t % T] = w
    else:
        arr = np.asarray(known, dtype=np.float64)
        if arr.shape != (T, K):
            raise ValueError(f"{name}: expected a ({T}, {K}) array (NaN = free) or a {{frame: weights}} mapping, got {arr.shape}")
        if np.isinf(arr).any():
            raise ValueError(f"{name}: known weights must be finite (NaN marks a free weight)")
        for t in np.flatnonzero(~np.isnan(arr).all(1)):
            rows[int(t)] = arr[t].copy()
    out = {t: rows[t] for t in sorted(rows) if not np.isnan(rows[t]).all()}
    for w in out.values():
        w.setflags(write=False)
    return out


def known_matrix(known, T: int, K: int, boundary="neutral", name: str = "known") -> np.ndarray:
    """Known weights as a dense (T, K) array, NaN where a weight is free (see :func:`known_rows`)."""
    Kn = np.full((T, K), np.nan)
    for t, w in known_rows(known, T, K, boundary, name).items():
        Kn[t] = w
    return Kn


# -- the energy -------------------------------------------------------------------------------
class SpacetimeEnergy(NamedTuple):
    """Terms of the spacetime energy (internal units: metres squared)."""

    match: float
    prior: float
    position: float
    ridge: float
    total: float


@dataclass(frozen=True)
class Edit:
    """A user pose edit (Seol 2012, §6).

    Parameters
    ----------
    frame : int
        Frame whose pose is set.
    weights : (K,) or (len(shapes),) float
        The pose: all weights, or the values of ``shapes``.
    shapes : sequence of int or str, optional
        Only these shapes are set; the frame's other weights stay free.
    window : (a, b), optional
        Propagation range. Frames ``a`` and ``b`` keep the current solution and only
        ``a..b`` is re-solved. None: re-solve the whole sequence with the solver's own
        boundary conditions.
    """

    frame: int
    weights: object
    shapes: Optional[Sequence] = None
    window: Optional[tuple] = None


# -- the solver -------------------------------------------------------------------------------
class SpacetimeSolver:
    """Precomputed spacetime retargeting problem (Seol et al. 2012, eq. 2, 4, 5 and §7.1).

    Minimises ``||D(BW)^T - DS^T||^2 + alpha sum_t E_prior(w_t) + beta sum_t f_t
    ||Gamma^1/2 (B w_t - s_t)||^2 (+ rho ||W||^2)`` subject to known weights; see the module
    docstring for the energy, the normal equations and the two exact solution paths.
    Construction does the ``O(K^3)`` work (prior quadratic, simultaneous diagonalisation);
    :meth:`solve` and :meth:`edit` are ``O(T M K + T K^2)`` on the fast path.

    Parameters
    ----------
    B : (K, M, 3) float or (3M, K) float
        Target marker blendshape deltas (metres); ``B = flatten(deltas).T``.
    S : (T, M, 3) float
        Source marker deltas (metres) after stabilisation/calibration; NaN = missing.
    alpha : float >= 0
        Prior weight for lengths in ``alpha_units`` (paper: 0.01).
    beta : float >= 0
        Sobolev position weight (§7.1); scale-free.
    prior : PCAPrior, (P, q) tuple, or None
        A fitted :class:`core.prior.PCAPrior` (its quadratic is taken for this ``B``), an
        explicit quadratic ``E_prior = w^T P w - 2 q^T w``, or None: PCA of ``B``'s shapes
        (the paper's default). Unused when ``alpha == 0``.
    known : mapping {frame: (K,)} or (T, K) array, optional
        Known weights, NaN = free (see :func:`known_matrix`).
    boundary : {"neutral", "none"}
        "neutral" (default) fixes frames 0 and T-1 to zero weights unless ``known`` sets them.
    valid : (T, M) bool, optional
        False where a marker sample is missing. Default: where ``S`` is finite.
    marker_weights : (M,) float >= 0, optional
        Per-marker Sobolev weights ``gamma`` (e.g. more weight around the mouth).
    frame_weights : (T,) float >= 0, optional
        Per-frame Sobolev weights ``f`` (e.g. force the mouth closed at chosen frames).
    alpha_units : str
        Length unit ``alpha`` is expressed for (default "cm"; "m" = no conversion).
    ridge : "auto" or float >= 0
        Relative ridge ``rho / sigma_max(B)^2``. "auto": ``1e-9`` when ``B`` is rank
        deficient (weights the markers cannot see are then pulled to zero), else 0.
    names : sequence of K str, optional
        Shape names, so edits may name shapes.
    method : {"auto", "fast", "block"}
        Solution path; "auto" takes the fast path whenever it is exact for the inputs.

    Attributes
    ----------
    alpha_ : float            internal prior weight ``alpha * s**2``
    ridge_ : float            absolute ridge ``rho`` (m^2), pass it to :func:`spacetime_reference`
    known_ : (T, K) float     the known weights, NaN = free
    P_, q_ : prior quadratic for ``B``
    fast_ : bool              whether the fast path is available for these inputs
    method_ : str             the path the last solve used

    Raises
    ------
    ValueError
        Shapes/values of any argument (naming it), or a singular problem.
    """

    def __init__(self, B, S, alpha: float = 0.01, beta: float = 0.0, prior=None, known=None,
                 boundary="neutral", valid=None, marker_weights=None, frame_weights=None,
                 alpha_units: str = "cm", ridge="auto", names=None, method: str = "auto"):
        Bm = as_basis(B)
        n3, K = Bm.shape
        M = n3 // 3
        S3 = as_sequence(S, M)
        T = len(S3)
        self.valid_ = as_valid(valid, S3)
        self._S = zero_filled(S3, self.valid_)
        self._holes = not self.valid_.all()
        self.T, self.K, self.M = T, K, M
        self._B = Bm
        self.alpha_ = alpha_for_units(alpha, alpha_units)
        beta = float(beta)
        if not np.isfinite(beta) or beta < 0:
            raise ValueError(f"beta must be a finite number >= 0, got {beta}")
        self.beta = beta
        gam = np.ones(M) if marker_weights is None else _nonneg(marker_weights, (M,), "marker_weights")
        fw = np.ones(T) if frame_weights is None else _nonneg(frame_weights, (T,), "frame_weights")
        self._gamma3 = np.repeat(gam, 3)
        self._bt = beta * fw  # per-frame Sobolev weight beta * f_t
        if method not in ("auto", "fast", "block"):
            raise ValueError(f"method must be 'auto', 'fast' or 'block', got {method!r}")
        self.method = method
        if names is not None:
            names = tuple(str(n) for n in names)
            if len(names) != K:
                raise ValueError(f"names: expected {K} shape names, got {len(names)}")
        self.names = names
        self._known = known_rows(known, T, K, boundary)

        A = Bm.T @ Bm
        self._A = A
        if self.alpha_ > 0:
            self.P_, self.q_, self._c = prior_quadratic(prior, Bm, K)
        else:
            self.P_, self.q_, self._c = np.zeros((K, K)), np.zeros(K), 0.0
        self._G = Bm.T @ (self._gamma3[:, None] * Bm)

        sig = np.linalg.svd(Bm, compute_uv=False)
        smax2 = float(sig[0] ** 2) if sig.size and sig[0] > 0 else 1.0
        deficient = K > n3 or sig[-1] <= max(n3, K) * np.finfo(float).eps * sig[0]
        if isinstance(ridge, str):
            if ridge != "auto":
                raise ValueError(f"ridge must be 'auto' or a number >= 0, got {ridge!r}")
            self.ridge_ = AUTO_RIDGE * smax2 if deficient else 0.0
        else:
            r = float(ridge)
            if not np.isfinite(r) or r < 0:
                raise ValueError(f"ridge must be 'auto' or a number >= 0, got {ridge!r}")
            self.ridge_ = r * smax2

        # directions no per-frame term pins (null space of alpha P + rho I): with no known frame
        # and no position term, a constant offset along them leaves the energy unchanged
        lam, vec = np.linalg.eigh(self.alpha_ * self.P_ + self.ridge_ * np.eye(K))
        top = max(np.linalg.norm(A, 2), lam[-1], 1e-300)
        self._free_dirs = vec[:, lam <= 1e-12 * top]

        # Which Kronecker-sum form (*) takes, if any.
        if np.ptp(gam) == 0:
            self._mode = "frame"  # G = gamma0 A: L' = L_uu + diag(beta f gamma0), C = alpha P + rho I
            self._lt = self._bt * gam[0]
            C = self.alpha_ * self.P_ + self.ridge_ * np.eye(K)
        elif np.ptp(fw) == 0:
            self._mode = "uniform"  # L' = L_uu, C = alpha P + beta f G + rho I
            self._lt = np.zeros(T)
            C = self.alpha_ * self.P_ + self._bt[0] * self._G + self.ridge_ * np.eye(K)
        else:
            self._mode = None
        self.fast_ = self._mode is not None and not self._holes
        if method == "fast" and not self.fast_:
            why = "missing samples" if self._holes else "both per-frame and per-marker weights"
            raise ValueError(f"method='fast' is not exact with {why}; use method='auto' or 'block'")
        if self._mode is not None:
            Mp = A + C
            Mp = 0.5 * (Mp + Mp.T)
            try:
                mu, U = scipy.linalg.eigh(A, Mp)
            except np.linalg.LinAlgError:
                raise ValueError(
                    "the per-frame system B^T B + alpha P (+ beta G) is singular: some weights move no "
                    "marker and have no prior; drop those shapes or pass ridge > 0"
                ) from None
            self._mu = np.clip(mu, 0.0, 1.0)
            self._nu = 1.0 - self._mu
            self._U = U
            self._BU = Bm @ U
            self._AU = A @ U
            self._Uq = U.T @ self.q_
            if self._mode == "uniform":
                self._GBU = (self._gamma3[:, None] * Bm) @ U
        self.method_ = None

    # -- public API ---------------------------------------------------------------------------
    @property
    def known_(self) -> np.ndarray:
        """(T, K) known weights, NaN = free (a new dense array)."""
        Kn = np.full((self.T, self.K), np.nan)
        for t, w in self._known.items():
            Kn[t] = w
        return Kn

    def solve(self, method: Optional[str] = None) -> np.ndarray:
        """Weights (T, K) minimising the energy subject to ``known_``.

        Parameters
        ----------
        method : {"auto", "fast", "block"}, optional
            Override the solver's ``method`` for this call.
        """
        return self._solve_range(0, self.T - 1, dict(self._known), method or self.method)

    def edit(self, W, frame=None, weights=None, window=None, shapes=None, edits=None,
             method: Optional[str] = None) -> np.ndarray:
        """Spacetime editing (Seol 2012, §6): set poses and propagate them.

        Each edit fixes ``weights`` (all, or only ``shapes``) at ``frame``; these act as new
        boundary conditions together with the solver's own ``known_``. With a window
        ``(a, b)`` frames ``a`` and ``b`` keep their values from ``W`` and only ``a..b`` is
        re-solved; without, the whole sequence is re-solved. Several edits are applied
        together: overlapping windows merge into one range whose ends keep ``W``; an edit
        without window makes the range the whole sequence.

        Parameters
        ----------
        W : (T, K) float
            Current solution (not modified).
        frame, weights, window, shapes
            One edit (see :class:`Edit`); or
        edits : sequence of Edit
            Several edits applied together (then ``frame``/``weights`` must be None).

        Returns
        -------
        (T, K) float, a new array: ``W`` outside the re-solved ranges.

        Raises
        ------
        ValueError
            ``W`` not (T, K); frame outside [0, T) or outside its window; bad window; weights
            of the wrong length; an unknown shape name.
        """
        W = np.asarray(W, dtype=np.float64)
        if W.shape != (self.T, self.K):
            raise ValueError(f"W: expected ({self.T}, {self.K}) weights, got {W.shape}")
        if edits is None:
            if frame is None or weights is None:
                raise ValueError("edit: give frame and weights, or edits=[Edit(...), ...]")
            edits = [Edit(frame, weights, shapes, window)]
        elif frame is not None or weights is not None:
            raise ValueError("edit: give either frame/weights or edits, not both")
        if len(edits) == 0:
            return W.copy()
        T = self.T
        rows = {t: w.copy() for t, w in self._known.items()}
        set_mask = {}
        intervals = []  # (a, b, pinned)
        for i, e in enumerate(edits):
            if not isinstance(e, Edit):
                raise ValueError(f"edits[{i}]: expected an Edit, got {type(e).__name__}")
            f = int(e.frame)
            if not 0 <= f < T:
                raise ValueError(f"edits[{i}].frame: {f} is outside [0, {T})")
            idx = self._shape_index(e.shapes, f"edits[{i}].shapes")
            w = np.asarray(e.weights, dtype=np.float64).ravel()
            if w.shape == (self.K,):
                vals = w[idx]
            elif w.shape == (len(idx),):
                vals = w
            else:
                raise ValueError(f"edits[{i}].weights: expected ({self.K},) or ({len(idx)},) values, got {w.shape}")
            if not np.isfinite(vals).all():
                raise ValueError(f"edits[{i}].weights: must be finite")
            rows.setdefault(f, np.full(self.K, np.nan))[idx] = vals
            set_mask.setdefault(f, np.zeros(self.K, bool))[idx] = True
            if e.window is None:
                intervals.append((0, T - 1, False))
            else:
                a, b = (int(x) for x in e.window)
                if not 0 <= a < b < T:
                    raise ValueError(f"edits[{i}].window: expected 0 <= a < b < {T}, got {e.window}")
                if not a <= f <= b:
                    raise ValueError(f"edits[{i}]: frame {f} is outside its window ({a}, {b})")
                intervals.append((a, b, True))
        intervals.sort()
        merged = []
        for a, b, pin in intervals:
            if merged and a <= merged[-1][1]:
                pa, pb, ppin = merged[-1]
                merged[-1] = (pa, max(pb, b), ppin and pin)
            else:
                merged.append((a, b, pin))
        out = W.copy()
        for a, b, pin in merged:
            Kr = {t - a: w.copy() for t, w in rows.items() if a <= t <= b}
            if pin:
                for t in (a, b):
                    keep = ~set_mask.get(t, np.zeros(self.K, bool))
                    row = Kr.setdefault(t - a, np.full(self.K, np.nan))
                    row[keep] = W[t, keep]
            out[a:b + 1] = self._solve_range(a, b, Kr, method or self.method)
        return out

    def energy(self, W) -> SpacetimeEnergy:
        """The energy terms at ``W`` (T, K), evaluated literally (metres squared)."""
        W = np.asarray(W, dtype=np.float64)
        if W.shape != (self.T, self.K):
            raise ValueError(f"W: expected ({self.T}, {self.K}) weights, got {W.shape}")
        X = W @ self._B.T - self._S  # (T, 3M); masked entries are multiplied out below
        v3 = np.repeat(self.valid_, 3, axis=1)
        ve = v3[:-1] & v3[1:]
        dX = (X[1:] - X[:-1]) * ve
        match = float((dX**2).sum())
        prior = float(self.alpha_ * (np.einsum("tk,kl,tl->", W, self.P_, W) - 2 * (W @ self.q_).sum() + self.T * self._c))
        position = float((self._bt[:, None] * self._gamma3 * v3 * X**2).sum())
        ridge = float(self.ridge_ * (W**2).sum())
        return SpacetimeEnergy(match, prior, position, ridge, match + prior + position + ridge)

    def gradient(self, W) -> np.ndarray:
        """``dE/dW`` (T, K) of :meth:`energy`, written out term by term.

        At a solution it vanishes on the free weights (to rounding): a backward-error check
        that does not depend on how the system was solved.
        """
        W = np.asarray(W, dtype=np.float64)
        if W.shape != (self.T, self.K):
            raise ValueError(f"W: expected ({self.T}, {self.K}) weights, got {W.shape}")
        Bm = self._B
        v3 = np.repeat(self.valid_, 3, axis=1)
        X = W @ Bm.T - self._S
        R = (X[1:] - X[:-1]) * (v3[:-1] & v3[1:]) @ Bm
        g = self.alpha_ * (W @ self.P_ - self.q_) + ((self._bt[:, None] * self._gamma3 * v3) * X) @ Bm + self.ridge_ * W
        g[1:] += R
        g[:-1] -= R
        return 2 * g

    def kkt_residual(self, W) -> float:
        """``max |dE/dW|`` over the free weights, relative to ``||B^T B|| max(1, max |W|)``."""
        g = self.gradient(W)
        free = np.ones(g.shape, bool)
        for t, w in self._known.items():
            free[t] = np.isnan(w)
        scale = np.linalg.norm(self._A, 2) * max(1.0, float(np.abs(W).max()))
        return float(np.abs(g[free]).max() / scale) if free.any() else 0.0

    # -- internals ---------------------------------------------------------------------------
    def _shape_index(self, shapes, what) -> np.ndarray:
        if shapes is None:
            return np.arange(self.K)
        idx = []
        for s in shapes:
            if isinstance(s, str):
                if self.names is None:
                    raise ValueError(f"{what}: shape names need SpacetimeSolver(names=...)")
                if s not in self.names:
                    import difflib

                    close = difflib.get_close_matches(s, self.names, n=3)
                    raise ValueError(f"{what}: no shape {s!r}" + (f"; did you mean {close}?" if close else ""))
                idx.append(self.names.index(s))
            else:
                k = int(s)
                if not 0 <= k < self.K:
                    raise ValueError(f"{what}: shape index {k} is outside [0, {self.K})")
                idx.append(k)
        if len(set(idx)) != len(idx):
            raise ValueError(f"{what}: repeated shapes")
        return np.asarray(idx, dtype=np.int64)

    def _solve_range(self, lo: int, hi: int, rows: dict, method: str) -> np.ndarray:
        """Solve frames lo..hi (inclusive); ``rows`` = {frame - lo: (K,) known row, NaN free}.

        Only the energy terms inside the range are used, which is exact when frames ``lo``
        and ``hi`` are known or are the sequence ends.
        """
        if method not in ("auto", "fast", "block"):
            raise ValueError(f"method must be 'auto', 'fast' or 'block', got {method!r}")
        if method == "fast" and not self.fast_:
            raise ValueError("method='fast' is not exact for these inputs (missing samples, or both per-frame and per-marker weights)")
        n = hi - lo + 1
        rows = {t: w for t, w in rows.items() if not np.isnan(w).all()}
        full = np.zeros(n, bool)
        partial = {}
        for t, w in rows.items():
            if np.isfinite(w).all():
                full[t] = True
            else:
                partial[t] = w
        if full.all():
            self.method_ = "known"
            return np.array([rows[t] for t in range(n)])
        needs_elimination = self._check_determined(lo, hi, full, partial)
        use_fast = self.fast_ and method != "block" and not needs_elimination
        p = sum(int(np.isfinite(w).sum()) for w in partial.values())
        if use_fast and p and method == "auto" and float(p) ** 3 > 8.0 * n * float(self.K) ** 3:
            use_fast = False  # the capacitance system would cost more than the block sweep
        if use_fast:
            return self._fast_range(lo, hi, rows, full, partial)
        Kn = np.full((n, self.K), np.nan)
        for t, w in rows.items():
            Kn[t] = w
        return self._block_range(lo, hi, Kn, np.isfinite(Kn))

    def _check_determined(self, lo, hi, full, partial):
        """Refuse a range whose solution is not unique; True when only partial constraints
        make it unique (the fast path's capacitance method then does not apply).

        Unknown frames split into runs between fully known frames; a run next to a known frame
        is pinned by the velocity term. A range with no fully known frame is pinned only by the
        per-frame terms: the position term where it has weight, else ``alpha P + rho I``,
        whose null directions must then be fixed by partial constraints.
        """
        if full.any() or self._free_dirs.shape[1] == 0:
            return False
        if ((self._bt[lo:hi + 1] > 0)[:, None] & self.valid_[lo:hi + 1] & (self._gamma3[::3] > 0)).any():
            return False
        ks = [k for w in partial.values() for k in np.flatnonzero(np.isfinite(w))]
        N = self._free_dirs[ks]
        if N.size and np.linalg.matrix_rank(N) == N.shape[1]:
            return True  # unique, but only thanks to the partial constraints
        raise ValueError(
            f"the spacetime system for frames {lo}..{hi} is singular: with no known frame, no position "
            f"term (beta = 0) and a prior that leaves {self._free_dirs.shape[1]} weight direction(s) free "
            "(a PCA of K shapes has at most K - 1 components), a constant offset does not change the "
            "energy; add a boundary frame, beta > 0, or a prior fitted on more examples"
        )

    def _fast_range(self, lo, hi, rows, full, partial):
        # Works in the transposed layout (K, n): each eigen-direction j is a contiguous row,
        # which is what the per-direction LAPACK tridiagonal solves want.
        K = self.K
        n = hi - lo + 1
        Sr = self._S[lo:hi + 1]
        Y = self._BU.T @ Sr.T  # (K, n): U^T B^T s_t
        rz = np.empty((K, n))  # (L Y)_t = sum over t's differences, + alpha U^T q
        rz[:] = (self.alpha_ * self._Uq)[:, None]
        if n > 1:
            dY = np.diff(Y, axis=1)
            rz[:, 1:] += dY
            rz[:, :-1] -= dY
            del dY
        lt = self._lt[lo:hi + 1]
        if self._mode == "frame":
            if lt.any():
                rz += lt * Y
        elif self._bt[0] > 0:
            rz += self._bt[0] * (self._GBU.T @ Sr.T)
        del Y
        # known full frames: their velocity coupling A w_k moves to the neighbours' rhs
        for t in np.flatnonzero(full):
            for nb in (t - 1, t + 1):
                if 0 <= nb < n and not full[nb]:
                    rz[:, nb] += rows[t] @ self._AU
        unk = ~full
        contiguous = not full[1:-1].any()  # only the range ends may be known
        if contiguous:
            u0 = int(full[0])
            u1 = n - int(full[-1])
            u = slice(u0, u1)
            uidx = np.arange(u0, u1)
        else:
            uidx = np.flatnonzero(unk)
            u = uidx
        nu = len(uidx)
        deg = np.full(n, 2.0)
        deg[0] -= 1
        deg[-1] -= 1
        dL = deg[u] + lt[u]
        eL = np.where(np.diff(uidx) == 1, -1.0, 0.0)
        if not contiguous:
            rz = rz[:, u]  # rows stay contiguous either way
        # partial frames: exact constraints through the capacitance system
        pf = sorted(partial)
        prow = np.searchsorted(uidx, pf)  # rows (in u) with constrained entries
        cr = np.concatenate([np.full(int(np.isfinite(partial[t]).sum()), i) for i, t in enumerate(pf)]).astype(int) if pf else np.zeros(0, int)
        ck = np.concatenate([np.flatnonzero(np.isfinite(partial[t])) for t in pf]).astype(int) if pf else np.zeros(0, int)
        cval = np.concatenate([partial[t][np.isfinite(partial[t])] for t in pf]) if pf else np.zeros(0)
        cr_u = prow[cr]  # constrained entries' rows in u
        F = len(pf)
        Gf = np.empty((K, F, F))
        facs = []
        zv = rz[:, u] if contiguous else rz  # (K, nu) view; each row contiguous
        for j in range(K):
            d = self._mu[j] * dL + self._nu[j]
            e = self._mu[j] * eL
            if nu == 1:  # LAPACK's wrappers reject the empty off-diagonal
                info = 0 if d[0] > 0 else 1
                x = np.column_stack([zv[j], np.ones((1, F))]) / d[0] if info == 0 else None
                if F and info == 0:
                    Gf[j] = x[prow, 1:]
                    facs.append((d, None))
            elif not F:
                d, e, x, info = dptsv(d, e, zv[j][:, None], overwrite_b=1)
            else:
                d, e, info = dpttrf(d, e)
                if info == 0:
                    rhs = np.zeros((nu, F + 1), order="F")
                    rhs[:, 0] = zv[j]
                    rhs[prow, 1 + np.arange(F)] = 1.0
                    x, info = dpttrs(d, e, rhs)
                    Gf[j] = x[prow, 1:]
                    facs.append((d, e))
            if info != 0:
                raise ValueError(
                    f"the spacetime system for frames {lo}..{hi} is singular: nothing fixes the weights' "
                    "level (no known frame, alpha = beta = 0?); add a boundary frame, alpha > 0 or beta > 0"
                )
            zv[j] = x[:, 0]
        z = zv  # (K, nu), solved in place
        if F:
            Uk = self._U[ck]  # (p, K)
            x0 = (z[:, cr_u].T * Uk).sum(1)
            Cc = np.einsum("ij,lj,jil->il", Uk, Uk, Gf[:, cr][:, :, cr])
            lam = scipy.linalg.solve(0.5 * (Cc + Cc.T), x0 - cval, assume_a="pos")
            rc = np.zeros((nu, K))
            np.add.at(rc, cr_u, lam[:, None] * Uk)
            for j in range(K):
                d, e = facs[j]
                x = rc[:, j:j + 1] / d[0] if nu == 1 else dpttrs(d, e, rc[:, j:j + 1])[0]
                z[j] -= x[:, 0]
            self.method_ = "fast+capacitance"
        else:
            self.method_ = "fast"
        out = np.empty((n, K))
        for t in np.flatnonzero(full):
            out[t] = rows[t]
        if contiguous:
            np.matmul(z.T, self._U.T, out=out[u])
        else:
            out[u] = z.T @ self._U.T
        out[uidx[cr_u], ck] = cval  # constraints hold exactly (they already do to rounding)
        return out

    def _block_range(self, lo, hi, Kn, kmask):
        K = self.K
        n = hi - lo + 1
        Bm = self._B
        Sr = self._S[lo:hi + 1]
        V3 = np.repeat(self.valid_[lo:hi + 1], 3, axis=1)
        bt = self._bt[lo:hi + 1]
        g3 = self._gamma3
        A = self._A
        Dg = np.empty((n, K, K))
        Dg[:] = self.alpha_ * self.P_ + self.ridge_ * np.eye(K)
        r = np.tile(self.alpha_ * self.q_, (n, 1))
        # position term: G_t = B^T diag(gamma * valid_t) B
        holes_t = ~V3.all(1)
        Gt = np.broadcast_to(self._G, (n, K, K)).copy()
        if holes_t.any():
            h = np.flatnonzero(holes_t)
            Gt[h] = np.einsum("ri,hr,rj->hij", Bm, g3 * V3[h], Bm, optimize=True)
        Dg += bt[:, None, None] * Gt
        r += bt[:, None] * ((Sr * g3 * V3) @ Bm)
        Of = None
        if n > 1:
            ve = V3[:-1] & V3[1:]
            Ye = ((Sr[1:] - Sr[:-1]) * ve) @ Bm
            Ae = np.broadcast_to(A, (n - 1, K, K)).copy()
            he = ~ve.all(1)
            if he.any():
                h = np.flatnonzero(he)
                Ae[h] = np.einsum("ri,hr,rj->hij", Bm, ve[h].astype(float), Bm, optimize=True)
            Dg[:-1] += Ae
            Dg[1:] += Ae
            r[:-1] -= Ye
            r[1:] += Ye
            Of = -Ae  # coupling of frame t (rows) with t+1 (columns)
        # eliminate known entries symmetrically: r -= H c, then identity rows/columns
        C = np.where(kmask, Kn, 0.0)
        r -= np.einsum("tij,tj->ti", Dg, C)
        if n > 1:
            r[:-1] -= np.einsum("tij,tj->ti", Of, C[1:])
            r[1:] -= np.einsum("tji,tj->ti", Of, C[:-1])
        f = (~kmask).astype(float)
        Dg *= f[:, :, None] * f[:, None, :]
        ti, ki = np.nonzero(kmask)
        Dg[ti, ki, ki] = 1.0
        r[kmask] = Kn[kmask]
        if n > 1:
            Of *= f[:-1, :, None] * f[1:, None, :]
        # block Cholesky-Thomas sweep: S_t = D_t - O_{t-1}^T S_{t-1}^-1 O_{t-1}
        X = np.empty((max(n - 1, 0), K, K))
        gh = np.empty((n, K))
        for t in range(n):
            if t == 0:
                St, gt = Dg[0], r[0]
            else:
                St = Dg[t] - Of[t - 1].T @ X[t - 1]
                gt = r[t] - Of[t - 1].T @ gh[t - 1]
            c, info = dpotrf(St, lower=1, clean=0)
            if info != 0:
                raise ValueError(
                    f"the spacetime system is singular at frame {lo + t}: no data, prior or constraint "
                    "determines some weights there (all markers missing with alpha = 0?); add alpha > 0, "
                    "a known pose, or interpolate the gap"
                )
            if t < n - 1:
                sol, _ = dpotrs(c, np.column_stack([gt, Of[t]]), lower=1)
                gh[t] = sol[:, 0]
                X[t] = sol[:, 1:]
            else:
                gh[t] = dpotrs(c, gt[:, None], lower=1)[0][:, 0]
        x = np.empty((n, K))
        x[-1] = gh[-1]
        for t in range(n - 2, -1, -1):
            x[t] = gh[t] - X[t] @ x[t + 1]
        x[kmask] = Kn[kmask]
        self.method_ = "block"
        return x


def solve_spacetime(B, S, alpha: float = 0.01, beta: float = 0.0, prior=None, known=None,
                    boundary="neutral", valid=None, marker_weights=None, frame_weights=None,
                    alpha_units: str = "cm", ridge="auto", method: str = "auto") -> np.ndarray:
    """Spacetime expression cloning in one call: ``SpacetimeSolver(...).solve()``.

    Minimises ``||D(BW)^T - DS^T||_F^2 + alpha sum_t E_prior(w_t) + beta sum_t f_t
    ||Gamma^1/2 (B w_t - s_t)||^2`` (Seol et al. 2012, eq. 2, 4 and §7.1) subject to known
    weights. Parameters as :class:`SpacetimeSolver`; returns weights (T, K).
    """
    return SpacetimeSolver(B, S, alpha, beta, prior, known, boundary, valid, marker_weights,
                           frame_weights, alpha_units, ridge, method=method).solve()


def spacetime_reference(B, S, alpha: float, beta: float, prior, known, *, boundary="neutral",
                        valid=None, marker_weights=None, frame_weights=None, alpha_units: str = "cm",
                        ridge: float = 0.0) -> np.ndarray:
    """Slow, literal reference: the paper's sparse Kronecker system solved by ``spsolve``.

    Stacks the least-squares rows of Seol et al. 2012 eq. 5 and §5, §7.1 with
    ``scipy.sparse.kron`` (``vec(W)`` stacks the frames' weight vectors)::

        J_match = diag(mask_e) (D (x) B),          y_match = diag(mask_e) (D (x) I_3M) vec(S)
        J_prior = sqrt(alpha) (I_T (x) Lambda^-1/2 E^T B),  y_prior = sqrt(alpha) (1_T (x) Lambda^-1/2 E^T mean)
        J_pos   = diag(sqrt(beta f_t gamma_m valid_tm)) (I_T (x) B),  y_pos = ... vec(S)
        J_ridge = sqrt(rho) I

    and solves ``J_u^T J_u x_u = J_u^T (y - J_k x_k)`` for the free entries with
    :func:`scipy.sparse.linalg.spsolve`. With a (P, q) prior the term ``alpha (I (x) P)`` is
    added to the normal equations instead.

    Parameters
    ----------
    B, S, alpha, beta, prior, known, boundary, valid, marker_weights, frame_weights, alpha_units
        As :class:`SpacetimeSolver` (``prior`` None = PCA of ``B``'s shapes).
    ridge : float
        Absolute ridge ``rho`` (m^2); use ``SpacetimeSolver(...).ridge_`` to compare.

    Returns
    -------
    (T, K) float
    """
    Bm = as_basis(B)
    n3, K = Bm.shape
    M = n3 // 3
    S3 = as_sequence(S, M)
    T = len(S3)
    valid = as_valid(valid, S3)
    Sz = zero_filled(S3, valid)
    a = alpha_for_units(alpha, alpha_units)
    gam = np.ones(M) if marker_weights is None else _nonneg(marker_weights, (M,), "marker_weights")
    fw = np.ones(T) if frame_weights is None else _nonneg(frame_weights, (T,), "frame_weights")
    Kn = known_matrix(known, T, K, boundary)
    vecS = Sz.ravel()
    Bs = sp.csr_matrix(Bm)
    blocks, rhs = [], []
    if T > 1:
        D = sp.diags([-np.ones(T - 1), np.ones(T - 1)], [0, 1], shape=(T - 1, T), format="csr")
        me = np.repeat(valid[:-1] & valid[1:], 3, axis=1).ravel().astype(float)
        Dm = sp.diags(me)
        blocks.append(Dm @ sp.kron(D, Bs, format="csr"))
        rhs.append(Dm @ (sp.kron(D, sp.identity(n3), format="csr") @ vecS))
    Pextra = None
    if a > 0:
        if prior is None:
            prior = PCAPrior().fit(Bm.T.reshape(K, M, 3))
        if isinstance(prior, PCAPrior):
            R, m = prior._factor(Bm)
            blocks.append(np.sqrt(a) * sp.kron(sp.identity(T), sp.csr_matrix(R), format="csr"))
            rhs.append(np.sqrt(a) * np.tile(m, T))
        else:
            P, q, _ = prior_quadratic(prior, Bm, K)
            Pextra = (a * sp.kron(sp.identity(T), sp.csr_matrix(P), format="csr"), a * np.tile(q, T))
    wpos = np.sqrt(beta * fw[:, None] * np.repeat(gam, 3)[None, :] * np.repeat(valid, 3, axis=1)).ravel()
    if beta > 0:
        Wp = sp.diags(wpos)
        blocks.append(Wp @ sp.kron(sp.identity(T), Bs, format="csr"))
        rhs.append(Wp @ vecS)
    if ridge > 0:
        blocks.append(np.sqrt(ridge) * sp.identity(T * K, format="csr"))
        rhs.append(np.zeros(T * K))
    J = sp.vstack(blocks, format="csc")
    y = np.concatenate(rhs)
    xk = Kn.ravel()
    kn = np.isfinite(xk)
    fr = ~kn
    Ju, Jk = J[:, fr], J[:, kn]
    N = (Ju.T @ Ju).tocsc()
    b = Ju.T @ (y - Jk @ xk[kn])
    if Pextra is not None:
        H, qq = Pextra
        H = H.tocsc()
        N = N + H[fr][:, fr]
        b = b + qq[fr] - H[fr][:, kn] @ xk[kn]
    x = xk.copy()
    if fr.any():
        x[fr] = scipy.sparse.linalg.spsolve(N.tocsc(), b)
    return x.reshape(T, K)
