"""Ribera 2017 §5 retargeting (eq. 16): IRLS + polish against a general convex solver; the bounded
solve (lower <= w <= upper) against Clarabel and OSQP, by hand (K = 1) and on the bundled take."""

import warnings

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import minimize

from core.geometry import cotangent_laplacian
from core.model import Rig
from core.names import NameMap
from core.pipeline import Pipeline, StageCache
from datapaths import face_markers
from core.solvers.geometric import (GeometricSolver, effective_weights, geometric_gram,
                                    laplacian_deltas, solve_geometric)
from pathlib import Path

PERFORMANCES = Path(__file__).resolve().parents[1] / "data" / "performances"


# -- helpers --------------------------------------------------------------------------------

def reference_l1(solver, frame):
    """Eq. 16 for one frame by L-BFGS-B on the split w = u - v, u, v >= 0 (smooth, bounded)."""
    H, c, K = solver.H, solver.c, solver.K
    b = solver.rhs(frame[None])[0]
    scale = max(np.abs(b).max(), 1e-300)  # keep the objective O(1) for the optimiser's tolerances

    def fun(x):
        w = x[:K] - x[K:]
        gw = 2 * (H @ w - b)
        val = w @ H @ w - 2 * b @ w + 2 * c * x.sum()
        return val / scale, np.concatenate([gw + 2 * c, -gw + 2 * c]) / scale

    res = minimize(fun, np.zeros(2 * K), jac=True, method="L-BFGS-B", bounds=[(0, None)] * (2 * K),
                   options=dict(ftol=1e-16, gtol=1e-13, maxiter=50000, maxcor=50))
    return res.x[:K] - res.x[K:]


def kkt_violation(solver, frames, W):
    """max over frames of the ℓ1 optimality violation, relative to c = λ/2K."""
    b = solver.rhs(frames)
    g = b - W @ solver.H
    c = solver.c
    on = W != 0
    v_on = np.abs(np.where(on, g - c * np.sign(W), 0.0))
    v_off = np.maximum(np.where(on, 0.0, np.abs(g) - c), 0.0)
    return max(v_on.max(), v_off.max()) / c


def rom_weights(rig, path=PERFORMANCES / "livelinkface_rom.csv"):
    header = open(path).readline().strip().split(",")[2:54]
    W = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=range(2, 54))
    return W @ NameMap.automatic(header, rig.names).matrix(header, rig.names).T


def grid_rig(K=5, n=7, seed=0):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 0.1, n), np.linspace(0, 0.1, n))
    V = np.column_stack([x.ravel(), y.ravel(), 0.01 * np.sin(30 * x.ravel())])
    F = []
    for j in range(n - 1):
        for i in range(n - 1):
            a = j * n + i
            F += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    D = rng.normal(scale=0.003, size=(K, len(V), 3))
    return Rig(V, np.array(F), D, [f"s{k}" for k in range(K)], name="grid")


@pytest.fixture(scope="module")
def ict_case(ict):
    idx = face_markers(ict, 60)
    S = ict.deltas[:, idx]
    W = rom_weights(ict)[::100]
    rng = np.random.default_rng(3)
    A = (W @ S.reshape(len(S), -1)).reshape(len(W), -1, 3) + rng.normal(scale=3e-4, size=(len(W), len(idx), 3))
    return S, A, W, geometric_gram(ict)


# -- the prior's matrix ---------------------------------------------------------------------

def test_gram_matches_explicit_3n_laplacian():
    rig = grid_rig()
    N, K = rig.n_vertices, rig.n_shapes
    L = cotangent_laplacian(rig.neutral, rig.faces)
    L3 = sp.kron(L, sp.identity(3)).toarray()  # (3N, 3N) acting on x0 y0 z0 x1 ...
    dV = rig.deltas.reshape(K, -1).T  # (3N, K), the paper's ΔV
    Q_explicit = (L3 @ dV).T @ (L3 @ dV) / N
    np.testing.assert_allclose(geometric_gram(rig), Q_explicit, rtol=1e-12, atol=1e-14 * abs(Q_explicit).max())
    w = np.random.default_rng(1).normal(size=K)
    np.testing.assert_allclose(w @ geometric_gram(rig) @ w, np.sum((L3 @ dV @ w) ** 2) / N, rtol=1e-12)
    assert laplacian_deltas(rig).shape == (K, N, 3)


def test_effective_weights_units():
    mu, lam = effective_weights(0.3, 0.6, "cm", "geometric")
    assert mu == pytest.approx(0.3) and lam == pytest.approx(0.6e-4)
    mu, lam = effective_weights(0.3, 0.6, "cm", "pca")
    assert mu == pytest.approx(0.3e-4) and lam == pytest.approx(0.6e-4)
    assert effective_weights(0.3, 0.6, "m") == (0.3, 0.6)
    with pytest.raises(ValueError, match="units"):
        effective_weights(0.3, 0.6, "furlong")


# -- against a general convex solver --------------------------------------------------------

@pytest.mark.parametrize("prior", ["geometric", "pca", "l2", "none"])
def test_small_random_matches_lbfgsb(prior):
    rng = np.random.default_rng(11)
    K, M, T = 9, 12, 25
    P = rng.normal(scale=0.01, size=(K, M, 3))  # 1 cm shapes, in metres
    w_true = rng.normal(size=(T, K)) * (rng.random((T, K)) < 0.4)
    A = (w_true @ P.reshape(K, -1)).reshape(T, M, 3) + rng.normal(scale=5e-4, size=(T, M, 3))
    G = rng.normal(size=(K, K))
    kw = {}
    if prior == "geometric":
        kw["gram"] = 1e-5 * G @ G.T
    if prior == "pca":
        kw["gram"] = G @ G.T / K
        kw["linear"] = rng.normal(size=K)
    solver = GeometricSolver(P, prior, lam=3.0, **kw)  # lam large enough for real sparsity
    sol = solver.solve(A)
    assert sol.polished.all()
    assert kkt_violation(solver, A, sol.weights) < 1e-6
    zeros = (sol.weights == 0).mean()
    assert 0.05 < zeros < 0.95  # the ℓ1 term is active: some but not all weights are exactly 0
    for f in range(T):
        ref = reference_l1(solver, A[f])
        e_ours = solver.energy(A[f], sol.weights[f])[0]
        e_ref = solver.energy(A[f], ref)[0]
        assert e_ours <= e_ref + 1e-9 * abs(e_ref)  # never worse than the general solver
        np.testing.assert_allclose(sol.weights[f], ref, atol=1e-5 * max(1.0, np.abs(ref).max()))


def test_real_ict_rom_matches_lbfgsb_and_prior_lowers_bending(ict_case):
    S, A, W, Q = ict_case
    solver = GeometricSolver(S, "geometric", gram=Q)  # paper's μ = 0.3, λ = 0.6 (cm), data in metres
    sol = solver.solve(A)
    assert sol.polished.all()
    assert kkt_violation(solver, A, sol.weights) < 1e-6
    for f in range(0, len(A), 4):
        ref = reference_l1(solver, A[f])
        e_ref = solver.energy(A[f], ref)[0]
        assert solver.energy(A[f], sol.weights[f])[0] <= e_ref + 1e-9 * abs(e_ref)
        np.testing.assert_allclose(sol.weights[f], ref, atol=1e-4 * max(1.0, np.abs(ref).max()))
    # the prior can only lower what it penalises (minimisers of f + μg vs f alone)
    plain = GeometricSolver(S, "none", gram=Q).solve(A).weights
    bend = lambda w: np.einsum("ik,kl,il->i", w, Q, w)
    assert (bend(sol.weights) <= bend(plain) * (1 + 1e-9) + 1e-18).all()
    assert bend(sol.weights).sum() < bend(plain).sum()
    # the recovered weights explain the captured markers to about the noise level
    fit = (sol.weights @ S.reshape(len(S), -1)).reshape(A.shape)
    rms = np.sqrt(np.mean((fit - A) ** 2))
    assert rms < 3 * 3e-4


def test_noise_free_recovery_with_tiny_lambda(ict_case):
    S, _, W, Q = ict_case
    A = (W @ S.reshape(len(S), -1)).reshape(len(W), -1, 3)
    sol = GeometricSolver(S, "none", lam=1e-6, units="cm").solve(A)
    fit = (sol.weights @ S.reshape(len(S), -1)).reshape(A.shape)
    assert np.abs(fit - A).max() < 1e-4 * 0.475  # 1e-4 of the head size
    ls = GeometricSolver(S, "none", lam=0.0).solve(A).weights
    np.testing.assert_allclose(ls, np.linalg.lstsq(S.reshape(len(S), -1).T, A.reshape(len(A), -1).T, rcond=None)[0].T,
                               atol=1e-6)


def test_unit_invariance():
    """Data in metres with μ, λ quoted for cm == the same data in cm with raw μ, λ."""
    rng = np.random.default_rng(5)
    rig = grid_rig(K=6)
    K, M = 6, 10
    P = rng.normal(scale=0.01, size=(K, M, 3))
    A = rng.normal(scale=0.01, size=(15, M, 3))
    Q = geometric_gram(rig)
    m = GeometricSolver(P, "geometric", gram=Q, mu=0.3, lam=0.6, units="cm").solve(A).weights
    cm = GeometricSolver(100 * P, "geometric", gram=1e4 * Q, mu=0.3, lam=0.6, units="m").solve(100 * A).weights
    np.testing.assert_allclose(m, cm, atol=1e-9)
    assert (m == 0).any()
    G = rng.normal(size=(K, K))
    m = GeometricSolver(P, "pca", gram=G @ G.T, mu=0.3, lam=0.6, units="cm").solve(A).weights
    cm = GeometricSolver(100 * P, "pca", gram=G @ G.T, mu=0.3, lam=0.6, units="m").solve(100 * A).weights
    np.testing.assert_allclose(m, cm, atol=1e-9)


def test_batch_equals_frame_by_frame_and_input_untouched(ict_case):
    S, A, _, Q = ict_case
    A0 = A.copy()
    solver = GeometricSolver(S, "geometric", gram=Q)
    batch = solver.solve(A).weights
    single = np.stack([solve_geometric(S, A[f], gram=Q).weights[0] for f in range(0, len(A), 7)])
    np.testing.assert_allclose(batch[::7], single, atol=1e-12)
    np.testing.assert_array_equal(A, A0)


def test_validation():
    P = np.zeros((3, 4, 3))
    with pytest.raises(ValueError, match="blendshapes"):
        GeometricSolver(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="prior"):
        GeometricSolver(P, "pcaa")
    with pytest.raises(ValueError, match="rig="):
        GeometricSolver(P, "geometric")
    with pytest.raises(ValueError, match="gram"):
        GeometricSolver(P, "pca")
    with pytest.raises(ValueError, match=r"rig 'grid' has 5 shapes"):
        GeometricSolver(P, "geometric", rig=grid_rig(K=5))
    s = GeometricSolver(P, "l2")
    with pytest.raises(ValueError, match=r"frames: expected"):
        s.solve(np.zeros((2, 5, 3)))
    bad = np.zeros((2, 4, 3))
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"frames \[1\]"):
        s.solve(bad)


# -- within bounds: lower <= w <= upper ----------------------------------------------------------

def qp_reference(solver, frames, lower, upper, zero=None, method="clarabel"):
    """Eq. 16 within the bounds for every frame by a general QP solver, in epigraph form:
    min wᵀHw − 2bᵀw + 2c 1ᵀt  s.t.  −t ≤ w ≤ t, lower ≤ w ≤ upper (held weights: w = clip(0, lower, upper)).
    Independent of the solver's split of w across zero and of its unit-box variables."""
    H, c, K = solver.H, solver.c, solver.K
    b = solver.rhs(frames)
    T = len(b)
    zero = np.zeros((T, K), bool) if zero is None else np.broadcast_to(zero, (T, K))
    scale = 2 * np.linalg.norm(H, 2)  # objective O(1) for the solvers' absolute tolerances
    I, O = sp.identity(K, format="csc"), sp.csc_matrix((K, K))
    P = sp.block_diag([2 * H / scale, O], format="csc")
    G = sp.vstack([sp.hstack([I, -I]), sp.hstack([-I, -I]), sp.hstack([I, O]), sp.hstack([-I, O])], format="csc")
    h = np.concatenate([np.zeros(2 * K), upper, -lower])
    out = np.zeros((T, K))
    for t in range(T):
        q = np.concatenate([-2 * b[t], 2 * c * np.ones(K)]) / scale
        held = np.flatnonzero(zero[t])
        E = sp.csc_matrix((np.ones(len(held)), (np.arange(len(held)), held)), shape=(len(held), 2 * K))
        e = np.clip(0.0, lower, upper)[held]
        if method == "clarabel":
            import clarabel

            st = clarabel.DefaultSettings()
            st.verbose = False
            st.tol_gap_abs = st.tol_gap_rel = st.tol_feas = 1e-12
            st.max_iter = 500
            cones = ([clarabel.ZeroConeT(len(held))] if len(held) else []) + [clarabel.NonnegativeConeT(4 * K)]
            s = clarabel.DefaultSolver(P, q, sp.vstack([E, G], format="csc"), np.concatenate([e, h]), cones, st).solve()
            assert "Solved" in str(s.status), s.status
            out[t] = np.asarray(s.x)[:K]
        else:
            import osqp

            m = osqp.OSQP()
            A = sp.vstack([E, G], format="csc")
            m.setup(sp.triu(P, format="csc"), q, A, np.concatenate([e, np.full(4 * K, -np.inf)]), np.concatenate([e, h]),
                    verbose=False, eps_abs=1e-12, eps_rel=1e-12, max_iter=200000, polishing=True, polish_refine_iter=10)
            r = m.solve(raise_error=False)
            assert "solved" in str(r.info.status).lower(), r.info.status
            out[t] = r.x[:K]
    return out


def prox_residual(solver, frames, W, lower, upper, zero=None):
    """(T,) optimality residual of eq. 16 within the bounds, relative: ‖w − prox(w − g/L)‖·L with
    g = 2(Hw − b), L = 2‖H‖₂ and prox = clip(soft(·, 2c/L), lower, upper) (the proximal map of
    2c|w| + the box, exact in 1-D); zero at the optimum. Held weights are constraints, left out."""
    H, c = solver.H, solver.c
    b = solver.rhs(frames)
    L = 2 * np.linalg.norm(H, 2)
    y = W - 2 * (W @ H - b) / L
    p = np.clip(np.sign(y) * np.maximum(np.abs(y) - 2 * c / L, 0.0), lower, upper)
    r = np.abs(W - p) * L
    if zero is not None:
        r = np.where(zero, 0.0, r)
    scale = L * np.maximum(1.0, np.abs(W).max(1)) + 2 * np.abs(b).max(1) + 2 * c
    return r.max(1) / scale


def check_bounded(solver, frames, sol, lower, upper, zero=None, method="clarabel", rtol_e=1e-9, atol_w=1e-4):
    W = sol.weights
    assert (W >= lower).all() and (W <= upper).all()  # exactly, no tolerance
    if zero is not None:
        held = np.broadcast_to(zero, W.shape)
        assert (W[held] == np.broadcast_to(np.clip(0.0, lower, upper), W.shape)[held]).all()
    assert sol.polished.all() and sol.extras["kkt"] <= 1e-9
    assert prox_residual(solver, frames, W, lower, upper, zero).max() < 1e-9
    ref = qp_reference(solver, frames, lower, upper, zero, method)
    e, er = solver.energy(frames, W), solver.energy(frames, ref)
    assert (e <= er + rtol_e * np.abs(er)).all()  # never worse than the general solver
    assert (e >= er - 1e-7 * np.abs(er)).all()    # nor (much) better: the reference is near-optimal too
    np.testing.assert_allclose(W, ref, atol=atol_w)
    return ref


def random_case(K=9, M=12, T=40, seed=11):
    """Weight curves that leave [0, 1] on both sides, and some zero runs (for the ℓ1 kink)."""
    rng = np.random.default_rng(seed)
    P = rng.normal(scale=0.01, size=(K, M, 3))
    W = np.cumsum(rng.normal(scale=0.3, size=(T, K)), axis=0) * (rng.random((T, K)) < 0.6)
    A = (W @ P.reshape(K, -1)).reshape(T, M, 3) + rng.normal(scale=5e-4, size=(T, M, 3))
    G = rng.normal(size=(K, K))
    return P, A, 1e-5 * G @ G.T, rng


def test_one_shape_by_hand():
    """K = 1: E = h w² − 2bw + 2c|w| (+ const) within [lo, hi] is minimised by clip(soft(b, c)/h, lo, hi)."""
    rng = np.random.default_rng(2)
    p = rng.normal(scale=0.01, size=(1, 5, 3))
    frames = np.concatenate([s * p for s in np.linspace(-2.5, 2.5, 41)])  # b = h s: across ±c and beyond the bounds
    lam = 0.6 * GeometricSolver(p, "none").H[0, 0]  # c = λ/2K = 0.3 h
    for lo, hi in [(0.0, 1.0), (-0.5, 1.0), (-1.0, -0.2), (0.3, 0.8), (-0.7, 0.0)]:
        s = GeometricSolver(p, "none", lam=lam, units="m", lower=lo, upper=hi)
        h, b, c = s.H[0, 0], s.rhs(frames)[:, 0], s.c
        expected = np.clip(np.sign(b) * np.maximum(np.abs(b) - c, 0.0) / h, lo, hi)
        W = s.solve(frames).weights[:, 0]
        np.testing.assert_allclose(W, expected, rtol=1e-12, atol=1e-14)
        assert ((W == lo) | (W == hi)).any() and (W[expected == 0] == 0).all()


@pytest.mark.parametrize("bounds", ["unit", "kink", "negative", "mixed"])
def test_bounded_small_random_matches_clarabel(bounds):
    P, A, Q, rng = random_case()
    K = len(P)
    lo, hi = {"unit": (np.zeros(K), np.ones(K)),
              "kink": (np.full(K, -0.5), np.full(K, 1.0)),
              "negative": (np.full(K, -1.2), np.full(K, -0.1)),
              "mixed": (np.array([0, -0.5, -1, 0.2, 0.4, -0.3, 0, -2, 0.1]),
                        np.array([1, 0.5, -0.2, 0.9, 0.4, 0.0, 0.7, 2, 1.5]))}[bounds]  # shape 4 fixed at 0.4
    s = GeometricSolver(P, "geometric", gram=Q, lam=3.0, lower=lo, upper=hi)
    sol = s.solve(A)
    check_bounded(s, A, sol, lo, hi)
    W = sol.weights
    assert ((W == lo) | (W == hi)).any()  # the bounds are active ...
    if bounds != "negative":
        assert (W == 0).any()  # ... and so is the ℓ1 term
    if bounds == "mixed":
        assert (W[:, 4] == 0.4).all()
    # never worse than the unbounded solution clipped into the bounds
    clipped = np.clip(GeometricSolver(P, "geometric", gram=Q, lam=3.0).solve(A).weights, lo, hi)
    assert (sol.energy <= s.energy(A, clipped) * (1 + 1e-12)).all()


@pytest.mark.parametrize("prior", ["pca", "l2", "none"])
def test_bounded_other_priors_and_held_weights_match_clarabel(prior):
    P, A, Q, rng = random_case(seed=4)
    K, T = len(P), len(A)
    kw = {"gram": Q * 1e5 / K, "linear": rng.normal(size=K)} if prior == "pca" else {}
    lo, hi = np.full(K, -0.4), np.full(K, 1.0)
    lo[2] = 0.2  # a held weight with lower > 0 sits at its lower bound
    zero = rng.random((T, K)) < 0.2
    s = GeometricSolver(P, prior, lam=3.0, lower=lo, upper=hi, quadratic=np.eye(K) * 0.01, **kw)
    sol = s.solve(A, zero=zero)
    check_bounded(s, A, sol, lo, hi, zero)
    assert (sol.weights[zero[:, 2], 2] == 0.2).all()
    z1 = np.zeros(K, bool)
    z1[[0, 5]] = True
    sol1 = s.solve(A, zero=z1)
    check_bounded(s, A, sol1, lo, hi, z1)


def test_bounded_matches_osqp():
    pytest.importorskip("osqp")
    P, A, Q, _ = random_case(seed=7, T=15)
    K = len(P)
    lo, hi = np.full(K, -0.5), np.ones(K)
    s = GeometricSolver(P, "geometric", gram=Q, lam=3.0, lower=lo, upper=hi)
    check_bounded(s, A, s.solve(A), lo, hi, method="osqp", rtol_e=1e-8, atol_w=1e-3)


def test_bounded_tiny_lambda_and_no_lambda():
    """The split across zero stays exact when the ℓ1 weight is tiny; λ = 0 is the plain box QP."""
    P, A, Q, _ = random_case(seed=9, T=30)
    K = len(P)
    lo, hi = np.full(K, -0.5), np.ones(K)
    for lam in (1e-9, 0.0):
        s = GeometricSolver(P, "geometric", gram=Q, lam=lam, lower=lo, upper=hi)
        check_bounded(s, A, s.solve(A), lo, hi)


def test_bounded_rank_deficient_gets_the_relative_ridge():
    """More shapes than marker coordinates and no prior: H is singular, the bounded solve adds
    AUTO_RIDGE λ_max(H) (as range_pf) and is exact for that; eq. 16's own energy is then within
    that ridge's size of the general solver's."""
    P, A, _, _ = random_case(K=12, M=3, T=30, seed=5)
    K = len(P)
    lo, hi = np.full(K, -0.5), np.ones(K)
    s = GeometricSolver(P, "none", lam=0.5, lower=lo, upper=hi)
    assert s.ridge_ == pytest.approx(1e-9 * np.linalg.eigvalsh(s.H)[-1])
    sol = s.solve(A)
    assert (sol.weights >= lo).all() and (sol.weights <= hi).all() and sol.polished.all() and sol.extras["kkt"] < 1e-12
    e, er = sol.energy, s.energy(A, qp_reference(s, A, lo, hi))
    assert (np.abs(e - er) <= 1e-8 * np.abs(er)).all()


def test_bounded_wide_bounds_are_the_unbounded_solution(ict_case):
    S, A, _, Q = ict_case
    K = len(S)
    free = GeometricSolver(S, "geometric", gram=Q).solve(A).weights
    assert np.abs(free).max() < 5
    wide = GeometricSolver(S, "geometric", gram=Q, lower=np.full(K, -5.0), upper=np.full(K, 5.0)).solve(A).weights
    np.testing.assert_allclose(wide, free, atol=1e-8)
    np.testing.assert_array_equal(wide == 0, free == 0)  # the same support


@pytest.mark.parametrize("bounds", [(0.0, 1.0), (-0.3, 1.0)])
def test_bounded_real_ict_rom_matches_clarabel(ict_case, bounds):
    S, A, W, Q = ict_case
    K = len(S)
    lo, hi = np.full(K, bounds[0]), np.full(K, bounds[1])
    s = GeometricSolver(S, "geometric", gram=Q, lower=lo, upper=hi)  # the paper's μ, λ
    sol = s.solve(A)
    # frame by frame (each from a cold start) gives what the warm-started sequence gives
    single = np.stack([s.solve(A[f]).weights[0] for f in range(0, len(A), 5)])
    np.testing.assert_allclose(sol.weights[::5], single, atol=1e-10)
    check_bounded(s, A[::3], SimpleSolution(sol, slice(None, None, 3)), lo, hi)


class SimpleSolution:
    """A frame subset of a Solution (weights, energy, polished, extras)."""

    def __init__(self, sol, rows):
        self.weights, self.energy, self.polished, self.extras = sol.weights[rows], sol.energy[rows], sol.polished[rows], sol.extras


def test_bounded_validation():
    P = np.random.default_rng(0).normal(size=(3, 4, 3))
    with pytest.raises(ValueError, match="both lower and upper"):
        GeometricSolver(P, "l2", lower=0.0)
    with pytest.raises(ValueError, match="lower must be <= upper"):
        GeometricSolver(P, "l2", lower=[0, 1, 0], upper=[1, 0.5, 1])
    with pytest.raises(ValueError, match=r"\(3,\) per-shape"):
        GeometricSolver(P, "l2", lower=np.zeros(4), upper=np.ones(4))
    with pytest.raises(ValueError, match="finite"):
        GeometricSolver(P, "l2", lower=-np.inf, upper=1.0)
    assert GeometricSolver(P, "l2").columns_ is None


def test_pipeline_geometric_stays_in_per_shape_bounds():
    """S07 -> Rocketbox's ARKit shapes: the geometric method solves within the per-shape bounds of
    the controls exactly (the first 300 frames are calm: a right blink allowed down to -0.02, across
    the ℓ1 kink, and a left blink capped at 0.05 both bind), and lowest/highest are part of its
    cache key."""
    files = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"),
                 source_rig=str(PERFORMANCES.parent / "rigs" / "ict_facekit.glb"),
                 target_rig=str(PERFORMANCES.parent / "rigs" / "rocketbox_female_adult_02.glb"))
    controls = {"shapes": {"AK_10_EyeBlinkRight": {"lower": -0.02}, "AK_09_EyeBlinkLeft": {"upper": 0.05}}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a shape no marker sees
        pipe = Pipeline(cache=StageCache(), **files, method="geometric", target_shapes="arkit", last_frame=299,
                        controls=controls)
        r = pipe.results(["calibrate", "personalize", "shapes", "solve"])
    lo, hi = r["solve"]["controls"].bounds()
    names = list(r["shapes"]["rig"].names)
    right, left = names.index("AK_10_EyeBlinkRight"), names.index("AK_09_EyeBlinkLeft")
    assert lo[right] == -0.02 and hi[left] == 0.05
    W = r["solve"]["weights"]
    assert (W >= lo).all() and (W <= hi).all() and (W == 0).any()
    assert (W[:, right] == -0.02).any() and (W[:, left] == 0.05).any()
    s = GeometricSolver(r["personalize"]["deltas"], "geometric", rig=r["shapes"]["rig"], lower=lo, upper=hi)
    A = r["calibrate"]["source"].deltas
    sol = s.solve(A)
    np.testing.assert_array_equal(sol.weights, W)
    check_bounded(s, A[::10], SimpleSolution(sol, slice(None, None, 10)), lo, hi)
    # the unbounded paper solution leaves the bounds on this take
    free = GeometricSolver(r["personalize"]["deltas"], "geometric", rig=r["shapes"]["rig"]).solve(A).weights
    assert ((free < lo) | (free > hi)).any()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pipe.configure(upper=0.06)
        W2 = pipe.results(["solve"])["solve"]["weights"]
    assert W.max() > 0.06 and W2.max() == 0.06
