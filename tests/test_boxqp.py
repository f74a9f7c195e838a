"""Box QPs along frames (core/solvers/boxqp.py) and the per-frame bounded solver built on it
(Range PF, core/solvers/baselines.py): against exhaustive enumeration, SciPy's BVLS
(``lsq_linear(method="bvls")``) and the independent PDAS solver, on random cases chosen to be
degenerate (rank-deficient B, tied shapes, shapes no marker sees, optima on both bounds with
zero multipliers, per-shape and pinned bounds, missing samples) and on the real sample."""

import itertools
import warnings

import numpy as np
import pytest
import scipy.optimize

from core.solvers.baselines import range_pf
from core.solvers.boxqp import _chol_append, _chol_delete, _chol_solve, _finish, solve_box_sequence
from core.solvers.qp import max_kkt_violation, solve_qp_batch
from datapaths import PERFORMANCES, RIGS


def J(H, f, idx, U):
    """Objectives 1/2 u^T H u + f^T u of (N, K) rows."""
    return 0.5 * np.einsum("nk,nkl,nl->n", U, H[idx], U) + np.einsum("nk,nk->n", f, U)


def enumerate_box(H, f):
    """Obviously-correct reference for tiny K: every (free / at 0 / at 1) pattern's equality-
    constrained minimiser, the best feasible one wins."""
    K = len(f)
    best, best_u = np.inf, None
    for pattern in itertools.product((0, 1, 2), repeat=K):
        pattern = np.array(pattern)
        free = pattern == 0
        u = np.where(pattern == 2, 1.0, 0.0)
        if free.any():
            u[free] = np.linalg.solve(H[np.ix_(free, free)], -f[free] - H[np.ix_(free, pattern == 2)].sum(1))
        if (u >= -1e-12).all() and (u <= 1 + 1e-12).all() and 0.5 * u @ H @ u + f @ u < best:
            best, best_u = 0.5 * u @ H @ u + f @ u, u
    return best_u


def random_walk_problem(rng, T, C, K, P, spread=2.0, step=0.15):
    """P ill-conditioned Hessians, linear terms drifting over T frames, per-frame Hessian index
    in runs (as mask patterns change in a take)."""
    D = rng.normal(size=(P, 3 * K, K)) * np.logspace(0, -spread, K)
    H = np.einsum("pmk,pml->pkl", D, D) + 1e-9 * np.eye(K)
    walk = np.cumsum(rng.normal(size=(T, C, K)) * step, axis=0)
    f = -np.einsum("pkl,tcl->tck", H[:1], 0.5 + walk)[:, :, :] * 1.3
    idx = np.repeat(rng.integers(0, P, size=(T // 7 + 1, C)), 7, axis=0)[:T]
    return H, f, idx


# ---------------------------------------------------------------------------- the sequence solver
def test_sequence_matches_exhaustive_enumeration():
    rng = np.random.default_rng(0)
    H, f, idx = random_walk_problem(rng, T=50, C=3, K=4, P=3)
    U, info = solve_box_sequence(H, f, idx, return_info=True)
    ref = np.array([[enumerate_box(H[idx[t, c]], f[t, c]) for c in range(3)] for t in range(50)])
    h, ff = idx.ravel(), f.reshape(-1, 4)
    u, r = U.reshape(-1, 4), ref.reshape(-1, 4)
    scale = np.abs(J(H, ff, h, np.zeros_like(u)) - J(H, ff, h, r)) + 1e-300
    assert np.all(np.abs(J(H, ff, h, u) - J(H, ff, h, r)) <= 1e-10 * scale)
    assert np.abs(u - r).max() < 1e-7
    assert max_kkt_violation(H, ff, h, u, "box") < 1e-10
    assert (u == 0).any() and (u == 1).any() and ((u > 0) & (u < 1)).any()  # both bounds and free variables


@pytest.mark.parametrize("kw", [dict(), dict(refresh=1), dict(refresh=3), dict(refresh=10**9)])
def test_factor_refresh_does_not_change_the_result(kw):
    """Cholesky updates along the chains or fresh factors (refresh=1: every change) reach the
    same optimum as the independent PDAS solver."""
    rng = np.random.default_rng(1)
    H, f, idx = random_walk_problem(rng, T=120, C=2, K=12, P=2, spread=3)
    ref = solve_qp_batch(H, f.reshape(-1, 12), idx.ravel(), constraint="box")[0]  # independent PDAS
    U, info = solve_box_sequence(H, f, idx, return_info=True, **kw)
    U = U.reshape(-1, 12)
    h, ff = idx.ravel(), f.reshape(-1, 12)
    scale = np.abs(J(H, ff, h, np.zeros_like(U)) - J(H, ff, h, ref)) + 1e-300
    assert np.all(np.abs(J(H, ff, h, U) - J(H, ff, h, ref)) <= 1e-9 * scale)
    assert max_kkt_violation(H, ff, h, U, "box") < 1e-10
    assert info["segments"] > 2 * 120 and info["fallback"] == 0  # the homotopy did the work


def test_split_sequence_with_warm_start_matches_one_sequence():
    """Frames 60.. started from frame 59's solution (``warm``, as the live path does) reach the
    optima of the single sequence."""
    rng = np.random.default_rng(6)
    H, f, idx = random_walk_problem(rng, T=120, C=2, K=12, P=1, spread=2)
    U = solve_box_sequence(H, f)
    V = solve_box_sequence(H, f[60:], warm=U[59])
    h, ff = idx[60:].ravel() * 0, f[60:].reshape(-1, 12)
    a, b = J(H, ff, h, U[60:].reshape(-1, 12)), J(H, ff, h, V.reshape(-1, 12))
    assert np.all(np.abs(a - b) <= 1e-9 * (np.abs(a) + 1e-300))


def test_cholesky_updates_keep_the_identity():
    """The factor's column appends and deletes (Givens) keep R^T R = H_FF for the current free
    list F, against numpy's Cholesky, along a random sequence of changes."""
    rng = np.random.default_rng(7)
    K = 9
    A = rng.normal(size=(K + 2, K))
    H = A.T @ A + 1e-6 * np.eye(K)
    R, F, w = np.zeros((K, K)), np.zeros(K, np.int64), np.zeros(K)
    free, n = [], 0
    for step in range(60):
        out = [j for j in range(K) if j not in free]
        if out and (not free or rng.random() < 0.55):
            j = int(rng.choice(out))
            assert _chol_append(R, n, H, F, j, w)
            free.append(j)
            n += 1
        else:
            p = int(rng.integers(n))
            _chol_delete(R, n, F, p)
            free.pop(p)
            n -= 1
        assert list(F[:n]) == free
        Rn = np.triu(R[:n, :n])
        np.testing.assert_allclose(Rn.T @ Rn, H[np.ix_(free, free)], rtol=1e-10, atol=1e-10 * np.abs(H).max())
        if n:
            assert (np.diag(Rn) > 0).all()
            np.testing.assert_allclose(Rn, np.linalg.cholesky(H[np.ix_(free, free)]).T, rtol=1e-8, atol=1e-10)
            x = rng.normal(size=K)
            y = x.copy()
            _chol_solve(R, n, y)
            np.testing.assert_allclose(H[np.ix_(free, free)] @ y[:n], x[:n], rtol=1e-8, atol=1e-10)
    B = np.array([[1.0, 1.0], [1.0, 1.0]])  # singular: the second column cannot join
    assert _chol_append(R, 0, B, F, 0, w) and not _chol_append(R, 1, B, F, 1, w)


def test_degenerate_sequences():
    """Constant frames (every previous set kept), optima exactly on the bounds with zero
    multipliers, a single frame, a single shape."""
    rng = np.random.default_rng(2)
    K = 6
    A = rng.normal(size=(10, K))
    H = (A.T @ A)[None]
    w = np.array([0.0, 1.0, 0.3, 0.0, 1.0, 0.7])  # at both bounds: multipliers exactly 0
    f = np.repeat(-(H[0] @ w)[None, None], 30, axis=0)
    f[15:] *= 1.0 + 1e-14  # a rounding-level change half way
    U, info = solve_box_sequence(H, f, return_info=True)
    np.testing.assert_allclose(U[:, 0], np.broadcast_to(w, (30, K)), atol=1e-9)
    assert info["fallback"] == 0 and U.min() >= 0 and U.max() <= 1
    assert info["kept"] >= 28  # after the cold first frame, the previous set passes outright
    one = solve_box_sequence(H, f[:1])
    np.testing.assert_allclose(one[0, 0], w, atol=1e-9)
    u1 = solve_box_sequence(np.array([[[2.0]]]), np.array([[-5.0], [1.0], [-1.0]]))
    np.testing.assert_allclose(u1[:, 0], [1.0, 0.0, 0.5])


def test_fallback_finishes_from_a_wrong_working_set():
    rng = np.random.default_rng(3)
    H, f, idx = random_walk_problem(rng, T=30, C=1, K=10, P=1, spread=3)
    ff, h = f[:, 0], idx[:, 0]
    ref = solve_qp_batch(H, ff, h, constraint="box")[0]
    lower = rng.random(ff.shape) < 0.5
    upper = ~lower & (rng.random(ff.shape) < 0.5)
    eps = 1e-11 * (np.trace(H[0]) / 10 + np.abs(ff).max(1))
    u = _finish(H, ff, h, lower, upper, eps)
    assert np.allclose(J(H, ff, h, u), J(H, ff, h, ref), rtol=1e-10, atol=1e-16)


def test_sequence_validation():
    with pytest.raises(ValueError, match="H: expected"):
        solve_box_sequence(np.eye(3), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="f: expected"):
        solve_box_sequence(np.eye(3)[None], np.zeros((2, 4)))
    with pytest.raises(ValueError, match="idx"):
        solve_box_sequence(np.eye(3)[None].repeat(2, 0), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="idx"):
        solve_box_sequence(np.eye(3)[None], np.zeros((2, 3)), idx=np.array([0, 1]))


# ---------------------------------------------------------------------------- Range PF vs BVLS
def lsq_case(name, rng, T=60, M=8, K=12):
    """(3M, K) basis, (T, M, 3) targets, bounds and validity for one named degenerate case."""
    B = rng.normal(size=(3 * M, K)) * 0.01
    lo, hi = -0.5, 1.5
    if "rankdef" in name:  # more shapes than coordinates would allow: rank 9 < K
        B = B[:, :9] @ rng.normal(size=(9, K))
    if "ties" in name:  # two identical shapes and one exactly opposite: the fit cannot split them
        B[:, 3] = B[:, 2]
        B[:, 5] = -B[:, 4]
    if "unseen" in name:  # a shape that moves no marker
        B[:, 7] = 0.0
    W = np.cumsum(rng.normal(size=(T, K)) * 0.25, axis=0) + 0.5
    if "perfect" in name:  # targets made by the rig with weights on the bounds: zero multipliers
        W = np.clip(W, lo, hi)
    S = (W @ B.T).reshape(T, M, 3) * (1.0 if "perfect" in name else 1.4)
    S = S + (0 if "perfect" in name else rng.normal(size=S.shape) * 2e-3)
    if "pershape" in name:
        lo = rng.uniform(-1.0, 0.2, K)
        hi = lo + rng.uniform(0.3, 1.5, K)
        hi[1] = lo[1]  # pinned shape
    valid = None
    if "missing" in name:
        valid = rng.random((T, M)) > 0.15
        valid[10] = False  # a frame without any marker
        S = np.where(valid[..., None], S, np.nan)
    return B, S, lo, hi, valid


CASES = ["plain", "rankdef", "ties", "unseen", "perfect", "pershape", "missing", "rankdef-ties-unseen-pershape-missing"]


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("ridge", [0.0, 1e-4])
def test_range_pf_matches_bvls(name, ridge):
    rng = np.random.default_rng(CASES.index(name) + 10)
    B, S, lo, hi, valid = lsq_case(name, rng)
    T, M, K = S.shape[0], S.shape[1], B.shape[1]
    W, info = range_pf(B, S, lo, hi, valid, ridge=ridge, return_info=True)
    lo_, hi_ = np.broadcast_to(lo, (K,)), np.broadcast_to(hi, (K,))
    assert (W >= lo_).all() and (W <= hi_).all()
    assert ((W == lo_) | (W == hi_)).any()
    if "pershape" in name:
        assert (W[:, 1] == lo_[1]).all()
    ok = np.ones((T, M), bool) if valid is None else valid
    rho = ridge * np.linalg.norm(B, 2) ** 2
    lam = np.linalg.eigvalsh(B.T @ B)[-1]
    pin = hi_ == lo_
    for t in range(T):
        rows = np.repeat(ok[t], 3)
        if not rows.any():
            np.testing.assert_array_equal(W[t], np.clip(0.0, lo_, hi_))
            continue
        s = S[t].ravel()[rows]
        A = np.vstack([B[rows], np.sqrt(rho) * np.eye(K)])
        y = np.concatenate([s, np.zeros(K)])
        y_free = y - A[:, pin] @ lo_[pin]  # BVLS wants lower < upper: pinned shapes moved to the data
        ref = np.array(lo_, dtype=float)
        ref[~pin] = scipy.optimize.lsq_linear(A[:, ~pin], y_free, bounds=(lo_[~pin], hi_[~pin]), method="bvls",
                                              tol=1e-14).x
        cost = lambda w: np.sum((A @ w - y) ** 2)  # noqa: E731
        # exact to the brief's 1e-8 relative gap, plus (rank-deficient frames only) what the
        # documented automatic ridge 1e-9 lambda_max ||w||^2 may cost against the unridged BVLS
        auto = 1e-9 * lam * np.sum(np.maximum(np.abs(lo_), np.abs(hi_)) ** 2)
        assert cost(W[t]) <= cost(ref) * (1 + 1e-8) + auto + 1e-30, (t, cost(W[t]), cost(ref))
    assert info["fallback"] <= T // 10


def test_range_pf_kkt_relative_to_scale():
    """The KKT residual of every frame, in the unit-box scaling the solver certifies."""
    rng = np.random.default_rng(4)
    B, S, lo, hi, _ = lsq_case("rankdef-pershape", rng, T=80)
    W = range_pf(B, S, lo, hi)
    H = B.T @ B
    H = H + 1e-9 * np.linalg.eigvalsh(H)[-1] * np.eye(len(H))  # the documented automatic ridge
    sol = hi > lo
    d = (hi - lo)[sol]
    Hu = H[np.ix_(sol, sol)] * d[:, None] * d[None, :]
    fu = ((lo @ H)[sol] - S.reshape(len(S), -1) @ B[:, sol]) * d
    u = (W[:, sol] - lo[sol]) / d
    assert max_kkt_violation(Hu[None], fu, np.zeros(len(S), int), u, "box") < 1e-10


def test_range_pf_validation():
    rng = np.random.default_rng(5)
    B, S, *_ = lsq_case("plain", rng, T=5)
    with pytest.raises(ValueError, match="lower must be <= upper"):
        range_pf(B, S, 1.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        range_pf(B, S, 0.0, np.inf)
    with pytest.raises(ValueError, match=r"\(12,\) per-shape"):
        range_pf(B, S, np.zeros(3), 1.0)
    W = range_pf(B, S, np.full(12, 0.25), 0.25)  # every shape pinned
    assert (W == 0.25).all()


# ---------------------------------------------------------------------------- the real sample
@pytest.fixture(scope="module")
def sample():
    """The dashboard's sample: ICT driven by a real Live Link take, personalised onto Rocketbox
    (2,028 frames, 165 shapes, 41 markers; the ``bounded_perframe`` benchmark case)."""
    from core.pipeline import Pipeline, StageCache

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pipe = Pipeline(cache=StageCache(), method="lsq", source=str(PERFORMANCES / "livelinkface_take_s07.csv"),
                        source_rig=str(RIGS / "ict_facekit.glb"), target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))
        r = pipe.results(["stabilize", "personalize"])
    return r["personalize"]["deltas"], r["stabilize"]["source"].deltas


@pytest.mark.slow
def test_real_sample_matches_bvls(sample):
    B, S = sample
    W, info = range_pf(B, S, 0.0, 1.0, return_info=True)
    Bm, s = B.reshape(len(B), -1).T, S.reshape(len(S), -1)
    H = Bm.T @ Bm
    H = H + 1e-9 * np.linalg.eigvalsh(H)[-1] * np.eye(len(H))  # rank 119 < 165 shapes: automatic ridge
    assert max_kkt_violation(H[None], -(s @ Bm), np.zeros(len(S), int), W, "box") < 1e-10
    cost = lambda w, t: np.sum((Bm @ w - s[t]) ** 2)  # noqa: E731
    for t in np.linspace(0, len(S) - 1, 8).astype(int):
        ref = scipy.optimize.lsq_linear(Bm, s[t], bounds=(0, 1), method="bvls", tol=1e-12).x
        assert cost(W[t], t) <= cost(ref, t) * (1 + 1e-8), t
    # per-shape bounds on the real rig (the upcoming per-shape controls): still exact
    K = len(B)
    lo = np.where(np.arange(K) % 3 == 0, -0.2, 0.0)
    hi = np.where(np.arange(K) % 5 == 0, 0.5, 1.0)
    Wp = range_pf(B, S[:300], lo, hi)
    for t in (0, 150, 299):
        ref = scipy.optimize.lsq_linear(Bm, s[t], bounds=(lo, hi), method="bvls", tol=1e-12).x
        assert cost(Wp[t], t) <= cost(ref, t) * (1 + 1e-8), t


def test_pieces_on_threads_give_the_same_bits(monkeypatch):
    """Chains cut into pieces (each started cold) and shared among threads: the same result bit
    for bit whatever the number of threads (the cut is a fixed rule), and the optimum."""
    import core.solvers.boxqp as boxqp

    rng = np.random.default_rng(8)
    H, f, idx = random_walk_problem(rng, T=300, C=3, K=10, P=2, spread=3)
    monkeypatch.setattr(boxqp, "PIECE", 70)  # 5 pieces per chain
    monkeypatch.setattr(boxqp, "_threads", lambda work: 1)
    one, info1 = solve_box_sequence(H, f, idx, return_info=True)
    monkeypatch.setattr(boxqp, "_threads", lambda work: 4)
    four, info4 = solve_box_sequence(H, f, idx, return_info=True)
    np.testing.assert_array_equal(one, four)
    assert info1 == info4 and info1["fallback"] == 0
    ref = solve_qp_batch(H, f.reshape(-1, 10), idx.ravel(), constraint="box")[0]
    h, ff, u = idx.ravel(), f.reshape(-1, 10), four.reshape(-1, 10)
    scale = np.abs(J(H, ff, h, np.zeros_like(u)) - J(H, ff, h, ref)) + 1e-300
    assert np.all(np.abs(J(H, ff, h, u) - J(H, ff, h, ref)) <= 1e-9 * scale)
    assert boxqp.kernel_cached()  # the kernel compiled above is in numba's cache now
