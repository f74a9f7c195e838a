"""Slow, obviously-correct reference solvers for the tests and benchmarks (STYLE.md, rule 9).

* :func:`kronecker_system`: the spacetime energy of Seol et al. 2012 (eq. 2, 4, 5, §5, §7.1)
  assembled literally as one sparse system over all ``T K`` weights with ``scipy.sparse.kron``;
* :func:`spacetime_reference`: that system solved by ``spsolve`` (the reference of
  :class:`core.solvers.spacetime.SpacetimeSolver`);
* :func:`bounded_spacetime_reference`: the same energy with bounds and L1 as a general sparse QP
  (Clarabel or OSQP, the optional ``qp`` extra; the reference of
  :mod:`core.solvers.bounded_spacetime`);
* :func:`solve_qp_scipy`: one ``scipy.optimize.minimize`` call per small QP (the reference of
  :mod:`core.solvers.qp`).

No production code path calls these: they are slow by design and exist so that a solver can be
compared with something one can check by eye.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.optimize import Bounds, LinearConstraint, minimize

from core.prior import PCAPrior, alpha_for_units, prior_quadratic
from core.solvers.inputs import as_basis, as_nonnegative, as_sequence, as_valid, zero_filled
from core.solvers.spacetime import known_matrix

__all__ = ["KroneckerSystem", "kronecker_system", "spacetime_reference", "bounded_spacetime_reference",
           "solve_qp_scipy"]


class KroneckerSystem(NamedTuple):
    """The literal normal equations over all ``T K`` weights: ``E = x^T H x - 2 r^T x + const``.

    ``x = vec(W)`` stacks the frames' weight vectors; ``known`` (T K,) holds the known entries
    (NaN = free).
    """

    H: sp.csc_matrix
    r: np.ndarray
    known: np.ndarray


def kronecker_system(B, S, alpha: float, beta: float, prior, known, *, boundary="neutral",
                     valid=None, marker_weights=None, frame_weights=None, alpha_units: str = "cm",
                     ridge: float = 0.0, name_target=None, name_weight=0.0, quadratic=None) -> KroneckerSystem:
    """The paper's sparse Kronecker system, assembled literally (the slow references' core).

    Stacks the least-squares rows of Seol et al. 2012 eq. 5 and §5, §7.1 with
    ``scipy.sparse.kron`` (``vec(W)`` stacks the frames' weight vectors)::

        J_match = diag(mask_e) (D (x) B),          y_match = diag(mask_e) (D (x) I_3M) vec(S)
        J_prior = sqrt(alpha) (I_T (x) Lambda^-1/2 E^T B),  y_prior = sqrt(alpha) (1_T (x) Lambda^-1/2 E^T mean)
        J_pos   = diag(sqrt(beta f_t gamma_m valid_tm)) (I_T (x) B),  y_pos = ... vec(S)
        J_ridge = sqrt(rho) I
        J_name  = diag(sqrt(gamma_k) [column k has a namesake]) (per frame),  y_name = ... vec(W_named)

    and returns ``H = J^T J``, ``r = J^T y`` (with a (P, q) prior ``alpha (I (x) P)`` and
    ``alpha (1 (x) q)`` are added instead of its rows).

    Parameters
    ----------
    B, S, alpha, beta, prior, known, boundary, valid, marker_weights, frame_weights, alpha_units
        As :class:`~core.solvers.spacetime.SpacetimeSolver` (``prior`` None = PCA of ``B``'s shapes).
    ridge : float
        Absolute ridge ``rho`` (m^2); use ``SpacetimeSolver(...).ridge_`` to compare.
    name_target : (T, K) float, optional
        Namesake curves, NaN columns = no namesake (as :class:`SpacetimeSolver`).
    name_weight : float or (K,) float
        Absolute name weight ``gamma`` (m^2); use ``SpacetimeSolver(...).name_weight_``.
    quadratic : (K, K) float, optional
        Absolute coupling ``Q`` (m^2), added as ``I_T (x) Q``; use ``SpacetimeSolver(...).quadratic_``.
    """
    Bm = as_basis(B)
    n3, K = Bm.shape
    M = n3 // 3
    S3 = as_sequence(S, M)
    T = len(S3)
    valid = as_valid(valid, S3)
    Sz = zero_filled(S3, valid)
    a = alpha_for_units(alpha, alpha_units)
    gam = np.ones(M) if marker_weights is None else as_nonnegative(marker_weights, (M,), "marker_weights")
    fw = np.ones(T) if frame_weights is None else as_nonnegative(frame_weights, (T,), "frame_weights")
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
    if name_target is not None:
        Wn = np.asarray(name_target, dtype=np.float64)
        has = np.isfinite(Wn).all(0)
        gn = np.broadcast_to(np.asarray(name_weight, dtype=np.float64), (K,)) * has
        if (gn > 0).any():
            wn = np.tile(np.sqrt(gn), T)
            blocks.append(sp.diags(wn, format="csr"))
            rhs.append(wn * np.where(has, Wn, 0.0).ravel())
    J = sp.vstack(blocks, format="csc")
    y = np.concatenate(rhs)
    H = (J.T @ J).tocsc()
    r = J.T @ y
    if Pextra is not None:
        H = (H + Pextra[0]).tocsc()
        r = r + Pextra[1]
    if quadratic is not None:
        H = (H + sp.kron(sp.identity(T), sp.csr_matrix(np.asarray(quadratic, dtype=np.float64)), format="csc")).tocsc()
    return KroneckerSystem(H, np.asarray(r).ravel(), Kn.ravel())


def spacetime_reference(B, S, alpha: float, beta: float, prior, known, *, boundary="neutral",
                        valid=None, marker_weights=None, frame_weights=None, alpha_units: str = "cm",
                        ridge: float = 0.0, name_target=None, name_weight=0.0, quadratic=None) -> np.ndarray:
    """Slow, literal reference: the paper's sparse Kronecker system solved by ``spsolve``.

    :func:`kronecker_system`, then ``H_uu x_u = r_u - H_uk x_k`` for the free entries with
    :func:`scipy.sparse.linalg.spsolve`.

    Parameters
    ----------
    As :func:`kronecker_system`.

    Returns
    -------
    (T, K) float
    """
    T, K = len(np.asarray(S)), as_basis(B).shape[1]
    H, r, xk = kronecker_system(B, S, alpha, beta, prior, known, boundary=boundary, valid=valid,
                                marker_weights=marker_weights, frame_weights=frame_weights,
                                alpha_units=alpha_units, ridge=ridge, name_target=name_target,
                                name_weight=name_weight, quadratic=quadratic)
    kn = np.isfinite(xk)
    fr = ~kn
    x = xk.copy()
    if fr.any():
        x[fr] = scipy.sparse.linalg.spsolve(H[fr][:, fr].tocsc(), r[fr] - H[fr][:, kn] @ xk[kn])
    return x.reshape(T, K)


def bounded_spacetime_reference(B, S, alpha: float, beta: float, prior, known, *, lower=None, upper=None,
                                l1=0.0, solver: str = "clarabel", tol: float = 1e-10, **kw):
    """Slow reference: the literal Kronecker QP solved by a general sparse QP solver.

    ``min x^T H x - 2 r^T x + l1^T |x|`` subject to ``lower <= x <= upper`` and the known
    entries, with ``(H, r)`` from :func:`kronecker_system` (known entries
    eliminated). The L1 term is linear where the bounds have one sign and uses auxiliary
    variables ``t >= |x|`` where they straddle zero.

    Parameters
    ----------
    B, S, alpha, beta, prior, known
        As :class:`~core.solvers.spacetime.SpacetimeSolver`; ``kw`` passes ``boundary``, ``valid``,
        ``marker_weights``,
        ``frame_weights``, ``alpha_units``, ``ridge`` (absolute), ``name_target``,
        ``name_weight`` (absolute), ``quadratic`` (absolute) on to :func:`kronecker_system`.
    lower, upper : float or (K,) float, optional
    l1 : float or (K,) float
        Absolute L1 weight (use ``SpacetimeSolver(...).l1_``).
    solver : {"clarabel", "osqp"}
        Clarabel (interior point) or OSQP (ADMM), both optional: ``pip install clarabel osqp``
        (the ``test`` extra).
    tol : float
        The solver's own tolerances (Clarabel: gap and feasibility; OSQP: eps_abs/eps_rel).

    Returns
    -------
    W : (T, K) float
    info : dict with the solver's ``status``, ``iterations`` and ``seconds``
    """
    Bm = np.asarray(B)
    K = Bm.shape[0] if Bm.ndim == 3 else Bm.shape[1]
    T = len(S)
    sysk = kronecker_system(B, S, alpha, beta, prior, known, **kw)
    xk = sysk.known
    kn = np.isfinite(xk)
    fr = ~kn
    H = sysk.H
    Hf = H[fr][:, fr].tocsc()
    q = -2.0 * (sysk.r[fr] - H[fr][:, kn] @ xk[kn])
    nf = int(fr.sum())
    lo = np.tile(np.broadcast_to(-np.inf if lower is None else np.asarray(lower, float), (K,)), T)[fr]
    hi = np.tile(np.broadcast_to(np.inf if upper is None else np.asarray(upper, float), (K,)), T)[fr]
    lam = np.tile(np.broadcast_to(np.asarray(l1, float), (K,)), T)[fr]
    pos = (lam > 0) & (lo >= 0)
    neg = (lam > 0) & (hi <= 0)
    q = q + np.where(pos, lam, 0.0) - np.where(neg, lam, 0.0)
    aux = np.flatnonzero((lam > 0) & ~pos & ~neg)
    na = len(aux)
    P = sp.block_diag([2.0 * Hf, sp.csc_matrix((na, na))], format="csc")
    qq = np.concatenate([q, lam[aux]])
    I = sp.identity(nf, format="csc")
    rows_u = np.flatnonzero(np.isfinite(hi))
    rows_l = np.flatnonzero(np.isfinite(lo))
    t0 = time.perf_counter()
    if solver == "clarabel":
        try:
            import clarabel
        except ImportError:
            raise ImportError("bounded_spacetime_reference(solver='clarabel') needs clarabel: pip install clarabel "
                              "(or the test extra: pip install -e .[test])") from None
        blocks, b = [], []
        if len(rows_u):
            blocks.append(sp.hstack([I[rows_u], sp.csc_matrix((len(rows_u), na))]))
            b.append(hi[rows_u])
        if len(rows_l):
            blocks.append(sp.hstack([-I[rows_l], sp.csc_matrix((len(rows_l), na))]))
            b.append(-lo[rows_l])
        if na:
            Ea = sp.csc_matrix((np.ones(na), (np.arange(na), aux)), shape=(na, nf))
            Ia = sp.identity(na, format="csc")
            blocks += [sp.hstack([Ea, -Ia]), sp.hstack([-Ea, -Ia])]
            b += [np.zeros(na), np.zeros(na)]
        Acon = sp.vstack(blocks, format="csc") if blocks else sp.csc_matrix((0, nf + na))
        bcon = np.concatenate(b) if b else np.zeros(0)
        st = clarabel.DefaultSettings()
        st.verbose = False
        st.tol_gap_abs = st.tol_gap_rel = st.tol_feas = tol
        st.tol_ktratio = min(1e-6, st.tol_ktratio)
        st.max_iter = 500
        cones = [clarabel.NonnegativeConeT(Acon.shape[0])] if Acon.shape[0] else []
        sol = clarabel.DefaultSolver(sp.triu(P, format="csc"), qq, Acon, bcon, cones, st).solve()
        z = np.asarray(sol.x)
        info = {"status": str(sol.status), "iterations": int(sol.iterations)}
    elif solver == "osqp":
        try:
            import osqp
        except ImportError:
            raise ImportError("bounded_spacetime_reference(solver='osqp') needs osqp: pip install osqp "
                              "(or the test extra: pip install -e .[test])") from None
        blocks = [sp.hstack([I, sp.csc_matrix((nf, na))])]
        lb, ub = [lo], [hi]
        if na:
            Ea = sp.csc_matrix((np.ones(na), (np.arange(na), aux)), shape=(na, nf))
            Ia = sp.identity(na, format="csc")
            blocks += [sp.hstack([Ea, -Ia]), sp.hstack([-Ea, -Ia])]
            lb += [np.full(na, -np.inf)] * 2
            ub += [np.zeros(na)] * 2
        Acon = sp.vstack(blocks, format="csc")
        m = osqp.OSQP()
        m.setup(sp.triu(P, format="csc"), qq, Acon, np.concatenate(lb), np.concatenate(ub), verbose=False,
                eps_abs=tol, eps_rel=tol, max_iter=200000, polishing=True, polish_refine_iter=10)
        res = m.solve(raise_error=False)
        z = np.asarray(res.x)
        info = {"status": str(res.info.status), "iterations": int(res.info.iter)}
    else:
        raise ValueError(f"solver must be 'clarabel' or 'osqp', got {solver!r}")
    info["seconds"] = time.perf_counter() - t0
    x = xk.copy()
    x[fr] = z[:nf]
    return x.reshape(T, K), info


def solve_qp_scipy(H, f, constraint: str = "simplex", method: str = "SLSQP", tol: float = 1e-15):
    """Slow reference for :mod:`core.solvers.qp`: one ``scipy.optimize.minimize`` call per QP.

    Parameters
    ----------
    H : (N, K, K), f : (N, K)
    constraint : {"simplex", "box"}
    method : "SLSQP" or "trust-constr"
    tol : float
        SLSQP ``ftol`` on the problem scaled to unit mean diagonal (trust-constr: ``gtol``).

    Returns
    -------
    (N, K) float64
    """
    H = np.asarray(H, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64)
    N, K = f.shape
    out = np.empty((N, K))
    bounds = Bounds(np.zeros(K), np.ones(K))
    cons = [LinearConstraint(np.ones((1, K)), -np.inf, 1.0)] if constraint == "simplex" else []
    for n in range(N):
        # scale to unit mean curvature: SLSQP's stopping tests are absolute, and eq. 2 in
        # metres has objective values ~1e-6 (the minimiser does not change)
        sc = max(np.trace(H[n]) / K, 1e-300)
        Hn, fn = H[n] / sc, f[n] / sc
        x0 = np.full(K, 1.0 / (K + 1))
        opts = {"ftol": tol, "maxiter": 1000} if method == "SLSQP" else {"gtol": max(tol, 1e-12), "xtol": 1e-14, "maxiter": 5000}
        res = minimize(lambda x: 0.5 * x @ Hn @ x + fn @ x, x0, jac=lambda x: Hn @ x + fn,
                       hess=(lambda x: Hn) if method == "trust-constr" else None,
                       bounds=bounds, constraints=cons, method=method, options=opts)
        out[n] = res.x
    return out
