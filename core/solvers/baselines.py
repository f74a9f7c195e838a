"""Per-frame retargeting baselines of Seol et al. 2012, §7 (Fig. 9–11).

* **No Const**: ``min_w ||B w_t - s_t||^2`` per frame (unconstrained least squares).
* **Range PF**: the same with ``-0.5 <= w <= 1.5`` (hard constraint, as Bregler et al. 2002).
* **Prior PF**: ``min_w ||B w_t - s_t||^2 + alpha E_prior(w_t)`` (soft constraint, §5 prior
  applied per frame, as Blanz and Vetter 1999).

All take ``B`` as (K, M, 3) marker deltas or the paper's (3M, K) matrix, ``S`` (T, M, 3) source
marker deltas in metres, and a (T, M) validity mask: a missing marker sample drops out of its
frame's fit. Frames are batched: frames sharing a mask pattern share one factorisation and are
solved as right-hand sides of it. A frame with no valid marker gets the minimum-norm answer
(zero weights for No Const, the prior's mode for Prior PF, the box projection of zero for
Range PF) — its result says nothing about the data.

Production controls (:mod:`core.controls`) enter the per-frame solves as two options, both off
by default (then the solves are exactly the papers'):

* ``quadratic`` — a constant (K, K) positive semi-definite ``Q``, relative to ``sigma_max(B)^2``
  like ``ridge``: the energy gains ``sigma_max(B)^2 w_t^T Q w_t`` per frame, i.e. ``Q`` joins the
  Gram matrix ``B_v^T B_v`` (e.g. the symmetry term ``mu_s sum_pairs (w_L - w_R)^2`` of
  :func:`core.controls.symmetry_matrix`);
* ``zero`` — (K,) or (T, K) bool: weights held at 0 (at the nearest bound when 0 is outside
  ``[lower, upper]``): the inactive shapes of an active set, or the weaker shape of a cancel
  pair in :func:`core.controls.cancel_pairs`' second pass.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from core.prior import alpha_for_units, prior_quadratic
from core.solvers.boxqp import solve_box_frame, solve_box_sequence
from core.solvers.inputs import as_basis, as_bounds, as_coupling, as_sequence, as_valid, as_zero_mask, zero_filled
from core.solvers.qp import solve_qp_batch
from core.solvers.spacetime import AUTO_RIDGE

__all__ = ["no_const", "range_pf", "RangePFPrecompute", "prior_pf", "box_lsq"]


def _groups(valid: np.ndarray):
    """Frames grouped by mask pattern: yields (pattern (M,), frame indices)."""
    if valid.all():
        yield valid[0], np.arange(len(valid))
        return
    patterns, inverse = np.unique(valid, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    for g, pat in enumerate(patterns):
        yield pat, np.flatnonzero(inverse == g)


def _setup(B, S, valid):
    Bm = as_basis(B)
    M = Bm.shape[0] // 3
    S3 = as_sequence(S, M)
    valid = as_valid(valid, S3)
    return Bm, zero_filled(S3, valid), valid


def no_const(B, S, valid=None, rcond: float = 1e-7) -> np.ndarray:
    """"No Const" per-frame least squares (Seol et al. 2012, §7): ``min_w ||B w_t - s_t||^2``.

    One ``scipy.linalg.lstsq`` (SVD-based, minimum-norm when ``B`` is rank deficient) per mask
    pattern with all its frames as right-hand sides. Singular values below ``rcond`` times the
    largest count as zero: a rig with more shapes than marker coordinates (Rocketbox: 175
    shapes, 123 coordinates) is numerically rank deficient, and machine-precision singular
    values gave weights of 1e12 that cancel each other.

    Parameters
    ----------
    B : (K, M, 3) or (3M, K) float
    S : (T, M, 3) float, NaN = missing
    valid : (T, M) bool, optional

    Returns
    -------
    (T, K) float
    """
    Bm, Sz, valid = _setup(B, S, valid)
    W = np.zeros((len(Sz), Bm.shape[1]))
    for pat, frames in _groups(valid):
        rows = np.repeat(pat, 3)
        if not rows.any():
            continue
        W[frames] = scipy.linalg.lstsq(Bm[rows], Sz[frames][:, rows].T, cond=rcond, lapack_driver="gelsd")[0].T
    return W


def data_gram(B, S, valid=None) -> dict:
    """The per-frame data term ``||B w_t - s_t||^2`` in weight space on the frames with every marker:
    ``B^T B`` (K, K) and ``s_t^T B`` of those frames, with ``sigma_max(B)^2``.

    These are what :func:`prior_pf` spends most of its time on for a long take at many points
    (1,000 frames x 1,000 dense points: two products with the (T, 3M) take and an SVD of B), and
    they do not depend on alpha, the ridge or the bounds: the pipeline computes them once per take
    and rig (the ``gram`` stage) and :func:`prior_pf` takes them as ``gram`` (the same products, so
    the same numbers).

    Parameters
    ----------
    B, S, valid
        As :func:`no_const`.

    Returns
    -------
    dict: ``frames`` (F,) int, the frames with every marker; ``H`` (K, K) ``B^T B``; ``rhs`` (F, K)
    ``S[frames] B``; ``smax2`` float ``sigma_max(B)^2``.
    """
    Bm, Sz, valid = _setup(B, S, valid)
    full = np.flatnonzero(valid.all(1))
    Sv = Sz if len(full) == len(Sz) else Sz[full]
    return {"frames": full, "H": Bm.T @ Bm, "rhs": Sv @ Bm, "smax2": _smax2(Bm)}


def prior_pf(B, S, alpha: float = 0.5, prior=None, valid=None, alpha_units: str = "cm", ridge: float = 0.0,
             quadratic=None, zero=None, gram=None) -> np.ndarray:
    """"Prior PF" (Seol et al. 2012, §7): ``min_w ||B w_t - s_t||^2 + alpha E_prior(w_t)`` per frame.

    Normal equations ``(B_v^T B_v + alpha P) w_t = B_v^T s_t + alpha q`` (``B_v``: valid rows),
    one Cholesky factorisation per mask pattern; falls back to ``lstsq`` (minimum norm) when the
    matrix is singular.

    Parameters
    ----------
    B, S, valid
        As :func:`no_const`.
    alpha : float >= 0
        Prior weight for lengths in ``alpha_units`` (paper: 0.5 for Prior PF); see
        :func:`core.prior.alpha_for_units`.
    prior : PCAPrior, (P, q) tuple or None
        None: PCA of ``B``'s shapes (paper default).
    ridge : float >= 0
        Relative Tikhonov weight (times ``sigma_max(B)^2``).
    quadratic : (K, K) float, optional
        Relative symmetric PSD ``Q``: adds ``sigma_max(B)^2 w_t^T Q w_t`` (module docstring).
    zero : (K,) or (T, K) bool, optional
        Weights held at 0: their rows and columns leave the frame's normal equations (one
        factorisation per mask pattern and zero pattern).
    gram : dict, optional
        :func:`data_gram` of the same ``B``, ``S`` and ``valid``: its products are used for the
        frames with every marker instead of being computed again; when those are all of ``S``'s
        frames, ``S`` and ``valid`` are not read at all (no pass over a long dense take).

    Returns
    -------
    (T, K) float
    """
    if gram is not None and len(gram["frames"]) == len(S):  # every frame has every marker: all in gram
        Bm = as_basis(B)
        T, groups = len(S), [(None, gram["frames"])]
    else:
        Bm, Sz, valid = _setup(B, S, valid)
        T, groups = len(Sz), _groups(valid)
    K = Bm.shape[1]
    a = alpha_for_units(alpha, alpha_units)
    if a > 0:
        P, q, _ = prior_quadratic(prior, Bm, K)
    else:
        P, q = np.zeros((K, K)), np.zeros(K)
    W = np.zeros((T, K))
    # sigma_max(B)^2 (an SVD) only scales the relative ridge and coupling: not computed without them
    smax2 = (gram["smax2"] if gram is not None else _smax2(Bm)) if ridge > 0 or quadratic is not None else 0.0
    rho = ridge * smax2
    Qs = as_coupling(quadratic, K, smax2, "prior_pf")
    zero = as_zero_mask(zero, T, K, "prior_pf")
    for pat, frames in groups:
        if pat is None or (pat.all() and gram is not None and np.array_equal(gram["frames"], frames)):
            H0, S0 = gram["H"], gram["rhs"]
        else:
            if pat.all():  # every marker: no copies of the take (with 1,000 dense points, 2 x 24 MB per solve)
                Bv, Sv = Bm, (Sz if len(frames) == len(Sz) else Sz[frames])
            else:
                rows = np.repeat(pat, 3)
                Bv, Sv = Bm[rows], Sz[frames][:, rows]
            H0, S0 = Bv.T @ Bv, Sv @ Bv
        H = H0 + a * P + rho * np.eye(K)
        if Qs is not None:
            H = H + Qs
        rhs = S0 + a * q
        if zero is None:
            W[frames] = _spd_solve(H, rhs)
            continue
        zp, zinv = np.unique(zero[frames], axis=0, return_inverse=True)
        zinv = np.asarray(zinv).ravel()
        for g, zrow in enumerate(zp):
            fr, free = frames[zinv == g], ~zrow
            if free.any():
                W[np.ix_(fr, np.flatnonzero(free))] = _spd_solve(H[np.ix_(free, free)], rhs[zinv == g][:, free])
    return W


def _spd_solve(H, rhs):
    """Rows of ``rhs`` solved with the symmetric ``H`` (Cholesky; ``lstsq`` when singular)."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(H, lower=True), rhs.T).T
    except np.linalg.LinAlgError:
        return scipy.linalg.lstsq(H, rhs.T)[0].T


def box_lsq(H: np.ndarray, rhs: np.ndarray, lower, upper, max_iter: int = 30):
    """Batched box-constrained quadratic programs sharing one Hessian.

    ``min_w 1/2 w^T H w - r_t^T w  s.t.  lower <= w <= upper`` for every row ``r_t`` of ``rhs``.
    With ``w = lower + D u``, ``D = diag(upper - lower)``, this is the unit-box QP
    ``min_u 1/2 u^T (D H D) u + (D (H lower - r_t))^T u, 0 <= u <= 1`` solved exactly by the
    batched primal-dual + primal active-set solver of :func:`core.solvers.qp.solve_qp_batch`
    (one implementation of the small-QP machinery for every method).

    Parameters
    ----------
    H : (K, K) float, symmetric positive definite
    rhs : (T, K) float
    lower, upper : float or (K,) float, ``lower < upper``

    Returns
    -------
    W : (T, K) float
    n_fallback : int, rows the primal-dual iteration did not settle (finished by the primal
        active set, still exact)
    """
    K = H.shape[0]
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (K,))
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (K,))
    if not (hi > lo).all():
        raise ValueError(f"box_lsq: need lower < upper for every shape, got lower={lower}, upper={upper}")
    if not len(rhs):
        return np.zeros((0, K)), 0
    d = hi - lo
    Hs = H * d[:, None] * d[None, :]
    f = (lo @ H - rhs) * d
    u, info = solve_qp_batch(Hs[None], f, np.zeros(len(rhs), dtype=np.int64), constraint="box", max_iter=max_iter)
    return np.clip(lo + u * d, lo, hi), int(info["fallback"])


def _smax2(Bm) -> float:
    """sigma_max(B)^2: the scale relative ridges are quoted in (as the spacetime solver's)."""
    return float(np.linalg.norm(Bm, 2) ** 2) if Bm.size else 0.0


def _gram(Bv, rho: float, Qs=None) -> np.ndarray:
    """``H = B_v^T B_v + rho I (+ Q_s)`` of :func:`range_pf`; when it is singular (``B`` rank
    deficient on these markers: the bounded fit is not unique) the spacetime solver's "auto"
    relative ridge is added, which picks the smallest-norm-ish fit."""
    K = Bv.shape[1]
    H = Bv.T @ Bv + rho * np.eye(K)
    if Qs is not None:
        H = H + Qs
    try:
        np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        H = H + AUTO_RIDGE * max(np.linalg.eigvalsh(H)[-1], 1e-300) * np.eye(K)
    return H


def _unit_box(H, sol, lo, held, d, zr):
    """The unit-box form of one Hessian of :func:`range_pf` (``w = start + D u``, the solved
    shapes ``sol``, held ones ``zr`` decoupled at ``u = 0``): ``(D H D, (start H)[sol],
    start[sol], diag D)``; a frame's linear term is ``((start H)[sol] - B_v^T s_t) * diag D``."""
    dz = np.where(zr, 0.0, d)
    Hs = H[np.ix_(sol, sol)] * dz[:, None] * dz[None, :]
    Hs[zr, zr] = 1.0  # a held weight: u = 0 decoupled from the others
    start = lo.copy()
    start[sol[zr]] = held[sol[zr]]  # the value the unit box starts from (held weights sit there)
    return Hs, (start @ H)[sol], start[sol], dz


class RangePFPrecompute:
    """:func:`range_pf` for frames that arrive one at a time with every marker valid: the
    Hessian, its unit-box form and the bounds built once (:func:`_gram`, :func:`_unit_box`, the
    same as the batch solve's), each frame then solved exactly by
    :func:`core.solvers.boxqp.solve_box_sequence` warm-started from the previous frame's
    solution (1 + its active-set changes homotopy segments instead of a cold start).

    Parameters
    ----------
    B : (K, M, 3) or (3M, K) float
    lower, upper, ridge, quadratic
        As :func:`range_pf`.
    zero : (K,) bool, optional
        Weights held at ``clip(0, lower, upper)`` in every frame.

    Attributes
    ----------
    B_ : (3M, K) float, the basis the frames are fitted with
    smax2_ : float, ``sigma_max(B)^2`` (the scale of ``ridge`` and ``quadratic``)
    """

    def __init__(self, B, lower=-0.5, upper=1.5, ridge: float = 0.0, quadratic=None, zero=None):
        Bm = as_basis(B)
        K = Bm.shape[1]
        self.B_ = Bm
        self.lo_, self.hi_ = as_bounds(lower, upper, K, "range_pf", finite=True)
        z = as_zero_mask(zero, 1, K, "range_pf")
        self.zero_ = None if z is None else z[0]
        self.held_ = np.clip(0.0, self.lo_, self.hi_)
        smax2 = self.smax2_ = _smax2(Bm)
        self.sol_ = np.flatnonzero(self.hi_ > self.lo_)
        zr = np.zeros(len(self.sol_), bool) if self.zero_ is None else self.zero_[self.sol_]
        H = _gram(Bm, ridge * smax2, as_coupling(quadratic, K, smax2, "range_pf"))
        d = (self.hi_ - self.lo_)[self.sol_]
        Hs, self.lin_, self.base_, self.dz_ = _unit_box(H, self.sol_, self.lo_, self.held_, d, zr)
        self.H_ = Hs[None]
        self._memo = {}  # the last working set's factor (core.solvers.boxqp.solve_box_frame)

    def solve(self, S, warm=None, linear=None):
        """Weights of frames ``S`` (T, M, 3) (or one frame (M, 3)), the first started from
        ``warm`` (the unit-box point :meth:`solve` returned for the previous frame).

        ``linear`` (T, K) or (K,), optional, is added to ``B^T s_t``: with a diagonal ``c I_N``
        in ``quadratic`` it makes the pull ``c sigma_max(B)^2 ||w_N - n_t||^2`` towards targets
        ``n_t`` (``linear = c sigma_max(B)^2 n_t`` on the pulled shapes ``N``).

        Returns ``(W (T, K), u)``: the weights, and the last frame's unit-box point to pass as
        the next call's ``warm``. Exact as :func:`range_pf` (same KKT certificate)."""
        S = np.asarray(S, dtype=np.float64)
        one = S.ndim == 2
        Sm = S.reshape(1 if one else len(S), -1)
        W = np.broadcast_to(self.held_, (len(Sm), len(self.lo_))).copy()
        u = None
        if len(self.sol_) and len(Sm):
            R = Sm @ self.B_
            if linear is not None:
                R = R + linear
            f = (self.lin_ - R[:, self.sol_]) * self.dz_
            if len(f) == 1 and warm is not None:  # a live frame: the last working set tried first
                u = solve_box_frame(self.H_[0], f[0], warm, self._memo)[None]
            else:
                u = solve_box_sequence(self.H_, f, warm=warm)
            W[:, self.sol_] = np.clip(self.base_ + u * self.dz_, self.lo_[self.sol_], self.hi_[self.sol_])
            u = u[-1]
        if self.zero_ is not None:
            W[:, self.zero_] = self.held_[self.zero_]
        return W, u


def range_pf(B, S, lower: float = -0.5, upper: float = 1.5, valid=None, ridge: float = 0.0, return_info: bool = False,
             quadratic=None, zero=None):
    """"Range PF" (Seol et al. 2012, §7): ``min_w ||B w_t - s_t||^2  s.t. lower <= w <= upper``.

    With ``w = lower + D u``, ``D = diag(upper - lower)``, every frame is the unit-box QP
    ``min_u 1/2 u^T (D H D) u + (D (H lower - B_v^T s_t))^T u``, ``0 <= u <= 1``, ``H = B_v^T B_v``
    (``B_v``: the frame's valid rows). All frames are solved by the compiled parametric
    active-set method of :func:`core.solvers.boxqp.solve_box_sequence`, each frame warm-started
    from the previous one (one Hessian per mask pattern, so frames with missing samples stay in
    the sequence); every frame's KKT conditions are checked, so the result is the exact
    optimum, as SciPy's BVLS (``lsq_linear(method="bvls")``) in the tests. The paper's range is
    [-0.5, 1.5].

    Parameters
    ----------
    B, S, valid
        As :func:`no_const`.
    lower, upper : float or (K,) float
        Weight bounds, finite, ``lower <= upper`` (per shape when arrays). A shape with
        ``lower == upper`` is fixed at that value.
    ridge : float >= 0
        Adds ``ridge * sigma_max(B)^2 ||w||^2`` (a relative Tikhonov term, 0 = the paper's
        method). When ``B`` restricted to a frame's valid markers is rank deficient the fit is
        not unique; a ridge ``1e-9 * lambda_max(B_v^T B_v) ||w||^2`` (the spacetime solver's
        ``ridge="auto"``) is then added to make it so.
    return_info : bool
        Also return the solver's counters (see :func:`core.solvers.boxqp.solve_box_sequence`).
    quadratic : (K, K) float, optional
        Relative symmetric PSD ``Q``: ``H = B_v^T B_v + rho I + sigma_max(B)^2 Q`` (module
        docstring), e.g. :func:`core.controls.symmetry_matrix`.
    zero : (K,) or (T, K) bool, optional
        Weights held at ``clip(0, lower, upper)`` (the active set's off shapes, a cancel pair's
        weaker shape). Per frame a held weight is one more pinned variable: its row and column of
        the unit-box Hessian become the identity (``u = 0``), one Hessian per mask pattern and
        zero pattern in the table of :func:`~core.solvers.boxqp.solve_box_sequence`.

    Returns
    -------
    (T, K) float, and ``info`` when ``return_info``.

    Raises
    ------
    ValueError
        ``lower > upper``, non-finite bounds, bounds of the wrong shape.
    """
    Bm, Sz, valid = _setup(B, S, valid)
    K = Bm.shape[1]
    lo, hi = as_bounds(lower, upper, K, "range_pf", finite=True)
    T = len(Sz)
    zero = as_zero_mask(zero, T, K, "range_pf")
    held = np.clip(0.0, lo, hi)
    W = np.broadcast_to(held, (T, K)).copy()  # frames without any valid marker
    info = {"fallback": 0}
    smax2 = _smax2(Bm)
    rho = ridge * smax2
    Qs = as_coupling(quadratic, K, smax2, "range_pf")
    sol = np.flatnonzero(hi > lo)  # shapes to solve for; the others are pinned at lower
    if len(sol):
        pats, inv = (valid[:1], np.zeros(T, np.int64)) if valid.all() else np.unique(valid, axis=0, return_inverse=True)
        inv = np.asarray(inv).ravel()
        d = (hi - lo)[sol]
        R = Sz @ Bm  # (T, K): B_v^T s_t for every frame (missing samples are zero-filled)
        Hfull = []
        for pat in pats:
            Hfull.append(_gram(Bm[np.repeat(pat, 3)], rho, Qs))
        # per frame: which Hessian (mask pattern, and the pattern of held weights among `sol`)
        if zero is None:
            zpats, zinv = np.zeros((1, len(sol)), bool), np.zeros(T, np.int64)
        else:
            zpats, zinv = np.unique(zero[:, sol], axis=0, return_inverse=True)
            zinv = np.asarray(zinv).ravel()
        combo, cinv = np.unique(np.column_stack([inv, zinv]), axis=0, return_inverse=True)
        cinv = np.asarray(cinv).ravel()
        Htab, lin, dtab = [], [], []
        for p, z in combo:
            Hs, li, base, dz = _unit_box(Hfull[p], sol, lo, held, d, zpats[z])
            Htab.append(Hs)
            lin.append(li)
            dtab.append((base, dz))
        has = pats.any(1)[inv]  # frames with at least one valid marker
        fr = np.flatnonzero(has)
        if len(fr):
            c = cinv[fr]
            dz = np.asarray([x[1] for x in dtab])[c]
            base = np.asarray([x[0] for x in dtab])[c]
            f = (np.asarray(lin)[c] - R[fr][:, sol]) * dz
            u, info = solve_box_sequence(np.asarray(Htab), f, c, return_info=True)
            W[np.ix_(fr, sol)] = np.clip(base + u * dz, lo[sol], hi[sol])
    if zero is not None:
        W[zero] = np.broadcast_to(held, (T, K))[zero]
    return (W, info) if return_info else W
