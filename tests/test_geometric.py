"""Ribera 2017 §5 retargeting (eq. 16): IRLS + polish against a general convex solver."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import minimize

from core.geometry import cotangent_laplacian
from core.model import Rig
from core.names import NameMap
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
