"""Production solver controls (core.controls and the solvers' quadratic / zero / bounds options):
each against a slow obvious reference on small random cases, and on the bundled Live Link take
driving ICT onto Rocketbox."""

import json
import warnings

import numpy as np
import pytest
import scipy.optimize as so

from core import controls as C
from core.model import flatten
from datapaths import LAYOUTS, PERFORMANCES, RIGS
from test_io_gltf import run_node_check

FILES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
             target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))
FPS = 30.0


def _problem(**settings):
    from core.pipeline import Pipeline, StageCache
    from core.stages.methods import named_target

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # shapes no marker sees
        pipe = Pipeline(cache=StageCache(), **FILES, **settings)
        r = pipe.results(["stabilize", "personalize", "shapes", "load", "frames", "prior", "vocabulary", "solve", "synthesize"])
    st = r["stabilize"]["source"]
    return {"B": r["personalize"]["deltas"], "S": st.deltas, "valid": st.valid, "names": list(r["shapes"]["rig"].names),
            "named": named_target(r), "prior": r["prior"]["prior"] if r.get("prior") else None, "results": r}


@pytest.fixture(scope="module")
def arkit():
    """The marker problem of the sample with the target's 51 ARKit shapes the markers see."""
    return _problem(method="bounded", target_shapes="arkit")


@pytest.fixture(scope="module")
def dense_weights():
    """The bounded solve of the sample on all of Rocketbox's shapes, as written (2028, 175)."""
    return _problem(method="bounded")["results"]["synthesize"]["weights"]


def _marker_mm(B, W, S, valid):
    from core.metrics import marker_error_mm

    return float(marker_error_mm(B, W, S, valid).distances.mean())


def _pairs_q(K, pairs, w):
    Q = np.zeros((K, K))
    for a, b in pairs:
        e = np.zeros(K)
        e[a], e[b] = 1.0, -1.0
        Q += w * np.outer(e, e)
    return Q


# -- names and pairs ----------------------------------------------------------------------


def test_pairs_from_the_bundled_rigs_names(rigs):
    ict, rb = rigs["ict_facekit"].names, rigs["rocketbox_female_adult_02"].names
    mp = dict(C.mirror_pairs(ict))
    assert mp["eyeBlink_L"] == "eyeBlink_R" and mp["jawLeft"] == "jawRight" and len(mp) == 22
    assert ("jawLeft", "jawRight") not in C.symmetry_pairs(ict)  # a direction, not a face half
    assert ("eyeLookIn_L", "eyeLookIn_R") not in C.symmetry_pairs(ict)  # horizontal gaze is conjugate
    assert ("eyeLookUp_L", "eyeLookUp_R") in C.symmetry_pairs(ict)
    m = C.mirror_map(rb)
    assert np.array_equal(m[m], np.arange(len(rb)))  # an involution
    mirror = {rb[i]: rb[j] for i, j in enumerate(m)}
    assert mirror["AK_09_EyeBlinkLeft"] == "AK_10_EyeBlinkRight"  # codes differ between the sides
    assert mirror["AU_02_L_OuterBrowRaiser"] == "AU_02_R_OuterBrowRaiser"  # L_/R_ infix
    assert mirror["SR_01_Cheek_Puff_Left"] == "SR_02_Cheek_Puff_Right"
    assert mirror["SR_07_Eye_Left_Left"] == "SR_15_Eye_Right_Right"  # every side token swapped
    assert mirror["AU_12_LipCornerPuller"] == "AU_12_LipCornerPuller"  # midline: itself
    sym = C.symmetry_pairs(rb)
    assert ("AU_12_L_LipCornerPuller", "AU_12_R_LipCornerPuller") in sym
    for directional in [("HB_01_L_Jaw", "HB_01_R_Jaw"), ("SR_20_Jaw_Left", "SR_22_Jaw_Right"),
                        ("SR_07_Eye_Left_Left", "SR_15_Eye_Right_Right"), ("AU_61_EyesTurnLeft", "AU_62_EyesTurnRight")]:
        assert directional in C.mirror_pairs(rb) and directional not in sym
    assert len(C.mirror_pairs(rb)) == 47 and len(sym) == 35


def test_layout_marker_names_pair_as_the_layouts_name_them():
    for layout in LAYOUTS.glob("*.json"):
        names = [m["name"] if isinstance(m, dict) else m for m in json.loads(layout.read_text())["markers"]]
        pairs = dict(C.mirror_pairs(names))
        assert pairs["Leye_Up"] == "Reye_Up" and pairs["Mouth_UpL1"] == "Mouth_UpR1" and pairs["Mouth_Lend"] == "Mouth_Rend"
        assert pairs["Chin_R2"] == "Chin_L2" and pairs["ForeHead_L"] == "ForeHead_R"
        mid = [n for n, k in zip(names, C.mirror_map(names)) if names[k] == n]
        assert mid == ["ForeHead_M", "Eyebrow_Center", "NoseTop", "NoseHead", "Mouth_Up", "Mouth_Down", "Chin"]


# -- the table ----------------------------------------------------------------------------


def test_table_round_trip_merge_and_resolve(tmp_path, rigs):
    names = rigs["rocketbox_female_adult_02"].names
    d = C.default_table(names)
    path = C.write_table(tmp_path / "controls.json", d)
    assert C.read_table(path, names) == d
    # a user's table in ARKit spelling applies to Rocketbox's AK_ shapes
    user = {"shapes": {"eyeBlinkLeft": {"gain": 1.5}, "jawOpen": {"upper": 0.8, "active": False}}, "cancel": [["eyeBlinkLeft", "eyeWideLeft"]]}
    m = C.merge_table(user, d)
    assert m["shapes"]["AK_09_EyeBlinkLeft"] == dict(C.SHAPE_FIELDS, gain=1.5)
    assert m["shapes"]["AK_25_JawOpen"]["upper"] == 0.8 and m["symmetry"] == d["symmetry"]
    ctl = C.resolve(m, names)
    k = names.index("AK_25_JawOpen")
    assert not ctl.active[k] and ctl.bounds()[1][k] == 0.0 and ctl.gain[names.index("AK_09_EyeBlinkLeft")] == 1.5
    assert ctl.cancel.tolist() == [[names.index("AK_09_EyeBlinkLeft"), names.index("AK_21_EyeWideLeft")]]
    sub = ctl.subset([n for n in names if n != "AK_21_EyeWideLeft"])
    assert len(sub.cancel) == 0 and len(sub.symmetry) == len(ctl.symmetry) - 1  # pairs with a dropped shape go


@pytest.mark.parametrize("table, match", [
    ({"shape": {}}, "unknown key 'shape'; did you mean 'shapes'"),
    ({"shapes": {"eyeBlinkLeft": {"gian": 2}}}, "unknown field 'gian'; did you mean 'gain'"),
    ({"shapes": {"eyeBlinkLeft": {"lower": 1, "upper": 0}}}, "lower 1 > upper 0"),
    ({"shapes": {"eyeBlinkLeft": {"gain": "2"}}}, r"gain: expected a finite number"),
    ({"shapes": {"eyeBlinkLeft": {"active": 1}}}, "active: expected true or false"),
    ({"shapes": {"eyeBlinkLef": {}}}, "did you mean"),
    ({"cancel": [["jawOpen"]]}, r"cancel\[0\]: expected a pair"),
    ({"symmetry": [["jawOpen", "jawOpen"]]}, "two different shapes"),
    ({"version": 2}, "version 1"),
])
def test_table_errors_name_the_key(table, match):
    from core.names import ARKIT_NAMES

    with pytest.raises(ValueError, match=match):
        C.validate_table(table, ARKIT_NAMES)


# -- per-shape: remap and bounds ----------------------------------------------------------


def test_gain_2_doubles_a_curve_up_to_its_bound(arkit):
    W = arkit["results"]["solve"]["weights"]
    k = arkit["names"].index("AK_25_JawOpen")
    out = C.remap(W, gain=np.where(np.arange(W.shape[1]) == k, 2.0, 1.0), offset=0.0, lower=0.0, upper=1.0)
    assert np.array_equal(out[:, k], np.minimum(2.0 * W[:, k], 1.0))
    assert (W[:, k] > 0.5).any()  # the bound is reached somewhere
    other = np.arange(W.shape[1]) != k
    assert np.array_equal(out[:, other], W[:, other])
    assert np.isnan(C.remap(np.array([[np.nan, 0.2]]), 2.0, 0.1, 0.0, 1.0)[0, 0])


def test_per_shape_bounds_and_active_set_in_the_bounded_solve(arkit):
    from core.solvers.baselines import range_pf

    B, S, valid, names = arkit["B"], arkit["S"], arkit["valid"], arkit["names"]
    table = C.merge_table({"shapes": {"jawOpen": {"upper": 0.3}, "mouthClose": {"active": False}}}, C.default_table(names))
    ctl = C.resolve(table, names)
    lo, hi = ctl.bounds()
    W = range_pf(B, S, lo, hi, valid, ridge=1e-5)
    assert W[:, names.index("AK_25_JawOpen")].max() == pytest.approx(0.3)
    assert (W[:, names.index("AK_27_MouthClose")] == 0).all()
    # the same active set through the zero option
    Wz = range_pf(B, S, ctl.lower, ctl.upper, valid, ridge=1e-5, zero=ctl.zero())
    assert np.abs(Wz - W).max() < 1e-9


# -- the solvers' quadratic and zero options against references --------------------------


def _random_problem(seed, K=8, M=5, T=30):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(K, M, 3))
    S = rng.normal(size=(T, M, 3)) * 0.8
    return rng, B, S


def test_range_pf_and_prior_pf_with_coupling_and_held_weights_match_bvls():
    from core.solvers.baselines import prior_pf, range_pf

    rng, B, S = _random_problem(0)
    T, K = len(S), len(B)
    zero = rng.random((T, K)) < 0.2
    valid = rng.random(S.shape[:2]) > 0.15
    Q = _pairs_q(K, [(0, 1), (2, 3)], 0.3)
    Bf = flatten(B).T
    L = np.linalg.cholesky(np.linalg.norm(Bf, 2) ** 2 * Q + 1e-14 * np.eye(K)).T  # sigma^2 Q = L^T L
    W = range_pf(B, S, -0.2, 1.0, valid, quadratic=Q, zero=zero)
    Wp = prior_pf(B, S, alpha=0.0, valid=valid, quadratic=Q, zero=zero)
    assert (W[zero] == 0).all() and (Wp[zero] == 0).all()
    for t in range(T):
        free, rows = ~zero[t], np.repeat(valid[t], 3)
        A = np.vstack([Bf[rows], L])[:, free]
        y = np.concatenate([S[t].ravel()[rows], np.zeros(K)])
        ref = so.lsq_linear(A, y, bounds=(-0.2, 1.0), method="bvls", tol=1e-14).x
        assert np.abs(W[t, free] - ref).max() < 1e-10
        assert np.abs(Wp[t, free] - np.linalg.lstsq(A, y, rcond=None)[0]).max() < 1e-10
    # defaults: exactly today's solves
    assert np.array_equal(range_pf(B, S, -0.2, 1.0, valid), range_pf(B, S, -0.2, 1.0, valid, quadratic=None, zero=None))


def test_spacetime_coupling_is_exact_on_both_paths_and_zero_matches_the_qp_reference():
    from core.solvers.reference import bounded_spacetime_reference, spacetime_reference
    from core.solvers.spacetime import SpacetimeSolver

    rng = np.random.default_rng(1)
    K, M, T = 6, 5, 30
    B = rng.normal(size=(K, M, 3))
    S = np.cumsum(rng.normal(size=(T, M, 3)) * 0.3, 0)
    Q = _pairs_q(K, [(0, 1), (2, 3)], 0.5)
    s = SpacetimeSolver(B, S, alpha=0.01, quadratic=Q)
    W = s.solve()
    assert s.method_ == "fast"  # the coupling joins C: the fast path stays
    R = spacetime_reference(B, S, 0.01, 0.0, None, None, ridge=s.ridge_, quadratic=s.quadratic_)
    assert np.abs(W - R).max() < 1e-10 * max(1.0, np.abs(R).max())
    valid = rng.random((T, M)) > 0.2
    sb = SpacetimeSolver(B, S, alpha=0.01, beta=0.1, quadratic=Q, valid=valid)
    Rb = spacetime_reference(B, S, 0.01, 0.1, None, None, ridge=sb.ridge_, quadratic=sb.quadratic_, valid=valid)
    assert sb.solve() is not None and sb.method_ == "block"
    assert np.abs(sb.solve() - Rb).max() < 1e-8 * max(1.0, np.abs(Rb).max())
    assert s.energy(W).quadratic == pytest.approx(float(np.einsum("tk,kl,tl->", W, s.quadratic_, W)))
    # held weights in the bounded solve: the general QP solver with those entries known
    s2 = SpacetimeSolver(B, S, alpha=0.01, quadratic=Q, lower=0.0, upper=1.0)
    zero = rng.random((T, K)) < 0.15
    W2 = s2.solve(zero=zero)
    known = np.full((T, K), np.nan)
    known[zero] = 0.0
    known[[0, -1]] = 0.0
    R2, info = bounded_spacetime_reference(B, S, 0.01, 0.0, None, known, lower=0, upper=1, ridge=s2.ridge_,
                                           quadratic=s2.quadratic_)
    assert (W2[zero] == 0).all() and np.abs(W2 - R2).max() < 1e-7


def test_local_coupling_bounds_and_held_weights_match_slsqp():
    from core.solvers.local import local_precompute

    rng = np.random.default_rng(3)
    K, M, T, R = 6, 7, 12, 3
    D = rng.normal(size=(K, M, 3)) * 0.01
    n = rng.normal(size=(M, 3)) * 0.05
    targets = n[None] + np.einsum("tk,kmc->tmc", rng.random((T, K)) * 0.6, D) + rng.normal(size=(T, M, 3)) * 1e-3
    mw = rng.random((R, M))
    Q = _pairs_q(K, [(0, 1)], 0.5)
    zero = rng.random((T, R, K)) < 0.2
    Bf = flatten(D).T
    for constraint, kw in [("box", dict(lower=-0.1, upper=np.linspace(0.5, 1, K))), ("simplex", {})]:
        prob = local_precompute(n, D, mw, constraint, quadratic=Q, **kw)
        U, info = prob.solve(targets, zero=zero, return_info=True)
        assert info["kkt_violation"] < 1e-12
        lo = np.broadcast_to(kw.get("lower", 0.0), (K,))
        hi = np.broadcast_to(kw.get("upper", 1.0), (K,))
        for t in range(T):
            for r in range(R):
                w3 = np.repeat(mw[r] ** 2, 3)
                H = Bf.T @ (w3[:, None] * Bf)
                H = H + prob.ridge * np.trace(H) / K * np.eye(K) + prob.coupling[r]
                f = -Bf.T @ (w3 * (targets[t] - n).ravel())
                fr = ~zero[t, r]
                Hf, ff = H[np.ix_(fr, fr)], f[fr]
                sc = np.trace(Hf) / fr.sum()
                cons = [so.LinearConstraint(np.ones((1, fr.sum())), -np.inf, 1)] if constraint == "simplex" else []
                res = so.minimize(lambda x: 0.5 * x @ Hf @ x / sc + ff @ x / sc, np.clip(np.full(fr.sum(), 0.1), lo[fr], hi[fr]),
                                  jac=lambda x: (Hf @ x + ff) / sc, bounds=so.Bounds(lo[fr], hi[fr]), constraints=cons,
                                  method="SLSQP", options={"ftol": 1e-15, "maxiter": 1000})
                assert np.abs(res.x - U[t, r, fr]).max() < 1e-6
        assert (U[zero] == np.clip(0.0, lo, hi)[np.nonzero(zero)[2]]).all()


def test_geometric_coupling_and_held_weights_reach_the_l1_optimum():
    from core.solvers.geometric import GeometricSolver

    rng = np.random.default_rng(5)
    K, M, T = 7, 6, 10
    P = rng.normal(size=(K, M, 3)) * 0.01
    W0 = rng.random((T, K)) * (rng.random((T, K)) < 0.5)
    A = np.einsum("tk,kmc->tmc", W0, P) + rng.normal(size=(T, M, 3)) * 1e-4
    zero = rng.random((T, K)) < 0.25
    g = GeometricSolver(P, "l2", mu=0.3, lam=0.6, quadratic=_pairs_q(K, [(0, 1)], 2.0))
    sol = g.solve(A, zero=zero)
    assert (sol.weights[zero] == 0).all() and sol.polished.all()
    for t in range(T):
        fr = ~zero[t]
        n = int(fr.sum())

        def energy(x):
            w = np.zeros(K)
            w[fr] = x[:n] - x[n:]
            return g.energy(A[t], w)[0]

        x0 = np.r_[np.clip(sol.weights[t, fr], 0, None), np.clip(-sol.weights[t, fr], 0, None)] + 1e-3
        ref = so.minimize(energy, x0, method="L-BFGS-B", bounds=[(0, None)] * (2 * n),
                          options={"ftol": 1e-20, "gtol": 1e-14, "maxiter": 20000})
        assert g.energy(A[t], sol.weights[t])[0] <= ref.fun + 1e-15


def test_symmetry_matrix_hand_case():
    Q = C.symmetry_matrix([[0, 2]], 3, 0.5)
    w = np.array([0.9, 7.0, 0.3])
    assert w @ Q @ w == pytest.approx(0.5 * (0.9 - 0.3) ** 2)
    assert np.allclose(Q, Q.T) and np.linalg.eigvalsh(Q).min() > -1e-15


# -- symmetry and cancel pairs on the real take -------------------------------------------


def test_symmetry_weight_lowers_the_blink_error_against_the_actor(arkit):
    """ICT driven by the Live Link take, onto Rocketbox's ARKit shapes: the actor's two blinks
    differ by 0.0024 RMS; the bounded per-frame solve makes them differ by 0.011 and misses
    them by 0.028 RMS; tying the sides brings both numbers down."""
    from core.solvers.baselines import range_pf

    B, S, valid, names, named = arkit["B"], arkit["S"], arkit["valid"], arkit["names"], arkit["named"]
    iL, iR = names.index("AK_09_EyeBlinkLeft"), names.index("AK_10_EyeBlinkRight")
    pairs = C.pair_indices(C.symmetry_pairs(names), names)

    def stats(W):
        both = np.sqrt(np.mean((W[:, [iL, iR]] - named[:, [iL, iR]]) ** 2))
        asym = np.sqrt(np.mean((W[:, iL] - W[:, iR]) ** 2))
        return both, asym, _marker_mm(B, W, S, valid)

    b0, a0, m0 = stats(range_pf(B, S, 0.0, 1.0, valid, ridge=1e-5))
    b1, a1, m1 = stats(range_pf(B, S, 0.0, 1.0, valid, ridge=1e-5, quadratic=C.symmetry_matrix(pairs, len(names), 0.1)))
    print(f"blink RMSE {b0:.4f} -> {b1:.4f}, L-R {a0:.4f} -> {a1:.4f} (actor {np.sqrt(np.mean((named[:, iL] - named[:, iR]) ** 2)):.4f}), "
          f"marker {m0:.3f} -> {m1:.3f} mm")
    assert b1 < b0 and a1 < 0.5 * a0
    assert m1 < 1.05 * m0  # the price in marker error is small


@pytest.mark.slow
def test_cancel_pairs_never_fire_together_and_cost_little(arkit):
    from core.solvers.baselines import range_pf
    from core.solvers.spacetime import SpacetimeSolver

    B, S, valid, names = arkit["B"], arkit["S"], arkit["valid"], arkit["names"]
    pairs = C.pair_indices(C.suggested_cancel_pairs(names), names)  # blink/wide per eye, jawOpen/mouthClose
    assert len(pairs) == 3

    def solve(z):
        return range_pf(B, S, 0.0, 1.0, valid, ridge=1e-5, zero=z)

    W0 = solve(None)
    for thr in (0.0, 0.05):
        fired = C.cancel_conflicts(W0, pairs, thr).any(1)
        assert fired.any()
        W, info = C.cancel_pairs(solve, W0, pairs, thr)
        assert not C.cancel_conflicts(W, pairs, thr).any() and info["clamped"] == 0
        m0, m1 = _marker_mm(B, W0[fired], S[fired], valid[fired]), _marker_mm(B, W[fired], S[fired], valid[fired])
        mc = _marker_mm(B, C.cancel_clamp(W0, pairs, thr)[fired], S[fired], valid[fired])
        print(f"threshold {thr}: {fired.sum()} frames, marker error there {m0:.4f} -> re-solve {m1:.4f}, clamp {mc:.4f} mm")
        assert m0 <= m1 + 1e-12 and m1 < mc  # re-solving costs less than clamping
    # spacetime: the held entries are partial known weights of the bounded solve
    s = SpacetimeSolver(B, S, alpha=0.01, prior=arkit["prior"], known={0: W0[0], len(W0) - 1: W0[-1]}, valid=valid,
                        ridge=1e-5, lower=0.0, upper=1.0)
    Ws0 = s.solve()
    Ws, info = C.cancel_pairs(lambda z: s.solve(zero=z), Ws0, pairs, 0.0)
    assert info["passes"] >= 1 and not C.cancel_conflicts(Ws, pairs, 0.0).any()
    assert _marker_mm(B, Ws, S, valid) < 1.02 * _marker_mm(B, Ws0, S, valid)


# -- temporal filters ---------------------------------------------------------------------


def _gain(y, f, t, amplitude):
    """Steady-state amplitude ratio at frequency f over whole periods in the middle half (away
    from the start-up of the causal filter and from the zero-phase filter's ends)."""
    n = int(round(FPS / f * np.floor(len(t) / 2 * f / FPS)))
    sl = slice(len(t) // 4, len(t) // 4 + n)
    X = np.c_[np.sin(2 * np.pi * f * t[sl]), np.cos(2 * np.pi * f * t[sl])]
    return float(np.hypot(*np.linalg.lstsq(X, y[sl] - y[sl].mean(), rcond=None)[0]) / amplitude)


@pytest.mark.parametrize("f", [0.25, 1.0, 3.0, 7.0, 12.0])
def test_one_euro_attenuation_matches_its_documented_response(f):
    t = np.arange(int(FPS * 120)) / FPS
    x = 0.5 + 0.2 * np.sin(2 * np.pi * f * t)
    # beta = 0: the first-order low-pass (R1) exactly
    y = C.filter_weights(x[:, None], FPS, "one_euro", min_cutoff=1.0, beta=0.0)[:, 0]
    assert _gain(y, f, t, 0.2) == pytest.approx(float(C.lowpass_response(f, FPS, 1.0)), rel=1e-6)
    # beta > 0: never below (R1) at min_cutoff, never above 1
    g = _gain(C.one_euro(x[:, None], FPS, 0.5, 0.5)[:, 0], f, t, 0.2)
    assert C.lowpass_response(f, FPS, 0.5) <= g <= 1.0


@pytest.mark.parametrize("min_cutoff, beta, speed", [(1.0, 0.5, 0.1), (1.0, 0.5, 3.0), (0.5, 2.0, 1.0), (1.0, 0.0, 1.0)])
def test_one_euro_cutoff_follows_the_speed_as_derived(min_cutoff, beta, speed):
    """On a ramp the filter settles to the lag of (R2): cutoff f_c(v), lag v (1 - a) / (a fps)."""
    t = np.arange(600) / FPS
    y = C.one_euro((speed * t)[:, None], FPS, min_cutoff, beta)[:, 0]
    fc, lag = C.one_euro_cutoff(speed, FPS, min_cutoff, beta)
    assert speed * t[-1] - y[-1] == pytest.approx(float(lag), rel=1e-9)
    assert fc >= min_cutoff


@pytest.mark.parametrize("sigma", [1.0, 2.0, 4.0])
def test_gaussian_response_and_one_implementation(sigma):
    from core.solvers.local import smooth_weights

    t = np.arange(int(FPS * 60)) / FPS
    for f in (0.5, 2.0, 5.0):
        x = 0.5 + 0.2 * np.sin(2 * np.pi * f * t)
        y = C.filter_weights(x[:, None], FPS, "gaussian", sigma=sigma)[:, 0]
        assert _gain(y, f, t, 0.2) == pytest.approx(float(C.gaussian_response(f, FPS, sigma)), abs=2e-4)
    W = np.random.default_rng(0).random((50, 3))
    assert np.array_equal(C.filter_weights(W, FPS, "gaussian", sigma=sigma), smooth_weights(W, sigma))


def test_filters_keep_the_solve_inside_its_bounds(arkit):
    from core.evaluate import jitter

    W = arkit["results"]["solve"]["weights"]
    for kind in ("gaussian", "one_euro"):
        out = C.filter_weights(W, FPS, kind, sigma=2.0, min_cutoff=1.0, beta=0.3)
        assert out.min() >= 0.0 and out.max() <= 1.0
        assert jitter(out).mean() < 0.5 * jitter(W).mean()
    with pytest.raises(ValueError, match="did you mean 'one_euro'"):
        C.filter_weights(W, FPS, "one_eur")
    with pytest.raises(ValueError, match="fill the gaps"):
        C.one_euro(np.array([[0.0], [np.nan]]), FPS)


# -- keyframe reduction -------------------------------------------------------------------


def _fewest_linear_keys(y, tol):
    """Brute-force reference: BFS over all segments, each checked at every frame it spans."""
    T = len(y)
    ok = np.zeros((T, T), bool)
    for i in range(T):
        for j in range(i + 1, T):
            s = np.arange(i, j + 1)
            ok[i, j] = np.all(np.abs(y[i] + (y[j] - y[i]) * (s - i) / (j - i) - y[s]) <= tol)
    best = np.full(T, 10**9)
    best[0] = 1
    for j in range(1, T):
        best[j] = min(best[i] + 1 for i in range(j) if ok[i, j])
    return best[-1]


def test_linear_reduction_is_optimal_against_brute_force():
    rng = np.random.default_rng(7)
    for trial in range(30):
        T = int(rng.integers(3, 40))
        y = np.cumsum(rng.normal(size=T)) * 0.02 * rng.choice([0.1, 1.0, 5.0])
        tol = float(rng.choice([0.003, 0.01, 0.05]))
        k = C.reduce_keys(y[:, None], FPS, tol)
        assert k.counts[0] == _fewest_linear_keys(y, tol * (1 - 1e-9) - 1e-15), trial
        assert np.abs(k.evaluate()[:, 0] - y).max() <= tol


@pytest.mark.parametrize("interpolation", ["LINEAR", "CUBICSPLINE"])
@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.slow
def test_reduced_curves_stay_within_tolerance_on_the_sample(dense_weights, interpolation, shared):
    W = dense_weights
    k = C.reduce_keys(W, FPS, 0.005, interpolation, shared=shared)
    assert np.abs(k.evaluate() - W).max() <= 0.005
    # the one-sampler layout reproduces every curve: union of the key times, exact
    F, t, V, A, Bt = k.grid()
    assert np.abs(C.evaluate_sampler(t, V, np.arange(len(W)) / FPS, interpolation, A, Bt) - k.evaluate()).max() < 1e-12
    print(f"{interpolation} shared={shared}: {k.counts.sum()} keys of {W.size} samples, one grid of {len(F)} of {len(W)} frames")
    assert k.counts.sum() < 0.8 * W.size


def test_reduced_glb_is_valid_and_plays_the_same_in_three_js(tmp_path, tiger):
    from core.io.gltf import read_animation, write_rig

    rng = np.random.default_rng(2)
    W = np.clip(np.cumsum(rng.normal(size=(90, tiger.n_shapes)) * 0.04, 0), 0, 1)
    for interpolation in ("LINEAR", "CUBICSPLINE"):
        k = C.reduce_keys(W, FPS, 0.01, interpolation)
        F, t, V, A, Bt = k.grid()
        path = write_rig(tmp_path / f"{interpolation}.gltf", tiger, V, times=t, interpolation=interpolation,
                         tangents=None if A is None else (A, Bt))
        perf = read_animation(path, fps=FPS)
        back = C.evaluate_sampler(perf.times, perf.data, np.arange(len(W)) / FPS, interpolation,
                                  perf.extras.get("in_tangents"), perf.extras.get("out_tangents"))
        assert np.abs(back - W).max() <= 0.01 + 1e-6  # float32 in the file
        ts = np.arange(len(W) - 1) / FPS + 0.013
        report = run_node_check(path, "--sample=" + ",".join(f"{x:.6f}" for x in ts))
        assert report["validator"]["numErrors"] == 0 and report["validator"]["numWarnings"] == 0
        assert np.abs(np.array(report["three"]["samples"]) - k.evaluate(ts)).max() < 1e-5


def test_keys_csv_round_trip(tmp_path, dense_weights):
    from core.io.curves_csv import read_keys_csv, write_keys_csv

    names = [f"s{k}" for k in range(dense_weights.shape[1])]
    for interpolation in ("LINEAR", "CUBICSPLINE"):
        k = C.reduce_keys(dense_weights[:300], FPS, 0.005, interpolation, names=names)
        info = write_keys_csv(tmp_path / "keys.csv", k)
        assert info == {"keys": int(k.counts.sum()), "dense": 300 * len(names)}
        back = read_keys_csv(tmp_path / "keys.csv")
        assert back.names == tuple(names) and back.fps == FPS and back.interpolation == interpolation
        assert np.abs(back.evaluate() - dense_weights[:300]).max() <= 0.005


# -- mirror -------------------------------------------------------------------------------


def test_mirror_weights_and_edits(rigs):
    from core.io.performance import read_performance

    perf = read_performance(PERFORMANCES / "livelinkface_take_s07.csv")
    m = C.mirror_performance(perf)
    iL, iR = perf.names.index("eyeBlinkLeft"), perf.names.index("eyeBlinkRight")
    assert np.array_equal(m.data[:, iL], perf.data[:, iR], equal_nan=True)
    assert np.array_equal(m.data[:, perf.names.index("jawOpen")], perf.data[:, perf.names.index("jawOpen")], equal_nan=True)
    assert np.array_equal(C.mirror_performance(m).data, perf.data, equal_nan=True)
    yaw = perf.extras["head_rotation"][:, 0]
    assert np.array_equal(m.extras["head_rotation"][:, 0], -yaw, equal_nan=True)
    assert np.array_equal(m.extras["eye_rotation_left"][:, 1], perf.extras["eye_rotation_right"][:, 1], equal_nan=True)
    names = rigs["rocketbox_female_adult_02"].names
    edit = {"frame": 10, "weights": {"AK_09_EyeBlinkLeft": 1.0, "AK_25_JawOpen": 0.4}, "window": [0, 30]}
    assert C.mirror_edit(edit, names) == {"frame": 10, "weights": {"AK_10_EyeBlinkRight": 1.0, "AK_25_JawOpen": 0.4}, "window": [0, 30]}
    both = C.mirror_edit(edit, names, keep=True)["weights"]
    assert both == {"AK_10_EyeBlinkRight": 1.0, "AK_25_JawOpen": 0.4, "AK_09_EyeBlinkLeft": 1.0}
    with pytest.raises(ValueError, match="did you mean"):
        C.mirror_edit({"frame": 0, "weights": {"AK_09_EyeBlinkLef": 1}}, names)


def test_mirrored_weights_move_the_mirror_vertices(ict):
    """ICT's mesh is left/right symmetric vertex for vertex: weights mirrored by name displace
    each vertex as the unmirrored weights displace its mirror vertex, reflected (the name
    pairing agrees with the geometry; ICT's own shapes are symmetric to 0.7 mm of 19 mm)."""
    from scipy.spatial import cKDTree

    from datapaths import face_markers

    v = face_markers(ict, 200)
    dist, mv = cKDTree(ict.neutral).query(ict.neutral[v] * [-1.0, 1.0, 1.0])
    assert dist.max() < 1e-6
    W = np.random.default_rng(4).random((5, ict.n_shapes)) * 0.7
    disp = lambda w: np.tensordot(w, ict.deltas, 1)  # (T, V, 3)
    mirrored = disp(C.mirror_weights(W, ict.names))[:, v]
    reflected = disp(W)[:, mv] * [-1.0, 1.0, 1.0]
    scale = np.abs(disp(W)[:, v]).max()
    print(f"mirror consistency: {np.abs(mirrored - reflected).max() * 1000:.2f} mm of {scale * 1000:.1f} mm")
    assert np.abs(mirrored - reflected).max() < 0.05 * scale
    assert np.array_equal(C.mirror_weights(C.mirror_weights(W, ict.names), ict.names), W)


def test_mirror_a_marker_capture():
    from core.io.performance import read_performance

    perf = read_performance(PERFORMANCES / "animface_markers_jaw_60hz.csv")
    m = C.mirror_performance(perf)
    i, j = perf.names.index("Lcheek_Up"), perf.names.index("Rcheek_Up")
    mid = [k for k, n in enumerate(perf.names) if n in ("ForeHead_M", "Eyebrow_Center", "NoseTop", "NoseHead", "Mouth_Up",
                                                         "Mouth_Down", "Chin")]
    c = np.nanmean(perf.data[:, mid, 0])
    assert np.allclose(m.data[:, i, 0], 2 * c - perf.data[:, j, 0], equal_nan=True)
    assert np.allclose(m.data[:, i, 1:], perf.data[:, j, 1:], equal_nan=True)
    assert np.array_equal(m.valid[:, i], perf.valid[:, j])
    assert np.allclose(C.mirror_performance(m).data, perf.data, equal_nan=True)
