"""Box-constrained QPs along a sequence of frames: a batched parametric active-set method.

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
reaches a bound (it joins the bound) or a multiplier reaches zero (its variable is freed). One
index changes per breakpoint, so ``H_FF^-1`` is kept as an explicit inverse and updated by a
rank-one (bordering / Schur complement) formula in ``O(|F|^2)`` instead of refactorised [1, 2].
Starting a frame from the previous frame's solution costs 1 + (number of active-set changes)
segments; ``tau = 1`` reached means the frame is solved. This is the warm start of the issue
("the active set of frame t-1 is usually right for frame t: try it first"): a frame whose set
did not change costs one product with the stored inverse.

Any feasible ``u`` with sign-clamped multipliers is an exact optimum of *some* ``f_0``
(``f_0 = lambda - H u``), so every start is consistent: the previous frame (warm), ``u = 0`` with
positive multipliers (cold), or another lane's solution (work stealing, below).

Batching
--------
Frames are cut into *lanes* of consecutive frames of one chain; every lane starts cold (for
small K a few batched primal-dual active-set iterations [3] settle most first frames outright)
and walks forward. All lanes advance one breakpoint per round in a few dozen numpy calls on
stacked arrays (inverses ``(lanes, b, b)`` zero-padded to the largest free set ``b``). After a
lane finishes a frame it checks the next ``lookahead`` frames against its current set with one
product each (frames whose set does not change are accepted at once). Lanes that run out of
frames take the second half of the longest remaining run of another lane, starting from that
lane's latest solution (a short homotopy between two nearby frames instead of a cold start).

Measured alternatives that lost (on the two benchmark cases): primal-dual active set (PDAS)
warm-started with the previous frame's set settles 42 % of the sample's frames at once but
cycles on 14 % (the rank-deficient rig makes wrong sets' equality-constrained minimisers wild);
projected Newton (Bertsekas 1982) from the previous solution stalls in tiny projected steps for
the same reason; grouping frames by identical active set (1,129 distinct sets in 2,028 frames)
still needs one fresh factorisation per group and per iteration; the primal active set from the
previous solution needs 3.6 fresh factorisations per frame on average with a long tail.

Exactness
---------
Every frame is accepted only after its KKT conditions are checked with a freshly computed
gradient ``g = H u + f``: ``|g_F| <= eps_l``, ``-eps_u <= u_F <= 1 + eps_u``, ``g_L >= -eps_l``,
``g_U <= eps_l`` with ``eps_u = 1e-11`` and ``eps_l = 1e-11 (mean diag H + max |f|)`` (the tests
of :func:`core.solvers.qp.solve_qp_batch`). The updated inverses drift in ill-conditioned
problems; they are refreshed from scratch every ``refresh`` updates, the point is refined by one
step of iterative refinement before the check, and a frame that still fails (or a lane stuck in
degenerate breakpoints) is finished by primal-dual active-set steps from its current set and the
finite primal active-set method of :func:`core.solvers.qp.primal_active_set` (counted in
``info["fallback"]``). The answer is therefore the optimum to rounding, as before, not to an
iteration tolerance.

References
----------
.. [1] M. J. Best, "An algorithm for the solution of the parametric quadratic programming
       problem", in Applied Mathematics and Parallel Computing, 1996, pp. 57-76.
.. [2] H. J. Ferreau, H. G. Bock, M. Diehl, "An online active set strategy to overcome the
       limitations of explicit MPC", Int. J. Robust Nonlinear Control 18(8), 2008 (qpOASES).
.. [3] M. Hintermueller, K. Ito, K. Kunisch, "The primal-dual active set strategy as a semismooth
       Newton method", SIAM J. Optim. 13(3), 2003 (the fallback's first steps).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from core.solvers.qp import primal_active_set, solve_eqp_batch

__all__ = ["solve_box_sequence", "solve_box_frame"]

EPS_U = 1e-11  # primal tolerance in unit-box coordinates
EPS_L = 1e-11  # dual tolerance relative to mean diag H + max |f|
_MEMORY = 64e6  # bytes allowed for the stacked inverses (caps the number of lanes)


class _Lanes:
    """Per-lane state, arrays with one row per lane (a lane = a run of frames of one chain)."""

    FIELDS = ("t", "c", "end", "h", "Hl", "u", "g", "d", "fresh", "delta", "tau", "lower", "upper", "perm", "nfree",
              "inv", "nupd", "seg", "last", "active")

    def take(self, keep):
        for name in self.FIELDS:
            setattr(self, name, getattr(self, name)[keep])


def _hmul(H, h, X):
    """``H[h[n]] @ X[n]`` for X (n, K), or ``X[n] @ H[h[n]]`` for X (n, m, K); H symmetric."""
    if len(H) == 1:
        return (X.reshape(-1, H.shape[1]) @ H[0]).reshape(X.shape)
    if X.ndim == 2:
        return np.einsum("nij,nj->ni", H[h], X)
    return X @ H[h]


def _lmul(H, L, rows, X):
    """``H_lane @ X`` for lanes ``rows`` (None: all lanes), with the lanes' Hessians stored in
    ``L.Hl`` when there are several (a batched matmul, 2-3x faster than gathering per call)."""
    if len(H) == 1:
        return (X.reshape(-1, H.shape[1]) @ H[0]).reshape(X.shape)
    Hl = L.Hl if rows is None else np.take(L.Hl, rows, axis=0)
    return (Hl @ X[..., None])[..., 0] if X.ndim == 2 else X @ Hl


def _blocks(L, rows, b):
    """The lanes' inverses, (n, b, b): whole blocks copied with ``np.take`` (a memcpy per lane;
    ``L.inv[rows, :b, :b]`` gathers element by element and cost 3x more)."""
    return np.take(L.inv, rows, axis=0)[:, :b, :b]


def _set_h(H, L, rows, h):
    """Lanes ``rows`` now use Hessian ``h``."""
    L.h[rows] = h
    if len(H) > 1:
        L.Hl[rows] = H[h]


def _inverse(H, h, perm, nfree, b):
    """Fresh inverses of the free blocks, zero-padded to (n, b, b)."""
    live = np.arange(b)[None] < nfree[:, None]
    p = perm[:, :b]
    A = H[h[:, None, None], p[:, :, None], p[:, None, :]]
    pair = live[:, :, None] & live[:, None, :]
    M = np.linalg.inv(np.where(pair, A, np.eye(b)[None]))
    # symmetric to rounding: the rank-one updates below assume M = M^T
    return np.where(pair, 0.5 * (M + M.transpose(0, 2, 1)), 0.0)


def _free_first(lower, upper):
    free = ~(lower | upper)
    return np.argsort(~free, axis=1, kind="stable"), free.sum(1)


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


def solve_box_sequence(H, f, idx=None, block=None, lanes=None, lookahead: int = 4, refresh: int = 32,
                       steal: int = 6, pdas=None, return_info: bool = False, warm=None):
    """Solve (1) of the module docstring for every frame, warm-started along the frames.

    ``min_u 1/2 u^T H_{idx[t,c]} u + f[t,c]^T u``  s.t. ``0 <= u <= 1``, exactly (KKT conditions
    checked at ``1e-11`` relative tolerances for every frame).

    Parameters
    ----------
    H : (P, K, K) float
        Symmetric positive-definite Hessians.
    f : (T, K) or (T, C, K) float
        Linear terms; axis 0 is time (consecutive frames are similar), C independent chains.
    idx : (T,) or (T, C) int, optional
        Which Hessian each problem uses; default 0 (then P must be 1).
    block : int, optional
        Frames per lane at the start (each lane starts cold). Default 128 for K <= 64 and 64
        above: a cold start costs O(K) breakpoints, so small problems afford longer lanes
        (measured on the two benchmark cases, ``benchmarks/bench_pipeline.py`` and
        ``bench_local.py``).
    lanes : int, optional
        Lanes advanced together (default: the initial lanes plus as many idle ones for work
        stealing, capped by memory). The result does not depend on ``block``, ``lanes``,
        ``lookahead`` or ``steal``; only the time does.
    lookahead : int
        Frames checked against a lane's current active set after each solved frame (0: off).
        Switched off by itself when, over the first 256 checks, the next frame kept the set
        less than half the time (the 165-shape sample: 42 %; the regional problems: 81 %).
    refresh : int
        Rank-one updates of an inverse before it is recomputed from scratch.
    steal : int
        A lane with at least this many frames left gives the second half to an idle lane.
    pdas : int, optional
        Primal-dual active-set iterations [3] tried on the lanes' first frames before the cold
        homotopy (which needs about as many breakpoints as free variables). Default 8 for
        K <= 64, 0 above: on the rank-deficient 165-shape sample PDAS from the clipped
        unconstrained minimiser thrashes (none of 64 frames settled in 100 iterations), on the
        22-shape regional problems it settles most first frames in a few.
    return_info : bool
    warm : (K,) or (C, K) float, optional
        A point in the unit box to start frame 0 of each chain from instead of cold (the
        previous frame's solution when frames arrive one at a time, :mod:`core.live`): it is
        the exact optimum of ``f_0 = lambda - H u`` with ``lambda`` the sign-clamped gradient
        (module docstring), so the homotopy to frame 0 costs 1 + its active-set changes.

    Returns
    -------
    U : same shape as ``f``, float64, in [0, 1]
    info : dict (when ``return_info``): ``rounds`` (batched steps), ``segments`` (lane steps),
        ``pdas_start`` (first frames settled by PDAS), ``lookahead`` (frames accepted by the
        look-ahead check), ``steals``, ``refreshes`` (fresh inverses), ``repairs`` (certificates
        that failed and were repaired with the lane's inverse), ``fallback`` (frames finished by
        the exact PDAS / primal active-set fallback).

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
    info = dict(rounds=0, segments=0, pdas_start=0, lookahead=0, steals=0, refreshes=0, repairs=0, fallback=0)
    U = np.zeros((T, C, K))
    if T == 0 or C == 0 or K == 0:
        return (U[:, 0] if squeeze else U, info) if return_info else (U[:, 0] if squeeze else U)
    eps_all = EPS_L * (np.einsum("pii->p", H)[idx] / K + np.abs(f).max(2))  # (T, C)

    # ---- lanes: blocks of `block` frames per chain, plus idle slots for work stealing
    block = (128 if K <= 64 else 64) if block is None else max(1, int(block))
    starts = np.arange(0, T, block)
    n0 = len(starts) * C
    cap_lanes = max(n0, int(_MEMORY // (8.0 * K * K * (1 if len(H) == 1 else 2))))
    nl = int(min(cap_lanes, max(n0, lanes if lanes is not None else 2 * n0)))
    L = _Lanes()
    L.c = np.zeros(nl, np.int64)
    L.t = np.zeros(nl, np.int64)
    L.end = np.zeros(nl, np.int64)
    L.c[:n0] = np.repeat(np.arange(C), len(starts))
    L.t[:n0] = np.tile(starts, C)
    L.end[:n0] = np.minimum(L.t[:n0] + block, T)
    L.active = np.zeros(nl, bool)
    L.active[:n0] = True
    L.h = idx[L.t, L.c]
    L.Hl = H[L.h] if len(H) > 1 else np.zeros((nl, 0, 0))
    # cold start: u = 0 is the exact optimum of f_0 = max(f, 0) + margin (every lower bound binds)
    ft = f[L.t, L.c]
    L.g = np.maximum(ft, 0.0) + 1e-3 * np.abs(ft).max(1, keepdims=True) + 1e-300
    L.delta = ft - L.g
    L.u = np.zeros((nl, K))
    L.d = np.zeros((nl, K))  # du/dtau of the current segment
    L.fresh = np.ones(nl, bool)  # d must be recomputed from the inverse (new frame, new inverse, new set)
    L.tau = np.zeros(nl)
    L.lower = np.ones((nl, K), bool)
    L.upper = np.zeros((nl, K), bool)
    L.perm = np.tile(np.arange(K), (nl, 1))
    L.nfree = np.zeros(nl, np.int64)
    L.nupd = np.zeros(nl, np.int64)
    L.seg = np.zeros(nl, np.int64)
    L.last = np.full(nl, -1)
    cap = min(K, 8)
    L.inv = np.zeros((nl, cap, cap))
    max_seg = 4 * K + 20
    k_look = max(0, int(lookahead))
    look = [0, 0]  # look-ahead checks, and checks whose first frame kept the set
    pdas = (8 if K <= 64 else 0) if pdas is None else int(pdas)
    cold = np.arange(n0)
    if warm is not None:
        cold = _warm_start(H, f, np.broadcast_to(np.asarray(warm, dtype=np.float64), (C, K)), L, n0, refresh)
    if pdas > 0 and len(cold):
        _pdas_start(H, f, idx, eps_all, L, cold, pdas, U, info, refresh)
    rows = np.arange(nl)

    while L.active.any():
        info["rounds"] += 1
        info["segments"] += int(L.active.sum())
        nl = len(L.t)
        if len(rows) != nl:
            rows = np.arange(nl)
        b = int(min(K, L.nfree.max() + 1))  # room for one more free variable
        if b > cap:
            cap = min(K, max(2 * cap, b))
            grown = np.zeros((nl, cap, cap))
            grown[:, :L.inv.shape[1], :L.inv.shape[2]] = L.inv
            L.inv = grown
        # -- fresh inverses (and a fresh point on the path) where the updates have piled up
        ref = np.flatnonzero(L.active & (L.nupd >= refresh))
        if len(ref):
            info["refreshes"] += len(ref)
            Mi = _inverse(H, L.h[ref], L.perm[ref], L.nfree[ref], b)
            blk = np.zeros((len(ref),) + L.inv.shape[1:])
            blk[:, :b, :b] = Mi
            L.inv[ref] = blk
            f_tau = f[L.t[ref], L.c[ref]] - (1.0 - L.tau[ref])[:, None] * L.delta[ref]
            ur = L.upper[ref].astype(np.float64)
            p = L.perm[ref, :b]
            x = (Mi @ -np.take_along_axis(f_tau + _lmul(H, L, ref, ur), p, 1)[:, :, None])[:, :, 0]
            live = np.arange(b)[None] < L.nfree[ref][:, None]
            np.put_along_axis(ur, p, np.where(live, x, np.take_along_axis(ur, p, 1)), 1)
            L.u[ref] = ur
            L.g[ref] = _lmul(H, L, ref, ur) + f_tau
            L.nupd[ref] = 0
            L.fresh[ref] = True
        # -- direction of the current segment: du/dtau on the free set (kept up to date by the
        #    rank-one updates, recomputed after a new frame or inverse), dg/dtau everywhere
        new = np.flatnonzero(L.fresh & L.active)
        if len(new):
            p = L.perm[new, :b]
            x = (_blocks(L, new, b) @ -np.take_along_axis(L.delta[new], p, 1)[:, :, None])[:, :, 0]  # 0 beyond nfree
            dn = np.zeros((len(new), K))
            np.put_along_axis(dn, p, x, 1)
            L.d[new] = dn
            L.fresh[new] = False
        d = L.d
        gam = _lmul(H, L, None, d) + L.delta
        # -- ratio test: first free variable to hit a bound / first multiplier to reach zero
        free = ~(L.lower | L.upper)
        with np.errstate(divide="ignore", invalid="ignore"):
            num = np.where(free, np.where(d < 0, L.u, 1.0 - L.u), np.where(L.lower, L.g, -L.g))
            den = np.where(free, np.abs(d), np.where(L.lower, -gam, gam))
            s = np.where(den > 0, np.maximum(num, 0.0) / den, np.inf)
        back = np.flatnonzero(L.last >= 0)  # no immediate zero-length reversal of the last move
        back = back[s[back, L.last[back]] <= 1e-13]
        s[back, L.last[back]] = np.inf
        j = np.argmin(s, axis=1)
        sj = s[rows, j]
        rem = 1.0 - L.tau
        done = (sj >= rem) & L.active
        step = np.minimum(sj, rem)
        L.u += step[:, None] * d
        L.g += step[:, None] * gam
        L.tau += step
        stuck = L.active & ~done & (L.seg >= max_seg)
        move = np.flatnonzero(L.active & ~done & ~stuck)
        fin = np.flatnonzero(done | stuck)
        if len(fin):
            go, Hu = _finish_frames(H, f, idx, eps_all, L, fin, free[fin], stuck[fin], b, U, info, k_look, look, refresh,
                                    max_seg)
            if k_look and look[0] >= 256 and look[1] < 0.5 * look[0]:
                k_look = 0  # the next frame rarely keeps the set: a check costs about one segment
            if steal:
                _steal(H, f, idx, L, go, Hu, steal, info)
        if len(move):
            _move(H, L, move, j[move], free[move, j[move]], d[move, j[move]], gam[move, j[move]], b)
        if L.active.sum() < 0.6 * len(L.t) and len(L.t) > 8 and (not steal or ((L.end - L.t)[L.active] < 2 * steal).all()):
            L.take(np.flatnonzero(L.active))
    U = np.clip(U, 0.0, 1.0)
    if squeeze:
        U = U[:, 0]
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


def _warm_start(H, f, warm, L, n0, refresh):
    """Start the lanes that begin at frame 0 from ``warm`` (C, K): ``u`` clipped to the box, the
    working set where it sits on a bound, multipliers ``lambda`` = the sign-clamped gradient
    ``H u + f`` (0 on the free set), so ``u`` is the optimum of ``f_0 = lambda - H u`` and the
    segment runs from ``f_0`` to ``f``. Returns the lanes left to start cold."""
    ln = np.flatnonzero(L.t[:n0] == 0)
    u = np.clip(warm[L.c[ln]], 0.0, 1.0)
    lo, up = u <= 0.0, u >= 1.0
    Hu = _hmul(H, L.h[ln], u)
    g = Hu + f[0, L.c[ln]]
    lam = np.where(lo, np.maximum(g, 0.0), np.where(up, np.minimum(g, 0.0), 0.0))
    L.lower[ln], L.upper[ln] = lo, up
    L.perm[ln], L.nfree[ln] = _free_first(lo, up)
    L.u[ln], L.g[ln] = u, lam
    L.delta[ln] = f[0, L.c[ln]] - lam + Hu
    L.nupd[ln] = refresh  # fresh inverses (and directions) in the first round
    return np.setdiff1d(np.arange(n0), ln)


def _pdas_start(H, f, idx, eps_all, L, lanes, iters, U, info, refresh):
    """Solve the lanes' first frames by a few PDAS iterations [3] from the clipped unconstrained
    minimiser; lanes that settle (KKT verified) start their second frame warm."""
    t, c, h = L.t[lanes], L.c[lanes], L.h[lanes]
    f1 = f[t, c]
    el = eps_all[t, c][:, None]
    u0 = np.linalg.solve(H[h], -f1[:, :, None])[:, :, 0]
    lower, upper = u0 <= 0.0, u0 >= 1.0
    todo = np.arange(len(lanes))
    for _ in range(iters):
        lo, up = lower[todo], upper[todo]
        ut, _ = solve_eqp_batch(H, f1[todo], h[todo], lo, up, np.zeros(len(todo), bool))
        g = _hmul(H, h[todo], ut) + f1[todo]
        ok = _kkt_ok(ut, g, lo, up, el[todo])
        ln = lanes[todo[ok]]
        if len(ln):
            info["pdas_start"] += len(ln)
            uo, go = np.clip(ut[ok], 0.0, 1.0), g[ok]
            L.lower[ln], L.upper[ln] = lo[ok], up[ok]
            L.perm[ln], L.nfree[ln] = _free_first(lo[ok], up[ok])
            U[L.t[ln], L.c[ln]] = uo
            nxt = L.t[ln] + 1
            cont = nxt < L.end[ln]
            L.active[ln[~cont]] = False
            gl, ug, gg, f0 = ln[cont], uo[cont], go[cont], f1[todo[ok]][cont]
            L.t[gl] = nxt[cont]
            lam = np.where(L.lower[gl], np.maximum(gg, 0.0), np.where(L.upper[gl], np.minimum(gg, 0.0), 0.0))
            Hu = gg - f0
            hn = idx[L.t[gl], L.c[gl]]
            new_h = hn != L.h[gl]
            if new_h.any():  # the next frame has another mask pattern
                _set_h(H, L, gl[new_h], hn[new_h])
                Hu[new_h] = _hmul(H, hn[new_h], ug[new_h])
            L.delta[gl] = f[L.t[gl], L.c[gl]] - lam + Hu
            L.g[gl], L.u[gl] = lam, ug
            L.nupd[gl] = refresh  # fresh inverses (and directions) in the first round
        el_t = el[todo][~ok]
        new_up = np.where(up[~ok], g[~ok] <= el_t, ut[~ok] > 1 + EPS_U)
        new_lo = np.where(lo[~ok], g[~ok] >= -el_t, ut[~ok] < -EPS_U) & ~new_up
        todo = todo[~ok]
        lower[todo], upper[todo] = new_lo, new_up
        if not len(todo):
            break


def _finish_frames(H, f, idx, eps_all, L, fin, free, stuck, b, U, info, k_look, look, refresh, max_seg):
    """Lanes that reached tau = 1 (or got stuck): certify, store, look ahead, start the next frame.

    Returns the lanes that continue and ``H u`` at their new starting points (for stealing).
    """
    t, c, h = L.t[fin], L.c[fin], L.h[fin]
    f1 = f[t, c]
    lo, up = L.lower[fin], L.upper[fin]
    u1 = np.where(free, L.u[fin], up.astype(np.float64))
    g1 = _lmul(H, L, fin, u1) + f1
    el = eps_all[t, c][:, None]
    # one step of iterative refinement where the stationarity residual is not tiny
    need = np.flatnonzero((free & (np.abs(g1) > 0.1 * el)).any(1))
    if len(need):
        p = L.perm[fin[need], :b]
        du = (_blocks(L, fin[need], b) @ -np.take_along_axis(g1[need], p, 1)[:, :, None])[:, :, 0]
        un = u1[need]
        np.put_along_axis(un, p, np.take_along_axis(un, p, 1) + du, 1)
        u1[need] = np.where(free[need], un, u1[need])
        g1[need] = _lmul(H, L, fin[need], u1[need]) + f1[need]
    ok = _kkt_ok(u1, g1, lo, up, el)
    hard = ~ok & (stuck | (L.seg[fin] >= max_seg))
    fix = np.flatnonzero(~ok & ~hard)
    if len(fix):
        # repair at tau = 1 with the lane's own inverse (the updates drift where H_FF is badly
        # conditioned): the worst violator moves -- a free variable outside [0, 1] joins its
        # bound, a negative multiplier frees its variable -- and the frame is certified again in
        # the next round (the refinement step above is then the Newton step to the new set's
        # minimiser); a stationarity residual alone asks for a fresh inverse
        info["repairs"] += len(fix)
        fr, uf, gf, e = free[fix], u1[fix], g1[fix], el[fix]
        score = np.maximum(np.where(fr, np.maximum(-uf, uf - 1.0) / EPS_U, 0.0),
                           np.where(lo[fix], -gf, np.where(up[fix], gf, 0.0)) / e)
        j = np.argmax(score, axis=1)
        movable = score[np.arange(len(fix)), j] > 1.0
        lanes = fin[fix]
        L.u[lanes], L.g[lanes] = uf, gf
        m = np.flatnonzero(movable)
        if len(m):
            _move(H, L, lanes[m], j[m], fr[m, j[m]], np.where(uf[m, j[m]] > 1.0, 1.0, -1.0), np.zeros(len(m)), b)
        L.fresh[lanes] = True
        L.nupd[lanes[~movable]] = refresh
        L.seg[lanes[~movable]] += 1  # repairs count against the segment cap (then the exact fallback)
        keep = np.ones(len(fin), bool)
        keep[fix] = False
        fin, t, c, h, f1, lo, up, u1, g1, free, el, hard = (
            x[keep] for x in (fin, t, c, h, f1, lo, up, u1, g1, free, el, hard))
    bad = np.flatnonzero(hard)
    if len(bad):
        info["fallback"] += len(bad)
        ub = _finish(H, f1[bad], h[bad], lo[bad], up[bad], el[bad, 0])
        u1[bad] = ub
        g1[bad] = _hmul(H, h[bad], ub) + f1[bad]
        fb = fin[bad]
        L.lower[fb], L.upper[fb] = ub <= 0.0, ub >= 1.0
        L.perm[fb], L.nfree[fb] = _free_first(L.lower[fb], L.upper[fb])
        L.nupd[fb] = refresh  # the stored inverse belongs to another set now
    U[t, c] = u1
    # -- look ahead: the same working set for the next frames, one product with the inverse each
    if k_look:
        T = len(f)
        ok_lane = np.flatnonzero((L.nupd[fin] < refresh) & (t + 1 < L.end[fin]))
        if len(ok_lane):
            ln = fin[ok_lane]
            tt = t[ok_lane, None] + 1 + np.arange(k_look)[None]
            tc = np.minimum(tt, T - 1)
            cc = c[ok_lane, None]
            df = f[tc, cc] - f1[ok_lane, None, :]  # (n, k, K)
            p = L.perm[ln, :b]
            x = -np.take_along_axis(df, p[:, None, :], axis=2) @ _blocks(L, ln, b)  # inverse symmetric
            du = np.zeros(df.shape)
            np.put_along_axis(du, np.broadcast_to(p[:, None, :], x.shape), x, axis=2)
            Uk = u1[ok_lane, None, :] + du
            Gk = g1[ok_lane, None, :] + df + _lmul(H, L, ln, du)
            okk = _kkt_ok(Uk, Gk, L.lower[ln, None, :], L.upper[ln, None, :], eps_all[tc, cc][:, :, None])
            okk &= (tt < L.end[ln, None]) & (idx[tc, cc] == L.h[ln, None])
            n_ok = np.argmin(np.concatenate([okk, np.zeros((len(ln), 1), bool)], axis=1), axis=1)  # accepted prefix
            look[0] += len(ln)
            look[1] += int((n_ok > 0).sum())
            hit = np.flatnonzero(n_ok > 0)
            if len(hit):
                info["lookahead"] += int(n_ok[hit].sum())
                r, k = np.nonzero(np.arange(k_look)[None] < n_ok[hit, None])
                U[tt[hit][r, k], cc[hit, 0][r]] = Uk[hit][r, k]
                pos = ok_lane[hit]
                last = n_ok[hit] - 1
                u1[pos], g1[pos] = Uk[hit, last], Gk[hit, last]
                t[pos] = tt[hit, last]
                f1[pos] = f[t[pos], c[pos]]
                L.t[fin[pos]] = t[pos]
    # -- next frame: start from this one's solution (exact optimum of f_0 = lambda - H u1)
    nxt = t + 1
    cont = nxt < L.end[fin]
    L.active[fin[~cont]] = False
    go = fin[cont]
    if not len(go):
        return go, None
    L.t[go] = nxt[cont]
    hn = idx[L.t[go], L.c[go]]
    new_h = hn != L.h[go]
    if new_h.any():
        _set_h(H, L, go[new_h], hn[new_h])
    gg = g1[cont]
    lam = np.where(L.lower[go], np.maximum(gg, 0.0), np.where(L.upper[go], np.minimum(gg, 0.0), 0.0))
    Hu = gg - f1[cont]
    if new_h.any():
        Hu[new_h] = _hmul(H, hn[new_h], u1[cont][new_h])
        L.nupd[go[new_h]] = refresh
    L.delta[go] = f[L.t[go], L.c[go]] - lam + Hu
    L.g[go] = lam
    L.u[go] = u1[cont]
    L.tau[go] = 0.0
    L.seg[go] = 0
    L.last[go] = -1
    L.fresh[go] = True
    return go, Hu


def _steal(H, f, idx, L, go, Hu, steal, info):
    """Idle lanes take the second half of the longest remaining runs of the lanes ``go`` that
    have just started a frame from an exact solution (module docstring)."""
    idle = np.flatnonzero(~L.active)
    if not len(idle) or not len(go):
        return
    left = L.end[go] - L.t[go]
    cand = np.flatnonzero(left >= steal)
    if not len(cand):
        return
    cand = cand[np.argsort(-left[cand], kind="stable")][:len(idle)]
    v = go[cand]
    th = idle[:len(cand)]
    m = L.t[v] + left[cand] // 2
    info["steals"] += len(v)
    L.end[th] = L.end[v]
    L.end[v] = m
    L.t[th] = m
    L.c[th] = L.c[v]
    for name in ("lower", "upper", "perm", "nfree", "inv", "u", "g", "nupd"):
        getattr(L, name)[th] = getattr(L, name)[v]
    hth = idx[m, L.c[v]]
    hu = Hu[cand]
    other = hth != L.h[v]
    if other.any():
        hu[other] = _hmul(H, hth[other], L.u[v][other])
        L.nupd[th[other]] = 10 ** 9  # refresh at the next round
    _set_h(H, L, th, hth)
    L.delta[th] = f[m, L.c[v]] - L.g[v] + hu
    L.tau[th] = 0.0
    L.seg[th] = 0
    L.last[th] = -1
    L.fresh[th] = True
    L.active[th] = True


def _move(H, L, mv, j, was_free, dj, gj, b):
    """Apply the breakpoint of each moving lane: index j joins a bound or leaves the free set.

    Both cases are one symmetric rank-one change of the stored inverse ``M = H_FF^-1`` and of
    the direction ``d = -M delta_F`` (so the next segment needs no product with M): with
    ``x = M z``,

    * j leaves (compact position p): ``z = e_p``, ``M <- M - x x^T / x_p``,
      ``d <- d - x d_p / x_p``, then row/column p is replaced by the last free one;
    * j joins (position q = nfree): ``z = H_Fj``, Schur complement ``s = H_jj - z^T x``,
      ``M <- M + x x^T / s``, row/column q = ``-x / s``, ``M_qq = 1 / s``;
      ``d_F <- d_F + x gamma_j / s``, ``d_j = -gamma_j / s`` (``gamma_j`` = dg_j/dtau).
    """
    L.seg[mv] += 1
    L.last[mv] = j
    L.nupd[mv] += 1
    n = len(mv)
    full = np.take(L.inv, mv, axis=0)  # whole blocks: a memcpy per lane, not an element-wise gather
    Ms = full[:, :b, :b]
    perm = L.perm[mv]
    nfree = L.nfree[mv]
    d = L.d[mv]
    rm = np.flatnonzero(was_free)
    ad = np.flatnonzero(~was_free)
    p = np.argmax(perm[rm, :b] == j[rm, None], axis=1)  # compact position of a leaving index
    Z = np.zeros((n, b))
    Z[rm, p] = 1.0
    live = np.arange(b)[None] < nfree[ad, None]
    Z[ad] = H[L.h[mv[ad]][:, None], perm[ad, :b], j[ad, None]] * live
    X = (Ms @ Z[:, :, None])[:, :, 0]
    coef = np.empty(n)
    coef[rm] = -1.0 / X[rm, p]
    schur = H[L.h[mv[ad]], j[ad], j[ad]] - np.einsum("ni,ni->n", Z[ad], X[ad])
    coef[ad] = 1.0 / schur
    Ms += X[:, :, None] * (coef[:, None] * X)[:, None, :]
    # direction, in the old compact order (before the permutation changes below)
    scale = np.empty(n)
    scale[rm] = -d[rm, j[rm]] / X[rm, p]
    scale[ad] = gj[ad] / schur
    np.put_along_axis(d, perm[:, :b], np.take_along_axis(d, perm[:, :b], 1) + scale[:, None] * X, 1)
    d[rm, j[rm]] = 0.0
    d[ad, j[ad]] = -gj[ad] / schur
    if len(rm):  # free -> bound
        ln, jr, to_up = mv[rm], j[rm], dj[rm] > 0
        L.lower[ln, jr] = ~to_up
        L.upper[ln, jr] = to_up
        L.u[ln, jr] = to_up.astype(np.float64)
        q = nfree[rm] - 1
        Ms[rm, p, :] = Ms[rm, q, :]
        Ms[rm, :, p] = Ms[rm, :, q]
        Ms[rm, q, :] = 0.0
        Ms[rm, :, q] = 0.0
        perm[rm, p] = perm[rm, q]
        perm[rm, q] = jr
        nfree[rm] -= 1
    if len(ad):  # bound -> free
        ln, ja, q = mv[ad], j[ad], nfree[ad]
        L.lower[ln, ja] = False
        L.upper[ln, ja] = False
        L.g[ln, ja] = 0.0
        w = X[ad] * coef[ad, None]
        Ms[ad, q, :] = -w
        Ms[ad, :, q] = -w
        Ms[ad, q, q] = coef[ad]
        pj = np.argmax(perm[ad] == ja[:, None], axis=1)
        perm[ad, pj] = perm[ad, q]
        perm[ad, q] = ja
        nfree[ad] += 1
    L.inv[mv] = full
    L.perm[mv], L.nfree[mv], L.d[mv] = perm, nfree, d
