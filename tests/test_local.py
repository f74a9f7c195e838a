"""Local retargeting (Liu et al. 2011, eq. 2 and 3): the batched QP solver against exhaustive
enumeration and SciPy on random problems, and against SLSQP on real ICT / Live Link data."""

import importlib.util
import itertools
from pathlib import Path

import numpy as np
import pytest

from core.model import MarkerLayout, Rig
from core.segment import marker_weights, segment
from core.solvers.local import (blend_weights, local_precompute, masks_at, reconstruct_markers, region_curves,
                                smooth_weights, solve_local, synthesize)
from core.solvers.qp import project, solve_qp_batch
from core.solvers.reference import solve_qp_scipy

ROOT = Path(__file__).resolve().parents[1]


def _liu_script():
    spec = importlib.util.spec_from_file_location("liu_table1", ROOT / "scripts" / "liu_table1.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def random_qps(rng, N, K, M=30, spread=2.0):
    """Ill-conditioned least-squares QPs like eq. 2: H = DᵀD, f = -Dᵀb."""
    D = rng.normal(size=(N, M, K)) * np.logspace(0, -spread, K)
    b = rng.normal(size=(N, M)) * 0.7 + D @ rng.uniform(0, 0.4, K)
    return np.einsum("nmk,nml->nkl", D, D), -np.einsum("nmk,nm->nk", D, b)


def J(H, f, u):
    return 0.5 * np.einsum("nk,nkl,nl->n", u, H, u) + np.einsum("nk,nk->n", f, u)


def enumerate_qp(H, f, constraint):
    """Obviously-correct reference for tiny K: try every active set, keep the best feasible
    equality-constrained minimiser (the optimum is one of them)."""
    K = len(f)
    best, best_u = np.inf, None
    states = (0, 1) if constraint == "simplex" else (0, 1, 2)  # free / at 0 / at 1
    for pattern in itertools.product(states, repeat=K):
        pattern = np.array(pattern)
        for sum_on in ((False, True) if constraint == "simplex" else (False,)):
            free = pattern == 0
            u = np.where(pattern == 2, 1.0, 0.0)
            nf = free.sum()
            if nf == 0 and sum_on:
                continue
            if nf:
                rhs = -f[free] - H[np.ix_(free, pattern == 2)].sum(1)
                if sum_on:
                    A = np.block([[H[np.ix_(free, free)], np.ones((nf, 1))], [np.ones((1, nf)), np.zeros((1, 1))]])
                    x = np.linalg.solve(A, np.append(rhs, 1.0))[:nf]
                else:
                    x = np.linalg.solve(H[np.ix_(free, free)], rhs)
                u[free] = x
            ok = (u >= -1e-12).all() and (u <= 1 + 1e-12).all() and (constraint == "box" or u.sum() <= 1 + 1e-12)
            if ok:
                val = 0.5 * u @ H @ u + f @ u
                if val < best:
                    best, best_u = val, u
    return best_u


# ---------------------------------------------------------------------------- the QP solver
@pytest.mark.parametrize("constraint", ["simplex", "box"])
def test_batched_qp_matches_exhaustive_enumeration(constraint):
    rng = np.random.default_rng(0)
    H, f = random_qps(rng, 40, 5)
    u, info = solve_qp_batch(H, f, constraint=constraint)
    ref = np.array([enumerate_qp(H[n], f[n], constraint) for n in range(len(f))])
    scale = np.abs(J(H, f, np.zeros_like(f)) - J(H, f, ref)) + 1e-12
    assert np.all(np.abs(J(H, f, u) - J(H, f, ref)) <= 1e-10 * scale + 1e-14)
    assert np.abs(u - ref).max() < 1e-7
    assert info["kkt_violation"] < 1e-10


@pytest.mark.parametrize("constraint", ["simplex", "box"])
def test_batched_qp_matches_scipy_and_the_fallback_path(constraint):
    rng = np.random.default_rng(1)
    H, f = random_qps(rng, 30, 12, spread=3)
    u, info = solve_qp_batch(H, f, constraint=constraint)
    ref = solve_qp_scipy(H, f, constraint)
    # SLSQP is a general NLP method: it can only be as good as the exact optimum
    assert np.all(J(H, f, u) <= J(H, f, ref) + 1e-9 * (np.abs(J(H, f, ref)) + 1e-12))
    assert np.all(J(H, f, u) >= J(H, f, ref) - 1e-6 * np.abs(J(H, f, ref)))
    # forcing the primal active-set fallback (PDAS limited to 1 iteration) gives the same optimum
    u1, info1 = solve_qp_batch(H, f, constraint=constraint, max_iter=1)
    assert info1["fallback"] > 0
    assert np.allclose(J(H, f, u1), J(H, f, u), rtol=1e-10, atol=1e-14)
    # and so does a warm start from an arbitrary feasible point
    u2, _ = solve_qp_batch(H, f, constraint=constraint, warm=project(rng.uniform(-1, 2, f.shape), constraint))
    assert np.allclose(J(H, f, u2), J(H, f, u), rtol=1e-10, atol=1e-14)


def test_trust_constr_reference_agrees_on_a_few_problems():
    rng = np.random.default_rng(2)
    H, f = random_qps(rng, 4, 8, spread=1)
    u, _ = solve_qp_batch(H, f, constraint="simplex")
    ref = solve_qp_scipy(H, f, "simplex", method="trust-constr")
    assert np.all(J(H, f, u) <= J(H, f, ref) + 1e-8 * np.abs(J(H, f, ref)))
    assert np.abs(u - ref).max() < 1e-3


def test_constraints_hold_exactly_and_projection():
    rng = np.random.default_rng(3)
    H, f = random_qps(rng, 200, 10)
    f *= 5  # push many solutions onto the constraints
    for c in ("simplex", "box"):
        u, _ = solve_qp_batch(H, f, constraint=c)
        assert u.min() >= 0 and u.max() <= 1
        if c == "simplex":
            assert u.sum(1).max() <= 1 + 1e-12
    x = rng.normal(size=(500, 6)) * 2
    p = project(x, "simplex")
    assert p.min() >= 0 and p.sum(1).max() <= 1 + 1e-12
    # the projection is the closest feasible point: check against SLSQP on a few rows
    ref = solve_qp_scipy(np.repeat(np.eye(6)[None], 5, 0), -x[:5], "simplex")
    assert np.abs(p[:5] - ref).max() < 1e-6


def test_qp_validation():
    with pytest.raises(ValueError, match="constraint"):
        solve_qp_batch(np.eye(2)[None], np.zeros((1, 2)), constraint="cube")
    with pytest.raises(ValueError, match="f: expected"):
        solve_qp_batch(np.eye(2)[None], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="idx"):
        solve_qp_batch(np.eye(2)[None], np.zeros((3, 2)))


# ---------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def liu(ict):
    mod = _liu_script()
    s = mod.setup("livelinkface_take_s07.csv", n_markers=97, frames=300)
    sym, layout = s["sym"], s["layout"]
    seg = segment(sym, n_regions=12)
    s["seg"] = seg
    s["mw"] = marker_weights(sym, layout, seg.masks, graph=seg.graph)
    s["n0"], s["D"] = layout.on_rig(sym)
    return s


@pytest.mark.parametrize("constraint", ["simplex", "box"])
def test_real_local_solve_matches_slsqp(liu, constraint):
    """ICT markers driven by real Live Link curves, the symmetric 22-shape rig, 12 regions."""
    prob = local_precompute(liu["n0"], liu["D"], liu["mw"], constraint)
    frames = np.arange(0, 300, 37)
    U, info = prob.solve(liu["targets"][frames], return_info=True)
    assert info["kkt_violation"] < 1e-8
    f = prob.linear_terms(liu["targets"][frames]).reshape(-1, prob.n_shapes)
    H = prob.H[np.tile(np.arange(12), len(frames))]
    u = U.reshape(-1, prob.n_shapes)
    pick = np.arange(3, len(u), 17)  # 6 of the 108 QPs: SLSQP needs ~0.3 s each on these
    ref = solve_qp_scipy(H[pick], f[pick], constraint)
    # objective J(u) = ½‖M_k(Du − b)‖² − ½‖M_k b‖²; compare relative to the residual scale
    b2 = np.einsum("rm,tmc->tr", liu["mw"] ** 2, (liu["targets"][frames] - liu["n0"]) ** 2).ravel()[pick]
    diff = (J(H[pick], f[pick], u[pick]) - J(H[pick], f[pick], ref)) / b2
    assert diff.max() <= 1e-9 and diff.min() >= -1e-6


def test_real_block_size_does_not_change_the_result(liu):
    prob = local_precompute(liu["n0"], liu["D"], liu["mw"], "simplex")
    T = liu["targets"][:120]
    U1 = prob.solve(T, block=1)  # every frame cold
    U16 = prob.solve(T, block=16)
    U1k = prob.solve(T, block=1000, warm_iter=1)  # one block, maximal warm starting
    f = prob.linear_terms(T).reshape(-1, prob.n_shapes)
    H = prob.H[np.tile(np.arange(12), len(T))]
    j1, j16, jk = (J(H, f, U.reshape(-1, prob.n_shapes)) for U in (U1, U16, U1k))
    assert np.allclose(j16, j1, rtol=1e-9, atol=1e-18) and np.allclose(jk, j1, rtol=1e-9, atol=1e-18)


def test_real_box_solve_matches_independent_pdas_with_missing_markers(liu):
    """The box form runs on core.solvers.boxqp (frames warm-started along every region); the
    independent cold PDAS of solve_qp_batch on the same QPs, missing markers included, agrees."""
    prob = local_precompute(liu["n0"], liu["D"], liu["mw"], "box")
    T = liu["targets"][:150].copy()
    T[40:70, [3, 40]] = np.nan
    T[90, 10:30] = np.nan
    U, info = prob.solve(T, return_info=True)
    assert info["kkt_violation"] < 1e-9 and info["fallback"] == 0
    valid = np.isfinite(T).all(2)
    K = prob.n_shapes
    H = np.stack([prob.hessians(v) for v in valid]).reshape(-1, K, K)
    f = prob.linear_terms(T, valid).reshape(-1, K)
    ref = solve_qp_batch(H, f, constraint="box")[0]
    b2 = np.einsum("rm,tmc->tr", liu["mw"] ** 2, np.where(valid[..., None], T - liu["n0"], 0.0) ** 2).ravel()
    assert np.abs(J(H, f, U.reshape(-1, K)) - J(H, f, ref)).max() <= 1e-10 * b2.max()
    assert np.all(J(H, f, U.reshape(-1, K)) <= J(H, f, ref) + 1e-12 * b2)


def test_local_error_falls_with_regions(liu):
    """Eq. 3 reconstruction of the markers: 12 regions beat the global solve (the paper's
    Table 1 trend), for both constraint sets."""
    n0, D, T = liu["n0"], liu["D"], liu["targets"]
    Bm = masks_at(liu["layout"], liu["seg"].masks)
    for c in ("simplex", "box"):
        Ug = solve_local(n0, D, T, None, c)
        Ul = solve_local(n0, D, T, liu["mw"], c)
        eg = np.linalg.norm(reconstruct_markers(n0, D, Ug, np.ones((1, len(n0)))) - T, axis=2).mean()
        el = np.linalg.norm(reconstruct_markers(n0, D, Ul, Bm) - T, axis=2).mean()
        assert el < 0.8 * eg, (c, el, eg)


def test_global_box_solve_reproduces_in_span_targets(ict):
    """Targets made by the rig itself with weights in [0, 1] are reproduced (box, R = 1)."""
    rng = np.random.default_rng(5)
    mod = _liu_script()
    layout = mod.face_markers(ict, 97)
    n0, D = layout.on_rig(ict)
    W = rng.uniform(0, 1, (6, ict.n_shapes)) * (rng.random((6, ict.n_shapes)) < 0.3)
    T = n0 + np.einsum("tk,kmc->tmc", W, D)
    U = solve_local(n0, D, T, None, "box")
    rec = reconstruct_markers(n0, D, U, np.ones((1, 97)))
    assert np.abs(rec - T).max() < 1e-6 * ict.size


def test_missing_markers_equal_dropping_them(liu):
    n0, D, mw = liu["n0"], liu["D"], liu["mw"]
    T = liu["targets"][:20].copy()
    T[5:9, [3, 40]] = np.nan
    U = solve_local(n0, D, T, mw, "simplex")
    keep = np.setdiff1d(np.arange(len(n0)), [3, 40])
    Ud = solve_local(n0[keep], D[:, keep], T[5:9][:, keep], mw[:, keep], "simplex")
    prob = local_precompute(n0[keep], D[:, keep], mw[:, keep], "simplex")
    f = prob.linear_terms(T[5:9][:, keep]).reshape(-1, prob.n_shapes)
    H = prob.H[np.tile(np.arange(12), 4)]
    assert np.allclose(J(H, f, U[5:9].reshape(-1, 22)), J(H, f, Ud.reshape(-1, 22)), rtol=1e-8, atol=1e-18)
    with pytest.raises(ValueError, match="no valid marker"):
        solve_local(n0, D, np.full((1, len(n0), 3), np.nan), mw)


def test_local_validation(liu):
    n0, D = liu["n0"], liu["D"]
    with pytest.raises(ValueError, match="marker_weights"):
        local_precompute(n0, D, np.ones((2, 5)))
    with pytest.raises(ValueError, match="constraint"):
        local_precompute(n0, D, None, "cube")
    with pytest.raises(ValueError, match="targets"):
        local_precompute(n0, D).solve(np.zeros((3, 5, 3)))


# ---------------------------------------------------------------------------- synthesis and views
def small_rig(rng, V=12, K=4):
    P = rng.normal(size=(V, 3)) * 0.05
    F = np.array([[i, i + 1, i + 2] for i in range(V - 2)])
    return Rig(P, F, rng.normal(size=(K, V, 3)) * 0.01, [f"s{k}" for k in range(K)])


def test_synthesize_is_eq3():
    rng = np.random.default_rng(6)
    rig = small_rig(rng)
    R, T = 3, 5
    B = rng.random((R, rig.n_vertices))
    B[0, :4] = 0  # sparse support
    B /= B.sum(0)
    U = rng.random((T, R, rig.n_shapes)) * 0.3
    X = synthesize(rig, U, B)
    # eq. 3 literally, with absolute poses S̄ = [n, n + d_1, ...] and w_0 = 1 - Σu
    S = np.concatenate([rig.neutral[None], rig.neutral[None] + rig.deltas])  # (K+1, V, 3)
    for t in range(T):
        ref = np.zeros_like(rig.neutral)
        for k in range(R):
            w = np.concatenate([[1 - U[t, k].sum()], U[t, k]])
            ref += B[k][:, None] * np.einsum("i,ivc->vc", w, S)
        assert np.allclose(X[t], ref, atol=1e-15)
    # one region, all ones: the ordinary rig evaluation
    assert np.allclose(synthesize(rig, U[:, :1], np.ones((1, rig.n_vertices))), rig.evaluate(U[:, 0]))
    # markers on vertices: reconstruct_markers agrees with the synthesized mesh
    lay = MarkerLayout.from_vertices(["a", "b", "c"], [1, 5, 9])
    n0, D = lay.on_rig(rig)
    assert np.allclose(reconstruct_markers(n0, D, U, masks_at(lay, B)), lay.points(X))
    with pytest.raises(ValueError, match="masks"):
        synthesize(rig, U, B[:2])


def test_smoothing_blending_and_curves():
    rng = np.random.default_rng(7)
    H, f = random_qps(rng, 60, 6)
    U = solve_qp_batch(H, f, constraint="simplex")[0].reshape(20, 3, 6)
    S = smooth_weights(U, 2.0)
    assert S.shape == U.shape and S.min() >= 0 and S.sum(2).max() <= 1 + 1e-12
    assert not np.allclose(S, U) and np.array_equal(smooth_weights(U, 0), U)
    const = np.broadcast_to(U[:1], U.shape)
    assert np.allclose(smooth_weights(const, 3.0), const)
    B = rng.random((3, 50))
    B /= B.sum(0)
    same = np.repeat(U[:, :1], 3, axis=1)
    assert np.allclose(blend_weights(same, B), U[:, 0])
    areas = rng.random(50)
    a = B @ areas
    assert np.allclose(blend_weights(U, B, areas), np.einsum("trk,r->tk", U, a / a.sum()))
    curves = region_curves(U, [f"s{i}" for i in range(6)])
    assert len(curves) == 18 and np.array_equal(curves["s2@r1"], U[:, 1, 2])
    with pytest.raises(ValueError, match="sigma"):
        smooth_weights(U, -1)
