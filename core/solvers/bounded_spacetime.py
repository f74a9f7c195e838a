"""Bounded, sparse spacetime retargeting: the spacetime energy with ``lower <= W <= upper`` and L1.

Minimise over the weights ``W`` (T, K) of a frame range (the whole take, or an edit window)::

    E(W) + sum_{t,k} l1_k |w_tk|      subject to  lower_k <= w_tk <= upper_k  and the known weights

where ``E`` is :class:`core.solvers.spacetime.SpacetimeSolver`'s energy (movement matching,
PCA prior, Sobolev term, ridge and name term; Seol et al. 2012 eq. 2, 4, 5 and §7.1) and the
bounds are scalars or per-shape. For ``lower >= 0`` the L1 term is linear, ``l1^T W 1``; across
zero it is the kink of ``|w|``. ``E(W) = x^T H x - 2 r^T x + c`` with ``x = vec(W)`` is the
convex quadratic of the normal equations (*) of the spacetime module, so this is a convex QP.

Method: primal-dual active set with an exact inner solve
----------------------------------------------------------
Each entry is in one *state*: fixed (at ``lower``, at ``upper``, at ``0`` between them when
``l1 > 0``, or known) or free with a sign ``s`` (its L1 slope ``l1 s``). For a state the
problem is the equality-constrained quadratic

    min  E(W) + l1 <s, W>_free   subject to  W[fixed] = values

which :meth:`~core.solvers.spacetime.RangeSystem.solve` solves *exactly* with the unbounded
fast path: the diagonalised tridiagonals plus a capacitance system for the fixed entries,
solved in ``O(p (32 + K) K)`` by the quasiseparable block Cholesky of
:func:`core.solvers.spacetime._capacitance_solve` (``p`` fixed entries; no dense ``p x p``
matrix). It also returns the gradient ``g = dE/dW``, whose values on the fixed entries are the
constraint forces. The primal-dual active-set step (Hintermüller, Ito and Kunisch 2002, a
semismooth Newton method) then sets each entry's next state from where the proximal point

    p = clip(soft(w - g / c, l1 / c), lower, upper),     c = 2 diag(2 A + C) per shape

lands: on a bound or on zero (fixed there), else free with ``sign(p)``. When no state changes
the iterate satisfies the optimality conditions exactly; the loop stops earlier as soon as the
KKT residual (below) is under the tolerance. On the bundled ICT->Rocketbox take (1,000 frames,
52 shapes, bounds [0, 1]) it takes 5 active-set steps after the unbounded solve.

PDAS is not monotone and may cycle (the Hessian is not an M-matrix: with the L1 kink inside the
bounds correlated shapes trade signs, and with many shapes the markers cannot tell apart, e.g.
all 165 of the Rocketbox head on 41 markers, a few dozen entries flip back and forth). A run
ends when a state repeats, when three steps in a row do not halve the fewest state changes of
the run (the KKT residual of PDAS iterates jumps around even in a converging run, the number of
changes falls fast), or after ``max_iter`` steps; the solve then runs ADMM from the unbounded
minimiser, which converges for any convex problem. After 10, 30, 70, 150, ... iterations it
starts a new active-set run from the state of the ADMM iterate -- but only once that state has
settled (fewer than ``ADMM_SETTLED`` = 2 % of its active entries changed since the previous
round: a run from a moving state cycles, and an inner solve with 13,000 fixed entries costs
~0.3 s) or once ADMM has done as much work as the active-set steps so far (a deterministic
flop count, :func:`_solve_work`), or stops when the ADMM iterate itself meets the tolerance. Close to the solution the
state is right and one inner solve is exact, so the combination ends with the active-set
method's exactness and ADMM's guarantee.

ADMM and the penalty metric
---------------------------
ADMM splits ``W = Z`` (``W``: the spacetime energy, ``Z``: bounds and L1). Its W-update is
``(H + diag(rho) / 2) x = r + rho (z - u) / 2`` and must stay the fast banded solve. A penalty
``rho I`` does *not* keep the simultaneous diagonalisation of the solver's pencil ``(A, A + C)``:
``U^T U`` is not diagonal. It does keep the Kronecker form, because ``diag(rho)`` is the same
K x K matrix in every frame: it joins ``C`` and the pencil ``(A, A + C + diag(rho) / 2)`` is
diagonalised once more (``O(K^3)``, ~1 ms for K = 52) into K new tridiagonals
(:meth:`RangeSystem.shifted`). The alternative metric ``rho (A + C)`` would need no new
eigendecomposition (``U^T (A + C) U = I``), but then the Z-update, a projection onto the box
with soft thresholding, is no longer separable per weight. So the metric is Euclidean with a
per-shape ``rho_k = 0.03 * 2 (2 A + C)_kk`` (scaled to each shape's curvature; on the 165-shape
case 0.03 found the active set in half the iterations of 0.3 and of 0.01), relaxation 1.6,
residual balancing between rounds (``rho`` times 5 or 1/5 when the primal and dual residuals
differ by more than 100x; at 10x it fired after the first round and slowed the 165-shape case
twofold), and one eigendecomposition per ``rho``.

Measured on the real take (1,000 frames; ``OPENBLAS_NUM_THREADS=1``, as the CLI and the server
set it): 51 ARKit shapes, bounds [0, 1]: 6 active-set steps after the unbounded solve, 0.1 s;
the L1 kink (bounds [-0.2, 1], l1 = 1e-3 relative): 70 ADMM iterations + 5 steps, 0.2 s. All
165 shapes, bounds [0, 1], ridge 1e-5: the first run stops after 4 steps, then 150 ADMM
iterations (~7 ms each) and 15 steps in four runs are exact, 6-7.5 s (it was 2,550 ADMM
iterations and 47 steps, 33 s, without converging, before the change-count stall rule, the
settled-state and work rules and ``rho`` 0.03). At larger alpha (0.1-0.5) ADMM itself is slow
there (KKT 1e-7 after 2,550 iterations, 15 s, not converged); with the default ridge 1e-3 the
same solves are exact in 0.2-1.4 s. With l1 = 1e-3 (ridge 1e-3) half the entries are active:
the capacitance system of ~80,000 constraints cost 1-3 s per step (25 s in all); once a
step's fixed entries make the block sweep over each frame's free weights cheaper
(:func:`core.solvers.spacetime._block_is_cheaper`) the inner solve switches to it, 0.3-0.4 s
per step, 3.5 s in all. Spacetime with the position term on the full 2,028-frame take onto all
175 shapes (``beta = 1``): 65 s before that switch, 11 s with it; on the 51 ARKit shapes (60 %
of the entries on a bound) 1.8 s -> 1.3 s.

Tolerance
---------
The optimality conditions: with ``g = dE/dW`` and ``h(w) = l1 |w| + indicator[lower, upper]``,
``-g`` lies in the subdifferential of ``h`` at ``w`` for every free (not known) weight. The
violation of an entry (:func:`kkt_violation_per_entry`) is ``|g + l1 sign(w)|`` inside the bounds,
``max(0, -(g + h'(lower+)))`` at a lower bound, ``max(0, g + h'(upper-))`` at an upper one,
``max(0, |g| - l1)`` at zero between them, and ``||B^T B||_2`` times the distance outside the
bounds. The solve returns when the largest violation is at most::

    tol * ||B^T B||_2 * max(1, max |W|)          (tol = KKT_RTOL = 1e-9 by default)

evaluated with the gradient the inner solve returns, and checks it once more at the end with
the gradient written out term by term (:meth:`SpacetimeSolver.gradient`); ``info["kkt"]`` is that
last, independent value. Bounds hold exactly: fixed entries are set to their bound and the
result is clipped (the clip moves an entry by at most the tolerance).

Paths: the fast path needs what the unbounded fast path needs (no missing samples; uniform
marker or frame weights). Otherwise each inner solve is the exact block-tridiagonal sweep of
the general path with the fixed entries eliminated, ``O(T K^3)`` per step: correct, but seconds
for a 1,000-frame take (an edit window of a few dozen frames stays in milliseconds).

References
----------
1. Seol, Seo, Kim, Lewis, Noh 2012, Spacetime expression cloning for blendshapes. ACM TOG 31(2).
2. Hintermüller, Ito, Kunisch 2002, The primal-dual active set strategy as a semismooth Newton
   method. SIAM J. Optim. 13(3).
3. Boyd, Parikh, Chu, Peleato, Eckstein 2011, Distributed optimization and statistical learning
   via the alternating direction method of multipliers. Found. Trends Mach. Learn. 3(1).
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import warnings
from typing import Optional

import numba
import numpy as np
from threadpoolctl import ThreadpoolController

from ..cores import free_cores

__all__ = ["solve_bounded", "kkt_violation_per_entry", "KKT_RTOL"]

#: KKT tolerance of the bounded solver, relative: the largest violation of the optimality
#: conditions (see :meth:`core.solvers.spacetime.SpacetimeSolver.kkt_residual`) must be at most
#: ``KKT_RTOL * ||B^T B||_2 * max(1, max |W|)``
KKT_RTOL = 1e-9


def kkt_violation_per_entry(W, g, lower, upper, l1, scale: float, out=None) -> np.ndarray:
    """Per-entry violation of the optimality conditions (absolute, in gradient units).

    Parameters
    ----------
    W : (n, K) float
        Weights.
    g : (n, K) float
        ``dE/dW`` of the smooth terms at ``W``.
    lower, upper, l1 : (K,) float
        Bounds (``-inf``/``inf`` for none) and L1 weights (absolute).
    scale : float
        ``||B^T B||_2``: a weight at distance ``d`` outside its bounds violates by ``scale d``.
    out : (n, K) float, optional
        Where to write the result (C-contiguous).

    Returns
    -------
    (n, K) float >= 0. See the module docstring for the conditions.
    """
    W = np.asarray(W, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    if W.ndim != 2:
        raise ValueError("kkt_violation_per_entry: W must be (n, K)")
    K = W.shape[1]
    lo, hi, lam = (np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=np.float64), (K,))) for a in (lower, upper, l1))
    return _kkt_entries(W, np.broadcast_to(g, W.shape), lo, hi, lam, float(scale), bool((lam > 0).any()),
                        np.empty(W.shape) if out is None else out)


# compiled: the same conditions in numpy were ~15 masked passes over the (n, K) arrays, 3 ms per
# active-set step of a 1,000 x 165 take (10 % of a setting change), one pass here
@numba.njit(cache=True, nogil=True)
def _kkt_entries(W, g, lo, hi, lam, scale, use_l1, out):  # pragma: no cover
    """:func:`kkt_violation_per_entry` entry by entry (NaN anywhere -> inf)."""
    n, K = W.shape
    for t in range(n):
        for k in range(K):
            w, gk, lk, hk, mk = W[t, k], g[t, k], lo[k], hi[k], lam[k]
            if use_l1:
                slo = mk if lk >= 0 else -mk  # h'(lower+), h'(upper-) of h = l1 |w|: the L1 slopes just inside each bound
                shi = mk if hk > 0 else -mk
                v = abs(gk + mk * np.sign(w))  # free: |g + l1 sign(w)|
                if w == 0 and mk > 0 and lk < 0 and hk > 0:  # at the kink inside the bounds
                    v = abs(gk) - mk
                    v = v if v > 0 or v != v else 0.0
            else:
                slo = shi = 0.0
                v = abs(gk)
            if w == lk:
                v = -(gk + slo)
                v = v if v > 0 or v != v else 0.0
            elif w == hk:
                v = gk + shi
                v = v if v > 0 or v != v else 0.0
            d = max(lk - w, w - hk)  # > 0 outside the bounds
            if d > 0 and v == v and scale * d > v:
                v = scale * d
            out[t, k] = np.inf if v != v else v  # NaN (a failed solve) never passes
    return out


# -- the solvers' second thread (used by core.solvers.spacetime too: this module is the one both import)
#: (K, n) arrays from which the tridiagonal solves and the weights' product use the worker thread
#: (a hand-over costs ~50 us: a 1,000 x 165 solve is ~1 ms, a 50-frame one ~20 us)
_THREAD_ENTRIES = 50_000


def _both(f1, f2, threads: Optional[bool] = None):
    """``(f1(), f2())``, ``f2`` in the worker thread when a second core is free (numba's nogil
    kernels, BLAS and LAPACK run without the GIL; ``threads`` forces it either way): the same
    work, so the numbers never depend on which."""
    if threads if threads is not None else free_cores() >= 2:
        fut = _worker_pool().submit(f2)
        return f1(), fut.result()
    return f1(), f2()


@functools.lru_cache(maxsize=1)
def _worker_pool():
    """One worker thread for :func:`_both` (made on first use)."""
    return concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="spacetime")


if hasattr(os, "register_at_fork"):  # a forked child has the executor but not its thread: a new one
    os.register_at_fork(after_in_child=_worker_pool.cache_clear)


def _prox_state(X, c, lo, hi, lam, known, g=None, old=None, out=None):
    """Next state from the proximal point ``p = clip(soft(y, lam / c), lo, hi)`` of
    ``y = X - nan_to_num(g) / c`` (``X`` without ``g``), ``y = 0`` on the ``known`` entries:
    (fixed (n, K) bool -- never a known entry --, values (n, K), sign (n, K) of the free entries),
    the number of entries whose state differs from ``old`` (a state; 0 without), and the new
    state's :func:`_state_key`. ``c``, ``lo``, ``hi``, ``lam``: (K,) per shape. ``out``: three
    arrays to write the state into (a state no longer needed: fresh (n, K) arrays cost their page
    faults, ~0.6 ms a step at 1,000 x 165). Made by halves of frames, the second in the worker
    thread when a core is free."""
    n, K = X.shape
    # numba compiles read-only arrays (a cached hint) as another signature: copies instead
    X, g = (a if a is None or a.flags.writeable and a.flags.c_contiguous else np.array(a, dtype=np.float64)
            for a in (X, g))
    fixed, values, sign = out if out is not None else (np.empty((n, K), bool), np.empty((n, K)), np.empty((n, K)))
    G, use_l1, bits = X if g is None else g, bool(lam.any()), values.view(np.uint64)

    def rows(a, b):
        _prox_entries(X[a:b], G[a:b], g is not None, c, lo, hi, lam, use_l1, known[a:b], fixed[a:b], values[a:b],
                      sign[a:b])
        # the count in a pass of its own: fused into the one above it cost 5x as much
        ch = _state_changes(*(s[a:b] for s in (fixed, values, sign) + tuple(old))) if old is not None else 0
        return ch, _state_hash(fixed[a:b], bits[a:b], sign[a:b])

    (c1, h1), (c2, h2) = _by_halves(rows, n, n * K)
    return (fixed, values, sign), c1 + c2, _hash_pair(h1, h2)


def _by_halves(f, n, size):
    """``f(0, n // 2)`` and ``f(n // 2, n)``, the second in the worker thread when a core is free and ``size`` entries make the hand-over worth it (the same work either
    way: the same numbers)."""
    m = n // 2
    return _both(lambda: f(0, m), lambda: f(m, n), None if size >= _THREAD_ENTRIES else False)


def _hash_pair(h1, h2) -> int:
    return hash((int(h1), int(h2)))


@numba.njit(cache=True, nogil=True)
def _state_changes(f, v, s, f0, v0, s0):  # pragma: no cover
    """Entries whose state (fixed, value, sign) differs between two states (NaN != NaN)."""
    a, b, d, a0, b0, d0 = f.ravel(), v.ravel(), s.ravel(), f0.ravel(), v0.ravel(), s0.ravel()
    changes = 0
    for i in range(a.size):
        changes += np.int64((a[i] != a0[i]) | (b[i] != b0[i]) | (d[i] != d0[i]))
    return changes


# compiled: in numpy the next state was ~15 passes over the (n, K) arrays (the gradient step,
# nan_to_num, clip, the masks, where, the comparison with the previous state), ~2.5 ms per
# active-set step of a 1,000 x 165 take; one pass here, the same numbers bit for bit (numpy's
# clip, maximum and sign written out, -0.0 and NaN included)
@numba.njit(cache=True, nogil=True)
def _prox_entries(X, g, use_g, c, lo, hi, lam, use_l1, known, fixed, values, sign):  # pragma: no cover
    # every choice is a select on a bitwise-combined condition: numba compiles a plain ``a if x > 0
    # else b`` to a branch, mispredicted on these data (5x slower)
    n, K = X.shape
    big = np.finfo(np.float64).max
    for t in range(n):
        for k in range(K):
            y = X[t, k]
            if use_g:
                gk = g[t, k]
                gk = gk if (gk <= big) | (gk != gk) else big  # np.nan_to_num
                gk = gk if (gk >= -big) | (gk != gk) else -big
                gk = gk if (gk == gk) | False else 0.0
                y = y - gk / c[k]
            kn = known[t, k]
            y = y if (not kn) | False else 0.0
            lk, hk = lo[k], hi[k]
            if use_l1:
                a = abs(y) - lam[k] / c[k]
                a = a if (a >= 0.0) | (a != a) else 0.0  # np.maximum(a, 0)
                sy = (y > 0) * 1.0 - (y < 0) * 1.0  # np.sign (NaN: NaN)
                sy = sy if (y == y) | False else y
                x = sy * a
            else:
                x = y + 0.0
            # np.clip: NaN stays NaN
            x = x if (x > lk) | (x != x) else lk
            x = x if (x < hk) | (x != x) else hk
            f = (x == lk) | (x == hk) | (use_l1 & (lam[k] > 0) & (x == 0))
            v = x if f | False else 0.0
            sx = (x > 0) * 1.0 - (x < 0) * 1.0
            sx = sx if (x == x) | False else x
            s = sx if (not f) | False else 0.0
            fixed[t, k] = f & (not kn)
            values[t, k] = v
            sign[t, k] = s


def solve_bounded(system, lower, upper, l1, tol: float = KKT_RTOL, max_iter: int = 30,
                  max_solves: int = 2000, warm=None):
    """Minimise a range's spacetime energy + ``l1 ||W||_1`` with ``lower <= W <= upper``.

    Primal-dual active set with :meth:`RangeSystem.solve` as the exact inner solve, restarted
    from ADMM iterates when it cycles or stalls (see the module docstring).

    Parameters
    ----------
    system : core.solvers.spacetime.RangeSystem
        The range and its known entries (:meth:`SpacetimeSolver.range_system`).
    lower, upper : (K,) float
        Bounds per shape (``-inf``/``inf`` for none), ``lower <= upper``.
    l1 : (K,) float >= 0
        Absolute L1 weights.
    tol : float
        Relative KKT tolerance (module docstring).
    max_iter : int
        Primal-dual steps per run; a run also ends when a state repeats or three steps in a
        row do not halve its fewest state changes. 0: ADMM and no active-set step.
    max_solves : int
        Inner solves (active-set and ADMM together) before giving up with a warning.
    warm : (n, K) float, optional
        A previous solution of a similar problem (the same range after a setting change): the
        first active-set run starts from its state instead of the unbounded minimiser's. Only
        the start changes: the problem is strictly convex, so its minimiser is unique and an
        active-set run that settles ends on it, to rounding (the same final state gives the same
        numbers); a run that does not settle is dropped and the cold start follows. A hint of
        another shape, or with NaN, is ignored. On the sample (1,000 frames, 165 shapes) a step
        of alpha by 5 % takes 4 steps instead of 9; a jump by 2x or more gains little.

    Returns
    -------
    W : (n, K) float, inside the bounds, known entries exact
    info : dict with ``warm`` (with a hint: whether its run settled), ``iterations`` (inner
        solves), ``pdas`` (active-set steps), ``admm``
        (ADMM iterations), ``rho_changes``, ``work_pdas``/``work_admm`` (rough flops spent in each),
        ``active`` (entries on a bound or at an L1 zero, known ones excluded), ``kkt`` (final relative KKT residual, literal gradient), ``converged``
    """
    # one BLAS thread: the inner solves are thousands of K x K products and small factorisations,
    # which OpenBLAS's threads slow down about tenfold (the capacitance solve of 1,000 frames x 165
    # shapes: 2.1 s per step with the default threads on 2 cores, 0.2 s with one); the CLI and
    # the server set OPENBLAS_NUM_THREADS=1 themselves, a script or notebook need not
    if warm is not None:
        warm = np.asarray(warm, dtype=np.float64)
        if warm.shape != (system.n, system.K) or not np.isfinite(warm).all():
            warm = None  # a hint of another shape (another range, other shapes): not used
    with _blas_controller().limit(limits=1, user_api="blas"):
        return _solve_bounded(system, lower, upper, l1, tol, max_iter, max_solves, warm)


@functools.lru_cache(maxsize=1)
def _blas_controller():
    """threadpoolctl's view of the loaded BLAS libraries, made once: ``threadpool_limits``
    looks them up again on every call (0.5 ms and a read of the process's library list; a
    whole bounded solve of the benchmark case takes 50 ms). NumPy's BLAS is loaded by then."""
    return ThreadpoolController()


def _state_key(fixed, values, sign) -> int:
    """A 64-bit hash of an active-set state (the fixed mask, the values on it -- ``values`` is 0
    elsewhere --, the signs), for the cycle check: equal states have equal keys; two different
    states share one with probability ~2^-64 (a false "cycle" ends the run early, and ADMM goes on
    from there). One compiled pass: the bytes of the three (n, K) arrays hashed by Python were
    ~1 ms a step on a 1,000 x 165 take."""
    fixed = np.ascontiguousarray(fixed)
    bits = np.ascontiguousarray(values, dtype=np.float64).view(np.uint64)
    sign = np.ascontiguousarray(sign, dtype=np.float64)
    # by halves of rows, as :func:`_prox_state` makes the key of the states it returns
    h1, h2 = _by_halves(lambda a, b: _state_hash(fixed[a:b], bits[a:b], sign[a:b]), len(fixed), fixed.size)
    return _hash_pair(h1, h2)


@numba.njit(cache=True, nogil=True)
def _state_hash(fixed, bits, sign):  # pragma: no cover
    """A polynomial hash mod 2^64 of the entries' codes (sign 0 / 1 / -1 / NaN, fixed or not)
    and, when fixed, their values' bits; finished by splitmix64's finaliser."""
    n, K = fixed.shape
    h = np.uint64(14695981039346656037)
    prime = np.uint64(0x100000001B3)
    for t in range(n):
        for k in range(K):
            s = sign[t, k]
            f = fixed[t, k]
            code = 1 + (s > 0) * 1 + (s < 0) * 2 + (s != s) * 3 + f * 4
            h = h * prime + np.uint64(code)
            if f:
                h = h * prime + bits[t, k]
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def _solve_bounded(system, lower, upper, l1, tol, max_iter, max_solves, warm=None):
    n, K = system.n, system.K
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (n, K))
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (n, K))
    lam = np.broadcast_to(np.asarray(l1, dtype=np.float64), (n, K))
    c = np.broadcast_to(np.maximum(system.curvature, 1e-300), (n, K))
    known = system.fixed
    use_l1 = bool((lam[~known] > 0).any()) if (~known).any() else False
    info = {"iterations": 0, "pdas": 0, "admm": 0, "rho_changes": 0, "work_pdas": 0.0, "work_admm": 0.0}

    free = ~known
    anyfree = bool(free.any())

    kkt_out = np.empty((n, K))  # one buffer for every step's per-entry residual (no page faults)

    def residual(X, g):
        if not anyfree:
            return 0.0
        v = kkt_violation_per_entry(X, g, lo[0], hi[0], lam[0], system.scale, kkt_out)
        return float(np.max(v, where=free, initial=0.0))  # v >= 0 (a boolean gather: 3x the time)

    def small(X, r):
        return r <= tol * system.scale * max(1.0, float(np.abs(X).max()))

    per_shape = [np.array(a[0]) for a in (c, lo, hi, lam)]  # writable copies: one compiled signature

    def state_of(X, g=None, old=None, out=None):
        """(the state of the proximal point of X - g / c, changes from ``old``, its key)"""
        return _prox_state(X, *per_shape, known, g, old, out)

    def pdas(state):
        """Active-set steps from a state; returns (done, X, g)."""
        fixed, values, sign = state
        seen, fewest, stall = set(), np.inf, 0
        X = g = None
        spare = None  # the arrays of a state of this run no longer needed (never the caller's)
        key = _state_key(fixed, values, sign)
        for _ in range(max_iter):
            if key in seen or info["iterations"] >= max_solves:
                break  # a cycle: PDAS is not monotone
            seen.add(key)
            X, g = system.solve(fixed, values, -0.5 * lam * sign if use_l1 else None)
            info["iterations"] += 1
            info["pdas"] += 1
            info["work_pdas"] += _solve_work(n, K, int(np.count_nonzero(fixed)))
            r = residual(X, g)
            if small(X, r):
                return True, X, g
            (nf, nv, ns), changes, key = state_of(X, g, (fixed, values, sign), spare)
            if changes == 0:
                return True, X, g  # the state's own KKT point (to rounding): nothing left to change
            # progress is the number of state changes halving (the KKT residual of PDAS iterates jumps
            # around even when the run converges; a cycling run keeps changing the same entries)
            if changes < 0.5 * fewest:
                fewest, stall = changes, 0
            else:
                stall += 1
                if stall >= 3:
                    break
            spare = (fixed, values, sign) if spare is not None or fixed is not state[0] else None
            fixed, values, sign = nf, nv, ns
        return False, X, g

    if warm is not None and max_iter > 0:
        # an active-set run from the state of a previous solution (a neighbouring setting): the
        # minimiser is unique, so where this run ends (on an exact KKT point) the cold start ends too
        cold = dict(info)
        done, X1, g1 = pdas(state_of(warm)[0])
        if done:
            info["warm"] = True
            return _finish(system, X1, lo, hi, lam, known, info, tol, True)
        info = cold  # not settled: the cold start below, as if no hint had come
        info["warm"] = False
    # start: the unbounded minimiser (no L1), soft-thresholded and clipped
    X, g = system.solve()
    info["iterations"] += 1
    state = state_of(X)[0]
    if not (state[0].any() or (use_l1 and (state[2] != 0).any())) and small(X, residual(X, g)):
        done = True  # no bound or L1 zero is active: the unbounded solution is the answer
    else:
        done, X1, g1 = pdas(state) if max_iter > 0 else (False, None, None)
        if done:  # else ADMM starts from the unbounded minimiser (a failed run's iterate starts it worse)
            X, g = X1, g1
    if not done:
        done, X, g = _admm_restarts(system, X, g, lo, hi, lam, c, known, info, max_solves, pdas, state_of,
                                    residual, small)
    return _finish(system, X, lo, hi, lam, known, info, tol, done)


def _finish(system, X, lo, hi, lam, known, info, tol, done):
    """The answer of a run that ended on ``X``: clipped, known entries exact, its KKT residual
    measured with the literal gradient; warns when it did not converge."""
    n, K = system.n, system.K
    X = np.clip(X, lo, hi)
    X[known] = system.values[known]
    gl = system.gradient(X)
    v = kkt_violation_per_entry(X, gl, lo[0], hi[0], lam[0], system.scale)[~known]
    info["kkt"] = float(v.max() / (system.scale * max(1.0, float(np.abs(X).max())))) if v.size else 0.0
    at = ((X == lo) | (X == hi) | ((lam > 0) & (X == 0))) & ~known
    info["active"] = int(at.sum())
    info["converged"] = bool(done and info["kkt"] <= tol)
    if not info["converged"]:
        warnings.warn(
            f"bounded spacetime solve of frames {system.lo}..{system.hi}: KKT residual {info['kkt']:.1e} "
            f"> tol {tol:.0e} after {info['iterations']} inner solves ({K} shapes: shapes the markers cannot tell "
            "apart make the active-set method cycle; solving on fewer shapes, e.g. the ARKit ones, converges in "
            "a few steps)",
            RuntimeWarning, stacklevel=4,
        )
    return X, info


#: ADMM penalty per shape, relative to the shape's curvature 2 (2 A + C)_kk (see ``_admm_restarts``)
ADMM_SIGMA = 0.03
#: an active-set run starts from an ADMM iterate once fewer than this fraction of its active entries
#: changed state since the previous round
ADMM_SETTLED = 0.02
#: ADMM over-relaxation (Boyd et al. 2011, §3.4.3)
ADMM_RELAX = 1.6


def _solve_work(n, K, p):
    """Flops, roughly, of one inner solve with ``p`` fixed entries (two K x K transforms of n
    frames plus the capacitance recursion, :func:`core.solvers.spacetime._capacitance_solve`):
    a deterministic clock to share the time between ADMM and active-set runs."""
    return 4.0 * n * K * K + p * (32.0 + K) * K


def _admm_restarts(system, X, g, lo, hi, lam, c, known, info, max_solves, pdas, state_of, residual, small):
    """ADMM on ``W = Z`` (W: the spacetime energy, Z: bounds + L1), with active-set runs from its
    iterates after 10, 20, 40, ... iterations; ADMM converges for any convex problem, and once
    its iterate is close enough the active-set run from its state is exact (or ADMM's iterate
    itself meets the tolerance). Returns (done, X, g)."""
    # (a shape no marker sees and no prior or ridge pins has no curvature: floor it)
    rho = ADMM_SIGMA * np.maximum(np.asarray(system.curvature, dtype=np.float64), 1e-9 * system.scale)
    step = system.shifted(rho)
    z = np.clip(np.where(known, system.values, X), lo, hi)
    u = np.where(known, 0.0, -np.nan_to_num(g) / rho)  # scaled dual: dE/dW = -rho u at a fixed point
    rounds = 10
    prev = None  # the state of the previous round's iterate
    while info["iterations"] < max_solves:
        for _ in range(rounds):
            x = step(0.5 * rho * (z - u))
            xh = ADMM_RELAX * x + (1.0 - ADMM_RELAX) * z
            v = xh + u
            z_prev = z
            z = np.clip(np.sign(v) * np.maximum(np.abs(v) - lam / rho, 0.0), lo, hi)
            z[known] = system.values[known]
            u += xh - z
            info["iterations"] += 1
            info["admm"] += 1
        info["work_admm"] += rounds * _solve_work(system.n, system.K, 0)
        # residual balancing (Boyd et al. 2011, §3.4.1): a new rho costs one eigendecomposition
        rp = np.abs(x - z).max() / max(np.abs(x).max(), np.abs(z).max(), 1e-300)
        rd = np.abs(rho * (z - z_prev)).max() / max(np.abs(rho * u).max(), 1e-300)
        if rp > 100 * rd or rd > 100 * rp:
            f = 5.0 if rp > rd else 0.2
            rho, u = rho * f, u / f
            step = system.shifted(rho)
            info["rho_changes"] += 1
        gz = system.gradient(z)
        if small(z, residual(z, gz)):
            return True, z, gz  # ADMM itself is within the tolerance
        # the state ADMM's iterate is in: on a bound / at the L1 kink (exactly, from the prox) or free
        fixed = ((z == lo) | (z == hi) | ((lam > 0) & (z == 0))) & ~known
        sign = np.where(fixed | known, 0.0, np.sign(z))
        moved = np.inf if prev is None else np.count_nonzero((fixed != prev[0]) | (sign != prev[1]))
        prev = fixed, sign
        rounds *= 2
        if moved > ADMM_SETTLED * max(int(fixed.sum()), 1) and info["work_pdas"] > info["work_admm"]:
            # the iterate's state still moves: an active-set run from it would likely cycle, and
            # active-set steps have already cost more than ADMM (one costs ~0.3 s with 13,000
            # entries fixed and K = 165; an ADMM iteration ~7 ms)
            continue
        done, X1, g1 = pdas((fixed, np.where(fixed, z, 0.0), sign))
        if done:
            return True, X1, g1
    return False, z, system.gradient(z)
