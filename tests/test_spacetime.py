"""Spacetime expression cloning (Seol et al. 2012): fast solver vs the literal Kronecker system.

Every solve is compared with :func:`spacetime_reference` (``scipy.sparse.kron`` + ``spsolve``)
on small random problems and on real data (ICT FaceKit markers driven by a real Live Link Face
take), and checked by properties: constraints hold exactly, the gradient vanishes on the free
weights, perturbations only raise the energy, consistent data is reproduced exactly.
"""

import json

import numpy as np
import pytest
import scipy.optimize

from core.metrics import marker_error_mm, velocity_error, weight_range
from core.names import NameMap
from core.prior import PCAPrior
from core.solvers.baselines import box_lsq, no_const, prior_pf, range_pf
from core.solvers.reference import spacetime_reference
from core.solvers.spacetime import PoseEdit, SpacetimeSolver, known_matrix, solve_spacetime
from datapaths import LAYOUTS, PERFORMANCES

TOL = 1e-8  # relative agreement with the reference, max |W - W_ref| / max |W_ref|


@pytest.fixture(scope="module", autouse=True)
def single_threaded_blas():
    """One OpenBLAS thread while this module runs, restored after.

    On the shared 2-core test machine OpenBLAS threads under oversubscription made the many
    small K x K products of the block path ~50x slower (4.5 s instead of 0.09 s).
    """
    import ctypes
    import glob
    import os

    import scipy

    restore = []
    for pkg in (np, scipy):
        for so in glob.glob(os.path.join(os.path.dirname(pkg.__file__), "..", pkg.__name__ + ".libs", "*openblas*.so*")):
            lib = ctypes.CDLL(so)
            for get, put in (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                             ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads")):
                if hasattr(lib, get) and hasattr(lib, put):
                    restore.append((getattr(lib, put), getattr(lib, get)()))
                    getattr(lib, put)(1)
                    break
    yield
    for put, n in restore:
        put(n)


def rel(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


def gradient(s: SpacetimeSolver, W):
    """dE/dW written out from the energy's definition (independent of both solvers)."""
    Bm = s._B
    X = W @ Bm.T - s._S
    v3 = np.repeat(s.valid_, 3, axis=1)
    Re = (X[1:] - X[:-1]) * (v3[:-1] & v3[1:])
    g = np.zeros_like(W)
    g[1:] += Re @ Bm
    g[:-1] -= Re @ Bm
    g += s.alpha_ * (W @ s.P_ - s.q_) + (s._bt[:, None] * s._gamma3 * v3 * X) @ Bm + s.ridge_ * W
    return 2 * g


def check_optimal(s: SpacetimeSolver, W, known):
    kn = known_matrix(known, s.T, s.K, "neutral") if not isinstance(known, np.ndarray) else known
    k = np.isfinite(kn)
    assert np.array_equal(W[k], kn[k])  # constraints hold exactly
    g = gradient(s, W)
    scale = np.linalg.norm(s._A, 2) * max(np.abs(W).max(), 1.0) + s.alpha_ * np.abs(s.P_).max()
    assert np.abs(g[~k]).max() <= 1e-10 * scale


# -- data -------------------------------------------------------------------------------------
def random_problem(T=40, M=8, K=6, seed=0):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(K, M, 3)) * 0.01
    W = np.cumsum(rng.normal(size=(T, K)) * 0.1, axis=0)
    S = np.einsum("tk,kmc->tmc", W, B) * 1.2 + rng.normal(size=(T, M, 3)) * 1e-3
    return B, S, rng


def ict_markers(ict):
    """Marker vertices: the bundled layout when present, else 54 well-spread moving vertices."""
    path = LAYOUTS / "ict_facekit.json"
    if path.exists():
        return np.array([m["vertex"] for m in json.loads(path.read_text())["markers"].values()])
    moving = np.flatnonzero(np.linalg.norm(ict.deltas, axis=2).max(0) > 0.05 * np.linalg.norm(ict.deltas, axis=2).max())
    P = ict.neutral[moving]
    pick = [int(np.argmin(np.linalg.norm(P - P.mean(0), axis=1)))]
    d = np.linalg.norm(P - P[pick[0]], axis=1)
    for _ in range(53):
        pick.append(int(d.argmax()))
        d = np.minimum(d, np.linalg.norm(P - P[pick[-1]], axis=1))
    return moving[pick]


def livelink_curves(rig, path=PERFORMANCES / "livelinkface_take_s07.csv"):
    """Real ARKit curves (columns 2..53) mapped onto ``rig``'s shapes by canonical names."""
    header = path.read_text().split("\n", 1)[0].split(",")
    src = header[2:54]
    C = np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(2, 54))
    return C @ NameMap.automatic(src, rig.names).matrix(src, rig.names).T


@pytest.fixture(scope="module")
def real(ict):
    """ICT marker blendshapes B (K, M, 3) and a source S (T, M, 3): the real take on ICT,
    scaled 1.15x with 0.3 mm noise so it is not exactly in the rig's span."""
    B = ict.deltas[:, ict_markers(ict)]
    Wt = livelink_curves(ict)[300:420]
    rng = np.random.default_rng(7)
    S = 1.15 * np.einsum("tk,kmc->tmc", Wt, B) + rng.normal(size=(len(Wt),) + B.shape[1:]) * 3e-4
    return B, S, Wt


# -- solver vs reference ------------------------------------------------------------------------
def _case(name, T, K, M, rng):
    kw = {}
    if "alpha" in name:
        kw["alpha"] = 30.0
    else:
        kw["alpha"] = 0.0
    if "beta" in name:
        kw["beta"] = 0.2
    if "fw" in name:
        kw["frame_weights"] = rng.uniform(0, 3, T)
    if "mw" in name:
        kw["marker_weights"] = rng.uniform(0, 3, M)
    if "nobnd" in name:
        kw["boundary"] = "none"
    if "alpha" in name and ("nobnd" in name or "mask" in name):
        # a PCA of K shapes leaves one weight direction free, which would leave a frame with
        # no valid marker (or a sequence without boundary) undetermined: use an example prior
        B = random_problem(T, M, K, seed=CASES.index(name))[0]
        ex = np.einsum("tk,kmc->tmc", rng.uniform(0, 1, (60, K)), B) + rng.normal(size=(60, M, 3)) * 1e-3
        kw["prior"] = PCAPrior().fit(ex, basis=B)
    if "known" in name:
        kw["known"] = {
            T // 3: rng.normal(size=K),
            T // 2: np.where(rng.random(K) < 0.5, rng.normal(size=K), np.nan),
            T // 2 + 1: np.r_[0.7, [np.nan] * (K - 1)],
            2 * T // 3: np.r_[[np.nan] * (K - 1), -0.3],
        }
    if "mask" in name:
        v = rng.random((T, M)) > 0.15
        v[T // 4] = False  # a whole frame lost
        kw["valid"] = v
    return kw


CASES = [
    "plain", "alpha", "beta", "alpha_beta", "alpha_beta_fw", "alpha_beta_mw", "alpha_beta_fw_mw",
    "alpha_known", "known", "alpha_beta_mw_known", "alpha_nobnd", "beta_nobnd_known",
    "alpha_beta_mask", "alpha_known_mask", "alpha_beta_fw_mask",
]


def _reference(B, S, s, kw):
    kw = dict(kw)
    return spacetime_reference(B, S, kw.pop("alpha", 0.01), kw.pop("beta", 0.0), kw.pop("prior", None),
                               kw.pop("known", None), ridge=s.ridge_, **kw)


@pytest.mark.parametrize("name", CASES)
def test_random_matches_reference(name):
    B, S, rng = random_problem(seed=CASES.index(name))
    kw = _case(name, len(S), B.shape[0], B.shape[1], rng)
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    expect_fast = "mask" not in name and not ("fw" in name and "mw" in name)
    assert s.method_.startswith("fast") == expect_fast
    if "known" in name and expect_fast:
        assert s.method_ == "fast+capacitance"
    R = _reference(B, S, s, kw)
    assert rel(W, R) <= TOL
    assert rel(s.solve(method="block"), R) <= TOL
    check_optimal(s, W, known_matrix(kw.get("known"), len(S), B.shape[0], kw.get("boundary", "neutral")))


@pytest.mark.parametrize("name", ["alpha", "alpha_beta_mw_known", "alpha_beta_fw", "alpha_known_mask"])
def test_real_matches_reference(real, name):
    B, S, _ = real
    rng = np.random.default_rng(11)
    kw = _case(name, len(S), B.shape[0], B.shape[1], rng)
    kw["alpha"] = 0.01 if "alpha" in name else 0.0  # the paper's value, cm scale
    if "mask" in name:
        S = S.copy()
        S[~kw.pop("valid")] = np.nan  # missing samples as NaN: the default mask
    s = SpacetimeSolver(B, S, **kw)
    W = s.solve()
    R = _reference(B, S, s, kw)
    assert rel(W, R) <= TOL
    check_optimal(s, W, known_matrix(kw.get("known"), len(S), B.shape[0]))


def test_prior_forms_agree(real):
    """A PCAPrior, its (P, q) quadratic and the default (None) give the same solution."""
    B, S, _ = real
    prior = PCAPrior().fit(B)
    W1 = solve_spacetime(B, S, alpha=0.01, prior=prior)
    W2 = solve_spacetime(B, S, alpha=0.01, prior=(prior.P_, prior.q_))
    W3 = solve_spacetime(B, S, alpha=0.01)
    assert rel(W1, W3) <= 1e-10 and rel(W2, W3) <= 1e-10
    # an example-animation prior (rows of the real take) is a different, valid prior
    ex = np.einsum("tk,kmc->tmc", random_examples(B), B)
    p2 = PCAPrior().fit(ex, basis=B)
    s = SpacetimeSolver(B, S, alpha=0.01, prior=p2)
    W4 = s.solve()
    assert rel(W4, spacetime_reference(B, S, 0.01, 0.0, p2, None)) <= TOL
    assert rel(W4, W3) > 1e-6


def random_examples(B):
    rng = np.random.default_rng(0)
    return rng.uniform(0, 1, (200, B.shape[0])) ** 3


def test_rank_deficient_basis_uses_ridge():
    """K > 3M: B^T B is singular; the auto ridge makes the problem unique and the reference agrees."""
    rng = np.random.default_rng(5)
    B = rng.normal(size=(20, 4, 3)) * 0.01
    B[3] = 0.0  # a shape that moves no marker
    S = rng.normal(size=(30, 4, 3)) * 0.01
    s = SpacetimeSolver(B, S, alpha=0.01)
    assert s.ridge_ > 0
    W = s.solve()
    R = spacetime_reference(B, S, 0.01, 0.0, None, None, ridge=s.ridge_)
    # what the markers see agrees to TOL; the weights only to the conditioning the tiny ridge
    # (curvature 1e-9 sigma_max^2 along null(B)) allows
    Bm = B.reshape(len(B), -1).T
    assert rel(W @ Bm.T, R @ Bm.T) <= TOL
    assert rel(W, R) <= 1e-5
    check_optimal(s, W, known_matrix(None, len(S), len(B)))
    assert np.abs(W[:, 3]).max() <= 1e-8 * np.abs(W).max()  # the unseen shape stays at rest
    with pytest.raises(ValueError, match="singular"):
        SpacetimeSolver(B, S, alpha=0.01, ridge=0.0)


@pytest.mark.parametrize("method", ["auto", "block"])
def test_undetermined_problems_are_refused(method):
    B, S, _ = random_problem()
    with pytest.raises(ValueError, match="singular"):
        solve_spacetime(B, S, alpha=0.0, beta=0.0, boundary="none", method=method)
    # the default PCA prior of K shapes has K - 1 components: one direction stays free
    with pytest.raises(ValueError, match="singular"):
        solve_spacetime(B, S, alpha=1.0, boundary="none", method=method)
    # ... unless a partial constraint pins it, or a position term does
    K = B.shape[0]
    W = solve_spacetime(B, S, alpha=1.0, boundary="none", known={7: np.r_[0.3, [np.nan] * (K - 1)]}, method=method)
    assert W[7, 0] == 0.3
    solve_spacetime(B, S, alpha=0.0, beta=0.1, boundary="none", method=method)
    # a frame with every marker missing is pinned only by the prior
    S2 = S.copy()
    S2[10] = np.nan
    with pytest.raises(ValueError, match="singular at frame 10"):
        solve_spacetime(B, S2, alpha=1.0, beta=0.1)


@pytest.mark.parametrize("T", [1, 2, 3])
def test_short_sequences(T):
    B, S, _ = random_problem(T=T, seed=T)
    K = B.shape[0]
    part = {0: np.r_[0.5, [np.nan] * (K - 1)]}
    for kw in ({"beta": 0.5, "boundary": "none"}, {"beta": 0.5, "boundary": "none", "known": part}, {"alpha": 1.0}):
        s = SpacetimeSolver(B, S, **kw)
        R = _reference(B, S, s, kw)
        assert rel(s.solve(), R) <= TOL and rel(s.solve(method="block"), R) <= TOL


# -- properties -------------------------------------------------------------------------------
def test_consistent_data_reproduces_weights(real):
    """alpha = beta = 0, S = B W, boundaries from W: movement matching returns W (Seol §4)."""
    B, _, Wt = real
    S = np.einsum("tk,kmc->tmc", Wt, B)
    known = {0: Wt[0], len(Wt) - 1: Wt[-1]}
    W = solve_spacetime(B, S, alpha=0.0, known=known)
    assert rel(W, Wt) <= 1e-8
    # per-frame No Const agrees with it too (Seol §4: identical without constraints)
    assert rel(no_const(B, S), Wt) <= 1e-8


def test_energy_is_minimal(real):
    B, S, _ = real
    rng = np.random.default_rng(2)
    known = {40: np.where(rng.random(B.shape[0]) < 0.3, 0.5, np.nan)}
    s = SpacetimeSolver(B, S, alpha=0.01, beta=0.05, known=known)
    W = s.solve()
    E0 = s.energy(W).total
    free = np.isnan(known_matrix(known, s.T, s.K))
    for scale in (1e-1, 1e-3, 1e-6):
        for _ in range(3):
            dW = rng.normal(size=W.shape) * scale * free
            assert s.energy(W + dW).total > E0
    # the public gradient agrees with the one written out here, and is ~0 at the solution
    np.testing.assert_allclose(s.gradient(W + 0.01), gradient(s, W + 0.01), rtol=1e-9, atol=1e-14)
    assert s.kkt_residual(W) <= 1e-12 and s.kkt_residual(W + 0.01) > 1e-6
    # the energy terms add up and the match term is the Fig. 11 velocity error (mm^2)
    e = s.energy(W)
    assert e.total == pytest.approx(e.match + e.prior + e.position + e.ridge)
    assert velocity_error(B, W, S).total == pytest.approx(e.match * 1e6, rel=1e-10)


def test_weight_space_gradient_matches_marker_space():
    """The solver evaluates the data terms from S B and B^T B (weight space) where a frame has
    every marker and in marker space where one is missing: against the gradient written out in
    marker space, with holes at the ends, in the middle and in neighbouring frames, per-marker
    weights and beta > 0, over the whole take and over a range."""
    B, S, rng = random_problem(T=30, M=8, K=6, seed=11)
    valid = np.ones((30, 8), bool)
    valid[0, 2] = valid[7, :3] = valid[8, 5] = valid[15] = valid[29, 0] = False
    s = SpacetimeSolver(B, S, alpha=0.05, beta=0.3, valid=valid, marker_weights=rng.uniform(0.2, 2.0, 8))
    W = rng.normal(size=(30, 6))
    np.testing.assert_allclose(s.gradient(W), gradient(s, W), rtol=1e-10, atol=1e-14)
    # a range: its own terms only (the differences inside it)
    lo, hi = 6, 16
    s1 = SpacetimeSolver(B[:, :, :], S[lo:hi + 1], alpha=0.05, beta=0.3, valid=valid[lo:hi + 1],
                         marker_weights=s._gamma3[::3])
    np.testing.assert_allclose(s._gradient_range(W[lo:hi + 1], lo), gradient(s1, W[lo:hi + 1]), rtol=1e-10, atol=1e-14)


def test_velocity_matching_vs_per_frame(real):
    """Seol §4: with No Const's values as boundary conditions and no prior, movement matching
    returns No Const itself. With constraints (Fig. 11) the spacetime solution keeps a smaller
    velocity error than per-frame matching with the prior."""
    B, S, _ = real
    W0 = no_const(B, S)
    Ws = solve_spacetime(B, S, alpha=0.0, known={0: W0[0], len(S) - 1: W0[-1]})
    assert rel(Ws, W0) <= 1e-8
    Wp = prior_pf(B, S, alpha=0.5)
    Wst = solve_spacetime(B, S, alpha=0.01)
    assert velocity_error(B, Wst, S).total < velocity_error(B, Wp, S).total


def test_alpha_units():
    """alpha for cm data == alpha_for_units(alpha, 'cm') for the same data in metres."""
    B, S, _ = random_problem()
    Wm = solve_spacetime(B, S, alpha=0.3, alpha_units="cm")
    Wcm = solve_spacetime(B * 100, S * 100, alpha=0.3, alpha_units="m")
    assert rel(Wm, Wcm) <= 1e-9


def test_inputs_not_modified():
    B, S, rng = random_problem()
    S[3, 2] = np.nan
    B0, S0 = B.copy(), S.copy()
    known = {5: rng.normal(size=B.shape[0])}
    k0 = known[5].copy()
    s = SpacetimeSolver(B, S, alpha=1.0, known=known)
    W = s.solve()
    W0 = W.copy()
    s.edit(W, 10, np.ones(B.shape[0]), window=(7, 14))
    np.testing.assert_array_equal(B, B0)
    np.testing.assert_array_equal(S, S0)
    np.testing.assert_array_equal(known[5], k0)
    np.testing.assert_array_equal(W, W0)


def test_validation_errors():
    B, S, _ = random_problem()
    with pytest.raises(ValueError, match=r"S: expected \(T, 8, 3\)"):
        SpacetimeSolver(B, S[:, :5])
    with pytest.raises(ValueError, match="marker_weights"):
        SpacetimeSolver(B, S, marker_weights=np.ones(3))
    with pytest.raises(ValueError, match="frame_weights"):
        SpacetimeSolver(B, S, frame_weights=-np.ones(len(S)))
    with pytest.raises(ValueError, match="beta"):
        SpacetimeSolver(B, S, beta=-1)
    with pytest.raises(ValueError, match="known\\[3\\]"):
        SpacetimeSolver(B, S, known={3: np.ones(2)})
    with pytest.raises(ValueError, match="outside"):
        SpacetimeSolver(B, S, known={400: np.ones(6)})
    with pytest.raises(ValueError, match="boundary"):
        SpacetimeSolver(B, S, boundary="first")
    v = np.ones(S.shape[:2], bool)
    S2 = S.copy()
    S2[4, 1, 0] = np.nan
    with pytest.raises(ValueError, match="frame 4, marker 1"):
        SpacetimeSolver(B, S2, valid=v)
    with pytest.raises(ValueError, match="method='fast'"):
        SpacetimeSolver(B, S2, method="fast")
    with pytest.raises(ValueError, match="prior"):
        SpacetimeSolver(B, S, prior="pca")


# -- editing (§6) -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def edit_setup(real):
    B, S, _ = real
    s = SpacetimeSolver(B, S, alpha=0.01, beta=0.02, names=[f"s{k}" for k in range(B.shape[0])])
    return B, S, s, s.solve()


def test_edit_window_matches_reference(edit_setup):
    B, S, s, W = edit_setup
    pose = np.linspace(0, 1, B.shape[0])
    a, b, f = 50, 61, 55
    W2 = s.edit(W, f, pose, window=(a, b))
    np.testing.assert_array_equal(W2[:a + 1], W[:a + 1])  # the window's ends keep the solution
    np.testing.assert_array_equal(W2[b:], W[b:])
    np.testing.assert_array_equal(W2[f], pose)
    R = spacetime_reference(B, S[a:b + 1], 0.01, 0.02, None, {0: W[a], f - a: pose, b - a: W[b]}, boundary="none")
    assert rel(W2[a:b + 1], R) <= TOL
    assert np.abs(W2[a + 1:b] - W[a + 1:b]).max() > 1e-3  # the edit did propagate


def test_partial_edit_matches_reference(edit_setup):
    B, S, s, W = edit_setup
    shapes = ["s3", "s10", "s20"]
    W2 = s.edit(W, 70, [0.9, 0.1, 0.5], window=(60, 90), shapes=shapes)
    assert np.array_equal(W2[70, [3, 10, 20]], [0.9, 0.1, 0.5])
    row = np.full(B.shape[0], np.nan)
    row[[3, 10, 20]] = [0.9, 0.1, 0.5]
    R = spacetime_reference(B, S[60:91], 0.01, 0.02, None, {0: W[60], 10: row, 30: W[90]}, boundary="none")
    assert rel(W2[60:91], R) <= TOL
    # the same edit through the block path
    assert rel(s.edit(W, 70, [0.9, 0.1, 0.5], window=(60, 90), shapes=[3, 10, 20], method="block")[60:91], R) <= TOL


def test_edit_without_window_is_a_full_resolve(edit_setup):
    B, S, s, W = edit_setup
    row = np.full(B.shape[0], np.nan)
    row[5] = 1.0
    W2 = s.edit(W, 30, [1.0], shapes=[5])
    R = spacetime_reference(B, S, 0.01, 0.02, None, {30: row})
    assert rel(W2, R) <= TOL
    assert rel(W2, solve_spacetime(B, S, alpha=0.01, beta=0.02, known={30: row})) <= 1e-12


def test_several_edits_merge(edit_setup):
    B, S, s, W = edit_setup
    K = B.shape[0]
    p1, p2, p3 = np.full(K, 0.2), np.full(K, 0.4), np.full(K, 0.1)
    edits = [PoseEdit(20, p1, window=(15, 30)), PoseEdit(28, p2, window=(25, 40)), PoseEdit(90, p3, window=(85, 95))]
    W2 = s.edit(W, edits=edits)
    # windows (15, 30) and (25, 40) merge into 15..40 with ends kept; 85..95 is separate
    R1 = spacetime_reference(B, S[15:41], 0.01, 0.02, None, {0: W[15], 5: p1, 13: p2, 25: W[40]}, boundary="none")
    R2 = spacetime_reference(B, S[85:96], 0.01, 0.02, None, {0: W[85], 5: p3, 10: W[95]}, boundary="none")
    assert rel(W2[15:41], R1) <= TOL and rel(W2[85:96], R2) <= TOL
    np.testing.assert_array_equal(W2[41:85], W[41:85])
    np.testing.assert_array_equal(W2[:15], W[:15])


def test_edit_errors(edit_setup):
    B, S, s, W = edit_setup
    K = B.shape[0]
    with pytest.raises(ValueError, match="outside its window"):
        s.edit(W, 10, np.zeros(K), window=(20, 30))
    with pytest.raises(ValueError, match="window"):
        s.edit(W, 25, np.zeros(K), window=(30, 20))
    with pytest.raises(ValueError, match="did you mean"):
        s.edit(W, 25, [1.0], shapes=["s100x"])
    with pytest.raises(ValueError, match="weights"):
        s.edit(W, 25, np.zeros(3), shapes=[1, 2])
    with pytest.raises(ValueError, match="W: expected"):
        s.edit(W[:5], 2, np.zeros(K))


# -- baselines --------------------------------------------------------------------------------
def test_no_const_and_prior_pf_match_dense(real):
    B, S, _ = real
    S = S.copy()
    rng = np.random.default_rng(4)
    lost = rng.random(S.shape[:2]) < 0.05
    S[lost] = np.nan
    Bm = B.reshape(len(B), -1).T
    prior = PCAPrior().fit(B)
    a = 0.5 * 1e-4  # Prior PF alpha = 0.5 at cm scale, in metres
    W0 = no_const(B, S)
    Wp = prior_pf(B, S, alpha=0.5, prior=prior)
    R, m = prior._factor(B)
    for t in range(0, len(S), 7):  # dense per-frame references
        rows = np.repeat(~lost[t], 3)
        st = S[t].ravel()[rows]
        np.testing.assert_allclose(W0[t], np.linalg.lstsq(Bm[rows], st, rcond=None)[0], rtol=1e-7, atol=1e-9)
        J = np.vstack([Bm[rows], np.sqrt(a) * R])
        y = np.r_[st, np.sqrt(a) * m]
        np.testing.assert_allclose(Wp[t], np.linalg.lstsq(J, y, rcond=None)[0], rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("source", ["random", "real"])
def test_range_pf_matches_lsq_linear(source, real):
    if source == "real":
        B, S, _ = real
        S = S * 1.5  # push weights against the bounds
    else:
        B, S, _ = random_problem(T=60, M=10, K=8, seed=9)
        S = S * 8
    S = S.copy()
    S[5, 2] = np.nan
    W = range_pf(B, S)
    assert W.min() >= -0.5 and W.max() <= 1.5
    assert ((W == -0.5) | (W == 1.5)).any()  # bounds are active somewhere
    Bm = B.reshape(len(B), -1).T
    for t in range(len(S)):
        rows = np.isfinite(S[t].ravel())
        ref = scipy.optimize.lsq_linear(Bm[rows], S[t].ravel()[rows], bounds=(-0.5, 1.5), method="bvls", tol=1e-14).x
        f = lambda w: np.sum((Bm[rows] @ w - S[t].ravel()[rows]) ** 2)  # noqa: E731
        assert f(W[t]) <= f(ref) * (1 + 1e-9) + 1e-18
        np.testing.assert_allclose(W[t], ref, atol=1e-6)


def test_box_lsq_fallback_is_exact():
    rng = np.random.default_rng(8)
    Q = rng.normal(size=(12, 12))
    H = Q @ Q.T + 0.1 * np.eye(12)
    rhs = rng.normal(size=(40, 12)) * 5
    W, _ = box_lsq(H, rhs, -0.5, 1.5)
    W1, n1 = box_lsq(H, rhs, -0.5, 1.5, max_iter=0)  # everything through the primal active set
    assert n1 == 40
    np.testing.assert_allclose(W, W1, atol=1e-7)
    # reference: SciPy's BVLS on the equivalent least-squares problem
    L = np.linalg.cholesky(H).T
    for t in range(0, 40, 7):
        y = scipy.linalg.solve_triangular(L, rhs[t], trans="T")
        ref = scipy.optimize.lsq_linear(L, y, bounds=(-0.5, 1.5), method="bvls", tol=1e-14).x
        np.testing.assert_allclose(W[t], ref, atol=1e-7)


# -- metrics ----------------------------------------------------------------------------------
def test_metrics_literal(real):
    B, S, _ = real
    S = S.copy()
    S[3, 4] = np.nan
    W = solve_spacetime(B, S, alpha=0.01)
    T, M = S.shape[:2]
    ve = velocity_error(B, W, S)
    X = np.einsum("tk,kmc->tmc", W, B) - S
    lit = np.zeros(T)
    for t in range(1, T):
        for m in range(M):
            if np.isfinite(X[t, m]).all() and np.isfinite(X[t - 1, m]).all():
                lit[t] += np.sum((X[t, m] - X[t - 1, m]) ** 2) * 1e6
    np.testing.assert_allclose(ve.per_frame, lit, rtol=1e-10)
    assert ve.total == pytest.approx(lit.sum(), rel=1e-10)
    me = marker_error_mm(B, W, S)
    d = np.linalg.norm(X, axis=2) * 1e3
    assert np.isnan(me.distances[3, 4])
    assert me.per_frame[3] == pytest.approx(np.sqrt(np.nanmean(d[3] ** 2)))
    assert me.per_marker[4] == pytest.approx(np.sqrt(np.nanmean(d[:, 4] ** 2)))
    assert me.rms == pytest.approx(np.sqrt(np.nanmean(d**2)))
    wr = weight_range(W)
    np.testing.assert_array_equal(wr.min, W.min(0))
    assert wr.high == W.max() and 0 <= wr.outside <= 1
    with pytest.raises(ValueError, match="W: expected"):
        velocity_error(B, W[:3], S)


def test_the_solver_given_its_data_products_gives_the_same_numbers():
    """SpacetimeSolver(products=data_products(...)) (what the pipeline's motion_gram stage keeps
    across setting changes) solves to the numbers it computes without them, bounded and not,
    with per-marker weights and missing samples; products of another take are refused."""
    from core.solvers.spacetime import data_products

    r = np.random.default_rng(5)
    K, M, T = 6, 9, 40
    B = r.normal(size=(K, M, 3)) * 1e-2
    S = np.einsum("tk,kmc->tmc", r.uniform(0, 1, (T, K)), B) + r.normal(size=(T, M, 3)) * 1e-4
    S[7, 2] = np.nan
    gam = r.uniform(0.5, 2.0, M)
    for kw in ({}, {"lower": 0.0, "upper": 1.0, "beta": 0.3}):
        want = SpacetimeSolver(B, S, alpha=0.05, marker_weights=gam, **kw).solve()
        pr = data_products(B, S, None, gam)
        got = SpacetimeSolver(B, S, alpha=0.05, marker_weights=gam, products=pr, **kw).solve()
        assert np.array_equal(got, want)
    with pytest.raises(ValueError, match="products"):
        SpacetimeSolver(B, S[:-1], products=pr)
