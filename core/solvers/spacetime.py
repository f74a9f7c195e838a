"""Spacetime expression cloning: whole-sequence movement matching (Seol et al. 2012, §4–7).

Minimise over the weights ``W`` (T, K), given target marker blendshapes ``B`` and source marker
deltas ``S`` (T, M, 3)::

    E(W) = sum_t ||B (w_t - w_{t-1}) - (s_t - s_{t-1})||^2          velocity / movement matching (eq. 2, 5)
         + alpha * sum_t E_prior(w_t)                                  PCA prior (§5, eq. 4)
         + sum_t beta * f_t * ||Gamma^1/2 (B w_t - s_t)||^2            Sobolev position term (§7.1)
         + rho * sum_t ||w_t||^2                                       ridge, only when B is rank deficient
         + sum_t sum_{k named} gamma_k (w_tk - n_tk)^2                 name term: pull toward namesake curves
         + sum_t w_t^T Q w_t                                           constant coupling (e.g. symmetry pairs)
        (+ sum_tk l1_k |w_tk|,  lower_k <= w_tk <= upper_k)            bounded solver, see below

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

    (L (x) A + I (x) (alpha P + Gn) + diag(beta f) (x) G + rho I) vec(W) = r               (*)

with ``Gn = diag(gamma_k [shape k has a namesake])``.

Known frames delete rows/columns of ``L`` (the unknown frames' ``L_uu`` stays tridiagonal and
falls apart into independent segments between known frames); their values move to ``r``.

Fast path (simultaneous diagonalisation), used when there is no missing sample and either the
marker weights are uniform (``G = c A``) or the frame weights are (``f = const``). Then (*) is
``L' (x) A + I (x) C`` with ``L' = L_uu + diag(beta f c)`` and ``C = alpha P + Gn + rho I`` (or
``L' = L_uu`` and ``C = alpha P + Gn + beta f G + rho I``). The name term keeps this form: ``Gn``
is not a multiple of ``I`` (only some shapes have a namesake) and is not diagonalised by the
``U`` of ``(A, alpha P)``, but it is the same K x K matrix in every frame, so it simply joins
``C`` before the pencil below is diagonalised (``name_weight = 0`` gives today's ``C`` exactly).
A constant coupling ``Q`` (any K x K PSD matrix the same in every frame, e.g. the symmetry term
``mu_s sum_pairs (w_L - w_R)^2`` of :func:`core.controls.symmetry_matrix`) joins ``C`` the same
way: ``C = alpha P + Gn + Q + rho I``, exact, still the fast path.
A namesake curve with gaps (some frames NaN) would make ``Gn`` vary per frame; it is refused.
The generalised symmetric eigenproblem of
the pencil ``(A, A + C)``, ``A U = (A + C) U diag(mu)``, ``U^T (A + C) U = I``, gives
``U^T A U = diag(mu)``, ``U^T C U = diag(1 - mu)`` with ``0 <= mu <= 1``; it needs only
``A + C`` positive definite (not ``A``), so rank-deficient ``B`` with a prior, or shapes the
markers barely see, are handled without inverting ``B^T B``. With ``W = Z U^T``, (*) becomes K
independent SPD tridiagonal systems ``(mu_j L' + (1 - mu_j) I) z_j = (R U)_j`` of size T, solved
by LAPACK ``pttrf/pttrs``. Cost ``O(K^3)`` once per solver, ``O(T M K + T K^2)`` per solve.

Partial known weights (some shapes of a frame fixed) are exact constraints ``E^T x = c`` on the
fast system ``H0`` where those frames are free: ``x = H0^-1 (r - E lam)`` with the capacitance
system ``(E^T H0^-1 E) lam = E^T H0^-1 r - c``. The inverse of each SPD tridiagonal is
semiseparable, so ``E^T H0^-1 E`` sorted by frame is quasiseparable with K x K diagonal
transitions and is factorised block by block without ever being formed
(:func:`_capacitance_solve`): ``O(p (32 + K) K)`` for ``p`` constrained entries, plus one more
banded solve. :class:`RangeSystem` packages this equality-constrained solve; the bounded
solver calls it once per active-set step.

Bounds and sparsity (:mod:`core.solvers.bounded_spacetime`): with ``lower``/``upper`` (scalars
or per shape) or ``l1 > 0`` the same energy plus ``l1 ||W||_1`` is minimised subject to the
bounds, exactly to the KKT tolerance ``tol * ||B^T B||_2 * max(1, max |W|)`` (default
:data:`~core.solvers.bounded_spacetime.KKT_RTOL` = 1e-9): a primal-dual active-set method whose
inner solve is the ``RangeSystem`` solve above (the fast path when it applies), restarted from ADMM iterates when
it cycles. Edits (§6) re-solve their windows the same way.

General path (block tridiagonal), used with missing samples or per-frame *and* per-marker
weights, and by the fast path itself when many entries are fixed (a bounded solve with a large
share of its weights on a bound: the capacitance system's ``O(p (32 + K) K)`` then exceeds the
sweep's, :func:`_block_is_cheaper`): (*) is block tridiagonal with K x K blocks (each
difference's and frame's own mask), known entries are eliminated, and a block Cholesky-Thomas
sweep over each frame's free entries solves it in ``O(sum_t k_t^3)`` time (``k_t <= K`` free
entries in frame t) and ``O(T K^2)`` memory. Exact, not iterative.

Units: ``B`` and ``S`` in metres (the library convention). ``alpha`` is given for lengths in
``alpha_units`` (default cm, see :func:`core.prior.alpha_for_units`) and used internally as
``alpha * s**2``. ``beta`` is scale-free (both terms are squared lengths). ``ridge``, ``l1`` and
``name_weight`` and ``quadratic`` are relative to ``sigma_max(B)^2`` (a weight costs ``sigma_max(B)^2`` per unit
squared in the data term of the most visible shape combination), so they do not depend on the
rig's size either; the absolute values are ``ridge_``, ``l1_``, ``name_weight_``, ``quadratic_``.
"""

from __future__ import annotations

import difflib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional, Sequence

import numba
import numpy as np
import scipy.linalg
from scipy.linalg.lapack import dgesv, dpotrf, dpotrs, dptsv, dpttrf, dpttrs

from core.prior import PCAPrior, alpha_for_units, prior_quadratic
from core.solvers.bounded_spacetime import (KKT_RTOL, _THREAD_ENTRIES, _both, kkt_violation_per_entry,
                                             solve_bounded)
from core.solvers.inputs import (as_basis, as_bounds, as_coupling, as_nonnegative, as_per_shape, as_sequence,
                                 as_valid, zero_filled)

__all__ = [
    "SpacetimeSolver", "solve_spacetime", "data_products", "DataProducts", "RangeSystem", "PoseEdit", "SpacetimeEnergy", "known_matrix", "known_rows",
]

#: relative ridge used by ``ridge="auto"`` when ``B`` is rank deficient (times sigma_max(B)^2)
AUTO_RIDGE = 1e-9


def _name_term(target, weight, T: int, K: int):
    """``(W_named zero-filled (T, K) or None, gamma (K,))`` of the name term (relative gamma)."""
    gam = as_per_shape(weight, K, "name_weight")
    if target is None:
        if (gam > 0).any():
            raise ValueError("name_weight > 0 needs name_target, the (T, K) namesake curves (NaN = no namesake)")
        return None, np.zeros(K)
    Wn = np.asarray(target, dtype=np.float64)
    if Wn.shape != (T, K):
        raise ValueError(f"name_target: expected ({T}, {K}) namesake curves (NaN = no namesake), got {Wn.shape}")
    has = np.isfinite(Wn)
    mixed = has.any(0) & ~has.all(0)
    if mixed.any():
        k = int(np.flatnonzero(mixed)[0])
        raise ValueError(
            f"name_target: column {k} mixes numbers and NaN; a shape has a namesake curve on every frame "
            "(all finite) or none (all NaN); fill the gaps of that curve or drop it"
        )
    if np.isinf(Wn).any():
        raise ValueError("name_target: contains inf")
    gam = np.where(has.all(0), gam, 0.0)
    if not (gam > 0).any():
        return None, np.zeros(K)
    return np.where(has, Wn, 0.0), gam


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
    """Terms of the spacetime energy (internal units: metres squared); ``total`` is their sum."""

    match: float
    prior: float
    position: float
    ridge: float
    total: float
    name: float = 0.0  # gamma ||W - W_named||^2 over the shapes with a namesake
    l1: float = 0.0  # l1 ||W||_1
    quadratic: float = 0.0  # sum_t w_t^T Q w_t (the constant coupling, absolute Q)


@dataclass(frozen=True)
class PoseEdit:
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


# -- the fast path's building blocks --------------------------------------------------------
class _Tridiagonals:
    """The K independent SPD tridiagonal systems ``(mu_j L' + nu_j I) z_j = r_j`` of the fast path.

    ``L'`` is given on the unknown frames of a range by its diagonal ``dL`` (n,) and
    off-diagonal ``eL`` (n-1,) (0 where known frames split the range into segments).
    :meth:`solve` works in the transposed layout (K, n), one contiguous row per direction.
    Without :meth:`factor` each solve runs LAPACK ``ptsv`` direction by direction in place
    (no stored factor: the memory of a 36,000-frame take stays that of its right-hand side);
    :meth:`factor` runs one ``pttrf`` on the K systems concatenated into a single tridiagonal
    of size K n (zero couplings between directions) and keeps what the capacitance solve needs:
    ``inv_diag`` (K, n), the diagonal of each inverse, and ``ratio`` (K, n), the ratios
    ``T_j^-1[c, b] / T_j^-1[c + 1, b]`` for ``c < b`` (the same for every column ``b``, see
    :func:`_capacitance_solve`).
    """

    def __init__(self, mu, nu, dL, eL, where: str):
        self.mu, self.nu, self.dL, self.eL = mu, nu, dL, eL
        self.K, self.n = len(mu), len(dL)
        self.where = where
        self._f = None

    def _singular(self):
        return ValueError(
            f"the spacetime system for {self.where} is singular: nothing fixes the weights' "
            "level (no known frame, alpha = beta = 0?); add a boundary frame, alpha > 0 or beta > 0"
        )

    def factor(self) -> "_Tridiagonals":
        if self._f is not None:
            return self
        K, n = self.K, self.n
        d = (self.mu[:, None] * self.dL[None, :] + self.nu[:, None]).ravel()
        e = np.zeros((K, n))
        if n > 1:
            e[:, :-1] = self.mu[:, None] * self.eL[None, :]
        e = e.ravel()[:-1]
        if d.size == 1:  # LAPACK's wrappers reject the empty off-diagonal
            if not d[0] > 0:
                raise self._singular()
            df, ef, db = d, e, d
        else:
            df, ef, info = dpttrf(d, e)
            if info != 0:
                raise self._singular()
            db, _, info = dpttrf(d[::-1].copy(), e[::-1].copy())  # pivots of the reversed order
            db = db[::-1]
        # diag of the inverse from forward and backward pivots: 1 / (d~_b + d^_b - d_b)
        self.inv_diag = (1.0 / (df + db - d)).reshape(K, n)
        ratio = np.zeros(K * n)
        ratio[:-1] = -ef  # l_c = e_c / d~_c; T^-1[c, b] = -l_c T^-1[c + 1, b] for c < b
        self.ratio = ratio.reshape(K, n)
        self.inv_diag_t = np.ascontiguousarray(self.inv_diag.T)  # (n, K): rows gathered by frame
        self.ratio_t = np.ascontiguousarray(self.ratio.T)
        self._f = (df, ef)
        return self

    def solve(self, Z, overwrite: bool = False) -> np.ndarray:
        """``T_j^-1 Z_j`` for every direction: Z (K, n) -> (K, n)."""
        K, n = self.K, self.n
        if self._f is not None:
            df, ef = self._f
            if df.size == 1:
                return Z / df[0]
            z = (np.ascontiguousarray(Z, dtype=np.float64) if overwrite else np.array(Z, dtype=np.float64)).reshape(-1)

            def run(a, b):
                x, _ = dpttrs(df[a:b], ef[a:b - 1], z[a:b], overwrite_b=1)
                if not np.shares_memory(x, z):
                    z[a:b] = x

            # directions 0 .. K/2 - 1 and the rest, in two threads when a core is free (zero coupling
            # between them: the numbers of one call)
            h = (K // 2) * n
            if h:
                _both(lambda: run(0, h), lambda: run(h, K * n), None if K * n >= _THREAD_ENTRIES else False)
            else:
                run(0, K * n)
            return z.reshape(K, n)
        out = Z if overwrite else np.array(Z)
        for j in range(K):
            d = self.mu[j] * self.dL + self.nu[j]
            if n == 1:
                if not d[0] > 0:
                    raise self._singular()
                out[j] /= d[0]
                continue
            _, _, x, info = dptsv(d, self.mu[j] * self.eL, out[j][:, None], overwrite_b=1)
            if info != 0:
                raise self._singular()
            out[j] = x[:, 0]
        return out


def _block_is_cheaper(fixed: np.ndarray, p: int) -> bool:
    """Whether eliminating the ``fixed`` (n, K) entries in a block sweep over each frame's free
    entries (:meth:`SpacetimeSolver._block_range`) costs less than the fast path's capacitance
    solve of their ``p`` constraints: ``O(p (32 + K) K)`` against ``O(sum_t k_t^2 (k_t + k_t+1))``
    plus a per-frame overhead, ``k_t`` the free entries of frame t. The constants are timings
    of both on the sample (OPENBLAS_NUM_THREADS=1; 2,028 frames x 51 shapes and 1,000 x 165,
    2 % … 70 % of the entries fixed): the capacitance solve 0.7–1.6 ns per unit, the sweep
    60 µs per frame + 0.2–0.3 ns per unit. With 2 % fixed the capacitance solve is 20x faster,
    with half of them fixed the sweep is 2x (51 shapes) to 8x (165 shapes) faster."""
    n, K = fixed.shape
    capacitance = 1.3e-9 * p * (32 + K) * K
    k = (K - np.count_nonzero(fixed, axis=1)).astype(np.float64)
    sweep = 6e-5 * n + 3e-10 * float(np.sum(k * k * (k + np.r_[k[1:], 0.0])))
    return sweep < capacitance


def warm_kernels() -> None:
    """Compile the capacitance recursion's kernels and the KKT check (the first call after an
    install or a change of these files: a few seconds of CPU, numba's cache next to the modules)
    or load them, with a 4-entry system. :func:`dashboard.serve.serve` runs it next to the box QP's
    ``warm`` when :func:`kernels_cached` says the cache is cold, so no request pays the compile."""
    tri = _Tridiagonals(np.ones(2), np.ones(2), np.full(3, 2.0), -np.ones(2), "warm-up").factor()
    _capacitance_solve(tri, np.eye(2), np.array([0, 0, 1, 2]), np.array([0, 1, 1, 0]), np.ones(4), block=2)
    kkt_violation_per_entry(np.zeros((1, 2)), np.ones((1, 2)), 0.0, 1.0, 0.0, 1.0)
    from core.solvers.bounded_spacetime import _prox_state, _state_key

    one = np.ones(2)
    state, _, _ = _prox_state(np.zeros((1, 2)), one, 0 * one, one, 0 * one, np.zeros((1, 2), bool), np.ones((1, 2)),
                              (np.zeros((1, 2), bool), np.zeros((1, 2)), np.zeros((1, 2))))
    _state_key(*state)


def kernels_cached() -> bool:
    """Whether numba's on-disk cache holds :func:`warm_kernels`' kernels for these sources."""
    from core.solvers import bounded_spacetime

    try:  # numba has no public query (as core.solvers.boxqp.kernel_cached)
        return all(bool(k._cache._cache_file._load_index()) for k in
                   (_capacitance_part, _capacitance_back, _segment_products, bounded_spacetime._kkt_entries,
                    bounded_spacetime._prox_entries, bounded_spacetime._state_changes, bounded_spacetime._state_hash))
    except Exception:  # noqa: BLE001 -- a private API: anything unexpected means "not known to be cached"
        return False


#: entries per block of the capacitance solve (see :func:`_capacitance_solve`)
CAPACITANCE_BLOCK = 32
#: ratio products below exp(-36) (< eps / 2) are taken as exp(-36) inside a block (see below)
_LOG_TINY = -36.0
_RATIO_TINY = float(np.exp(_LOG_TINY))
#: largest block: its products from the middle entry span at most 36 (block // 2) <= 700 (no overflow)
_MAX_BLOCK = 39
#: the recursion's state is kept as ``W = diag(g) W' diag(g)``; a direction's ``g`` below this is
#: folded into ``W'`` (its ``1 / g^2`` <= 1e120 scales the rank updates: no overflow)
_STATE_RESCALE = 1e-60


# Compiled kernels of the capacitance recursion (numba, nogil): a part's whole forward recursion and
# its back substitution run in one call each. In Python the recursion was ~8 calls a block (BLAS
# through scipy's wrappers, which hold the GIL, and small kernels), so two threads could not overlap;
# here numba's own BLAS calls (np.dot) run without it, and the 32 x 32 Cholesky factor and its
# inverse are written out (a few microseconds; LAPACK's wrappers would need the GIL back).
@numba.njit(cache=True, nogil=True)
def _capacitance_part(U, shapes, rows, inv_diag, seg, segi, sidx, c, p, Phi, final, thr,
                      W, v, g, Psi, Qg, Li, Nw, Ny):  # pragma: no cover
    """The forward recursion over the ``nb = len(Qg)`` blocks of ``bs = Qg.shape[1]`` entries
    ``0 .. nb bs - 1`` of one part (entries ``>= p``: padding, decoupled identity rows).
    ``seg``: the ratio products floored at exp(-36), ``segi`` their reciprocals (made once per
    solve, so that a block has multiplications only: its ~13,000 divisions were ~30 % of its
    scalar work).

    Block arrays (``E[y] = e^(l_y - l_m)``, ``l`` the ratio products' logs from the block's first
    entry, ``m = bs // 2`` its middle one; each ratio floored at exp(-36)): ``Pc = U / E``,
    ``Qc = U diag(T^-1) E`` (the diagonal block is ``Pc Qc^T`` above its diagonal), ``Pg = Pc E[last]``
    (carried to the block's last entry), ``Qg = Qc / E[0]`` (from its first), ``Psi = E[last] / E[0]``.
    The state ``W = diag(g) W' diag(g)``, ``v = g v'`` comes in and goes out in ``W``, ``v``, ``g``
    (``W'``, ``v'``); block ``i``'s ``L_ii^-1``, ``N_i^T`` and ``y_i`` go to ``Li``, ``Nw``, ``Ny``.
    The state advances past every block but the last, and past the last one too when ``final``
    (with ``Phi[nb - 1]``: the state at the next part's first entry). Returns 0, or ``i + 1`` when
    block ``i``'s pivot is not positive (numerically not positive definite)."""
    K = U.shape[1]
    nb, bs = Qg.shape[0], Qg.shape[1]
    m = bs // 2
    E = np.empty((bs, K))
    Ei = np.empty((bs, K))  # 1 / E
    A2 = np.empty((bs, 2 * K))  # [Qc | -Q W]
    B2 = np.empty((bs, 2 * K))  # [Pc | Q g]
    Qsc = np.empty((bs, K))
    X = np.empty((bs, K))
    Xv = np.empty(bs)
    Cd = np.empty((bs, bs))
    L = np.zeros((bs, bs))
    rhs = np.empty((bs, K))
    ry = np.empty(bs)
    Np = np.empty((bs, K))
    Wt = np.empty((K, K))
    fk = np.empty(K)
    for i in range(nb):
        base = i * bs
        E[m, :] = 1.0
        Ei[m, :] = 1.0
        for y in range(m + 1, bs):
            s = sidx[base + y - 1]
            for k in range(K):
                E[y, k] = E[y - 1, k] * seg[s, k]
                Ei[y, k] = Ei[y - 1, k] * segi[s, k]
        for y in range(m - 1, -1, -1):
            s = sidx[base + y]
            for k in range(K):
                E[y, k] = E[y + 1, k] * segi[s, k]
                Ei[y, k] = Ei[y + 1, k] * seg[s, k]
        for k in range(K):
            Psi[i, k] = E[bs - 1, k] * Ei[0, k]
        for y in range(bs):
            e = base + y
            if e < p:
                u, t = shapes[e], rows[e]
                for k in range(K):
                    pc = U[u, k] * Ei[y, k]
                    qc = U[u, k] * inv_diag[t, k] * E[y, k]
                    qg = qc * Ei[0, k]
                    A2[y, k] = qc
                    B2[y, k] = pc
                    rhs[y, k] = pc * E[bs - 1, k]  # Pg, minus Q W Psi below
                    Qg[i, y, k] = qg
                    Qsc[y, k] = qg * g[k]
            else:
                for k in range(K):
                    A2[y, k] = B2[y, k] = rhs[y, k] = Qg[i, y, k] = Qsc[y, k] = 0.0
        # Q_i [W | v] = (Q_i g) [W' g | v']
        np.dot(Qsc, W, X)
        np.dot(Qsc, v, Xv)
        for y in range(bs):
            for k in range(K):
                A2[y, K + k] = -X[y, k]
                B2[y, K + k] = Qsc[y, k]
        # Cd[y, x] = C_ii[x, y] - (Q W Q^T)[x, y]: valid for x <= y (the other triangle holds
        # e^(l_y - l_x) >= 1 products, which may overflow in long blocks of frames far apart: never read)
        np.dot(A2, B2.T, Cd)
        for y in range(bs):
            if base + y >= p:
                for x in range(y):
                    Cd[y, x] = 0.0
                Cd[y, y] = 1.0
        for y in range(bs):
            for k in range(K):
                rhs[y, k] -= X[y, k] * g[k] * Psi[i, k]
            ry[y] = c[base + y] - Xv[y]
        # L L^T = Cd's lower triangle (Cholesky, column by column), then L^-1 into Li[i]
        for j in range(bs):
            d = Cd[j, j]
            for q in range(j):
                d -= L[j, q] * L[j, q]
            if not d > 0.0:
                return i + 1
            d = np.sqrt(d)
            L[j, j] = d
            for r in range(j + 1, bs):
                s2 = Cd[r, j]
                for q in range(j):
                    s2 -= L[r, q] * L[j, q]
                L[r, j] = s2 / d
        Lin = Li[i]
        for j in range(bs):
            Lin[j, j] = 1.0 / L[j, j]
            for r in range(j + 1, bs):
                s2 = 0.0
                for q in range(j, r):
                    s2 -= L[r, q] * Lin[q, j]
                Lin[r, j] = s2 / L[r, r]
            for r in range(j):
                Lin[r, j] = 0.0
        # [N_i^T | y_i] = L_ii^-1 [P_i - Q_i W Psi_i | c_i - Q_i v]
        np.dot(Lin, rhs, Nw[i])
        np.dot(Lin, ry, Ny[i])
        if i < nb - 1 or final:
            # W <- Phi (Psi W Psi + N N^T) Phi = a W a + (N Phi)(N Phi)^T, v <- a v + Phi N y; the scale
            # a = Psi Phi goes to g, folded into W' (and v') for directions whose g fell below thr
            for k in range(K):
                gk = g[k] * Psi[i, k] * Phi[i, k]
                if gk < thr:
                    for j in range(K):
                        W[k, j] *= gk
                    for j in range(K):
                        W[j, k] *= gk
                    v[k] *= gk
                    gk = 1.0
                g[k] = gk
            for k in range(K):
                fk[k] = Phi[i, k] / g[k]
            for y in range(bs):
                for k in range(K):
                    Np[y, k] = Nw[i, y, k] * fk[k]
            np.dot(Np.T, Np, Wt)
            for k in range(K):
                for j in range(K):
                    W[k, j] += Wt[k, j]
            for y in range(bs):
                f = Ny[i, y]
                for k in range(K):
                    v[k] += Np[y, k] * f
    return 0


@numba.njit(cache=True, nogil=True)
def _segment_products(ratio, frames, seg):  # pragma: no cover
    """``seg[i] = prod ratio[frames[i] .. frames[i + 1] - 1]`` (row by row, in order: what
    ``np.multiply.reduceat`` computes, without its ~1 ms over the whole (n, K) array)."""
    K = ratio.shape[1]
    for i in range(len(frames) - 1):
        for k in range(K):
            seg[i, k] = ratio[frames[i], k]
        for t in range(frames[i] + 1, frames[i + 1]):
            for k in range(K):
                seg[i, k] *= ratio[t, k]


@numba.njit(cache=True, nogil=True)
def _capacitance_back(Li, Nw, Ny, Qg, Psi, Phi, z, lam):  # pragma: no cover
    """The back substitution of a part: ``lam_i = L_ii^-T (y_i - N_i^T z)`` from its last block
    to its first, ``z <- (z Psi_i + Q_i^T lam_i) Phi_(i-1)``; ``z`` comes in as the later entries'
    ``sum Q^T lam`` carried to the part's last entry (0 for a whole system)."""
    nb = Li.shape[0]
    t = np.empty(Li.shape[1])
    for i in range(nb - 1, -1, -1):
        np.dot(Nw[i], z, t)
        for y in range(t.shape[0]):
            t[y] = Ny[i, y] - t[y]
        np.dot(Li[i].T, t, lam[i])
        if i:
            z = (z * Psi[i] + np.dot(Qg[i].T, lam[i])) * Phi[i - 1]


def _capacitance_solve(tri: _Tridiagonals, U: np.ndarray, rows: np.ndarray, shapes: np.ndarray,
                       rhs: np.ndarray, block: int = CAPACITANCE_BLOCK, presorted: bool = False,
                       split: Optional[bool] = None, threads: Optional[bool] = None) -> np.ndarray:
    """``lam`` with ``(E^T H^-1 E) lam = rhs`` for the fast path's ``H^-1 = U diag_j(T_j^-1) U^T``.

    ``E`` selects the ``p`` entries ``(rows[a], shapes[a])`` (frame in the range's unknown
    frames, shape); ``T_j`` are the factorised tridiagonals ``tri``. The capacitance matrix is
    ``C[a, b] = sum_j U[k_a, j] U[k_b, j] T_j^-1[t_a, t_b]``. The inverse of an irreducible
    SPD tridiagonal is semiseparable: ``T^-1[s, t] = T^-1[t, t] prod_{s <= c < t} theta_c`` for
    ``s <= t``, with ``theta_c`` the negated multipliers of its LDL^T factorisation (all in
    [0, 1) for these diagonally dominant systems, 0 across a known frame). Sorted by frame,
    ``C`` is therefore *quasiseparable* with diagonal K x K transitions, and its block Cholesky
    factor inherits the structure: with entries in blocks of ``block``,

        C_li = Q_l Phi_{i->l} P_i^T  (l > i),   L_li = Q_l Phi_{i->l} N_i,
        L_ii L_ii^T = C_ii - Q_i W_i Q_i^T,     L_ii N_i^T = P_i - Q_i W_i Psi_i,
        W_{i+1} = Phi_i (Psi_i W_i Psi_i + N_i N_i^T) Phi_i

    where ``P`` (``Q``) are the entries' rows of ``U`` (times ``diag T^-1``) carried to the
    block's last (from its first) entry, ``Psi_i`` the transition across block ``i`` and
    ``Phi_i`` from block ``i`` to ``i + 1``: products of ratios <= 1, no division across blocks,
    no overflow. ``W_i = Z^T C_<i^-1 Z`` (``Z``: the earlier entries' ``P`` carried to block
    ``i``) and ``v_i = Z^T C_<i^-1 rhs_<i``. The dense diagonal blocks are ``(U e^-l) (Q e^l)^T``
    with ``l`` the block-local log ratio products centred on the block's middle entry (formed as
    products and quotients of the ratios), each ratio floored at ``exp(-36)`` (< eps / 2) so that
    blocks of up to 39 entries cannot overflow; the floor changes an entry by less than rounding.
    The state is kept as ``W = diag(g) W' diag(g)`` (and ``v = g v'``): each block multiplies
    ``g`` by ``Psi_i Phi_i`` instead of scaling the K x K state, and a direction's ``g`` is
    folded into ``W'`` once it falls below 1e-60. Cost ``O(p (block + K) K)`` time and
    ``O(p (block + K))`` memory instead of the dense ``O(p^3)``; the recursion is compiled
    (:func:`_capacitance_part`, :func:`_capacitance_back`).

    Two halves in parallel (``split``; by default from ``4 K`` entries on): the
    recursion is sequential in time, so the entries are cut at a block boundary into an early
    part 1 and a late part 2, and ``C12 = Z1 Q2^T`` (rank <= K: ``Z1`` part 1's ``P`` carried to
    part 2's first entry, ``Q2`` part 2's ``Q`` from there). Part 1 runs the recursion above and
    ends with ``W1 = Z1^T C11^-1 Z1``, ``v1 = Z1^T C11^-1 rhs1``; part 2 runs the *same* recursion
    in reversed order -- a reversed tridiagonal's inverse is semiseparable with the ratios
    ``theta'_c = T^-1[s, c + 1] / T^-1[s, c] = theta_c T^-1[c+1, c+1] / T^-1[c, c]`` and the
    diagonal on the other index, so ``Q2 = D P2'`` with ``D = diag T^-1`` at part 2's first
    frame and ``P2'`` the reversed run's ``P`` carried to its end -- and ends with
    ``W2 = P2'^T C22^-1 P2'``, ``v2``. With ``c = Z1^T x1`` and ``a' = P2'^T x2``:

        c = v1 - W1 D a',   a' = v2 - W2 D c    (solved as (I - S W1 S S W2 S) S c = ..., S = D^1/2)

    and each part's back substitution starts from the other's: ``z = Phi a`` (``a = D a'``) at
    part 1's last block, ``z = D c`` at part 2's. Both parts run in threads when a second core
    is free (:func:`core.cores.free_cores`; ``threads`` forces it); the arithmetic is
    the same either way, so the results are bit-identical.

    Raises
    ------
    numpy.linalg.LinAlgError
        The capacitance system is numerically not positive definite.
    """
    p = len(rows)
    if p == 0:
        return np.zeros(0)
    K = U.shape[1]
    order = None if presorted else np.lexsort((shapes, rows))
    if order is not None:
        rows, shapes, rhs = rows[order], shapes[order], rhs[order]
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    shapes = np.ascontiguousarray(shapes, dtype=np.int64)
    bs = int(max(1, min(block, p, _MAX_BLOCK)))
    nb = -(-p // bs)
    # ratio products from each entry to the next (1 within a frame): row ``sidx[e]`` of ``seg``
    # (its last row is ones)
    frames = np.unique(rows)
    seg = np.ones((len(frames), K))
    sidx = np.full(nb * bs, len(frames) - 1, dtype=np.int64)
    nxt = np.flatnonzero(rows[1:] > rows[:-1])
    if len(frames) > 1:
        _segment_products(tri.ratio_t, frames, seg)  # frames[i] -> frames[i+1]
        sidx[nxt] = np.searchsorted(frames, rows[nxt])
    U = np.ascontiguousarray(U, dtype=float)
    inv_diag = tri.inv_diag_t
    if split is None:  # by the system's size only: the arithmetic never depends on the machine's load
        split = nb >= 4 and p >= _SPLIT_ENTRIES_PER_SHAPE * K
    # part 1 (this thread) takes the odd block: part 2 (the worker, which starts a little later)
    # also advances past its last block
    nb1 = (nb + 1) // 2 if split and nb >= 2 else nb
    s = nb1 * bs  # part 1: entries 0 .. s - 1 (whole blocks, s < p when split)

    def part(rows_, shapes_, c_, p_, sidx_, seg_, Phi_, final):
        n_ = len(Phi_)
        out = dict(W=np.zeros((K, K)), v=np.zeros(K), g=np.ones(K), Psi=np.empty((n_, K)),
                   Qg=np.empty((n_, bs, K)), Li=np.empty((n_, bs, bs)), Nw=np.empty((n_, bs, K)),
                   Ny=np.empty((n_, bs)), Phi=Phi_)
        c_ = np.concatenate([c_, np.zeros(n_ * bs - len(c_))])
        segc = np.maximum(seg_, _RATIO_TINY)  # (each ratio product floored, see above)
        out["err"] = _capacitance_part(U, shapes_, rows_, inv_diag, segc, 1.0 / segc, sidx_, c_, p_, Phi_, final,
                                       _STATE_RESCALE, out["W"], out["v"], out["g"], out["Psi"], out["Qg"],
                                       out["Li"], out["Nw"], out["Ny"])
        return out

    def back(f, z):
        lam_ = np.empty((len(f["Li"]), bs))
        _capacitance_back(f["Li"], f["Nw"], f["Ny"], f["Qg"], f["Psi"], f["Phi"], z, lam_)
        return lam_

    def check(*fs):
        if any(f["err"] for f in fs):
            raise np.linalg.LinAlgError("capacitance system not positive definite")

    Phi = seg[sidx[bs - 1::bs]]  # (nb, K): last entry of block i -> first of i + 1 (the last: ones)
    if nb1 == nb:
        f = part(rows, shapes, rhs, p, sidx, seg, Phi, False)
        check(f)
        lam = back(f, np.zeros(K)).ravel()[:p]
    else:
        # part 2 reversed: its entries from the last; the ratio products of the reversed order are
        # seg's times diag(T^-1) at the later frame over the earlier one (see above)
        m2 = p - s
        nb2 = -(-m2 // bs)
        rows2, shapes2 = rows[s:][::-1].copy(), shapes[s:][::-1].copy()
        f0 = int(np.searchsorted(frames, rows[s]))  # part 2's frames: frames[f0:]
        seg2 = np.ones((len(frames) - f0, K))
        seg2[:-1] = seg[f0:-1] * (inv_diag[frames[f0 + 1:]] / inv_diag[frames[f0:-1]])
        sidx2 = np.full(nb2 * bs, len(seg2) - 1, dtype=np.int64)
        j = nxt[nxt >= s]  # entries j -> j + 1 change frame: reversed, entry j + 1 -> j
        sidx2[p - 2 - j] = sidx[j] - f0
        Phi2 = seg2[sidx2[bs - 1::bs]]
        Phi2[-1] = 1.0  # part 2's state at its own last entry (the first of part 2 in time)
        args1 = (rows[:s], shapes[:s], rhs[:s], s, sidx[:s], seg, Phi[:nb1], True)
        args2 = (rows2, shapes2, rhs[s:][::-1], m2, sidx2, seg2, Phi2, True)
        f1, f2 = _both(lambda: part(*args1), lambda: part(*args2), threads)
        check(f1, f2)
        # the interface in S-scaled coordinates: A_k = S W_k S = (S g) W_k' (S g), S v_k = (S g) v_k'
        D = inv_diag[rows[s]]
        S = np.sqrt(D)
        h1, h2 = S * f1["g"], S * f2["g"]
        A1 = f1["W"] * h1[:, None] * h1
        A2 = f2["W"] * h2[:, None] * h2
        r2 = h2 * f2["v"]  # S v2
        M = A1 @ A2
        M *= -1.0
        M.flat[::K + 1] += 1.0
        # LAPACK's dgesv itself: scipy.linalg.solve adds a condition estimate, 0.5 ms against 0.15
        _, _, ct, info = dgesv(M, h1 * f1["v"] - A1 @ r2, overwrite_a=1, overwrite_b=1)  # S c
        if info != 0:
            raise np.linalg.LinAlgError("capacitance interface singular")
        cc = ct / S
        a = S * (r2 - A2 @ ct)  # D (v2 - W2 D c)
        lam1, lam2 = _both(lambda: back(f1, Phi[nb1 - 1] * a), lambda: back(f2, D * cc), threads)
        lam = np.concatenate([lam1.ravel(), lam2.ravel()[:m2][::-1]])
    if not np.isfinite(lam).all():
        raise np.linalg.LinAlgError("capacitance solve not finite")
    if order is None:
        return np.array(lam)
    out = np.empty(p)
    out[order] = lam
    return out


#: :func:`_capacitance_solve` runs as two halves from this many entries per shape on: each half
#: saves ~p / 2 blocks of ``4 block K^2`` flops, the interface costs ~``3 K^3`` (a K x K product and
#: LU), plus the threads' hand-over
_SPLIT_ENTRIES_PER_SHAPE = 4


class RangeSystem:
    """The normal equations (*) of frames ``lo..hi`` with their known entries, ready for repeated
    solves with more entries fixed: the building block of the bounded solver
    (:mod:`core.solvers.bounded_spacetime`) and of :meth:`SpacetimeSolver.solve` itself.

    Made by :meth:`SpacetimeSolver.range_system`. Only the energy terms inside the range are
    used (exact when frames ``lo`` and ``hi`` are known or are the take's ends).

    Attributes
    ----------
    lo, hi, n, K : int      the range (inclusive) and its size
    fixed : (n, K) bool     entries known in the range (constraints of every solve)
    values : (n, K) float   their values (0 elsewhere; made on first use)
    path : str              "fast" (diagonalised tridiagonals + capacitance) or "block"
    scale : float           ``||B^T B||_2``, the scale KKT residuals are measured in
    curvature : (K,) float  ``2 diag(2 A + C)``, a per-shape curvature for active-set steps
    """

    def __init__(self, solver: "SpacetimeSolver", lo: int, hi: int, rows: dict, path: str):
        self.solver, self.lo, self.hi = solver, lo, hi
        self.n, self.K = hi - lo + 1, solver.K
        self.path = path
        n, K = self.n, self.K
        self._rows = rows
        self.fixed = np.zeros((n, K), bool)
        for t, w in rows.items():
            self.fixed[t] = np.isfinite(w)
        self.full = self.fixed.all(1)
        self._values = None
        self.scale = solver.scale_
        self.curvature = 2.0 * (2.0 * np.diag(solver._A) + np.diag(solver._C))
        self._Z0 = self._X0 = None
        self._work = None  # the capacitance steps' work arrays (made on first use)
        if path == "fast":
            self._setup_fast()

    @property
    def values(self) -> np.ndarray:
        """(n, K) known values, 0 where not known (made on first use)."""
        if self._values is None:
            v = np.zeros((self.n, self.K))
            for t, w in self._rows.items():
                m = np.isfinite(w)
                v[t, m] = w[m]
            self._values = v
        return self._values

    def _put_known(self, X):
        """Known entries into ``X`` exactly, row by row (no dense (n, K) values array)."""
        for t, w in self._rows.items():
            m = np.isfinite(w)
            X[t, m] = w[m]

    # -- the fast path ------------------------------------------------------------------------
    def _setup_fast(self):
        s, lo, hi, n, K = self.solver, self.lo, self.hi, self.n, self.K
        full = self.full
        Y = (s._SB[lo:hi + 1] @ s._U).T  # (K, n): U^T B^T s_t
        rz = np.empty((K, n))  # (L Y)_t = sum over t's differences, + alpha U^T q (+ name term)
        rz[:] = (s.alpha_ * s._Uq)[:, None]
        if n > 1:
            dY = np.diff(Y, axis=1)
            rz[:, 1:] += dY
            rz[:, :-1] -= dY
            del dY
        lt = s._lt[lo:hi + 1]
        if s._mode == "frame":
            if lt.any():
                rz += lt * Y
        elif s._bt[0] > 0:
            rz += s._bt[0] * (s._SGB[lo:hi + 1] @ s._U).T
        del Y
        if s._named is not None:
            rz += ((s.name_weight_ * s._named[lo:hi + 1]) @ s._U).T
        # known full frames: their velocity coupling A w_k moves to the neighbours' rhs
        for t in np.flatnonzero(full):
            for nb in (t - 1, t + 1):
                if 0 <= nb < n and not full[nb]:
                    rz[:, nb] += self._rows[t] @ s._AU
        contiguous = not full[1:-1].any()  # only the range ends may be known
        if contiguous:
            u0, u1 = int(full[0]), n - int(full[-1])
            uidx = np.arange(u0, u1)
            rz = rz[:, u0:u1]  # a view: each row stays contiguous
        else:
            uidx = np.flatnonzero(~full)
            rz = rz[:, uidx]
        deg = np.full(n, 2.0)
        deg[0] -= 1
        deg[-1] -= 1
        self._uidx, self._contiguous = uidx, contiguous
        self._rz = rz
        self._tri = _Tridiagonals(s._mu, s._nu, deg[uidx] + lt[uidx], np.where(np.diff(uidx) == 1, -1.0, 0.0),
                                  f"frames {lo}..{hi}")

    def solve(self, fixed=None, values=None, linear=None, *, _consume=False):
        """Minimise the range energy ``- 2 <linear, X>`` subject to ``X[fixed] = values[fixed]``.

        Parameters
        ----------
        fixed : (n, K) bool, optional
            Entries to fix, in addition to :attr:`fixed` (the known ones always are).
        values : (n, K) float, optional
            Their values (read only where ``fixed``).
        linear : (n, K) float, optional
            A linear term (the L1 term of a sign pattern in the bounded solver).

        Returns
        -------
        X : (n, K) float, the constrained minimiser (fixed entries exactly their values)
        g : (n, K) float, the range energy's gradient ``dE/dX`` at ``X`` (without the linear
            term): ``2 linear`` on the free entries up to rounding, the constraint forces on
            the fixed ones, NaN on fully known frames.

        On the fast path the fixed entries are exact constraints through the capacitance
        system (:func:`_capacitance_solve`): ``X = H^-1 (r + linear - E lam)``,
        ``(E^T H^-1 E) lam = E^T H^-1 (r + linear) - values``, so ``g = 2 (linear - E lam)``
        comes with the solve. The block path eliminates them and evaluates ``g`` literally.
        """
        n, K = self.n, self.K
        if fixed is None:
            fx, val = self.fixed, None  # only the known entries: no dense values needed
        else:
            fx = self.fixed | np.asarray(fixed, bool)
            val = np.where(self.fixed, self.values, values)
        if self.path == "block":
            return self._solve_block(fx, self.values if val is None else val, linear)
        s = self.solver
        uidx, U, tri = self._uidx, s._U, self._tri
        rows, ks = np.nonzero(fx[uidx])  # constrained entries on the unknown frames
        if len(rows) and _block_is_cheaper(fx, len(rows)):
            return self._solve_block(fx, self.values if val is None else val, linear)
        X0 = None  # Z in weight coordinates (n_u, K): read at the constrained entries
        if linear is None and self._Z0 is not None:
            Z, X0 = self._Z0, self._X0
        else:
            rz = self._rz if linear is None else self._rz + (np.asarray(linear)[uidx] @ U).T
            if len(rows):
                tri.factor()
            Z = tri.solve(rz, overwrite=_consume and linear is None)
            if linear is None and not _consume:
                # every active-set step of a run without L1 starts from this Z: kept, with its
                # weights (one (n, K) x (K, K) product instead of a gather of Z's columns per step)
                self._Z0, self._X0 = Z, Z.T @ U.T
                X0 = self._X0
        lam = None
        if len(rows):
            tri.factor()
            x0 = X0[rows, ks] if X0 is not None else np.einsum("ja,aj->a", Z[:, rows], U[ks])
            vf = (self.values if val is None else val)[uidx[rows], ks]
            try:  # np.nonzero's entries come sorted by frame, as the recursion wants them
                lam = _capacitance_solve(tri, U, rows, ks, x0 - vf, presorted=True)
            except np.linalg.LinAlgError:  # numerically singular capacitance: eliminate directly
                return self._solve_block(fx, self.values if val is None else val, linear)
            first = np.r_[True, rows[1:] != rows[:-1]]
            dr = rows[first]  # frames with constrained entries
            # three (n_u, K) work arrays kept for every step of this range (fresh ones each step were
            # ~1 ms of page faults and allocator work a step at 1,000 x 165, more with two threads)
            if self._work is None:
                self._work = (np.empty((len(uidx), K)), np.empty((len(uidx), K)), np.empty((K, len(uidx))))
            Lw, Pw, Vu = self._work
            Ld = Lw[:len(dr)]
            Ld.fill(0.0)
            Ld[np.cumsum(first) - 1, ks] = lam
            LU = np.matmul(Ld, U, out=Pw[:len(dr)])
            Vu.fill(0.0)
            Vu[:, dr] = LU.T  # U^T E lam, nonzero only on those frames
            Y = tri.solve(Vu, overwrite=True)  # in place
            Z = np.subtract(Z, Y, out=Y)  # Z itself is kept for the next step
            s.method_ = "fast+capacitance"
        else:
            s.method_ = "fast"
        X = np.empty((n, K))
        if self._contiguous and len(uidx):
            # the frames' weights in two halves of frames (two threads when a core is free); always
            # two, so that the numbers never depend on the machine's load
            Xu, m = X[uidx[0]:uidx[-1] + 1], len(uidx) // 2
            _both(lambda: np.matmul(Z[:, :m].T, U.T, out=Xu[:m]), lambda: np.matmul(Z[:, m:].T, U.T, out=Xu[m:]),
                  None if Z.size >= _THREAD_ENTRIES else False)
        elif len(uidx):
            X[uidx] = Z.T @ U.T
        # constraints hold exactly (they already do to rounding)
        self._put_known(X)
        if len(rows):
            X[uidx[rows], ks] = vf
        if _consume:
            return X, None
        g = np.zeros((n, K)) if linear is None else 2.0 * np.asarray(linear, dtype=np.float64)
        if lam is not None:
            g[uidx[rows], ks] -= 2.0 * lam
        g[self.full] = np.nan
        return X, g

    def shifted(self, rho) -> "Callable":
        """A solver for ``(H + diag(rho) / 2) X = r + extra`` on the range's free entries (known
        entries fixed): the W-update of ADMM with the per-shape penalty ``rho`` (K,).

        ``diag(rho)`` is the same K x K matrix in every frame, so it joins ``C`` in the pencil
        ``(A, A + C + diag(rho) / 2)``: a new ``O(K^3)`` generalised eigendecomposition (the
        ``U`` of ``(A, A + C)`` does not diagonalise it), then K tridiagonals as for the solve
        itself. Returns ``solve(extra (n, K)) -> X (n, K)``.
        """
        rho = np.broadcast_to(np.asarray(rho, dtype=np.float64), (self.K,))
        s, n, K = self.solver, self.n, self.K
        known, vals, full = self.fixed, self.values, self.full
        if self.path == "block":
            def solve_block(extra):
                return s._block_range(self.lo, self.hi, np.where(known, vals, np.nan), known, extra, 0.5 * rho)
            return solve_block
        Mp = s._Mp + np.diag(0.5 * rho)
        mu, U2 = scipy.linalg.eigh(s._A, Mp)
        mu = np.clip(mu, 0.0, 1.0)
        tri = self._tri
        tri2 = _Tridiagonals(mu, 1.0 - mu, tri.dL, tri.eL, tri.where).factor()
        uidx = self._uidx
        Rw = (self._rz.T @ s._U.T) @ s._Mp  # weight coordinates: r_t = Mp U (U^T r_t)

        def solve_fast(extra):
            rhs = Rw + extra[uidx]
            Z = tri2.solve(U2.T @ rhs.T, overwrite=True)
            X = np.empty((n, K))
            X[full] = vals[full]
            X[uidx] = Z.T @ U2.T
            return X

        return solve_fast

    def _solve_block(self, fx, val, linear):
        Kn = np.where(fx, val, np.nan)
        X = self.solver._block_range(self.lo, self.hi, Kn, fx, linear)
        g = self.gradient(X)
        g[self.full] = np.nan
        return X, g

    def gradient(self, X) -> np.ndarray:
        """The range energy's gradient ``dE/dX`` (n, K) written out term by term (no linear term)."""
        return self.solver._gradient_range(np.asarray(X, dtype=np.float64), self.lo)

    def energy(self, X) -> float:
        """The range energy (its smooth terms) at ``X`` (n, K), written out term by term."""
        return self.solver._energy_range(np.asarray(X, dtype=np.float64), self.lo).total


# -- the solver -------------------------------------------------------------------------------
class DataProducts(NamedTuple):
    """What :class:`SpacetimeSolver` makes of ``B``, ``S``, ``valid`` and the marker weights alone
    (:func:`data_products`): the inputs normalised and their products in weight space."""

    B: np.ndarray       # (3M, K)
    S3: np.ndarray      # (T, M, 3) as given (NaN kept)
    S: np.ndarray       # (T, 3M) zero-filled
    valid: np.ndarray   # (T, M) bool
    gamma: np.ndarray   # (M,) marker weights
    A: np.ndarray       # (K, K) B^T B
    G: np.ndarray       # (K, K) B^T Gamma B
    SB: np.ndarray      # (T, K) S_t B
    SGB: np.ndarray     # (T, K) (Gamma S_t) B
    sig: np.ndarray     # singular values of B


def data_products(B, S, valid=None, marker_weights=None) -> DataProducts:
    """The spacetime problem's data in weight space: everything :class:`SpacetimeSolver` computes
    from the markers that alpha, beta, the bounds and the other settings do not change.

    The data terms' gradients and right-hand sides need only ``S_t B`` and ``(Gamma S_t) B``
    (T, K) and ``A``, ``G`` (K x K) on a frame with every marker, so the iterations of a bounded
    solve never touch the (T, 3M) marker space again (1,000 dense points: 3,000 numbers a frame
    instead of K); frames with missing markers use it exactly. With 1,000 dense points and 1,000
    frames these products and the SVD of ``B`` are ~0.1 s, most of a solver's construction: the
    pipeline makes them once per take and rig (the ``motion_gram`` stage) and passes them as
    ``SpacetimeSolver(products=...)``."""
    Bm = as_basis(B)
    n3, K = Bm.shape
    M = n3 // 3
    S3 = as_sequence(S, M)
    valid = as_valid(valid, S3)
    Sz = zero_filled(S3, valid)
    gam = np.ones(M) if marker_weights is None else as_nonnegative(marker_weights, (M,), "marker_weights")
    g3 = np.repeat(gam, 3)
    SB = Sz @ Bm
    SGB = gam[0] * SB if np.ptp(gam) == 0 else (Sz * g3) @ Bm
    return DataProducts(Bm, S3, Sz, valid, gam, Bm.T @ Bm, Bm.T @ (g3[:, None] * Bm), SB, SGB,
                        np.linalg.svd(Bm, compute_uv=False))


class SpacetimeSolver:
    """Precomputed spacetime retargeting problem (Seol et al. 2012, eq. 2, 4, 5 and §7.1).

    Minimises ``||D(BW)^T - DS^T||^2 + alpha sum_t E_prior(w_t) + beta sum_t f_t
    ||Gamma^1/2 (B w_t - s_t)||^2 (+ rho ||W||^2 + gamma ||W - W_named||^2)`` subject to known
    weights, and with ``lower``/``upper``/``l1`` subject to the bounds with the L1 term; see the
    module docstring for the energy, the normal equations and the exact solution paths.
    Construction does the ``O(K^3)`` work (prior quadratic, simultaneous diagonalisation);
    :meth:`solve` and :meth:`edit` are ``O(T M K + T K^2)`` on the fast path, times the few
    active-set steps (each ``O(T K^2 + p (32 + K) K)`` for ``p`` weights on a bound, or the block
    sweep over the free weights when that is cheaper) when bounded.

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
    lower, upper : float or (K,) float, optional (keyword only)
        Weight bounds (None: unbounded). Known weights (boundary frames included) must lie
        inside them; edit values outside are clipped with a warning.
    l1 : float or (K,) float >= 0 (keyword only)
        Relative L1 weight: ``l1 * sigma_max(B)^2 * ||W||_1`` is added (a linear term for
        non-negative bounds). 0: none.
    name_target : (T, K) float, optional (keyword only)
        Namesake curves ``W_named``: for each shape the curve of the source channel with the
        same (canonical) name; a column of NaN = no namesake, no term for that shape.
    name_weight : float or (K,) float >= 0 (keyword only)
        Relative ``gamma``: ``gamma * sigma_max(B)^2 ||W - W_named||^2`` over the named shapes.
        0 (default): today's energy exactly.
    tol : float > 0 (keyword only)
        Relative KKT tolerance of the bounded solver (default
        :data:`~core.solvers.bounded_spacetime.KKT_RTOL`).
    quadratic : (K, K) float, optional (keyword only)
        Relative symmetric PSD ``Q``: ``sigma_max(B)^2 sum_t w_t^T Q w_t`` is added (joins ``C``,
        see the module docstring), e.g. :func:`core.controls.symmetry_matrix`. None: none.
    products : DataProducts, optional (keyword only)
        :func:`data_products` of the same ``B``, ``S``, ``valid`` and ``marker_weights``: the
        products with the take that no other setting changes, made once (the pipeline's
        ``motion_gram`` stage) instead of per solver (the same numbers). Default: made here.

    Attributes
    ----------
    alpha_ : float            internal prior weight ``alpha * s**2``
    ridge_ : float            absolute ridge ``rho`` (m^2), pass it to :func:`~core.solvers.reference.spacetime_reference`
    known_ : (T, K) float     the known weights, NaN = free
    P_, q_ : prior quadratic for ``B``
    fast_ : bool              whether the fast path is available for these inputs
    method_ : str             the path the last solve used ("fast", "fast+capacitance", "block",
                              "fast+bounded", "block+bounded", "known")
    scale_ : float            ``sigma_max(B)^2 = ||B^T B||_2``, the scale of the relative settings
    lower_, upper_ : (K,)     bounds (-inf/inf where none)
    l1_, name_weight_ : (K,)  absolute L1 and name weights (m^2)
    quadratic_ : (K, K) or None  absolute coupling ``sigma_max(B)^2 Q`` (m^2)
    bounded_ : bool           whether solves go through the bounded solver
    info_ : dict              the bounded solver's report of the last solve (iterations, active,
                              kkt, converged; see :func:`core.solvers.bounded_spacetime.solve_bounded`)

    Raises
    ------
    ValueError
        Shapes/values of any argument (naming it), known weights outside the bounds, a
        namesake curve with gaps, or a singular problem.
    """

    def __init__(self, B, S, alpha: float = 0.01, beta: float = 0.0, prior=None, known=None,
                 boundary="neutral", valid=None, marker_weights=None, frame_weights=None,
                 alpha_units: str = "cm", ridge="auto", names=None, method: str = "auto", *,
                 lower=None, upper=None, l1=0.0, name_target=None, name_weight=0.0, tol: float = KKT_RTOL,
                 quadratic=None, products=None):
        if products is None:
            products = data_products(B, S, valid, marker_weights)
        elif not isinstance(products, DataProducts):
            raise ValueError(f"products: expected the DataProducts of data_products(), got {type(products).__name__}")
        Bm, S3, self.valid_ = products.B, products.S3, products.valid
        n3, K = Bm.shape
        M = n3 // 3
        T = len(S3)
        if np.shape(S) != S3.shape or np.size(B) != Bm.size:
            raise ValueError(f"products: made for B {Bm.shape} and S {S3.shape}, given {np.shape(B)} and {np.shape(S)}")
        self._S = products.S
        self._holes = not self.valid_.all()
        self.T, self.K, self.M = T, K, M
        self._B = Bm
        self.alpha_ = alpha_for_units(alpha, alpha_units)
        beta = float(beta)
        if not np.isfinite(beta) or beta < 0:
            raise ValueError(f"beta must be a finite number >= 0, got {beta}")
        self.beta = beta
        gam = products.gamma
        fw = np.ones(T) if frame_weights is None else as_nonnegative(frame_weights, (T,), "frame_weights")
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

        A = products.A
        self._A = A
        if self.alpha_ > 0:
            self.P_, self.q_, self._c = prior_quadratic(prior, Bm, K)
        else:
            self.P_, self.q_, self._c = np.zeros((K, K)), np.zeros(K), 0.0
        self._G, self._SB, self._SGB = products.G, products.SB, products.SGB
        self._full_ = self.valid_.all(1)  # (T,) frames with every marker

        sig = products.sig
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

        self.scale_ = smax2
        # bounds, L1 and the name term: the options of the bounded solver (and gamma of the fast path)
        self.lower_, self.upper_ = as_bounds(lower, upper, K)
        self.l1_ = as_per_shape(l1, K, "l1") * smax2
        self._named, self.name_weight_ = _name_term(name_target, name_weight, T, K)
        self.name_weight_ = self.name_weight_ * smax2
        self.quadratic_ = as_coupling(quadratic, K, smax2)
        tol = float(tol)
        if not (np.isfinite(tol) and tol > 0):
            raise ValueError(f"tol must be a finite number > 0, got {tol}")
        self.tol = tol
        self.bounded_ = bool(np.isfinite(self.lower_).any() or np.isfinite(self.upper_).any() or (self.l1_ > 0).any())
        for t, w in self._known.items():
            out = np.isfinite(w) & ((w < self.lower_) | (w > self.upper_))
            if out.any():
                k = int(np.flatnonzero(out)[0])
                hint = " (boundary='neutral' fixes frames 0 and T-1 to zero)" if boundary == "neutral" and t in (0, T - 1) else ""
                raise ValueError(
                    f"known[{t}][{k}] = {w[k]:g}{hint} is outside the bounds [{self.lower_[k]:g}, {self.upper_[k]:g}]; "
                    "widen the bounds or give known poses inside them"
                )
        # per-frame terms other than the data: C = alpha P + rho I + diag(gamma_name)
        Cf = self.alpha_ * self.P_ + self.ridge_ * np.eye(K) + np.diag(self.name_weight_)
        if self.quadratic_ is not None:
            Cf = Cf + self.quadratic_
        self._C = Cf

        self._free = None  # _free_dirs, made when a range without a known frame asks

        # Which Kronecker-sum form (*) takes, if any.
        if np.ptp(gam) == 0:
            self._mode = "frame"  # G = gamma0 A: L' = L_uu + diag(beta f gamma0), C = alpha P + rho I + Gn
            self._lt = self._bt * gam[0]
            C = Cf
        elif np.ptp(fw) == 0:
            self._mode = "uniform"  # L' = L_uu, C = alpha P + beta f G + rho I + Gn
            self._lt = np.zeros(T)
            C = Cf + self._bt[0] * self._G
        else:
            self._mode = None
        self.fast_ = self._mode is not None and not self._holes
        if method == "fast" and not self.fast_:
            why = "missing samples" if self._holes else "both per-frame and per-marker weights"
            raise ValueError(f"method='fast' is not exact with {why}; use method='auto' or 'block'")
        if self._mode is not None:
            Mp = A + C
            Mp = 0.5 * (Mp + Mp.T)
            self._Mp = Mp  # the pencil's metric: U^T Mp U = I
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
            self._AU = A @ U
            self._Uq = U.T @ self.q_
        self.method_ = None
        self.info_ = {}

    # -- public API ---------------------------------------------------------------------------
    @property
    def known_(self) -> np.ndarray:
        """(T, K) known weights, NaN = free (a new dense array)."""
        Kn = np.full((self.T, self.K), np.nan)
        for t, w in self._known.items():
            Kn[t] = w
        return Kn

    def solve(self, method: Optional[str] = None, zero=None, warm=None) -> np.ndarray:
        """Weights (T, K) minimising the energy subject to ``known_``.

        Parameters
        ----------
        method : {"auto", "fast", "block"}, optional
            Override the solver's ``method`` for this call.
        zero : (K,) or (T, K) bool, optional
            Weights held at ``clip(0, lower, upper)`` for this solve: more known entries (partial
            poses, so the fast path's capacitance system takes them exactly); the solver's own
            known weights win where both set an entry. E.g. the weaker shape of each cancel pair
            (:func:`core.controls.cancel_pairs`) or the off shapes of an active set.
        warm : (T, K) float, optional
            With bounds or L1: a previous solution of a similar problem (e.g. before a setting
            change), where the bounded solver's active-set run starts. The result does not
            depend on it (the minimiser is unique; see
            :func:`~core.solvers.bounded_spacetime.solve_bounded`), only the time.
        """
        rows = dict(self._known)
        if zero is not None:
            z = np.asarray(zero)
            if z.dtype != bool or z.shape not in ((self.K,), (self.T, self.K)):
                raise ValueError(f"zero: expected a ({self.K},) or ({self.T}, {self.K}) bool mask, got "
                                 f"{z.dtype} {z.shape}")
            z = np.broadcast_to(z, (self.T, self.K))
            held = np.clip(0.0, self.lower_, self.upper_)
            for t in np.flatnonzero(z.any(1)):
                row = rows[t].copy() if t in rows else np.full(self.K, np.nan)
                put = z[t] & np.isnan(row)
                row[put] = held[put]
                row.setflags(write=False)
                rows[int(t)] = row
            rows = {t: rows[t] for t in sorted(rows)}
        return self._solve_range(0, self.T - 1, rows, method or self.method, warm)

    def edit(self, W, frame=None, weights=None, window=None, shapes=None, edits=None,
             method: Optional[str] = None) -> np.ndarray:
        """Spacetime editing (Seol 2012, §6): set poses and propagate them.

        Each edit fixes ``weights`` (all, or only ``shapes``) at ``frame``; these act as new
        boundary conditions together with the solver's own ``known_``. With a window
        ``(a, b)`` frames ``a`` and ``b`` keep their values from ``W`` and only ``a..b`` is
        re-solved; without, the whole sequence is re-solved. Several edits are applied
        together: overlapping windows merge into one range whose ends keep ``W``; an edit
        without window makes the range the whole sequence.

        A solver with bounds, L1 or the name term re-solves with them (the bounded solver on
        the range): every re-solved weight stays inside its bounds, and an edit value outside
        them is clipped to them with a ``UserWarning`` (the window's end frames keep ``W``'s
        values as they are). Outside the ranges the result is ``W`` itself.

        Parameters
        ----------
        W : (T, K) float
            Current solution (not modified).
        frame, weights, window, shapes
            One edit (see :class:`PoseEdit`); or
        edits : sequence of PoseEdit
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
                raise ValueError("edit: give frame and weights, or edits=[PoseEdit(...), ...]")
            edits = [PoseEdit(frame, weights, shapes, window)]
        elif frame is not None or weights is not None:
            raise ValueError("edit: give either frame/weights or edits, not both")
        if len(edits) == 0:
            return W.copy()
        T = self.T
        rows = {t: w.copy() for t, w in self._known.items()}
        set_mask = {}
        intervals = []  # (a, b, pinned)
        for i, e in enumerate(edits):
            if not isinstance(e, PoseEdit):
                raise ValueError(f"edits[{i}]: expected a PoseEdit, got {type(e).__name__}")
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
            lo_i, hi_i = self.lower_[idx], self.upper_[idx]
            out_of = (vals < lo_i) | (vals > hi_i)
            if out_of.any():  # the bounds are the animator's declared range: a pose past them is clipped
                k = int(np.flatnonzero(out_of)[0])
                name = self.names[idx[k]] if self.names is not None else f"shape {idx[k]}"
                warnings.warn(
                    f"edits[{i}]: {int(out_of.sum())} weight(s) outside the solver's bounds are clipped to them "
                    f"(e.g. {name} = {vals[k]:g} -> {np.clip(vals[k], lo_i[k], hi_i[k]):g} at frame {f})",
                    UserWarning, stacklevel=2,
                )
                vals = np.clip(vals, lo_i, hi_i)
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
        return self._energy_range(self._check_weights(W), 0, l1=True)

    def gradient(self, W) -> np.ndarray:
        """``dE/dW`` (T, K) of :meth:`energy`'s smooth terms (all but the L1 term), term by term.

        At an unbounded solution it vanishes on the free weights (to rounding): a backward-error
        check that does not depend on how the system was solved.
        """
        return self._gradient_range(self._check_weights(W), 0)

    def kkt_residual(self, W) -> float:
        """Largest violation of the optimality conditions at ``W``, relative to
        ``||B^T B||_2 max(1, max |W|)``.

        With ``g = dE/dW`` (:meth:`gradient`) and ``h(w) = l1 |w|`` on ``[lower, upper]``, a
        free weight must have ``-g`` in the subdifferential of ``h`` at ``w``: ``|g + l1 sign(w)|``
        inside the bounds, ``max(0, -(g + h'(lower+)))`` at a lower bound, ``max(0, g + h'(upper-))``
        at an upper one, ``max(0, |g| - l1)`` at zero between them; a weight outside its bounds
        counts as ``||B^T B||_2`` times its distance. Known weights are exempt. Without bounds
        and L1 this is ``max |g|`` over the free weights. The bounded solver stops when this is
        at most ``tol`` (default :data:`~core.solvers.bounded_spacetime.KKT_RTOL`).
        """
        W = self._check_weights(W)
        g = self.gradient(W)
        free = np.ones(g.shape, bool)
        for t, w in self._known.items():
            free[t] = np.isnan(w)
        v = kkt_violation_per_entry(W, g, self.lower_, self.upper_, self.l1_, self.scale_)
        scale = self.scale_ * max(1.0, float(np.abs(W).max()))
        return float(v[free].max() / scale) if free.any() else 0.0

    def range_system(self, lo: int = 0, hi: Optional[int] = None, rows: Optional[dict] = None,
                     method: Optional[str] = None) -> RangeSystem:
        """The normal equations of frames ``lo..hi`` as a :class:`RangeSystem`.

        ``rows`` = ``{frame - lo: (K,) known row, NaN free}``; default the solver's own known
        rows inside the range. ``method`` as :meth:`solve`.
        """
        hi = self.T - 1 if hi is None else int(hi)
        if not 0 <= lo <= hi < self.T:
            raise ValueError(f"range_system: expected 0 <= lo <= hi < {self.T}, got {lo}, {hi}")
        if rows is None:
            rows = {t - lo: w for t, w in self._known.items() if lo <= t <= hi}
        method = method or self.method
        rows = {t: w for t, w in rows.items() if not np.isnan(w).all()}
        full = np.zeros(hi - lo + 1, bool)
        partial = {}
        for t, w in rows.items():
            if np.isfinite(w).all():
                full[t] = True
            else:
                partial[t] = w
        needs_elimination = not full.all() and self._check_determined(lo, hi, full, partial)  # raises if singular
        use_fast = self.fast_ and method != "block" and not full.all() and not needs_elimination
        return RangeSystem(self, lo, hi, rows, "fast" if use_fast else "block")

    # -- internals ---------------------------------------------------------------------------
    def _check_weights(self, W) -> np.ndarray:
        W = np.asarray(W, dtype=np.float64)
        if W.shape != (self.T, self.K):
            raise ValueError(f"W: expected ({self.T}, {self.K}) weights, got {W.shape}")
        return W

    def _energy_range(self, X: np.ndarray, lo: int, l1: bool = False) -> SpacetimeEnergy:
        """Energy terms of frames ``lo .. lo + len(X) - 1`` (the L1 term only with ``l1``)."""
        sl = slice(lo, lo + len(X))
        R = X @ self._B.T - self._S[sl]  # (n, 3M); masked entries are multiplied out below
        v3 = np.repeat(self.valid_[sl], 3, axis=1)
        dR = (R[1:] - R[:-1]) * (v3[:-1] & v3[1:])
        match = float((dR**2).sum())
        prior = float(self.alpha_ * (np.einsum("tk,kl,tl->", X, self.P_, X) - 2 * (X @ self.q_).sum() + len(X) * self._c))
        position = float((self._bt[sl, None] * self._gamma3 * v3 * R**2).sum())
        ridge = float(self.ridge_ * (X**2).sum())
        name = float((self.name_weight_ * (X - self._named[sl]) ** 2).sum()) if self._named is not None else 0.0
        lone = float((self.l1_ * np.abs(X)).sum()) if l1 else 0.0
        quad = float(np.einsum("tk,kl,tl->", X, self.quadratic_, X)) if self.quadratic_ is not None else 0.0
        return SpacetimeEnergy(match, prior, position, ridge, match + prior + position + ridge + name + lone + quad, name,
                               lone, quad)

    def _gradient_range(self, X: np.ndarray, lo: int) -> np.ndarray:
        """Gradient of the energy terms of frames ``lo .. lo + len(X) - 1`` (smooth terms)."""
        sl = slice(lo, lo + len(X))
        Rb = X @ self._A - self._SB[sl]  # R_t B = (B w_t - s_t)^T B on a frame with every marker
        Re = Rb[1:] - Rb[:-1]
        holes, pairs = self._holes_in(sl)
        bt = self._bt[sl]
        # without the position term (beta = 0, the default) its product and passes are zeros: skipped
        pos = bt[:, None] * (X @ self._G - self._SGB[sl]) if len(holes) or bt.any() else 0.0
        if len(holes) or len(pairs):  # frames with missing markers: their terms in marker space
            Bm, S, V = self._B, self._S[sl], self.valid_[sl]
            if len(holes):
                v3 = np.repeat(V[holes], 3, axis=1)
                pos[holes] = ((self._bt[sl][holes, None] * self._gamma3 * v3) * (X[holes] @ Bm.T - S[holes])) @ Bm
            if len(pairs):
                ve = np.repeat(V[pairs] & V[pairs + 1], 3, axis=1)
                Re[pairs] = (((X[pairs + 1] - X[pairs]) @ Bm.T - (S[pairs + 1] - S[pairs])) * ve) @ Bm
        g = self.alpha_ * (X @ self.P_ - self.q_) + pos + self.ridge_ * X
        if self._named is not None:
            g += self.name_weight_ * (X - self._named[sl])
        if self.quadratic_ is not None:
            g += X @ self.quadratic_
        g[1:] += Re
        g[:-1] -= Re
        return 2 * g

    def _holes_in(self, sl: slice) -> tuple:
        """Frames (relative to ``sl``) with a missing marker, and the differences (t, t + 1)
        that touch one: the only places the data terms need the marker space."""
        holes = np.flatnonzero(~self._full_[sl])
        if not len(holes):
            return holes, holes
        n = len(self._full_[sl])
        pairs = np.unique(np.r_[holes - 1, holes])
        return holes, pairs[(pairs >= 0) & (pairs < n - 1)]

    def _shape_index(self, shapes, what) -> np.ndarray:
        if shapes is None:
            return np.arange(self.K)
        idx = []
        for s in shapes:
            if isinstance(s, str):
                if self.names is None:
                    raise ValueError(f"{what}: shape names need SpacetimeSolver(names=...)")
                if s not in self.names:
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

    def _solve_range(self, lo: int, hi: int, rows: dict, method: str, warm=None) -> np.ndarray:
        """Solve frames lo..hi (inclusive); ``rows`` = {frame - lo: (K,) known row, NaN free}.

        Only the energy terms inside the range are used, which is exact when frames ``lo``
        and ``hi`` are known or are the sequence ends. With bounds or L1 the bounded solver
        (:func:`core.solvers.bounded_spacetime.solve_bounded`) runs on the range's system.
        """
        if method not in ("auto", "fast", "block"):
            raise ValueError(f"method must be 'auto', 'fast' or 'block', got {method!r}")
        if method == "fast" and not self.fast_:
            raise ValueError("method='fast' is not exact for these inputs (missing samples, or both per-frame and per-marker weights)")
        n = hi - lo + 1
        rows = {t: w for t, w in rows.items() if not np.isnan(w).all()}
        if len(rows) == n and all(np.isfinite(w).all() for w in rows.values()):
            self.method_ = "known"
            return np.array([rows[t] for t in range(n)])
        system = self.range_system(lo, hi, rows, method)
        if self.bounded_:
            X, self.info_ = solve_bounded(system, self.lower_, self.upper_, self.l1_, tol=self.tol, warm=warm)
            self.method_ = system.path + "+bounded"
            return X
        return system.solve(_consume=True)[0]

    @property
    def _free_dirs(self) -> np.ndarray:
        """(K, f) directions no per-frame term pins (null space of ``alpha P + rho I +
        diag(gamma)``): with no known frame and no position term, a constant offset along them
        leaves the energy unchanged. Made on first use (an eigendecomposition and a 2-norm,
        ~3.5 ms at K = 165: a setting change of a take with known end frames never asks)."""
        if self._free is None:
            lam, vec = np.linalg.eigh(self._C)
            top = max(np.linalg.norm(self._A, 2), lam[-1], 1e-300)
            self._free = vec[:, lam <= 1e-12 * top]
        return self._free

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

    def _block_range(self, lo, hi, Kn, kmask, linear=None, shift=None):
        """Exact block-tridiagonal solve of frames lo..hi with the entries ``kmask`` fixed to
        ``Kn``; ``linear`` (n, K) adds to the right-hand side, ``shift`` (K,) to the diagonal.

        Frame t's diagonal block is ``C + beta f_t G_t + sum of A_e over its differences e``, the
        coupling of frames t, t+1 is ``-A_e``; ``G_t`` and ``A_e`` are the constant ``G``, ``A``
        except where markers are missing. Only those exceptions are stored (no (n, K, K) arrays:
        allocating them cost more than the sweep), and the sweep runs on each frame's free
        entries alone (a bounded solve with half its entries on a bound costs an eighth of a
        sweep over all K)."""
        K = self.K
        n = hi - lo + 1
        Bm = self._B
        bt = self._bt[lo:hi + 1]
        g3 = self._gamma3
        A, G = self._A, self._G
        Cm = self._C if shift is None else self._C + np.diag(shift)  # alpha P + rho I + diag(gamma_name)
        r = np.tile(self.alpha_ * self.q_, (n, 1))
        if self._named is not None:
            r += self.name_weight_ * self._named[lo:hi + 1]
        if linear is not None:
            r += linear
        # the data in weight space; frames with a missing marker (and the differences touching
        # them) in marker space, where G_t = B^T diag(gamma valid_t) B and A_e differ from G, A
        holes, pairs = self._holes_in(slice(lo, hi + 1))
        Sr, V = self._S[lo:hi + 1], self.valid_[lo:hi + 1]
        SG = self._SGB[lo:hi + 1].copy()
        Gh: dict = {}
        for t in holes:
            v3 = np.repeat(V[t], 3)
            SG[t] = (Sr[t] * g3 * v3) @ Bm
            Gh[int(t)] = np.einsum("ri,r,rj->ij", Bm, g3 * v3, Bm, optimize=True)
        r += bt[:, None] * SG
        Ah: dict = {}
        if n > 1:
            SB = self._SB[lo:hi + 1]
            Ye = SB[1:] - SB[:-1]
            for e in pairs:
                ve = np.repeat(V[e] & V[e + 1], 3)
                Ye[e] = ((Sr[e + 1] - Sr[e]) * ve) @ Bm
                Ah[int(e)] = np.einsum("ri,r,rj->ij", Bm, ve.astype(float), Bm, optimize=True)
            r[:-1] -= Ye
            r[1:] += Ye
        # eliminate known entries: r -= H c
        C = np.where(kmask, Kn, 0.0)
        r -= C @ Cm.T
        r -= bt[:, None] * (C @ G)
        for t, Gt in Gh.items():
            r[t] += bt[t] * (C[t] @ G - C[t] @ Gt)
        if n > 1:
            dC = C[:-1] - C[1:]
            Ad = dC @ A
            for e, Ae in Ah.items():
                Ad[e] = dC[e] @ Ae
            r[:-1] -= Ad
            r[1:] += Ad

        blocks: dict = {}

        def diag_block(t):
            """Frame t's full K x K block (without holes: one per (beta f_t, differences) pair)."""
            d = (t > 0) + (t < n - 1)
            if t not in Gh and (t - 1) not in Ah and t not in Ah:
                key = (float(bt[t]), d)
                M = blocks.get(key)
                if M is None:
                    M = blocks[key] = Cm + bt[t] * G + d * A
                return M
            M = Cm + bt[t] * Gh.get(t, G)
            for e in (t - 1, t):
                if 0 <= e < n - 1:
                    M = M + Ah.get(e, A)
            return M

        # block Cholesky-Thomas sweep on the free entries F_t of each frame:
        # S_t = D_t - O_{t-1}^T S_{t-1}^-1 O_{t-1}, O_t = -A_t
        free = [np.flatnonzero(row) for row in ~kmask]
        Xs: list = [None] * n  # S_t^-1 O_t (F_t x F_{t+1})
        gh: list = [None] * n
        for t in range(n):
            F = free[t]
            if not len(F):
                continue
            St, gt = diag_block(t)[F[:, None], F], r[t, F]
            if t and Xs[t - 1] is not None:
                Ot = -Ah.get(t - 1, A)[free[t - 1][:, None], F]
                St = St - Ot.T @ Xs[t - 1]
                gt = gt - Ot.T @ gh[t - 1]
            c, info = dpotrf(St, lower=1, clean=0)
            if info != 0:
                raise ValueError(
                    f"the spacetime system is singular at frame {lo + t}: no data, prior or constraint "
                    "determines some weights there (all markers missing with alpha = 0?); add alpha > 0, "
                    "a known pose, or interpolate the gap"
                )
            Fn = free[t + 1] if t < n - 1 else F[:0]
            rhs = np.empty((len(F), 1 + len(Fn)))
            rhs[:, 0] = gt
            if len(Fn):
                np.negative(Ah.get(t, A)[F[:, None], Fn], out=rhs[:, 1:])
            sol, _ = dpotrs(c, rhs, lower=1)
            gh[t] = sol[:, 0]
            Xs[t] = sol[:, 1:] if len(Fn) else None
        x = C  # the fixed entries already hold their values
        for t in range(n - 1, -1, -1):
            F = free[t]
            if not len(F):
                continue
            x[t, F] = gh[t] if Xs[t] is None else gh[t] - Xs[t] @ x[t + 1, free[t + 1]]
        self.method_ = "block"
        return x


def solve_spacetime(B, S, alpha: float = 0.01, beta: float = 0.0, prior=None, known=None,
                    boundary="neutral", valid=None, marker_weights=None, frame_weights=None,
                    alpha_units: str = "cm", ridge="auto", method: str = "auto", **options) -> np.ndarray:
    """Spacetime expression cloning in one call: ``SpacetimeSolver(...).solve()``.

    Minimises ``||D(BW)^T - DS^T||_F^2 + alpha sum_t E_prior(w_t) + beta sum_t f_t
    ||Gamma^1/2 (B w_t - s_t)||^2`` (Seol et al. 2012, eq. 2, 4 and §7.1) subject to known
    weights. Parameters as :class:`SpacetimeSolver` (``options``: its keyword-only ``lower``,
    ``upper``, ``l1``, ``name_target``, ``name_weight``, ``tol``, ``quadratic``); returns weights (T, K).
    """
    return SpacetimeSolver(B, S, alpha, beta, prior, known, boundary, valid, marker_weights,
                           frame_weights, alpha_units, ridge, method=method, **options).solve()
