"""Batched small convex QPs: ``min ½ uᵀ H u + fᵀ u`` over the box or the simplex-like set.

The problems
------------
N problems (tens of thousands), each with a handful to a few dozen variables and a symmetric
positive-definite Hessian taken from a small table ``H[idx[n]]``::

    "simplex":  u ≥ 0,  1ᵀu ≤ 1          (Liu et al. 2011, eq. 2 in delta form)
    "box":      0 ≤ u ≤ 1

Users: Liu 2011's regional solve (:class:`core.solvers.local.LocalProblem`, the simplex form
by :func:`solve_simplex_sequence`), :func:`core.solvers.baselines.box_lsq`, and the parametric
active-set method along frames of :mod:`core.solvers.boxqp` (which borrows the equality-
constrained solve and the primal active set below for its exact fallback).

The solver
----------
The work is in batching, not in any single QP. We use a batched **primal–dual active-set**
method (Hintermüller, Ito & Kunisch 2003; Nocedal & Wright 2006 §16.4 for active sets): from
the clipped unconstrained minimiser, every iteration solves the equality-constrained KKT
system of the current active set exactly (all problems with the same number of free variables
in one ``numpy.linalg.solve`` call, :func:`solve_eqp_batch`), then updates the set from the
signs of primal variables and multipliers. When the set stops changing the KKT conditions hold
exactly (stationarity by construction, primal and dual feasibility by the stopping test), so
the solution is the QP's optimum to rounding, not to an iteration tolerance. PDAS can cycle on
non-M-matrix Hessians; the (rare) problems that have not settled after ``max_iter`` iterations
are finished by a batched **primal active-set** method (Nocedal & Wright, Alg. 16.3,
:func:`primal_active_set`) started at u = 0, which decreases the objective monotonically and
terminates finitely. No library does this batched over tens of thousands of tiny QPs
(quadprog/OSQP/daqp solve one at a time, and the Python call overhead alone is ~10–50 µs per
problem), hence the hand-written code. The slow reference is
:func:`core.solvers.reference.solve_qp_scipy`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CONSTRAINTS", "solve_qp_batch", "solve_simplex_sequence", "solve_eqp_batch", "primal_active_set",
           "project", "max_kkt_violation", "hessian_products"]

CONSTRAINTS = ("simplex", "box")


def hessian_products(H, idx, X):
    """Rows ``H[idx[n]] @ X[n]`` without gathering an (N, K, K) copy of the Hessians."""
    if len(H) > 64:  # many validity patterns: one gathered einsum is cheaper than a loop
        return np.einsum("nij,nj->ni", H[idx], X)
    out = np.empty_like(X)
    present = np.bincount(idx, minlength=len(H)) > 0
    for p in np.flatnonzero(present):
        r = idx == p
        out[r] = X[r] @ H[p]  # H symmetric
    return out


def solve_eqp_batch(H, f, idx, lower, upper, sum_active):
    """Minimise ½uᵀHu + fᵀu with the working constraints as equalities, batched.

    ``lower[n, i]``: u_i = 0; ``upper[n, i]``: u_i = 1; ``sum_active[n]``: 1ᵀu = 1.
    Each problem's KKT system is compacted to its free variables (plus the sum multiplier)
    and padded with identity rows to a bucket size (a multiple of 4), so a whole batch takes
    a handful of ``numpy.linalg.solve`` calls on small matrices.

    Returns u (N, K) and the sum multiplier μ (N,) (0 where the sum is not active).
    """
    N, K = f.shape
    fixed = lower | upper
    nfree = K - fixed.sum(1)
    sa = sum_active & (nfree > 0)
    u = np.where(upper, 1.0, 0.0)
    mu = np.zeros(N)
    perm = np.argsort(fixed, axis=1, kind="stable")  # free variables first
    rhs_full = -f
    if upper.any():
        rhs_full = rhs_full - hessian_products(H, idx, upper.astype(np.float64))
    bucket = np.minimum(K, 4 * ((nfree + 3) // 4))
    for b in np.unique(bucket):
        if b == 0:
            continue
        rows = np.flatnonzero(bucket == b)
        n = len(rows)
        pf = perm[rows, :b]  # (n, b): free variables first, then padding
        live = np.arange(b)[None, :] < nfree[rows, None]  # (n, b)
        Hc = H[idx[rows][:, None, None], pf[:, :, None], pf[:, None, :]]
        pair = live[:, :, None] & live[:, None, :]
        Hc = np.where(pair, Hc, np.eye(b)[None])
        s_r = sa[rows]
        A = np.zeros((n, b + 1, b + 1))
        A[:, :b, :b] = Hc
        A[:, :b, b] = live & s_r[:, None]
        A[:, b, :b] = A[:, :b, b]
        A[:, b, b] = ~s_r
        rhs = np.zeros((n, b + 1))
        rhs[:, :b] = np.where(live, np.take_along_axis(rhs_full[rows], pf, axis=1), 0.0)
        rhs[:, b] = np.where(s_r, 1.0 - upper[rows].sum(1), 0.0)
        x = np.linalg.solve(A, rhs[..., None])[..., 0]
        mu[rows] = np.where(s_r, x[:, b], 0.0)
        ur = u[rows]
        rr, cc = np.nonzero(live)
        ur[rr, pf[rr, cc]] = x[rr, cc]
        u[rows] = ur
    return u, mu


def _snap(u, simplex):
    """Remove rounding-level infeasibility (1 + 2e-16 and the like) from exact KKT solutions."""
    u = np.clip(u, 0.0, 1.0)
    if simplex:
        tot = u.sum(1)
        over = tot > 1.0
        u[over] /= tot[over, None]
    return u


def _scales(H, f, idx):
    d = np.einsum("pii->p", H) / H.shape[1]
    return d[idx] + np.abs(f).max(1)


def solve_qp_batch(H, f, idx=None, constraint: str = "simplex", max_iter: int = 30, warm=None):
    """Solve N small convex QPs  min ½uᵀH_{idx[n]}u + f_nᵀu  at once.

    ``constraint="simplex"``: u ≥ 0, 1ᵀu ≤ 1 (Liu et al. 2011, eq. 2 in delta form);
    ``"box"``: 0 ≤ u ≤ 1. Cold start: batched primal–dual active set from the clipped
    unconstrained minimiser, then the primal active set for the problems PDAS did not
    settle. Warm start (``warm`` given): primal active set from that feasible point.

    Parameters
    ----------
    H : (P, K, K) float
        Symmetric positive-definite Hessians (a table; problems index into it).
    f : (N, K) float
        Linear terms.
    idx : (N,) int, optional
        Which Hessian each problem uses (default ``arange(N)``; P must then equal N).
    constraint : {"simplex", "box"}
    max_iter : int
        PDAS iterations before the fallback.
    warm : (N, K) float, optional
        A feasible starting point, e.g. the previous frame's solution (it is projected onto
        the feasible set, so a slightly infeasible one is accepted).

    Returns
    -------
    u : (N, K) float64
    info : dict
        ``pdas_iterations`` (max over problems), ``fallback`` (problems finished by the
        primal active set), ``kkt_violation`` (max relative violation at exit).

    Raises
    ------
    ValueError
        Bad shapes or an unknown constraint.
    """
    H = np.asarray(H, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64)
    if constraint not in CONSTRAINTS:
        raise ValueError(f"constraint: expected one of {CONSTRAINTS}, got {constraint!r}")
    if H.ndim != 3 or H.shape[1] != H.shape[2]:
        raise ValueError(f"H: expected (P, K, K), got {H.shape}")
    K = H.shape[1]
    if f.ndim != 2 or f.shape[1] != K:
        raise ValueError(f"f: expected (N, {K}), got {f.shape}")
    N = len(f)
    if idx is None:
        if len(H) != N:
            raise ValueError(f"idx omitted: H must hold one Hessian per problem ({N}), got {len(H)}")
        idx = np.arange(N)
    idx = np.asarray(idx, dtype=np.int64)
    if idx.shape != (N,) or (N and (idx.min() < 0 or idx.max() >= len(H))):
        raise ValueError(f"idx: expected (N,) = ({N},) ints in [0, {len(H)}), got shape {idx.shape}")
    simplex = constraint == "simplex"
    scale = _scales(H, f, idx)
    eps_u = 1e-11
    eps_l = 1e-11 * scale
    if warm is not None:
        w = np.asarray(warm, dtype=np.float64)
        if w.shape != (N, K):
            raise ValueError(f"warm: expected ({N}, {K}), got {w.shape}")
        w = project(w, constraint)
        u, its = primal_active_set(H, f, idx, simplex, eps_u, eps_l, init=w)
        u = _snap(u, simplex)
        return u, {"pdas_iterations": 0, "fallback": N, "active_set_iterations": its,
                   "kkt_violation": max_kkt_violation(H, f, idx, u, constraint)}
    Hinv = np.linalg.inv(H)
    u0 = np.empty((N, K))
    for p in np.unique(idx):
        r = idx == p
        u0[r] = -f[r] @ Hinv[p].T
    lower = u0 <= 0
    upper = (u0 >= 1) if not simplex else np.zeros((N, K), bool)
    sum_active = (np.clip(u0, 0, None).sum(1) >= 1) if simplex else np.zeros(N, bool)
    u = np.zeros((N, K))
    todo = np.arange(N)
    it = 0
    for it in range(1, max_iter + 1):
        lo, up, sa = lower[todo], upper[todo], sum_active[todo]
        ut, mt = solve_eqp_batch(H, f[todo], idx[todo], lo, up, sa)
        g = hessian_products(H, idx[todo], ut) + f[todo] + mt[:, None]
        el = eps_l[todo][:, None]
        new_lo = np.where(lo, g >= -el, ut < -eps_u)
        if simplex:
            new_up = up
            new_sa = np.where(sa, mt >= -eps_l[todo], ut.sum(1) > 1 + eps_u)
        else:
            new_up = np.where(up, -g >= -el, ut > 1 + eps_u)
            new_sa = sa
        new_lo &= ~new_up
        same = (new_lo == lo).all(1) & (new_up == up).all(1) & (new_sa == sa)
        u[todo[same]] = ut[same]
        lower[todo], upper[todo], sum_active[todo] = new_lo, new_up, new_sa
        todo = todo[~same]
        if len(todo) == 0:
            break
    n_fallback = len(todo)
    its = 0
    if n_fallback:
        # resume from the projection of the last PDAS iterate (feasible, usually close)
        start = project(ut[~same] if it else u0[todo], constraint)
        u[todo], its = primal_active_set(H, f[todo], idx[todo], simplex, eps_u, eps_l[todo], init=start)
    u = _snap(u, simplex)
    return u, {"pdas_iterations": it, "fallback": n_fallback, "active_set_iterations": its,
               "kkt_violation": max_kkt_violation(H, f, idx, u, constraint)}


def project(u, constraint: str = "simplex") -> np.ndarray:
    """Euclidean projection onto the feasible set, rows independently.

    ``"box"``: clip to [0, 1]. ``"simplex"``: {u ≥ 0, 1ᵀu ≤ 1}: clip at 0; rows whose sum
    then exceeds 1 are projected onto {u ≥ 0, 1ᵀu = 1} by the sort-based algorithm of
    Held, Wolfe & Crowder 1974 / Duchi et al. 2008 (vectorised over rows).
    """
    u = np.asarray(u, dtype=np.float64)
    if constraint == "box":
        return np.clip(u, 0.0, 1.0)
    v = np.clip(u, 0.0, None)
    over = v.sum(1) > 1
    if over.any():
        x = u[over]
        srt = -np.sort(-x, axis=1)
        css = np.cumsum(srt, axis=1) - 1.0
        k = np.arange(1, x.shape[1] + 1)
        cond = srt - css / k > 0
        rho = x.shape[1] - 1 - np.argmax(cond[:, ::-1], axis=1)
        theta = css[np.arange(len(x)), rho] / (rho + 1)
        v[over] = np.clip(x - theta[:, None], 0.0, None)
    return v


def primal_active_set(H, f, idx, simplex, eps_u, eps_l, init=None, max_iter=None, strict=True):
    """Batched primal active-set method (Nocedal & Wright 2006, Alg. 16.3).

    Starts at the feasible ``init`` (default u = 0) with the constraints active there as the
    working set. Each iteration moves towards the working set's equality-constrained
    minimiser, adding the first blocking constraint, or -- at that minimiser -- drops the
    constraint with the most negative multiplier; so the objective never increases and the
    method ends after finitely many steps (barring degenerate cycling, guarded by
    ``max_iter``). A full step is followed by the multiplier test in the same iteration.

    Returns u (N, K), the number of iterations and, when ``strict`` is False, a (N,) bool
    "converged" mask (unconverged rows hold a feasible iterate to resume from); when
    ``strict`` is True an unconverged problem raises RuntimeError.
    """
    N, K = f.shape
    max_iter = max_iter or 20 * (K + 1)
    if init is None:
        u = np.zeros((N, K))
    else:
        u = np.array(init, dtype=np.float64)
    lower = u <= 0.0
    upper = (u >= 1.0) & ~lower if not simplex else np.zeros((N, K), bool)
    sa = (np.abs(u.sum(1) - 1.0) <= 1e-12) if simplex else np.zeros(N, bool)
    u[lower] = 0.0
    u[upper] = 1.0
    todo = np.arange(N)
    it = 0
    for it in range(1, max_iter + 1):
        if len(todo) == 0:
            it -= 1
            break
        lo, up, s = lower[todo], upper[todo], sa[todo]
        ue, me = solve_eqp_batch(H, f[todo], idx[todo], lo, up, s)
        ut = u[todo]
        p = ue - ut
        n = len(todo)
        ar = np.arange(n)
        # -- step towards the EQP minimiser, blocked by the first constraint it would cross
        alpha = np.ones(n)
        kind = np.zeros(n, np.int64)  # 0 none, 1 lower, 2 upper, 3 sum
        which = np.zeros(n, np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.clip(np.where((p < 0) & ~lo, -ut / p, np.inf), 0, None)
            i = np.argmin(a, axis=1)
            v = a[ar, i]
            hit = v < alpha
            alpha, kind, which = np.where(hit, v, alpha), np.where(hit, 1, kind), np.where(hit, i, which)
            if simplex:
                ps = p.sum(1)
                v = np.clip(np.where((ps > 0) & ~s, (1 - ut.sum(1)) / ps, np.inf), 0, None)
                hit = v < alpha
                alpha, kind = np.where(hit, v, alpha), np.where(hit, 3, kind)
            else:
                a = np.clip(np.where((p > 0) & ~up, (1 - ut) / p, np.inf), 0, None)
                i = np.argmin(a, axis=1)
                v = a[ar, i]
                hit = v < alpha
                alpha, kind, which = np.where(hit, v, alpha), np.where(hit, 2, kind), np.where(hit, i, which)
        full = kind == 0
        unew = np.where(full[:, None], ue, ut + alpha[:, None] * p)
        r1 = np.flatnonzero(kind == 1)
        unew[r1, which[r1]] = 0.0
        lo[r1, which[r1]] = True
        r2 = np.flatnonzero(kind == 2)
        unew[r2, which[r2]] = 1.0
        up[r2, which[r2]] = True
        s[kind == 3] = True
        # -- at the EQP minimiser (full step): multiplier test, drop the most negative
        g = hessian_products(H, idx[todo], ue) + f[todo] + (me[:, None] if simplex else 0.0)
        lam = np.minimum(np.where(lo, g, np.inf), np.where(up, -g, np.inf))
        lmin = lam.min(1)
        mneg = np.where(s, me, np.inf)
        worst = np.minimum(lmin, mneg)
        done = full & (worst >= -eps_l[todo])
        drop = np.flatnonzero(full & ~done)
        if len(drop):
            dsum = mneg[drop] <= lmin[drop]
            s[drop[dsum]] = False
            rb = drop[~dsum]
            ib = np.argmin(lam[rb], axis=1)
            lo[rb, ib] = False
            up[rb, ib] = False
        u[todo] = unew
        lower[todo], upper[todo], sa[todo] = lo, up, s
        todo = todo[~done]
    if not strict:
        conv = np.ones(N, bool)
        conv[todo] = False
        return u, it, conv
    if len(todo):
        raise RuntimeError(f"primal active set did not converge for {len(todo)} QPs in {max_iter} iterations")
    return u, it


def max_kkt_violation(H, f, idx, u, constraint: str = "simplex") -> float:
    """Largest relative violation of the KKT conditions at ``u`` (0 at an exact optimum).

    Primal: bounds and sum, in weight units. Dual: with g = Hu + f, the best multipliers
    for the active constraints are found and the remaining stationarity residual and
    negative multipliers are measured relative to ``mean diag H + max |f|``.
    """
    H = np.asarray(H, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    g = hessian_products(H, np.asarray(idx), u) + f
    scale = _scales(H, f, idx)[:, None]
    primal = np.maximum(-u, 0).max(1)
    tol = 1e-9
    if constraint == "simplex":
        primal = np.maximum(primal, np.maximum(u.sum(1) - 1, 0))
        # at u: free variables (u > tol) must share g_i = -μ; μ >= 0 only if sum is active
        free = u > tol
        cnt = free.sum(1)
        mu = np.where(cnt > 0, -np.where(free, g, 0).sum(1) / np.maximum(cnt, 1), 0.0)
        sum_act = u.sum(1) >= 1 - tol
        mu = np.where(sum_act, np.maximum(mu, 0), 0.0)
        r = g + mu[:, None]
        stat = np.where(free, np.abs(r), np.maximum(-r, 0)).max(1)
    else:
        primal = np.maximum(primal, np.maximum(u - 1, 0).max(1))
        at_lo, at_up = u <= tol, u >= 1 - tol
        stat = np.where(at_lo, np.maximum(-g, 0), np.where(at_up, np.maximum(g, 0), np.abs(g))).max(1)
    return float(max(primal.max(initial=0), (stat / scale[:, 0]).max(initial=0)))


def solve_simplex_sequence(H, f, idx, block=None, max_iter: int = 10, warm_iter: int = 3):
    """Solve ``min ½uᵀH_{idx[t,c]}u + f[t,c]ᵀu  s.t.  u ≥ 0, 1ᵀu ≤ 1`` for every frame t and chain c,
    warm-started along the frames.

    Frames are cut into blocks of ``block`` consecutive frames: the first frame of every block
    is solved cold by :func:`solve_qp_batch` (all blocks at once), the others by the primal
    active set (:func:`primal_active_set`) from the previous frame's solution. Every QP is
    solved to its KKT conditions, so the result does not depend on ``block``.

    Parameters
    ----------
    H : (P, K, K) float
        Symmetric positive-definite Hessians.
    f : (T, C, K) float
        Linear terms; axis 0 is time.
    idx : (T, C) int
        Which Hessian each problem uses.
    block : int, optional
        Frames per warm-start block (default 16).
    max_iter : int
        PDAS iterations of the cold solves before the primal active-set fallback.
    warm_iter : int
        Active-set iterations a warm-started QP gets within its step; the few that need more
        are resumed from their (feasible) iterate in one batch at the end.

    Returns
    -------
    U : (T, C, K) float64
    info : dict
        ``pdas_iterations``, ``fallback``, ``active_set_iterations``.
    """
    T, R, K = f.shape
    block = 16 if block is None else block
    U = np.empty((T, R, K))
    # all blocks advance one frame per step, each QP warm-started from the previous frame's
    # solution (consecutive frames usually share their active set, so most finish in one or
    # two small solves)
    L = max(1, int(block))
    starts = np.arange(0, T, L)
    its, fb, as_its = 0, 0, 0
    pending = np.zeros((T, R), bool)  # warm solves stopped early, finished below
    for j in range(L):
        fr = starts + j
        fr = fr[fr < T]
        if len(fr) == 0:
            break
        ff, hh = f[fr].reshape(-1, K), idx[fr].ravel()
        if j == 0:
            u, inf = solve_qp_batch(H, ff, hh, "simplex", max_iter=max_iter)
            its, fb = inf["pdas_iterations"], inf["fallback"]
            as_its += inf["active_set_iterations"]
        else:
            scale = _scales(H, ff, hh)
            u, k, conv = primal_active_set(H, ff, hh, True, 1e-11, 1e-11 * scale,
                                           init=U[fr - 1].reshape(-1, K), max_iter=warm_iter, strict=False)
            as_its += k
            pending[fr] = ~conv.reshape(len(fr), R)
        U[fr] = u.reshape(len(fr), R, K)
    if pending.any():
        # every pending iterate is feasible: resume the primal active set from it
        tt, rr = np.nonzero(pending)
        ff, hh = f[tt, rr], idx[tt, rr]
        u, k = primal_active_set(H, ff, hh, True, 1e-11, 1e-11 * _scales(H, ff, hh), init=U[tt, rr])
        U[tt, rr] = u
        as_its += k
        fb += len(tt)
    U = _snap(U.reshape(T * R, K), True).reshape(T, R, K)
    return U, {"pdas_iterations": its, "fallback": fb, "active_set_iterations": as_its}
