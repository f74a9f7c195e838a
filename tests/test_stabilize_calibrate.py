"""Stabilisation (Seol 2012 §3.1) and RBF calibration (§3.2) on synthetic and real data."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.calibrate import RBFWarp, calibrate_deltas
from core.model import Performance
from core.stabilize import kabsch, restore, stabilize


def _random_motion(T, rng):
    R = Rotation.from_rotvec(rng.normal(scale=0.2, size=(T, 3))).as_matrix()
    t = rng.normal(scale=0.05, size=(T, 3))
    return R, t


def test_kabsch_recovers_rotation_exactly():
    rng = np.random.default_rng(0)
    Y = rng.normal(size=(12, 3))
    R, t = _random_motion(20, rng)
    X = np.einsum("tij,mj->tmi", R, Y) + t[:, None]
    R2, t2 = kabsch(Y, X, np.ones((20, 12)))
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-10)
    assert np.allclose(np.linalg.det(R2), 1)


def test_stabilize_removes_head_motion_keeps_expression_and_handles_missing():
    rng = np.random.default_rng(1)
    M, T = 20, 30
    names = [f"ForeHead_{i}" for i in range(5)] + [f"Mouth_{i}" for i in range(M - 5)]
    Y = rng.normal(scale=0.05, size=(M, 3))
    expr = np.zeros((T, M, 3))
    expr[:, 5:] = rng.normal(scale=0.005, size=(T, M - 5, 3))  # only non-rigid markers move
    R, t = _random_motion(T, rng)
    R[0], t[0] = np.eye(3), 0
    X = restore(Y + expr, R, t)
    valid = np.ones((T, M), bool)
    valid[3, 0] = valid[7, 2] = valid[7, 10] = False  # missing samples, incl. a rigid one
    valid[12, :4] = False  # only 1 rigid marker left: motion held from a neighbour
    perf = Performance.markers(X, names, 60.0, valid=valid)
    with pytest.warns(UserWarning, match="held"):
        st = stabilize(perf)
    ok = ~st.held
    np.testing.assert_allclose(st.rotations[ok], R[ok], atol=1e-9)
    good = valid & ok[:, None]
    np.testing.assert_allclose(st.markers.data[good], (Y + expr)[good], atol=1e-9)
    assert np.isnan(st.markers.data[3, 0]).all()  # missing stays missing, never zeroed
    assert st.held[12] and st.held.sum() == 1
    back = restore(st.markers.data, st.rotations, st.translations)
    np.testing.assert_allclose(back[good], X[good], atol=1e-9)


def test_stabilize_robust_to_one_outlier_rigid_marker():
    rng = np.random.default_rng(2)
    Y = rng.normal(scale=0.05, size=(8, 3))
    R, t = _random_motion(10, rng)
    X = restore(np.repeat(Y[None], 10, 0), R, t)
    X[:, 0] += 0.03  # one marker slides on the skin
    st = stabilize(Performance.markers(X, [f"forehead{i}" for i in range(8)], 30.0), neutral=Y)
    np.testing.assert_allclose(st.rotations, R, atol=1e-6)


def test_stabilize_real_capture_reduces_rigid_marker_spread(data_dir):
    from core.io.performance import read_performance

    perf = read_performance(data_dir / "performances" / "animface_markers_jaw_60hz.csv")
    st = stabilize(perf)
    rigid = [perf.names.index(n) for n in st.rigid]
    before = np.nanstd(perf.data[:, rigid], axis=0).mean()
    after = np.nanstd(st.markers.data[:, rigid], axis=0).mean()
    assert after < 0.5 * before
    assert np.median(st.residual) < 2e-3  # rigid markers agree to ~mm after alignment


def test_rbf_exact_on_affine_and_interpolates():
    rng = np.random.default_rng(3)
    c = rng.normal(size=(15, 3))
    A = rng.normal(size=(3, 3)) + 2 * np.eye(3)
    b = rng.normal(size=3)
    warp = RBFWarp().fit(c, c @ A.T + b)
    x = rng.normal(size=(50, 3))
    np.testing.assert_allclose(warp(x), x @ A.T + b, atol=1e-9)
    np.testing.assert_allclose(warp.weights_, 0, atol=1e-9)
    v = rng.normal(size=(15, 3))
    warp = RBFWarp().fit(c, v)
    np.testing.assert_allclose(warp(c), v, atol=1e-9)


def test_rbf_matches_scipy_reference():
    from scipy.interpolate import RBFInterpolator

    rng = np.random.default_rng(4)
    c, v, x = rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), rng.normal(size=(30, 3))
    ref = RBFInterpolator(c, v, kernel="linear", degree=1)(x)
    np.testing.assert_allclose(RBFWarp().fit(c, v)(x), ref, rtol=1e-8, atol=1e-10)


def test_rbf_evaluates_many_points_in_blocks(monkeypatch):
    """Warping every shape of a dense correspondence (here 40 x 500 points, 300 centres) in
    blocks gives the formula's values; the whole (points, centres, 3) array took 10 GB for the
    sample's 175 shapes x 1,000 points."""
    import core.calibrate as calibrate

    rng = np.random.default_rng(4)
    c = rng.normal(size=(300, 3))
    warp = RBFWarp().fit(c, c + 0.1 * rng.normal(size=c.shape))
    x = rng.normal(size=(40, 500, 3))
    r = np.linalg.norm(x.reshape(-1, 3)[:, None] - c[None], axis=2)
    ref = (r @ warp.weights_ + warp.affine_[0] + x.reshape(-1, 3) @ warp.affine_[1:]).reshape(40, 500, 3)
    monkeypatch.setattr(calibrate, "RBF_BLOCK", 300 * 777)  # 777 points per block: the last one is short
    np.testing.assert_allclose(warp(x), ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(warp(x[0, 0]), ref[0, 0], rtol=1e-12, atol=1e-12)


def test_rbf_errors():
    with pytest.raises(ValueError, match="at least 4"):
        RBFWarp().fit(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="coplanar"):
        pts = np.c_[np.random.default_rng(0).normal(size=(10, 2)), np.zeros(10)]
        RBFWarp().fit(pts, pts)


def test_calibrate_deltas_scales_with_proportions(ict):
    idx = np.linspace(0, ict.n_vertices - 1, 40).astype(int)
    n = ict.neutral[idx]
    d = ict.deltas[:, idx]
    out, warp = calibrate_deltas(n, d, 1.3 * n + [0.1, 0, 0])
    np.testing.assert_allclose(out, 1.3 * d, atol=1e-9 * ict.size)
