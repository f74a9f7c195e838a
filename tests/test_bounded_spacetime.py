"""Bounded, sparse spacetime retargeting (bounds, L1, name term, edits under bounds).

Every bounded solve is compared with a general QP solver on the literal Kronecker system
(:func:`bounded_spacetime_reference`: Clarabel at tight tolerance) and, for box constraints, with
SciPy's bounded least squares (BVLS, an exact active-set method) on the dense Cholesky factor;
on small random problems and on the bundled ICT -> Rocketbox take. Properties: bounds hold
exactly, the KKT residual is below the stated tolerance, the unbounded limit is
``SpacetimeSolver.solve``, the energy is not above the clipped unbounded solution's, a hand-derived
one-unknown case.
"""

import os
import warnings

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

from core.prior import PCAPrior
from core.solvers import bounded_spacetime, spacetime
from core.solvers.bounded_spacetime import KKT_RTOL, kkt_violation_per_entry, solve_bounded
from core.solvers.reference import bounded_spacetime_reference, kronecker_system, spacetime_reference
from core.solvers.spacetime import SpacetimeSolver, _capacitance_solve, _Tridiagonals
from datapaths import PERFORMANCES, RIGS

pytest.importorskip("clarabel")


def random_problem(T=40, M=8, K=6, seed=0, scale=1.6):
    """Weights that leave [0, 1] on both sides, so both bounds become active."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(K, M, 3)) * 0.01
    W = np.cumsum(rng.normal(size=(T, K)) * 0.15, axis=0)
    S = np.einsum("tk,kmc->tmc", W, B) * scale + rng.normal(size=(T, M, 3)) * 1e-3
    return B, S, rng


def reference_kw(s: SpacetimeSolver, kw: dict) -> dict:
    """The solver's settings as the references take them (absolute ridge, name weight, l1)."""
    out = {k: kw[k] for k in ("boundary", "valid", "marker_weights", "frame_weights") if k in kw}
    out["ridge"] = s.ridge_
    if kw.get("name_target") is not None:
        out["name_target"] = kw["name_target"]
        out["name_weight"] = s.name_weight_
    return out


def qp_reference(B, S, s, kw):
    W, info = bounded_spacetime_reference(B, S, kw.get("alpha", 0.01), kw.get("beta", 0.0), kw.get("prior"),
                                          kw.get("known"), lower=s.lower_, upper=s.upper_, l1=s.l1_, tol=1e-12,
                                          **reference_kw(s, kw))
    assert "Solved" in info["status"], info
    return W


def bvls_reference(B, S, s, kw):
    """Box QP (L1 only as a linear term, lower >= 0) as bounded least squares on the Cholesky factor."""
    H, r, xk = kronecker_system(B, S, kw.get("alpha", 0.01), kw.get("beta", 0.0), kw.get("prior"), kw.get("known"),
                                **reference_kw(s, kw))
    kn = np.isfinite(xk)
    fr = ~kn
    Hd = H.toarray()
    Hf = Hd[np.ix_(fr, fr)]
    rf = r[fr] - Hd[np.ix_(fr, kn)] @ xk[kn] - 0.5 * np.tile(s.l1_, s.T)[fr]
    L = np.linalg.cholesky(Hf)
    y = scipy.linalg.solve_triangular(L, rf, lower=True)
    lo, hi = np.tile(s.lower_, s.T)[fr], np.tile(s.upper_, s.T)[fr]
    x = scipy.optimize.lsq_linear(L.T, y, bounds=(lo, hi), method="bvls", tol=1e-15, max_iter=20000).x
    out = xk.copy()
    out[fr] = x
    return out.reshape(s.T, s.K)


def check_solution(s: SpacetimeSolver, W):
    """Bounds hold exactly, known weights exact, KKT residual within the stated tolerance."""
    assert (W >= s.lower_).all() and (W <= s.upper_).all()
    kn = s.known_
    k = np.isfinite(kn)
    assert np.array_equal(W[k], kn[k])
    assert s.kkt_residual(W) <= s.tol
    assert s.info_["converged"] and s.info_["kkt"] <= s.tol


def F(s, W):
    return s.energy(W).total


CASES = {
    "box": dict(lower=0.0, upper=1.0),
    "box_alpha_beta": dict(alpha=30.0, beta=0.2, lower=0.0, upper=1.0),
    "box_per_shape": dict(alpha=30.0, lower=np.linspace(-0.3, 0.0, 6), upper=np.linspace(0.5, 1.2, 6)),
    "box_l1": dict(alpha=30.0, lower=0.0, upper=1.0, l1=0.05),
    "l1_across_zero": dict(alpha=30.0, lower=-0.4, upper=1.0, l1=0.05),
    "l1_only": dict(alpha=30.0, l1=0.05),
    "box_known": dict(alpha=30.0, lower=0.0, upper=1.0, known={13: np.r_[0.7, [np.nan] * 5], 20: np.full(6, 0.5),
                                                               27: np.r_[[np.nan] * 5, 0.0]}),
    "box_name": dict(alpha=30.0, lower=0.0, upper=1.0, name_weight=0.3),
    "box_mask": dict(alpha=30.0, beta=0.1, lower=0.0, upper=0.6),
    "box_fw_mw_l1": dict(alpha=30.0, beta=0.2, lower=0.0, upper=1.0, l1=0.02),
    "box_nobnd": dict(alpha=30.0, beta=0.3, lower=0.4, upper=0.5, boundary="none"),
}


def _setup(name):
    B, S, rng = random_problem(seed=list(CASES).index(name))
    kw = dict(CASES[name])
    T, K, M = len(S), B.shape[0], B.shape[1]
    if "name" in name:
        Wn = np.full((T, K), np.nan)
        Wn[:, [1, 4]] = rng.uniform(0, 1, (T, 2))
        kw["name_target"] = Wn
    if "mask" in name:
        v = rng.random((T, M)) > 0.15
        v[T // 4] = False
        kw["valid"] = v
        ex = np.einsum("tk,kmc->tmc", rng.uniform(0, 1, (60, K)), B) + rng.normal(size=(60, M, 3)) * 1e-3
        kw["prior"] = PCAPrior().fit(ex, basis=B)
    if "fw_mw" in name:
        kw["frame_weights"] = rng.uniform(0, 3, T)
        kw["marker_weights"] = rng.uniform(0, 3, M)
    if "nobnd" in name:
        ex = np.einsum("tk,kmc->tmc", rng.uniform(0, 1, (60, K)), B) + rng.normal(size=(60, M, 3)) * 1e-3
        kw["prior"] = PCAPrior().fit(ex, basis=B)
    return B, S, kw


# -- against general QP solvers -------------------------------------------------------------
@pytest.mark.parametrize("name", list(CASES))
def test_random_matches_general_qp(name):
    B, S, kw = _setup(name)
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    check_solution(s, W)
    expect_block = "mask" in name or "fw_mw" in name
    assert s.method_ == ("block+bounded" if expect_block else "fast+bounded")
    assert s.info_["active"] > 0  # the bounds (or L1 zeros) do bind
    R = qp_reference(B, S, s, kw)
    # Clarabel is an interior-point method: its answer is accurate to its tolerance, ours is the
    # exact KKT point; ours must not be worse and both must agree closely
    assert F(s, W) <= F(s, np.clip(R, s.lower_, s.upper_)) * (1 + 1e-12)
    assert np.abs(W - R).max() <= 1e-5
    if "across" not in name and "only" not in name:  # box (L1 linear): the exact active-set BVLS
        Rb = bvls_reference(B, S, s, kw)
        assert np.abs(W - Rb).max() <= 1e-8 * max(1.0, np.abs(Rb).max())


def test_hand_derived_single_unknown():
    """T = 3, K = 1, frames 0 and 2 neutral, alpha = 0: E(w) = 2 ||b w - s||^2 + l1 |w|, so the
    answer is the soft-thresholded, clipped w* = b^T s / b^T b."""
    b = np.array([[[0.01, -0.02, 0.005], [0.0, 0.01, 0.02]]])  # (K=1, M=2, 3)
    s1 = 0.8 * b[0] + np.array([[1e-3, 0, 0], [0, -1e-3, 0]])
    S = np.stack([np.zeros_like(s1), s1, np.zeros_like(s1)])
    bb = float((b**2).sum())
    wstar = float((b[0] * s1).sum()) / bb
    for lower, upper, l1 in [(0.0, 1.0, 0.0), (0.0, 0.5, 0.0), (-1.0, 0.3, 0.0), (-1.0, 1.0, 0.1), (-1, 1, 2.0)]:
        sol = SpacetimeSolver(b, S, alpha=0.0, lower=lower, upper=upper, l1=l1)
        lam = sol.l1_[0]
        expect = np.clip(np.sign(wstar) * max(abs(wstar) - lam / (4 * bb), 0.0), lower, upper)
        W = sol.solve()
        assert W[1, 0] == pytest.approx(expect, rel=1e-12, abs=1e-15)
        assert W[0, 0] == W[2, 0] == 0.0


# -- properties -------------------------------------------------------------------------------
def test_unbounded_limit_is_the_unbounded_solver():
    B, S, rng = random_problem(seed=3)
    K = B.shape[0]
    known = {10: np.r_[0.5, [np.nan] * (K - 1)]}
    ref = SpacetimeSolver(B, S, alpha=30.0, beta=0.1, known=known)
    W0 = ref.solve()
    # infinite bounds and l1 = 0 are the unbounded problem: the same code path, bit for bit
    s = SpacetimeSolver(B, S, alpha=30.0, beta=0.1, known=known, lower=-np.inf, upper=np.full(K, np.inf), l1=0.0)
    assert not s.bounded_
    np.testing.assert_array_equal(s.solve(), W0)
    # finite bounds that never bind: the bounded solver returns the unbounded solution to rounding
    s = SpacetimeSolver(B, S, alpha=30.0, beta=0.1, known=known, lower=-1e3, upper=1e3)
    W = s.solve()
    assert s.bounded_ and s.info_["active"] == 0
    assert np.abs(W - W0).max() <= 1e-12 * np.abs(W0).max()


@pytest.mark.parametrize("name", ["box", "box_l1", "l1_across_zero", "box_mask"])
def test_energy_not_above_clipped_unbounded(name):
    B, S, kw = _setup(name)
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    unb = {k: v for k, v in kw.items() if k not in ("lower", "upper", "l1")}
    W0 = SpacetimeSolver(B, S, **unb).solve()
    assert F(s, W) <= F(s, np.clip(W0, s.lower_, s.upper_))
    rng = np.random.default_rng(1)
    free = np.isnan(s.known_)
    for _ in range(5):  # feasible perturbations only raise the energy
        Wp = np.clip(W + rng.normal(size=W.shape) * 1e-3 * free, s.lower_, s.upper_)
        assert F(s, Wp) >= F(s, W)


@pytest.mark.parametrize("max_iter", [0, 1])
def test_admm_restarts_reach_the_same_answer(max_iter):
    """With the active-set runs cut short, ADMM (whose W-update is the banded solve with the
    re-diagonalised pencil) carries the solve; the answer is the same KKT point."""
    B, S, kw = _setup("l1_across_zero")
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    sys_ = s.range_system()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        W2, info = solve_bounded(sys_, s.lower_, s.upper_, s.l1_, tol=s.tol, max_iter=max_iter)
    assert info["admm"] > 0 and info["converged"]
    assert np.abs(W2 - W).max() <= 1e-7


def test_kkt_violation_per_entry_cases():
    lo, hi, l1 = np.array([0.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0]), np.array([0.0, 0.5, 0.5])
    W = np.array([[0.0, 0.0, 0.3], [1.0, -1.0, 1.5]])
    g = np.array([[2.0, 0.2, -0.5], [-3.0, 0.7, 0.0]])
    v = kkt_violation_per_entry(W, g, lo, hi, l1, scale=10.0)
    # at lower with g >= 0: fine; at the kink |g| <= l1: fine; free: |g + l1 sign w| = 0
    np.testing.assert_allclose(v[0], [0.0, 0.0, 0.0])
    # at upper with g < 0: fine; at lower -1 with g - l1 = 0.2 >= 0: fine; 0.5 outside: 10 * 0.5
    np.testing.assert_allclose(v[1], [0.0, 0.0, 5.0])
    v = kkt_violation_per_entry(W, -g, lo, hi, l1, scale=10.0)
    np.testing.assert_allclose(v[0], [2.0, 0.0, 1.0])


def _kkt_entry_reference(w, g, lo, hi, l1, scale):
    """One entry's violation, straight from the module docstring's conditions."""
    if np.isnan(g):
        return np.inf
    slope_lo, slope_hi = (l1 if lo >= 0 else -l1), (l1 if hi > 0 else -l1)
    if w == lo:
        v = max(-(g + slope_lo), 0.0)
    elif w == hi:
        v = max(g + slope_hi, 0.0)
    elif w == 0 and l1 > 0 and lo < 0 < hi:
        v = max(abs(g) - l1, 0.0)
    else:
        v = abs(g + l1 * np.sign(w))
    return max(v, scale * max(lo - w, w - hi, 0.0))


@pytest.mark.parametrize("seed", range(6))
def test_kkt_violation_per_entry_matches_reference(seed):
    """The compiled per-entry conditions against the plain statement: entries on either bound,
    at zero, free, outside the bounds, NaN gradients; infinite bounds, pinned shapes, with and without L1."""
    rng = np.random.default_rng(seed)
    n, K = 40, 9
    lo = rng.choice([-np.inf, -1.0, 0.0, 0.5], K)
    hi = np.maximum(lo, rng.choice([np.inf, 1.0, 0.0, 2.0], K))
    l1 = rng.choice([0.0, 0.3], K) if seed % 2 else np.zeros(K)
    W = rng.normal(size=(n, K))
    pick = rng.random((n, K))
    W = np.where(pick < 0.2, lo, np.where(pick < 0.4, hi, np.where(pick < 0.5, 0.0, W)))
    W = np.where(np.isfinite(W), W, 0.3)
    g = rng.normal(size=(n, K))
    failed = rng.random((n, K)) < 0.03  # a failed solve: NaN weights and gradients
    g[failed] = W[failed] = np.nan
    g[rng.random((n, K)) < 0.03] = np.nan
    v = kkt_violation_per_entry(W, g, lo, hi, l1, scale=3.0)
    ref = np.array([[_kkt_entry_reference(W[t, k], g[t, k], lo[k], hi[k], l1[k], 3.0) for k in range(K)] for t in range(n)])
    np.testing.assert_array_equal(v, ref)


# -- the exact inner solve --------------------------------------------------------------------
@pytest.mark.parametrize("rescale", [1e-60, 0.5, 1e-120])
@pytest.mark.parametrize("halves", ["one", "serial", "threads"])
@pytest.mark.parametrize("block", [1, 3, 16, 64])
def test_capacitance_solve_matches_dense(block, halves, rescale, monkeypatch):
    """The quasiseparable block Cholesky of E^T H^-1 E against the dense matrix, with a split
    (known frame), a direction whose ratios underflow (prior-dominated) and padding; as one
    recursion or as two halves (the later one in reversed order) joined by their K x K
    interface, one after the other or in two threads; the state's lazy scale folded into it at
    the default threshold, almost every block (0.5) or rarely (1e-120: the split, the
    underflowing direction)."""
    monkeypatch.setattr(spacetime, "_STATE_RESCALE", rescale)
    rng = np.random.default_rng(block)
    K, n = 5, 70
    mu = rng.uniform(0, 1, K)
    mu[0], mu[1] = 1.0, 1e-9
    nu = 1.0 - mu
    nu[0] = 1e-3
    dL = np.full(n, 2.0)
    dL[[0, -1]] = 1.0
    eL = -np.ones(n - 1)
    eL[30] = 0.0
    tri = _Tridiagonals(mu, nu, dL, eL, "test").factor()
    U = np.linalg.qr(rng.normal(size=(K, K)))[0] * rng.uniform(0.5, 2.0, K)
    G = [np.linalg.inv(np.diag(mu[j] * dL + nu[j]) + np.diag(mu[j] * eL, 1) + np.diag(mu[j] * eL, -1)) for j in range(K)]
    np.testing.assert_allclose(tri.inv_diag, [np.diag(g) for g in G], rtol=1e-12)
    key = np.unique(rng.integers(0, n * K, 90))
    rows, ks = key // K, key % K
    C = np.einsum("aj,bj,jab->ab", U[ks], U[ks], np.array([g[np.ix_(rows, rows)] for g in G]))
    c = rng.normal(size=len(rows))
    perm = rng.permutation(len(rows))
    kw = dict(split=False) if halves == "one" else dict(split=True, threads=halves == "threads")
    lam = _capacitance_solve(tri, U, rows[perm], ks[perm], c[perm], block=block, **kw)
    ref = np.linalg.solve(C, c)
    assert np.abs(lam - ref[perm]).max() <= 1e-10 * np.abs(ref).max()


@pytest.mark.parametrize("case", ["capacitance", "sweep", "holes"])
def test_block_sweep_on_free_entries_matches_dense(case, monkeypatch):
    """The block sweep over each frame's free entries (taken for many fixed entries, and always
    with missing markers) against the dense Kronecker system with the same entries fixed: half
    the entries fixed at random, two whole frames fixed inside the range, one frame with none."""
    B, S, rng = random_problem(T=60, M=9, K=7, seed=3)
    kw = dict(beta=0.3, boundary="neutral")
    holes = case == "holes"
    if case == "sweep":  # what a take with many entries on a bound gets from the fast path
        import core.solvers.spacetime as spacetime

        monkeypatch.setattr(spacetime, "_block_is_cheaper", lambda fixed, p: True)
    if holes:
        valid = rng.random(S.shape[:2]) > 0.15
        S = np.where(valid[..., None], S, np.nan)
        kw["valid"] = valid
    s = SpacetimeSolver(B, S, 0.01, kw["beta"], None, None, kw["boundary"], kw.get("valid"))
    rs = s.range_system()
    assert rs.path == ("block" if holes else "fast")
    fixed = rng.random((s.T, s.K)) < 0.5
    fixed[[20, 21]] = True
    fixed[40] = False
    values = rng.uniform(0.0, 1.0, (s.T, s.K))
    X, g = rs.solve(fixed, values)
    assert s.method_ == ("fast+capacitance" if case == "capacitance" else "block")
    H, r, xk = kronecker_system(B, S, 0.01, kw["beta"], None, None, **reference_kw(s, kw))
    H = H.toarray()
    allfix = (rs.fixed | fixed).ravel()
    xv = np.where(rs.fixed, rs.values, values).ravel()
    x = np.where(allfix, xv, 0.0)
    fr = ~allfix
    x[fr] = np.linalg.solve(H[np.ix_(fr, fr)], r[fr] - H[np.ix_(fr, allfix)] @ xv[allfix])
    assert np.abs(X.ravel() - x).max() <= 1e-9 * np.abs(x).max()
    # the gradient the bounded solver reads: H x - r (x 2) on every entry of a frame not fully known
    grad = 2.0 * (H @ x - r).reshape(s.T, s.K)
    live = ~rs.full
    assert np.abs(g[live] - grad[live]).max() <= 1e-7 * np.abs(grad).max()


# -- the name term ----------------------------------------------------------------------------
def test_name_term():
    B, S, rng = random_problem(seed=5)
    T, K = len(S), B.shape[0]
    Wn = np.full((T, K), np.nan)
    Wn[:, [0, 3]] = rng.uniform(0, 1, (T, 2))
    base = SpacetimeSolver(B, S, alpha=30.0).solve()
    # gamma = 0 (or no namesake at all) is today's behaviour exactly
    np.testing.assert_array_equal(SpacetimeSolver(B, S, alpha=30.0, name_target=Wn, name_weight=0.0).solve(), base)
    np.testing.assert_array_equal(SpacetimeSolver(B, S, alpha=30.0, name_target=np.full((T, K), np.nan),
                                                  name_weight=1.0).solve(), base)
    # gamma I on a subset of shapes is the same matrix every frame: it joins C of the pencil and
    # the fast path stays exact (measured against the Kronecker system)
    err = []
    for gamma in (0.01, 1.0, 100.0):
        s = SpacetimeSolver(B, S, alpha=30.0, name_target=Wn, name_weight=gamma)
        W = s.solve()
        assert s.method_ == "fast"
        R = spacetime_reference(B, S, 30.0, 0.0, None, None, name_target=Wn, name_weight=s.name_weight_)
        assert np.abs(W - R).max() <= 1e-8 * np.abs(R).max()
        np.testing.assert_allclose(s.solve(method="block"), R, atol=1e-8 * np.abs(R).max())
        err.append(np.abs(W[1:-1, [0, 3]] - Wn[1:-1, [0, 3]]).mean())
        assert np.abs(s.gradient(W)[1:-1]).max() <= 1e-10 * s.scale_
    assert err[0] > err[1] > err[2]  # a larger gamma pulls harder toward the namesakes
    # per-frame gaps in a namesake curve are refused (that column would not be one matrix per frame)
    Wbad = Wn.copy()
    Wbad[5, 0] = np.nan
    with pytest.raises(ValueError, match="column 0 mixes"):
        SpacetimeSolver(B, S, name_target=Wbad, name_weight=1.0)
    with pytest.raises(ValueError, match="needs name_target"):
        SpacetimeSolver(B, S, name_weight=1.0)


# -- edits under bounds -----------------------------------------------------------------------
def test_bounded_edit_matches_reference():
    B, S, _ = _setup("box_alpha_beta")
    K = B.shape[0]
    s = SpacetimeSolver(B, S, alpha=30.0, beta=0.2, lower=0.0, upper=1.0, names=[f"s{k}" for k in range(K)])
    W = s.solve()
    a, b, f = 12, 30, 20
    with pytest.warns(UserWarning, match="clipped"):
        W2 = s.edit(W, f, [1.4, 0.2], shapes=["s2", "s4"], window=(a, b))
    np.testing.assert_array_equal(W2[:a + 1], W[:a + 1])
    np.testing.assert_array_equal(W2[b:], W[b:])
    assert W2[f, 2] == 1.0 and W2[f, 4] == 0.2
    assert (W2 >= 0).all() and (W2 <= 1).all()
    row = np.full(K, np.nan)
    row[[2, 4]] = [1.0, 0.2]
    known = {0: W[a], f - a: row, b - a: W[b]}
    R, _ = bounded_spacetime_reference(B, S[a:b + 1], 30.0, 0.2, None, known, lower=0.0, upper=1.0, boundary="none",
                                       tol=1e-12, ridge=s.ridge_)
    Rb = np.clip(R, 0, 1)
    sw = SpacetimeSolver(B, S[a:b + 1], alpha=30.0, beta=0.2, known=known, boundary="none", lower=0.0, upper=1.0)
    assert F(sw, W2[a:b + 1]) <= F(sw, Rb) * (1 + 1e-12)
    assert np.abs(W2[a:b + 1] - R).max() <= 1e-5


def test_known_outside_bounds_is_refused():
    B, S, _ = random_problem()
    with pytest.raises(ValueError, match="boundary='neutral'"):
        SpacetimeSolver(B, S, lower=0.1, upper=1.0)
    with pytest.raises(ValueError, match=r"known\[5\]\[0\] = 2"):
        SpacetimeSolver(B, S, lower=0.0, upper=1.0, known={5: np.r_[2.0, [np.nan] * 5]})
    with pytest.raises(ValueError, match="lower must be <= upper"):
        SpacetimeSolver(B, S, lower=1.0, upper=0.0)
    with pytest.raises(ValueError, match=r"upper: expected a number or \(6,\)"):
        SpacetimeSolver(B, S, upper=np.ones(3))
    with pytest.raises(ValueError, match="l1"):
        SpacetimeSolver(B, S, l1=-1.0)


# -- real data: the bundled ICT -> Rocketbox take, the pipeline's marker problem -------------------
FILES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
             target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))


@pytest.fixture(scope="module")
def rocketbox_problem():
    """B (51 ARKit shapes the markers see, 41 markers) and S (2028 frames) as the pipeline builds them."""
    from core.pipeline import Pipeline, StageCache

    pipe = Pipeline(cache=StageCache(), method="spacetime", target_shapes="arkit", **FILES)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "1 target shapes move no marker" (the tongue)
        res = pipe.results(["calibrate", "personalize", "stabilize"])
    st = res["stabilize"]["source"]
    return np.asarray(res["personalize"]["deltas"]), np.asarray(st.deltas), np.asarray(st.valid), list(res["calibrate"]["rig"].names)


def test_real_matches_general_qp(rocketbox_problem):
    B, S, valid, names = rocketbox_problem
    S = S[300:420]
    kw = dict(alpha=0.01, ridge=1e-5, lower=0.0, upper=1.0)
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    check_solution(s, W)
    assert s.info_["active"] > 100
    R = qp_reference(B, S, s, kw)
    assert F(s, W) <= F(s, np.clip(R, 0, 1)) * (1 + 1e-12)
    # the rig is ill-conditioned (nearly interchangeable shapes): weights agree only to Clarabel's
    # own accuracy, while our energy is the lower one (checked above)
    assert np.abs(W - R).max() <= 1e-3
    # unbounded, the same take leaves [0, 1]
    W0 = SpacetimeSolver(B, S, alpha=0.01, ridge=1e-5).solve()
    assert W0.min() < -0.05
    assert F(s, W) < F(s, np.clip(W0, 0, 1))


def test_real_edit_stays_in_bounds(rocketbox_problem):
    """The issue's case: AK_25_JawOpen = 1.39 at frame 437, half-window 12, bounds [0, 1]."""
    from core.solvers.baselines import range_pf

    B, S, valid, names = rocketbox_problem
    W = range_pf(B, S, 0.0, 1.0, valid, ridge=1e-5)  # the pipeline's default 'bounded' solution
    known = {0: W[0], len(W) - 1: W[-1]}
    f, h = 437, 12
    unb = SpacetimeSolver(B, S, alpha=0.01, known=known, valid=valid, names=names)
    W_unb = unb.edit(W, f, [1.39], shapes=["AK_25_JawOpen"], window=(f - h, f + h))
    assert W_unb.min() < -1 or W_unb.max() > 2  # what the issue saw
    s = SpacetimeSolver(B, S, alpha=0.01, known=known, valid=valid, names=names, lower=0.0, upper=1.0)
    with pytest.warns(UserWarning, match="AK_25_JawOpen = 1.39 -> 1"):
        W2 = s.edit(W, f, [1.39], shapes=["AK_25_JawOpen"], window=(f - h, f + h))
    assert (W2 >= 0).all() and (W2 <= 1).all()
    np.testing.assert_array_equal(W2[:f - h + 1], W[:f - h + 1])
    np.testing.assert_array_equal(W2[f + h:], W[f + h:])
    assert W2[f, names.index("AK_25_JawOpen")] == 1.0
    assert s.info_["converged"] and s.info_["kkt"] <= KKT_RTOL
    assert np.abs(W2[f - h + 1:f + h] - W[f - h + 1:f + h]).max() > 1e-3  # the edit did propagate


def test_osqp_reference_agrees():
    pytest.importorskip("osqp")
    B, S, kw = _setup("box_l1")
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    R, info = bounded_spacetime_reference(B, S, kw["alpha"], 0.0, None, None, lower=s.lower_, upper=s.upper_,
                                          l1=s.l1_, solver="osqp", tol=1e-9, ridge=s.ridge_)
    assert "solved" in info["status"].lower()
    assert F(s, W) <= F(s, np.clip(R, s.lower_, s.upper_)) * (1 + 1e-12)
    assert np.abs(W - R).max() <= 1e-4


@pytest.mark.slow
def test_every_rocketbox_shape_converges_exactly():
    """All 165 Rocketbox shapes on 41 markers (rank 119, ridge 1e-5: nearly interchangeable shapes).

    The active-set runs used to cycle on a few dozen entries here: 2,550 ADMM iterations and ~50
    steps without reaching the tolerance (KKT 2.4e-7 > 1e-9, 8 s for these 150 frames). The
    schedule (stop a run when its state changes stop halving; start one from ADMM only once its
    state has settled) must end exact."""
    from core.pipeline import Pipeline, StageCache

    pipe = Pipeline(cache=StageCache(), method="spacetime", **FILES)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = pipe.results(["personalize", "stabilize"])
    B, S = np.asarray(res["personalize"]["deltas"]), np.asarray(res["stabilize"]["source"].deltas)[300:450]
    assert B.shape[0] == 165
    s = SpacetimeSolver(B, S, alpha=0.01, ridge=1e-5, lower=0.0, upper=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a non-converged solve warns
        W = s.solve()
    check_solution(s, W)
    assert s.info_["admm"] <= 640 and s.info_["pdas"] <= 40, s.info_
    W0 = SpacetimeSolver(B, S, alpha=0.01, ridge=1e-5).solve()
    assert F(s, W) < F(s, np.clip(W0, 0, 1))


def test_bounded_solve_runs_with_one_blas_thread(monkeypatch):
    """The inner solves are thousands of small products that OpenBLAS's threads slow down about
    tenfold: the solve limits BLAS to one thread while it runs and restores the caller's count."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import core.solvers.bounded_spacetime as bs

    def blas_threads():
        return sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})

    seen, inner = [], bs._solve_bounded
    monkeypatch.setattr(bs, "_solve_bounded", lambda *a, **k: (seen.append(blas_threads()), inner(*a, **k))[1])
    rng = np.random.default_rng(3)
    B = rng.normal(size=(5, 6, 3)) * 0.01
    S = np.einsum("tk,kmc->tmc", rng.uniform(-0.2, 1.2, (20, 5)), B)
    with threadpool_limits(limits=2, user_api="blas"):
        outside = blas_threads()
        W = SpacetimeSolver(B, S, alpha=0.01, lower=0.0, upper=1.0).solve()
        after = blas_threads()
    assert outside == after == [2] and seen == [[1]]
    assert W.min() >= 0.0 and W.max() <= 1.0


# -- warm start: one result however it is reached -------------------------------------------
def _warm_vs_cold(B, S, kw, kw_before, **extra):
    """Cold solve of ``kw`` and one warm-started from the solution of ``kw_before``."""
    prev = SpacetimeSolver(B, S, **kw_before, **extra).solve()
    cold_s = SpacetimeSolver(B, S, **kw, **extra)
    cold = cold_s.solve()
    warm_s = SpacetimeSolver(B, S, **kw, **extra)
    warm = warm_s.solve(warm=prev)
    check_solution(warm_s, warm)
    return cold, warm, cold_s.info_, warm_s.info_


@pytest.mark.parametrize("name", ["box", "box_l1", "l1_across_zero", "box_known", "box_mask"])
def test_warm_start_gives_the_cold_result(name):
    B, S, kw = _setup(name)
    before = dict(kw, alpha=kw.get("alpha", 0.01) * 1.5)
    cold, warm, ic, iw = _warm_vs_cold(B, S, kw, before)
    assert "warm" in iw and "warm" not in ic
    assert np.abs(warm - cold).max() <= 1e-9


def test_warm_start_on_the_sample_is_the_cold_result_in_fewer_steps(rocketbox_problem):
    B, S, valid, names = rocketbox_problem
    S = S[:1000]
    kw = dict(ridge=1e-3, lower=0.0, upper=1.0)
    cold, warm, ic, iw = _warm_vs_cold(B, S, dict(kw, alpha=0.0105), dict(kw, alpha=0.01))
    assert iw["warm"] and np.abs(warm - cold).max() <= 1e-9
    assert iw["pdas"] < ic["pdas"]  # the neighbouring setting's state is nearly the answer's


def test_a_bad_or_foreign_hint_changes_nothing():
    B, S, kw = _setup("box")
    s = SpacetimeSolver(B, S, **kw)
    cold = s.solve()
    # a hint of another shape is ignored; one far from the answer either settles on the same
    # minimiser or is dropped for the cold start
    for hint in (np.zeros((3, 3)), np.full(cold.shape, np.nan), np.ones_like(cold), -cold):
        W = SpacetimeSolver(B, S, **kw).solve(warm=hint)
        assert np.abs(W - cold).max() <= 1e-9


def test_a_hint_that_does_not_settle_leaves_the_cold_run_as_it_was():
    B, S, kw = _setup("box_l1")
    s = SpacetimeSolver(B, S, **kw)
    system = s.range_system()
    args = (system, s.lower_, s.upper_, s.l1_)
    cold, ic = solve_bounded(*args, max_iter=1)  # one active-set step: the run goes on with ADMM
    W, iw = solve_bounded(*args, max_iter=1, warm=np.ones((s.T, s.K)))
    assert iw.pop("warm") is False
    assert np.array_equal(W, cold) and iw == ic


def test_warm_kernels_fill_numba_cache():
    """What the dashboard runs at start-up when the cache is cold: after it, the capacitance
    kernels and the KKT check load from numba's cache (no compile in a request)."""
    spacetime.warm_kernels()
    assert spacetime.kernels_cached()


def _prox_state_reference(y, c, lo, hi, lam, known):
    """The active-set rule in numpy, as it was written before it was compiled."""
    y = np.where(known, 0.0, y)
    if not lam.any():
        p = np.clip(y + 0.0, lo, hi)
        fixed = (p == lo) | (p == hi)
        return fixed & ~known, np.where(fixed, p, 0.0), np.where(fixed, 0.0, np.sign(p))
    p = np.clip(np.sign(y) * np.maximum(np.abs(y) - lam / c, 0.0), lo, hi)
    fixed = (p == lo) | (p == hi) | ((lam > 0) & (p == 0))
    return fixed & ~known, np.where(fixed, p, 0.0), np.where(fixed, 0.0, np.sign(p))


@pytest.mark.parametrize("l1", [False, True])
def test_prox_state_matches_numpy_bit_for_bit(l1):
    """The compiled next state (one pass) against the numpy rule on awkward values: exact zeros of
    both signs, points on the bounds, NaN and infinite gradients, known entries, shapes without L1;
    the values bytes equal (the state's hash reads them) and the change count against a state."""
    from core.solvers.bounded_spacetime import _prox_state, _state_key

    rng = np.random.default_rng(3)
    n, K = 60, 7
    lo = np.array([0.0, -0.2, -np.inf, 0.0, -1.0, 0.1, 0.0])
    hi = np.array([1.0, 1.0, np.inf, 0.5, 0.0, 0.9, 1.0])
    lam = np.where(rng.random(K) < 0.7, rng.uniform(0, 0.3, K), 0.0) if l1 else np.zeros(K)
    c = rng.uniform(0.5, 2.0, K)
    X = rng.choice([0.0, -0.0, 1.0, 0.5, -0.2, 0.1], (n, K)) + np.where(rng.random((n, K)) < 0.5, rng.normal(0, 0.3, (n, K)), 0.0)
    g = rng.choice([0.0, -0.0, 0.3, -0.3], (n, K)) * np.where(rng.random((n, K)) < 0.5, 1.0, rng.normal(0, 1, (n, K)))
    g[rng.random((n, K)) < 0.05] = np.nan
    g[rng.random((n, K)) < 0.03] = np.inf
    g[rng.random((n, K)) < 0.03] = -np.inf
    known = rng.random((n, K)) < 0.1
    for y, gg in ((X, None), (X, g)):
        with np.errstate(over="ignore"):  # nan_to_num's largest float over c < 1
            ref = _prox_state_reference(y if gg is None else y - np.nan_to_num(gg) / c, c, lo, hi, lam, known)
        old = _prox_state_reference(rng.normal(0, 0.5, (n, K)), c, lo, hi, lam, known)
        state, changes, key = _prox_state(y, c, lo, hi, lam, known, gg, old)
        for a, b in zip(state, ref):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        assert key == _state_key(*ref)
        spare = tuple(np.full_like(a, 7) for a in ref)  # written into, whatever it held
        again, _, _ = _prox_state(y, c, lo, hi, lam, known, gg, None, spare)
        assert all(a is b and a.tobytes() == r.tobytes() for a, b, r in zip(again, spare, ref))
        want = np.count_nonzero((ref[0] != old[0]) | (ref[1] != old[1]) | (ref[2] != old[2]))
        assert changes == want > 0


def test_state_key_equal_exactly_for_equal_states():
    """The active-set state's hash: equal for equal states (also from copies and other layouts),
    different after any one change: a fixed entry released, a value's sign or last bit, a sign."""
    from core.solvers.bounded_spacetime import _state_key

    rng = np.random.default_rng(5)
    n, K = 40, 9
    fixed = rng.random((n, K)) < 0.4
    values = np.where(fixed, rng.choice([0.0, 1.0, 0.3], (n, K)), 0.0)
    sign = np.where(fixed, 0.0, rng.choice([1.0, -1.0, 0.0, np.nan], (n, K)))
    key = _state_key(fixed, values, sign)
    assert key == _state_key(fixed.copy(), values.copy(), np.asfortranarray(sign))
    t, k = np.argwhere(fixed & (values == 1.0))[0]
    changed = []
    f2 = fixed.copy(); f2[t, k] = False; changed.append((f2, values, sign))
    v2 = values.copy(); v2[t, k] = -1.0; changed.append((fixed, v2, sign))
    v3 = values.copy(); v3[t, k] = np.nextafter(1.0, 2.0); changed.append((fixed, v3, sign))
    t, k = np.argwhere(~fixed & (sign == 1.0))[0]
    s2 = sign.copy(); s2[t, k] = -1.0; changed.append((fixed, values, s2))
    s3 = sign.copy(); s3[t, k] = np.nan; changed.append((fixed, values, s3))
    s4 = sign.copy(); s4[[0, 1]] = s4[[1, 0]]; changed.append((fixed, values, s4))  # same entries, other places
    keys = [_state_key(*c) for c in changed]
    assert key not in keys and len(set(keys)) == len(keys)


def test_threads_or_not_the_same_numbers(rocketbox_problem, monkeypatch):
    """The capacitance solve's two halves, the tridiagonal solves' two groups of directions and
    the weights' two halves of frames run in a second thread only when a core is free: a bounded
    solve of the sample (1,000 frames x 51 shapes, thousands of constraints: the capacitance
    systems are split) gives the same bits and the same active-set steps either way."""
    B, S, valid, names = rocketbox_problem
    S = S[:1000]
    out = []
    calls = []
    orig = spacetime._capacitance_solve

    def spy(tri, U, rows, *a, **kw):
        calls.append(len(rows) >= 4 * U.shape[1] and len(rows) >= 4 * spacetime.CAPACITANCE_BLOCK)
        return orig(tri, U, rows, *a, **kw)

    monkeypatch.setattr(spacetime, "_capacitance_solve", spy)
    for cores in (1, 2):
        monkeypatch.setattr(bounded_spacetime, "free_cores", lambda: cores)
        s = SpacetimeSolver(B, S, alpha=0.01, ridge=1e-3, lower=0.0, upper=1.0)
        out.append((s.solve(), dict(s.info_)))
    assert any(calls)  # split systems were solved
    (W1, i1), (W2, i2) = out
    assert np.array_equal(W1, W2) and i1 == i2


@pytest.mark.parametrize("case", ["within_frame", "known_frame_at_split", "underflow", "tiny_second_half"])
def test_capacitance_halves_at_awkward_splits(case):
    """Two halves against the dense capacitance matrix where the cut is awkward: inside a frame's
    entries (no transition across it), on a known frame (zero coupling: the halves are
    independent), across a gap where a direction's ratios underflow, and with a second half of a
    single entry (all padding but one)."""
    rng = np.random.default_rng(11)
    K, n = 6, 40
    mu = rng.uniform(0.2, 1, K)
    nu = 1.0 - mu
    if case == "underflow":
        mu[0], nu[0] = 1e-12, 1.0  # prior-dominated: ratios ~1e-12 per frame
    dL = np.full(n, 2.0)
    dL[[0, -1]] = 1.0
    eL = -np.ones(n - 1)
    rows = np.repeat(np.arange(n), K)
    ks = np.tile(np.arange(K), n)
    keep = rng.random(len(rows)) < (1.0 if case == "known_frame_at_split" else 0.8)  # whole frames: blocks of K
    rows, ks = rows[keep], ks[keep]
    p = len(rows)
    block = {"within_frame": 5, "known_frame_at_split": K, "underflow": 3, "tiny_second_half": 4}[case]
    if case == "tiny_second_half":
        rows, ks = rows[: 2 * block + 1], ks[: 2 * block + 1]  # 3 blocks, the last one entry: part 2
        p = len(rows)
    nb = -(-p // block)
    s = ((nb + 1) // 2) * block  # where _capacitance_solve cuts
    if case == "tiny_second_half":
        assert p - s == 1
    if case == "within_frame":
        assert rows[s - 1] == rows[s]
    if case == "known_frame_at_split":
        assert rows[s - 1] < rows[s]
        eL[rows[s - 1]] = 0.0  # theta = 0 between the halves' frames
    tri = _Tridiagonals(mu, nu, dL, eL, "test").factor()
    U = np.linalg.qr(rng.normal(size=(K, K)))[0] * rng.uniform(0.5, 2.0, K)
    G = [np.linalg.inv(np.diag(mu[j] * dL + nu[j]) + np.diag(mu[j] * eL, 1) + np.diag(mu[j] * eL, -1)) for j in range(K)]
    C = np.einsum("aj,bj,jab->ab", U[ks], U[ks], np.array([g[np.ix_(rows, rows)] for g in G]))
    c = rng.normal(size=p)
    ref = np.linalg.solve(C, c)
    one = _capacitance_solve(tri, U, rows, ks, c, block=block, presorted=True, split=False)
    for threads in (False, True):
        lam = _capacitance_solve(tri, U, rows, ks, c, block=block, presorted=True, split=True, threads=threads)
        assert np.abs(lam - ref).max() <= 1e-10 * np.abs(ref).max()
        assert np.abs(lam - one).max() <= 1e-12 * np.abs(one).max()
    assert np.array_equal(lam, _capacitance_solve(tri, U, rows, ks, c, block=block, presorted=True, split=True,
                                                  threads=False))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_worker_thread_survives_a_fork():
    """A forked child inherits the worker thread's executor but not the thread: it gets a new one
    (else its first hand-over would wait forever)."""
    assert bounded_spacetime._both(lambda: 1, lambda: 2, threads=True) == (1, 2)
    pid = os.fork()
    if pid == 0:  # pragma: no cover -- the child
        import signal

        signal.alarm(30)  # a hang kills the child (SIGALRM), failing the test instead of blocking it
        code = 0 if bounded_spacetime._both(lambda: 1, lambda: 2, threads=True) == (1, 2) else 1
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
