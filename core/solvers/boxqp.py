"""Box-constrained QPs along a sequence of frames: a parametric active-set method, compiled.

The problem
-----------
For every frame t and chain c (a region, or the single global problem)::

    min_u  1/2 u^T H_{idx[t,c]} u + f_{t,c}^T u      s.t.   0 <= u <= 1                  (1)

with symmetric positive-definite Hessians ``H`` (a small table indexed per problem) and linear
terms that change slowly from frame to frame. :func:`core.solvers.baselines.range_pf` (per-frame
bounded least squares, ``H = B_v^T B_v``) and the box form of Liu et al. 2011 eq. 2
(:class:`core.solvers.local.LocalProblem`) are both (1) after ``w = lower + (upper - lower) u``.

The method (parametric active set, "online active set strategy")
----------------------------------------------------------------
Let ``u*`` be optimal for ``f_0`` with working set (lower / upper / free) ``W`` and multipliers
``lambda = H u* + f_0`` (``>= 0`` at lower bounds, ``<= 0`` at upper, ``0`` on the free set).
Along ``f(tau) = f_0 + tau (f_1 - f_0)``, ``tau`` in [0, 1], the optimum is piecewise linear in
``tau``: while ``W`` holds, ``du/dtau = -H_FF^-1 (f_1 - f_0)_F`` on the free set ``F`` and the
multipliers move linearly. The next breakpoint is the smallest step at which a free variable
reaches a bound (it joins the bound) or a multiplier reaches zero (its variable is freed) [1, 2].
One index changes per breakpoint, so the Cholesky factor ``H_FF = R^T R`` is updated, not
recomputed: a column appended in ``O(|F|^2)`` (one triangular solve), a column deleted in
``O(|F|^2)`` (Givens rotations restore the triangle) [4, §12.5]. Every frame starts from the
previous frame's solution, so it costs 1 + (number of active-set changes) segments. The
previous working set is tried first: ``u + d`` (the first segment taken to ``tau = 1``) is
accepted outright when it passes the certificate below, which skips the ratio test for a frame
whose set does not change (81 % of the local benchmark's frames, 42 % of the 165-shape sample's).

Any feasible ``u`` with sign-clamped multipliers is an exact optimum of *some* ``f_0``
(``f_0 = lambda - H u``), so every start is consistent: the previous frame (warm), ``u = 0`` with
positive multipliers (cold: about as many breakpoints as free variables), or a point given by
the caller (``warm``).

Running it
----------
Each chain is walked frame by frame in compiled code (numba, ``_solve_chains``): the method is
sequential per chain and its steps are ``O(K^2)`` scalar loops. The numpy version it replaces
advanced lanes of frames in batched rounds and paid ~1 ms of call overhead per round for ~34
lanes moving (291 rounds on the ``bounded_perframe`` sample: 3,600 frames/s on a loaded machine,
where ~10,000 were wanted). Chains are cut into pieces of at most :data:`PIECE` frames, each
started cold, and the pieces are shared among the process's cores (the kernel releases the GIL).
The cut is a fixed rule, so the result does not depend on the number of cores. The kernel is
compiled once after an install (~6 s of CPU; numba's cache next to this module) and loaded from
that cache by later processes (~0.5 s, numba's start-up): :func:`warm`, :func:`kernel_cached`.

Exactness
---------
At ``tau = 1`` the frame is accepted only after its KKT conditions are checked with the gradient
``g = H u + f`` computed from scratch (after one step of iterative refinement with the factor
where the stationarity residual is not tiny): ``|g_F| <= eps_l``, ``-eps_u <= u_F <= 1 + eps_u``,
``g_L >= -eps_l``, ``g_U <= eps_l`` with ``eps_u = 1e-11`` and ``eps_l = 1e-11 (mean diag H +
max |f|)`` (the tests of :func:`core.solvers.qp.solve_qp_batch`). A frame that fails is repaired
at ``tau = 1`` (the worst violator changes side, the free set is solved afresh with a new
factor); the few that still fail are
finished by primal-dual active-set steps [3] and the finite primal active-set method of
:func:`core.solvers.qp.primal_active_set` (counted in ``info["fallback"]``). The answer is
therefore the optimum to the KKT tolerance, not to an iteration tolerance.

What the tolerance leaves open: where ``H`` is ill-conditioned (the local solve's ridge of
``1e-9`` mean diag: condition numbers up to ~1e10) a gradient tolerance ``eps_l`` admits weights
that differ by up to ``~eps_l / lambda_min(H)`` along the weakly penalised directions, and a
multiplier within ``eps_l`` of zero admits either working set. Two correct solvers, or one
started from other points (the numpy lanes with another ``block``; other pieces), may then
return weights that differ visibly (2e-2 measured on the local box benchmark, in the regions
whose Hessians are nearly singular; 1e-11 in the well-conditioned ones) with objectives equal to
~1e-13 relative. The minimiser is unique; the answer is pinned down to that tolerance, not
tighter. For a given input the result is deterministic.

References
----------
.. [1] M. J. Best, "An algorithm for the solution of the parametric quadratic programming
       problem", in Applied Mathematics and Parallel Computing, 1996, pp. 57-76.
.. [2] H. J. Ferreau, H. G. Bock, M. Diehl, "An online active set strategy to overcome the
       limitations of explicit MPC", Int. J. Robust Nonlinear Control 18(8), 2008 (qpOASES).
.. [3] M. Hintermueller, K. Ito, K. Kunisch, "The primal-dual active set strategy as a semismooth
       Newton method", SIAM J. Optim. 13(3), 2003 (the fallback's first steps).
.. [4] G. H. Golub, C. F. Van Loan, "Matrix Computations", 4th ed., 2013 (§6.5.4 and §12.5:
       updating the Cholesky / QR factorisation after adding or deleting a column).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import scipy.linalg

from core.solvers.qp import primal_active_set, solve_eqp_batch

__all__ = ["solve_box_sequence", "solve_box_frame"]

EPS_U = 1e-11  # primal tolerance in unit-box coordinates
EPS_L = 1e-11  # dual tolerance relative to mean diag H + max |f|
PIECE = 1024  # frames per piece of a chain (each starts cold; pieces run on separate cores)
_THREAD_WORK = 2e6  # T C K^2 below which one thread does it all (a thread costs ~0.1 ms)
_FREE, _LOWER, _UPPER = 0, 1, 2  # working-set codes of the compiled kernel
_SEGMENTS, _FACTORISATIONS, _REPAIRS, _FALLBACK, _KEPT = range(5)  # counters of the compiled kernel


def _threads(work: float) -> int:
    """Threads for a solve of ``work`` = T C K^2: the cores this process may use, one for small
    solves."""
    if work < _THREAD_WORK:
        return 1
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def _hmul(H, h, X):
    """``H[h[n]] @ X[n]`` for X (n, K), or ``X[n] @ H[h[n]]`` for X (n, m, K); H symmetric."""
    if len(H) == 1:
        return (X.reshape(-1, H.shape[1]) @ H[0]).reshape(X.shape)
    if X.ndim == 2:
        return np.einsum("nij,nj->ni", H[h], X)
    return X @ H[h]


def _kkt_ok(u, g, lower, upper, eps_l):
    """Rows of (n, ..., K) arrays that satisfy the box KKT conditions at tolerance (see module)."""
    free = ~(lower | upper)
    bad = (free & ((u < -EPS_U) | (u > 1 + EPS_U) | (np.abs(g) > eps_l))) | (lower & (g < -eps_l)) | (upper & (g > eps_l))
    return ~bad.any(-1)


def _finish(H, f, h, lower, upper, eps_l, pdas_steps=6):
    """Exact solutions for the (few) frames the homotopy could not certify.

    Primal-dual active-set steps [3] from the lane's (nearly right) working set, then the finite
    primal active-set method for whatever has not settled.
    """
    n = len(f)
    u = np.zeros_like(f)
    todo = np.arange(n)
    lower, upper = lower.copy(), upper.copy()
    ut = np.zeros_like(f)
    same = np.zeros(0, bool)
    for _ in range(pdas_steps):
        lo, up = lower[todo], upper[todo]
        ut, _ = solve_eqp_batch(H, f[todo], h[todo], lo, up, np.zeros(len(todo), bool))
        g = _hmul(H, h[todo], ut) + f[todo]
        el = eps_l[todo][:, None]
        new_up = np.where(up, g <= el, ut > 1 + EPS_U)
        new_lo = np.where(lo, g >= -el, ut < -EPS_U) & ~new_up
        same = (new_lo == lo).all(1) & (new_up == up).all(1)
        u[todo[same]] = ut[same]
        lower[todo], upper[todo] = new_lo, new_up
        todo = todo[~same]
        if not len(todo):
            return np.clip(u, 0.0, 1.0)
    start = np.clip(ut[~same], 0.0, 1.0)
    u[todo], _ = primal_active_set(H, f[todo], h[todo], False, EPS_U, eps_l[todo], init=start)
    return np.clip(u, 0.0, 1.0)


def solve_box_sequence(H, f, idx=None, refresh: int = 64, return_info: bool = False, warm=None):
    """Solve (1) of the module docstring for every frame, warm-started along the frames.

    ``min_u 1/2 u^T H_{idx[t,c]} u + f[t,c]^T u``  s.t. ``0 <= u <= 1``, exactly (KKT conditions
    checked at ``1e-11`` relative tolerances for every frame; module docstring, *Exactness*).

    Parameters
    ----------
    H : (P, K, K) float
        Symmetric positive-definite Hessians.
    f : (T, K) or (T, C, K) float
        Linear terms; axis 0 is time (consecutive frames are similar), C independent chains.
    idx : (T,) or (T, C) int, optional
        Which Hessian each problem uses; default 0 (then P must be 1).
    refresh : int
        Updates of the Cholesky factor (added or deleted columns) before it is recomputed from
        scratch (Givens updates are stable; this bounds the drift of long chains). The result
        does not depend on it beyond the KKT tolerance.
    return_info : bool
    warm : (K,) or (C, K) float, optional
        A point in the unit box to start frame 0 of each chain from instead of cold (the
        previous frame's solution when frames arrive one at a time, :mod:`core.live`): it is
        the exact optimum of ``f_0 = lambda - H u`` with ``lambda`` the sign-clamped gradient
        (module docstring), so the homotopy to frame 0 costs 1 + its active-set changes.

    Returns
    -------
    U : same shape as ``f``, float64, in [0, 1]
    info : dict (when ``return_info``): ``segments`` (homotopy segments over all frames),
        ``factorisations`` (Cholesky factors computed from scratch), ``repairs`` (certificates
        that failed at ``tau = 1`` and were repaired with the chain's factor), ``fallback``
        (frames finished by the exact PDAS / primal active-set fallback).

    Raises
    ------
    ValueError
        Shapes that disagree, or ``idx`` out of range.
    """
    H = np.asarray(H, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64)
    if H.ndim != 3 or H.shape[1] != H.shape[2]:
        raise ValueError(f"H: expected (P, K, K), got {H.shape}")
    K = H.shape[1]
    squeeze = f.ndim == 2
    if squeeze:
        f = f[:, None]
    if f.ndim != 3 or f.shape[2] != K:
        raise ValueError(f"f: expected (T, {K}) or (T, C, {K}), got {f.shape}")
    T, C = f.shape[:2]
    if idx is None:
        if len(H) != 1:
            raise ValueError(f"idx omitted: H must hold one Hessian, got {len(H)}")
        idx = np.zeros((T, C), np.int64)
    idx = np.asarray(idx, dtype=np.int64).reshape(T, -1) if np.ndim(idx) else np.full((T, C), int(idx))
    if idx.shape != (T, C) or (idx.size and (idx.min() < 0 or idx.max() >= len(H))):
        raise ValueError(f"idx: expected ({T}, {C}) ints in [0, {len(H)}), got shape {np.shape(idx)}")
    stats = np.zeros(5, np.int64)
    U = np.zeros((T, C, K))
    if T and C and K:
        scale = np.einsum("pii->p", H) / K
        start = np.zeros((C, K)) if warm is None else np.broadcast_to(np.asarray(warm, dtype=np.float64), (C, K))
        flag = np.zeros((T, C), np.bool_)
        # pieces: every chain cut into runs of at most PIECE frames (a cold start each), a fixed
        # rule so that the result does not depend on the number of cores that share them out
        cuts = -(-T // PIECE)
        bounds = (np.arange(cuts + 1) * T) // cuts
        pieces = np.array([(c, bounds[i], bounds[i + 1]) for c in range(C) for i in range(cuts)], np.int64)
        args = (np.ascontiguousarray(H), np.ascontiguousarray(f), np.ascontiguousarray(idx), scale)
        tail = (np.ascontiguousarray(start), warm is not None, max(1, int(refresh)), U, flag)
        n_work = min(len(pieces), _threads(T * C * K * K))
        if n_work == 1:
            _solve_chains(*args, pieces, *tail, stats)
        else:  # the kernel releases the GIL: the pieces, longest first, shared among threads
            order = pieces[np.argsort(-(pieces[:, 2] - pieces[:, 1]), kind="stable")]
            parts = [np.ascontiguousarray(order[i::n_work]) for i in range(n_work)]
            counts = np.zeros((n_work, len(stats)), np.int64)
            with ThreadPoolExecutor(n_work) as pool:
                list(pool.map(lambda i: _solve_chains(*args, parts[i], *tail, counts[i]), range(n_work)))
            stats += counts.sum(0)
        if flag.any():  # the exact fallback, from the working set the kernel ended with
            tt, cc = np.nonzero(flag)
            ub, ff = U[tt, cc], f[tt, cc]
            U[tt, cc] = _finish(H, ff, idx[tt, cc], ub <= 0.0, ub >= 1.0, EPS_L * (scale[idx[tt, cc]] + np.abs(ff).max(1)))
    if squeeze:
        U = U[:, 0]
    info = dict(segments=int(stats[_SEGMENTS]), factorisations=int(stats[_FACTORISATIONS]),
                repairs=int(stats[_REPAIRS]), fallback=int(stats[_FALLBACK]), kept=int(stats[_KEPT]))
    return (U, info) if return_info else U


def solve_box_frame(H, f, warm, memo: dict) -> np.ndarray:
    """One frame of (1), ``H`` (K, K), ``f`` (K,), started from the previous frame's point
    ``warm`` (K,): first the working set ``warm`` sits in is tried outright (the free block's
    Cholesky factor kept in ``memo`` while the set does not change, so an unchanged set costs two
    triangular solves), accepted only if it passes the KKT check of :func:`solve_box_sequence`;
    otherwise the warm-started homotopy of :func:`solve_box_sequence`. Exact either way.

    Returns u (K,) in [0, 1]."""
    lower, upper = warm <= 0.0, warm >= 1.0
    free = ~(lower | upper)
    key = (lower.tobytes(), upper.tobytes())
    if memo.get("key") != key:
        F = np.flatnonzero(free)
        memo["key"], memo["F"], memo["U"] = key, F, np.flatnonzero(upper)
        memo["chol"] = None
        if len(F):
            try:
                memo["chol"] = scipy.linalg.cho_factor(H[np.ix_(F, F)], lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                memo["key"] = None
    F, U = memo["F"], memo["U"]
    if memo.get("key") == key and (memo["chol"] is not None or not len(F)):
        u = upper.astype(np.float64)
        if len(F):
            rhs = -(f[F] + H[np.ix_(F, U)].sum(1)) if len(U) else -f[F]
            u[F] = scipy.linalg.cho_solve(memo["chol"], rhs, check_finite=False)
        g = H @ u + f
        eps = EPS_L * (np.trace(H) / len(H) + np.abs(f).max())
        if _kkt_ok(u, g, lower, upper, eps):
            return np.clip(u, 0.0, 1.0)
    return solve_box_sequence(H[None], f[None], warm=warm)[0]


def warm() -> None:
    """Compile the kernel (the first call after an install or a change of this file: ~6 s of CPU,
    written to numba's cache next to this module) or load it from that cache (~0.5 s: numba's
    LLVM start-up), with a one-frame problem. :func:`dashboard.serve.serve` runs it in a separate
    process at start-up when :func:`kernel_cached` says the cache is cold, so no request pays
    the compile."""
    solve_box_sequence(np.eye(2)[None], np.ones((1, 2)))


def kernel_cached() -> bool:
    """Whether numba's on-disk cache holds the kernel for this version of the module (an index
    whose stamp, numba's hash of the source, matches), so the first call loads it instead of
    compiling it."""
    try:
        return bool(_solve_chains._cache._cache_file._load_index())  # numba has no public query
    except Exception:  # noqa: BLE001 -- a private API: anything unexpected means "not known to be cached"
        return False


# ---------------------------------------------------------------------------- the compiled kernel
# Cholesky factor of the free block, upper triangular: H_FF = R^T R, R[:n, :n], the free variables
# in factor order F[:n]. Rows of R are contiguous, so every inner loop runs along a row.

@numba.njit(cache=True, nogil=True)
def _chol_append(R, n, Hh, F, j, w):
    """Variable ``j`` joins the free set at position ``n``: column n of R solves
    ``R^T r = H_Fj``, ``R_nn = sqrt(H_jj - r^T r)``. False (R unchanged) when that is not
    positive, i.e. H_FF + j is numerically singular."""
    for a in range(n):
        w[a] = Hh[j, F[a]]
    for a in range(n):
        w[a] /= R[a, a]
        wa = w[a]
        for k in range(a + 1, n):
            w[k] -= wa * R[a, k]
    s = Hh[j, j]
    for a in range(n):
        s -= w[a] * w[a]
    if not s > 1e-15 * abs(Hh[j, j]):
        return False
    for a in range(n):
        R[a, n] = w[a]
    R[n, n] = np.sqrt(s)
    F[n] = j
    return True


@numba.njit(cache=True, nogil=True)
def _chol_delete(R, n, F, p):
    """The free variable at position ``p`` leaves: column p is deleted and the Hessenberg rows
    below it are rotated back to a triangle (Givens, Golub & Van Loan §12.5)."""
    for a in range(n):
        for k in range(max(p, a - 1), n - 1):
            R[a, k] = R[a, k + 1]
    for k in range(p, n - 1):
        F[k] = F[k + 1]
    for k in range(p, n - 1):
        x, y = R[k, k], R[k + 1, k]
        r = np.sqrt(x * x + y * y)
        R[k + 1, k] = 0.0
        if r == 0.0:
            continue
        c, s = x / r, y / r
        R[k, k] = r
        for m in range(k + 1, n - 1):
            x, y = R[k, m], R[k + 1, m]
            R[k, m] = c * x + s * y
            R[k + 1, m] = c * y - s * x


@numba.njit(cache=True, nogil=True)
def _chol_solve(R, n, x):
    """``x[:n] <- (R^T R)^-1 x[:n]`` in place."""
    for a in range(n):
        x[a] /= R[a, a]
        xa = x[a]
        for k in range(a + 1, n):
            x[k] -= xa * R[a, k]
    for a in range(n - 1, -1, -1):
        s = x[a]
        for k in range(a + 1, n):
            s -= R[a, k] * x[k]
        x[a] = s / R[a, a]


@numba.njit(cache=True, nogil=True)
def _factor(R, Hh, st, F, w):
    """Factor of the free block from scratch; returns its size, -1 when H_FF is singular."""
    n = 0
    for j in range(len(st)):
        if st[j] == _FREE:
            if not _chol_append(R, n, Hh, F, j, w):
                return -1
            n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _gradient(Hh, ft, u, g):
    """``g = H u + f`` (rows of H where u is non-zero)."""
    K = len(u)
    for j in range(K):
        g[j] = ft[j]
    for k in range(K):
        uk = u[k]
        if uk != 0.0:
            for j in range(K):
                g[j] += Hh[k, j] * uk


@numba.njit(cache=True, nogil=True)
def _violation(u, g, st, el):
    """The worst KKT violator in tolerance units (module docstring): ``(j, score)``, score <= 1
    everywhere means the point passes; ``j = -2`` flags a stationarity residual only."""
    jb, best, resid = -1, 1.0, False
    for j in range(len(u)):
        if st[j] == _FREE:
            s = max(-u[j], u[j] - 1.0) / EPS_U
            if abs(g[j]) > el:
                resid = True
        elif st[j] == _LOWER:
            s = -g[j] / el
        else:
            s = g[j] / el
        if s > best:
            jb, best = j, s
    if jb < 0 and resid:
        jb = -2
    return jb


@numba.njit(cache=True, nogil=True)
def _certify(Hh, ft, el, st, F, n, R, u, g, x, fresh):
    """At tau = 1: ``g = H u + f`` from scratch at the path's point (``fresh``: with the free
    variables solved afresh, ``u_F = -H_FF^-1 (f_F + H_FU 1)``), one step of iterative refinement
    where the stationarity residual is not tiny. Returns the worst violator as
    :func:`_violation` (-1: the frame is certified)."""
    K = len(u)
    if fresh:
        for k in range(K):
            u[k] = 1.0 if st[k] == _UPPER else 0.0
        _gradient(Hh, ft, u, g)  # f + H_:U 1
        for a in range(n):
            x[a] = -g[F[a]]
        _chol_solve(R, n, x)
        for a in range(n):
            u[F[a]] = x[a]
    _gradient(Hh, ft, u, g)
    small = True
    for a in range(n):
        if abs(g[F[a]]) > 0.1 * el:
            small = False
    if not small:
        for a in range(n):
            x[a] = -g[F[a]]
        _chol_solve(R, n, x)
        for a in range(n):
            u[F[a]] += x[a]
        _gradient(Hh, ft, u, g)
    return _violation(u, g, st, el)


@numba.njit(cache=True, nogil=True)
def _solve_chains(H, f, idx, scale, pieces, warm, use_warm, refresh, U, flag, stats):
    """Every piece (chain c, frames t0 <= t < t1; rows of ``pieces``, (n, 3) int), frame by frame:
    the homotopy from the previous frame's optimum (module docstring), certification and repair
    at tau = 1. ``scale`` (P,): mean diag of each Hessian (``eps_l = EPS_L (scale + max |f|)``).
    A piece starts cold, or from ``warm[c]`` when ``use_warm`` and ``t0 == 0``. Writes ``U``
    (T, C, K) clipped to [0, 1], ``flag`` (T, C) (frames left to the exact fallback) and the
    counters ``stats``."""
    T, C, K = f.shape
    R = np.zeros((K, K))
    F = np.zeros(K, np.int64)
    st = np.zeros(K, np.int8)
    u, g, d, gam, delta = np.zeros(K), np.zeros(K), np.zeros(K), np.zeros(K), np.zeros(K)
    x, w, hu, us, gs = np.zeros(K), np.zeros(K), np.zeros(K), np.zeros(K), np.zeros(K)
    max_seg = 4 * K + 20
    max_rep = 2 * K + 10
    for i in range(len(pieces)):
        c, t0, t1 = pieces[i, 0], pieces[i, 1], pieces[i, 2]
        h, n, nupd, cold = -1, 0, 0, not (use_warm and t0 == 0)
        for t in range(t0, t1):
            ht = idx[t, c]
            Hh = H[ht]
            ft = f[t, c]
            fmax = 0.0
            for j in range(K):
                fmax = max(fmax, abs(ft[j]))
            el = EPS_L * (scale[ht] + fmax)
            # ---- the start: u optimal for f_0 = lam - H u (lam: sign-clamped gradient, now in g)
            if cold:  # u = 0 is the exact optimum of f_0 = max(f, 0) + margin
                for j in range(K):
                    u[j] = 0.0
                    st[j] = _LOWER
                    g[j] = max(ft[j], 0.0) + 1e-3 * fmax + 1e-300
                    delta[j] = ft[j] - g[j]
                n, h, nupd, cold, warm_start = 0, ht, 0, False, False
            else:
                warm_start = True
                if t == t0:  # the caller's point: its working set and gradient
                    for j in range(K):
                        u[j] = min(max(warm[c, j], 0.0), 1.0)
                        st[j] = _LOWER if u[j] <= 0.0 else (_UPPER if u[j] >= 1.0 else _FREE)
                    _gradient(Hh, ft, u, g)
                    h = -1
                if ht == h:  # H u = g - f_prev
                    fp = f[t - 1, c]
                    for j in range(K):
                        hu[j] = g[j] - fp[j]
                else:
                    _gradient(Hh, ft, u, hu)
                    for j in range(K):
                        hu[j] -= ft[j]
                    h = ht
                    nupd = refresh
                for j in range(K):
                    lam = 0.0 if st[j] == _FREE else (max(g[j], 0.0) if st[j] == _LOWER else min(g[j], 0.0))
                    g[j] = lam
                    delta[j] = ft[j] - lam + hu[j]
                if nupd >= refresh:
                    n = _factor(R, Hh, st, F, w)
                    stats[_FACTORISATIONS] += 1
                    nupd = 0
            # ---- the previous working set first: u + d, the first segment taken to tau = 1, is
            #      accepted outright when it passes the certificate (most frames keep their set)
            done = False
            if warm_start and n >= 0:
                for a in range(n):
                    x[a] = -delta[F[a]]
                _chol_solve(R, n, x)
                inbox = True
                for a in range(n):
                    v = u[F[a]] + x[a]
                    if v < -EPS_U or v > 1.0 + EPS_U:
                        inbox = False
                        break
                if inbox:  # the bound variables stay; u_F and g are kept to go back to
                    for a in range(n):
                        us[a] = u[F[a]]
                        u[F[a]] += x[a]
                    for j in range(K):
                        gs[j] = g[j]
                    fresh = False
                    done = _certify(Hh, ft, el, st, F, n, R, u, g, x, fresh) == -1
                    if done:
                        stats[_KEPT] += 1
                    else:
                        for a in range(n):
                            u[F[a]] = us[a]
                        for j in range(K):
                            g[j] = gs[j]
            if not done:
                # ---- the homotopy, tau from 0 to 1
                tau, seg, last, broken = 0.0, 0, -1, n < 0
                while not broken:
                    stats[_SEGMENTS] += 1
                    for a in range(n):
                        x[a] = -delta[F[a]]
                    _chol_solve(R, n, x)
                    for j in range(K):
                        d[j] = 0.0
                        gam[j] = delta[j]
                    for a in range(n):
                        col, xa = F[a], x[a]
                        d[col] = xa
                        for j in range(K):
                            gam[j] += Hh[col, j] * xa
                    # ratio test: first free variable to hit a bound / first multiplier to reach zero
                    best, jb = np.inf, -1
                    for j in range(K):
                        if st[j] == _FREE:
                            num = u[j] if d[j] < 0.0 else 1.0 - u[j]
                            den = abs(d[j])
                        elif st[j] == _LOWER:
                            num, den = g[j], -gam[j]
                        else:
                            num, den = -g[j], gam[j]
                        if den > 0.0:
                            s = max(num, 0.0) / den
                            if s < best and not (j == last and s <= 1e-13):  # no zero-length reversal
                                best, jb = s, j
                    step = min(best, 1.0 - tau)
                    for j in range(K):
                        if st[j] == _FREE:
                            u[j] += step * d[j]
                        else:
                            g[j] += step * gam[j]
                    if best >= 1.0 - tau:
                        break
                    tau += step
                    if seg >= max_seg:  # degenerate breakpoints: repairs, then the exact fallback
                        break
                    seg += 1
                    last = jb
                    nupd += 1
                    if st[jb] == _FREE:  # joins the bound it reached
                        st[jb] = _UPPER if d[jb] > 0.0 else _LOWER
                        u[jb] = 1.0 if d[jb] > 0.0 else 0.0
                        g[jb] = 0.0
                        p = 0
                        while F[p] != jb:
                            p += 1
                        _chol_delete(R, n, F, p)
                        n -= 1
                    else:  # its multiplier reached zero: freed
                        st[jb] = _FREE
                        g[jb] = 0.0
                        if not _chol_append(R, n, Hh, F, jb, w):
                            broken = True
                            break
                        n += 1
                    if nupd >= refresh:
                        n = _factor(R, Hh, st, F, w)
                        stats[_FACTORISATIONS] += 1
                        nupd = 0
                        broken = n < 0
                # ---- tau = 1: certify, repair with the chain's factor
                fresh = False  # the path's point first; a repair solves the free set afresh
                jb = -3 if broken else _certify(Hh, ft, el, st, F, n, R, u, g, x, fresh)
                rep, refactored = 0, False
                while jb != -1 and jb != -3 and rep < max_rep:
                    if jb == -2:  # stationarity residual only: a fresh factor, once
                        if refactored:
                            break
                        refactored = True
                    elif st[jb] == _FREE:  # outside the box: to the bound it crossed
                        st[jb] = _LOWER if u[jb] < 0.5 else _UPPER
                    else:  # a multiplier of the wrong sign: freed
                        st[jb] = _FREE
                    stats[_REPAIRS] += 1
                    rep += 1
                    n = _factor(R, Hh, st, F, w)
                    stats[_FACTORISATIONS] += 1
                    nupd = 0
                    if n < 0:
                        jb = -3
                        break
                    fresh = True
                    jb = _certify(Hh, ft, el, st, F, n, R, u, g, x, fresh)
                if jb != -1:  # the exact fallback finishes this frame; the chain goes on from the
                    flag[t, c] = True  # clipped point (any feasible point is an exact start)
                    stats[_FALLBACK] += 1
                    for j in range(K):
                        u[j] = min(max(u[j], 0.0), 1.0)
                        st[j] = _LOWER if u[j] <= 0.0 else (_UPPER if u[j] >= 1.0 else _FREE)
                    _gradient(Hh, ft, u, g)
                    n = _factor(R, Hh, st, F, w)
                    stats[_FACTORISATIONS] += 1
                    nupd = 0
                    cold = n < 0
            for j in range(K):
                U[t, c, j] = min(max(u[j], 0.0), 1.0)
